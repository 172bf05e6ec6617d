"""The life of a tagswarm process: logging, signals, the ``main`` of a node, and the one
boundary that turns errors into exit codes (:func:`run_main`)."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Protocol, TypeVar

from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.errors import UsageError
from tagswarm.runtime.config import ConfigError


def setup_logging(level: str | None, role: str) -> None:
    """Log to stderr as ``time role level message``."""
    name = (level or "INFO").upper()
    if name not in logging.getLevelNamesMapping():
        raise ConfigError(f"--log-level: unknown level {level!r}")
    logging.basicConfig(level=name, stream=sys.stderr,
                        format=f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s", force=True)


def child_env(environ: Mapping[str, str], *, keep: Collection[str] = (),
              import_path: Sequence[str] | None = None) -> dict[str, str]:
    """The environment of a child process started by ``tagswarm up`` or the pytest fixture: ours
    without ``TAGSWARM_*`` (but the names in ``keep``), unbuffered.  Whoever starts the children
    resolved the run's settings (scenario file < environment < flags) into the scenario file and
    flags it gives them; a child reading a variable again would put it above those flags, unlike
    what the run folder says (and a developer's own variables would leak into a test).
    ``import_path`` (a test's ``sys.path``, for an agent running the test's own controller module)
    is appended to ``PYTHONPATH``: what the test can import, that agent can."""
    env = {k: v for k, v in environ.items() if not k.startswith("TAGSWARM_") or k in keep}
    env["PYTHONUNBUFFERED"] = "1"
    if import_path is not None:
        extra = [p for p in import_path if p and Path(p).is_dir()]
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys([*env.get("PYTHONPATH", "").split(os.pathsep), *extra])
                                            ).strip(os.pathsep)
    return env


def run_main(prog: str, body: Callable[[], int]) -> int:
    """The one boundary that turns errors into exit codes: a
    :class:`~tagswarm.protocol.errors.UsageError` (bad flags, environment, scenario, or a
    file the command names) -> 2 with a one-line message, Ctrl-C -> 130, anything else
    propagates (Python prints the traceback and exits with 1)."""
    try:
        return body()
    except UsageError as exc:
        one_line = " ".join(str(exc).split())  # whatever a parser put in its message
        sys.stderr.write(f"{prog}: error: {one_line}\n")
        return 2
    except KeyboardInterrupt:
        return 130


def install_stop_signals(stop: threading.Event) -> None:
    """SIGTERM and SIGINT set ``stop`` so a node's loop ends and its Zenoh session
    closes cleanly (a no-op outside the main thread, e.g. nodes run in tests)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())


class _Node(Protocol):
    def run(self, stop_event: threading.Event) -> int: ...


class _NodeConfig(Protocol):
    @property
    def bus(self) -> BusConfig: ...

    @property
    def log_level(self) -> str: ...


C = TypeVar("C", bound=_NodeConfig)


def serve_node(prog: str, build: Callable[[], C], role: Callable[[C], str],
               make_node: Callable[[C, Bus], _Node]) -> int:
    """The common ``main`` of a node process: build the config (errors -> exit 2),
    log as ``role``, open the bus, run the node until done or SIGTERM/SIGINT, then
    call its ``close()`` if it has one and close the session."""

    def body() -> int:
        config = build()
        setup_logging(config.log_level, role(config))
        stop = threading.Event()
        with open_bus(config.bus) as bus:
            node = make_node(config, bus)
            try:
                install_stop_signals(stop)
                return node.run(stop)
            finally:
                close = getattr(node, "close", None)
                if close is not None:
                    close()

    return run_main(prog, body)
