"""What ``tagswarm up`` prints at the end of a run, from its metrics (no processes)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from tagswarm.upsummary import print_controller_trouble, print_summary


def _printed(metrics: dict[str, Any]) -> str:
    out = io.StringIO()
    print_summary(Console(file=out, width=400, color_system=None), metrics)
    return out.getvalue()


def _metrics(firsts: dict[str, float | None], warnings: list[str]) -> dict[str, Any]:
    ate = {"rmse": 0.01, "max": 0.02}
    return {"run": {"origin_id": 0}, "swarm": {"fused": {"ate_unaligned": ate, "time_localised": 0.5},
                                               "odom": {"ate_unaligned": ate}},
            "robots": {k: {"fused": {"first_s": f}} for k, f in firsts.items()}, "warnings": warnings}


def test_robots_never_placed_are_named_with_what_helps() -> None:
    text = _printed(_metrics({"0": 0.0, "1": 2.5, "2": None, "3": None}, []))
    assert "never localised: robot(s) 2, 3 of 4" in text
    assert "the other 2" in text and "origin robot 0" in text


def test_a_run_where_every_robot_was_placed_prints_no_such_line() -> None:
    assert "never localised" not in _printed(_metrics({"0": 0.0, "1": 2.5}, []))


def test_robots_placed_late_are_named_with_when() -> None:
    # the depot through the realistic camera: two robots holding at the far end first placed at 23.7 and 25.8 s
    # of 45, when a patrol passed; the summary said only "time localised 74 %"
    m = _metrics({"0": 0.0, "1": 6.2, "2": 25.8, "4": 23.7}, [])
    m["run"]["sim_time_s"] = 45.0
    text = _printed(m)
    assert "localised late: robot(s) 2 (25.8 s), 4 (23.7 s)" in text and "1 (6.2 s)" not in text
    assert "start_prior_sigma" in text  # the way out for robots that start at known places
    m["run"]["sim_time_s"] = 200.0  # 25.8 s of a 200 s run is not late
    assert "localised late" not in _printed(m)
    assert "localised late" not in _printed(_metrics({"0": 0.0, "1": 9.0}, []))


def test_robots_the_map_is_unsure_of_are_named_weakly_tied() -> None:
    m = _metrics({"0": 0.0, "1": 2.5, "2": 3.0, "3": 4.0}, [])
    for k, sigma in (("0", 0.004), ("1", 0.89), ("2", 0.07), ("3", 1.19)):
        m["robots"][k]["fused"]["sigma_median_m"] = sigma
    text = _printed(m)
    assert "weakly tied: robot(s) 1, 3 (the map's position σ, median over the run: 0.89-1.19 m)" in text
    m["robots"]["1"]["fused"]["sigma_median_m"] = m["robots"]["3"]["fused"]["sigma_median_m"] = 0.08
    assert "weakly tied" not in _printed(m)  # every robot of the built-in scenes stays under 0.08 m


def test_a_silent_source_is_printed_other_warnings_are_not() -> None:
    text = _printed(_metrics({"0": 0.0}, ["the recorder heard nothing from server after 15.9 s of the run's 60.0 s: x",
                                          "no mode samples: time_lost_s is 0"]))
    assert "warning: the recorder heard nothing from server after 15.9 s" in text
    assert "no mode samples" not in text
    hung = "the lockstep world stopped waiting for a participant alive but silent (1 time(s)): x"
    assert "warning: the lockstep world stopped waiting" in _printed(_metrics({"0": 0.0}, [hung]))


def test_up_pace_counts_from_the_first_simulated_time_not_process_start() -> None:
    from tagswarm.up import Pace

    pace = Pace()
    assert pace.rtf(0.0, 100.0) == 0.0  # processes starting: no simulated time yet
    assert pace.rtf(0.1, 104.0) == 0.0  # the first tick heard, 4 s after start
    assert pace.rtf(0.2, 104.1) == 0.0  # too short to tell
    assert pace.rtf(10.1, 114.0) == pytest.approx(1.0)
    assert pace.rtf(15.1, 124.0) == pytest.approx(0.75)


def test_robots_that_went_over_10cm_are_named_worst_first() -> None:
    m = _metrics({"0": 0.0, "1": 2.5, "2": 3.0, "3": 4.0}, [])
    for k, (rmse, mx) in {"0": (0.001, 0.002), "1": (0.021, 0.107), "2": (0.01, 0.099), "3": (0.135, 0.677)}.items():
        m["robots"][k]["fused"]["ate_unaligned"] = {"rmse": rmse, "max": mx}
    text = _printed(m)
    assert "over 10 cm at some time: robot(s) 3 (max 67.7 cm, RMSE 13.5 cm), 1 (max 10.7 cm, RMSE 2.1 cm);" in text
    assert "plots/error_over_time.png" in text
    for k in ("1", "3"):
        m["robots"][k]["fused"]["ate_unaligned"] = {"rmse": 0.01, "max": 0.05}
    assert "over 10 cm" not in _printed(m)


def test_the_default_run_folder_is_new_even_within_one_second(tmp_path: Path) -> None:
    from datetime import datetime

    from tagswarm.runtime.config import ConfigError
    from tagswarm.up import check_out, default_out

    now = datetime(2026, 12, 4, 2, 40, 0)
    first = default_out(tmp_path, now)
    assert first == tmp_path / "20261204-024000"
    first.mkdir()
    (first / "run.json").write_text("{}")
    second = default_out(tmp_path, now)
    assert second == tmp_path / "20261204-024000-2"
    check_out(second)  # new: no error
    with pytest.raises(ConfigError, match="already holds files"):
        check_out(first)


def test_a_failing_or_slow_own_controller_is_named_and_a_healthy_run_prints_nothing(tmp_path: Path) -> None:
    def printed(counters: dict[str, Any]) -> str:
        (tmp_path / "run.json").write_text(json.dumps({"counters": counters}))
        out = io.StringIO()
        print_controller_trouble(Console(file=out, width=400, color_system=None), tmp_path)
        return out.getvalue()

    healthy = {"agent/0": {"fixes": 9}, "agent/1": {"controller_cycles": 150, "controller_errors": 0}, "server": {}}
    assert printed(healthy) == ""
    text = printed({**healthy, "agent/2": {"controller_cycles": 150, "controller_errors": 75, "controller_slow": 3}})
    assert "robot 2's controller: 75 of 150 steps failed" in text and "logs/agent2.log" in text
    assert "robot 2's controller: 3 of 150 steps took longer than a control period" in text and "robot 1" not in text
    assert "stopped waiting" not in text
    hung = printed({**healthy, "world": {"ack_timeouts": 3, "ack_stalls": 1}})
    assert "the lockstep world stopped waiting for a participant alive but silent (1 time(s))" in hung
    (tmp_path / "run.json").write_text("{not json")
    out = io.StringIO()
    print_controller_trouble(Console(file=out), tmp_path)  # a run that crashed early: nothing, no traceback
    assert out.getvalue() == ""


def test_never_placed_with_landmarks_blames_the_landmarks_and_a_failed_run_blames_nothing() -> None:
    m = _metrics({"0": None, "1": None, "2": 1.0}, [])
    m["run"]["landmarks"] = 4
    text = _printed(m)
    assert "never localised: robot(s) 0, 1 of 3" in text and "landmark" in text and "origin robot 0" not in text
    failed = io.StringIO()
    print_summary(Console(file=failed, width=400, color_system=None), _metrics({"0": None, "1": None}, []), failed=True)
    assert "the run failed" in failed.getvalue() and "never placed" not in failed.getvalue()
