"""Per-key traffic statistics of ``tagswarm spy`` and their snapshots (plain text or
a rich table).

Pure code: :class:`Traffic` is fed payloads, their Zenoh encodings and a clock (seconds,
monotonic) by :class:`tagswarm.spy.spy.Spy` or a test; rates are messages per second and
bandwidth bytes per second over the last ``window_s`` seconds.  Each key shows the newest
sample's encoding and how many of its samples had an encoding that does not match the
message (:func:`encoding_mismatch`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from rich.table import Table
from rich.text import Text

from tagswarm.protocol import codec, wire
from tagswarm.protocol import messages as m
from tagswarm.spy.describe import decode, summarise, type_name

LAST_WIDTH = 90
"""Characters of the newest-message view shown in a snapshot."""


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
    encoding: str = ""  # of the newest sample; "" = not known (a bus that does not hand it)
    mismatched: int = 0  # samples whose encoding does not match their message
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
    encoding: str = ""
    mismatched: int = 0


def encoding_mismatch(encoding: str, payload: bytes, decoded: m.Msg | codec.DecodeError) -> bool:
    """Whether a sample's Zenoh ``encoding`` disagrees with its payload: a message must carry
    ``application/msgpack;<its type>`` (:mod:`tagswarm.protocol.wire`); an undecodable
    payload must not name another type than the one its ``type`` entry claims (a
    ``WheelCommand`` with a NaN still is one), and one that claims none must not name any
    (garbage goes out as ``zenoh/bytes``).  A missing encoding (``zenoh/bytes`` on a
    message, from an older sender or recording) counts as a mismatch."""
    claimed = wire.type_of_encoding(encoding)
    if isinstance(decoded, codec.DecodeError):
        return claimed is not wire.message_type_of(payload)
    return claimed is not type(decoded)


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
        self.mismatched = 0

    def add(self, key: str, payload: bytes, now: float, encoding: str | None = None) -> m.Msg | codec.DecodeError:
        """Count one sample; ``encoding`` is its Zenoh encoding (None: not known, not checked)."""
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
        if encoding is not None:
            st.encoding = encoding
            if encoding_mismatch(encoding, payload, decoded):
                st.mismatched += 1
                self.mismatched += 1
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
                           None if st.stamp_ns is None else st.stamp_ns / 1e9, st.last, st.encoding, st.mismatched))
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


def _no_space(text: str) -> str:
    return "_".join(text.split())  # an encoding is data from the network: keep the columns splittable


def short_encoding(encoding: str) -> str:
    """``msgpack;Tick`` for ``application/msgpack;Tick`` (the table's narrow column)."""
    return encoding.removeprefix("application/")


def plain_snapshot(rows: list[Row], alive: set[str], title: str) -> str:
    """Whitespace-aligned text: ``# title``, a header, one row per key (only the last
    column, LAST, may contain spaces), then ``alive <key>`` lines.  ENCODING is the newest
    sample's Zenoh encoding (``-``: not known), BAD_ENC the samples whose encoding did not
    match their message."""
    head = ("KEY", "TYPE", "ENCODING", "MSGS", "BAD_ENC", "RATE_HZ", "BANDWIDTH", "SIM_T_S", "LAST")
    cells = [(r.key, r.kind, _no_space(r.encoding) or "-", str(r.count), str(r.mismatched), f"{r.rate_hz:.2f}",
              human_rate(r.bytes_per_s), "-" if r.stamp_s is None else f"{r.stamp_s:.3f}", _clip(r.last, LAST_WIDTH))
             for r in rows]
    widths = [max(len(c[i]) for c in [head, *cells]) for i in range(len(head) - 1)]
    lines = [f"# {title}"]
    for c in [head, *cells]:
        fixed = [v.ljust(w) if i < 3 else v.rjust(w) for i, (v, w) in enumerate(zip(c[:-1], widths, strict=True))]
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
    t.add_column("encoding", no_wrap=True, overflow="ellipsis", min_width=8)
    for name in ("msgs", "bad enc", "Hz", "bandwidth", "t [s]"):
        t.add_column(Text(name), justify="right", no_wrap=True, min_width=len(name))
    t.add_column("last", overflow="ellipsis", max_width=LAST_WIDTH, min_width=8)
    for r in rows:  # Text cells: keys and payload details are data, never rich markup
        kind = Text(r.kind, style="red" if r.kind.startswith("undecodable") else "")
        bad = "red" if r.mismatched else ""
        enc = Text(short_encoding(r.encoding) or "-", style=bad)
        t.add_row(Text(short(r.key)), kind, enc, str(r.count), Text(str(r.mismatched), style=bad),
                  f"{r.rate_hz:.1f}", human_rate(r.bytes_per_s), "-" if r.stamp_s is None else f"{r.stamp_s:.2f}",
                  Text(r.last))
    if alive:
        t.add_section()
        for k in sorted(alive):
            t.add_row(Text(short(k)), Text("alive", style="green"), "", "", "", "", "", "", "liveliness token")
    return t
