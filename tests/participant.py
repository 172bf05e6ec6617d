"""A stand-alone lockstep participant process for tests: acks every tick
(``--hang`` : declares liveliness but never acks)."""

from __future__ import annotations

import argparse
import threading

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.process import install_stop_signals


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--connect", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--name", required=True)
    p.add_argument("--hang", action="store_true")
    a = p.parse_args()
    keys = Keys(a.run)
    stop = threading.Event()
    install_stop_signals(stop)
    with open_bus(BusConfig(connect=(a.connect,))) as bus:
        ticks = bus.subscribe(keys.tick())
        bus.declare_token(keys.alive(a.name))
        me = Participant(bus, keys, a.name)
        while not stop.is_set():
            bus.wait(0.1)
            me.serve((codec.decode(m.Tick, item.value) for item in ticks.drain()), lambda _: not a.hang)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
