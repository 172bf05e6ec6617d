"""Durability helpers of the journal: fsync in a background thread, and fsync of a
new file's directory entry."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path


class Syncer:
    """Runs ``fsync`` (the journal's, which also counts and times it) in a thread
    of its own when asked, so that the server's loop never waits for the disk (an
    fsync takes 0.2-5 ms here, more under I/O load).  Requests made while one runs
    coalesce into one more fsync; the first error is kept for the journal to act
    on.  Only this thread calls ``fsync`` while it runs."""

    def __init__(self, fsync: Callable[[], None]) -> None:
        self._fsync = fsync
        self._wake = threading.Condition()
        self._wanted = False
        self._stopping = False
        self.error: OSError | None = None
        self._thread = threading.Thread(target=self._run, name="journal-fsync", daemon=True)
        self._thread.start()

    def request(self) -> None:
        """Ask for an fsync of everything written so far (returns at once)."""
        with self._wake:
            self._wanted = True
            self._wake.notify()

    def stop(self) -> None:
        """Do a pending fsync, then end the thread."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join()

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._wanted and not self._stopping:
                    self._wake.wait()
                if not self._wanted:
                    return
                self._wanted = False
            try:
                self._fsync()
            except OSError as exc:
                self.error = exc
                return


def fsync_dir(folder: Path) -> None:
    """Make a new file's directory entry durable (POSIX; a no-op where unsupported)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
