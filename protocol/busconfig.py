"""How a process joins the Zenoh network: :class:`BusConfig`, its ranges and defaults.

Plain settings, no Zenoh import, so that configuration code can build and check them
without a session; :mod:`tagswarm.protocol.bus` turns them into a Zenoh config and
re-exports every name of this module.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from tagswarm.protocol.keys import ROOT, Keys

MAX_DELAY_MS = 60_000.0
# Zenoh link lease (transport/link/tx/lease): a process announces it to its peers, which
# close the link, and so drop its liveliness tokens, when nothing (data or keep-alive)
# arrived from it for that long; what counts is the lease the silent process announced.
# A SIGKILL closes the socket and is seen in ~20 ms either way; the lease is what bounds
# detection of a frozen, hung or partitioned process: Zenoh's 10 s default would be far
# too late to mark an agent not alive within 2 s.  The floor is the longest a *receiving*
# process may stall: its Zenoh receive thread runs our callbacks, which need the GIL (and
# the lock Bus.wait_for holds), so while another thread holds the GIL in one long C call
# (a gtsam optimisation, a pybullet scene load) or the process gets no CPU on a loaded
# 2-core machine, the link is not read, and a stall longer than the lease drops a healthy
# peer (measured: a 1.1 s stall drops a 1 s lease).  1500 ms detects a frozen process in
# ~1.5 s (it sends every tick; when idle, keep-alives every 375 ms: 1.1-1.5 s) and
# tolerates stalls 3x the longest seen in the e2e runs (0.47 s: the world loading its
# scene right after opening its session; nodes otherwise < 0.3 s).
DEFAULT_LEASE_MS = 1500
MIN_LEASE_MS = 100
MAX_LEASE_MS = 600_000
KEEP_ALIVE = 4  # keep-alives per lease (Zenoh's default and recommendation: the lease is 4 missed ones)


class BusConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """How a process joins the Zenoh network.

    ``listen``/``connect`` are Zenoh endpoints such as ``tcp/127.0.0.1:7447``.
    Multicast scouting is off unless asked for: explicit endpoints open a
    session in ~1 ms instead of ~0.5 s and keep test runs isolated.
    ``config_file`` (or the ``ZENOH_CONFIG`` environment variable) names a Zenoh
    JSON5 config that is loaded first; the fields here are applied on top.

    Authentication: ``user`` and ``password_file`` (a file holding the password,
    so it never shows in a config dump or ``ps``) are presented to the router;
    a router given ``users_file`` (Zenoh's ``user:password`` dictionary) admits
    only sessions that present one of its entries, and ``access_control`` (the JSON
    of a Zenoh ``access_control`` block, see tagswarm/deploy/acl.py) limits what each user
    may publish, subscribe, query and declare.

    Fault injection (receive side, see :mod:`tagswarm.protocol.netfaults`): samples that
    arrive on keys matching ``fault_keys`` (key expressions; empty = the
    :func:`default_fault_keys`) are lost with probability ``loss`` (0..1) and
    delivered ``delay_ms`` milliseconds late (± ``jitter_ms``, per-key order kept);
    ``fault_seed`` fixes the pattern.

    ``lease_ms`` is the Zenoh link lease this process announces (applied on top of a
    config file, like the other fields): its peers drop it, and its liveliness tokens,
    after that long without hearing from it (see :data:`DEFAULT_LEASE_MS`).
    """

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str | None = None
    user: str | None = None
    password_file: str | None = None
    users_file: str | None = None
    access_control: str | None = None
    loss: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 0.0
    delay_ms: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_DELAY_MS)] = 0.0
    jitter_ms: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_DELAY_MS)] = 0.0
    fault_keys: tuple[str, ...] = ()
    fault_seed: int = 0
    lease_ms: Annotated[int, msgspec.Meta(ge=MIN_LEASE_MS, le=MAX_LEASE_MS)] = DEFAULT_LEASE_MS


def default_fault_keys() -> tuple[str, ...]:
    """Key expressions (any run) that faults apply to unless told otherwise: small
    must-arrive messages whose loss the system absorbs (encoders, wheel commands,
    goals, observations, odometry, map).  A lockstep server does not wait for a lost
    odometry message: the agent's ack of the tick, sent after it, tells it the
    message is gone (``odometry_lost`` in its status).  Left out: the lockstep clock
    (tick, acks, render requests: losing one stalls the run), corrections (a sync
    point too: a lockstep agent waits up to ``agent.frame_wait_s`` for the
    correction of the last tick, so every loss would cost that timeout; name them in
    ``fault_keys`` to impair them, e.g. in realtime runs), camera images (already
    DROP / newest-only), ground truth and statuses (evaluation and monitoring, not
    the system under test)."""
    k = Keys("any")
    data = (k.encoders(), k.cmd(), k.goal(), k.observation(), k.odometry(), k.map())
    return tuple(f"{ROOT}/*/{key[len(k.prefix) + 1:]}" for key in data)
