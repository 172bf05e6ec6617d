"""An agent process under bad input and a restart (realtime, real processes)."""

from __future__ import annotations

import signal
from contextlib import ExitStack
from pathlib import Path

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tests.harness import client, endpoint, process, script, wait_alive

SCEN = ["--set", "robots.count=2", "--duration", "120"]


def _status(bus, keys: Keys, rid: int, pred, timeout: float = 30.0) -> dict[str, int]:  # type: ignore[no-untyped-def]
    inbox = bus.subscribe(keys.robot_status(rid))
    last: dict[str, int] = {}

    def check() -> bool:
        for it in inbox.drain():
            last.clear()
            last.update(codec.decode(m.AgentStatus, it.value).counters)
        return bool(last) and pred(last)

    assert bus.wait_for(check, timeout), last
    return last


def test_bad_input_is_counted_and_a_restarted_agent_resumes_from_the_map(tmp_path: Path) -> None:
    ep, run = endpoint(), "agentproc"
    keys = Keys(run)
    common = ["--run", run, "--connect", ep, *SCEN]
    agent1 = [script("tagswarm-agent"), "--robot-id", "1", *common]
    with ExitStack() as st:
        st.enter_context(process([script("tagswarm-world"), "--listen", ep, "--run", run, *SCEN], tmp_path / "w.log"))
        st.enter_context(process([script("tagswarm-server"), *common], tmp_path / "s.log"))
        st.enter_context(process([script("tagswarm-agent"), "--robot-id", "0", *common], tmp_path / "a0.log"))
        victim = st.enter_context(process(agent1, tmp_path / "a1.log"))
        bus = st.enter_context(client(ep))
        wait_alive(bus, keys, "agent/1")
        _status(bus, keys, 1, lambda c: c.get("localised") == 1 and c.get("corrections", 0) > 5)

        good = m.CameraImage(seq=0, stamp_ns=0, robot_id=1, camera="front", step=0, width=4, height=4, fx_px=1.0,
                             fy_px=1.0, cx_px=2.0, cy_px=2.0, mount=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.2), data=bytes(16))
        raw = _patch_bytes(codec.encode(good), b"\xa5mono8", b"\xa4rgb8")
        bad_corr = m.Correction(seq=0, stamp_ns=0, robot_id=1, map_odom_x_m=float("nan"), map_odom_y_m=0.0,
                                map_odom_yaw_rad=0.0, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9)
        other = m.Correction(seq=0, stamp_ns=0, robot_id=0, map_odom_x_m=50.0, map_odom_y_m=0.0,
                             map_odom_yaw_rad=0.0, x_m=50.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9)
        for _ in range(20):
            bus.put(keys.image(1, "front"), codec.encode(_replace(good, data=bytes(15))), drop=False)
            bus.put(keys.image(1, "front"), raw, drop=False)
            bus.put(keys.correction(1), codec.encode(bad_corr))
            bus.put(keys.correction(1), codec.encode(other))
        counters = _status(bus, keys, 1, lambda c: c.get("rejected_non_finite", 0) >= 20
                           and c.get("rejected_spoofed", 0) >= 20
                           and c.get("rejected_inconsistent", 0) + c.get("rejected_malformed", 0) >= 1)
        assert victim.poll() is None  # still running
        assert counters["localised"] == 1

        victim.send_signal(signal.SIGKILL)
        victim.wait(10)
        # the server notices through liveliness: robot 1 stays in the map, marked not alive
        maps = bus.subscribe(keys.map())
        seen: dict[int, bool] = {}

        def marked_dead() -> bool:
            for it in maps.drain():
                seen.update({e.robot_id: e.alive for e in codec.decode(m.GlobalMap, it.value).robots})
            return seen.get(1) is False

        assert bus.wait_for(marked_dead, 5), seen
        assert seen.get(0) is True
        with process(agent1, tmp_path / "a1b.log"):
            first = _status(bus, keys, 1, lambda c: "resumed_from_map" in c or c.get("corrections", 0) > 0)
            assert first.get("resumed_from_map") == 1, first
            assert first.get("map_entries_at_start", 0) == 2


def _patch_bytes(payload: bytes, old: bytes, new: bytes) -> bytes:
    assert old in payload
    return payload.replace(old, new)


def _replace(msg: m.CameraImage, **changes: object) -> m.CameraImage:
    import msgspec

    return msgspec.structs.replace(msg, **changes)
