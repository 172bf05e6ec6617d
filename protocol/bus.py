"""Zenoh session setup and the small pub/sub surface the nodes use.

This is the only module that imports ``zenoh``.  Every publication carries the Zenoh
encoding of its message type, ``application/msgpack;<MessageType>`` (:mod:`tagswarm.protocol.wire`).
Rules it enforces (docs/architecture.md, sections 2 and 5): callbacks only enqueue
into an :class:`Inbox` and wake the owner's loop (on Zenoh's own receive thread, so arrival order across keys is kept);
sessions are opened in a ``with`` block (:func:`open_bus`) and always
closed; large frames go out with DROP congestion control into newest-only
inboxes, small must-arrive messages with BLOCK into FIFO inboxes.

Security (docs/security.md): a client presents a Zenoh user/password
(``user`` + ``password_file``); a router checks them against a dictionary file
(``users_file``) and may enforce an ACL (``access_control``).  Fault injection
(``loss``, ``delay_ms`` on ``fault_keys``) impairs what this process receives;
see :mod:`tagswarm.protocol.netfaults`.

The settings (:class:`BusConfig`, in :mod:`tagswarm.protocol.busconfig`) and the inboxes
(:class:`Inbox`, in :mod:`tagswarm.protocol.inbox`) need no Zenoh and live in their own
modules; this one re-exports them.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import zenoh

from tagswarm.protocol import wire
from tagswarm.protocol.busconfig import (
    DEFAULT_LEASE_MS,
    KEEP_ALIVE,
    MAX_DELAY_MS,
    MAX_LEASE_MS,
    MIN_LEASE_MS,
    BusConfig,
    default_fault_keys,
)
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.inbox import Inbox, Received
from tagswarm.protocol.netfaults import NetFaults

__all__ = [
    "DEFAULT_LEASE_MS", "KEEP_ALIVE", "MAX_DELAY_MS", "MAX_LEASE_MS", "MIN_LEASE_MS", "Bus", "BusConfig", "BusError",
    "Inbox", "Publisher", "Received", "check_key_expr", "default_fault_keys", "encoding_for", "key_matches",
    "net_faults", "open_bus", "read_password", "zenoh_config", "zenoh_message",
]

log = logging.getLogger(__name__)


class BusError(UsageError):
    """The Zenoh session could not be configured or opened."""


def check_key_expr(expr: str) -> str:
    """``expr`` if it is a valid Zenoh key expression, else :class:`BusError`."""
    try:
        zenoh.KeyExpr(expr)
    except Exception as exc:  # "Invalid Key Expr `x`: why at <rust source path>"
        why = str(exc).split(" at /", 1)[0]
        raise BusError(f"{expr!r} is not a valid Zenoh key expression: {why}") from None
    return expr


def key_matches(pattern: str, key: str) -> bool:
    """Whether the key expression ``pattern`` matches every key of ``key`` (for a
    concrete ``key``: whether it matches that key)."""
    return bool(zenoh.KeyExpr(pattern).includes(zenoh.KeyExpr(key)))


def read_password(path: str) -> str:
    """The password in ``path`` without its trailing newline; :class:`BusError` if unreadable or empty."""
    try:
        with open(path, encoding="utf-8") as fh:
            password = fh.read().rstrip("\r\n")
    except OSError as exc:
        raise BusError(f"cannot read password file {path}: {exc.strerror}") from None
    if not password or "\n" in password:
        raise BusError(f"password file {path} must hold one non-empty line")
    return password


def zenoh_message(exc: BaseException) -> str:
    """Zenoh's error text on one line, without the Rust source location it appends."""
    text = " ".join(str(exc).split())
    return re.sub(r"\s+at /\S+\.rs:\d+\.?$", "", text)


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """Build the ``zenoh.Config`` for ``cfg``; raises :class:`BusError`."""
    path = cfg.config_file or os.environ.get("ZENOH_CONFIG")
    try:
        conf = zenoh.Config.from_file(path) if path else zenoh.Config()
        conf.insert_json5("mode", json.dumps(cfg.mode))
        if cfg.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        if cfg.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
        conf.insert_json5("transport/link/tx/lease", json.dumps(cfg.lease_ms))
        conf.insert_json5("transport/link/tx/keep_alive", json.dumps(KEEP_ALIVE))
    except Exception as exc:  # zenoh raises ZError with a readable message
        raise BusError(f"bad Zenoh configuration: {zenoh_message(exc)}") from None
    if (cfg.user is None) != (cfg.password_file is None):
        raise BusError("a Zenoh user needs a password file and a password file needs a user")
    # field by field, so a config file may set the others (e.g. a TLS block)
    auth: dict[str, str] = {}
    if cfg.user is not None and cfg.password_file is not None:
        auth = {"user": cfg.user, "password": read_password(cfg.password_file)}
    if cfg.users_file is not None:
        if not os.path.isfile(cfg.users_file):
            raise BusError(f"no such users file {cfg.users_file}")
        auth["dictionary_file"] = cfg.users_file
    try:
        for field, value in auth.items():
            conf.insert_json5(f"transport/auth/usrpwd/{field}", json.dumps(value))
        if cfg.access_control is not None:
            conf.insert_json5("access_control", cfg.access_control)
    except Exception as exc:
        raise BusError(f"bad Zenoh security configuration: {exc}") from None
    return conf


def net_faults(cfg: BusConfig) -> NetFaults:
    """The receive-side fault injector for ``cfg`` (inactive when loss and delay are 0)."""
    patterns = [zenoh.KeyExpr(check_key_expr(k)) for k in (cfg.fault_keys or default_fault_keys())]

    def matches(key: str) -> bool:
        ke = zenoh.KeyExpr(key)
        return any(p.intersects(ke) for p in patterns)

    try:
        return NetFaults(loss=cfg.loss, delay_s=cfg.delay_ms / 1000.0, seed=cfg.fault_seed, matches=matches,
                         jitter_s=cfg.jitter_ms / 1000.0)
    except ValueError as exc:
        raise BusError(f"network faults: {exc}") from None


# One Encoding object per message type, built once: "application/msgpack;<MessageType>" (protocol/wire.py).
_ENCODINGS: dict[type[Any], zenoh.Encoding] = {cls: zenoh.Encoding(wire.encoding_of(cls))
                                               for cls in wire.MESSAGE_TYPES}
_NO_ENCODING = zenoh.Encoding.ZENOH_BYTES  # a payload that is not a tagswarm message (tests' garbage)


def encoding_for(payload: bytes) -> zenoh.Encoding:
    """The Zenoh encoding of ``payload``: ``application/msgpack;<MessageType>`` read from its
    ``type`` entry, or ``zenoh/bytes`` for a payload that is not a tagswarm message."""
    cls = wire.message_type_of(payload)
    return _NO_ENCODING if cls is None else _ENCODINGS[cls]


class Publisher:
    """Publishes payloads on one key, each with the Zenoh encoding of its message type.

    The Zenoh publisher is declared at the first put, with the encoding of that payload's
    type, so every later payload of the same type (the same head bytes: one key carries
    one type) goes out with the declared encoding at no cost per put; another payload
    sets its own encoding."""

    def __init__(self, declare: Any) -> None:
        self._declare = declare
        self._pub: Any = None
        self._declared = _NO_ENCODING
        self._head = b""  # payloads starting with it are of the declared type

    def put(self, payload: bytes) -> None:
        if self._head and payload.startswith(self._head):
            self._pub.put(payload)
            return
        head = wire.message_head(payload)
        encoding = _NO_ENCODING if head is None else _ENCODINGS[head[0]]
        if self._pub is None:
            self._pub, self._declared = self._declare(encoding), encoding
            if head is not None:
                self._head = bytes(payload[: head[1]])
        if encoding is self._declared:
            self._pub.put(payload)
        else:
            self._pub.put(payload, encoding=encoding)


class Bus:
    """A thin façade over one open Zenoh session (use :func:`open_bus`)."""

    def __init__(self, session: zenoh.Session, faults: NetFaults | None = None) -> None:
        self._session = session
        self._faults = faults if faults is not None and faults.active else None
        self._wake = threading.Condition()
        self._publishers: dict[tuple[str, bool], Publisher] = {}
        self._keep: list[Any] = []  # declared entities live as long as the bus

    @property
    def zid(self) -> str:
        return str(self._session.info.zid())

    def publisher(self, key: str, *, drop: bool = False) -> Publisher:
        """Publisher for ``key``; ``drop=True`` for large frames (DROP congestion
        control), otherwise BLOCK so small messages are not lost under load.  Every
        payload carries the Zenoh encoding of its message type (see :class:`Publisher`)."""
        cached = self._publishers.get((key, drop))
        if cached is None:
            cc = zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK

            def declare(encoding: zenoh.Encoding) -> Any:
                return self._session.declare_publisher(key, congestion_control=cc, express=not drop,
                                                       encoding=encoding)

            cached = self._publishers[(key, drop)] = Publisher(declare)
        return cached

    def put(self, key: str, payload: bytes, *, drop: bool = False) -> None:
        """Publish ``payload`` on ``key`` through a cached publisher."""
        self.publisher(key, drop=drop).put(payload)

    def subscribe(self, key: str, *, newest_only: bool = False, capacity: int = 65536,
                  wakes: bool = True) -> Inbox[bytes]:
        """Subscribe to ``key`` (may contain wildcards); payloads arrive as bytes.
        With network faults configured, matching samples may be lost or delayed.
        ``wakes=False``: arrivals do not wake :meth:`wait` / :meth:`wait_for` (see :class:`Inbox`)."""
        inbox: Inbox[bytes] = Inbox(self._wake, newest_only=newest_only, capacity=capacity, wakes=wakes)
        faults = self._faults

        def on_sample(sample: zenoh.Sample) -> None:
            inbox.put(str(sample.key_expr), sample.payload.to_bytes())

        def on_faulty_sample(sample: zenoh.Sample) -> None:
            assert faults is not None
            got = str(sample.key_expr)
            if not faults.admit(key, got):
                inbox.count_fault_drop()
                return
            payload = sample.payload.to_bytes()  # copied now: the sample is not ours after the callback
            faults.hold(got, lambda: inbox.put(got, payload))

        faulty = faults is not None and faults.matches(key)
        self._keep.append(self._session.declare_subscriber(key, _direct(on_faulty_sample if faulty else on_sample)))
        return inbox

    def subscribe_encoded(self, key: str, *, capacity: int = 65536) -> Inbox[tuple[str, bytes]]:
        """Subscribe to ``key`` keeping each sample's Zenoh encoding: the inbox holds
        ``(encoding, payload)`` pairs (for inspection tools; no fault injection)."""
        inbox: Inbox[tuple[str, bytes]] = Inbox(self._wake, newest_only=False, capacity=capacity)

        def on_sample(sample: zenoh.Sample) -> None:
            inbox.put(str(sample.key_expr), (str(sample.encoding), sample.payload.to_bytes()))

        self._keep.append(self._session.declare_subscriber(key, _direct(on_sample)))
        return inbox

    def wait_matched(self, key: str, timeout_s: float) -> bool:
        """True once this session knows of a subscriber matching ``key`` (in any process,
        this one included), False after ``timeout_s`` wall seconds.  A probe publisher's
        matching listener wakes the wait (no polling); undeclaring the probe afterwards does
        not make the session forget the subscribers it learnt."""
        matched = threading.Event()
        probe = self._session.declare_publisher(key)
        try:
            listener = probe.declare_matching_listener(lambda status: matched.set() if status.matching else None)
            try:
                # a MatchingStatus object (zenoh 1.10's stub says bool, and any object is truthy)
                now: Any = probe.matching_status
                return bool(now.matching) or matched.wait(timeout_s)
            finally:
                listener.undeclare()
        finally:
            probe.undeclare()

    def fault_stats(self) -> dict[str, int]:
        """Samples lost to / delayed by injected network faults so far (for statuses)."""
        f = self._faults
        return {"net_dropped": 0 if f is None else f.dropped, "net_delayed": 0 if f is None else f.delayed}

    def close(self) -> None:
        """Stop the fault injector's timer (the session itself is closed by :func:`open_bus`)."""
        if self._faults is not None:
            self._faults.close()

    def declare_token(self, key: str) -> None:
        """Declare a liveliness token that lives as long as the session."""
        self._keep.append(self._session.liveliness().declare_token(key))

    def watch_liveliness(self, key: str) -> Inbox[bool]:
        """Liveliness changes under ``key``: ``True`` when a token appears
        (including tokens already present), ``False`` when it goes away."""
        inbox: Inbox[bool] = Inbox(self._wake, newest_only=False, capacity=65536)

        def on_change(sample: zenoh.Sample) -> None:
            inbox.put(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        self._keep.append(self._session.liveliness().declare_subscriber(key, _direct(on_change), history=True))
        return inbox

    def alive_now(self, key: str, timeout_s: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens currently matching ``key`` (blocking query)."""
        replies = self._session.liveliness().get(key, timeout=timeout_s)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def queryable(self, key: str) -> Inbox[Any]:
        """Queries on ``key``; answer them from the loop with :meth:`reply`."""
        inbox: Inbox[Any] = Inbox(self._wake, newest_only=False, capacity=1024)

        def on_query(query: zenoh.Query) -> None:
            inbox.put(str(query.selector.key_expr), query)

        self._keep.append(self._session.declare_queryable(key, _direct(on_query)))
        return inbox

    @staticmethod
    def reply(query: Any, key: str, payload: bytes) -> None:
        """Answer a query taken from a :meth:`queryable` inbox, then finish it."""
        with query:  # leaving the block finalises the query
            query.reply(key, payload, encoding=encoding_for(payload))

    def get(self, key: str, timeout_s: float = 2.0) -> list[Received[bytes]]:
        """Query ``key`` and collect the answers (blocking, never from a callback)."""
        out: list[Received[bytes]] = []
        for reply in self._session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                out.append(Received(str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
        return out

    def wait(self, timeout_s: float) -> None:
        """Block until any inbox of this bus receives something, or the timeout."""
        with self._wake:
            self._wake.wait(timeout_s)

    def wait_for(self, predicate: Any, timeout_s: float) -> bool:
        """Block until ``predicate()`` is true (re-checked on every arrival).

        ``predicate`` runs with the inboxes' lock held, so what it drains from several
        inboxes is one consistent snapshot; meanwhile Zenoh's receive thread waits on
        that lock.  Keep it short (a receive thread stalled longer than a peer's lease
        drops that peer), and never make a blocking Zenoh call such as :meth:`get` in
        it: its reply could not be delivered until the call timed out."""
        deadline = time.monotonic() + timeout_s
        with self._wake:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._wake.wait(min(left, 0.05))
        return True


def _direct(fn: Any) -> Any:
    """Run ``fn`` on Zenoh's receiving thread.  zenoh-python's default runs each
    callback on its own Python thread, which loses the order between keys (a
    command published before a tick ack could be enqueued after it, breaking
    lockstep determinism).  Our callbacks only enqueue, so running them
    directly is cheap."""
    return zenoh.handlers.Callback(fn, indirect=False)


@contextmanager
def open_bus(cfg: BusConfig) -> Iterator[Bus]:
    """Open a Zenoh session for ``cfg`` and close it on exit, whatever happens."""
    conf = zenoh_config(cfg)
    faults = net_faults(cfg)
    # Zenoh's own log (to stderr, the process's log) only when asked for with RUST_LOG
    zenoh.try_init_log_from_env()
    try:
        session = zenoh.open(conf)
    except Exception as exc:
        who = f", user {cfg.user!r}" if cfg.user else ""
        raise BusError(f"cannot open Zenoh session ({cfg.mode}, listen={list(cfg.listen)}, "
                       f"connect={list(cfg.connect)}{who}): {exc}") from None
    if faults.active:
        log.warning("injecting network faults on receive: loss %.3g, delay %.3g ± %.3g ms, seed %d, keys %s",
                    cfg.loss, cfg.delay_ms, cfg.jitter_ms, cfg.fault_seed,
                    ", ".join(cfg.fault_keys or default_fault_keys()))
    with session:
        bus = Bus(session, faults)
        try:
            yield bus
        finally:
            bus.close()
