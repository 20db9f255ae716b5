"""Stereo calibration check: OpenCV and pycolmap against the renderer's exact calibration.

Two tiers. Noise-free corners (projected with the true calibration) must give back the true
calibration to numerical precision with both methods. Rendered board images (640x480, 20
views, 4 spp; corner noise ~0.2 px RMS) give statistical errors, measured on this scene as:
focal <= 0.09 %, principal point <= 1.7 px, baseline <= 0.05 %, rig rotation <= 0.2 deg (the
principal-point error of the two cameras, 3 px apart, tilts the rig by that much); the
tolerances below are about twice that. The issue's targets (0.2 %, 1 px, 0.5 %) are for the
full-size preset: benchmarks/colmap_checks.py.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from satpose.datasets.board import BoardConfig, board_corners, board_poses, charuco_board
from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.scenarios import preset, scaled
from satpose.datasets.sequence import Calibration, load_sequence
from satpose.tools.calibcheck import (
    BoardView,
    CalibCheckConfig,
    CalibrationCheckError,
    board_from_target,
    calibrate_opencv,
    calibrate_pycolmap,
    camera_errors,
    compare_calibration,
    homography_focal,
    rig_errors,
)
from satpose.tools.cli import main

SIZE = (640, 480)  # the board_sequence fixture's (tests/conftest.py: BOARD_SIZE, BOARD_VIEWS)
VIEWS = 20


def _projected_views(
    calib: Calibration, board: BoardConfig, views: int, noise_px: float, seed: int
) -> dict[str, list[BoardView]]:
    """Board corners projected with the exact calibration at the preset's poses (inside the
    image with a 5 px margin), plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    corners = board_corners(board)
    out: dict[str, list[BoardView]] = {"left": [], "right": []}
    for k, pose in enumerate(board_poses(board, calib, views, seed)):
        for cam in out:
            camera = calib.camera(cam)  # type: ignore[arg-type]
            assert calib.right_from_left is not None
            T = pose if cam == "left" else calib.right_from_left @ pose
            uv = camera.project(T.apply(corners))
            inside = np.all((uv > 5) & (uv < np.array(camera.size) - 6), axis=1)
            ids = np.flatnonzero(inside)
            if ids.size >= 12:
                px = uv[ids] + rng.normal(0.0, noise_px, (ids.size, 2))
                out[cam].append(BoardView(frame=k, ids=ids, pixels=px))
    return out


def _true_calibration() -> Calibration:
    return scaled(preset("calibration"), size=SIZE).rig.calibration()


@pytest.mark.parametrize("method", [calibrate_opencv, calibrate_pycolmap])
def test_noise_free_corners_give_the_exact_calibration(method) -> None:  # type: ignore[no-untyped-def]
    """Tight tier: exact corners -> exact K, distortion and right_from_left (numerical
    precision of the solvers: 1e-6 relative focal, 1e-3 px, 1e-4 deg)."""
    calib, board = _true_calibration(), BoardConfig()
    views = _projected_views(calib, board, 12, 0.0, seed=1)
    sizes = {c: calib.camera(c).size for c in views}  # type: ignore[arg-type]
    fit = method(views, sizes, board, CalibCheckConfig())
    e = compare_calibration(fit.calibration, calib)
    for cam, ce in e.cameras.items():
        assert max(abs(x) for x in ce.focal_rel) < 1e-6, cam
        assert max(abs(x) for x in ce.principal_point_px) < 1e-3, cam
        assert ce.max_image_px < 1e-3, cam
    assert e.rig is not None
    assert abs(e.rig.baseline_rel) < 1e-6 and e.rig.rotation_deg < 1e-4
    assert max(fit.rms_px[c] for c in ("left", "right")) < 1e-4


def test_homography_focal_length() -> None:
    """With the principal point at the image centre and no distortion, Zhang's constraints
    give the focal length exactly (noise-free) and within 0.5 % with 0.3 px noise (the
    pycolmap path only needs a starting value)."""
    from satpose.datasets.camera import PinholeCamera

    w, h = SIZE
    cam = PinholeCamera(
        width=w, height=h, K=np.array([[900.0, 0, (w - 1) / 2], [0, 900.0, (h - 1) / 2], [0, 0, 1]])
    )
    calib = Calibration(
        left=cam, right=cam, right_from_left=Rigid3(R=np.eye(3), t=np.array([-0.3, 0.0, 0.0]))
    )
    board = BoardConfig()
    exact = _projected_views(calib, board, 10, 0.0, seed=2)["left"]
    noisy = _projected_views(calib, board, 10, 0.3, seed=2)["left"]
    assert homography_focal(exact, board, SIZE) == pytest.approx(900.0, rel=1e-9)
    assert homography_focal(noisy, board, SIZE) == pytest.approx(900.0, rel=5e-3)


def test_error_measures() -> None:
    """Known perturbations come out as such: focal x1.001, principal point +0.5 px, baseline
    x1.01 and a 0.1 deg rotation of the rig."""
    calib = _true_calibration()
    K = calib.left.K.copy()
    K[0, 0] *= 1.001
    K[0, 2] += 0.5
    from dataclasses import replace

    e = camera_errors(replace(calib.left, K=K), calib.left)
    assert e.focal_rel[0] == pytest.approx(1e-3) and e.focal_rel[1] == pytest.approx(0.0)
    assert e.principal_point_px == pytest.approx((0.5, 0.0))
    assert e.max_image_px > 0.5
    rfl = calib.right_from_left
    assert rfl is not None
    turned = Rigid3.from_rotvec(np.radians([0.0, 0.1, 0.0]), [0.0, 0.0, 0.0])
    r = rig_errors(Rigid3(R=turned.R @ rfl.R, t=1.01 * rfl.t), rfl)
    assert r.baseline_rel == pytest.approx(0.01)
    assert r.rotation_deg == pytest.approx(0.1)
    assert r.direction_deg == pytest.approx(0.0, abs=1e-9)


def test_too_few_views_is_an_error() -> None:
    calib, board = _true_calibration(), BoardConfig()
    views = _projected_views(calib, board, 3, 0.0, seed=3)
    sizes = {c: calib.camera(c).size for c in views}  # type: ignore[arg-type]
    with pytest.raises(CalibrationCheckError, match="at least 5 are needed"):
        calibrate_opencv(views, sizes, board, CalibCheckConfig())


def test_board_description_is_required() -> None:
    with pytest.raises(ConfigError, match=r"target\.yaml: no `board` mapping"):
        board_from_target({}, "seq/target.yaml")
    with pytest.raises(ConfigError, match="missing"):
        board_from_target({"board": {"squares_x": 5}}, "seq/target.yaml")


# --------------------------------------------------------------------------------------------
# Rendered board
# --------------------------------------------------------------------------------------------


@pytest.mark.render
def test_rendered_board_corners_land_on_the_truth(board_sequence: Path) -> None:
    """ChArUco corners detected in the rendered images against the truth (calib.yaml +
    groundtruth.csv + target.yaml's board) projected: no offset (mean < 0.05 px: the board
    frame, texture orientation and pixel conventions agree) and 4-spp noise (RMS < 0.3 px)."""
    seq = load_sequence(board_sequence)
    assert seq.truth is not None and seq.target is not None
    board = board_from_target(seq.target.extras, "target.yaml")
    corners = np.asarray(seq.target.extras["board_corners"])
    np.testing.assert_allclose(corners, board_corners(board))
    detector = cv2.aruco.CharucoDetector(charuco_board(board))
    assert seq.calibration.right_from_left is not None
    for cam in ("left", "right"):
        residuals = []
        for i, frame in enumerate(seq):
            grey = cv2.cvtColor(frame.image(cam), cv2.COLOR_BGR2GRAY)
            found, ids, _, _ = detector.detectBoard(grey)
            if ids is None:
                continue
            pose = seq.truth.pose(i)
            T = pose if cam == "left" else seq.calibration.right_from_left @ pose
            uv = seq.calibration.camera(cam).project(T.apply(corners[ids.ravel()]))  # type: ignore[arg-type]
            residuals.append(found.reshape(-1, 2) - uv)
        r = np.vstack(residuals)
        assert len(r) > 30 * VIEWS, cam
        assert np.all(np.abs(r.mean(axis=0)) < 0.05), (cam, r.mean(axis=0))
        assert np.sqrt(np.mean(np.sum(r**2, axis=1))) < 0.3, cam


@pytest.mark.render
def test_check_calib_writes_a_calibration_close_to_the_truth(
    board_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Statistical tier (see the module docstring): OpenCV and pycolmap both within focal
    0.2 %, principal point 3 px, baseline 0.2 %, rig rotation 0.4 deg of the truth, and within
    1.5 px of each other over the image; calib.yaml is a valid sequence calibration."""
    out = tmp_path / "check"
    assert main(["check-calib", str(board_sequence), "--out", str(out)]) == 0
    assert "targets" in capsys.readouterr().out
    report = yaml.safe_load((out / "calib_report.yaml").read_text())
    assert report["reference"] == "truth (rendered sequence)"
    truth = load_sequence(board_sequence).calibration
    for name in ("calib.yaml", "calib_pycolmap.yaml"):
        # The written calibration must load as part of a sequence.
        seq_copy = tmp_path / f"seq-{name}"
        shutil.copytree(board_sequence, seq_copy)
        shutil.copy(out / name, seq_copy / "calib.yaml")
        est = load_sequence(seq_copy).calibration
        e = compare_calibration(est, truth)
        for cam, ce in e.cameras.items():
            assert max(abs(x) for x in ce.focal_rel) < 2e-3, (name, cam, ce)
            assert max(abs(x) for x in ce.principal_point_px) < 3.0, (name, cam, ce)
        assert e.rig is not None
        assert abs(e.rig.baseline_rel) < 2e-3, (name, e.rig)
        assert e.rig.rotation_deg < 0.4, (name, e.rig)
    cross = report["pycolmap_minus_opencv"]
    assert max(cross[c]["max_image_px"] for c in ("left", "right")) < 1.5
    views = (out / "calib_views.csv").read_text().splitlines()
    assert len(views) > 2 * VIEWS


def test_check_calib_without_a_board_is_a_one_line_error(
    synthetic_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check-calib", str(synthetic_sequence), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "board" in err and "target.yaml" in err


@pytest.mark.render
def test_check_calib_refuses_an_existing_folder_and_replaces_its_own(
    board_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An existing non-empty folder is refused before any work (exit 2, one line); a
    check-calib folder is replaced with --overwrite, built aside and renamed (no staging
    folder left)."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    for extra in ([], ["--overwrite"]):  # never someone else's folder, even with --overwrite
        assert main(["check-calib", str(board_sequence), "--out", str(other), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "not a check-calib folder" in err
    assert sorted(p.name for p in other.iterdir()) == ["keep.txt"]
    out = tmp_path / "check"
    assert main(["check-calib", str(board_sequence), "--out", str(out)]) == 0
    assert main(["check-calib", str(board_sequence), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["check-calib", str(board_sequence), "--out", str(out), "--overwrite"]) == 0
    assert (out / "calib_report.yaml").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
