"""A test's subscription to a live run (tagswarm.testing.subscription) over loopback: ``get``
delivers what its processes sent last, and once they have all exited and nothing is left it
says so instead of waiting out its timeout."""

from __future__ import annotations

import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.testing.errors import SwarmTimeout
from tagswarm.testing.subscription import Subscription
from tests.harness import endpoint

KEYS = Keys("subend")


def _odometry(stamp_ns: int) -> bytes:
    return codec.encode(m.OdometryEstimate(seq=stamp_ns, stamp_ns=stamp_ns, robot_id=1, x_m=0.0, y_m=0.0,
                                           yaw_rad=0.0, cov=(1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4), distance_m=0.0))


def test_get_says_the_run_ended_and_still_delivers_its_last_messages() -> None:
    ended = [False]
    with open_bus(BusConfig(listen=(endpoint(),))) as bus:
        sub = Subscription(bus, KEYS.odometry(1), ended=lambda: ended[0])
        bus.put(KEYS.odometry(1), _odometry(1))
        assert sub.get(timeout_s=30).msg.stamp_ns == 1
        ended[0] = True  # every process exited ...
        bus.put(KEYS.odometry(1), _odometry(2))  # ... after sending this, still on its way
        assert sub.get(timeout_s=30).msg.stamp_ns == 2
        with pytest.raises(SwarmTimeout, match="and the run has ended"):
            sub.get(timeout_s=60)  # not "within 60 s": it gave up once the run was over
        bare = Subscription(bus, KEYS.odometry(2))  # no way to know the run's end: the timeout holds
        with pytest.raises(SwarmTimeout, match=r"within 0\.5 s"):
            bare.get(timeout_s=0.5)
