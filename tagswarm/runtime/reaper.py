"""The last line of defence against stray processes: run as a plain script (no tagswarm
import, so it starts in milliseconds) by :mod:`tagswarm.runtime.procgroup`, in its own
session so a Ctrl-C in the terminal does not reach it.

It reads lines from stdin: ``+PGID`` (a process group the owner started),
``-PGID`` (that group is gone).  When stdin reaches end of file -- the owner
closed it, exited, or was killed in any way, even SIGKILL or pytest-timeout's
``os._exit`` -- it SIGKILLs every group still listed, then exits.
"""

from __future__ import annotations

import os
import signal
import sys


def kill_groups(groups: set[int]) -> None:
    """SIGKILL each process group (a stopped process dies of SIGKILL too); gone ones are skipped."""
    for pgid in sorted(groups):
        try:
            os.killpg(pgid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def follow(lines: object) -> set[int]:
    """The groups still listed once ``lines`` (an iterable of ``+PGID`` / ``-PGID``) ends."""
    groups: set[int] = set()
    for line in lines:  # type: ignore[attr-defined]
        text = str(line).strip()
        if len(text) > 1 and text[0] in "+-" and text[1:].isdigit():
            (groups.add if text[0] == "+" else groups.discard)(int(text[1:]))
    return groups


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # only end of file ends us
    kill_groups(follow(sys.stdin))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
