"""`satpose campaign`: spec checks, a small campaign on a Dask LocalCluster, a cell that fails
on purpose, resuming, and the time limit."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from satpose.datasets.errors import ConfigError
from satpose.tools.campaign import PeakMemory, _write_table, read_results, run_campaign, run_cell
from satpose.tools.campaign_spec import load_spec
from satpose.tools.cli import main

# 640x480 from 4.5 m: a small render on which the frontend finds the ring of seed 0's
# paper-docking (at 7 m, or at 160x120 to 480x360 with 1 spp, it sees nothing and every cell
# fails: no estimate).
SPEC = """\
name: test
time_limit_s: 300
base:
  scenario: paper-docking
  seed: 0
  frames: 3
  size: 640x480
  spp: 2
  perturb: {motion.start_position_m: [0.15, 0.05, 4.5]}
axes:
  estimator: [offline, kalman]
  config:
    plain: {compare: false, recording.images: false, recording.orb_points: false}
    broken: {compare: maybe}
"""
"""Four cells, one render: the two `broken` cells fail on purpose (compare is a bool)."""


def _write(tmp_path: Path, text: str, name: str = "spec.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("campaign")
    spec = _write(base, SPEC)
    out = base / "out"
    assert main(["campaign", str(spec), "--out", str(out), "--workers", "2"]) == 0
    return spec, out


def test_spec_expands_the_product(tmp_path: Path) -> None:
    spec = load_spec(_write(tmp_path, SPEC))
    assert len(spec.cells) == 4
    assert len({c.cell_id for c in spec.cells}) == 4
    assert {(c.axes["estimator"], c.axes["config"]) for c in spec.cells} == {
        ("offline", "plain"),
        ("offline", "broken"),
        ("kalman", "plain"),
        ("kalman", "broken"),
    }
    broken = next(c for c in spec.cells if c.axes["config"] == "broken")
    assert broken.config == {"compare": "maybe"}
    plain = next(c for c in spec.cells if c.axes["config"] == "plain")
    assert plain.config["recording"] == {"images": False, "orb_points": False}
    # The same spec read again gives the same cell ids (what resuming relies on).
    assert [c.cell_id for c in load_spec(tmp_path / "spec.yaml").cells] == [
        c.cell_id for c in spec.cells
    ]


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("name: x\nbase: {scenario: paper-docking}\nlimits: 3\n", "limits"),
        ("base: {scenario: paper-docking}\naxes: {colour: [red]}\n", "axes.colour"),
        ("base: {scenario: no-such-preset}\n", "base.scenario"),
        ("base: {sequence: does/not/exist}\n", "base.sequence"),
        ("base: {scenario: paper-docking}\naxes: {estimator: [online, ekf]}\n", "axes.estimator"),
        (
            "base: {scenario: paper-docking}\naxes: {config: {a: {backend.no_such_key: 1}}}\n",
            "no_such_key",
        ),
        ("base: {scenario: paper-docking, perturb: {rig.wobble: 2}}\n", "wobble"),
        ("base: {scenario: paper-docking}\naxes: {seed: [1, 2\n", "not valid YAML"),
        ("base: {scenario: random}\n", "seed"),
        ("base: {sequence: ., seed: 3}\n", "sequence"),
        ("base: {scenario: spin-far, pipeline: orbit}\n", "base.pipeline"),
        ("base: {scenario: spin-far}\naxes: {pipeline: [spin, stereo]}\n", "axes.pipeline"),
        ("base: {scenario: spin-far, pipeline: spin, estimator: online}\n", "estimator"),
        ("base: {scenario: paper-docking, pipeline: bracket, estimator: frontend}\n", "frontend"),
        ("base: {scenario: spin-far, pipeline: spin, config: {rate.no_such: 1}}\n", "no_such"),
        ("base: {scenario: bracket-random, pipeline: bracket}\n", "seed"),
        ("base: {scenario: bracket-random, seed: 1}\n", "pipeline: bracket"),
        ("base: {scenario: bracket-random, seed: 1, pipeline: bracket, spp: 4}\n", "spp"),
        ("base: {scenario: paper-docking}\naxes: {perturb.: {a: {}}}\n", "axes.perturb."),
    ],
)
def test_bad_spec_is_one_line_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, key: str
) -> None:
    spec = _write(tmp_path, text)
    with pytest.raises(ConfigError):
        load_spec(spec)
    assert main(["campaign", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith("satpose campaign: error: ") and str(spec) in err and key in err
    assert not (tmp_path / "out").exists()  # refused before any work


def test_results_table(campaign: tuple[Path, Path]) -> None:
    _, out = campaign
    df = read_results(out)
    assert len(df) == 4 and df["cell"].is_unique
    ok = df[df["config"] == "plain"]
    broken = df[df["config"] == "broken"]
    assert (ok["status"] == "ok").all(), ok["error"].tolist()
    assert (broken["status"] == "failed").all()
    assert broken["error"].str.contains("compare").all()
    for col in ("est.pos_cm", "est.rot_deg", "est.ate_m", "est.rpe_trans_m", "total_s"):
        assert np.isfinite(ok[col].to_numpy(dtype=float)).all() and (ok[col] > 0).all(), col
    assert (ok["peak_rss_mb"] > 0).all()
    assert {"est.nees_mean", "est.bias.depth_cm", "est.bias.depth_sd_cm"} <= set(df.columns)
    # Each estimator's own trajectory is the one under est.
    off = ok[ok["estimator"] == "offline"].iloc[0]
    assert off["est.pos_cm"] == off["offline.pos_cm"]
    # One render shared by the four cells, and the run folders on the workers' path.
    assert len(list((out / "sequences").iterdir())) == 1
    for run in ok["run_path"]:
        assert (Path(run) / "metrics.json").is_file()
    summary = (out / "summary.md").read_text()
    assert "| ok | 2 |" in summary and "| failed | 2 |" in summary
    assert (out / "pos_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_rerun_skips_done_cells(campaign: tuple[Path, Path]) -> None:
    spec, out = campaign
    before = read_results(out)
    outcome = run_campaign(load_spec(spec), out)  # nothing to do: no cluster is started
    assert (outcome.ran, outcome.skipped) == (0, 4)
    pd.testing.assert_frame_equal(read_results(out), before)


def test_resume_runs_only_missing_cells(campaign: tuple[Path, Path], tmp_path: Path) -> None:
    spec, out = campaign
    # A copy of the campaign folder missing one finished cell (as after a Ctrl-C).
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    before = read_results(copy)
    gone = before[(before["status"] == "ok") & (before["estimator"] == "kalman")].iloc[0]
    before[before["cell"] != gone["cell"]].to_parquet(copy / "results.parquet", index=False)
    outcome = run_campaign(load_spec(spec), copy, workers=1)
    assert (outcome.ran, outcome.skipped) == (1, 3)
    table = read_results(copy)
    assert pd.api.types.is_integer_dtype(table["seed"])  # old and new rows: one column type
    after = table.set_index("cell")
    assert set(after.index) == set(before["cell"])
    # The same cell on the same (cached) render gives the same metrics, bit for bit.
    again = after.loc[gone["cell"]]
    assert again["status"] == "ok"
    for col in ("est.pos_cm", "est.rot_deg", "est.ate_m", "est.nees_mean"):
        assert again[col] == gone[col], col


def test_time_limit_is_a_timeout_row(campaign: tuple[Path, Path], tmp_path: Path) -> None:
    spec, out = campaign
    cell = next(c for c in load_spec(spec).cells if c.axes["config"] == "plain")
    folder = next((out / "sequences").iterdir())
    rendered = {"path": str(folder), "render_s": 0.0, "status": "ok", "error": ""}
    row = run_cell(cell, rendered, str(tmp_path), 1e-6)
    assert row["status"] == "timeout" and "time limit" in row["error"]
    assert not (tmp_path / "cells" / cell.cell_id / "run").exists()  # no half-written run


SPECS = sorted((Path(__file__).parents[2] / "benchmarks" / "campaigns").glob("*.yaml"))


@pytest.mark.parametrize("spec", SPECS, ids=lambda p: p.name)
def test_shipped_specs_load(spec: Path) -> None:
    assert len(SPECS) >= 2
    loaded = load_spec(spec)
    assert loaded.cells and loaded.time_limit_s > 0


def test_out_that_is_a_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = _write(tmp_path, SPEC)
    out = tmp_path / "taken"
    out.write_text("not a folder")
    assert main(["campaign", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(out) in err


def test_perturbation_value_fails_its_cells_only(tmp_path: Path) -> None:
    spec = _write(
        tmp_path,
        "base: {scenario: paper-docking, frames: 2, size: 160x120}\n"
        "axes:\n  perturb:\n    wide: {rig.baseline_m: wide}\n    bad-focal: {rig.focal_px: -1}\n",
    )
    # Both cells fail on the client (no render, no cluster) and land in the table.
    outcome = run_campaign(load_spec(spec), tmp_path / "out")
    assert outcome.statuses == {"ok": 0, "failed": 2, "timeout": 0}
    df = read_results(tmp_path / "out").set_index("perturb")
    assert "baseline_m" in df.loc["wide", "error"]
    assert "focal" in df.loc["bad-focal", "error"]
    assert not (tmp_path / "out" / "sequences").exists()


def test_named_override_axes_multiply_and_merge(tmp_path: Path) -> None:
    spec = load_spec(
        _write(
            tmp_path,
            "base: {pipeline: spin, scenario: spin-far, perturb: {render.masks: false}}\n"
            "axes:\n"
            "  perturb.target: {sym: {}, asym: {target.wings.nx_span_m: 0.5}}\n"
            "  perturb.rate:\n"
            "    '25': {motion.angular_velocity_deg_s: [0, 0, 25]}\n"
            "    '120': {motion.angular_velocity_deg_s: [0, 0, 120]}\n"
            "  config: {'19': {}, '40': {rate.window_frames: 40}}\n",
        )
    )
    assert len(spec.cells) == 2 * 2 * 2
    cell = next(
        c
        for c in spec.cells
        if (c.axes["perturb.target"], c.axes["perturb.rate"], c.axes["config"])
        == ("asym", "120", "40")
    )
    assert cell.pipeline == "spin" and "estimator" not in cell.axes
    # base perturb, then perturb.target, then perturb.rate: one nested override
    assert cell.perturb == {
        "render": {"masks": False},
        "target": {"wings": {"nx_span_m": 0.5}},
        "motion": {"angular_velocity_deg_s": [0, 0, 120]},
    }
    assert cell.config == {"rate": {"window_frames": 40}}


# --------------------------------------------------------------------------------------------
# Cell kinds: the stereo frontend alone, spin, bracket (run on a worker's code path without a
# cluster: run_cell, then the table's Parquet round trip)
# --------------------------------------------------------------------------------------------


def _one_row(tmp_path: Path, row: dict) -> dict:
    """A row as it comes back from results.parquet."""
    _write_table([row], tmp_path / "results.parquet")
    return read_results(tmp_path).iloc[0].to_dict()


def test_frontend_cell_scores_the_frontend_alone(
    campaign: tuple[Path, Path], tmp_path: Path
) -> None:
    from satpose.datasets.sequence import load_sequence
    from satpose.frontend.pipeline import FrontendConfig
    from satpose.frontend.pose import PoseConfig
    from satpose.tools.frontend_score import (
        pose_stats,
        ring_stats,
        run_frontend,
        score_from_columns,
    )

    _, out = campaign
    folder = next((out / "sequences").iterdir())
    spec = _write(
        tmp_path,
        SPEC.replace("  estimator: [offline, kalman]\n", "  estimator: [frontend]\n").replace(
            "    broken: {compare: maybe}\n", "    eq9: {frontend.pose.method: eq9}\n"
        ),
    )
    cells = {c.axes["config"]: c for c in load_spec(spec).cells}
    rendered = {"path": str(folder), "render_s": 0.0, "status": "ok", "error": ""}
    row = _one_row(tmp_path, run_cell(cells["eq9"], rendered, str(tmp_path), 300.0, order=1))
    assert row["status"] == "ok", row["error"]
    assert row["pipeline"] == "stereo" and row["frontend_method"] == "eq9" and row["order"] == 1
    # The same numbers as the frontend scored here directly (deterministic: exactly equal).
    seq = load_sequence(folder)
    results, _, _ = run_frontend(seq, FrontendConfig(pose=PoseConfig(method="eq9")))
    score = score_from_columns(row)
    assert score["ring"] == ring_stats(seq, results)
    direct = pose_stats(seq, results)
    assert score["pose"] == direct
    assert direct["poses"] >= 2  # the ring and a landmark are found at 4.5 m
    assert row["est.pos_cm"] == direct["pos_cm"] and row["est.rot_deg"] == direct["rot_deg"]
    assert (tmp_path / "cells" / cells["eq9"].cell_id / "run" / "score.json").is_file()


def test_spin_cell_matches_the_spin_frontend(rendered_spin: Path, tmp_path: Path) -> None:
    from satpose.datasets.sequence import load_sequence
    from satpose.frontend.spin import RateConfig, SpinConfig, SpinFrontend, SpinStep
    from satpose.tools.spin_score import spin_stats, stats_columns, stats_from_columns

    spec = load_spec(
        _write(
            tmp_path,
            f"base: {{pipeline: spin, sequence: {rendered_spin}}}\n"
            "axes:\n  config: {plain: {}, prior: {rate.max_rate_deg_s: 89}}\n",
        )
    )
    cell = next(c for c in spec.cells if c.axes["config"] == "prior")
    row = _one_row(tmp_path, run_cell(cell, None, str(tmp_path), 300.0))
    assert row["status"] == "ok", row["error"]
    stats = stats_from_columns(row)
    # An independent pass of the spin frontend with the same config: the same windows.
    steps: list[SpinStep] = []
    seq = load_sequence(rendered_spin)
    fe = SpinFrontend(
        seq.calibration.left, SpinConfig(rate=RateConfig(max_rate_deg_s=89.0)), steps.append
    )
    for frame in seq:
        fe.process_frame(frame)
    assert seq.truth is not None and seq.truth.angular_velocity is not None
    truth = np.degrees(np.linalg.norm(seq.truth.angular_velocity, axis=1))
    direct = spin_stats([(k, s.fit) for k, s in enumerate(steps) if s.fit is not None], truth)
    # Field by field, NaN equal to NaN (one disjoint window has no spread): as JSON text.
    assert json.dumps(stats_columns(stats), sort_keys=True) == json.dumps(
        stats_columns(direct), sort_keys=True
    )
    assert stats.windows == len(seq) - 19 + 1  # one estimate per frame once 19 are buffered
    # 60 deg/s below the stated fold: accepted and near the truth (noisy: 0.5 deg/s)
    assert stats.status["ok"] >= 1 and abs(stats.bias) < 0.5
    assert row["spin.truth_deg_s"] == pytest.approx(60.0, abs=1e-6)
    assert (Path(row["run_path"]) / "spin.csv").is_file()


def test_bracket_cell_round_trips_its_score(tmp_path: Path) -> None:
    from satpose.tools.bracket_score import score_from_json, score_sequence, score_to_json
    from satpose.tools.campaign import render_cached
    from satpose.tools.campaign_spec import scenario_of

    spec = load_spec(
        _write(
            tmp_path,
            "base: {pipeline: bracket, scenario: bracket-random, seed: 1, frames: 2,"
            " size: 480x384}\n",
        )
    )
    (cell,) = spec.cells
    assert cell.axes["estimator"] == "none"
    rendered = render_cached(scenario_of(cell), str(tmp_path / "seq"), 300.0)
    assert rendered["status"] == "ok", rendered["error"]
    row = _one_row(tmp_path, run_cell(cell, rendered, str(tmp_path), 300.0))
    assert row["status"] == "ok", row["error"]
    score = score_from_json(row["bracket.score"])
    assert row["bracket.frames"] == len(score["rows"]) == 2
    # Each frame has a pose or the reason it has none.
    assert all(("e_pos_m" in r) != ("reason" in r) for r in score["rows"])
    assert row["frames_with_pose"] == sum("e_pos_m" in r for r in score["rows"])
    # The same member scored again: the same rows, and JSON keeps every float exactly (the
    # CPU time aside).
    again = score_sequence(tmp_path / "seq", tmp_path / "again")
    again["cpu_s"] = score["cpu_s"]
    assert score_to_json(again) == score_to_json(score)


def test_peak_memory_is_the_cells_own() -> None:
    big = np.ones(400 * 2**20 // 8)  # 400 MB resident before the cell
    try:
        before = PeakMemory._vmhwm() / 2**20  # the process's peak so far, with the block
    except (OSError, ValueError):
        pytest.skip("no /proc/self/status VmHWM: the sampled fallback is tested below")
    del big
    with PeakMemory() as memory:
        block = np.ones(100 * 2**20 // 8)  # 100 MB inside it
        del block
    assert memory.method == "vmhwm"
    # The cell's peak holds its 100 MB block on top of what the process keeps resident, not
    # the 400 MB block before it (which the process's peak, the old column, would report):
    # below it by the 300 MB difference, less 50 MB of slack for the allocator.
    assert 100.0 <= memory.peak_mb < before - 250.0


def test_peak_memory_sampled_where_the_mark_cannot_be_reset(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def refuse() -> None:
        raise OSError("read-only /proc")

    monkeypatch.setattr(PeakMemory, "_reset", staticmethod(refuse))
    with PeakMemory(interval_s=0.005) as memory:
        block = np.ones(100 * 2**20 // 8)
        time.sleep(0.05)  # several samples while the block is resident
        del block
    assert memory.method == "sampled"
    assert memory.peak_mb >= 100.0


def test_bracket_mc_cell_is_the_monte_carlo_run(tmp_path: Path) -> None:
    from satpose.tools.bracket_montecarlo import MonteCarloConfig, result_from_json, run_config

    spec = load_spec(
        _write(
            tmp_path,
            "base: {pipeline: bracket-mc, seed: 1003}\n"
            "axes: {config: {coarse: {dt_s: 1.0, ant_iterations: 2, smooth: true}}}\n",
        )
    )
    (cell,) = spec.cells
    row = _one_row(tmp_path, run_cell(cell, None, str(tmp_path), 300.0))
    assert row["status"] == "ok", row["error"]
    assert row["mc.dt_s"] == 1.0 and row["mc.ant_iterations"] == 2 and row["mc.smooth"]
    got = result_from_json(row["mc.result"])
    # The same seed run here: the same simulated points, so the same errors (NaN where a
    # method gave no pose), bit for bit.
    direct = run_config(MonteCarloConfig(dt_s=1.0, ant_iterations=2, smooth=True), 1003)
    assert set(got.err) == set(direct.err) >= {"ours per frame", "ours + offline smoother"}
    for method in direct.err:
        np.testing.assert_array_equal(got.err[method], direct.err[method])
    np.testing.assert_array_equal(got.nees, direct.nees)
    assert got.candidates == direct.candidates and got.fails == direct.fails
    assert len(got.t_s) == 21  # 20 s at 1 s
    # 1 px noise, 10 mm vertex error: one run's RMS stays below the worst single frame of
    # 100 runs in docs/results/bracket.md (669.7 mm, 31.93 deg; the RMS over them is 91 mm).
    assert 0 < row["mc.ours_pos_rms_mm"] < 670.0 and row["mc.ours_rot_rms_deg"] < 32.0


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("base: {pipeline: bracket-mc}\n", "seed"),
        ("base: {pipeline: bracket-mc, seed: 1, scenario: paper-docking}\n", "scenario"),
        ("base: {pipeline: bracket-mc, seed: 1, config: {sigma: 1}}\n", "sigma"),
    ],
)
def test_bracket_mc_spec_errors(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        load_spec(_write(tmp_path, text))


def test_a_list_of_axes_is_the_union_of_products(tmp_path: Path) -> None:
    spec = load_spec(
        _write(
            tmp_path,
            "base: {pipeline: bracket-mc}\n"
            "axes:\n"
            "- {seed: [1, 2, 3], config: {a: {}, b: {sigma_px: 0.5}}}\n"
            "- {seed: [1], config: {slow: {ant_iterations: 40}}}\n",
        )
    )
    assert [(c.axes["seed"], c.axes["config"]) for c in spec.cells] == [
        (1, "a"), (1, "b"), (2, "a"), (2, "b"), (3, "a"), (3, "b"), (1, "slow")
    ]  # fmt: skip
    with pytest.raises(ConfigError, match="repeat"):
        load_spec(
            _write(tmp_path, "base: {pipeline: bracket-mc}\naxes: [{seed: [1]}, {seed: [1]}]\n")
        )
    with pytest.raises(ConfigError, match=r"axes\[1\]\.colour"):
        load_spec(
            _write(tmp_path, "base: {pipeline: bracket-mc}\naxes: [{seed: [1]}, {colour: [2]}]\n")
        )
