"""Measurement factors: one function per measurement type of `satpose.frontend.measurements`.

Every factor acts on the graph's pose variable ``X(i) = target_from_left_cam = T^-1`` (``T =
left_cam_from_target``; right perturbation, [rotation, translation] tangent, see
`satpose.backend.pose3`) and carries the noise the frontend reports, optionally inside a robust
kernel (`MeasurementConfig.robust`).

Loosely coupled (``coupling = "loose"``):

- `pose_factor`: the per-frame pose (seed 000 eq. 9/10 or the frontend's least squares):
  ``e = Log(X_meas^-1 X)`` with ``X_meas = T_meas^-1`` and the measurement covariance mapped by
  ``Ad(T_meas)`` (`pose3.pose_covariance_to_state`). GTSAM's C++ ``PriorFactorPose3``.

Tightly coupled (``coupling = "tight"``):

- `ring_factor` (Python `gtsam.CustomFactor`, analytic Jacobians): the ring's 3-D circle,
  fitted by the frontend to the edge points of both images, its centre and normal:
  ``e = [t - c ; B^T R e_z]`` (5,) where ``(R, t) = T``, ``c``, ``n`` are the measured centre
  and normal and ``B`` (3x2) a tangent basis of ``n``. The target origin is the ring centre and
  its z axis the ring normal, so this factor also fixes five of the six gauge freedoms.
  Covariance: the frontend's covariance of ``[centre, normal]`` with the normal block projected
  on ``B``. With ``MeasurementConfig.ring_disparity_bias_px`` the measured centre is modelled
  as biased by a disparity error ``beta`` [px] common to all frames (the variable
  ``DISPARITY_BIAS``, zero-mean prior of that standard deviation): a disparity error
  ``beta`` (> 0: the disparity measured too small) moves the centre away from the cameras
  along its line of sight by ``|c|^2 beta / (f b)`` (focal length
  ``f`` [px], baseline ``b``), so ``e = [t - c + u |c|^2 beta / (f b) ; B^T R e_z]`` with ``u =
  c / |c|`` (`ring_radius_factor` stays conditioned on the measured centre). The edges of a
  rim are seen differently
  by the two cameras (its wall, a shadow's sliver, a glint; docs/frontend.md), a bias that
  the smoother cannot average away; with the variable its uncertainty is in every frame's
  covariance, and the radius shared over a changing range and the landmarks of a turning
  target make it observable.
- `ring_radius_factor` (Python): the measured radius ``r`` against the radius variable
  ``rho = R(k)`` of the circle it belongs to, *conditioned* on the centre and normal residual:
  ``e = (rho - r) - K^T e_cn`` with ``K = C_cn^-1 C_cn,r`` and variance
  ``C_rr - C_r,cn C_cn^-1 C_cn,r`` (``C`` the 6x6 covariance of ``[centre, B^T normal,
  radius]``). Without robust kernel the two factors' costs add up exactly to that of the joint
  6-D Gaussian (marginal times conditional); with one, a radius that disagrees (a biased edge,
  another circle) loses its own weight without taking the circle's centre and normal along.
  Sharing the radius over frames is what a factor on the two image conics adds over
  independent per-frame circles (the ring's apparent size fixes depth); the per-frame circle
  is the Gauss-Newton summary of the edge points, so the information is the same to first
  order. The rim shows several concentric circles (outer and inner front edge, ~13% apart):
  the graph keeps one radius variable per circle (`satpose.backend.graph`).
- `landmark_factors`: a tracked point ``p = L(j)`` (target frame, a variable) observed in the
  undistorted left and right images: two GTSAM C++ ``GenericProjectionFactorCal3_S2`` on
  ``(X(i), L(j))`` (the right one with ``body_P_sensor = left_from_right``; the rig is not
  rectified, so ``GenericStereoFactor3D`` does not apply), isotropic ``sigma_px``.
- `gauge_factor` (Python): the last gauge freedom (rotation about the ring normal): the anchor
  landmark has ``y = 0`` in the target frame (x toward the anchor projected on the ring plane,
  as the frontend's `TargetFrameTracker` defines it).

Either coupling:

- `spin_rate_factor` (Python, analytic Jacobian): the spin rate a single camera measured over
  a window of frames (seed 001): ``e = |omega_i| - r`` (1,) on the twist ``V(i)`` of the frame
  the measurement arrives with, standard deviation ``sigma``. The rate is a magnitude, so it
  constrains the twist whatever target frame the graph uses; it combines with stereo
  tracking wherever both exist.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Literal

import gtsam
import gtsam_unstable
import numpy as np
from scipy.stats import chi2

from satpose.backend.errors import BackendError
from satpose.backend.keys import DISPARITY_BIAS, RIG, L, R, V, X
from satpose.backend.pose3 import (
    ROT,
    TRANS,
    gaussian,
    pose_covariance_to_state,
    to_pose3,
    to_state,
)
from satpose.datasets.geometry import Rigid3, skew
from satpose.datasets.sequence import Calibration
from satpose.frontend.measurements import (
    LandmarkKind,
    LandmarkMeasurement,
    PoseMeasurement,
    RingMeasurement,
    SpinRateMeasurement,
)

E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, kw_only=True)
class MeasurementConfig:
    """Which measurements become factors, and how they are weighted.

    Attributes:
        coupling: ``loose`` (per-frame poses) or ``tight`` (ring + landmark pixels).
        robust: robust kernel on every measurement factor: ``none``, ``huber`` or ``cauchy``.
            Cauchy (default) ignores gross outliers (a ring fitted to the wrong one of its two
            circular sections, a mismatched landmark); Huber's pull, linear in the residual,
            still moves a frame by ``~k sigma_motion^2 / sigma_meas`` when one precise
            measurement is wrong (tests/backend/test_estimators.py).
        robust_quantile: the kernel's threshold ``k`` on the whitened residual norm is
            ``sqrt(chi2.ppf(robust_quantile, dim))`` for a factor of dimension ``dim``, so an
            inlier is down-weighted with probability ``1 - robust_quantile`` whatever the
            factor's size.
        ring_radius: estimate the ring's radius, one variable per circle shared by every frame
            that measured that circle (tight only); without it only the centre and normal are
            used.
        ring_circle_gap: a ring whose radius differs from every circle seen so far by more than
            this fraction is another circle of the rim and gets its own radius variable. The
            rim's front edges are ``(outer - inner) / outer`` apart (13% on the presets), the
            frontend's radius of one edge varies by < 1% (0.7% over paper-docking's 7 m to
            3 m); 4% is also the frontend's own limit (``StereoRingConfig.max_radius_change``).
        landmark_kinds: landmark kinds used in tight coupling.
        max_orb_per_frame: at most this many ORB landmarks per frame become factors (None: all):
            the anchor, then the longest-tracked. ORB tracks are many (up to 360 per frame on
            `tumble`) and short, each one a variable: they dominate iSAM2's cost, and beyond
            ~20 per frame they did not improve the estimate of the rendered sequences
            (docs/backend.md).
        anchor_min_axis_distance_m: a landmark closer than this to the ring axis cannot fix
            the x axis (same rule as the frontend's ``PoseConfig.min_axis_distance_m``).
        gauge_sigma_m: standard deviation of the anchor's ``y = 0`` constraint [m]
            (effectively hard).
        ring_disparity_bias_px: standard deviation [px] of the ring edges' disparity bias
            common to all frames (tight only; None, the default: no such variable, each
            frame's ring is independent). On the random family's tuning seeds the
            per-sequence depth biases of the ring correspond to 0.06-0.29 px of disparity
            (0.2 makes the smoothers' covariances honest there); off by default because the
            landmarks then fix the depth alone, and their own depth bias shows
            (docs/backend.md, "The ring's common disparity bias").
        ring_disparity_consider_px: standard deviation [px] of a disparity error of the ring
            edges common to all frames that the offline smoother *considers* without
            estimating it (tight only; None: not considered): the estimate is the one without
            it, and its covariances add that error's effect through the estimate's
            sensitivity to it (Schmidt's consider covariance, docs/backend.md). Ignored when
            ``ring_disparity_bias_px`` estimates the bias.
        landmark_disparity_bias_px: standard deviation [px] of a disparity error common to
            every landmark (tight, stereo; None, the default: none): the right-image
            observations see the right camera through the variable ``RIG``, the calibrated
            ``left_from_right`` whose yaw is free with a prior of ``sigma / f`` [rad] (a yaw
            ``d`` moves every right-image point by ``f d`` across: a disparity error).
        spin_rate: turn accepted spin-rate measurements (`FrameMeasurements.spin`) into
            factors on ``|omega|``. Only windows disjoint from the last one used are taken:
            consecutive sliding windows share all but one frame, and as independent factors
            they would count the same angles up to ``n`` times.
    """

    coupling: Literal["loose", "tight"] = "tight"
    robust: Literal["none", "huber", "cauchy"] = "cauchy"
    robust_quantile: float = 0.999
    ring_radius: bool = True
    landmark_kinds: tuple[LandmarkKind, ...] = (
        LandmarkKind.CORNER,
        LandmarkKind.COMPONENT,
        LandmarkKind.ORB,
    )
    anchor_min_axis_distance_m: float = 0.08
    gauge_sigma_m: float = 1e-6
    ring_circle_gap: float = 0.04
    max_orb_per_frame: int | None = 20
    spin_rate: bool = True
    ring_disparity_bias_px: float | None = None
    ring_disparity_consider_px: float | None = None
    landmark_disparity_bias_px: float | None = None

    def __post_init__(self) -> None:
        if self.coupling not in ("loose", "tight"):
            raise BackendError(f"coupling must be 'loose' or 'tight', got {self.coupling!r}")
        if self.robust not in ("none", "huber", "cauchy"):
            raise BackendError(f"robust must be none, huber or cauchy, got {self.robust!r}")
        if not 0.5 < self.robust_quantile < 1.0:
            raise BackendError(f"robust_quantile must be in (0.5, 1), got {self.robust_quantile}")
        if not (self.gauge_sigma_m > 0 and self.anchor_min_axis_distance_m >= 0):
            raise BackendError("gauge_sigma_m must be positive, anchor distance non-negative")
        if not 0 < self.ring_circle_gap < 1:
            raise BackendError(f"ring_circle_gap must be in (0, 1), got {self.ring_circle_gap}")
        b = self.ring_disparity_bias_px
        if b is not None and not (math.isfinite(b) and b > 0):
            raise BackendError(f"ring_disparity_bias_px must be > 0 or null, got {b}")
        b = self.ring_disparity_consider_px
        if b is not None and not (math.isfinite(b) and b > 0):
            raise BackendError(f"ring_disparity_consider_px must be > 0 or null, got {b}")
        b = self.landmark_disparity_bias_px
        if b is not None and not (math.isfinite(b) and b > 0):
            raise BackendError(f"landmark_disparity_bias_px must be > 0 or null, got {b}")
        if self.max_orb_per_frame is not None and self.max_orb_per_frame < 0:
            raise BackendError(f"max_orb_per_frame must be >= 0, got {self.max_orb_per_frame}")
        object.__setattr__(
            self, "landmark_kinds", tuple(LandmarkKind(k) for k in self.landmark_kinds)
        )


@dataclass
class FactorClock:
    """Accumulates the time spent inside Python factors (diagnostics for the step report)."""

    seconds: float = 0.0
    calls: int = 0

    def start(self) -> float:
        return time.perf_counter()

    def stop(self, t0: float) -> None:
        self.seconds += time.perf_counter() - t0
        self.calls += 1


@dataclass(frozen=True)
class StereoRig:
    """The undistorted rig in GTSAM's terms: left (and right) ``Cal3_S2`` and the right camera's
    pose in the left camera frame (``left_from_right``)."""

    cal_left: gtsam.Cal3_S2
    cal_right: gtsam.Cal3_S2 | None = None
    left_from_right: gtsam.Pose3 | None = None

    @staticmethod
    def from_calibration(calib: Calibration) -> StereoRig:
        def cal(K: np.ndarray) -> gtsam.Cal3_S2:
            return gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])

        if calib.right is None or calib.right_from_left is None:
            return StereoRig(cal(calib.left.K))
        return StereoRig(
            cal(calib.left.K), cal(calib.right.K), to_pose3(calib.right_from_left.inverse())
        )


def robust(noise: gtsam.noiseModel.Base, dim: int, config: MeasurementConfig) -> Any:
    """Wrap ``noise`` in the configured robust kernel (threshold from ``robust_quantile``)."""
    if config.robust == "none":
        return noise
    k = math.sqrt(float(chi2.ppf(config.robust_quantile, dim)))
    est = (
        gtsam.noiseModel.mEstimator.Huber.Create(k)
        if config.robust == "huber"
        else gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    )
    return gtsam.noiseModel.Robust.Create(est, noise)


# --------------------------------------------------------------------------------------------
# Loose coupling
# --------------------------------------------------------------------------------------------


def pose_factor(m: PoseMeasurement, i: int, config: MeasurementConfig) -> gtsam.NonlinearFactor:
    """Prior on ``X(i)`` from a per-frame pose (``T_true = T_meas Exp(xi)``, ``xi ~ N(0, C)``)."""
    T = m.left_cam_from_target
    C = pose_covariance_to_state(T, m.covariance)
    return gtsam.PriorFactorPose3(X(i), to_state(T), robust(gaussian(C), 6, config))


# --------------------------------------------------------------------------------------------
# Tight coupling
# --------------------------------------------------------------------------------------------


def tangent_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors completing the unit ``n`` to a right-handed basis."""
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return np.c_[u, np.cross(n, u)]


def ring_covariance(m: RingMeasurement, with_radius: bool) -> np.ndarray:
    """Covariance (6x6, or 5x5 without radius) of ``[centre, B^T normal, radius]``."""
    B = tangent_basis(m.normal)
    G = np.zeros((6, 7))
    G[0:3, 0:3] = np.eye(3)
    G[3:5, 3:6] = B.T
    G[5, 6] = 1.0
    if not with_radius:
        G = G[:5]
    C = G @ m.covariance @ G.T
    return 0.5 * (C + C.T)


def _centre_normal(
    Xp: gtsam.Pose3, c: np.ndarray, B: np.ndarray, jacobian: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """``e = [t - c ; B^T n]`` (5,) and its Jacobian (5x6) w.r.t. ``X``'s right perturbation.

    With ``X = T^-1``: ``t = -R_X^T t_X`` and ``R e_z = R_X^T e_z =: n``; for ``X Exp(d)``,
    ``dt/d(theta) = [t]x``, ``dt/d(rho) = -I``, ``dn/d(theta) = [n]x``.
    """
    Rx = Xp.rotation().matrix()
    t = -Rx.T @ Xp.translation()
    n = Rx[2]  # R_X^T e_z
    e = np.empty(5)
    e[0:3] = t - c
    e[3:5] = B.T @ n
    if not jacobian:
        return e, None
    H = np.zeros((5, 6))
    H[0:3, ROT] = skew(t)
    H[0:3, TRANS] = -np.eye(3)
    H[3:5, ROT] = B.T @ skew(n)
    return e, H


def ring_factor(
    m: RingMeasurement,
    i: int,
    config: MeasurementConfig,
    clock: FactorClock | None = None,
    focal_baseline: float | None = None,
) -> gtsam.CustomFactor:
    """The ring's centre and normal at state ``i`` (see the module docstring).

    Args:
        focal_baseline: ``f b`` [px m] of the rig: the factor then also acts on the common
            disparity bias ``DISPARITY_BIAS``."""
    c = np.asarray(m.center_m, float)
    B = tangent_basis(m.normal)
    # centre shift per pixel of disparity bias (along the line of sight) [m/px]
    dc = None if focal_baseline is None else c * float(np.linalg.norm(c)) / focal_baseline

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        t0 = clock.start() if clock is not None else 0.0
        ks = this.keys()
        e, Hx = _centre_normal(values.atPose3(ks[0]), c, B, H is not None)
        if dc is not None:
            e[0:3] += dc * values.atVector(ks[1])[0]
        if H is not None:
            H[0] = np.asfortranarray(Hx)
            if dc is not None:
                H[1] = np.asfortranarray(np.r_[dc, 0.0, 0.0][:, None])
        if clock is not None:
            clock.stop(t0)
        return e

    noise = robust(gaussian(ring_covariance(m, with_radius=False)), 5, config)
    keys = [X(i)] if dc is None else [X(i), DISPARITY_BIAS]
    return gtsam.CustomFactor(noise, keys, error)


def ring_radius_factor(
    m: RingMeasurement,
    i: int,
    circle: int,
    config: MeasurementConfig,
    clock: FactorClock | None = None,
) -> gtsam.CustomFactor:
    """The ring's radius at state ``i`` against the radius variable ``R(circle)``, conditioned
    on the centre and normal (see the module docstring): ``e = (rho - r) - K^T e_cn``,
    ``de/dX = -K^T de_cn/dX``, ``de/drho = 1``. It is conditioned on the *measured* centre
    (without the common disparity bias): a centre measured too far by ``d`` comes with a radius
    too large by ``K^T d`` (the circle fit's own regression), which the term already holds."""
    c = np.asarray(m.center_m, float)
    B = tangent_basis(m.normal)
    r = float(m.radius_m)
    C = ring_covariance(m, with_radius=True)
    K = np.linalg.solve(C[:5, :5], C[:5, 5])
    variance = float(C[5, 5] - C[5, :5] @ K)
    if not variance > 0:
        raise BackendError("ring covariance: the radius is determined by the centre and normal")
    H_rho = np.asfortranarray(np.ones((1, 1)))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        t0 = clock.start() if clock is not None else 0.0
        ks = this.keys()
        e_cn, Hx = _centre_normal(values.atPose3(ks[0]), c, B, H is not None)
        e = np.array([values.atVector(ks[1])[0] - r - K @ e_cn])
        if H is not None:
            assert Hx is not None
            H[0] = np.asfortranarray(-(K @ Hx)[None, :])
            H[1] = H_rho
        if clock is not None:
            clock.stop(t0)
        return e

    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, math.sqrt(variance)), 1, config)
    return gtsam.CustomFactor(noise, [X(i), R(circle)], error)


def landmark_factors(
    m: LandmarkMeasurement, i: int, rig: StereoRig, config: MeasurementConfig
) -> list[gtsam.NonlinearFactor]:
    """Reprojection factors of a tracked point on ``(X(i), L(track_id))``: the left image and,
    for a stereo observation, the right one (GTSAM C++ projection factors; a point behind a
    camera gives a constant error instead of an exception). With
    ``landmark_disparity_bias_px`` the right one is on ``(X(i), RIG, L(track_id))`` (gtsam's
    ``ProjectionFactorPPP``: the camera at ``X(i) RIG``); the caller adds ``RIG``."""
    noise = robust(gtsam.noiseModel.Isotropic.Sigma(2, float(m.sigma_px)), 2, config)
    out: list[gtsam.NonlinearFactor] = [
        gtsam.GenericProjectionFactorCal3_S2(
            np.asarray(m.left_px, float), noise, X(i), L(m.track_id), rig.cal_left, False, False
        )
    ]
    if m.right_px is None or rig.cal_right is None or rig.left_from_right is None:
        return out
    if config.landmark_disparity_bias_px is not None:
        out.append(
            gtsam_unstable.ProjectionFactorPPPCal3_S2(
                np.asarray(m.right_px, float),
                noise,
                X(i),
                RIG,
                L(m.track_id),
                rig.cal_right,
                False,
                False,
            )
        )
    else:
        out.append(
            gtsam.GenericProjectionFactorCal3_S2(
                np.asarray(m.right_px, float),
                noise,
                X(i),
                L(m.track_id),
                rig.cal_right,
                False,
                False,
                rig.left_from_right,
            )
        )
    return out


def gauge_factor(track_id: int, config: MeasurementConfig) -> gtsam.CustomFactor:
    """``y = 0`` for the anchor landmark ``L(track_id)`` (fixes the rotation about z)."""
    H_p = np.asfortranarray(np.array([[0.0, 1.0, 0.0]]))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        p = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = H_p
        return np.array([p[1]])

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(1, config.gauge_sigma_m), [L(track_id)], error
    )


# --------------------------------------------------------------------------------------------
# Either coupling
# --------------------------------------------------------------------------------------------


def spin_rate_factor(
    m: SpinRateMeasurement, i: int, config: MeasurementConfig, clock: FactorClock | None = None
) -> gtsam.CustomFactor:
    """``|omega_i| - r`` on the twist ``V(i) = [omega, v]`` (1,), noise ``sigma_rad_s``.

    Jacobian ``[omega^T / |omega|, 0, 0, 0]`` (1x6). ``|omega|`` has no derivative at
    ``omega = 0``; there the Jacobian takes the target x axis (any unit vector is a
    subgradient), so a Gauss-Newton step still moves the rate toward ``r``.

    Raises:
        BackendError: the measurement was refused (``status != ok``): it has no rate to use.
    """
    if not m.ok:
        raise BackendError(f"a refused spin rate ({m.status}) cannot become a factor")
    r = float(m.rate_rad_s)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        t0 = clock.start() if clock is not None else 0.0
        w = values.atVector(this.keys()[0])[ROT]
        n = float(np.linalg.norm(w))
        if H is not None:
            Hv = np.zeros((1, 6), order="F")
            Hv[0, ROT] = w / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])
            H[0] = Hv
        if clock is not None:
            clock.stop(t0)
        return np.array([n - r])

    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, float(m.sigma_rad_s)), 1, config)
    return gtsam.CustomFactor(noise, [V(i)], error)


# --------------------------------------------------------------------------------------------
# The gauge (target frame) of tight coupling
# --------------------------------------------------------------------------------------------

KIND_PRIORITY = {LandmarkKind.CORNER: 0, LandmarkKind.COMPONENT: 1, LandmarkKind.ORB: 2}


def axis_distance(ring: RingMeasurement, point_m: np.ndarray) -> float:
    """Distance [m] of a left-frame point from the ring axis."""
    d = np.asarray(point_m, float) - ring.center_m
    return float(np.linalg.norm(d - (d @ ring.normal) * ring.normal))


def choose_anchor(
    ring: RingMeasurement, landmarks: tuple[LandmarkMeasurement, ...], config: MeasurementConfig
) -> LandmarkMeasurement | None:
    """The landmark that fixes the x axis: the frontend's rule (docs/measurements.md) — among
    triangulated landmarks far enough from the ring axis, corners before components before
    ORB features, then the lowest track id."""
    usable = [
        lm
        for lm in landmarks
        if lm.point_m is not None
        and lm.kind in config.landmark_kinds
        and axis_distance(ring, lm.point_m) >= config.anchor_min_axis_distance_m
    ]
    if not usable:
        return None
    return min(usable, key=lambda lm: (KIND_PRIORITY[lm.kind], lm.track_id))


def gauge_pose(ring: RingMeasurement, anchor_point_m: np.ndarray) -> Rigid3:
    """``left_cam_from_target`` defined by the gauge: origin = ring centre, z = ring normal,
    x toward the anchor projected on the ring plane (seed 000 eq. 9)."""
    z = np.asarray(ring.normal, float)
    d = np.asarray(anchor_point_m, float) - ring.center_m
    x = d - (d @ z) * z
    n = np.linalg.norm(x)
    if n < 1e-9:
        raise BackendError("the anchor landmark lies on the ring axis")
    x /= n
    return Rigid3(R=np.c_[x, np.cross(z, x), z], t=np.asarray(ring.center_m, float))
