"""`satpose run`, `eval` and `report` end to end on a small rendered sequence."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from rerun.chunk import RrdReader

from satpose.datasets.config import load_config
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import load_sequence
from satpose.tools.cli import main
from satpose.tools.evaluate import ate_rmse
from satpose.tools.files import read_tum, write_tum
from satpose.tools.pipeline import (
    TRAJECTORY_COLUMNS,
    PipelineConfig,
    read_estimate_npz,
    run_pipeline,
)
from satpose.tools.recording import CAMERA, PLOTS, TARGET_ESTIMATE, TARGET_TRUTH, TRAJECTORY

DETERMINISTIC = [
    "trajectory.csv",
    "trajectory.tum",
    "trajectory_smoothed.csv",
    "trajectory_smoothed.tum",
    "estimate.npz",
    "estimate_smoothed.npz",
    "estimate_offline.npz",
    "estimate_kalman.npz",
    "frontend_pose.tum",
    "measurements.parquet",
    "config.yaml",
]
"""Every output except the wall-clock ones (timings.csv, run.rrd) and provenance (run.yaml)."""


@pytest.fixture(scope="module")
def runs(docking_small: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same `satpose run` twice (online, comparing all estimators)."""
    base = tmp_path_factory.mktemp("runs")
    for name in ("a", "b"):
        assert main(["run", str(docking_small), "--out", str(base / name)]) == 0
    return base / "a", base / "b"


def _temporal_rows(path: Path) -> dict[str, int]:
    """Rows per entity on the timelines (static rows left out), read with the Rerun SDK."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(str(path)).store().stream():
        if not chunk.is_static:
            key = chunk.entity_path.lstrip("/")
            rows[key] = rows.get(key, 0) + chunk.num_rows
    return rows


def _static_entities(path: Path) -> set[str]:
    return {c.entity_path.lstrip("/") for c in RrdReader(str(path)).store().stream() if c.is_static}


def test_run_writes_its_files(runs: tuple[Path, Path], docking_small: Path) -> None:
    run, _ = runs
    n = len(load_sequence(docking_small))
    df = pd.read_csv(run / "trajectory.csv")
    assert list(df.columns) == TRAJECTORY_COLUMNS
    assert df["frame"].tolist() == list(range(n))
    assert np.isfinite(df.to_numpy()).all()
    assert (df.filter(like="sigma_") > 0).all().all()
    t, poses = read_tum(run / "trajectory.tum")
    np.testing.assert_allclose(t, df["t_s"], atol=1e-9)
    np.testing.assert_allclose([p.t for p in poses], df[["tx", "ty", "tz"]], atol=1e-9)
    timings = pd.read_csv(run / "timings.csv")
    assert len(timings) == n
    assert {"frontend_total", "backend_online", "backend_offline", "backend_kalman"} <= set(
        timings.columns
    )
    assert any(c.startswith("frontend_ring") for c in timings.columns)
    assert load_config(PipelineConfig, run / "config.yaml") == PipelineConfig()
    prov = yaml.safe_load((run / "run.yaml").read_text())
    # every frame but the first: the frontend fixes its target frame at the ring's second sighting
    assert prov["estimator"] == "online" and prov["frames_with_pose"] == n - 1
    assert not [p.name for p in run.parent.iterdir() if p.name.startswith(".")]


def test_same_inputs_give_identical_outputs(runs: tuple[Path, Path]) -> None:
    a, b = runs
    for name in DETERMINISTIC:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_recording_reads_back_with_entities_and_rows(
    runs: tuple[Path, Path], docking_small: Path
) -> None:
    n = len(load_sequence(docking_small))
    rows = _temporal_rows(runs[0] / "run.rrd")
    per_frame = [
        f"{CAMERA['left']}/image",
        f"{CAMERA['right']}/image",
        f"{CAMERA['left']}/ring",
        f"{CAMERA['right']}/ring",
        f"{CAMERA['left']}/ring_estimate",
        f"{CAMERA['left']}/landmarks/corner",
        TARGET_ESTIMATE,
        f"{TARGET_ESTIMATE}/axes",
        TARGET_TRUTH,
        "world/covariance",
        f"{PLOTS}/error/position_cm/isam2",
        f"{PLOTS}/spin/truth",
        f"{PLOTS}/timing_ms/backend_online",
    ]
    for entity in per_frame:
        assert rows.get(entity) == n, (entity, rows.get(entity))
    # the Kalman filter starts on the frontend's first pose (at the ring's second sighting)
    kalman = f"{PLOTS}/error/position_cm/kalman"
    assert rows.get(kalman) == n - 1, rows.get(kalman)
    # a line from the second frame on; from the third for the frontend's poses and the Kalman
    # filter, which start at the ring's second sighting
    for name, first in (("truth", 1), ("isam2", 1), ("per_frame", 2), ("kalman", 2)):
        line = rows.get(f"{TRAJECTORY}/{name}")
        assert line == n - first, (name, line)
    # the smoothed estimates are known at the end: a series over all frames, a static line
    assert rows[f"{PLOTS}/error/position_cm/smoothed"] == n
    assert rows[f"{PLOTS}/error/position_cm/isam2_smoothed"] == n
    static = _static_entities(runs[0] / "run.rrd")
    assert {CAMERA["left"], CAMERA["right"], f"{TRAJECTORY}/smoothed"} <= static


def test_eval_table_metrics_and_files(
    runs: tuple[Path, Path], docking_small: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = runs[0]
    assert main(["eval", str(docking_small), str(run)]) == 0
    text = capsys.readouterr().out
    assert "| online filtered |" in text and "| kalman |" in text and "5-3 m" in text
    metrics = json.loads((run / "metrics.json").read_text())
    assert set(metrics) >= {"online filtered", "online smoothed", "offline", "kalman"}
    # 6 frames at 4.5 m, 640x480: the frontend alone is within 1.5 cm per frame
    for name in ("online smoothed", "offline", "per-frame (frontend)"):
        assert metrics[name]["pos_cm"] < 1.5, (name, metrics[name])
        assert metrics[name]["rot_deg"] < 1.0, (name, metrics[name])
    per_frame = pd.read_csv(run / "metrics.csv")
    assert set(per_frame["trajectory"]) == set(metrics)
    assert (per_frame["range_m"].between(4.0, 5.0)).all()


def _evo_ape_rmse(gt: Path, est: Path, *extra: str) -> float:
    """The rmse of ``evo_ape tum GT EST [extra]`` at full precision (its saved results)."""
    evo = Path(sys.executable).parent / "evo_ape"
    if not evo.exists():
        pytest.fail(f"{evo} missing: evo is a test dependency (pip install -e .[test])")
    res = est.with_name(f"{est.stem}-evo{''.join(extra)}.zip")
    res.unlink(missing_ok=True)
    cmd = [str(evo), "tum", str(gt), str(est), *extra, "--save_results", str(res)]
    subprocess.run(cmd, capture_output=True, text=True, check=True)
    with zipfile.ZipFile(res) as zf:
        return float(json.loads(zf.read("stats.json"))["rmse"])


def test_ate_equals_evo_ape(runs: tuple[Path, Path], docking_small: Path) -> None:
    run = runs[0]
    assert main(["eval", str(docking_small), str(run)]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    # TUM files hold 9 decimals; evo prints 6 significant digits
    for name, file in (
        ("online filtered", "trajectory.tum"),
        ("per-frame (frontend)", "frontend_pose.tum"),
    ):
        evo = _evo_ape_rmse(run / "groundtruth.tum", run / file)
        assert metrics[name]["ate_m"] == pytest.approx(evo, rel=1e-6), name
        # a straight-line approach: evo refuses the -a alignment, so do we
        assert metrics[name]["ate_aligned_m"] is None


def test_aligned_ate_equals_evo_ape_a(tmp_path: Path) -> None:
    """`evo_ape -a` on a curved trajectory with a rotated, shifted, noisy estimate."""
    rng = np.random.default_rng(3)
    k = np.arange(40)
    truth = [
        Rigid3.from_rotvec(0.1 * rng.normal(size=3), [np.sin(0.2 * i), np.cos(0.15 * i), 0.1 * i])
        for i in k
    ]
    G = Rigid3.from_rotvec([0.3, -0.2, 0.5], [1.0, 2.0, -0.5])
    est = [
        G @ T @ Rigid3.from_rotvec(0.01 * rng.normal(size=3), 0.02 * rng.normal(size=3))
        for T in truth
    ]
    write_tum(0.1 * k, truth, tmp_path / "gt.tum")
    write_tum(0.1 * k, est, tmp_path / "est.tum")
    _, est_back = read_tum(tmp_path / "est.tum")
    _, truth_back = read_tum(tmp_path / "gt.tum")
    ours = ate_rmse(est_back, truth_back, align=True)
    assert ours is not None and 0.01 < ours < 0.05
    assert ours == pytest.approx(
        _evo_ape_rmse(tmp_path / "gt.tum", tmp_path / "est.tum", "-a"), rel=1e-5
    )
    # collinear positions: no alignment, as in evo
    line = [Rigid3.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 3.0 + 0.1 * i]) for i in k]
    assert ate_rmse(line, line, align=True) is None


def test_report_writes_plots(runs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    import matplotlib.image

    run = runs[1]
    assert main(["report", str(run)]) == 0
    written = [Path(line.removeprefix("wrote ")) for line in capsys.readouterr().out.splitlines()]
    assert {p.name for p in written} >= {"range.png", "rotation.png", "errors.png", "timing.png"}
    for p in written:
        img = matplotlib.image.imread(p)
        assert img.shape[0] > 200 and img.shape[1] > 300 and img[..., :3].std() > 0.05, p


# -- bad input -------------------------------------------------------------------------------


def _one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    for w in words:
        assert w in err, (w, err)
    return err


def test_run_on_a_wrong_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "nope"), "--out", str(out)]) == 2
    _one_line_error(capsys, "nope")
    assert not out.exists()


def test_run_with_an_unknown_config_key(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("backend:\n  process_noise_typo: 1.0\n")
    out = tmp_path / "out"
    assert main(["run", str(docking_small), "--out", str(out), "--config", str(cfg)]) == 2
    _one_line_error(capsys, "c.yaml", "process_noise_typo")
    assert not out.exists()


def test_run_into_an_unwritable_place(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["run", str(docking_small), "--out", str(blocker / "out")]) == 2
    _one_line_error(capsys, "out", "cannot create")
    assert main(["run", str(docking_small), "--out", str(blocker)]) == 2
    _one_line_error(capsys, "not a folder")
    assert blocker.read_text() == "not a folder"


def test_existing_folders_are_kept(
    runs: tuple[Path, Path], docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    for extra in ([], ["--overwrite"]):
        assert main(["run", str(docking_small), "--out", str(mine), *extra]) == 2
        _one_line_error(capsys, "not a run folder")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    before = (runs[1] / "trajectory.csv").read_bytes()
    assert main(["run", str(docking_small), "--out", str(runs[1])]) == 2
    _one_line_error(capsys, "--overwrite")
    assert (runs[1] / "trajectory.csv").read_bytes() == before


def test_interrupted_run_leaves_nothing(docking_small: Path, tmp_path: Path) -> None:
    def stop(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(docking_small, "offline", out, progress=stop)
    assert list(tmp_path.iterdir()) == []


def test_without_ground_truth_run_works_and_eval_says_so(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = tmp_path / "real"
    shutil.copytree(docking_small, seq)
    (seq / "groundtruth.csv").unlink()
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("compare: false\nrecording:\n  images: false\n")
    run = tmp_path / "run"
    assert (
        main(["run", str(seq), "--estimator", "kalman", "--out", str(run), "--config", str(cfg)])
        == 0
    )
    est = read_estimate_npz(run / "estimate.npz")
    assert len(est) == len(load_sequence(seq))
    assert not (run / "estimate_offline.npz").exists()
    capsys.readouterr()
    assert main(["eval", str(seq), str(run)]) == 2
    _one_line_error(capsys, "groundtruth.csv")
    assert not (run / "metrics.json").exists()
    assert main(["report", str(run)]) == 0  # plots without truth
