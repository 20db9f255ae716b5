"""The motion prior: white noise on acceleration (constant twist) over ``(pose, twist)`` states.

The target's body twist ``xi = [omega, v]`` (target frame, [rad/s, m/s]) is a random walk driven
by white angular and linear acceleration with power spectral densities ``q_omega`` [rad^2/s^3]
and ``q_v`` [m^2/s^3] (the "WNOA" prior of Barfoot, *State Estimation for Robotics*, 2nd ed.,
sec. 11.1, on SE(3)). Between frames ``k`` and ``k+1``, ``dt`` apart, with
``T = left_cam_from_target``, the residual

    e = [ Log(T_k^-1 T_k+1) - dt xi_k ;  xi_k+1 - xi_k ]      (12,)

has covariance ``Q(dt) = [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) diag(q_omega I3, q_v I3)``. It is
exactly zero on a constant-twist trajectory ``T(t) = T_0 Exp(xi t)`` however fast the spin,
unlike `gtsam.ConstantVelocityFactor`, which keeps the rotation constant. The process noise acts
in the target's body frame (torques about the target, forces on it), not about the camera.

`constant_twist_factor` is a Python `gtsam.CustomFactor` with analytic Jacobians. The graph
stores ``X = T^-1`` (`satpose.backend.pose3`), so ``T_k^-1 T_k+1 = X_k X_k+1^-1``. GTSAM's C++
``WnoaMotionFactorPose3`` (gtsam >= 4.3) implements the same prior with the second block
``J_r^-1(Log(.)) xi_k+1 - xi_k`` (equal to first order) but on the pose variable itself: on
``X`` it would put the angular noise about the camera centre, 5-7 m from the target, so it
serves as the C++ reference in tests and benchmarks only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.keys import V, X
from satpose.backend.pose3 import exp, local_error, tangent
from satpose.datasets.geometry import Rigid3


@dataclass(frozen=True, kw_only=True)
class MotionConfig:
    """Constant-twist motion prior.

    Attributes:
        angular_accel_noise_rad_s2_rthz: square root of the power spectral density of the
            white angular acceleration, per axis, target frame [rad/s^2/sqrt(Hz)]: the angular
            rate random-walks by ``this * sqrt(dt)`` [rad/s] over ``dt``. A torque-free body
            spinning about a principal axis keeps its body rate (environmental torques on a
            satellite are ~1e-8 rad/s^2), so the default is small; a nutating tumbler changes
            its body rate by up to ``|omega|^2 dI/I`` (~1e-4 rad/s^2 at 1 deg/s): raise it to
            ~1e-3 for such targets (docs/results/backend_simulated.md, sensitivity table).
        linear_accel_noise_m_s2_rthz: same for the linear acceleration of the target-frame
            origin, target frame [m/s^2/sqrt(Hz)]. Covers what a constant body twist does not
            model: a centroid moving in a straight line while the body spins makes the
            body-frame velocity of the ring centre turn at the spin rate (``|omega x v|``, up
            to ~1.5e-4 m/s^2 on the presets), plus the chaser's own accelerations.
        first_angular_rate_sigma_rad_s: standard deviation of the zero-mean prior on the first
            state's angular velocity (per axis) [rad/s]; weak, it only keeps the first frames
            determined.
        first_linear_velocity_sigma_m_s: same for the first linear velocity [m/s].
    """

    angular_accel_noise_rad_s2_rthz: float = 1e-5
    linear_accel_noise_m_s2_rthz: float = 2e-4
    first_angular_rate_sigma_rad_s: float = 1.0
    first_linear_velocity_sigma_m_s: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "angular_accel_noise_rad_s2_rthz",
            "linear_accel_noise_m_s2_rthz",
            "first_angular_rate_sigma_rad_s",
            "first_linear_velocity_sigma_m_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise BackendError(f"motion.{name} must be positive, got {value}")


def psd(config: MotionConfig) -> np.ndarray:
    """Diagonal power spectral density of the twist's derivative (6,) ``[q_omega x3, q_v x3]``."""
    return tangent(
        np.full(3, config.angular_accel_noise_rad_s2_rthz**2),
        np.full(3, config.linear_accel_noise_m_s2_rthz**2),
    )


def process_covariance(dt: float, config: MotionConfig) -> np.ndarray:
    """Covariance ``Q(dt)`` (12x12) of the motion residual over ``[pose tangent (6), twist (6)]``
    for a step of ``dt`` seconds (see the module docstring)."""
    Qc = np.diag(psd(config))
    return np.block([[dt**3 / 3 * Qc, dt**2 / 2 * Qc], [dt**2 / 2 * Qc, dt * Qc]])


def first_twist_covariance(config: MotionConfig) -> np.ndarray:
    """Covariance (6x6) of the prior on the first state's twist."""
    return np.diag(
        tangent(
            np.full(3, config.first_angular_rate_sigma_rad_s**2),
            np.full(3, config.first_linear_velocity_sigma_m_s**2),
        )
    )


def predict(T: Rigid3, twist: np.ndarray, dt: float) -> Rigid3:
    """Constant-twist prediction ``T * Exp(twist * dt)`` (``dt`` may be negative)."""
    return exp(T, np.asarray(twist, float) * dt)


def twist_between(T0: Rigid3, T1: Rigid3, dt: float) -> np.ndarray:
    """The constant body twist (6,) that moves ``T0`` to ``T1`` in ``dt`` seconds."""
    return local_error(T0, T1) / dt


def twist_prior_factor(i: int, config: MotionConfig) -> gtsam.NonlinearFactor:
    """Zero-mean prior on the twist of state ``i`` (the first state)."""
    return gtsam.PriorFactorVector(
        V(i), np.zeros(6), gtsam.noiseModel.Gaussian.Covariance(first_twist_covariance(config))
    )


def constant_twist_factor(
    i: int, j: int, dt: float, config: MotionConfig, clock: Any = None
) -> gtsam.CustomFactor:
    """The motion prior on ``(X(i), V(i), X(j), V(j))``, ``dt`` seconds apart (Python factor).

    Residual (12,): ``[Log(D) - dt xi_i ; xi_j - xi_i]`` with ``D = X_i X_j^-1 = T_i^-1 T_j``,
    covariance ``Q(dt)``. Right perturbations ``X Exp(delta)``: ``D`` becomes
    ``D Exp(Ad(X_j) delta_i)`` and ``D Exp(-Ad(X_j) delta_j)``, so with ``d = Log(D)``:
    ``dd/dX_i = J_r^-1(d) Ad(X_j)``, ``dd/dX_j = -J_r^-1(d) Ad(X_j)``.

    Args:
        clock: optional `satpose.backend.factors.FactorClock` timing the Python evaluations.
    """
    if not dt > 0:
        raise BackendError(f"frame times must increase, got a step of {dt} s")
    eye, zero = np.eye(6), np.zeros((6, 6))
    H_vi = np.asfortranarray(np.vstack([-dt * eye, -eye]))
    H_vj = np.asfortranarray(np.vstack([zero, eye]))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        t0 = clock.start() if clock is not None else 0.0
        keys = this.keys()
        Xi, Xj = values.atPose3(keys[0]), values.atPose3(keys[2])
        xi_i, xi_j = values.atVector(keys[1]), values.atVector(keys[3])
        D = Xi.compose(Xj.inverse())
        d = gtsam.Pose3.Logmap(D)
        e = np.concatenate([d - dt * xi_i, xi_j - xi_i])
        if H is not None:
            A = gtsam.Pose3.LogmapDerivative(d) @ Xj.AdjointMap()
            H[0] = np.asfortranarray(np.vstack([A, zero]))
            H[1] = H_vi
            H[2] = np.asfortranarray(np.vstack([-A, zero]))
            H[3] = H_vj
        if clock is not None:
            clock.stop(t0)
        return e

    return gtsam.CustomFactor(
        gtsam.noiseModel.Gaussian.Covariance(process_covariance(dt, config)),
        [X(i), V(i), X(j), V(j)],
        error,
    )


def sample_trajectory(
    T0: Rigid3,
    twist0: np.ndarray,
    t_s: np.ndarray,
    config: MotionConfig,
    rng: np.random.Generator,
) -> tuple[list[Rigid3], np.ndarray]:
    """A trajectory drawn from the motion prior itself (for consistency tests).

    Each step draws the factor's residual ``w ~ N(0, Q(dt))`` and solves for the next state:
    ``T_k+1 = T_k Exp(dt xi_k + w_1)``, ``xi_k+1 = xi_k + w_2`` — so the residuals of
    `constant_twist_factor` along the sample are exactly Gaussian with covariance ``Q(dt)``.

    Returns:
        (``left_cam_from_target`` per time, twists (N, 6)).
    """
    poses = [T0]
    twists = [np.asarray(twist0, float)]
    for k in range(1, len(t_s)):
        dt = float(t_s[k] - t_s[k - 1])
        w = rng.multivariate_normal(np.zeros(12), process_covariance(dt, config))
        poses.append(exp(poses[-1], dt * twists[-1] + w[:6]))
        twists.append(twists[-1] + w[6:])
    return poses, np.array(twists)
