"""Latency image -> correction and real-time factor across hosts, beside one host.

Each point is one realtime run of the paper scenario (``--robots`` robots, seed 0):

- ``one host``: ``tagswarm up`` (peer-to-peer over loopback);
- ``hosts, D ms``: the multi-host harness (tagswarm/deploy/multihost.py): router,
  world, server and every agent in network namespaces of their own, all traffic
  through the router, D ms of one-way delay between hosts (the receive-side fault
  layer on every key: this kernel has no netem), optionally iptables loss.

Latency: for every correction whose ``last_fix_ns`` is new for its robot, the wall
time from the first arrival of the image stamped ``last_fix_ns`` to the arrival of
that correction, seen by a client delayed like an agent
(tagswarm/deploy/hostprobe.py; the same method as bench/speed.py).  RTF: simulated
over wall seconds between the first and last tick after the warm-up.  Writes
``bench/results/multihost.json``.  Needs root (network namespaces).

Usage: sudo python bench/multihost.py [--seconds 30] [--robots 3] [--delays 0,20,50] [--repeat 2] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.deploy import netns  # noqa: E402
from tagswarm.deploy.hostprobe import Probe  # noqa: E402
from tagswarm.deploy.multihost import MultiHost  # noqa: E402
from tagswarm.protocol.bus import BusConfig, open_bus  # noqa: E402
from tagswarm.protocol.keys import Keys  # noqa: E402
from tagswarm.protocol.scenario import Scenario, load_scenario  # noqa: E402
from tests.harness import endpoint  # noqa: E402

TAGSWARM = str(Path(sys.executable).parent / "tagswarm")
OUT = ROOT / "bench" / "results" / "multihost.json"


def scenario(robots: int, seconds: float) -> Scenario:
    return load_scenario("paper", ['clock.mode="realtime"', f"robots.count={robots}", f"duration_s={seconds}",
                                   "seed=0"])


def watch(probe: Probe, poll: Any, warmup_s: float, done: Any, timeout_s: float) -> dict[str, Any]:
    """Poll until ``done()``; latencies and RTF counted after ``warmup_s`` simulated seconds."""
    deadline = time.monotonic() + timeout_s
    warm = False
    while not done():
        if time.monotonic() > deadline:
            raise RuntimeError("the run did not end in time")
        poll()
        if not warm and probe.sim_s() >= warmup_s:
            warm = True
            probe.latencies_s.clear()
            probe.first_tick = None
        time.sleep(0.02)
    poll()
    s = probe.summary()
    return {"rtf": s["rtf"], "latency_ms": s["latency_image_to_correction_ms"], "sim_s": s["sim_s"]}


def one_host(robots: int, seconds: float, warmup_s: float) -> dict[str, Any]:
    ep, run = endpoint(), f"mhbench{os.getpid()}"
    out = Path(tempfile.mkdtemp(prefix="tagswarm-mhbench-"))
    argv = [TAGSWARM, "up", "--clock", "realtime", "--robots", str(robots), "--seed", "0", "--duration",
            f"{seconds:g}", "--listen", ep, "--run", run, "--out", str(out / "run"), "--no-live", "--no-report"]
    with open(out / "up.log", "wb") as log:
        up = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            time.sleep(0.5)  # up's world listens on ep once started: retried below
            for _ in range(100):
                try:
                    cm = open_bus(BusConfig(connect=(ep,)))
                    bus = cm.__enter__()
                    break
                except Exception:
                    if up.poll() is not None:
                        raise RuntimeError(f"tagswarm up exited {up.returncode}; see {out / 'up.log'}") from None
                    time.sleep(0.3)
            else:
                raise RuntimeError("could not join tagswarm up's network")
            try:
                probe = Probe(bus, Keys(run), scenario(robots, seconds), latency=True)
                result = watch(probe, probe.poll, warmup_s, lambda: up.poll() is not None, seconds * 5 + 120)
            finally:
                cm.__exit__(None, None, None)
        finally:
            if up.poll() is None:
                up.send_signal(signal.SIGINT)
                up.wait(60)
    return {"setup": "one host", "delay_ms": 0.0, "loss": 0.0, **result}


def several_hosts(robots: int, seconds: float, warmup_s: float, delay_ms: float, loss: float) -> dict[str, Any]:
    out = Path(tempfile.mkdtemp(prefix="tagswarm-mhbench-"))
    with MultiHost(out / "run", scenario(robots, seconds), delay_ms=delay_ms, loss=loss, latency=True,
                   report=False) as mh:
        mh.start()
        assert mh.probe is not None
        world = mh.children["world"]
        result = watch(mh.probe, mh.poll, warmup_s, lambda: world.poll() is not None, seconds * 5 + 120)
        codes = mh.wait_end(120)
    return {"setup": "several hosts", "delay_ms": delay_ms, "loss": loss, "exit_codes": codes, **result}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=30.0, help="simulated seconds per run (realtime)")
    p.add_argument("--warmup", type=float, default=4.0, help="simulated seconds not counted")
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--delays", default="0,20,50", help="link delays (ms) across hosts, comma-separated")
    p.add_argument("--loss", type=float, default=0.05, help="also a run at 20 ms with this loss (0: none)")
    p.add_argument("--repeat", type=int, default=1, help="rounds of every point, interleaved (the machine is shared)")
    p.add_argument("--quick", action="store_true", help="15 s runs")
    args = p.parse_args()
    why = netns.check_available()
    if why is not None:
        print(f"bench/multihost.py: {why}", file=sys.stderr)
        return 2
    seconds = 15.0 if args.quick else args.seconds
    t0 = time.monotonic()
    points: list[dict[str, Any]] = []
    for rnd in range(args.repeat):
        points.append({"round": rnd, **one_host(args.robots, seconds, args.warmup)})
        for d in [float(x) for x in args.delays.split(",") if x.strip()]:
            points.append({"round": rnd, **several_hosts(args.robots, seconds, args.warmup, d, 0.0)})
        if args.loss > 0:
            points.append({"round": rnd, **several_hosts(args.robots, seconds, args.warmup, 20.0, args.loss)})
    result = {
        "what": "latency image -> correction and RTF, realtime paper scenario, one host vs several (namespaces)",
        "robots": args.robots, "seconds": seconds, "warmup_s": args.warmup, "seed": 0,
        "delay_by": "receive-side fault layer on every key (--net-delay-ms), loss by iptables statistic",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_avg_at_end": os.getloadavg()},
        "bench_wall_s": round(time.monotonic() - t0, 1),
        "points": points,
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=1))
    t = Table(title=f"multi-host: {args.robots} robots, realtime, {seconds:g} s")
    for col in ("round", "setup", "delay ms", "loss", "RTF", "latency p50 / p95 / max ms", "n"):
        t.add_column(col)
    for pt in points:
        lat = pt["latency_ms"] or {}
        t.add_row(str(pt["round"]), pt["setup"], f"{pt['delay_ms']:g}", f"{pt['loss']:g}", f"{pt['rtf']}",
                  f"{lat.get('p50')} / {lat.get('p95')} / {lat.get('max')}", str(lat.get("n")))
    Console().print(t)
    print(f"written {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
