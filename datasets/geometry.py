"""Rigid transforms and rotation helpers shared by every satpose package (numpy + scipy).

Conventions (see docs/conventions.md):

- ``a_from_b`` maps coordinates in frame ``b`` to frame ``a``: ``x_a = R @ x_b + t``, so
  compositions read right to left: ``cam_from_world = cam_from_rig @ rig_from_world``.
- Quaternions are ``[qx, qy, qz, qw]`` (scalar last), unit norm.
- Rotation vectors are ``axis * angle`` in radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from satpose.datasets.errors import SatposeError


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` of a 3-vector, so that ``skew(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """SO(3) exponential: rotation vector(s) ``(..., 3)`` [rad] to matrices ``(..., 3, 3)``."""
    rv = np.asarray(rotvec, dtype=float)
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(*rv.shape[:-1], 3, 3)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """SO(3) logarithm: matrices ``(..., 3, 3)`` to rotation vectors ``(..., 3)`` [rad]."""
    m = np.asarray(R, dtype=float)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(*m.shape[:-2], 3)


def quat_xyzw_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` ``[qx, qy, qz, qw]`` to rotation matrices ``(..., 3, 3)``."""
    q = np.asarray(quat_xyzw, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to quaternions ``[qx, qy, qz, qw]`` with ``qw >= 0``."""
    m = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(*m.shape[:-2], 4)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) [rad] in ``[0, pi]`` of matrices ``(..., 3, 3)``, robust near 0 and pi."""
    return np.linalg.norm(matrix_to_rotvec(R), axis=-1)


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> bool:
    """True if ``R`` is 3x3, orthonormal (``R R^T = I`` within ``tol``) with ``det R = +1``."""
    m = np.asarray(R, dtype=float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        return False
    # Plain max-abs tests: np.allclose costs more than the rest of a Rigid3 together.
    if float(np.abs(m @ m.T - np.eye(3)).max()) > tol:
        return False
    return abs(float(np.linalg.det(m)) - 1.0) < tol


class GeometryError(SatposeError):
    """A rigid transform was built from invalid numbers."""


@dataclass(frozen=True, kw_only=True)
class Rigid3:
    """A rigid transform ``a_from_b``: ``x_a = R @ x_b + t``.

    Attributes:
        R: rotation matrix, shape (3, 3), ``det R = +1``.
        t: translation, shape (3,), in the units of the target frame ``a`` (metres).
    """

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        R = np.array(self.R, dtype=float)
        t = np.array(self.t, dtype=float).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise GeometryError(f"Rigid3 needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise GeometryError("Rigid3 holds a NaN or infinite value")
        if not is_rotation(R, tol=1e-5):
            raise GeometryError("Rigid3.R is not a rotation matrix (R R^T != I or det R != 1)")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @staticmethod
    def identity() -> Rigid3:
        """The identity transform."""
        return Rigid3()

    @staticmethod
    def from_matrix(T: np.ndarray) -> Rigid3:
        """From a 4x4 homogeneous matrix ``[[R, t], [0, 1]]``."""
        m = np.asarray(T, dtype=float)
        if m.shape != (4, 4):
            raise GeometryError(f"expected a 4x4 matrix, got {m.shape}")
        return Rigid3(R=m[:3, :3], t=m[:3, 3])

    @staticmethod
    def from_quat_xyzw(quat_xyzw: np.ndarray, t: np.ndarray) -> Rigid3:
        """From a unit quaternion ``[qx, qy, qz, qw]`` and a translation (3,)."""
        return Rigid3(R=quat_xyzw_to_matrix(quat_xyzw), t=t)

    @staticmethod
    def from_rotvec(rotvec: np.ndarray, t: np.ndarray) -> Rigid3:
        """From a rotation vector [rad] and a translation (3,)."""
        return Rigid3(R=rotvec_to_matrix(rotvec), t=t)

    @property
    def quat_xyzw(self) -> np.ndarray:
        """Rotation as a unit quaternion ``[qx, qy, qz, qw]`` with ``qw >= 0``."""
        return matrix_to_quat_xyzw(self.R)

    @property
    def rotvec(self) -> np.ndarray:
        """Rotation as a rotation vector [rad]."""
        return matrix_to_rotvec(self.R)

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def inverse(self) -> Rigid3:
        """``b_from_a`` for ``self = a_from_b``."""
        return Rigid3(R=self.R.T, t=-self.R.T @ self.t)

    def __matmul__(self, other: Rigid3) -> Rigid3:
        """Composition: ``(a_from_b @ b_from_c) = a_from_c``."""
        if not isinstance(other, Rigid3):
            return NotImplemented
        return Rigid3(R=self.R @ other.R, t=self.R @ other.t + self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points ``(..., 3)`` given in frame b to frame a."""
        p = np.asarray(points, dtype=float)
        return p @ self.R.T + self.t

    def rotate(self, vectors: np.ndarray) -> np.ndarray:
        """Rotate direction vectors ``(..., 3)`` from frame b to frame a (no translation)."""
        return np.asarray(vectors, dtype=float) @ self.R.T


def absolute_orientation(model: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arun et al. 1987 / Umeyama 1991 (no scale): ``observed ~ R model + t``, batched.

    Args:
        model: ``(..., n, 3)`` points in the target frame.
        observed: ``(..., n, 3)`` the same points in the camera frame.

    Returns:
        ``R (..., 3, 3)`` (a proper rotation: the reflection case is fixed as Umeyama does) and
        ``t (..., 3)``.
    """
    mq = model.mean(axis=-2)
    mp = observed.mean(axis=-2)
    H = np.swapaxes(model - mq[..., None, :], -1, -2) @ (observed - mp[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    det = np.linalg.det(V @ np.swapaxes(U, -1, -2))
    D = np.zeros_like(H)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.sign(det) + (det == 0)
    R = V @ D @ np.swapaxes(U, -1, -2)
    t = mp - np.einsum("...ij,...j->...i", R, mq)
    return R, t
