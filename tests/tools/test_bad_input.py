"""Bad input to whole commands: garbage frames and a failing stage degrade the run (exit 0,
a trajectory for every frame, a warning per bad file, a summary by reason); bad files around
the frames stay one-line errors that say where."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from satpose.datasets.sequence import load_sequence
from satpose.frontend import pipeline as frontend_pipeline
from satpose.frontend.pipeline import StereoFrontend
from satpose.tools.cli import main

pytestmark = pytest.mark.render

DIVERGING_FRAME = 5


def _garbage_copy(src: Path, dst: Path) -> dict[int, str]:
    """A copy of ``src`` with bad images in frames 1-4; the file each bad frame names."""
    shutil.copytree(src, dst)
    seq = load_sequence(dst)
    h, w = seq.calibration.left.height, seq.calibration.left.width
    (dst / "left" / "000001.png").write_bytes(b"")  # zero bytes
    for cam in ("left", "right"):  # all black
        cv2.imwrite(str(dst / cam / "000002.png"), np.zeros((h, w, 3), np.uint8))
    cv2.imwrite(str(dst / "right" / "000003.png"), np.full((h // 2, w // 2, 3), 90, np.uint8))
    rng = np.random.default_rng(0)
    for cam in ("left", "right"):  # noise: no ring, no pose, but nothing wrong with the file
        cv2.imwrite(str(dst / cam / "000004.png"), rng.integers(0, 256, (h, w, 3), np.uint8))
    return {1: "left/000001.png", 2: "left/000002.png", 3: "right/000003.png"}


def _diverge_at(monkeypatch: pytest.MonkeyPatch, frame: int) -> None:
    """The refinement of the ring circle raises OverflowError in ``frame`` (as it did on a
    tumbling render before it was bounded): an unexpected exception inside a stage."""
    current = {"frame": -1}
    process = StereoFrontend.process  # every driver's way in (run, frontend, track --live)
    refine_circle = frontend_pipeline.refine_circle

    def tracked(self: StereoFrontend, index, *args):  # type: ignore[no-untyped-def]
        current["frame"] = index
        return process(self, index, *args)

    def diverging(*args, **kwargs):  # type: ignore[no-untyped-def]
        if current["frame"] == frame:
            raise OverflowError("math range error")
        return refine_circle(*args, **kwargs)

    monkeypatch.setattr(StereoFrontend, "process", tracked)
    monkeypatch.setattr(frontend_pipeline, "refine_circle", diverging)


def _warnings_by_frame(caplog: pytest.LogCaptureFixture) -> dict[int, list[str]]:
    out: dict[int, list[str]] = {}
    for r in caplog.records:
        msg = r.getMessage()
        if r.levelno == logging.WARNING and msg.startswith("frame "):
            out.setdefault(int(msg.split()[1]), []).append(msg)
    return out


def test_run_survives_garbage_frames_and_a_failing_stage(
    docking_small: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    seq = tmp_path / "seq"
    files = _garbage_copy(docking_small, seq)
    _diverge_at(monkeypatch, DIVERGING_FRAME)
    out = tmp_path / "run"
    with caplog.at_level(logging.WARNING):
        assert main(["run", str(seq), "--out", str(out)]) == 0
    n = len(load_sequence(seq))
    # every frame has a trajectory row (the estimators predict through the bad ones)
    traj = pd.read_csv(out / "trajectory.csv")
    assert traj["frame"].tolist() == list(range(n))
    assert np.all(np.isfinite(traj[["tx", "ty", "tz", "qx", "qy", "qz", "qw"]].to_numpy()))
    # one warning per bad frame, naming its file and the reason
    warned = _warnings_by_frame(caplog)
    assert sorted(warned) == [1, 2, 3, DIVERGING_FRAME]
    assert all(len(v) == 1 for v in warned.values())
    for frame, reason in (
        (1, "not a readable PNG"),
        (2, "too dark"),
        (3, "calib.yaml says"),
        (DIVERGING_FRAME, "ring: internal error: OverflowError: math range error"),
    ):
        assert reason in warned[frame][0]
    for frame, name in files.items():
        assert name in warned[frame][0]
    assert f"left/{DIVERGING_FRAME:06d}.png" in warned[DIVERGING_FRAME][0]
    # the summary counts them by reason; run.yaml keeps the counts
    summary = capsys.readouterr().out
    assert f"4 bad frames (of {n}):" in summary
    for reason in ("unreadable image 1", "black image 1", "wrong image size 1"):
        assert reason in summary
    assert "internal error in ring 1" in summary
    prov = yaml.safe_load((out / "run.yaml").read_text())
    assert prov["bad_frames"] == 4
    assert "np.float" not in (out / "run.yaml").read_text()


def test_frontend_refuses_an_existing_folder_and_leaves_nothing_when_interrupted(
    docking_small: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "fe"
    assert main(["frontend", str(docking_small), "--out", str(out)]) == 0
    before = (out / "measurements.parquet").read_bytes()
    capsys.readouterr()
    assert main(["frontend", str(docking_small), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "already exists" in err and "--overwrite" in err
    assert (out / "measurements.parquet").read_bytes() == before
    # not one of ours: never replaced
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    assert main(["frontend", str(docking_small), "--out", str(other), "--overwrite"]) == 2
    assert "not a frontend folder" in capsys.readouterr().err
    # interrupted: the old folder stays as it was, no staging folder is left behind
    process_frame = StereoFrontend.process_frame

    def interrupted(self: StereoFrontend, fr):  # type: ignore[no-untyped-def]
        if fr.index == 2:
            raise KeyboardInterrupt
        return process_frame(self, fr)

    monkeypatch.setattr(StereoFrontend, "process_frame", interrupted)
    assert main(["frontend", str(docking_small), "--out", str(out), "--overwrite"]) == 130
    assert main(["frontend", str(docking_small), "--out", str(tmp_path / "new")]) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fe", "other"]
    assert (out / "measurements.parquet").read_bytes() == before
    monkeypatch.setattr(StereoFrontend, "process_frame", process_frame)
    assert main(["frontend", str(docking_small), "--out", str(out), "--overwrite"]) == 0


def test_spin_names_an_unreadable_frame(
    rendered_spin: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    seq = tmp_path / "spin"
    shutil.copytree(rendered_spin, seq)
    (seq / "left" / "000005.png").write_bytes(b"")
    with caplog.at_level(logging.WARNING):
        assert main(["spin", str(seq), "--out", str(tmp_path / "o")]) == 0
    warned = _warnings_by_frame(caplog)
    assert list(warned) == [5] and "left/000005.png" in warned[5][0]
    angles = pd.read_csv(tmp_path / "o" / "spin_angles.csv")
    assert len(angles) == len(load_sequence(seq))
