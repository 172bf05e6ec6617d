"""A deliberately slow agent (``--inject-frame-delay``) in a realtime run: it skips
camera frames instead of queueing them, its memory stays flat, and the world keeps
its pace: its step rate (realtime, 30 Hz) with the slow agent is within 10 % of the rate
before, both measured the same way over windows of 8-12 s (a least-squares slope of step
against the wall time each world status arrived, so one status read late at either end of
a window moves it by well under 1 %)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import psutil

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.testing import SwarmFactory

SLOW = 1
DELAY_S = 0.25  # per frame: 4 frames/s at most against a 10 Hz camera
MB = 1 << 20


def test_slow_agent_skips_frames_keeps_flat_memory_and_the_world_keeps_pace(tmp_path: Path,
                                                                             swarm: SwarmFactory) -> None:
    with swarm.start("paper", seed=5, duration_s=300, clock="realtime", launch=False) as sw:
        world_status = sw.bus.subscribe(sw.keys.world_status())
        statuses = sw.bus.subscribe(sw.keys.robot_status(SLOW))
        presence = sw.bus.watch_liveliness(sw.keys.alive(f"agent/{SLOW}"))
        sw.launch()
        steps: list[tuple[float, int]] = []  # (wall, world step) from the world's status
        world: dict[str, int] = {}

        def rate(since: float) -> float:
            """World steps per wall second since ``since``: the slope fitted through every status (one a
            simulated second), not the two end points, so a status drained late barely moves it."""
            pts = np.array([(w, s) for w, s in steps if w >= since], float)
            assert len(pts) >= 6, pts
            return float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0])

        def track() -> None:
            for it in world_status.drain():
                world.update(codec.decode(m.AgentStatus, it.value).counters)
                steps.append((time.monotonic(), world["step"]))

        def sim_past(t_s: float) -> bool:
            track()
            return sw.recorder.sim_ns >= t_s * 1e9

        sw.wait(lambda: sim_past(2.0), 60, "the world never started")
        t_normal = time.monotonic()
        sw.wait(lambda: sim_past(10.0), 60, "the world stalled")
        normal_rate = rate(t_normal)

        # the same robot's agent again, now with a slow detector
        sw.kill(f"agent/{SLOW}")
        presence.drain()
        statuses.drain()  # the killed agent's
        sw.spawn(f"agent/{SLOW}", "--inject-frame-delay", str(DELAY_S))
        sw.wait(lambda: any(c.value for c in presence.drain()), 60, "the slow agent never came up")
        slow = psutil.Process(sw.pid(f"agent/{SLOW}"))
        counters: dict[str, int] = {}

        def latest() -> bool:
            track()
            for it in statuses.drain():
                counters.update(codec.decode(m.AgentStatus, it.value).counters)
            return counters.get("observations", 0) > 0

        # warmed up (the first tag sightings allocate a few MB once): from here on memory must stay flat
        sw.wait(latest, 60, "the slow agent never saw a tag")
        t0 = sw.recorder.sim_ns / 1e9
        t_slow = time.monotonic()
        rss: list[tuple[float, int]] = []

        def sample() -> bool:
            if not rss or time.monotonic() - rss[-1][0] >= 0.5:
                rss.append((time.monotonic(), slow.memory_info().rss))
            return sim_past(t0 + 12.0)

        sw.wait(sample, 60, "the world stalled")
        slow_rate = rate(t_slow)
        n = counters["frames_processed"]
        sw.wait(lambda: latest() and counters["frames_processed"] > n, 30, "no status from the slow agent")
        sw.recorder.poll()
        server = dict(sw.recorder.counters.get("server", {}))

    received, processed, skipped = counters["frames_received"], counters["frames_processed"], counters["frames_skipped"]
    # realtime: an observation lands after later odometry (its image had to be rendered and detected,
    # 0.25 s more on the slow agent) and is fused at its own instant, not dropped as late
    assert server.get("fusion_late_observations", 0) > 0, server
    assert server.get("fusion_rejected_late", 0) <= 0.02 * server["accepted_observations"], server
    # at most ~1/DELAY_S frames per second get processed; the rest are skipped, none wait in a queue
    assert skipped > processed > 0, counters
    assert received - skipped - processed <= 1, counters  # every frame was either processed or skipped
    # the frame it works on is never older than one frame period plus one detector delay (simulated time)
    assert counters["frame_age_max_ms"] <= 1000 * (DELAY_S + 0.1) + 150, counters
    mem = np.array([r for _, r in rss], float) / MB
    growth = float(mem[-3:].mean() - mem[:3].mean())
    # the skipped frames are gone, not parked: keeping them would hold 77 kB x 6 frames/s x 12 s ~ 5.5 MB,
    # ~0.23 MB between two samples. One step of its own (the allocator taking a fresh 2.1 MB block once,
    # seen in CI) is not a queue, so the growth is judged without the largest single step
    step = float(np.diff(mem).max()) if len(mem) > 1 else 0.0
    assert len(mem) >= 20 and growth - max(step, 0.0) < 1.5, mem.round(2).tolist()
    slope = float(np.polyfit([w for w, _ in rss], mem, 1)[0])
    # the realtime world keeps its pace with a slow agent on the network
    rate_change = slow_rate / normal_rate - 1
    assert abs(rate_change) < 0.10, (normal_rate, slow_rate)
    report = {"world_steps_per_s_normal": normal_rate, "world_steps_per_s_with_slow_agent": slow_rate,
              "rate_change": rate_change, "realtime_overruns": world.get("realtime_overruns", 0),
              "frames_received": received, "frames_processed": processed, "frames_skipped": skipped,
              "frame_age_max_ms": counters["frame_age_max_ms"], "rss_mb_start": float(mem[0]),
              "rss_growth_mb": growth, "rss_largest_step_mb": step, "rss_slope_mb_per_s": slope,
              "rss_samples": len(mem)}
    (tmp_path / "overload_report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
