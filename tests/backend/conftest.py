"""Shared helpers for the backend tests: truth trajectories, measurements with exactly known
Gaussian noise, and numerical Jacobians of GTSAM factors.

Helpers are handed out through fixtures (the suite runs with ``--import-mode=importlib``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import gtsam
import numpy as np
import pytest

from satpose.backend.factors import tangent_basis
from satpose.backend.motion import MotionConfig, sample_trajectory
from satpose.backend.pose3 import exp
from satpose.datasets.geometry import Rigid3
from satpose.datasets.scenarios import preset, trajectory
from satpose.datasets.sequence import Calibration
from satpose.datasets.target import geometry
from satpose.frontend.measurements import (
    FrameMeasurements,
    PoseMeasurement,
    RingMeasurement,
)
from satpose.frontend.pose import PoseConfig
from satpose.frontend.simulate import SimulationConfig, simulate_measurements


@dataclass(frozen=True)
class Case:
    """A simulated sequence: truth, calibration and measurements."""

    name: str
    calib: Calibration
    t_s: np.ndarray
    poses: list[Rigid3]
    twists: np.ndarray  # (N, 6) body twists [omega, v]
    measurements: list[FrameMeasurements]


def preset_truth(
    name: str, frames: int
) -> tuple[Calibration, np.ndarray, list[Rigid3], np.ndarray]:
    """The preset's exact kinematics (first ``frames`` frames) with body twists."""
    s = replace(preset(name), frames=frames)
    tr = trajectory(s)
    poses = list(tr.left_cam_from_target)
    twists = np.array(
        [
            np.r_[w, T.R.T @ v]
            for w, v, T in zip(tr.angular_velocity, tr.linear_velocity, poses, strict=True)
        ]
    )
    return s.rig.calibration(), tr.t_s, poses, twists


def frontend_case(name: str, frames: int, seed: int, sigma_px: float = 0.5) -> Case:
    """The preset's truth through the frontend's simulator (``frame = truth``)."""
    calib, t_s, poses, twists = preset_truth(name, frames)
    ms = simulate_measurements(
        poses,
        t_s,
        calib,
        geometry(preset(name).target),
        SimulationConfig(sigma_px=sigma_px),
        seed=seed,
    )
    return Case(name, calib, t_s, poses, twists, ms)


def exact_case(name: str, frames: int, seed: int, motion: MotionConfig) -> Case:
    """A truth drawn from the motion prior (starting at the preset's first state) and
    measurements whose noise is exactly the Gaussian each factor assumes.

    The frontend's simulator supplies realistic covariances and landmark visibility; the noise
    is then redrawn in each factor's own parameterisation: pose ``T_m = T Exp(-xi)``,
    ``xi ~ N(0, C)``; ring ``[c, n, r]`` from its covariance; landmark pixels ``+ N(0, s^2)``.
    """
    calib, t_s, poses0, twists0 = preset_truth(name, frames)
    rng = np.random.default_rng(seed)
    poses, twists = sample_trajectory(poses0[0], twists0[0], t_s, motion, rng)
    target = geometry(preset(name).target)
    template = simulate_measurements(
        poses,
        t_s,
        calib,
        target,
        SimulationConfig(sigma_px=0.5, pose=PoseConfig(map_sigma_m=1e-6)),
        seed=seed,
    )
    assert target.panel_corners is not None and target.components is not None
    assert target.ring is not None
    points = np.vstack([target.panel_corners, target.components])
    assert calib.right is not None and calib.right_from_left is not None
    out = []
    for m, T in zip(template, poses, strict=True):
        assert m.pose is not None and m.ring is not None
        xi = rng.multivariate_normal(np.zeros(6), m.pose.covariance)
        pose = PoseMeasurement(
            left_cam_from_target=exp(T, -xi), covariance=m.pose.covariance, method=m.pose.method
        )
        C = m.ring.covariance
        B = np.c_[tangent_basis(T.R[:, 2])]
        G = np.zeros((7, 6))  # [c, n_tangent (2), r] -> [c, n, r] (first order)
        G[0:3, 0:3] = np.eye(3)
        G[3:6, 3:5] = B
        G[6, 5] = 1.0
        C6 = np.linalg.pinv(G) @ C @ np.linalg.pinv(G).T
        d = rng.multivariate_normal(np.zeros(6), 0.5 * (C6 + C6.T))
        n = T.R[:, 2] + B @ d[3:5]
        ring = RingMeasurement(
            ellipses=(),
            center_m=T.t + d[0:3],
            normal=n / np.linalg.norm(n),
            radius_m=target.ring.radius_m + d[5],
            covariance=C,
        )
        lms = []
        for lm in m.landmarks:
            X = T.apply(points[lm.track_id])
            pl = calib.left.K @ X
            Xr = calib.right_from_left.apply(X)
            pr = calib.right.K @ Xr
            lms.append(
                replace(
                    lm,
                    left_px=pl[:2] / pl[2] + rng.normal(0, lm.sigma_px, 2),
                    right_px=pr[:2] / pr[2] + rng.normal(0, lm.sigma_px, 2),
                )
            )
        out.append(
            FrameMeasurements(frame=m.frame, t_s=m.t_s, ring=ring, landmarks=tuple(lms), pose=pose)
        )
    return Case(name, calib, t_s, poses, twists, out)


@pytest.fixture(scope="session")
def cases() -> Callable[..., Case]:
    """``cases(kind, name, frames, seed)``: cached `frontend_case` / `exact_case`."""
    cache: dict[tuple[object, ...], Case] = {}

    def get(kind: str, name: str, frames: int, seed: int) -> Case:
        key = (kind, name, frames, seed)
        if key not in cache:
            cache[key] = (
                frontend_case(name, frames, seed)
                if kind == "frontend"
                else exact_case(name, frames, seed, MotionConfig())
            )
        return cache[key]

    return get


def numerical_jacobian(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, step: float = 1e-6
) -> np.ndarray:
    """Central differences of ``unwhitenedError`` w.r.t. each variable's tangent (Pose3 by
    ``retract``, vectors by addition), columns in key order."""
    cols = []
    for key in factor.keys():
        try:
            base: object = values.atPose3(key)
            dim = 6
        except RuntimeError:
            base = values.atVector(key)
            dim = len(base)  # type: ignore[arg-type]
        for a in range(dim):
            d = np.zeros(dim)
            d[a] = step
            out = []
            for sign in (1.0, -1.0):
                v = gtsam.Values(values)
                if isinstance(base, gtsam.Pose3):
                    v.update(key, base.retract(sign * d))
                else:
                    v.update(key, np.asarray(base) + sign * d)
                out.append(factor.unwhitenedError(v))
            cols.append((out[0] - out[1]) / (2 * step))
    return np.array(cols).T


def analytic_jacobian(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> np.ndarray:
    """The factor's own (unwhitened) Jacobian, from ``linearize`` and its noise model."""
    A, _ = factor.linearize(values).jacobian()
    return np.linalg.solve(factor.noiseModel().R(), A)


@pytest.fixture
def jacobians() -> tuple[Callable[..., np.ndarray], Callable[..., np.ndarray]]:
    """``(analytic_jacobian, numerical_jacobian)``."""
    return analytic_jacobian, numerical_jacobian
