"""Measurements simulated directly from ground truth with known Gaussian pixel noise.

No rendering and no detection: the truth is projected, pixel noise is added, and the frontend's
own geometry (ellipse fit, stereo circle fit, triangulation, `TargetFrameTracker`) turns the
noisy pixels into measurements with covariances — so estimator consistency (NEES) can be
tested against a known noise model, and the backend can be developed without images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration, TargetGeometry
from satpose.frontend.conics import circle_to_conic, fit_ellipse_direct, refine_ellipse
from satpose.frontend.measurements import (
    Camera,
    EllipseObservation,
    FrameMeasurements,
    LandmarkKind,
    LandmarkMeasurement,
    RingMeasurement,
)
from satpose.frontend.pose import PoseConfig, TargetFrameTracker, _MapPoint
from satpose.frontend.stereo import (
    GeometryFailure,
    StereoRig,
    circle_from_stereo_conics,
    refine_circle,
    triangulate,
)


@dataclass(frozen=True, kw_only=True)
class SimulationConfig:
    """What to simulate.

    Attributes:
        sigma_px: standard deviation of the Gaussian noise on every image coordinate [px].
        ring_points: edge points per image on the ring's outer front edge.
        corners, components: simulate panel corners / components as landmarks.
        frame: ``truth``: the tracker's target frame and map are seeded from target.yaml, so
            poses are directly comparable with groundtruth.csv; ``bootstrap``: the frame is
            fixed from the first noisy frame, as on real data (a constant offset remains).
        dropout_frames: frame indices with no measurements at all.
        hidden_track_ids: landmarks never observed (track ids: corners 0-3 in target.yaml
            order, then components).
        pose: per-frame pose settings.
    """

    sigma_px: float = 0.3
    ring_points: int = 180
    corners: bool = True
    components: bool = True
    frame: Literal["truth", "bootstrap"] = "truth"
    dropout_frames: tuple[int, ...] = ()
    hidden_track_ids: tuple[int, ...] = ()
    pose: PoseConfig = field(default_factory=PoseConfig)


def _ellipse_observation(
    camera: Camera,
    K: np.ndarray,
    cam_from_target: Rigid3,
    radius: float,
    config: SimulationConfig,
    rng: np.random.Generator,
) -> EllipseObservation:
    from satpose.frontend.conics import conic_to_ellipse

    true = conic_to_ellipse(circle_to_conic(K, cam_from_target, radius))
    pts = true.points(config.ring_points, phase=rng.uniform(0, 2 * np.pi))
    pts = pts + rng.normal(0.0, config.sigma_px, pts.shape)
    ell, cov, _ = refine_ellipse(pts, fit_ellipse_direct(pts), sigma_px=config.sigma_px)
    return EllipseObservation(
        camera=camera,
        center_px=ell.center,
        axes_px=[ell.a, ell.b],
        angle_rad=ell.theta,
        conic=ell.conic(),
        covariance=cov,
        edge_points_px=pts,
        sigma_px=config.sigma_px,
    )


def simulate_frame(
    index: int,
    t_s: float,
    left_cam_from_target: Rigid3,
    calib: Calibration,
    target: TargetGeometry,
    tracker: TargetFrameTracker,
    config: SimulationConfig,
    rng: np.random.Generator,
) -> FrameMeasurements:
    """Measurements of one frame (see the module docstring)."""
    if index in config.dropout_frames:
        return FrameMeasurements(frame=index, t_s=t_s, failures=("simulated dropout",))
    rig = StereoRig.from_calibration(calib)
    right_from_target = rig.right_from_left @ left_cam_from_target
    failures: list[str] = []
    ring = None
    if target.ring is not None:
        try:
            obs_l = _ellipse_observation(
                Camera.LEFT, rig.K_left, left_cam_from_target, target.ring.radius_m, config, rng
            )
            obs_r = _ellipse_observation(
                Camera.RIGHT, rig.K_right, right_from_target, target.ring.radius_m, config, rng
            )
            c, n, r = circle_from_stereo_conics(rig, obs_l.conic, obs_r.conic)
            circle = refine_circle(
                rig, c, n, r, obs_l.edge_points_px, obs_r.edge_points_px, sigma_px=config.sigma_px
            )
            ring = RingMeasurement(
                ellipses=(obs_l, obs_r),
                center_m=circle.center,
                normal=circle.normal,
                radius_m=circle.radius,
                covariance=circle.covariance,
            )
        except GeometryFailure as exc:
            failures.append(f"ring: {exc}")
    landmarks = []
    for kind, track_ids, points in _landmark_points(target, config):
        Xl = left_cam_from_target.apply(points)
        pl, pr = rig.project(Xl)
        visible = _in_image(pl, calib.left.size) & _in_image(pr, calib.camera("right").size)
        visible &= (Xl[:, 2] > 0) & (rig.right_from_left.apply(Xl)[:, 2] > 0)
        visible &= ~np.isin(track_ids, config.hidden_track_ids)
        if not np.any(visible):
            continue
        nl = pl[visible] + rng.normal(0.0, config.sigma_px, pl[visible].shape)
        nr = pr[visible] + rng.normal(0.0, config.sigma_px, pr[visible].shape)
        X, cov = triangulate(rig, nl, nr, sigma_px=config.sigma_px)
        for tid, ul, ur, x, c in zip(np.asarray(track_ids)[visible], nl, nr, X, cov, strict=True):
            if np.all(np.isfinite(x)):
                landmarks.append(
                    LandmarkMeasurement(
                        track_id=int(tid),
                        kind=kind,
                        left_px=ul,
                        right_px=ur,
                        sigma_px=config.sigma_px,
                        point_m=x,
                        covariance=c,
                    )
                )
    pose, reason = tracker.update(ring, landmarks)
    if reason is not None:
        failures.append(reason)
    return FrameMeasurements(
        frame=index,
        t_s=t_s,
        ring=ring,
        landmarks=tuple(landmarks),
        pose=pose,
        failures=tuple(failures),
    )


def _landmark_points(
    target: TargetGeometry, config: SimulationConfig
) -> list[tuple[LandmarkKind, list[int], np.ndarray]]:
    out = []
    next_id = 0
    if config.corners and target.panel_corners is not None:
        n = len(target.panel_corners)
        out.append((LandmarkKind.CORNER, list(range(next_id, next_id + n)), target.panel_corners))
        next_id += n
    if config.components and target.components is not None:
        n = len(target.components)
        out.append((LandmarkKind.COMPONENT, list(range(next_id, next_id + n)), target.components))
    return out


def _in_image(px: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    return (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)


def make_tracker(target: TargetGeometry, config: SimulationConfig) -> TargetFrameTracker:
    """A `TargetFrameTracker` seeded from the truth (``frame = truth``) or empty."""
    tracker = TargetFrameTracker(config=config.pose)
    if config.frame == "truth":
        for kind, ids, points in _landmark_points(target, config):
            for tid, p in zip(ids, points, strict=True):
                tracker.map[tid] = _MapPoint(
                    kind=kind, position=np.asarray(p, float), count=config.pose.map_observations
                )
        tracker.anchor_id = 0
    return tracker


def simulate_measurements(
    poses: Sequence[Rigid3],
    t_s: Sequence[float],
    calib: Calibration,
    target: TargetGeometry,
    config: SimulationConfig = SimulationConfig(),
    seed: int = 0,
) -> list[FrameMeasurements]:
    """Measurements for every frame of a trajectory (``left_cam_from_target`` per frame).

    Args:
        poses, t_s: the true trajectory and frame times (e.g. a sequence's groundtruth.csv or
            `satpose.datasets.scenarios.trajectory`).
        calib: a stereo calibration (distortion is ignored: measurements are undistorted).
        target: target.yaml geometry (ring radius, panel corners, components).
        seed: seeds the noise.
    """
    rng = np.random.default_rng(seed)
    tracker = make_tracker(target, config)
    return [
        simulate_frame(k, float(t), pose, calib, target, tracker, config, rng)
        for k, (pose, t) in enumerate(zip(poses, t_s, strict=True))
    ]
