"""Conversions between satpose's numpy poses and GTSAM's Pose3 — the one place that owns the
order of the Pose3 tangent space.

GTSAM orders a Pose3 tangent vector (and therefore every 6x6 pose covariance, noise model and
Jacobian column block) as **[rotation (rad), translation (m)]**, with right perturbation:
``T_true = T_est * Exp(xi)``. GTSAM's own examples got this wrong (borglab/gtsam issues 205 and
1793), so nothing else in the backend slices a pose covariance by hand: use `ROT`, `TRANS`
and the helpers below. The frontend's `PoseMeasurement.covariance` uses the same order.

The same order holds for the body twist ``[omega (rad/s), v (m/s)]``: it is a Pose3 tangent
vector per second.

Inside the graph a pose is stored as GTSAM's usual "camera in world" pose with the target as the
world: ``X = target_from_left_cam = left_cam_from_target^-1`` (so that GTSAM's C++ projection
factors observe target-frame landmarks directly). `to_state` / `from_state` convert, and
`state_to_pose_jacobian` maps GTSAM's right perturbation of ``X`` to the right perturbation of
``left_cam_from_target`` that every covariance leaving the backend uses:
``X_true = X Exp(d)``  =>  ``T_true = T Exp(-Ad_X d)``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from satpose.datasets.geometry import Rigid3

ROT = slice(0, 3)
"""Rotation block of a Pose3 tangent vector / covariance (and angular part of a twist)."""
TRANS = slice(3, 6)
"""Translation block of a Pose3 tangent vector / covariance (and linear part of a twist)."""


def tangent(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Stack a rotation part (3,) and a translation part (3,) into a Pose3 tangent vector (6,)."""
    out = np.empty(6)
    out[ROT] = rotation
    out[TRANS] = translation
    return out


def block_diagonal(rotation_cov: np.ndarray, translation_cov: np.ndarray) -> np.ndarray:
    """A 6x6 pose covariance from independent rotation (3x3, rad^2) and translation (3x3, m^2)
    blocks."""
    out = np.zeros((6, 6))
    out[ROT, ROT] = rotation_cov
    out[TRANS, TRANS] = translation_cov
    return out


def to_pose3(T: Rigid3) -> gtsam.Pose3:
    """`Rigid3` -> `gtsam.Pose3` (same transform)."""
    return gtsam.Pose3(gtsam.Rot3(np.asarray(T.R, float)), np.asarray(T.t, float))


def from_pose3(P: gtsam.Pose3) -> Rigid3:
    """`gtsam.Pose3` -> `Rigid3`, re-orthonormalising the rotation (GTSAM keeps it to ~1e-15)."""
    R = P.rotation().matrix()
    U, _, Vt = np.linalg.svd(R)
    return Rigid3(R=U @ Vt, t=np.asarray(P.translation(), float))


def local_error(est: Rigid3, truth: Rigid3) -> np.ndarray:
    """``Log(est^-1 truth)`` (6,) in [rotation, translation] order: the right-perturbation error
    whose covariance the estimators report (``truth = est * Exp(error)``)."""
    return np.asarray(gtsam.Pose3.Logmap(to_pose3(est).between(to_pose3(truth))), float)


def exp(T: Rigid3, xi: np.ndarray) -> Rigid3:
    """``T * Exp(xi)`` with ``xi`` (6,) in [rotation, translation] order."""
    return from_pose3(to_pose3(T).compose(gtsam.Pose3.Expmap(np.asarray(xi, float))))


def adjoint(T: Rigid3) -> np.ndarray:
    """The 6x6 adjoint ``Ad_T`` in [rotation, translation] order:
    ``T * Exp(xi) = Exp(Ad_T xi) * T``."""
    return np.asarray(to_pose3(T).AdjointMap(), float)


def gaussian(covariance: np.ndarray) -> gtsam.noiseModel.Gaussian:
    """A full-covariance noise model (symmetrised first; order as the factor's residual)."""
    C = np.asarray(covariance, float)
    return gtsam.noiseModel.Gaussian.Covariance(0.5 * (C + C.T))


def to_state(T: Rigid3) -> gtsam.Pose3:
    """The graph's pose variable ``X = T^-1`` for ``T = left_cam_from_target``."""
    return to_pose3(T.inverse())


def from_state(X: gtsam.Pose3) -> Rigid3:
    """``left_cam_from_target`` from the graph's pose variable ``X = target_from_left_cam``."""
    return from_pose3(X.inverse())


def state_to_pose_jacobian(X: gtsam.Pose3) -> np.ndarray:
    """6x6 ``J`` with ``xi = J d`` for ``X_true = X Exp(d)``, ``T_true = T Exp(xi)``
    (``J = -Ad_X``); a covariance ``C_X`` of ``d`` becomes ``J C_X J^T``."""
    return -np.asarray(X.AdjointMap(), float)


def pose_covariance_to_state(T: Rigid3, covariance: np.ndarray) -> np.ndarray:
    """The covariance of ``d`` (``X_true = X Exp(d)``) from that of ``xi`` (``T_true = T Exp(xi)``):
    ``d = -Ad_T xi``."""
    A = adjoint(T)
    C = A @ np.asarray(covariance, float) @ A.T
    return 0.5 * (C + C.T)


def state_covariance_to_pose(X: gtsam.Pose3, covariance: np.ndarray) -> np.ndarray:
    """The covariance of ``xi`` (``T_true = T Exp(xi)``) from that of ``d``
    (``X_true = X Exp(d)``), i.e. ``J C J^T`` with `state_to_pose_jacobian`."""
    J = state_to_pose_jacobian(X)
    C = J @ np.asarray(covariance, float) @ J.T
    return 0.5 * (C + C.T)
