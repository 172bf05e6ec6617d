"""tagswarm.evaluation.report: metrics.json + four PNG plots from a synthetic run folder, and the
``tagswarm report`` entry point (summary table, one-line errors with exit code 2)."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest

from tagswarm.evaluation import report
from tagswarm.evaluation.metrics import RunFolderError, compute_metrics
from tagswarm.protocol.layout import start_poses
from tagswarm.protocol.scenario import load_scenario
from tests.unit.evaluation.test_metrics import three_circles

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def paper_scenario() -> dict[str, object]:
    """The built-in paper scenario as run.json stores it (resolved, JSON builtins)."""
    table: dict[str, object] = msgspec.to_builtins(load_scenario("paper"))
    return table


def modes_and_obs() -> tuple[list[tuple[int, int, str]], list[tuple[int, int, str, int]]]:
    modes = [(s * 10**9, k, "lost" if (k, s) == (2, 4) else "visual") for k in range(3) for s in range(20)]
    obs = [(i * 250_000_000, 0, "robot", 1) for i in range(80)] + [(5 * 10**9, 2, "robot", 1)]
    return modes, obs


def test_write_report_writes_metrics_json_and_four_pngs(tmp_path: Path) -> None:
    modes, obs = modes_and_obs()
    counters = {"world": {"frames_rendered": 300}, "agent/0": {"fixes": 4, "frames_processed": 90,
                                                               "frames_skipped": 10}}
    run = three_circles(tmp_path / "run", scenario=paper_scenario(), modes=modes, observations=obs,
                        counters=counters)
    metrics = report.write_report(run)
    for name in report.PLOTS:
        data = (run / "plots" / name).read_bytes()
        assert data[:8] == PNG_MAGIC, name
        assert len(data) > 10_000, name  # a drawn figure, not an empty canvas
    on_disk = json.loads((run / "metrics.json").read_text())
    assert on_disk == metrics
    assert on_disk == compute_metrics(run)
    assert on_disk["schema"] == "tagswarm.evaluation.metrics/1"
    assert on_disk["swarm"]["time_lost_s"] == pytest.approx(1.0)
    assert on_disk["error_vs_distance"]["samples"] > 0
    assert on_disk["cost"]["real_time_factor"] == pytest.approx(2.0)
    assert on_disk["warnings"] == []


def test_write_report_without_scenario_or_fused_still_plots(tmp_path: Path) -> None:
    run = three_circles(tmp_path / "run")
    for k in range(3):
        (run / "trajectories" / f"fused_{k}.tum").write_text("")
    metrics = report.write_report(run)
    assert sorted(p.name for p in (run / "plots").iterdir()) == sorted(report.PLOTS)
    assert any("no scenario" in w for w in metrics["warnings"])
    assert metrics["swarm"]["fused"]["ate_unaligned"] is None
    assert json.loads((run / "metrics.json").read_text())["swarm"]["fused"]["alignment"] is None


def test_invalid_scenario_is_a_run_folder_error(tmp_path: Path) -> None:
    run = three_circles(tmp_path / "run", scenario={"arena": {"size_x_m": "wide"}})
    with pytest.raises(RunFolderError, match="size_x_m"):
        report.write_report(run)


def test_arena_points_move_into_the_map_frame() -> None:
    # the map frame is the origin robot's first pose: that pose maps to (0, 0) and its heading to +x
    s = load_scenario("paper")
    x, y, yaw = start_poses(s)[s.map.origin_id]
    ahead = [x + np.cos(yaw), y + np.sin(yaw)]
    out = report.arena_points_to_map(s, np.array([[x, y], ahead]))
    assert out == pytest.approx(np.array([[0.0, 0.0], [1.0, 0.0]]), abs=1e-12)


# --------------------------------------------------------------------------- CLI


def test_cli_missing_folder_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert report.main([str(tmp_path / "missing")]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1
    assert captured.err.startswith("tagswarm report: error: ")
    assert "missing" in captured.err


def test_cli_bad_run_json_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "run.json").write_text("{\n  broken")
    assert report.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run.json" in err


def test_cli_without_argument_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        report.main([])
    assert exc.value.code == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_cli_prints_summary_and_returns_0(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    modes, obs = modes_and_obs()
    run = three_circles(tmp_path / "run", scenario=paper_scenario(), modes=modes, observations=obs)
    assert report.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "swarm" in out and "fused ATE" in out and "searches" in out
    assert "real-time factor 2.00" in out
    assert "shared SE(2) alignment" in out
    assert (run / "metrics.json").is_file()


def test_the_maps_own_sigma_of_each_robot_is_in_the_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    from tests.unit.evaluation.test_metrics_relocalisation import T10, kidnap_run, write_cov

    run = kidnap_run(tmp_path / "run")
    write_cov(run, 1, T10, np.diag([0.1369, 0.0169, 0.01]))  # sigma 0.37 m along the larger axis
    assert report.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "σ" in out and "0.370" in out


def test_recovery_in_the_summary_and_marked_on_the_error_plot(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    from matplotlib.figure import Figure

    from tagswarm.evaluation.metrics import evaluate, load_run
    from tests.unit.evaluation.test_metrics_relocalisation import kidnap_run, write_commands, write_relocs

    counters = {"world": {"contacts_robot_robot": 2, "contacts_robot_1": 2, "contacts_robot_2": 2}}
    run = kidnap_run(tmp_path / "run", counters=counters)
    write_commands(run, [(5.0, 1, "teleport", 5.0)])
    write_relocs(run, [(6.45, 1, 1.02, 4, "0 -1"), (7.0, 2, 0.3, 3, "1")])
    assert report.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "time" in out and "localised" in out and "NEES" in out
    assert "re-localisations: 2" in out
    assert "t=6.45 s robot 1: jump 1.02 m on 4 observations by 0, landmark; error 1.000 -> 0.050 m" in out
    assert "kidnap t=5.00 s robot 1 (teleport, 1.00 m): localised again after 1.50 s, first re-localisation " \
           "after 1.45 s" in out
    assert "contacts: robot-robot 2, robot-obstacle 0, robot-wall 0" in out
    # robot 1's fused error in the map frame, then the same outside its kidnap (1 m off from 5 to 6.5 s)
    m = json.loads((run / "metrics.json").read_text())["robots"]["1"]["fused"]
    full, nominal = m["ate_unaligned"]["rmse"], m["ate_unaligned_nominal"]["rmse"]
    assert nominal < 0.05 < full and f"{full:.3f} ({nominal:.3f})" in out
    assert (run / "plots" / "error_over_time.png").read_bytes()[:8] == PNG_MAGIC

    ev = evaluate(load_run(run))
    fig = Figure()
    ax_f, ax_o = fig.subplots(2, 1)
    handles = report._mark_events(ax_f, ax_o, ev)
    assert [h.get_label() for h in handles] == ["re-localisation", "kidnap"]
    # two events and one kidnap, a vertical line each on both axes (x data = [t, t])
    for ax in (ax_f, ax_o):
        xs = sorted(line.get_xdata()[0] for line in ax.get_lines() if len(line.get_xdata()) == 2)
        assert xs == pytest.approx([5.0, 6.45, 7.0])
