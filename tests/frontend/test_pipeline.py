"""The stereo frontend end to end on rendered images, and on bad images."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from satpose.datasets.sequence import Sequence, load_sequence
from satpose.frontend.conics import circle_to_conic, conic_to_ellipse
from satpose.frontend.measurements import FrameMeasurements, LandmarkKind
from satpose.frontend.pipeline import StereoFrontend
from satpose.tools.files import read_measurements, read_tum, write_measurements
from satpose.tools.metrics import pose_errors

pytestmark = pytest.mark.render


@pytest.fixture(scope="module")
def measured(docking_small: Path):  # type: ignore[no-untyped-def]
    seq = load_sequence(docking_small)
    fe = StereoFrontend(seq.calibration)
    return seq, [fe.process_frame(f) for f in seq]


def test_ring_found_on_its_outer_front_edge(measured) -> None:  # type: ignore[no-untyped-def]
    seq, results = measured
    for i, m in enumerate(results):
        assert m.ring is not None, m.failures
        for e in m.ring.ellipses:
            cam = seq.calibration.camera(e.camera.value)
            T = seq.truth.pose(i)
            T = T if e.camera.value == "left" else seq.calibration.right_from_left @ T
            true = conic_to_ellipse(circle_to_conic(cam.K, T, seq.target.ring.radius_m))
            # Sub-pixel edges on a small 8-spp render: the centre within 0.5 px, the axes
            # within 1 px (the inner edge is 4 px away here, the wall base ~1-2 px).
            assert np.linalg.norm(e.center_px - true.center) < 0.5
            assert np.abs(e.axes_px - [true.a, true.b]).max() < 1.0


def test_per_frame_pose_against_truth(measured) -> None:  # type: ignore[no-untyped-def]
    seq, results = measured
    # the target frame is fixed at the ring's second sighting (`PoseConfig.confirm_radius_gap`)
    assert results[0].pose is None and results[0].ring is not None
    assert any("second sighting" in f for f in results[0].failures)
    assert all(m.pose is not None for m in results[1:]), [m.failures for m in results]
    assert any(lm.kind == LandmarkKind.CORNER for lm in results[0].landmarks)
    est = [m.pose.left_cam_from_target for m in results[1:]]
    truth = [seq.truth.pose(i) for i in range(1, len(results))]
    err = pose_errors(est, truth)
    # At 4.5-4.25 m on 640x480 images: centimetre-level position, sub-degree rotation.
    assert err.position_m.max() < 0.03, err.position_m
    assert err.rotation_deg.max() < 1.5, err.rotation_deg
    ring_err = [
        np.linalg.norm(m.ring.center_m - seq.truth.pose(i).t) for i, m in enumerate(results)
    ]
    assert max(ring_err) < 0.03


def test_measurements_round_trip_through_parquet(measured, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, results = measured
    path = write_measurements(results, tmp_path / "m.parquet")
    back = read_measurements(path)
    assert len(back) == len(results)
    for a, b in zip(results, back, strict=True):
        assert (a.frame, a.t_s, a.failures) == (b.frame, b.t_s, b.failures)
        np.testing.assert_allclose(a.ring.center_m, b.ring.center_m)
        np.testing.assert_allclose(a.ring.covariance, b.ring.covariance)
        np.testing.assert_allclose(
            a.ring.ellipses[1].edge_points_px, b.ring.ellipses[1].edge_points_px
        )
        assert [lm.track_id for lm in a.landmarks] == [lm.track_id for lm in b.landmarks]
        assert (a.pose is None) == (b.pose is None)
        if a.pose is None:  # the first frame: the target frame waits for a second sighting
            continue
        np.testing.assert_allclose(
            a.pose.left_cam_from_target.matrix(), b.pose.left_cam_from_target.matrix(), atol=1e-12
        )
        assert a.pose.method == b.pose.method
    assert set(pd.read_parquet(path)["item"]) >= {"frame", "ring", "ellipse", "landmark", "pose"}


def test_black_and_saturated_frames_degrade_without_exceptions(docking_small: Path) -> None:
    seq = load_sequence(docking_small)
    fe = StereoFrontend(seq.calibration)
    fe.process_frame(seq[0])  # the ring's first sighting: the target frame is fixed at the next
    ok = fe.process_frame(seq[1])
    assert ok.pose is not None
    h, w = seq.calibration.left.height, seq.calibration.left.width
    black = fe.process(2, seq[2].t_s, np.zeros((h, w, 3), np.uint8), np.zeros((h, w, 3), np.uint8))
    assert black.ring is None and black.pose is None
    assert any("too dark" in f for f in black.failures)
    white = np.full((h, w, 3), 255, np.uint8)
    sat = fe.process(3, seq[3].t_s, white, white)
    assert sat.ring is None and any("saturated" in f for f in sat.failures)
    # Good images again: the frontend re-acquires the ring and keeps the target frame.
    again = fe.process_frame(seq[4])
    assert again.ring is not None and again.pose is not None
    first = ok.pose.left_cam_from_target
    np.testing.assert_allclose(
        again.pose.left_cam_from_target.R @ first.R.T,
        seq.truth.pose(4).R @ seq.truth.pose(1).R.T,
        atol=0.03,
    )


def test_ring_half_out_of_view_degrades(docking_small: Path) -> None:
    seq = load_sequence(docking_small)
    fe = StereoFrontend(seq.calibration)
    left, right = seq[0].left(), seq[0].right()
    true = conic_to_ellipse(circle_to_conic(seq.calibration.left.K, seq.truth.pose(0), 0.3))
    shift = int(true.cx)  # move the ring's centre onto the left image border
    cut_l = np.zeros_like(left)
    cut_l[:, : left.shape[1] - shift] = left[:, shift:]
    cut_r = np.zeros_like(right)
    cut_r[:, : right.shape[1] - shift] = right[:, shift:]
    m = fe.process(0, 0.0, cut_l, cut_r)  # must not raise
    assert m.pose is None or m.ring is not None
    assert isinstance(m.failures, tuple)


def test_unreadable_image_is_a_failure_not_an_exception(
    docking_small: Path, tmp_path: Path
) -> None:
    copy = tmp_path / "seq"
    shutil.copytree(docking_small, copy)
    (copy / "left" / "000002.png").write_bytes(b"garbage")
    seq = load_sequence(copy)
    fe = StereoFrontend(seq.calibration)
    results = [fe.process_frame(f) for f in seq]
    assert results[2].ring is None and any("not a readable PNG" in f for f in results[2].failures)
    assert results[3].pose is not None


def test_an_exception_inside_a_stage_ends_only_that_frame(
    docking_small: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bug in one stage (here: the panel stage raising) is that frame's failure, naming
    the stage and the exception; the next frame is measured normally, in the same target
    frame."""
    seq = load_sequence(docking_small)
    fe = StereoFrontend(seq.calibration)
    fe.process_frame(seq[0])  # the target frame is fixed at the ring's second sighting
    first = fe.process_frame(seq[1]).pose
    assert first is not None
    real = fe._panel

    def broken(*args: object, **kwargs: object) -> object:
        raise RuntimeError("boom")

    monkeypatch.setattr(fe, "_panel", broken)
    bad = fe.process_frame(seq[2])
    assert bad.pose is None and bad.ring is None
    assert bad.failures == ("panel: internal error: RuntimeError: boom",)
    monkeypatch.setattr(fe, "_panel", real)
    again = fe.process_frame(seq[3])
    assert again.ring is not None and again.pose is not None, again.failures
    # ... in the same target frame: the prediction from the last pose tells the panel
    # corners' half turns apart when they are re-identified
    assert seq.truth is not None
    np.testing.assert_allclose(
        again.pose.left_cam_from_target.R @ first.left_cam_from_target.R.T,
        seq.truth.pose(3).R @ seq.truth.pose(1).R.T,
        atol=0.03,
    )


def test_orb_without_a_circle_looks_over_the_whole_target(
    docking_small: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """When the two ring ellipses give no stereo circle, one of them may lie anywhere: ORB
    must not take its features around the two ellipses (their masks then cover different
    parts of the target and no stereo pair survives) but over the whole lit target. Here
    the right ellipse is replaced by a half-size one 300 px away and the circles dropped:
    ORB still pairs at least half as many features as with the true ellipses (measured 243
    of 255; with the masks around the two ellipses it paired 0)."""
    from satpose.frontend.orb import ORB_FIRST_ID, OrbConfig
    from satpose.frontend.pipeline import FrontendConfig

    seq = load_sequence(docking_small)
    counts = {}
    for case in ("true", "moved"):
        fe = StereoFrontend(seq.calibration, FrontendConfig(orb=OrbConfig(min_other_landmarks=100)))
        fe.process_frame(seq[0])  # the target frame is fixed at the ring's second sighting
        assert fe.process_frame(seq[1]).pose is not None
        real = fe._ring

        def ring(*args, _real=real, _case=case):  # type: ignore[no-untyped-def]
            circles, obs, ellipses = _real(*args)
            if _case == "true":
                return circles, obs, ellipses
            r = ellipses["right"]
            # a small curve elsewhere (a bolt head, a shadow's edge)
            dx = 300.0 if r.cx < 320 else -300.0
            moved = type(r)(cx=r.cx + dx, cy=r.cy, a=r.a / 2, b=r.b / 2, theta=r.theta)
            return [], obs, {**ellipses, "right": moved}

        monkeypatch.setattr(fe, "_ring", ring)
        m = fe.process_frame(seq[2])
        counts[case] = sum(lm.track_id >= ORB_FIRST_ID for lm in m.landmarks)
    assert counts["true"] >= 20, counts
    assert counts["moved"] >= 0.5 * counts["true"], counts


def test_nan_pixels_are_named(docking_small: Path) -> None:
    seq = load_sequence(docking_small)
    fe = StereoFrontend(seq.calibration)
    left = seq[0].left().astype(np.float32) / 255.0
    left[10:20, 10:20] = np.nan
    m = fe.process(0, 0.0, left, seq[0].right())
    assert m.pose is None
    assert any(f.startswith("image (left): non-finite pixel values") for f in m.failures)


def test_frontend_cli_writes_its_files(docking_small: Path, tmp_path: Path) -> None:
    from satpose.tools.cli import main

    out = tmp_path / "fe"
    assert main(["frontend", str(docking_small), "--out", str(out)]) == 0
    t, _ = read_tum(out / "frontend_pose.tum")
    seq = load_sequence(docking_small)
    # every frame but the first, where the target frame waits for the ring's second sighting
    np.testing.assert_allclose(t, [f.t_s for f in seq][1:])
    assert len(read_measurements(out / "measurements.parquet")) == len(seq)
    assert (out / "config.yaml").is_file()


def _assert_outer_front_edge(seq: Sequence, i: int, m: FrameMeasurements) -> None:
    """The frame's ring ellipses are the truth's outer front edge (not the inner edge, 6-12 px
    inside it, nor another concentric edge)."""
    assert m.ring is not None, m.failures
    assert seq.truth is not None and seq.target is not None and seq.target.ring is not None
    for e in m.ring.ellipses:
        cam = seq.calibration.camera(e.camera.value)
        T = seq.truth.pose(i)
        cam_from_target = T if e.camera.value == "left" else seq.calibration.right_from_left @ T
        true = conic_to_ellipse(circle_to_conic(cam.K, cam_from_target, seq.target.ring.radius_m))
        assert np.linalg.norm(e.center_px - true.center) < 0.5
        assert np.abs(e.axes_px - [true.a, true.b]).max() < 1.0


def test_small_ring_is_acquired_on_its_outer_edge(tmp_path: Path) -> None:
    """At 7 m the detector finds only the inner edge of a 0.22 m ring (the outer one is 6 px
    away); acquisition must still start on the outer front edge (edge search around the
    candidate), or the first frames measure a 0.19 m circle.

    Statistical tier: over render-noise seeds (and AVX2 vs AVX-512 renders, whose noise
    differs) a single 16 spp frame acquires the ring in about 9 of 10 cases and refuses the
    rest; at 4 spp the foil's sampling noise made 2 of 10 take the inner edge. So: three
    frames at 16 spp, a ring in at least one, and never the inner edge."""
    from satpose.datasets.config import replace_nested
    from satpose.datasets.render import render_sequence
    from satpose.datasets.scenarios import preset, scaled

    ring = {"outer_radius_m": 0.22, "inner_radius_m": 0.19}
    scenario = scaled(
        replace_nested(preset("paper-docking"), {"target": {"ring": ring}}), frames=3, spp=16
    )
    seq = load_sequence(render_sequence(scenario, tmp_path / "small-ring"))
    fe = StereoFrontend(seq.calibration)
    rings = 0
    for i, frame in enumerate(seq):
        m = fe.process_frame(frame)
        if m.ring is None:
            continue
        rings += 1
        assert m.ring.radius_m == pytest.approx(0.22, abs=0.005), i
        _assert_outer_front_edge(seq, i, m)
    assert rings >= 1


def test_side_lit_ring_is_not_taken_on_its_inner_edge(tmp_path: Path) -> None:
    """`tumble`'s sun is off the camera axis: the grey rim is darker than the lit foil on one
    side and brighter than the shadowed foil on the other, so its outer edge has no single
    polarity and the detector only finds the inner edge (0.258 m instead of 0.300 m).
    Acquisition must search for the outer edge with mixed polarity and never settle for the
    inner one.

    What this scene does not yet give on every render: over texture and noise seeds (and
    AVX2 vs AVX-512 renders, OpenCV 4.12 vs 5.0) 5 of 7 renders measure 0.299 m in 2-3
    frames of 3, but some acquire an ellipse that mixes the rim with the wall's silhouette
    (0.277-0.285 m, stereo RMS 0.57 px against 0.12-0.21 px for the rim) and track it. That
    is the ring-measurement defect the stereo-generalisation issue owns (model the rim, the
    wall's silhouette and the base); until then this test asserts what holds on any
    machine: a ring in at least one frame, each within 10 % of the outer radius (the inner
    edge is 14 % short)."""
    from satpose.datasets.render import render_sequence
    from satpose.datasets.scenarios import preset, scaled

    seq = load_sequence(
        # 16 spp: at 4 the sunlit foil's sampling noise hides the ring from the detector
        render_sequence(scaled(preset("tumble"), frames=3, spp=16), tmp_path / "tumble")
    )
    fe = StereoFrontend(seq.calibration)
    radii = [m.ring.radius_m for m in map(fe.process_frame, seq) if m.ring is not None]
    assert len(radii) >= 1
    assert all(abs(r - 0.30) < 0.03 for r in radii), radii


def test_a_known_ring_from_a_config_file_is_used_as_a_model(
    docking_small: Path, tmp_path: Path
) -> None:
    """The ring's dimensions stated as a user would (outer and inner radius, wall height, in
    the run config's YAML): the frontend fits the outline of that cylinder and still finds
    the ring in every frame, its centre within 2 cm of the truth (6 frames at 4.5 m; the
    per-frame bar of tests above)."""
    from satpose.datasets.config import load_config
    from satpose.tools.pipeline import PipelineConfig

    seq = load_sequence(docking_small)
    ring = seq.target.ring
    yaml_text = (
        "frontend:\n  stereo_ring:\n    known_ring:\n"
        f"      outer_radius_m: {ring.radius_m}\n"
        f"      inner_radius_m: {ring.extras['inner_radius_m']}\n"
        f"      wall_height_m: {ring.extras['height_m']}\n"
    )
    (tmp_path / "known.yaml").write_text(yaml_text)
    cfg = load_config(PipelineConfig, tmp_path / "known.yaml").frontend
    assert cfg.stereo_ring.known_ring is not None
    assert cfg.stereo_ring.known_ring.wall_height_m == pytest.approx(ring.extras["height_m"])
    fe = StereoFrontend(seq.calibration, cfg)
    for i, frame in enumerate(seq):
        m = fe.process_frame(frame)
        assert m.ring is not None, m.failures
        assert np.linalg.norm(m.ring.center_m - seq.truth.pose(i).t) < 0.02


def test_impossible_known_ring_dimensions_name_their_field() -> None:
    from satpose.frontend.pipeline import KnownRing

    with pytest.raises(ValueError, match=r"known_ring\.inner_radius_m"):
        KnownRing(outer_radius_m=0.5, inner_radius_m=0.6)
    with pytest.raises(ValueError, match=r"known_ring\.wall_height_m"):
        KnownRing(outer_radius_m=0.5, wall_height_m=-0.1)
    with pytest.raises(ValueError, match=r"known_ring\.lip_thickness_m"):
        KnownRing(outer_radius_m=0.5, lip_thickness_m=float("nan"))
    with pytest.raises(ValueError, match=r"known_ring\.edge_tolerance"):
        KnownRing(outer_radius_m=0.5, edge_tolerance=0.0)
    assert KnownRing(outer_radius_m=0.5, wall_outer_radius_m=0.48, lip_thickness_m=0.01).lip == (
        pytest.approx(0.02),
        0.01,
    )
