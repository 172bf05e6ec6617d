"""An agent frozen by SIGSTOP mid-run (real processes, lockstep) is marked not alive by
the server within 2 s of wall time, through the Zenoh lease alone.

A SIGKILL closes the agent's TCP sockets, so its peers see its liveliness token vanish
at once (~20 ms; test_agent_restart.py).  A frozen process -- stopped, hung, or cut off
by a partition -- keeps its sockets open and just goes silent: only the link lease it
announced (``BusConfig.lease_ms``, default :data:`~tagswarm.protocol.busconfig.DEFAULT_LEASE_MS`)
tells its peers it is gone, and Zenoh's own default lease would take 10 s.  So the
detection here must come after the stop by most of a lease (nothing else can notice
a silent process) and before 2 s.  Then the frozen agent is SIGKILLed and the others
must run the scenario to its end.

The server's view is read from its map queryable (answered between ticks, so it shows
the server's alive flags at once), not from the map it publishes at 2 simulated Hz:
while the world waits for the frozen agent's ack it hardly steps, so the next
published map may be seconds of wall time away.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import DEFAULT_LEASE_MS
from tagswarm.testing import SwarmFactory

VICTIM = 2
STOP_AT_S = 4.0
DURATION_S = 12.0
QUERY_EVERY_S = 0.02  # at most this long between two looks at the server's map


def test_frozen_agent_is_marked_not_alive_within_2s_by_the_lease_and_the_others_run_on(
        tmp_path: Path, swarm: SwarmFactory) -> None:
    with swarm.start("paper", seed=3, duration_s=DURATION_S, launch=False) as sw:
        scen = sw.scenario
        keys = sw.keys
        presence = sw.bus.watch_liveliness(keys.alive(f"agent/{VICTIM}"))
        odom = {rid: sw.bus.subscribe(keys.odometry(rid)) for rid in scen.robot_ids if rid != VICTIM}
        sw.launch()

        last: list[Any] = [-math.inf, None]  # when the server was last asked, and its answer

        def server_says_alive() -> bool | None:
            """The victim's alive flag in the map the server answers with (None: not in it, or no answer),
            asked at most every QUERY_EVERY_S."""
            if time.monotonic() - last[0] >= QUERY_EVERY_S:
                last[0], last[1] = time.monotonic(), None
                for reply in sw.bus.get(keys.map(), timeout_s=1.0):
                    gmap = codec.decode(m.GlobalMap, reply.value)
                    last[1] = next((e.alive for e in gmap.robots if e.robot_id == VICTIM), None)
            return cast("bool | None", last[1])

        def until(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
            """Like ``sw.wait``, but ``cond`` runs outside the bus lock: ``Bus.wait_for`` holds it while
            checking, which blocks Zenoh's receive thread, so a query made there gets no reply."""
            deadline = time.monotonic() + timeout_s
            sw.recorder.poll()
            while not cond():
                left = deadline - time.monotonic()
                assert left > 0, f"{what} (after {timeout_s} s)\n{sw.tails()}"
                sw.bus.wait(min(left, QUERY_EVERY_S))
                sw.recorder.poll()

        # mid-run, with the victim localised and alive in the server's map
        until(lambda: sw.recorder.sim_ns >= STOP_AT_S * 1e9 and server_says_alive() is True, 120,
              "the victim never showed up alive in the server's map")
        victim = sw.process(f"agent/{VICTIM}")
        stop_sim_s = sw.recorder.sim_ns / 1e9
        presence.drain()
        t_stop = time.monotonic()
        sw.freeze(f"agent/{VICTIM}")  # SIGSTOP
        seen: dict[str, float] = {}

        def noticed() -> bool:
            if "liveliness" not in seen and any(not c.value for c in presence.drain()):
                seen["liveliness"] = time.monotonic() - t_stop
            if "server" not in seen and server_says_alive() is False:
                seen["server"] = time.monotonic() - t_stop
                seen["server_sim_s"] = sw.recorder.sim_ns / 1e9
                seen["victim_still_running"] = float(victim.poll() is None)
            return "liveliness" in seen and "server" in seen

        # waited for well past Zenoh's default lease (10 s): a failure then says how late, not just "late"
        until(noticed, 30, "the frozen agent was never marked not alive")
        lease_s = DEFAULT_LEASE_MS / 1000
        # a frozen process only goes silent: it cannot be noticed before most of its lease has passed (its
        # last keep-alive or data left at most a quarter of a lease before the stop) ...
        assert seen["victim_still_running"] == 1.0, seen  # stopped, not dead: its sockets were open
        assert 0.5 * lease_s < seen["liveliness"], seen
        assert 0.5 * lease_s < seen["server"], seen
        # ... and the lease noticed it within 2 s of wall time (Zenoh's 10 s default would not)
        assert seen["server"] < 2.0, seen

        # ---- kill the frozen agent for good; the others run the scenario to its end
        sw.kill(f"agent/{VICTIM}")
        for inbox in odom.values():
            inbox.drain()
        killed_sim_s = sw.recorder.sim_ns / 1e9
        sw.wait_exit()
        after = {rid: [codec.decode(m.OdometryEstimate, it.value).stamp_ns / 1e9 for it in inbox.drain()]
                 for rid, inbox in odom.items()}
    # every other agent kept publishing odometry up to the end of the run
    for rid, stamps in after.items():
        assert stamps and max(stamps) >= DURATION_S - 0.5, (rid, killed_sim_s, stamps[-3:])
    report = {"lease_ms": DEFAULT_LEASE_MS, "stop_sim_s": stop_sim_s, "killed_sim_s": killed_sim_s,
              "liveliness_gone_wall_s": round(seen["liveliness"], 3),
              "server_marked_not_alive_wall_s": round(seen["server"], 3),
              "sim_s_at_detection": seen["server_sim_s"]}
    (tmp_path / "lease_report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
