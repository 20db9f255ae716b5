"""Measurement factors: residuals at the truth, analytic Jacobians vs numerical derivatives,
robust thresholds, and the gauge."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from satpose.backend.errors import BackendError
from satpose.backend.factors import (
    MeasurementConfig,
    StereoRig,
    choose_anchor,
    gauge_factor,
    gauge_pose,
    landmark_factors,
    pose_factor,
    ring_covariance,
    ring_factor,
    ring_radius_factor,
)
from satpose.backend.keys import DISPARITY_BIAS, RADIUS, L, X
from satpose.backend.keys import RIG as RIG_KEY
from satpose.backend.pose3 import exp, to_state
from satpose.datasets.geometry import Rigid3
from satpose.datasets.scenarios import preset
from satpose.frontend.measurements import (
    LandmarkKind,
    LandmarkMeasurement,
    PoseMeasurement,
    PoseMethod,
    RingMeasurement,
)

CALIB = preset("tumble").rig.calibration()
RIG = StereoRig.from_calibration(CALIB)
T_TRUE = Rigid3.from_rotvec([2.6, 0.4, -0.7], [-0.35, 0.2, 5.5])
P_TARGET = np.array([0.711, 0.0, -0.1])


def _ring(T: Rigid3, radius: float = 0.3) -> RingMeasurement:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 7)) * 1e-3
    C = A @ A.T + np.eye(7) * 1e-6
    n = T.R[:, 2]
    P = np.eye(7)
    P[3:6, 3:6] -= np.outer(n, n)  # rank-2 normal block, as the frontend reports it
    return RingMeasurement(
        ellipses=(), center_m=T.t, normal=n, radius_m=radius, covariance=P @ C @ P.T
    )


def _landmark(T: Rigid3, p: np.ndarray, stereo: bool = True) -> LandmarkMeasurement:
    assert CALIB.right is not None and CALIB.right_from_left is not None
    X_ = T.apply(p)
    pl = CALIB.left.K @ X_
    pr = CALIB.right.K @ CALIB.right_from_left.apply(X_)
    return LandmarkMeasurement(
        track_id=3,
        kind=LandmarkKind.CORNER,
        left_px=pl[:2] / pl[2],
        right_px=pr[:2] / pr[2] if stereo else None,
        sigma_px=0.5,
        point_m=X_ if stereo else None,
        covariance=np.eye(3) * 1e-4 if stereo else None,
    )


def _values(T: Rigid3, p: np.ndarray | None = None, radius: float | None = None) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(X(0), to_state(T))  # the graph stores target_from_left_cam
    if p is not None:
        v.insert(L(3), np.asarray(p, float))
    if radius is not None:
        v.insert(RADIUS, np.array([radius]))
    return v


NO_ROBUST = MeasurementConfig(robust="none")
OFF = Rigid3.from_rotvec([0.02, -0.03, 0.05], [0.01, -0.02, 0.03])  # a perturbation


def test_residuals_vanish_at_the_truth() -> None:
    m = PoseMeasurement(left_cam_from_target=T_TRUE, covariance=np.eye(6) * 1e-4, method="orb")
    assert np.abs(pose_factor(m, 0, NO_ROBUST).unwhitenedError(_values(T_TRUE))).max() < 1e-12
    f = ring_factor(_ring(T_TRUE), 0, NO_ROBUST)
    assert np.abs(f.unwhitenedError(_values(T_TRUE))).max() < 1e-12
    f = ring_radius_factor(_ring(T_TRUE), 0, 0, NO_ROBUST)
    assert np.abs(f.unwhitenedError(_values(T_TRUE, radius=0.3))).max() < 1e-12
    for stereo in (True, False):
        fs = landmark_factors(_landmark(T_TRUE, P_TARGET, stereo), 0, RIG, NO_ROBUST)
        assert len(fs) == (2 if stereo else 1)
        for f in fs:  # GTSAM's C++ projection factors with our Cal3_S2 and left_from_right
            assert np.abs(f.unwhitenedError(_values(T_TRUE, P_TARGET))).max() < 1e-9  # px


def test_pose_factor_covariance_is_mapped_to_the_state() -> None:
    """A perturbation drawn from the measurement's covariance (T = T_m Exp(xi)) must have the
    same Mahalanobis norm in the factor (which acts on X = T^-1)."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6)) * 1e-2
    C = A @ A.T + np.eye(6) * 1e-6
    m = PoseMeasurement(left_cam_from_target=T_TRUE, covariance=C, method="orb")
    f = pose_factor(m, 0, NO_ROBUST)
    for _ in range(5):
        xi = rng.normal(size=6) * 1e-4
        expected = 0.5 * xi @ np.linalg.solve(C, xi)
        assert f.error(_values(exp(T_TRUE, xi))) == pytest.approx(expected, rel=1e-4)


def test_ring_factor_jacobians(jacobians) -> None:  # type: ignore[no-untyped-def]
    analytic, numerical = jacobians
    for f, values, shape in (
        (ring_factor(_ring(T_TRUE), 0, NO_ROBUST), _values(T_TRUE @ OFF), (5, 6)),
        (
            ring_radius_factor(_ring(T_TRUE), 0, 0, NO_ROBUST),
            _values(T_TRUE @ OFF, radius=0.31),
            (1, 7),
        ),
    ):
        J, Jn = analytic(f, values), numerical(f, values)
        assert J.shape == shape
        # entries up to ~6 (the camera-to-ring lever arm); central differences exact to ~1e-9
        assert np.abs(J - Jn).max() < 1e-8 * max(1.0, np.abs(Jn).max())


def test_ring_factors_with_the_disparity_bias(jacobians) -> None:  # type: ignore[no-untyped-def]
    """The ring's common disparity bias: zero bias leaves the factor as without it; a bias
    beta moves the predicted centre along the line of sight by |c|^2 beta / (f b); analytic
    Jacobians match central differences."""
    analytic, numerical = jacobians
    fb = 1500.0 * 0.3
    ring = _ring(T_TRUE)

    def values(T: Rigid3, beta: float, radius: float | None = None) -> gtsam.Values:
        v = _values(T, radius=radius)
        v.insert(DISPARITY_BIAS, np.array([beta]))
        return v

    plain = ring_factor(ring, 0, NO_ROBUST).unwhitenedError(_values(T_TRUE @ OFF))
    biased = ring_factor(ring, 0, NO_ROBUST, focal_baseline=fb)
    np.testing.assert_allclose(biased.unwhitenedError(values(T_TRUE @ OFF, 0.0)), plain, atol=1e-12)
    # the truth seen with a disparity bias beta > 0 (disparity too small): the measured
    # centre lies beyond the true one along its ray
    beta = 0.25
    c = T_TRUE.t
    shifted = replace(ring, center_m=c + c * np.linalg.norm(c) * beta / fb)
    f = ring_factor(shifted, 0, NO_ROBUST, focal_baseline=fb)
    shift = float(np.linalg.norm(c)) ** 2 * beta / fb
    # exact to first order: the rest is ~2 shift^2 / |c| (the shift evaluated at the
    # measured rather than the true centre)
    residual = np.abs(f.unwhitenedError(values(T_TRUE, beta))[:3]).max()
    assert residual < 2.5 * shift**2 / float(np.linalg.norm(c)) < 0.02 * shift
    for f, v, shape in ((biased, values(T_TRUE @ OFF, 0.3), (5, 7)),):
        J, Jn = analytic(f, v), numerical(f, v)
        assert J.shape == shape
        assert np.abs(J - Jn).max() < 1e-8 * max(1.0, np.abs(Jn).max())


def test_ring_factors_add_up_to_the_joint_gaussian() -> None:
    """Centre/normal factor + conditional radius factor = the 6-D Gaussian of
    ``[centre, B^T normal, radius]`` with the frontend's covariance (marginal times
    conditional), at any state and radius."""
    ring = _ring(T_TRUE)
    C = ring_covariance(ring, with_radius=True)
    cn = ring_factor(ring, 0, NO_ROBUST)
    rad = ring_radius_factor(ring, 0, 0, NO_ROBUST)
    rng = np.random.default_rng(4)
    for _ in range(5):
        T = exp(T_TRUE, rng.normal(size=6) * 3e-3)
        rho = 0.3 + rng.normal() * 1e-3
        v = _values(T, radius=rho)
        e = np.r_[cn.unwhitenedError(v), rho - ring.radius_m]
        expected = 0.5 * e @ np.linalg.solve(C, e)
        assert cn.error(v) + rad.error(v) == pytest.approx(expected, rel=1e-9)


def test_radius_outlier_keeps_centre_and_normal() -> None:
    """With the robust kernel, a radius 20 sigma off (another edge of the rim) is down-weighted
    on its own: the centre/normal factor does not see the radius at all."""
    cfg = MeasurementConfig()
    ring = _ring(T_TRUE)
    rad_sigma = float(np.sqrt(ring.covariance[6, 6]))
    v = _values(T_TRUE, radius=0.3 + 20 * rad_sigma)
    assert ring_factor(ring, 0, cfg).error(v) < 1e-12
    rad = ring_radius_factor(ring, 0, 0, cfg)
    plain = ring_radius_factor(ring, 0, 0, NO_ROBUST)
    assert rad.error(v) < 0.25 * plain.error(v)  # Cauchy: far less than quadratic


def test_landmark_behind_the_camera_does_not_raise() -> None:
    f = landmark_factors(_landmark(T_TRUE, P_TARGET), 0, RIG, NO_ROBUST)[0]
    behind = Rigid3(R=T_TRUE.R, t=-T_TRUE.t)
    assert np.all(np.isfinite(f.unwhitenedError(_values(behind, P_TARGET))))


def test_gauge_factor_jacobian(jacobians) -> None:  # type: ignore[no-untyped-def]
    analytic, numerical = jacobians
    v = gtsam.Values()
    v.insert(L(3), np.array([0.7, 0.01, -0.1]))
    f = gauge_factor(3, NO_ROBUST)
    np.testing.assert_allclose(analytic(f, v), numerical(f, v), atol=1e-9)
    assert f.unwhitenedError(v)[0] == pytest.approx(0.01)


def test_ring_covariance_projects_the_normal_block() -> None:
    ring = _ring(T_TRUE)
    C = ring_covariance(ring, with_radius=True)
    assert C.shape == (6, 6) and np.linalg.eigvalsh(C).min() > 0  # rank 2 normal -> full 2x2
    np.testing.assert_allclose(C[0:3, 0:3], ring.covariance[0:3, 0:3])
    assert C[5, 5] == pytest.approx(ring.covariance[6, 6])


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_threshold_follows_the_chi2_quantile(kernel: str) -> None:
    cfg = MeasurementConfig(robust=kernel, robust_quantile=0.99)  # type: ignore[arg-type]
    k = np.sqrt(chi2.ppf(0.99, 6))
    m = PoseMeasurement(left_cam_from_target=T_TRUE, covariance=np.eye(6) * 1e-4, method="orb")
    f = pose_factor(m, 0, cfg)
    plain = pose_factor(m, 0, NO_ROBUST)

    def weight(mahalanobis: float) -> float:
        xi = np.zeros(6)
        xi[0] = mahalanobis * 1e-2
        v = _values(exp(T_TRUE, xi))
        return f.error(v) / plain.error(v)

    def expected(r: float) -> float:  # loss / (r^2 / 2), GTSAM's definitions
        if kernel == "huber":
            return 1.0 if r <= k else (k * r - k * k / 2) / (r * r / 2)
        return (k * k / (r * r)) * np.log1p(r * r / (k * k))

    for r in (0.5 * k, 0.99 * k, 3 * k, 10 * k):
        assert weight(r) == pytest.approx(expected(r), rel=1e-9)
    assert weight(10 * k) < 0.25  # a 10-threshold outlier costs far less than quadratically


def test_anchor_rule_and_gauge_pose() -> None:
    ring = _ring(T_TRUE)
    corner = _landmark(T_TRUE, P_TARGET)
    on_axis = LandmarkMeasurement(
        track_id=0,
        kind=LandmarkKind.CORNER,
        left_px=[1.0, 1.0],
        sigma_px=0.5,
        point_m=T_TRUE.apply([0.0, 0.0, -0.2]),  # on the ring axis: cannot fix x
        covariance=np.eye(3) * 1e-4,
    )
    comp = LandmarkMeasurement(
        track_id=1,
        kind=LandmarkKind.COMPONENT,
        left_px=[1.0, 1.0],
        sigma_px=0.5,
        point_m=T_TRUE.apply([0.2, 0.3, -0.1]),
        covariance=np.eye(3) * 1e-4,
    )
    anchor = choose_anchor(ring, (on_axis, comp, corner), MeasurementConfig())
    assert anchor is corner  # corners first, axis-near ones excluded
    assert anchor.point_m is not None
    T = gauge_pose(ring, anchor.point_m)
    # P_TARGET has y = 0 in the target frame: the gauge reproduces the truth frame
    np.testing.assert_allclose(T.R, T_TRUE.R, atol=1e-12)
    np.testing.assert_allclose(T.t, T_TRUE.t, atol=1e-12)
    assert choose_anchor(ring, (on_axis,), MeasurementConfig()) is None


def test_pose_method_enum_is_accepted() -> None:
    m = PoseMeasurement(
        left_cam_from_target=T_TRUE, covariance=np.eye(6) * 1e-4, method=PoseMethod.RING_LANDMARK
    )
    assert pose_factor(m, 0, MeasurementConfig()).keys() == [X(0)]


@pytest.mark.parametrize("name", ["ring_disparity_bias_px", "landmark_disparity_bias_px"])
@pytest.mark.parametrize("value", [0.0, -0.1, float("nan"), float("inf")])
def test_disparity_bias_sigmas_are_checked(name: str, value: float) -> None:
    with pytest.raises(BackendError, match=name):
        MeasurementConfig(**{name: value})


def test_right_landmark_factor_sees_the_rig_variable() -> None:
    """With ``landmark_disparity_bias_px`` the right-image factor is on (X, RIG, L) and, at
    the calibrated rig, has the error of the plain stereo factor; a yaw of the right camera
    by ``d`` moves its error across by about ``f d``."""
    m = _landmark(T_TRUE, P_TARGET, True)
    plain = landmark_factors(m, 0, RIG, NO_ROBUST)[1]
    cfg = replace(NO_ROBUST, landmark_disparity_bias_px=0.2)
    biased = landmark_factors(m, 0, RIG, cfg)[1]
    assert set(biased.keys()) == {X(0), RIG_KEY, L(m.track_id)}
    v = gtsam.Values()
    v.insert(X(0), to_state(T_TRUE))
    v.insert(L(m.track_id), P_TARGET)
    v.insert(RIG_KEY, RIG.left_from_right)
    e0 = plain.unwhitenedError(v)
    np.testing.assert_allclose(biased.unwhitenedError(v), e0, atol=1e-9)
    d = 1e-4
    turned = RIG.left_from_right.compose(gtsam.Pose3(gtsam.Rot3.Ry(d), np.zeros(3)))
    v.update(RIG_KEY, turned)
    shift = biased.unwhitenedError(v) - e0
    f = RIG.cal_right.fx()
    assert abs(abs(shift[0]) - f * d) < 0.05 * f * d, shift
    assert abs(shift[1]) < 0.1 * f * d, shift
