"""Ellipses and conics in the image: parameters, fitting, distances, projections of circles.

An ellipse is ``(cx, cy, a, b, theta)``: centre [px], semi-axes ``a >= b`` [px], and the
angle of the major axis from the image x axis [rad, in [0, pi)]. Its conic is the symmetric
3x3 ``C`` with ``p^T C p = 0`` for homogeneous pixels ``p = (x, y, 1)`` on it, negative
inside. Pixel convention: OpenCV (pixel (0, 0) is the centre of the top-left pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3


class ConicError(SatposeError):
    """A conic is not a real ellipse, or a fit is degenerate."""


@dataclass(frozen=True, kw_only=True)
class Ellipse:
    """An image ellipse (see the module docstring for conventions)."""

    cx: float
    cy: float
    a: float
    b: float
    theta: float

    def __post_init__(self) -> None:
        vals = (self.cx, self.cy, self.a, self.b, self.theta)
        if not all(math.isfinite(v) for v in vals):
            raise ConicError(f"ellipse has non-finite parameters {vals}")
        if not self.a >= self.b > 0:
            raise ConicError(f"ellipse needs a >= b > 0, got a={self.a}, b={self.b}")

    @property
    def center(self) -> np.ndarray:
        return np.array([self.cx, self.cy])

    @property
    def params(self) -> np.ndarray:
        """``[cx, cy, a, b, theta]``."""
        return np.array([self.cx, self.cy, self.a, self.b, self.theta])

    @staticmethod
    def from_params(p: np.ndarray) -> Ellipse:
        """From ``[cx, cy, a, b, theta]`` in any order of axes; normalises to ``a >= b`` and
        ``theta`` in ``[0, pi)``."""
        cx, cy, a, b, th = (float(v) for v in p)
        a, b = abs(a), abs(b)
        if b > a:
            a, b = b, a
            th += math.pi / 2
        return Ellipse(cx=cx, cy=cy, a=a, b=b, theta=th % math.pi)

    def conic(self) -> np.ndarray:
        """The 3x3 conic, unit Frobenius norm, negative inside."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        R = np.array([[c, -s], [s, c]])
        M = R @ np.diag([1 / self.a**2, 1 / self.b**2]) @ R.T  # (p-c)^T M (p-c) = 1
        ctr = self.center
        C = np.empty((3, 3))
        C[:2, :2] = M
        C[:2, 2] = C[2, :2] = -M @ ctr
        C[2, 2] = ctr @ M @ ctr - 1.0
        return C / np.linalg.norm(C)

    def points(self, n: int = 16, phase: float = 0.0) -> np.ndarray:
        """``n`` points evenly spaced in the eccentric anomaly, (n, 2)."""
        t = phase + np.linspace(0.0, 2 * math.pi, n, endpoint=False)
        c, s = math.cos(self.theta), math.sin(self.theta)
        x = self.a * np.cos(t)
        y = self.b * np.sin(t)
        return np.stack([self.cx + c * x - s * y, self.cy + s * x + c * y], axis=1)

    def normals(self, n: int = 16, phase: float = 0.0) -> np.ndarray:
        """Outward unit normals at `points` with the same ``n`` and ``phase``, (n, 2)."""
        t = phase + np.linspace(0.0, 2 * math.pi, n, endpoint=False)
        c, s = math.cos(self.theta), math.sin(self.theta)
        nx = self.b * np.cos(t)
        ny = self.a * np.sin(t)
        out = np.stack([c * nx - s * ny, s * nx + c * ny], axis=1)
        return out / np.linalg.norm(out, axis=1, keepdims=True)

    @property
    def perimeter(self) -> float:
        """Ramanujan's approximation [px]."""
        a, b = self.a, self.b
        h = ((a - b) / (a + b)) ** 2
        return math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))


def conic_to_ellipse(C: np.ndarray) -> Ellipse:
    """Ellipse parameters of a real ellipse conic (any scale or sign)."""
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    M = C[:2, :2]
    if np.linalg.det(M) <= 0:
        raise ConicError("conic is not an ellipse (det of its 2x2 block <= 0)")
    center = -np.linalg.solve(M, C[:2, 2])
    k = -(C[2, 2] + C[:2, 2] @ center)  # (p-c)^T M (p-c) = k
    w, V = np.linalg.eigh(M / k)
    if np.any(w <= 0):
        raise ConicError("conic is imaginary (no real points)")
    # Smallest eigenvalue <-> largest semi-axis.
    a, b = 1 / math.sqrt(w[0]), 1 / math.sqrt(w[1])
    theta = math.atan2(V[1, 0], V[0, 0]) % math.pi
    return Ellipse(cx=float(center[0]), cy=float(center[1]), a=a, b=b, theta=theta)


def fit_ellipse_direct(points: np.ndarray) -> Ellipse:
    """Direct least-squares ellipse fit (Fitzgibbon 1999, stable form of Halir & Flusser 1998).

    Args:
        points: (N, 2) with N >= 5, not collinear.

    Raises:
        ConicError: too few points or no ellipse fits them.
    """
    p = np.asarray(points, float).reshape(-1, 2)
    if p.shape[0] < 5:
        raise ConicError(f"an ellipse fit needs >= 5 points, got {p.shape[0]}")
    mean = p.mean(axis=0)
    scale = math.sqrt(2) / max(float(np.sqrt(((p - mean) ** 2).sum(axis=1)).mean()), 1e-12)
    x, y = ((p - mean) * scale).T
    D1 = np.stack([x * x, x * y, y * y], axis=1)
    D2 = np.stack([x, y, np.ones_like(x)], axis=1)
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        raise ConicError("degenerate point set for an ellipse fit") from None
    M = S1 + S2 @ T
    M = np.array([M[2] / 2, -M[1], M[0] / 2])
    w, V = np.linalg.eig(M)
    V = np.real(V)
    cond = 4 * V[0] * V[2] - V[1] ** 2
    ok = np.flatnonzero(cond > 0)
    if ok.size == 0:
        raise ConicError("no ellipse fits these points")
    a1 = V[:, ok[np.argmin(np.abs(np.real(w[ok])))]]
    A, B, Cc = a1
    Dd, E, F = T @ a1
    Cn = np.array([[A, B / 2, Dd / 2], [B / 2, Cc, E / 2], [Dd / 2, E / 2, F]])
    # Undo the normalisation: q = s (p - m)  =>  C_p = H^T C_q H with H = [[s, 0, -s m], ...].
    H = np.array([[scale, 0, -scale * mean[0]], [0, scale, -scale * mean[1]], [0, 0, 1]])
    return conic_to_ellipse(H.T @ Cn @ H)


def sampson_distance(points: np.ndarray, C: np.ndarray) -> np.ndarray:
    """First-order geometric distance [px] of points (N, 2) to the conic ``C`` (signed:
    negative inside for a conic that is negative inside)."""
    p = np.c_[np.asarray(points, float).reshape(-1, 2), np.ones(len(points))]
    Cp = p @ C
    num = np.einsum("ij,ij->i", Cp, p)
    grad = 2 * Cp[:, :2]
    return num / np.maximum(np.linalg.norm(grad, axis=1), 1e-300)


def refine_ellipse(
    points: np.ndarray, init: Ellipse, iterations: int = 10, sigma_px: float | None = None
) -> tuple[Ellipse, np.ndarray, float]:
    """Geometric least-squares refinement of an ellipse (Gauss-Newton on orthogonal
    distances, each point's foot parameter solved by Newton's method).

    Args:
        points: (N, 2) edge points, N >= 6.
        init: starting ellipse (e.g. `fit_ellipse_direct`).
        sigma_px: known point noise; if None it is estimated from the residuals.

    Returns:
        (ellipse, 5x5 covariance of ``[cx, cy, a, b, theta]``, residual RMS [px]).
    """
    p = np.asarray(points, float).reshape(-1, 2)
    n = p.shape[0]
    if n < 6:
        raise ConicError(f"refinement needs >= 6 points, got {n}")
    x = init.params.copy()
    t = None  # the points' foot parameters, carried from one iteration to the next
    for _ in range(iterations):
        if not np.all(np.isfinite(x)) or min(abs(x[2]), abs(x[3])) < 1e-6:
            raise ConicError("ellipse refinement degenerated (an axis reached zero or infinity)")
        r, J, t = _orthogonal_residuals(p, x, t)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            # checked before LAPACK sees it: a NaN there prints to stderr
            raise ConicError("ellipse refinement diverged (non-finite residuals)")
        try:
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        except np.linalg.LinAlgError:
            raise ConicError("ellipse refinement is degenerate") from None
        if not np.all(np.isfinite(step)):
            raise ConicError("ellipse refinement diverged (non-finite step)")
        # Trust region: no step moves the centre or an axis by more than the current major
        # axis (a converging fit takes far smaller steps; a diverging one runs off to
        # infinity). The angle is periodic and left alone (free on a near-circle).
        ratio = float(np.abs(step[:4]).max()) / max(abs(x[2]), abs(x[3]), 1e-3)
        if ratio > 1.0:
            step = step / ratio
        x = x + step
        if np.abs(step[:4]).max() < 1e-9 and abs(step[4]) < 1e-11:
            break
        if np.abs(step[:4]).max() > 0.05 * min(abs(x[2]), abs(x[3])) or abs(step[4]) > 0.05:
            t = None  # a large step: the old feet may lead Newton to a far foot point
    r, J, _ = _orthogonal_residuals(p, x, t)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise ConicError("ellipse refinement diverged")
    rms = float(np.sqrt(np.mean(r**2)))
    s2 = (sigma_px**2) if sigma_px is not None else float(r @ r) / max(n - 5, 1)
    JtJ = J.T @ J
    try:
        cov = np.linalg.inv(JtJ) * s2
    except np.linalg.LinAlgError:
        raise ConicError("ellipse covariance is singular (too few or degenerate points)") from None
    ell = Ellipse.from_params(x)
    if ell.theta != x[4] % math.pi or ell.a != abs(x[2]):
        # Axes were swapped or sign-flipped during normalisation: reorder the covariance.
        perm = [0, 1, 3, 2, 4] if abs(x[3]) > abs(x[2]) else [0, 1, 2, 3, 4]
        cov = cov[np.ix_(perm, perm)]
    return ell, 0.5 * (cov + cov.T), rms


def _orthogonal_residuals(
    p: np.ndarray, x: np.ndarray, t: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed orthogonal distances of points to the ellipse ``x``, their Jacobian (N, 5) and
    the points' foot parameters (N,). ``t``: foot parameters of an ellipse close to ``x`` (the
    previous Gauss-Newton iterate) to start Newton's method from; None: start from scratch."""
    cx, cy, a, b, th = x
    c, s = math.cos(th), math.sin(th)
    dx, dy = p[:, 0] - cx, p[:, 1] - cy
    u = c * dx + s * dy  # point in the ellipse frame
    v = -s * dx + c * dy
    # Newton on d/dt |q - e(t)|^2 = 0, quadratic: from scratch (the exact foot of a circle)
    # 5 steps reach 1e-12; from the previous iterate's feet 3 do.
    steps = 5 if t is None else 3
    if t is None:
        t = np.arctan2(a * v, b * u)
    ab = a * a - b * b
    for _ in range(steps):
        ct, st = np.cos(t), np.sin(t)
        f = ab * st * ct - u * a * st + v * b * ct
        fp = ab * (ct * ct - st * st) - u * a * ct - v * b * st
        t = t - f / np.where(np.abs(fp) > 1e-12, fp, 1e-12)
    ct, st = np.cos(t), np.sin(t)
    ex, ey = a * ct, b * st
    nx, ny = b * ct, a * st
    nn = np.hypot(nx, ny)
    with np.errstate(divide="ignore", invalid="ignore"):  # non-finite: refused by the caller
        nx, ny = nx / nn, ny / nn  # outward unit normal in the ellipse frame
    r = (u - ex) * nx + (v - ey) * ny
    # d r / d params at the foot point (the foot parameter is stationary).
    J = np.empty((p.shape[0], 5))
    J[:, 0] = -(c * nx - s * ny)
    J[:, 1] = -(s * nx + c * ny)
    J[:, 2] = -ct * nx
    J[:, 3] = -st * ny
    J[:, 4] = v * nx - u * ny  # rotating the ellipse frame moves the point by (v, -u)
    return r, J, t


def circle_to_conic(K: np.ndarray, cam_from_circle: Rigid3, radius: float) -> np.ndarray:
    """Image conic of a circle of ``radius`` centred at the origin of the plane z = 0 of a
    frame posed ``cam_from_circle``, seen by an undistorted camera ``K``."""
    R, t = cam_from_circle.R, cam_from_circle.t
    H = K @ np.c_[R[:, 0], R[:, 1], t]
    Hinv = np.linalg.inv(H)
    C = Hinv.T @ np.diag([1.0, 1.0, -(radius**2)]) @ Hinv
    C = C / np.linalg.norm(C)
    # Negative inside: the image of the circle's centre lies inside.
    centre = H[:, 2] / H[2, 2]
    return C if centre @ C @ centre < 0 else -C
