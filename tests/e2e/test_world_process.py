"""The world as a real OS process (the installed ``tagswarm-world`` script), seen
over Zenoh on a private loopback network."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tagswarm.agents.odometry import DiffDriveOdometry, DiffDriveParams
from tagswarm.protocol import codec, tags
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import pose3_to_matrix
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import load_scenario
from tests.geometry_check import detector, facing, project, tag_owner, world_corners
from tests.harness import Participant, client, endpoint, process, script, world_argv

SPREAD = [  # (x, y, yaw): several distances (0.9 .. 3 m) and viewing angles
    'robots.placement="explicit"', "robots.count=5",
    "robots.start=[{x_m=0.0, y_m=0.0, yaw_rad=0.0}, {x_m=1.0, y_m=0.1, yaw_rad=3.1416},"
    " {x_m=2.2, y_m=-0.9, yaw_rad=2.5}, {x_m=2.9, y_m=1.0, yaw_rad=-2.2}, {x_m=-0.6, y_m=-1.8, yaw_rad=1.2}]",
    'robot.cameras=[{name="front", width=640, height=480, hfov_deg=70, rate_hz=5}]',
]


def test_images_decode_to_the_true_tags_and_reproject(tmp_path: Path) -> None:
    ep, run = endpoint(), "img"
    s = load_scenario("paper", SPREAD)
    keys = Keys(run)
    with process(world_argv(ep, run, *SPREAD, "duration_s=30"), tmp_path / "world.log") as world, client(ep) as bus:
        images = bus.subscribe(keys.images())
        truths = bus.subscribe(keys.truth())
        frames: dict[int, m.CameraImage] = {}
        poses: dict[int, m.GroundTruthPose] = {}

        def collect() -> bool:
            for it in images.drain():
                img = codec.decode(m.CameraImage, it.value)
                frames.setdefault(img.robot_id, img)
            for it in truths.drain():
                t = codec.decode(m.GroundTruthPose, it.value)
                poses[t.robot_id] = t
            return len(frames) == 5 and len(poses) == 5

        assert bus.wait_for(collect, 30), f"got images of {sorted(frames)}; world rc={world.poll()}"
    owner = tag_owner(s)
    errors: list[float] = []
    seen: dict[int, set[tuple[int, tags.Face]]] = {}
    for rid, img in frames.items():
        assert (img.width, img.height, img.encoding) == (640, 480, "mono8")
        pixels = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
        t_wc = pose3_to_matrix(poses[rid].pose) @ pose3_to_matrix(img.mount)
        seen[rid] = set()
        for d in detector().detect(pixels):
            assert d.tag_id in owner, f"robot {rid} decoded unknown tag {d.tag_id}"
            target, face = owner[d.tag_id]
            assert target != rid
            target_pose = pose3_to_matrix(poses[target].pose)
            assert face in facing(t_wc, target_pose)[1], f"robot {rid} saw the {face.name} of {target} from behind"
            seen[rid].add((target, face))
            uv = project((img.fx_px, img.fy_px, img.cx_px, img.cy_px), t_wc, world_corners(s, target_pose, face))
            errors.extend(np.linalg.norm(d.corners - 0.5 - uv, axis=1))
    # robot 1 faces robot 0 and vice versa: each sees the other's front tag (and, from the mast
    # camera above the cubes, its top), never a side or the back
    for a, b in ((0, 1), (1, 0)):
        faces = {f for t, f in seen[a] if t == b}
        assert tags.Face.FRONT in faces and faces <= {tags.Face.FRONT, tags.Face.TOP}, faces
    assert sum(len(v) for v in seen.values()) >= 6
    assert len(errors) >= 24
    assert float(np.median(errors)) < 1.0, f"median reprojection error {np.median(errors):.2f} px"


def _drive(ep: str, run: str, steps: int, schedule) -> tuple[list[bytes], list[tuple[int, int, int]]]:
    """Act as lockstep participant agent/0: send the scheduled commands, record every
    ground-truth pose (raw payload bytes) and every encoder reading."""
    keys = Keys(run)
    truth_raw: list[bytes] = []
    encoders: list[tuple[int, int, int]] = []
    with client(ep) as bus:
        truths = bus.subscribe(keys.truth())
        encs = bus.subscribe(keys.encoders())
        me = Participant(bus, keys, "agent/0")
        seq = 0

        def on_tick(tick: m.Tick) -> bool:
            nonlocal seq
            truth_raw.extend(it.value for it in truths.drain())
            for it in encs.drain():
                e = codec.decode(m.EncoderTicks, it.value)
                encoders.append((e.robot_id, e.left_ticks, e.right_ticks))
            if tick.step >= steps:
                return False
            for rid, (left, right) in schedule(tick.step).items():
                bus.put(keys.cmd(rid), codec.encode(m.WheelCommand(seq=seq, stamp_ns=tick.stamp_ns, robot_id=rid,
                                                                   left_rad_s=left, right_rad_s=right)))
                seq += 1
            return True

        me.serve(on_tick)
    return truth_raw, encoders


LOCKSTEP = ["clock.mode=\"lockstep\"", 'clock.participants=["agent/0"]', "clock.command_timeout_s=5",
            'robot.cameras=[{name="front", rate_hz=1}]']


def test_lockstep_runs_are_bit_identical_and_encoders_drift(tmp_path: Path) -> None:
    def schedule(k: int) -> dict[int, tuple[float, float]]:
        return {0: (8.0, 8.0 + 2 * math.sin(k / 15)), 1: (6.0, 9.0), 2: (9.0, 5.0 + k % 7)}

    runs = []
    for i in range(2):
        ep, run = endpoint(), f"det{i}"
        argv = world_argv(ep, run, *LOCKSTEP, "robots.count=3", "seed=42", "duration_s=60")
        with process(argv, tmp_path / f"world{i}.log"):
            runs.append(_drive(ep, run, 240, schedule))
    (truth_a, enc_a), (truth_b, enc_b) = runs
    decoded = [codec.decode(m.GroundTruthPose, b) for b in truth_a]
    assert len(decoded) == 3 * 241 and {t.step for t in decoded} == set(range(241))
    # bit-identical except each run's own sequence numbers/stamps, which are identical too
    assert truth_a == truth_b
    assert enc_a == enc_b
    start = {t.robot_id: (t.x_m, t.y_m) for t in decoded if t.step == 0}
    end = {t.robot_id: (t.x_m, t.y_m) for t in decoded if t.step == 239}
    assert all(math.dist(start[r], end[r]) > 0.3 for r in range(3))


def test_dead_reckoning_from_published_ticks_within_1cm_after_10m(tmp_path: Path) -> None:
    ep, run = endpoint(), "enc"
    argv = world_argv(ep, run, *LOCKSTEP, "robots.count=1", 'robots.placement="explicit"',
                      "robots.start=[{x_m=0.0, y_m=-1.0, yaw_rad=0.0}]", "encoders.error_model=false",
                      "duration_s=120")

    def schedule(k: int) -> dict[int, tuple[float, float]]:
        return {0: (9.0, 9.0) if k % 75 < 45 else (4.0, 9.0)}

    with process(argv, tmp_path / "world.log"):
        truth_raw, enc = _drive(ep, run, 800, schedule)
    s = load_scenario("paper")
    od = DiffDriveOdometry(DiffDriveParams(s.robot.wheel_radius_m, s.robot.wheel_base_m, s.encoders.ticks_per_rev),
                           x_m=0.0, y_m=-1.0)
    for _, left, right in enc:
        od.update(left, right)
    last = codec.decode(m.GroundTruthPose, truth_raw[-1])
    assert od.distance_m > 10.0
    assert math.hypot(last.x_m - od.x_m, last.y_m - od.y_m) < 0.01


def test_killed_participant_does_not_hang_lockstep(tmp_path: Path) -> None:
    ep, run = endpoint(), "kill"
    keys = Keys(run)
    parts = ['clock.participants=["agent/0", "agent/1"]', 'clock.mode="lockstep"', "clock.ack_timeout_s=30",
             "duration_s=40"]
    helper = [sys.executable, "-m", "tests.participant", "--connect", ep, "--run", run]
    with process(world_argv(ep, run, *parts), tmp_path / "world.log") as world, \
            process([*helper, "--name", "agent/0"]), process([*helper, "--name", "agent/1"]) as victim, \
            client(ep) as bus:
        ticks = bus.subscribe(keys.tick())
        last = -1

        def reached(step: int):
            def check() -> bool:
                nonlocal last
                for it in ticks.drain():
                    last = max(last, codec.decode(m.Tick, it.value).step)
                return last >= step
            return check

        assert bus.wait_for(reached(30), 60), f"lockstep world never reached step 30 (at {last})"
        assert last < 1000  # far from the end (1200 steps): the world must get past the kill by itself
        victim.send_signal(signal.SIGKILL)
        killed_at = last
        # ack timeout is 30 s: only liveliness can unblock the world this fast
        t0 = time.monotonic()
        assert bus.wait_for(reached(killed_at + 60), 20), f"world stuck at step {last} after SIGKILL"
        assert time.monotonic() - t0 < 20
        assert world.wait(timeout=60) == 0
    assert "agent/1 left" in (tmp_path / "world.log").read_text()


def test_alive_but_silent_participant_is_skipped_after_ack_timeout(tmp_path: Path) -> None:
    ep, run = endpoint(), "hang"
    parts = ['clock.participants=["agent/0"]', 'clock.mode="lockstep"', "clock.ack_timeout_s=0.2", "duration_s=0.4"]
    hang = [sys.executable, "-m", "tests.participant", "--connect", ep, "--run", run, "--name", "agent/0", "--hang"]
    with process(hang), process(world_argv(ep, run, *parts), tmp_path / "world.log") as world:
        assert world.wait(timeout=60) == 0
    assert "did not acknowledge step" in (tmp_path / "world.log").read_text()


@pytest.mark.parametrize("args", [
    ["--set", "tags.id_stride=3"],
    ["--set", "robot.cameras=[{width=-640}]"],
    ["--scenario", "no-such-scenario"],
    ["--set", "robots.count=many"],
    ["--render-workers", "-1"],
])
def test_invalid_config_exits_2_with_one_line(args: list[str]) -> None:
    res = subprocess.run([script("tagswarm-world"), *args], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "error" in lines[0], res.stderr
    assert "Traceback" not in res.stderr
