"""Renderer: truth lands on the rendered features (sub-pixel), determinism, kinematics, looks.

Tolerances: the truth checks render noise-free emissive geometry with many samples per pixel,
so centroids are exact up to sampling noise (~0.02 px); the requirement is 0.1 px.
"""

from __future__ import annotations

import filecmp
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.render_check import geometry_errors, marker_errors
from satpose.datasets.scenarios import RigConfig, Scenario, preset, scaled, trajectory
from satpose.datasets.sequence import load_sequence
from satpose.datasets.target import MASK_IDS, geometry
from satpose.tools.cli import main

pytestmark = pytest.mark.render

SUBPIXEL_TOL_PX = 0.1  # the brief's requirement for projected truth vs rendered features
TRUTH_SPP = 256  # emissive-only scenes: cheap; sampling noise ~0.02 px at this count


def _small(name: str) -> Scenario:
    return scaled(preset(name), size=(320, 256), spp=TRUTH_SPP)


def _pose_at_4m(s: Scenario) -> Rigid3:
    return trajectory(scaled(s, frames=61)).left_cam_from_target[60]


@pytest.mark.parametrize("resampling", ["linear", "area"])
def test_truth_projects_onto_rendered_markers(resampling: str) -> None:
    """Ring centre, ring rim, panel corners and components, projected with calib + truth
    (distortion on, both cameras), land on emissive markers rendered at those points; with
    the canvas resampled once per pixel (``linear``) and over 3 x 3 sub-pixels per pixel of
    a 3x finer canvas (``area``, whose sub-pixel geometry this checks)."""
    s = _small("paper-docking")
    s = replace(s, render=replace(s.render, resampling=resampling))
    errors = marker_errors(s, _pose_at_4m(s), spp=TRUTH_SPP)
    assert set(errors) == {"left", "right"}
    for cam, groups in errors.items():
        for group, err in groups.items():
            assert err.max() < SUBPIXEL_TOL_PX, f"{cam} {group}: {np.round(err, 3)} px"


def test_rendered_ring_and_panel_match_target_geometry() -> None:
    """The rendered ring front face (outer edge = target.yaml's ring) and panel front face
    (corners = target.yaml's panel_corners) have the area, centroid and second moments of
    their analytic projections."""
    s = _small("paper-docking")
    for cam, parts in geometry_errors(s, _pose_at_4m(s), spp=TRUTH_SPP).items():
        for part, e in parts.items():
            assert e.centroid_px < SUBPIXEL_TOL_PX / 2, f"{cam} {part}: {e}"
            assert e.area_rel < 2e-3, f"{cam} {part}: {e}"
            assert e.axes_px.max() < 0.05, f"{cam} {part}: {e}"


def test_geometry_check_detects_a_wrong_ring() -> None:
    """The check can fail: a target.yaml whose ring is 2 % too large is caught."""
    s = _small("paper-docking")
    g = geometry(s.target)
    wrong = replace(g, ring=replace(g.ring, radius_m=g.ring.radius_m * 1.02))
    errors = geometry_errors(s, _pose_at_4m(s), spp=64, truth=wrong)
    assert errors["left"]["ring"].area_rel > 0.02


def test_render_is_deterministic(rendered_tiny: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    assert (
        main(
            [
                "render",
                "paper-docking",
                "--out",
                str(again),
                "--frames",
                "3",
                "--size",
                "320x256",
                "--spp",
                "4",
            ]
        )
        == 0
    )
    for sub in ("left", "right", "masks/left", "masks/right"):
        names = sorted(p.name for p in (rendered_tiny / sub).iterdir())
        _match, mismatch, errors = filecmp.cmpfiles(
            rendered_tiny / sub, again / sub, names, shallow=False
        )
        assert not mismatch and not errors, f"{sub}: {mismatch} {errors}"
    assert filecmp.cmp(rendered_tiny / "groundtruth.csv", again / "groundtruth.csv", shallow=False)
    other = tmp_path / "seed1"
    assert (
        main(
            [
                "render",
                "paper-docking",
                "--out",
                str(other),
                "--frames",
                "1",
                "--size",
                "320x256",
                "--spp",
                "4",
                "--seed",
                "1",
            ]
        )
        == 0
    )
    a = cv2.imread(str(rendered_tiny / "left/000000.png"))
    b = cv2.imread(str(other / "left/000000.png"))
    assert np.mean(a != b) > 0.05  # other textures and noise


def test_rendered_sequence_loads_and_shows_the_features(rendered_tiny: Path) -> None:
    seq = load_sequence(rendered_tiny)
    seq.verify()
    assert seq.kind == "stereo" and len(seq) == 3 and seq.has_masks
    assert seq.generator["tool"] == "satpose-render"
    assert seq.target is not None and seq.target.panel_corners.shape == (4, 3)
    cam = seq.calibration.left
    for i, fr in enumerate(seq):
        img = cv2.cvtColor(fr.left(), cv2.COLOR_BGR2GRAY).astype(float)
        mask = fr.mask("left")
        # The features the frontend needs are there and distinct: a bright ring, dark
        # components on the panel, the four panel corners inside the image.
        panel = img[mask == MASK_IDS["panel"]].mean()
        assert img[mask == MASK_IDS["components"]].mean() < 0.4 * panel
        assert img[mask == MASK_IDS["ring"]].mean() > 0.8 * panel
        # Black space (read noise only) away from the target's edge pixels.
        near_target = cv2.dilate((mask > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert np.all(img[~near_target] < 8)
        corners = cam.project(seq.truth.pose(i).apply(seq.target.panel_corners))
        assert np.all((corners > 0) & (corners < [cam.width - 1, cam.height - 1]))
        # The ring mask sits where the truth says the ring is.
        centre = cam.project(seq.truth.pose(i).apply(np.zeros((1, 3))))[0]
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        rim = cam.project(
            seq.truth.pose(i).apply(np.c_[0.28 * np.cos(a), 0.28 * np.sin(a), np.zeros(16)])
        )  # mid ring face
        assert np.all(
            mask[np.rint(rim[:, 1]).astype(int), np.rint(rim[:, 0]).astype(int)] == MASK_IDS["ring"]
        )
        assert mask[round(centre[1]), round(centre[0])] == MASK_IDS["panel"]


def _finite_difference_velocities(seq):  # type: ignore[no-untyped-def]
    truth = seq.truth
    R, t, ts = truth.rotations(), truth.translation, truth.t_s
    w_fd, v_fd = [], []
    for k in range(1, len(ts) - 1):
        dt = ts[k + 1] - ts[k - 1]
        w_fd.append(matrix_to_rotvec(R[k - 1].T @ R[k + 1]) / dt)  # body rate, constant
        v_fd.append((t[k + 1] - t[k - 1]) / dt)
    return np.array(w_fd), np.array(v_fd), slice(1, len(ts) - 1)


def test_truth_velocities_match_finite_differences(rendered_tiny: Path, tmp_path: Path) -> None:
    # paper-docking spins about the ring axis through its centre of mass: the ring centre
    # moves linearly, so central differences are exact even at 5 s per frame.
    seq = load_sequence(rendered_tiny)
    w_fd, v_fd, rows = _finite_difference_velocities(seq)
    np.testing.assert_allclose(w_fd, seq.truth.angular_velocity[rows], atol=1e-12)
    np.testing.assert_allclose(v_fd, seq.truth.linear_velocity[rows], atol=1e-12)
    np.testing.assert_allclose(np.degrees(seq.truth.angular_velocity[:, 2]) / seq.rate_hz, 10.0)

    # tumble rotates about the bus centroid, off the ring: the ring centre's velocity changes.
    # Rendered (mono, tiny) at 20 Hz, central differences agree to O(|w|^2 r dt^2) ~ 1e-7.
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("rate_hz: 20.0\nrig: {stereo: false}\nrender: {masks: false}\n")
    out = tmp_path / "tumble"
    assert (
        main(
            [
                "render",
                "tumble",
                "--out",
                str(out),
                "--frames",
                "5",
                "--size",
                "64x48",
                "--spp",
                "1",
                "--config",
                str(cfg),
            ]
        )
        == 0
    )
    seq = load_sequence(out)
    assert seq.kind == "mono" and not seq.has_masks
    w_fd, v_fd, rows = _finite_difference_velocities(seq)
    np.testing.assert_allclose(w_fd, seq.truth.angular_velocity[rows], atol=1e-12)
    np.testing.assert_allclose(v_fd, seq.truth.linear_velocity[rows], atol=1e-6)
    assert np.ptp(seq.truth.linear_velocity[:, 0]) > 1e-5  # really not constant


def test_renderer_needs_square_pixels() -> None:
    from satpose.datasets.render import make_view
    from satpose.datasets.scene import RenderError

    cam = RigConfig().calibration().left
    K = cam.K.copy()
    K[1, 1] *= 1.01
    with pytest.raises(RenderError, match="square pixels"):
        make_view("left", replace(cam, K=K), Rigid3.identity())


@pytest.mark.parametrize("k1", [-0.1, 0.024])
def test_lens_distortion_round_trip_keeps_positions(k1: float) -> None:
    """The renderer's distortion (canvas sampled at each output pixel's undistorted position,
    `distort`) followed by the frontend's undistortion (`Undistorter`) puts small blobs back
    where the pinhole canvas had them: centroids within 0.02 px (measured up to 0.009 px,
    with the 8-bit image and the 1/32 px fixed-point maps) for barrel and pincushion lenses.
    The round trip only blurs; it moves nothing."""
    from satpose.datasets.render import distort, make_view
    from satpose.frontend.preprocess import Undistorter

    cam = RigConfig(dist_left=(k1, 0.03, -1.6e-4, 4e-5, 0.0)).calibration().left
    view = make_view("left", cam, Rigid3.identity())
    canvas = view.canvas
    blobs = [(512.3, 384.7), (200.2, 150.9), (800.6, 600.4), (130.5, 650.3)]  # output px
    yy, xx = np.mgrid[0 : canvas.height, 0 : canvas.width].astype(float)
    img = np.zeros((canvas.height, canvas.width))
    for bx, by in blobs:  # the same point in the canvas: same focal length, its own centre
        cx = bx - cam.K[0, 2] + canvas.K[0, 2]
        cy = by - cam.K[1, 2] + canvas.K[1, 2]
        img += np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 1.5**2))
    out = distort(view, img)
    und = Undistorter(cam)(np.clip(out * 255, 0, 255).astype(np.uint8)).gray.astype(float)
    for bx, by in blobs:
        r0, c0 = round(by), round(bx)
        win = und[r0 - 6 : r0 + 7, c0 - 6 : c0 + 7]
        ys, xs = np.mgrid[r0 - 6 : r0 + 7, c0 - 6 : c0 + 7]
        got = np.array([(win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()])
        assert np.abs(got - [bx, by]).max() < 0.02, (bx, by, got)


@pytest.mark.parametrize("supersample", [1, 3])
def test_precomputed_resampling_equals_map_coordinates(supersample: int) -> None:
    """`distort`'s precomputed bilinear operator and nearest indices give what scipy's
    `map_coordinates` gives on the same map (bilinear at every sub-pixel, mean over the
    sub-pixels; ids at the centre sub-pixel), to float rounding, ids exactly. A canvas
    with values outside the map's reach checks the constant (0) border too."""
    from scipy import ndimage

    from satpose.datasets.render import distort, make_view

    cam = RigConfig(dist_left=(-0.12, 0.03, -1.6e-4, 4e-5, 0.0)).calibration().left
    cam = cam.scaled(64, 48)
    view = make_view("left", cam, Rigid3.identity(), supersample)
    assert view.sample_rc is not None
    rng = np.random.default_rng(3)
    img = rng.random((view.canvas.height, view.canvas.width, 3)).astype(np.float32)
    ref = np.stack(
        [
            ndimage.map_coordinates(img[..., c], view.sample_rc, order=1, mode="constant")
            for c in range(3)
        ],
        axis=-1,
    )
    s = supersample
    ref = ref.astype(np.float64).reshape(48, s, 64, s, 3).mean(axis=(1, 3))
    assert np.abs(distort(view, img) - ref).max() < 1e-6
    ids = rng.integers(0, 7, size=img.shape[:2]).astype(np.float32)
    centre = view.sample_rc[:, s // 2 :: s, s // 2 :: s]
    ref_ids = ndimage.map_coordinates(ids, centre, order=0, mode="constant")
    assert np.array_equal(distort(view, ids, nearest=True), ref_ids)
    # a sample map that reaches past the canvas: those neighbours count as 0
    shifted = replace(view, sample_rc=view.sample_rc - 2.0)
    ref_edge = ndimage.map_coordinates(img[..., 0], shifted.sample_rc, order=1, mode="constant")
    ref_edge = ref_edge.astype(np.float64).reshape(48, s, 64, s).mean(axis=(1, 3))
    assert np.abs(distort(shifted, img[..., 0]) - ref_edge).max() < 1e-6
