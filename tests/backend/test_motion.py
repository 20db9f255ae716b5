"""The constant-twist motion prior: zero on constant twist (fast spin, tumble), Jacobians,
agreement with GTSAM's C++ WNOA factor, noise model, and the sampler used by the consistency
tests."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from satpose.backend.keys import V, X
from satpose.backend.motion import (
    MotionConfig,
    constant_twist_factor,
    predict,
    process_covariance,
    psd,
    sample_trajectory,
)
from satpose.backend.pose3 import to_pose3, to_state
from satpose.datasets.geometry import Rigid3

# Body twists [omega (rad/s), v (m/s)] and frame intervals of the two presets' motions.
DOCKING = (np.array([0.0, 0.0, np.radians(2.0), 0.0014, 0.0007, -0.0099]), 5.0)  # 10 deg/frame
TUMBLE = (
    np.array([0.0122, -0.0075, 0.0100, 0.0029, -0.0066, -0.0085]),  # 1 deg/s, 55 deg off z
    2.0,
)
FAST = (np.array([0.9, -0.4, 1.3, 0.2, -0.1, 0.05]), 1.0)  # 95 deg per frame
MOTIONS = pytest.mark.parametrize(
    "motion", [DOCKING, TUMBLE, FAST], ids=["docking", "tumble", "fast"]
)


def _values(poses: list[Rigid3], twists: list[np.ndarray], state: bool = True) -> gtsam.Values:
    """Graph values: ``X = T^-1`` (the backend's convention) or ``T`` itself (``state=False``,
    for GTSAM's WNOA factor, which acts on ``T`` directly)."""
    values = gtsam.Values()
    for i, (T, xi) in enumerate(zip(poses, twists, strict=True)):
        values.insert(X(i), to_state(T) if state else to_pose3(T))
        values.insert(V(i), np.asarray(xi, float))
    return values


@MOTIONS
def test_zero_on_constant_twist(motion: tuple[np.ndarray, float]) -> None:
    xi, dt = motion
    T0 = Rigid3.from_rotvec([2.9, 0.3, -0.4], [0.15, 0.05, 7.0])
    poses = [T0]
    for _ in range(3):
        poses.append(predict(poses[-1], xi, dt))
    values = _values(poses, [xi] * 4)
    for i in range(3):
        f = constant_twist_factor(i, i + 1, dt, MotionConfig())
        # exact up to rounding of Exp/Log on 7 m translations
        assert np.abs(f.unwhitenedError(values)).max() < 1e-12


@MOTIONS
def test_jacobians_are_exact(motion: tuple[np.ndarray, float], jacobians) -> None:  # type: ignore[no-untyped-def]
    analytic, numerical = jacobians
    rng = np.random.default_rng(1)
    xi, dt = motion
    T0 = Rigid3.from_rotvec([0.3, -1.2, 0.4], [0.15, 0.05, 7.0])
    # off the constant-twist manifold, so that every Jacobian block matters
    T1 = predict(predict(T0, xi, dt), rng.normal(0, 0.05, 6), 1.0)
    values = _values([T0, T1], [xi, xi + rng.normal(0, 0.01, 6)])
    f = constant_twist_factor(0, 1, dt, MotionConfig())
    J, Jn = analytic(f, values), numerical(f, values)
    # entries up to ~7 (lever arm of the camera centre); central differences with h = 1e-6
    # are exact to ~1e-9 here
    assert np.abs(J - Jn).max() < 1e-7 * max(1.0, np.abs(Jn).max())


@pytest.mark.parametrize("motion", [DOCKING, TUMBLE], ids=["docking", "tumble"])
def test_agrees_with_gtsams_wnoa_factor(motion: tuple[np.ndarray, float]) -> None:
    """Same prior as GTSAM's C++ WnoaMotionFactorPose3 (applied to T = left_cam_from_target):
    identical pose residual and noise model; the twist residuals differ by
    ``(J_r^-1(d) - I) xi_j = ad(d) xi_j / 2 + ...``, second order near constant twist."""
    rng = np.random.default_rng(2)
    xi, dt = motion
    T0 = Rigid3.from_rotvec([0.3, -1.2, 0.4], [0.15, 0.05, 7.0])
    T1 = predict(predict(T0, xi, dt), rng.normal(0, 1e-3, 6), 1.0)
    xi1 = xi + rng.normal(0, 1e-4, 6)
    ours = constant_twist_factor(0, 1, dt, MotionConfig())
    wnoa = gtsam.WnoaMotionFactorPose3(
        gtsam.StateData(X(0), V(0), 0.0), gtsam.StateData(X(1), V(1), dt), psd(MotionConfig())
    )
    e = ours.unwhitenedError(_values([T0, T1], [xi, xi1]))
    e_ref = wnoa.unwhitenedError(_values([T0, T1], [xi, xi1], state=False))
    np.testing.assert_allclose(e[:6], e_ref[:6], atol=1e-12)
    d = e[:6] + dt * xi
    second_order = np.linalg.norm(gtsam.Pose3.adjointMap(d) @ xi1) / 2
    assert np.abs(e[6:] - e_ref[6:]).max() < 1.5 * second_order
    np.testing.assert_allclose(ours.noiseModel().R(), wnoa.noiseModel().R(), rtol=1e-12)


def test_noise_model_is_the_wnoa_covariance() -> None:
    cfg = MotionConfig(angular_accel_noise_rad_s2_rthz=3e-4, linear_accel_noise_m_s2_rthz=2e-3)
    R = constant_twist_factor(0, 1, 5.0, cfg).noiseModel().R()
    np.testing.assert_allclose(np.linalg.inv(R.T @ R), process_covariance(5.0, cfg), rtol=1e-9)
    Q = process_covariance(5.0, cfg)
    # angular rate random walk: variance q * dt on omega, q dt^3 / 3 on the attitude
    assert Q[6, 6] == pytest.approx(3e-4**2 * 5.0)
    assert Q[0, 0] == pytest.approx(3e-4**2 * 125 / 3)
    assert Q[3, 9] == pytest.approx(2e-3**2 * 25 / 2)


def test_samples_have_the_prior_statistics() -> None:
    """The sampler's whitened residuals are chi2(12) per step (oracle for the NEES tests)."""
    cfg = MotionConfig(angular_accel_noise_rad_s2_rthz=1e-3, linear_accel_noise_m_s2_rthz=1e-3)
    t = np.arange(200) * 2.0
    T0 = Rigid3.from_rotvec([0.1, 0.2, 0.3], [0, 0, 5.0])
    poses, twists = sample_trajectory(T0, TUMBLE[0], t, cfg, np.random.default_rng(3))
    values = _values(poses, list(twists))
    stats = [2 * constant_twist_factor(i, i + 1, 2.0, cfg).error(values) for i in range(199)]
    lo, hi = chi2.ppf([0.001, 0.999], 12 * len(stats))
    # sum of 199 chi2(12) draws: inside its 99.8% interval
    assert lo < np.sum(stats) < hi
