"""``tagswarm spy [KEYEXPR]``: live inspection of what flows on a running system's Zenoh bus.

Joins the network with the same flags and ``TAGSWARM_*`` variables as every
process (``--connect``, ``--zenoh-mode``, ``--run`` ...) as a passive
subscriber (it declares no liveliness token, so it never joins a lockstep) and
shows, per key: the message type (every payload is decoded once with
:func:`protocol.codec.decode_any`; undecodable ones are shown as
``undecodable:<kind>``, never raised), the rate, the bandwidth, the simulation
time and a short view of the newest message (images are summarised as
``320x240 mono8 robot 1 front``, never dumped).  Liveliness tokens matching
KEYEXPR (``tagswarm/<run>/alive/...``) are listed below the table.

Modes:

- default: a live table (rich) on a terminal; plain-text snapshots every
  ``--window`` seconds when stdout is not a terminal.
- ``--once [--window S]``: sample for S seconds (default 2), print one snapshot
  (plain text unless stdout is a terminal) and exit 0.
- ``--echo``: print every message as one JSON line (``{"key", "size", "msg"}``,
  bytes fields replaced by a summary; ``{"key", "size", "error"}`` for an
  undecodable payload; ``{"key", "alive"}`` for a liveliness change).  With
  ``--once`` it stops after the window.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import msgspec
from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from protocol import codec
from protocol import messages as m
from protocol.bus import Bus, open_bus
from protocol.config import (
    ConfigError,
    OneLineParser,
    add_common_args,
    bus_from,
    env_of,
    install_stop_signals,
    pick,
    run_main,
    setup_logging,
)
from protocol.keys import Keys

PROG = "tagswarm spy"
#: Items an unread subscription may hold before the oldest are dropped (and counted).
INBOX_CAPACITY = 20_000
LAST_WIDTH = 90


# --------------------------------------------------------------------------- message views


def _pose(x: float, y: float, yaw: float) -> str:
    return f"({x:+.2f}, {y:+.2f}, {math.degrees(yaw):+.0f}°)"


def type_name(msg: m.Msg) -> str:
    """The message's class name (``CameraImage``, ``Tick`` ...)."""
    return type(msg).__name__


def image_summary(img: m.CameraImage) -> str:
    """``320x240 mono8 robot 1 front``: what an image is, without its pixels."""
    return f"{img.width}x{img.height} {img.encoding} robot {img.robot_id} {img.camera}"


def summarise(msg: m.Msg) -> str:
    """A short one-line view of a decoded message (never its raw bytes)."""
    if isinstance(msg, m.CameraImage):
        return f"{image_summary(msg)} step {msg.step}"
    if isinstance(msg, m.Tick):
        return f"step {msg.step} {msg.mode} dt {msg.dt_ns / 1e6:g} ms, {len(msg.cameras_rendered)} frame(s)"
    if isinstance(msg, m.TickAck):
        return f"{msg.participant} acked step {msg.step}"
    if isinstance(msg, m.EncoderTicks):
        return f"robot {msg.robot_id} L {msg.left_ticks} R {msg.right_ticks} ticks ({msg.ticks_per_rev}/rev)"
    if isinstance(msg, m.WheelCommand):
        return f"robot {msg.robot_id} L {msg.left_rad_s:+.2f} R {msg.right_rad_s:+.2f} rad/s"
    if isinstance(msg, m.GroundTruthPose):
        return f"robot {msg.robot_id} {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} v {msg.v_m_s:+.2f} m/s"
    if isinstance(msg, m.RelativeObservation):
        return (f"robot {msg.robot_id} sees {msg.target_kind} {msg.target_id} at "
                f"{_pose(msg.x_m, msg.y_m, msg.yaw_rad)} rms {msg.reprojection_rms_px:.2f} px ({msg.camera})")
    if isinstance(msg, m.OdometryEstimate):
        return f"robot {msg.robot_id} {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} travelled {msg.distance_m:.2f} m"
    if isinstance(msg, m.Correction):
        if not msg.localised:
            return f"robot {msg.robot_id} not localised"
        return f"robot {msg.robot_id} at {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} (map)"
    if isinstance(msg, m.GlobalMap):
        alive = sum(1 for e in msg.robots if e.alive)
        return f"origin {msg.origin_id}, {len(msg.robots)} robot(s) ({alive} alive), {len(msg.edges)} edge(s)"
    if isinstance(msg, m.AgentStatus):
        who = msg.role if msg.robot_id is None else f"{msg.role} {msg.robot_id}"
        counters = " ".join(f"{k}={v}" for k, v in list(msg.counters.items())[:4])
        return f"{who} {msg.mode} {counters}".rstrip()
    if isinstance(msg, m.RenderPoses):
        return f"step {msg.step}: {len(msg.robot_ids)} robot(s), {len(msg.cameras)} camera(s)"
    if isinstance(msg, m.Goal):
        return f"robot {msg.robot_id} -> ({msg.x_m:+.2f}, {msg.y_m:+.2f}) ±{msg.tolerance_m:g} m"
    return type_name(msg)  # pragma: no cover - every wire type is listed above


def _strip_bytes(value: Any, image: m.CameraImage | None) -> Any:
    if isinstance(value, (bytes, bytearray, memoryview)):
        size = len(value)
        return f"<{image_summary(image)}: {size} bytes>" if image is not None else f"<{size} bytes>"
    if isinstance(value, dict):
        return {k: _strip_bytes(v, image) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strip_bytes(v, image) for v in value]
    return value


def message_json(msg: m.Msg) -> Any:
    """The message as JSON-ready builtins with every bytes field replaced by a summary."""
    raw = msgspec.to_builtins(msg, builtin_types=(bytes, bytearray, memoryview))
    return _strip_bytes(raw, msg if isinstance(msg, m.CameraImage) else None)


def decode(payload: bytes) -> m.Msg | codec.DecodeError:
    """Decode any wire message; a bad payload comes back as the error, never raised."""
    try:
        msg: m.Msg = codec.decode_any(payload)
        return msg
    except codec.DecodeError as exc:
        return exc
    except Exception as exc:  # decode_any wraps everything; this is the spy's own "never crash"
        return codec.DecodeError("malformed", f"{type(exc).__name__}: {exc}")


def echo_line(key: str, size: int, decoded: m.Msg | codec.DecodeError) -> str:
    """One JSON line for ``--echo``."""
    if isinstance(decoded, codec.DecodeError):
        doc: dict[str, Any] = {"key": key, "size": size, "error": {"kind": decoded.kind, "detail": decoded.detail}}
    else:
        doc = {"key": key, "size": size, "msg": message_json(decoded)}
    return msgspec.json.encode(doc).decode()


# --------------------------------------------------------------------------- statistics


@dataclass
class KeyStats:
    """Everything seen on one key."""

    key: str
    kind: str = "?"
    count: int = 0
    total_bytes: int = 0
    undecodable: int = 0
    last: str = ""
    stamp_ns: int | None = None
    recent: deque[tuple[float, int]] = field(default_factory=deque)

    def trim(self, now: float, window_s: float) -> None:
        while self.recent and self.recent[0][0] <= now - window_s:
            self.recent.popleft()


@dataclass
class Row:
    """One line of a snapshot."""

    key: str
    kind: str
    count: int
    rate_hz: float
    bytes_per_s: float
    stamp_s: float | None
    last: str


class Traffic:
    """Per-key counts, rates (over the last ``window_s``), bandwidth and the newest
    message, plus the set of live liveliness tokens.  Pure: fed by :class:`Spy`
    (or a test) with payloads and a clock."""

    def __init__(self, window_s: float, started: float) -> None:
        self.window_s = window_s
        self.started = started
        self.keys: dict[str, KeyStats] = {}
        self.alive: set[str] = set()
        self.total = 0

    def add(self, key: str, payload: bytes, now: float) -> m.Msg | codec.DecodeError:
        decoded = decode(payload)
        st = self.keys.get(key)
        if st is None:
            st = self.keys[key] = KeyStats(key)
        st.count += 1
        st.total_bytes += len(payload)
        st.recent.append((now, len(payload)))
        st.trim(now, self.window_s)
        self.total += 1
        if isinstance(decoded, codec.DecodeError):
            st.undecodable += 1
            st.kind = f"undecodable:{decoded.kind}"
            st.last = f"{len(payload)} B: {decoded.detail}"
        else:
            st.kind = type_name(decoded)
            st.last = summarise(decoded)
            st.stamp_ns = decoded.stamp_ns
        return decoded

    def liveliness(self, key: str, alive: bool) -> None:
        if alive:
            self.alive.add(key)
        else:
            self.alive.discard(key)

    def rows(self, now: float) -> list[Row]:
        """A snapshot: rates are messages in the last ``window_s`` (or since the
        start, if that is shorter) per second."""
        span = max(min(self.window_s, now - self.started), 1e-6)
        out = []
        for key in sorted(self.keys):
            st = self.keys[key]
            st.trim(now, self.window_s)
            n = len(st.recent)
            size = sum(s for _, s in st.recent)
            out.append(Row(key, st.kind, st.count, n / span, size / span,
                           None if st.stamp_ns is None else st.stamp_ns / 1e9, st.last))
        return out


def human_rate(bytes_per_s: float) -> str:
    """``12.3KB/s`` (no spaces, so plain snapshots split on whitespace)."""
    value = bytes_per_s
    for unit in ("B/s", "KB/s", "MB/s"):
        if value < 1000 or unit == "MB/s":
            return f"{value:.0f}{unit}" if unit == "B/s" else f"{value:.1f}{unit}"
        value /= 1000
    raise AssertionError("unreachable")  # pragma: no cover


def _clip(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def plain_snapshot(rows: list[Row], alive: set[str], title: str) -> str:
    """Whitespace-aligned text: ``# title``, a header, one row per key (only the last
    column, LAST, may contain spaces), then ``alive <key>`` lines."""
    head = ("KEY", "TYPE", "MSGS", "RATE_HZ", "BANDWIDTH", "SIM_T_S", "LAST")
    cells = [(r.key, r.kind, str(r.count), f"{r.rate_hz:.2f}", human_rate(r.bytes_per_s),
              "-" if r.stamp_s is None else f"{r.stamp_s:.3f}", _clip(r.last, LAST_WIDTH)) for r in rows]
    widths = [max(len(c[i]) for c in [head, *cells]) for i in range(len(head) - 1)]
    lines = [f"# {title}"]
    for c in [head, *cells]:
        fixed = [v.ljust(w) if i < 2 else v.rjust(w) for i, (v, w) in enumerate(zip(c[:-1], widths, strict=True))]
        lines.append("  ".join([*fixed, c[-1]]))
    lines.append(f"# alive: {len(alive)} liveliness token(s)")
    lines += [f"alive  {k}" for k in sorted(alive)]
    return "\n".join(lines)


def rich_snapshot(rows: list[Row], alive: set[str], title: str, caption: str = "", strip: str = "") -> Table:
    """The same snapshot as a rich table (for a terminal); keys are shown without the
    common ``strip`` prefix (e.g. ``tagswarm/<run>/``, named in the title)."""

    def short(key: str) -> str:
        return key[len(strip):] if strip and key.startswith(strip) and len(key) > len(strip) else key

    t = Table(title=Text(title), caption=Text(caption) if caption else None, expand=False)
    # on a narrow terminal the key folds and the newest-message view wraps, never the numbers
    t.add_column("key", style="cyan", overflow="fold", min_width=12)
    t.add_column("type", no_wrap=True, overflow="ellipsis", min_width=6)
    for name in ("msgs", "Hz", "bandwidth", "t [s]"):
        t.add_column(Text(name), justify="right", no_wrap=True, min_width=len(name))
    t.add_column("last", overflow="ellipsis", max_width=LAST_WIDTH, min_width=8)
    for r in rows:  # Text cells: keys and payload details are data, never rich markup
        kind = Text(r.kind, style="red" if r.kind.startswith("undecodable") else "")
        t.add_row(Text(short(r.key)), kind, str(r.count), f"{r.rate_hz:.1f}", human_rate(r.bytes_per_s),
                  "-" if r.stamp_s is None else f"{r.stamp_s:.2f}", Text(r.last))
    if alive:
        t.add_section()
        for k in sorted(alive):
            t.add_row(Text(short(k)), Text("alive", style="green"), "", "", "", "", "liveliness token")
    return t


# --------------------------------------------------------------------------- the process


class Spy:
    """Subscribes to ``keyexpr`` (and its liveliness tokens) and feeds a :class:`Traffic`."""

    def __init__(self, bus: Bus, keyexpr: str, window_s: float, *, alive: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.traffic = Traffic(window_s, clock())
        try:
            self.inbox = bus.subscribe(keyexpr, capacity=INBOX_CAPACITY)
            self.alive_in = bus.watch_liveliness(keyexpr) if alive else None
        except Exception as exc:  # zenoh rejects malformed key expressions when declaring
            reason = " ".join(str(exc).split()).split(" at /", 1)[0]  # drop zenoh's Rust source location
            raise ConfigError(f"bad key expression {keyexpr!r}: {reason}") from None

    @property
    def dropped(self) -> int:
        return self.inbox.overflow

    def poll(self, echo: Callable[[str], None] | None = None) -> None:
        """Take in everything that arrived; ``echo`` gets one JSON line per event."""
        now = self.clock()
        if self.alive_in is not None:
            for change in self.alive_in.drain():
                self.traffic.liveliness(change.key, change.value)
                if echo is not None:
                    echo(msgspec.json.encode({"key": change.key, "alive": change.value}).decode())
        for item in self.inbox.drain():
            decoded = self.traffic.add(item.key, item.value, now)
            if echo is not None:
                echo(echo_line(item.key, len(item.value), decoded))


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("keyexpr", nargs="?", metavar="KEYEXPR",
                   help="Zenoh key expression to watch (default: every key of the run, tagswarm/<run>/**)")
    p.add_argument("--once", action="store_true", help="sample for --window seconds, print one snapshot, exit 0")
    p.add_argument("--window", type=float, default=2.0, metavar="SECONDS",
                   help="sampling window of --once and averaging window of the rates (default 2)")
    p.add_argument("--echo", action="store_true", help="print every message as a JSON line instead of the table")
    p.add_argument("--plain", action="store_true", help="plain-text snapshots even on a terminal")
    p.add_argument("--no-alive", action="store_true", help="do not list liveliness tokens")
    add_common_args(p)
    return p


def _writer(out: TextIO) -> Callable[[str], None]:
    def write(line: str) -> None:
        out.write(line + "\n")

    return write


def run_spy(spy: Spy, *, keyexpr: str, once: bool, window_s: float, echo: bool, plain: bool,
            stop: threading.Event, out: TextIO) -> int:
    """The loop: poll every 0.1 s; print per mode (see the module docstring)."""
    emit = _writer(out) if echo else None
    t0 = spy.clock()
    deadline = t0 + window_s if once else math.inf

    def title() -> str:
        now = spy.clock()
        return (f"tagswarm spy  {keyexpr}  {now - t0:.1f} s  {len(spy.traffic.keys)} key(s)  "
                f"{spy.traffic.total} msg(s)" + (f"  dropped {spy.dropped}" if spy.dropped else ""))

    strip = keyexpr[:-2] if keyexpr.endswith("/**") else ""  # "tagswarm/<run>/" for the default

    def snapshot_plain() -> None:
        out.write(plain_snapshot(spy.traffic.rows(spy.clock()), spy.traffic.alive, title()) + "\n")
        out.flush()

    if echo or once or plain or not out.isatty():
        next_print = t0 + window_s
        while not stop.is_set():
            left = deadline - spy.clock()
            if left <= 0:
                break
            stop.wait(min(0.1, left))
            spy.poll(emit)
            if echo:
                out.flush()
            elif not once and spy.clock() >= next_print:
                snapshot_plain()
                next_print += window_s
        spy.poll(emit)
        if once and not echo:
            if plain or not out.isatty():
                snapshot_plain()
            else:
                Console(file=out).print(rich_snapshot(spy.traffic.rows(spy.clock()), spy.traffic.alive, title(),
                                                      strip=strip))
        return 0
    console = Console(file=out)
    with Live(console=console, refresh_per_second=4, transient=False) as live:
        while not stop.is_set():
            stop.wait(0.25)
            spy.poll()
            live.update(rich_snapshot(spy.traffic.rows(spy.clock()), spy.traffic.alive, title(),
                                      "Ctrl-C to quit", strip=strip))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm spy``."""

    def body() -> int:
        args = parser().parse_args(list(argv) if argv is not None else None)
        env = env_of()
        if not math.isfinite(args.window) or args.window <= 0:
            raise ConfigError("--window must be a positive number of seconds")
        setup_logging(pick(args, env, "log_level", "WARNING"), "spy")  # validates --log-level too
        keys = Keys(pick(args, env, "run", "default"))
        keyexpr = args.keyexpr if args.keyexpr is not None else keys.all()
        if not keyexpr.strip():
            raise ConfigError("KEYEXPR must not be empty")
        stop = threading.Event()
        install_stop_signals(stop)
        with open_bus(bus_from(args, env)) as bus:
            spy = Spy(bus, keyexpr, args.window, alive=not args.no_alive)
            try:
                return run_spy(spy, keyexpr=keyexpr, once=args.once, window_s=args.window, echo=args.echo,
                               plain=args.plain, stop=stop, out=sys.stdout)
            except BrokenPipeError:  # e.g. `tagswarm spy --echo | head`: stop quietly
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return 0

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
