"""Delivery of one-shot operator commands to a reader that subscribed just before:
``tagswarm kidnap`` run in-process N times against a loopback session holding the world's
liveliness token, each time with a fresh reader session subscribed to the command key a
moment before the command starts.  Compares the command as shipped (it waits for the
key's Zenoh matching status, :func:`tagswarm.operator.reach.wait_matched`) with the same
command publishing right after the liveliness wait (the wait patched out): commands lost
and the command's wall time (median, max).  Writes ``bench/results/operator_delivery.json``.

Usage: python bench/operator_delivery.py [--n 40]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tagswarm.operator import kidnap, reach  # noqa: E402
from tagswarm.protocol.bus import BusConfig, open_bus  # noqa: E402
from tagswarm.protocol.keys import Keys  # noqa: E402
from tests.harness import endpoint  # noqa: E402


def trial(n: int, wait: bool) -> dict[str, Any]:
    """``n`` commands, each to a reader that subscribed just before it."""
    original = reach.wait_matched
    if not wait:
        reach.wait_matched = lambda bus, key, timeout_s: True
    keys, ep = Keys("bench-deliver"), endpoint()
    lost, walls = 0, []
    try:
        with open_bus(BusConfig(listen=(ep,))) as hub:
            hub.declare_token(keys.alive("world/0"))
            for i in range(n):
                with open_bus(BusConfig(connect=(ep,))) as reader:
                    inbox = reader.subscribe(keys.world_command())
                    t0 = time.monotonic()
                    with contextlib.redirect_stdout(io.StringIO()):
                        code = kidnap.main([str(i), "0", "0", "--connect", ep, "--run", keys.run, "--timeout", "10",
                                            "--log-level", "ERROR"])
                    walls.append(time.monotonic() - t0)
                    if code != 0 or not reader.wait_for(inbox.__len__, 3.0):
                        lost += 1
    finally:
        reach.wait_matched = original
    return {"commands": n, "lost": lost, "wall_s_median": round(statistics.median(walls), 4),
            "wall_s_max": round(max(walls), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=40, help="commands per variant (default 40)")
    args = ap.parse_args()
    result = {
        "bench": "operator_delivery",
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "waits_for_matching_subscriber": trial(args.n, wait=True),
        "publishes_after_liveliness_only": trial(args.n, wait=False),
    }
    out = ROOT / "bench" / "results" / "operator_delivery.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
