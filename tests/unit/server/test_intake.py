"""The server's input checks (tagswarm.server.intake): what reaches the fusion and what is
dropped and counted, and the lockstep bookkeeping of whose odometry of a tick is still due."""

from __future__ import annotations

import logging
from collections import Counter, deque

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Received
from tagswarm.protocol.keys import Keys
from tagswarm.runtime import streams
from tagswarm.server.intake import AckLog, Intake, OdometryWait

KEYS = Keys("t")
DT = 33_333_333  # a lockstep clock step (ns): a tick of step k is stamped k * DT
COV = (0.01, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.01)


def _intake() -> tuple[Intake, streams.RejectCounter, Counter[str]]:
    rejects, counters = streams.RejectCounter(logging.getLogger("test")), Counter[str]()
    return Intake(KEYS, {0, 1, 2}, rejects, streams.GapCounter(), counters), rejects, counters


def _odom(key_robot: int, robot: int, seq: int = 0) -> Received[bytes]:
    return Received(KEYS.odometry(key_robot), codec.encode(m.OdometryEstimate(
        seq=seq, stamp_ns=1000, robot_id=robot, x_m=1.0, y_m=2.0, yaw_rad=0.5, cov=COV, distance_m=3.0)))


def _obs(key_robot: int, robot: int, target: int, kind: str = "robot",
         tags: tuple[int, ...] = (1,)) -> Received[bytes]:
    return Received(KEYS.observation(key_robot), codec.encode(m.RelativeObservation(
        seq=0, stamp_ns=1000, robot_id=robot, target_kind=kind, target_id=target, x_m=1.0, y_m=0.0, yaw_rad=0.0,
        cov=COV, pose=m.Pose3(x_m=1.0, y_m=0.0, z_m=0.0), reprojection_rms_px=0.2, tag_ids=tags,
        camera="front")))  # type: ignore[arg-type]


def test_odometry_of_a_roster_robot_on_its_own_key_passes_as_a_record() -> None:
    intake, rejects, _ = _intake()
    ((key, rec, seq),) = intake.odometry([_odom(1, 1, seq=7)])
    assert (key, seq) == (KEYS.odometry(1), 7)
    assert (rec.robot_id, rec.stamp_ns, rec.x_m, rec.y_m, rec.yaw_rad, rec.distance_m) == (1, 1000, 1.0, 2.0, 0.5, 3.0)
    assert not rejects.counts


def test_spoofed_unknown_and_malformed_inputs_are_dropped_and_counted() -> None:
    intake, rejects, _ = _intake()
    bad_odom = [_odom(1, 2), _odom(5, 5), Received(KEYS.odometry(1), b"\xc1")]
    assert list(intake.odometry(bad_odom)) == []
    bad_obs = [_obs(1, 2, 0), _obs(1, 1, 1), _obs(1, 1, 9), _obs(7, 7, 0)]
    assert list(intake.observations(bad_obs)) == []
    assert rejects.counts == {"spoofed": 2, "unknown_robot": 4, "malformed": 1}


def test_observations_pass_and_joint_landmark_fixes_are_counted() -> None:
    intake, rejects, counters = _intake()
    recs = list(intake.observations([_obs(0, 0, 2), _obs(2, 2, 40, kind="landmark", tags=(40, 41))]))
    assert [(r.observer, r.target_kind, r.target_id) for r in recs] == [(0, "robot", 2), (2, "landmark", 40)]
    assert counters["multi_landmark_fixes"] == 1 and not rejects.counts


def test_an_ack_counts_only_from_its_own_agent() -> None:
    intake, rejects, _ = _intake()
    mine = Received(KEYS.ack("agent/1"), codec.encode(m.TickAck(seq=0, stamp_ns=500, participant="agent/1", step=5)))
    forged = Received(KEYS.ack("agent/1"), codec.encode(m.TickAck(seq=1, stamp_ns=500, participant="agent/2",
                                                                  step=6)))
    assert list(intake.acks(1, [mine, forged])) == [(5, 500)]
    assert rejects.counts == {"spoofed": 1}


def test_odometry_wait_settles_on_arrival_or_after_the_grace_of_an_ack() -> None:
    acked: dict[int, deque[tuple[int, int]]] = {0: deque(), 1: deque(), 2: deque()}
    wait = OdometryWait(step=4, stamp_ns=400, grace_s=0.03, deadline=10.0)
    latest = {0: 400, 1: 300}
    # robot 1 has neither its odometry nor an ack: wait until the deadline; robot 2 is not alive
    assert not wait.settled(0.0, {0, 1}, latest, acked) and wait.next_at == 10.0
    acked[1].append((4, 400))  # its ack is in, the odometry sent before it is not (yet)
    assert not wait.settled(1.0, {0, 1}, latest, acked) and wait.next_at == 1.03
    assert not wait.settled(1.02, {0, 1}, latest, acked)
    assert wait.settled(1.03, {0, 1}, latest, acked)  # the grace ran out: lost, not late
    assert wait.lost({0, 1}, latest, acked) == [1]
    latest[1] = 400
    assert wait.settled(1.04, {0, 1}, latest, acked) and wait.lost({0, 1}, latest, acked) == []


def test_an_ack_of_another_tick_excuses_nothing() -> None:
    acked: dict[int, deque[tuple[int, int]]] = {0: deque([(5, 500), (3, 300)])}
    wait = OdometryWait(step=4, stamp_ns=400, grace_s=0.0, deadline=10.0)
    assert not wait.settled(5.0, {0}, {0: 300}, acked)
    assert wait.lost({0}, {0: 300}, acked) == []


def test_a_robot_with_frames_in_the_tick_is_waited_for_until_its_ack() -> None:
    # its odometry comes first, the observations of its frames after it, its ack last: advancing on the
    # odometry alone let an observation of the tick come late under load (a lockstep run then left its
    # byte-identical path)
    acked: dict[int, deque[tuple[int, int]]] = {0: deque(), 1: deque()}
    wait = OdometryWait(step=4, stamp_ns=400, grace_s=0.03, deadline=10.0, with_frames={1})
    latest = {0: 400, 1: 400}
    assert not wait.settled(0.0, {0, 1}, latest, acked) and wait.next_at == 10.0
    acked[0].append((4, 400))  # robot 0 had no frame this tick: its ack was never needed
    assert not wait.settled(0.5, {0, 1}, latest, acked)
    acked[1].append((3, 300))  # an ack of another tick does not do
    assert not wait.settled(0.6, {0, 1}, latest, acked)
    acked[1].append((4, 400))
    assert wait.settled(0.7, {0, 1}, latest, acked) and wait.lost({0, 1}, latest, acked) == []
    # without frames in the tick the odometry alone settles it, as before
    assert OdometryWait(step=4, stamp_ns=400, grace_s=0.03, deadline=10.0).settled(0.0, {0, 1}, latest,
                                                                                  {0: deque(), 1: deque()})


def test_a_flood_of_forged_future_acks_never_pushes_out_the_genuine_one() -> None:
    # the injection test's flood: 72 copies of an ack of step 10**9 on agent 1's own key (its participant
    # matches, so the intake passes it) arrived just after the real ack of the waited tick; an 8-slot FIFO
    # then forgot the real one and the tick waited clock.ack_timeout_s for it
    log = AckLog(capacity=8)
    log.extend([(33, 33 * DT)])
    log.extend([(10**9, 0)] * 72)
    assert (33, 33 * DT) in log and len(log) == 2
    log.expect(33, 33 * DT, DT)  # the wait for tick 33 begins: (10**9, 0) is not where the clock puts it
    assert (33, 33 * DT) in log and len(log) == 1
    # distinct plausible future acks beyond capacity: the latest steps go, the waited one stays
    log.extend((34 + i, (34 + i) * DT) for i in range(100))
    assert (33, 33 * DT) in log and len(log) == 8 and (41, 41 * DT) not in log
    wait = OdometryWait(step=33, stamp_ns=33 * DT, grace_s=0.03, deadline=10.0, with_frames={1})
    assert wait.settled(0.0, {1}, {1: 33 * DT}, {1: log})


def test_forged_acks_of_the_waited_step_or_earlier_ones_are_dropped_while_it_is_waited_for() -> None:
    # 64 forged acks of the waited step with smaller stamps, or of earlier steps, arriving during the wait
    # would have been smaller than the real one and pushed it out as the largest
    log = AckLog(capacity=8)
    log.expect(33, 33 * DT, DT)
    log.extend([(33, 33 * DT)])
    log.extend((33, i) for i in range(64))
    log.extend((i, i * DT) for i in range(33))
    assert len(log) == 1 and (33, 33 * DT) in log


def test_ack_log_on_a_restarted_world_forgets_the_old_runs_later_steps() -> None:
    log = AckLog(capacity=4)
    log.expect(40, 40 * DT, DT)
    log.extend([(40, 40 * DT), (41, 41 * DT)])
    log.restart(2)  # the new run's first tick is step 2: the old run's 40 and 41 would excuse its own
    assert len(log) == 0
    log.extend([(1, 1 * DT), (2, 2 * DT)])  # no expectation until the new run's first wait
    log.expect(2, 2 * DT, DT)
    assert (2, 2 * DT) in log and (1, DT) not in log


def test_a_restarted_worlds_first_ack_that_overtakes_its_first_tick_is_kept() -> None:
    # the old run waits for tick 300; the new world's agents ack its tick 0 before the server sees that tick
    log = AckLog(capacity=8)
    log.expect(300, 300 * DT, DT)
    log.extend([(0, 0)])
    assert (0, 0) not in log  # not an ack of the old run's waited tick or a later one
    log.restart(0)
    log.expect(0, 0, DT)
    assert (0, 0) in log
