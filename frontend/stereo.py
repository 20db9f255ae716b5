"""Stereo geometry of seed 000: triangulation, the ring's 3-D circle from two image ellipses,
and the per-frame pose — each with first-order covariances propagated from pixel noise.

All pixels are undistorted pixels of the camera concerned; 3-D results are in the left camera
frame. ``P_l = K_l [I | 0]``, ``P_r = K_r [R | t]`` with ``right_from_left = (R, t)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec, rotvec_to_matrix, skew
from satpose.datasets.sequence import Calibration
from satpose.frontend.conics import sampson_distance
from satpose.frontend.measurements import Camera


class GeometryFailure(SatposeError):
    """A geometric reconstruction is impossible for these observations (degenerate input)."""


@dataclass(frozen=True)
class StereoRig:
    """The undistorted stereo rig: intrinsics and ``right_from_left``."""

    K_left: np.ndarray
    K_right: np.ndarray
    right_from_left: Rigid3

    @staticmethod
    def from_calibration(calib: Calibration) -> StereoRig:
        if calib.right is None or calib.right_from_left is None:
            raise GeometryFailure("a stereo rig needs a right camera and right_from_left")
        return StereoRig(calib.left.K, calib.right.K, calib.right_from_left)

    @property
    def P_left(self) -> np.ndarray:
        """3x4 projection matrix of the left camera."""
        return self.K_left @ np.c_[np.eye(3), np.zeros(3)]

    @property
    def P_right(self) -> np.ndarray:
        """3x4 projection matrix of the right camera (left-camera coordinates in)."""
        return self.K_right @ np.c_[self.right_from_left.R, self.right_from_left.t]

    def fundamental(self) -> np.ndarray:
        """F with ``x_r^T F x_l = 0`` (seed 000 eq. 2), for undistorted pixels."""
        R, t = self.right_from_left.R, self.right_from_left.t
        return np.linalg.inv(self.K_right).T @ skew(t) @ R @ np.linalg.inv(self.K_left)

    def epipolar_distance(self, left_px: np.ndarray, right_px: np.ndarray) -> np.ndarray:
        """Distance [px] of right points (M, 2) from the epipolar lines of left points (N, 2),
        shape (N, M) (seed 000 eq. 3: ``l_r = F p_l``)."""
        F = self.fundamental()
        lines = np.c_[left_px, np.ones(len(left_px))] @ F.T  # (N, 3)
        lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        return np.abs(lines @ np.c_[right_px, np.ones(len(right_px))].T)

    def project(self, points_left: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project left-frame points (N, 3) into both images: (N, 2), (N, 2)."""
        return self.project_into(Camera.LEFT, points_left), self.project_into(
            Camera.RIGHT, points_left
        )

    def intrinsics(self, cam: Camera) -> np.ndarray:
        """``K`` of camera ``cam``."""
        return self.K_left if cam is Camera.LEFT else self.K_right

    def cam_from_left(self, cam: Camera) -> Rigid3:
        """The transform from the left camera's frame into camera ``cam``'s."""
        return Rigid3.identity() if cam is Camera.LEFT else self.right_from_left

    def center(self, cam: Camera) -> np.ndarray:
        """Camera ``cam``'s centre in the left camera frame [m]."""
        T = self.cam_from_left(cam)
        return -T.R.T @ T.t

    def rays(self, cam: Camera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rays of camera ``cam`` through undistorted ``pixels`` (N, 2), in the left
        camera frame: the camera's centre (3,) and the directions (N, 3), each reaching depth
        1 in ``cam``'s own frame (not unit length)."""
        px = np.asarray(pixels, float).reshape(-1, 2)
        T = self.cam_from_left(cam)
        d = (np.c_[px, np.ones(len(px))] @ np.linalg.inv(self.intrinsics(cam)).T) @ T.R
        return self.center(cam), d

    def circle_conic(self, cam: Camera, circle: Circle3D) -> np.ndarray:
        """Image conic of a left-frame ``circle`` in camera ``cam`` (`circle_conic`)."""
        return circle_conic(
            self.intrinsics(cam),
            self.cam_from_left(cam),
            circle.center,
            circle.normal,
            circle.radius,
        )

    def project_into(self, cam: Camera, points_left: np.ndarray) -> np.ndarray:
        """Project left-frame points (N, 3) into camera ``cam``'s image, (N, 2)."""
        X = np.asarray(points_left, float).reshape(-1, 3)
        if cam is Camera.RIGHT:
            X = self.right_from_left.apply(X)
        p = X @ self.intrinsics(cam).T
        return p[:, :2] / p[:, 2:]


def triangulate(
    rig: StereoRig,
    left_px: np.ndarray,
    right_px: np.ndarray,
    sigma_px: float | np.ndarray = 0.5,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT, seed 000 eqs. 4-5) triangulation, optionally refined to the minimum of the
    reprojection error, with its covariance.

    Args:
        left_px, right_px: (N, 2) undistorted pixels.
        sigma_px: pixel noise std per coordinate (scalar or (N,)).
        refine: Gauss-Newton on the reprojection error after the DLT (2 iterations).

    Returns:
        points (N, 3) in the left frame [m], covariances (N, 3, 3) [m^2]. Points that cannot
        be triangulated (parallel rays, behind a camera) are NaN with NaN covariance.
    """
    pl = np.asarray(left_px, float).reshape(-1, 2)
    pr = np.asarray(right_px, float).reshape(-1, 2)
    Pl, Pr = rig.P_left, rig.P_right
    A = np.stack(
        [
            pl[:, :1] * Pl[2] - Pl[0],
            pl[:, 1:] * Pl[2] - Pl[1],
            pr[:, :1] * Pr[2] - Pr[0],
            pr[:, 1:] * Pr[2] - Pr[1],
        ],
        axis=1,
    )  # (N, 4, 4)
    # Row-normalise (the DLT is not scale invariant); smallest right singular vector of A.
    A = A / np.linalg.norm(A, axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    sig = np.broadcast_to(np.asarray(sigma_px, float), (pl.shape[0],))
    if refine:
        for _ in range(2):
            r, J = _reprojection(rig, X, pl, pr)
            JtJ = np.einsum("nki,nkj->nij", J, J)
            Jtr = np.einsum("nki,nk->ni", J, r)
            ok = np.linalg.cond(JtJ) < 1e12
            step = np.zeros_like(X)
            step[ok] = -np.linalg.solve(JtJ[ok], Jtr[ok][..., None])[..., 0]
            X = X + step
    r, J = _reprojection(rig, X, pl, pr)
    JtJ = np.einsum("nki,nkj->nij", J, J)
    cov = np.full((pl.shape[0], 3, 3), np.nan)
    Xr = rig.right_from_left.apply(X)
    good = (np.linalg.cond(JtJ) < 1e12) & (X[:, 2] > 0) & (Xr[:, 2] > 0)
    cov[good] = np.linalg.inv(JtJ[good]) * (sig[good] ** 2)[:, None, None]
    X[~good] = np.nan
    return X, cov


def _reprojection(
    rig: StereoRig, X: np.ndarray, pl: np.ndarray, pr: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 4) and Jacobians (N, 4, 3) of the stereo reprojection of points X."""
    R, t = rig.right_from_left.R, rig.right_from_left.t
    res = np.empty((X.shape[0], 4))
    J = np.empty((X.shape[0], 4, 3))
    for k, (K, Rc, tc, p) in enumerate(
        ((rig.K_left, np.eye(3), np.zeros(3), pl), (rig.K_right, R, t, pr))
    ):
        Xc = X @ Rc.T + tc
        q = Xc @ K.T
        z = q[:, 2:3]
        res[:, 2 * k : 2 * k + 2] = q[:, :2] / z - p
        # d(q_xy / q_z)/dX = (K_xy - (q_xy/q_z) K_z) Rc / q_z
        KR = K @ Rc
        J[:, 2 * k : 2 * k + 2, :] = (
            KR[None, :2, :] - (q[:, :2] / z)[:, :, None] * KR[None, 2:3, :]
        ) / z[:, :, None]
    return res, J


# --------------------------------------------------------------------------------------------
# The ring: a 3-D circle from its image conics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Circle3D:
    """A circle in the left camera frame: centre [m], unit normal (toward the cameras),
    radius [m], and the 7x7 covariance of ``[center, normal, radius]`` (normal block rank 2)."""

    center: np.ndarray
    normal: np.ndarray
    radius: float
    covariance: np.ndarray


def cone_circle_candidates(K: np.ndarray, conic: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The two circular sections of the elliptic cone through an image ellipse (seed 000 eq. 6).

    Args:
        K: 3x3 intrinsics (undistorted).
        conic: 3x3 image conic of the ellipse.

    Returns:
        Two ``(normal, center_direction)`` pairs in this camera's frame: the unit plane normal
        pointing toward the camera (``normal_z < 0``), and the unit direction of the circle's
        centre (the centre is at ``(radius / s) * center_direction`` for a known radius, see
        `circle_scale`).
    """
    S = K.T @ conic @ K  # the cone X^T S X = 0 (seed 000: S = K^T E K)
    S = 0.5 * (S + S.T)
    w, V = np.linalg.eigh(S)
    # Normalise the sign so that two eigenvalues are positive and one negative.
    if np.sum(w > 0) == 1:
        w, V = -w[::-1], V[:, ::-1]
    # Now w ascending: w[0] < 0 < w[1] <= w[2]. Seed 000 eq. 6 with l1 >= l2 > 0 > l3.
    l3, l2, l1 = w
    e3, e1 = V[:, 0], V[:, 2]
    if not (l3 < 0 < l2 <= l1):
        raise GeometryFailure("the ellipse's back-projected cone is not elliptic")
    a = math.sqrt(max(l1 - l2, 0.0) / (l1 - l3))
    b = math.sqrt(max(l2 - l3, 0.0) / (l1 - l3))
    Sinv = np.linalg.inv(S)
    out = []
    for sign in (1.0, -1.0):
        n = a * e1 + sign * b * e3
        n /= np.linalg.norm(n)
        c = Sinv @ n  # the centre of the section lies along S^-1 n (pole of the plane)
        if c[2] < 0:
            c = -c
        if n @ c > 0:  # the plane normal faces the camera: n . X_c < 0
            n = -n
        out.append((n, c / np.linalg.norm(c)))
    return out


def circle_scale(
    K: np.ndarray, conic: np.ndarray, normal: np.ndarray, center_dir: np.ndarray
) -> float:
    """Distance to the circle's centre per metre of radius for a candidate section, so that
    ``center = radius * circle_scale(...) * center_dir``."""
    S = K.T @ conic @ K
    S = 0.5 * (S + S.T)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    mu = 0.5 * (u @ S @ u + v @ S @ v)  # isotropic on the circle's plane
    # (s d)^T S (s d) + r^2 mu = 0 with r = 1  ->  s^2 = -mu / (d^T S d)
    q = center_dir @ S @ center_dir
    if q * mu >= 0:
        raise GeometryFailure("inconsistent circular section")
    return math.sqrt(-mu / q)


def circle_from_stereo_conics(
    rig: StereoRig, conic_left: np.ndarray, conic_right: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Seed 000 eqs. 6-8: the circle seen as ``conic_left`` and ``conic_right``.

    Each view gives two candidate normals; the pair that agrees between the views (after
    rotating the right one into the left frame) resolves the two-fold ambiguity; the centre's
    image in each view (along ``S^-1 n``) is triangulated (eq. 8 + eqs. 4-5); the radius
    follows from the left cone.

    Returns:
        ``(center [m], unit normal toward the cameras, radius [m])`` in the left frame.
    """
    R = rig.right_from_left.R
    cl = cone_circle_candidates(rig.K_left, conic_left)
    cr = cone_circle_candidates(rig.K_right, conic_right)
    best = None
    for nl, dl in cl:
        for nr, dr in cr:
            err = float(np.linalg.norm(nl - R.T @ nr))
            if best is None or err < best[0]:
                best = (err, nl, dl, nr, dr)
    assert best is not None
    _, nl, dl, nr, dr = best
    normal = nl + R.T @ nr
    normal /= np.linalg.norm(normal)
    pl = (rig.K_left @ dl)[:2] / (rig.K_left @ dl)[2]
    pr = (rig.K_right @ dr)[:2] / (rig.K_right @ dr)[2]
    X, _ = triangulate(rig, pl[None], pr[None], refine=True)
    center = X[0]
    if not np.all(np.isfinite(center)):
        raise GeometryFailure("the ring centre could not be triangulated")
    # Radius: the left cone scaled to put the centre at the triangulated depth.
    s = circle_scale(rig.K_left, conic_left, nl, dl)
    radius = float(np.linalg.norm(center) / s)
    return center, normal, radius


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit ``n`` to a right-handed orthonormal basis."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    if abs(x) < 0.9:  # u = n x e_x
        u = np.array([0.0, z, -y])
    else:  # u = n x e_y
        u = np.array([-z, 0.0, x])
    u /= math.sqrt(float(u @ u))
    v = np.array([y * u[2] - z * u[1], z * u[0] - x * u[2], x * u[1] - y * u[0]])
    return u, v


def _tangent_bases(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`tangent_basis` of each row of ``normals`` (M, 3): two (M, 3) arrays."""
    x, y, z = normals.T
    small = np.abs(x) < 0.9
    u = np.where(
        small[:, None],
        np.c_[np.zeros_like(x), z, -y],  # n x e_x
        np.c_[-z, np.zeros_like(x), x],  # n x e_y
    )
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(normals, u)


def circle_conic(
    K: np.ndarray, cam_from_left: Rigid3, center: np.ndarray, normal: np.ndarray, radius: float
) -> np.ndarray:
    """Image conic of a left-frame circle in a camera ``cam_from_left`` with intrinsics K."""
    u, v = tangent_basis(normal)
    return _circle_conics(K, cam_from_left, center[None], u[None], v[None], np.array([radius]))[0]


def _circle_conics(
    K: np.ndarray,
    cam_from_left: Rigid3,
    centers: np.ndarray,
    us: np.ndarray,
    vs: np.ndarray,
    radii: np.ndarray,
) -> np.ndarray:
    """Image conics (M, 3, 3), unit Frobenius norm, of M left-frame circles given by centre,
    two orthonormal in-plane directions and radius, in a camera ``cam_from_left``."""
    R, t = cam_from_left.R, cam_from_left.t
    H = np.empty((len(centers), 3, 3))
    H[:, :, 0] = (us @ R.T) * radii[:, None]
    H[:, :, 1] = (vs @ R.T) * radii[:, None]
    H[:, :, 2] = centers @ R.T + t
    Hinv = np.linalg.inv(K @ H)
    C = np.einsum("mki,mkj->mij", Hinv * np.array([1.0, 1.0, -1.0])[:, None], Hinv)
    return C / np.linalg.norm(C, axis=(1, 2))[:, None, None]


def _sampson_and_jacobian(p: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sampson distances (N,) of homogeneous points p (N, 3) to conic C and their derivatives
    with respect to the 9 entries of C, (N, 9) (row-major)."""
    q = p @ C  # C symmetric: (Cp)^T = p^T C
    s = np.einsum("ij,ij->i", q, p)
    g = 2.0 * np.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2)
    g = np.maximum(g, 1e-300)
    d = s / g
    J = np.einsum("ni,nj->nij", p, p) / g[:, None, None]
    qi = np.zeros_like(q)
    qi[:, :2] = q[:, :2]
    J -= (s / g**3 * 4.0)[:, None, None] * np.einsum("ni,nj->nij", qi, p)
    return d, J.reshape(-1, 9)


def refine_circle(
    rig: StereoRig,
    center: np.ndarray,
    normal: np.ndarray,
    radius: float,
    left_points: np.ndarray,
    right_points: np.ndarray,
    sigma_px: float | None = None,
    iterations: int = 8,
    radius_prior: tuple[float, float] | None = None,
    fixed_normal: bool = False,
    band: tuple[np.ndarray, np.ndarray] | None = None,
) -> Circle3D:
    """Fit a 3-D circle to the sub-pixel edge points of both images (Gauss-Newton on the
    points' first-order geometric distances to the projected circle), with covariance.

    This is the tightly coupled version of eqs. 6-8: both views constrain centre, normal and
    radius at once, instead of averaging per-view normals. Jacobians: analytic from the
    distances to the conics' entries, numerical from the conics to the 6 parameters.

    Args:
        left_points, right_points: (N, 2) / (M, 2) undistorted edge points of the ring's
            outer front edge in each image.
        sigma_px: edge point noise; estimated from the residuals if None.
        radius_prior: ``(radius_m, sigma_m)`` of a ring whose outer radius is known (a
            standard interface): one more residual ``(r - radius_m) / sigma_m``, in units of
            the edge noise, so that it weighs as the prior says.
        fixed_normal: keep ``normal`` and fit centre and radius only (points that cover part
            of the circle, whose normal a fit to all of them constrains better); the
            covariance is still that of all six parameters at the result.
        band: per edge point of each image (left (N,), right (M,)), how far [px] outside
            the circle's image the edge is expected per metre of one unknown ``k`` that both
            images share (a shadow band beside the rim whose width is proportional to the
            wall's height: `satpose.frontend.rim.shadow_band`): the distances become
            ``d - k * band``, ``k`` is fitted with the circle, and the covariance is the
            circle's marginal over it.
    """
    cams = [
        (
            rig.K_left,
            Rigid3.identity(),
            np.c_[np.asarray(left_points, float).reshape(-1, 2), np.ones(len(left_points))],
        ),
        (
            rig.K_right,
            rig.right_from_left,
            np.c_[np.asarray(right_points, float).reshape(-1, 2), np.ones(len(right_points))],
        ),
    ]
    n_pts = sum(len(p) for _, _, p in cams)
    if n_pts < 12:
        raise GeometryFailure(f"too few ring edge points to fit a circle ({n_pts})")

    def unpack(
        x: np.ndarray, c0: np.ndarray, n0: np.ndarray, r0: float
    ) -> tuple[np.ndarray, np.ndarray, float]:
        u, v = tangent_basis(n0)
        n = n0 + x[3] * u + x[4] * v
        return c0 + x[:3], n / np.linalg.norm(n), r0 * math.exp(x[5])

    steps = np.array([1e-5, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6])
    # The circle and its 12 central-difference neighbours, as rows of local parameters.
    dxs = np.vstack([np.zeros(6), np.diag(steps), -np.diag(steps)])

    def linearise(c: np.ndarray, n: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
        u0, v0 = tangent_basis(n)
        centers = c + dxs[:, :3]
        normals = n + dxs[:, 3:4] * u0 + dxs[:, 4:5] * v0
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        us, vs = _tangent_bases(normals)
        radii = r * np.exp(dxs[:, 5])
        res, jac = [], []
        for K, T, p in cams:
            C = _circle_conics(K, T, centers, us, vs, radii)
            C0 = C[0]
            dC = (C[1:7] - C[7:13]).reshape(6, 9).T / (2 * steps)
            d, Jd = _sampson_and_jacobian(p, C0)
            res.append(d)
            jac.append(Jd @ dC)
        return np.concatenate(res), np.vstack(jac)

    beta = None if band is None else np.concatenate([np.asarray(b, float) for b in band])
    if beta is not None and not np.any(np.abs(beta) > 1e-9):
        beta = None  # no band anywhere: nothing to fit it to
    k = 0.0

    def with_band(res: np.ndarray, J: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
        if beta is None:
            return res, J
        res = np.r_[res[: beta.size] - k * beta, res[beta.size :]]
        col = np.r_[-beta, np.zeros(J.shape[0] - beta.size)]
        return res, np.c_[J, col]

    c, n, r = np.asarray(center, float), np.asarray(normal, float), float(radius)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(n)) and math.isfinite(r) and r > 0):
        raise GeometryFailure("the ring circle fit has no finite starting circle")
    diverged = "the ring circle fit diverged (ring seen nearly edge-on)"
    try:
        for _ in range(iterations):
            r0, J = linearise(c, n, r)
            if not (np.all(np.isfinite(r0)) and np.all(np.isfinite(J))):
                raise GeometryFailure(diverged)
            if radius_prior is not None:
                r0, J = _with_radius_prior(r0, J, r, radius_prior, sigma_px)
            r0, J = with_band(r0, J, k)
            if fixed_normal:
                J = J.copy()
                J[:, 3:5] = 0.0  # no step in the normal (lstsq: the minimum-norm step)
            step = _bounded_circle_step(np.linalg.lstsq(J, -r0, rcond=None)[0], r)
            c, n, r = unpack(step, c, n, r)
            if beta is not None:
                k += float(step[6])
            if np.abs(step[:3]).max() < 1e-7 and np.abs(step[3:]).max() < 1e-8:
                break
        res, J = linearise(c, n, r)
    except GeometryFailure:
        raise
    except (np.linalg.LinAlgError, ArithmeticError, ValueError):
        # An edge-on ring: the conics degenerate (singular homography) or diverge
        # (ArithmeticError: OverflowError, FloatingPointError, ZeroDivisionError).
        raise GeometryFailure(diverged) from None
    if not (np.all(np.isfinite(res)) and np.all(np.isfinite(J))):
        raise GeometryFailure(diverged)
    if not (math.isfinite(r) and r > 0 and c[2] > 0):
        raise GeometryFailure(diverged)
    res, J = with_band(res, J, k)
    s2 = sigma_px**2 if sigma_px is not None else float(res @ res) / max(res.size - J.shape[1], 1)
    if radius_prior is not None:
        res, J = _with_radius_prior(res, J, r, radius_prior, math.sqrt(s2))
    try:
        cov6 = (np.linalg.inv(J.T @ J) * s2)[:6, :6]
    except np.linalg.LinAlgError:
        raise GeometryFailure("the ring circle is not constrained by its edge points") from None
    cov7 = circle_covariance(cov6, n, r)
    if n @ c > 0:
        n = -n
    return Circle3D(center=c, normal=n, radius=r, covariance=cov7)


def circle_covariance(cov6: np.ndarray, normal: np.ndarray, radius: float) -> np.ndarray:
    """The 7x7 covariance of ``[center, normal, radius]`` (`Circle3D.covariance`) from that of
    the local parameters ``[dc (3), du, dv, dlog r]`` (``tangent_basis(normal)``), symmetric."""
    u, v = tangent_basis(normal)
    G = np.zeros((7, 6))
    G[:3, :3] = np.eye(3)
    G[3:6, 3] = u
    G[3:6, 4] = v
    G[6, 5] = radius
    cov7 = G @ cov6 @ G.T
    return 0.5 * (cov7 + cov7.T)


def _with_radius_prior(
    res: np.ndarray,
    J: np.ndarray,
    r: float,
    prior: tuple[float, float],
    sigma_px: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel residuals and Jacobian (local parameters, last = log r) with the known-radius
    residual appended, scaled by the pixel noise (given, or the residuals' RMS) so that it
    weighs ``1 / sigma_m**2`` after the covariance's multiplication by the pixel variance."""
    radius_m, sigma_m = prior
    if not (radius_m > 0 and sigma_m > 0):
        raise GeometryFailure(f"known ring: radius {radius_m} m and sigma {sigma_m} m must be > 0")
    s = (
        sigma_px
        if sigma_px is not None
        else max(math.sqrt(float(res @ res) / max(res.size - 6, 1)), 0.05)
    )
    row = np.zeros((1, J.shape[1]))
    row[0, 5] = s * r / sigma_m
    return np.r_[res, s * (r - radius_m) / sigma_m], np.vstack([J, row])


MAX_CIRCLE_STEP = (0.5, 0.3, 0.3)
"""Trust region of one `refine_circle` step: centre move in ring radii, normal tilt [rad],
change of log(radius). A Gauss-Newton step beyond it is shortened along its direction
(far outside what a converging fit takes from the eqs. 6-8 start; a diverging step, e.g.
on a nearly edge-on ring, would otherwise overflow ``exp`` or leave the cone)."""


def _bounded_circle_step(step: np.ndarray, radius: float) -> np.ndarray:
    """``step`` (6,) = ``[dc (m), du, dv, dlog r]`` scaled down into `MAX_CIRCLE_STEP`.

    Raises:
        GeometryFailure: the step is not finite (a singular or NaN system).
    """
    if not np.all(np.isfinite(step)):
        raise GeometryFailure("the ring circle fit diverged (non-finite step)")
    c_max, n_max, r_max = MAX_CIRCLE_STEP
    ratio = max(
        float(np.linalg.norm(step[:3])) / (c_max * radius),
        float(np.linalg.norm(step[3:5])) / n_max,
        abs(float(step[5])) / r_max,
    )
    return step / ratio if ratio > 1.0 else step


def circle_rms(
    rig: StereoRig, circle: Circle3D, left_points: np.ndarray, right_points: np.ndarray
) -> float:
    """RMS first-order distance [px] of both images' edge points to the circle's images."""
    r = np.concatenate(
        [
            sampson_distance(points, rig.circle_conic(cam, circle))
            for cam, points in ((Camera.LEFT, left_points), (Camera.RIGHT, right_points))
        ]
    )
    return float(np.sqrt(np.mean(r**2)))


# --------------------------------------------------------------------------------------------
# Per-frame pose
# --------------------------------------------------------------------------------------------


def pose_from_ring_landmark(center: np.ndarray, normal: np.ndarray, landmark: np.ndarray) -> Rigid3:
    """Seed 000 eq. 9: z = ring normal, x toward the landmark, y = z x x, t = ring centre.

    The landmark direction is projected onto the ring plane so that the rotation is exactly
    orthonormal (the paper takes it as is; a landmark off the ring plane tilts x otherwise).
    """
    z = np.asarray(normal, float) / np.linalg.norm(normal)
    d = np.asarray(landmark, float) - center
    x = d - (d @ z) * z
    nx = np.linalg.norm(x)
    if nx < 1e-6:
        raise GeometryFailure("the landmark lies on the ring axis: x is undefined")
    x /= nx
    return Rigid3(R=np.c_[x, np.cross(z, x), z], t=np.asarray(center, float))


def pose_tangent_error(a: Rigid3, b: Rigid3) -> np.ndarray:
    """``Log(a^-1 b)`` as ``[rotation, translation]`` (6,), the right-perturbation difference
    used by the covariances (translation part in a's frame)."""
    d = a.inverse() @ b
    return np.concatenate([matrix_to_rotvec(d.R), d.t])


def propagate(
    fn: Callable[[np.ndarray], Rigid3], x0: np.ndarray, cov_x: np.ndarray, steps: np.ndarray
) -> np.ndarray:
    """First-order covariance (6x6, [rot, trans]) of a pose ``fn(x)`` for input covariance
    ``cov_x`` at ``x0``, by central differences with per-input ``steps``."""
    T0 = fn(x0)
    J = np.empty((6, x0.size))
    for k in range(x0.size):
        dx = np.zeros(x0.size)
        dx[k] = steps[k]
        J[:, k] = (pose_tangent_error(T0, fn(x0 + dx)) - pose_tangent_error(T0, fn(x0 - dx))) / (
            2 * steps[k]
        )
    C = J @ cov_x @ J.T
    return 0.5 * (C + C.T)


def pose_covariance_ring_landmark(
    center: np.ndarray,
    normal: np.ndarray,
    ring_cov: np.ndarray,
    landmark: np.ndarray,
    landmark_cov: np.ndarray,
) -> np.ndarray:
    """Covariance (6x6, [rot, trans]) of `pose_from_ring_landmark` from the ring's 7x7 and the
    landmark's 3x3 covariances (first order)."""

    def fn(x: np.ndarray) -> Rigid3:
        return pose_from_ring_landmark(x[:3], x[3:6] / np.linalg.norm(x[3:6]), x[7:10])

    x0 = np.concatenate([center, normal, [0.0], landmark])
    cov = np.zeros((10, 10))
    cov[:7, :7] = ring_cov
    cov[7:, 7:] = landmark_cov
    C = propagate(fn, x0, cov, np.full(10, 1e-6))
    return C + np.eye(6) * 1e-12  # keep it strictly positive definite


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` [rad] about the unit ``axis``."""
    return rotvec_to_matrix(np.asarray(axis, float) * angle)
