"""A stand-alone lockstep participant process for tests: acks every tick
(``--hang`` : declares liveliness but never acks)."""

from __future__ import annotations

import argparse
import threading

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.config import install_stop_signals
from tagswarm.protocol.keys import Keys


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
        seq = 0
        while not stop.is_set():
            bus.wait(0.1)
            for item in ticks.drain():
                tick = codec.decode(m.Tick, item.value)
                if not a.hang:
                    bus.put(keys.ack(a.name), codec.encode(m.TickAck(seq=seq, stamp_ns=tick.stamp_ns,
                                                                     participant=a.name, step=tick.step)))
                    seq += 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
