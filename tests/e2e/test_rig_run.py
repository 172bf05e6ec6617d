"""The ``rig`` scenario (four 120 deg fisheyes per robot) through real world and agent processes,
lockstep: a robot's four frames carry one stamp (robots are staggered, a rig's cameras are
not), and the agent's estimate of a robot standing in the overlap of two fisheyes uses both
(``RelativeObservation.camera`` names every camera of the estimate, joined with '+')."""

from __future__ import annotations

from collections import defaultdict

from tagswarm.protocol import messages as m
from tagswarm.testing import SwarmFactory

# robot 1 stands 45 deg to robot 0's left, facing it: in the 30 deg overlap of robot 0's front and
# left fisheyes (tests/unit/agents/test_rig.py renders the same view)
SETTINGS = {
    "robots.placement": "explicit",
    "robots.start": [{"x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0}, {"x_m": 0.8, "y_m": 0.8, "yaw_rad": -2.36}],
    "missions": [],
    "map.origin_id": 0,
    "render.stagger_cameras": True,
}
DURATION_S = 1.0


def test_a_rigs_frames_share_a_stamp_and_its_estimate_uses_two_cameras(swarm: SwarmFactory) -> None:
    with swarm.start("rig", robots=2, seed=0, duration_s=DURATION_S, set=SETTINGS, launch=False) as sw:
        frames = sw.subscribe("robot/*/camera/*")
        observations = sw.subscribe("robot/0/observation")
        sw.launch()
        run = sw.finish(timeout_s=600)
        stamps: dict[int, dict[int, set[str]]] = defaultdict(lambda: defaultdict(set))
        for s in frames.drain():
            img: m.CameraImage = s.msg
            stamps[img.robot_id][img.stamp_ns].add(img.camera)
        seen = [s.msg for s in observations.drain()]
    assert run.exit_codes and all(c == 0 for c in run.exit_codes.values()), run.exit_codes
    assert set(stamps) == {0, 1}
    for rid, by_stamp in stamps.items():
        # images are sent best-effort: allow one frame lost on the test's own subscription
        whole = [st for st, cams in by_stamp.items() if cams == {"front", "left", "rear", "right"}]
        assert len(whole) >= max(3, len(by_stamp) - 1), (rid, dict(by_stamp))
    # the robots are staggered: robot 1's rig fires between robot 0's (after the first tick, where every
    # sensor fires)
    first = min(min(stamps[0]), min(stamps[1]))
    assert not (set(stamps[0]) & set(stamps[1])) - {first}, (sorted(stamps[0]), sorted(stamps[1]))
    of_1 = [o for o in seen if o.target_kind == "robot" and o.target_id == 1]
    assert of_1, [(o.target_kind, o.target_id, o.camera) for o in seen]
    rig_estimates = [o for o in of_1 if len(o.camera.split("+")) >= 2]
    assert rig_estimates, [o.camera for o in of_1]
    assert {"front", "left"} <= set(rig_estimates[0].camera.split("+"))
    for o in rig_estimates:  # the truth in robot 0's frame: (0.8, 0.8), yaw -2.36
        assert abs(o.x_m - 0.8) < 0.05 and abs(o.y_m - 0.8) < 0.05, (o.x_m, o.y_m)
