"""Conversions between satpose's numpy poses and GTSAM's Pose3 — the one place that owns the
order of the Pose3 tangent space.

GTSAM orders a Pose3 tangent vector (and therefore every 6x6 pose covariance, noise model and
Jacobian column block) as **[rotation (rad), translation (m)]**, with right perturbation:
``T_true = T_est * Exp(xi)``. GTSAM's own examples got this wrong (borglab/gtsam issues 205 and
1793), so nothing else in the backend slices a pose covariance by hand: use `ROT`, `TRANS`
and the helpers below. The frontend's `PoseMeasurement.covariance` uses the same order.

The same order holds for the body twist ``[omega (rad/s), v (m/s)]``: it is a Pose3 tangent
vector per second.
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
