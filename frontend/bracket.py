"""Pose from part of a solar-panel triangular bracket seen by one camera (seed 002).

The camera sees the strut ``P1P2`` whole and the first part of the struts ``P1P5`` and ``P2P5``
(Wu et al. 2017, fig. 2). The image gives four points: ``p1``, ``p2`` (the vertices), ``p4`` (a
point on ``P1P5``) and ``p3`` (a point on ``P2P5``); the apex image ``p5`` is the intersection
of the image lines ``p1p4`` and ``p2p3``. Each of ``p1``, ``p2``, ``p5`` gives a back-projection
ray ``P_c = d [k_x, k_y, 1]`` (eq. 8); the bracket's three side lengths fix the depths
``d1, d2, d5`` (eq. 9); the triangle's incentre is a fourth point, and absolute orientation
(Arun et al. 1987) gives ``left_cam_from_target``.

Two depth solvers:

- ``closed-form`` (ours): eq. 9 is the three-point perspective problem: Grunert's quartic
  (Haralick et al. 1994, "Review and analysis of solutions of the three point perspective pose
  estimation problem", IJCV 13(3)) gives every solution, Gauss-Newton polishes each root, and
  the candidates are told apart (multiple-solution check) by a prior (the previous frame) or by
  where the visible strut ends fall on the reconstructed struts.
- ``ant-colony`` (the paper's baseline, sec. 3.3): 500 ants, 10 iterations, Q = 10, alpha = 1,
  rho = 1, p = 10 %; the update rules are reconstructed in docs/bracket.md (the equations are
  images missing from the paper's text).

Measurement model: four image points with white noise ``sigma_px`` and vertex coordinates with
white error ``vertex_sigma_m``. Six image numbers (four for ``p1, p2``, one for each strut
direction) fix six pose parameters, so the problem is exactly determined and the covariance is
the first-order propagation of both error sources through the solver (central differences of
the whole pipeline, batched).

Everything here is numpy; a frame that cannot be solved gives a result with ``pose = None`` and
a ``reason``, never an exception.
"""

from __future__ import annotations

import cmath
import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import (
    Rigid3,
    absolute_orientation,
    matrix_to_rotvec,
    rotvec_to_matrix,
)
from satpose.frontend.measurements import (
    FrameMeasurements,
    MeasurementError,
    PoseMeasurement,
    PoseMethod,
)


class BracketError(SatposeError):
    """Invalid bracket geometry or solver settings."""


@dataclass(frozen=True, kw_only=True)
class BracketGeometry:
    """The bracket's known geometry.

    Attributes:
        vertices_m: (3, 3) rows ``P1, P2, P5`` in the target frame [m].
        vertex_sigma_m: standard deviation of each vertex coordinate's error (deformation,
            manufacturing) [m]; enters the per-frame covariance.
        visible_fraction: fraction of ``P1P5`` and ``P2P5`` visible from ``P1`` and ``P2``, if
            known (the paper's simulation: 1/5); used only to choose among P3P solutions.
    """

    vertices_m: np.ndarray
    vertex_sigma_m: float = 0.01 / math.sqrt(3.0)
    visible_fraction: float | None = None

    def __post_init__(self) -> None:
        v = np.array(self.vertices_m, dtype=float)
        if v.shape != (3, 3) or not np.all(np.isfinite(v)):
            raise BracketError(f"vertices_m: expected 3 finite rows P1, P2, P5, got {v.shape}")
        area = 0.5 * np.linalg.norm(np.cross(v[1] - v[0], v[2] - v[0]))
        if area < 1e-6:
            raise BracketError("vertices_m: the bracket's vertices are collinear")
        v.setflags(write=False)
        object.__setattr__(self, "vertices_m", v)
        if not (np.isfinite(self.vertex_sigma_m) and self.vertex_sigma_m >= 0):
            raise BracketError(f"vertex_sigma_m must be >= 0, got {self.vertex_sigma_m}")
        if self.visible_fraction is not None and not 0 < self.visible_fraction < 1:
            raise BracketError(f"visible_fraction must be in (0, 1), got {self.visible_fraction}")

    @property
    def sides_m(self) -> np.ndarray:
        """``[|P1P2|, |P1P5|, |P2P5|]`` [m]."""
        return triangle_sides(self.vertices_m)


def triangle_sides(vertices: np.ndarray) -> np.ndarray:
    """``[|P1P2|, |P1P5|, |P2P5|]`` of ``(..., 3, 3)`` vertex rows ``P1, P2, P5``."""
    v = np.asarray(vertices, dtype=float)
    return np.stack(
        [
            np.linalg.norm(v[..., 0, :] - v[..., 1, :], axis=-1),
            np.linalg.norm(v[..., 0, :] - v[..., 2, :], axis=-1),
            np.linalg.norm(v[..., 1, :] - v[..., 2, :], axis=-1),
        ],
        axis=-1,
    )


def incentre(vertices: np.ndarray) -> np.ndarray:
    """Incentre ``(a P1 + b P2 + c P5) / (a + b + c)`` of ``(..., 3, 3)`` rows ``P1, P2, P5``;
    ``a, b, c`` are the sides opposite each vertex."""
    v = np.asarray(vertices, dtype=float)
    s = triangle_sides(v)  # |P1P2| (opp. P5), |P1P5| (opp. P2), |P2P5| (opp. P1)
    w = np.stack([s[..., 2], s[..., 1], s[..., 0]], axis=-1)
    return np.einsum("...i,...ij->...j", w, v) / w.sum(axis=-1, keepdims=True)


@dataclass(frozen=True, kw_only=True)
class BracketObservation:
    """The bracket's image points (undistorted pixels, OpenCV convention); None = not found.

    Attributes:
        p1_px, p2_px: vertices ``P1``, ``P2`` (2,).
        p3_px: a point on strut ``P2P5`` away from ``P2`` (2,).
        p4_px: a point on strut ``P1P5`` away from ``P1`` (2,).
        sigma_px: standard deviation of each coordinate [px].
    """

    p1_px: np.ndarray | None
    p2_px: np.ndarray | None
    p3_px: np.ndarray | None
    p4_px: np.ndarray | None
    sigma_px: float = 1.0

    def missing(self) -> list[str]:
        """Names of the points that are absent or not finite."""
        out = []
        for name in ("p1_px", "p2_px", "p3_px", "p4_px"):
            p = getattr(self, name)
            if p is None or np.shape(p) != (2,) or not np.all(np.isfinite(p)):
                out.append(name)
        return out

    def points(self) -> np.ndarray:
        """(4, 2) rows ``p1, p2, p3, p4`` (only for a complete observation)."""
        return np.array([self.p1_px, self.p2_px, self.p3_px, self.p4_px], dtype=float)


@dataclass(frozen=True, kw_only=True)
class AntColonyConfig:
    """The paper's ant-colony search (sec. 3.3 and sec. 4 settings).

    Attributes:
        ants: colony size ``k`` (paper: 500).
        first_ants: colony size when there is no prior (the paper enlarges the colony for the
            first search over wide intervals; its size is not given).
        iterations: ``N_max`` (paper: 10).
        pheromone_q: pheromone intensity ``Q`` (paper: 10).
        alpha: pheromone heuristic factor (paper: 1).
        rho: pheromone forgetting factor (paper: 1).
        p0: global state-transition threshold (paper: "p = 10", read as 10 %).
        step_fraction: search step ``omega`` as a fraction of the interval width.
        first_interval_m: depth interval of every variable when there is no prior [m].
        track_half_width_m: smallest half width of the interval around the previous frame's
            depths [m].
        track_half_width_fraction: half width as a fraction of each previous depth (the
            frame-to-frame scatter of the depths grows with range: ~10 % at 2 m, 1 px).
        stop_cost_mm2: early stop when the best cost is below this [mm^2].
    """

    ants: int = 500
    first_ants: int = 5000
    iterations: int = 10
    pheromone_q: float = 10.0
    alpha: float = 1.0
    rho: float = 1.0
    p0: float = 0.10
    step_fraction: float = 0.1
    first_interval_m: tuple[float, float] = (0.3, 5.0)
    track_half_width_m: float = 0.05
    track_half_width_fraction: float = 0.1
    stop_cost_mm2: float = 1e-6


@dataclass(frozen=True, kw_only=True)
class BracketConfig:
    """Settings of `solve_bracket`.

    Attributes:
        solver: ``closed-form`` (P3P quartic + Gauss-Newton) or ``ant-colony`` (paper).
        min_strut_angle_deg: below this angle between the image lines ``p1p4`` and ``p2p3``
            the apex is ill-defined (bracket seen edge-on) and the frame is refused.
        max_depth_cost_m: a solution whose eq. 9 residual norm exceeds this is refused [m].
        covariance: propagate the pixel and vertex errors to a 6x6 pose covariance.
        prior_least_squares: with ``prior_depths``, minimise eq. 9 by Levenberg-Marquardt
            from the prior (the nearest exact root, or, where noise has turned two nearby
            roots complex, their least-squares point) instead of taking the nearest real
            root; falls back to the real roots if that is not admissible.
        ant: ant-colony settings.
    """

    solver: Literal["closed-form", "ant-colony"] = "closed-form"
    min_strut_angle_deg: float = 2.0
    max_depth_cost_m: float = 0.05
    covariance: bool = True
    prior_least_squares: bool = False
    ant: AntColonyConfig = field(default_factory=AntColonyConfig)

    def __post_init__(self) -> None:
        if self.solver not in ("closed-form", "ant-colony"):
            raise BracketError(f"solver must be closed-form or ant-colony, got {self.solver!r}")


@dataclass(frozen=True, kw_only=True)
class BracketResult:
    """One frame's answer.

    Attributes:
        pose: ``left_cam_from_target``, or None (see ``reason``).
        covariance: 6x6 over ``[rotation (rad), translation (m)]``, right perturbation
            (``T_true = T Exp(xi)``), or None.
        depths_m: ``d1, d2, d5`` (3,), or None.
        apex_px: image of ``P5`` (2,), or None.
        candidates: number of admissible P3P solutions (closed-form), 1 for the ant colony.
        selected_by: ``unique``, ``prior``, ``fraction``, ``first`` (ambiguous) or ``search``.
        depth_cost_m: norm of the eq. 9 residual at the solution [m].
        reason: why ``pose`` is None ("" when solved).
        solve_cpu_s: CPU time of the depth solve alone [s].
    """

    pose: Rigid3 | None
    covariance: np.ndarray | None = None
    depths_m: np.ndarray | None = None
    apex_px: np.ndarray | None = None
    candidates: int = 0
    selected_by: str = ""
    depth_cost_m: float = math.nan
    reason: str = ""
    solve_cpu_s: float = 0.0

    @property
    def ambiguous(self) -> bool:
        """More than one admissible solution and nothing but their order to choose by."""
        return self.selected_by == "first"


# --- image geometry -------------------------------------------------------------------------


def _homog(p: np.ndarray) -> np.ndarray:
    return np.concatenate([p, np.ones((*p.shape[:-1], 1))], axis=-1)


def strut_apex(points_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apex image ``p5`` and the angle between the strut lines.

    Args:
        points_px: ``(..., 4, 2)`` rows ``p1, p2, p3, p4``.

    Returns:
        ``p5`` ``(..., 2)`` (NaN where the lines are parallel) and the angle between the image
        lines ``p1p4`` and ``p2p3`` ``(...)`` [rad].
    """
    h = _homog(np.asarray(points_px, dtype=float))
    l14 = np.cross(h[..., 0, :], h[..., 3, :])
    l23 = np.cross(h[..., 1, :], h[..., 2, :])
    x = np.cross(l14, l23)
    with np.errstate(divide="ignore", invalid="ignore"):
        p5 = x[..., :2] / x[..., 2:3]
    d14 = h[..., 3, :2] - h[..., 0, :2]
    d23 = h[..., 2, :2] - h[..., 1, :2]
    cross = d14[..., 0] * d23[..., 1] - d14[..., 1] * d23[..., 0]
    angle = np.arctan2(np.abs(cross), np.abs(np.sum(d14 * d23, axis=-1)))
    return p5, angle


def project(cam_from_target: Rigid3, points_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection ``(N, 3)`` target-frame points -> ``(N, 2)`` pixels."""
    pc = cam_from_target.apply(np.asarray(points_m, dtype=float))
    uv = pc @ np.asarray(K).T
    return uv[:, :2] / uv[:, 2:3]


def bracket_image_points(
    cam_from_target: Rigid3, vertices_m: np.ndarray, K: np.ndarray, fraction: float
) -> np.ndarray:
    """Exact ``(4, 2)`` images of ``P1, P2``, ``P3 = P2 + f (P5 - P2)``, ``P4 = P1 + f (P5 -
    P1)`` for the bracket ``vertices_m`` (rows ``P1, P2, P5``)."""
    v = np.asarray(vertices_m, dtype=float)
    p3 = v[1] + fraction * (v[2] - v[1])
    p4 = v[0] + fraction * (v[2] - v[0])
    return project(cam_from_target, np.array([v[0], v[1], p3, p4]), K)


# --- depth solvers (eq. 9) ------------------------------------------------------------------


def depth_residual(depths: np.ndarray, rays: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """Eq. 9: ``|P_i - P_j| - l_ij`` for ``(P1P2, P1P5, P2P5)``.

    Args:
        depths: ``(..., 3)`` ``d1, d2, d5`` [m].
        rays: ``(..., 3, 3)`` rows ``[k_x, k_y, 1]`` of ``p1, p2, p5``.
        sides: ``(..., 3)`` ``l12, l15, l25`` [m].
    """
    P = depths[..., :, None] * rays
    return triangle_sides(P) - sides


def _depth_jacobian(depths: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual-free part: ``(sides of the reconstructed triangle, d sides / d depths)``."""
    P = depths[..., :, None] * rays
    pairs = ((0, 1), (0, 2), (1, 2))
    lens = []
    J = np.zeros((*depths.shape[:-1], 3, 3))
    for row, (i, j) in enumerate(pairs):
        diff = P[..., i, :] - P[..., j, :]
        n = np.linalg.norm(diff, axis=-1)
        lens.append(n)
        unit = diff / np.maximum(n, 1e-300)[..., None]
        J[..., row, i] = np.sum(unit * rays[..., i, :], axis=-1)
        J[..., row, j] = -np.sum(unit * rays[..., j, :], axis=-1)
    return np.stack(lens, axis=-1), J


def refine_depths(
    depths: np.ndarray, rays: np.ndarray, sides: np.ndarray, iterations: int = 8
) -> np.ndarray:
    """Levenberg-Marquardt on eq. 9 (batched over leading axes), started at ``depths``.

    A square system: at a regular root this is Newton's method (quadratic convergence); the
    damping only matters away from a root (no real P3P solution, the least-squares point).
    """
    d = np.array(depths, dtype=float)
    lam = np.full(d.shape[:-1], 1e-9)
    for _ in range(iterations):
        lens, J = _depth_jacobian(d, rays)
        F = lens - sides
        JtJ = np.swapaxes(J, -1, -2) @ J
        g = np.einsum("...ji,...j->...i", J, F)
        A = JtJ + lam[..., None, None] * np.eye(3) * np.maximum(
            np.trace(JtJ, axis1=-2, axis2=-1)[..., None, None], 1e-12
        )
        step = np.linalg.solve(A, g[..., None])[..., 0]
        d_new = d - step
        F_new = depth_residual(d_new, rays, sides)
        better = np.sum(F_new**2, axis=-1) <= np.sum(F**2, axis=-1)
        d = np.where(better[..., None], d_new, d)
        lam = np.where(better, lam * 0.1, lam * 100.0)
        lam = np.clip(lam, 1e-12, 1e6)
    return d


def quartic_roots(a4: float, a3: float, a2: float, a1: float, a0: float) -> list[complex]:
    """The four complex roots of ``a4 x^4 + ... + a0`` (Ferrari, resolvent cubic by Cardano).

    Pure-Python scalars (a 4x4 companion eigenproblem in numpy costs several times more per
    call); accurate to ~1e-6 relative in bad cases, so callers polish the roots they keep.
    """
    a, b, c, d = a3 / a4, a2 / a4, a1 / a4, a0 / a4
    p = b - 3 * a * a / 8
    q = c - a * b / 2 + a**3 / 8
    r = d - a * c / 4 + a * a * b / 16 - 3 * a**4 / 256
    shift = -a / 4
    if abs(q) < 1e-14:
        disc = cmath.sqrt(p * p - 4 * r)
        out = []
        for z in ((-p + disc) / 2, (-p - disc) / 2):
            sz = cmath.sqrt(z)
            out += [sz + shift, -sz + shift]
        return out
    # Resolvent cubic m^3 + p m^2 + (p^2/4 - r) m - q^2/8 = 0; its largest root is > 0.
    B, C, D = p, p * p / 4 - r, -q * q / 8
    Q = (3 * C - B * B) / 9
    R = (9 * B * C - 27 * D - 2 * B**3) / 54
    disc = cmath.sqrt(Q**3 + R * R)
    S = (R + disc) ** (1 / 3) if R + disc != 0 else (R - disc) ** (1 / 3)
    T = -Q / S if S != 0 else 0j
    w = complex(-0.5, math.sqrt(3) / 2)
    ms = (S + T - B / 3, w * S + w.conjugate() * T - B / 3, w.conjugate() * S + w * T - B / 3)
    m = max(ms, key=lambda z: z.real)
    sm = cmath.sqrt(2 * m)
    out = []
    for s1 in (1, -1):
        inner = cmath.sqrt(-(2 * p + 2 * m + s1 * math.sqrt(2) * q / cmath.sqrt(m)))
        for s2 in (1, -1):
            out.append((s1 * sm + s2 * inner) / 2 + shift)
    return out


def _newton_depths(
    d: list[float],
    r: list[list[float]],
    sides: tuple[float, float, float],
    iterations: int,
    tol: float,
) -> tuple[list[float], float]:
    """Newton on eq. 9 in pure-Python scalars (3x3, Cramer's rule) until the residual norm is
    below ``tol`` [m] (the closed-form roots usually are already); returns depths and the
    residual norm [m]."""
    pairs = ((0, 1), (0, 2), (1, 2))
    d1, d2, d3 = d
    res = math.inf
    for it in range(iterations + 1):
        dd = (d1, d2, d3)
        F = [0.0, 0.0, 0.0]
        E = []
        for row, (i, j) in enumerate(pairs):
            ri, rj = r[i], r[j]
            ex = dd[i] * ri[0] - dd[j] * rj[0]
            ey = dd[i] * ri[1] - dd[j] * rj[1]
            ez = dd[i] * ri[2] - dd[j] * rj[2]
            n = math.sqrt(ex * ex + ey * ey + ez * ez)
            F[row] = n - sides[row]
            E.append((ex, ey, ez, n))
        res = math.sqrt(F[0] ** 2 + F[1] ** 2 + F[2] ** 2)
        if it == iterations or res <= tol:
            break
        J = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        for row, (i, j) in enumerate(pairs):
            ri, rj = r[i], r[j]
            ex, ey, ez, n = E[row]
            if n > 0:
                J[row][i] = (ex * ri[0] + ey * ri[1] + ez * ri[2]) / n
                J[row][j] = -(ex * rj[0] + ey * rj[1] + ez * rj[2]) / n
        (a, b, c), (e, f, g), (h, k, m) = J
        det = a * (f * m - g * k) - b * (e * m - g * h) + c * (e * k - f * h)
        if abs(det) < 1e-300:
            break
        x0 = (F[0] * (f * m - g * k) - b * (F[1] * m - g * F[2]) + c * (F[1] * k - f * F[2])) / det
        x1 = (a * (F[1] * m - g * F[2]) - F[0] * (e * m - g * h) + c * (e * F[2] - F[1] * h)) / det
        x2 = (a * (f * F[2] - F[1] * k) - b * (e * F[2] - F[1] * h) + F[0] * (e * k - f * h)) / det
        d1, d2, d3 = d1 - x0, d2 - x1, d3 - x2
    return [d1, d2, d3], res


def _grunert_coefficients(cos_a: Any, cos_b: Any, cos_g: Any, a2: Any, b2: Any, c2: Any) -> tuple:
    """Grunert's quartic ``A4 v^4 + ... + A0`` in ``v = d5 / d1`` (Haralick et al. 1994, sec.
    2.1) from the rays' cosines and the squared opposite sides; floats or numpy arrays."""
    amc = (a2 - c2) / b2
    apc = (a2 + c2) / b2
    return (
        (amc - 1) ** 2 - 4 * c2 / b2 * cos_a**2,
        4 * (amc * (1 - amc) * cos_b - (1 - apc) * cos_a * cos_g + 2 * c2 / b2 * cos_a**2 * cos_b),
        2
        * (
            amc**2
            - 1
            + 2 * amc**2 * cos_b**2
            + 2 * (b2 - c2) / b2 * cos_a**2
            - 4 * apc * cos_a * cos_b * cos_g
            + 2 * (b2 - a2) / b2 * cos_g**2
        ),
        4 * (-amc * (1 + amc) * cos_b + 2 * a2 / b2 * cos_g**2 * cos_b - (1 - apc) * cos_a * cos_g),
        (1 + amc) ** 2 - 4 * a2 / b2 * cos_g**2,
    )


def _p3p_scalar(r: list[list[float]], sides: tuple[float, float, float]) -> list[list[float]]:
    """`p3p_depths` on Python lists (rows ``[k_x, k_y, 1]``; sides ``l12, l15, l25``)."""
    norms = [math.sqrt(x * x + y * y + z * z) for x, y, z in r]
    j = [[v / n for v in row] for row, n in zip(r, norms, strict=True)]
    # Grunert's notation: points 1, 2, 3 = P1, P2, P5; a, b, c are the sides opposite them.
    lc, lb, la = sides
    cos_a = j[1][0] * j[2][0] + j[1][1] * j[2][1] + j[1][2] * j[2][2]
    cos_b = j[0][0] * j[2][0] + j[0][1] * j[2][1] + j[0][2] * j[2][2]
    cos_g = j[0][0] * j[1][0] + j[0][1] * j[1][1] + j[0][2] * j[1][2]
    a2, b2, c2 = la * la, lb * lb, lc * lc
    A4, A3, A2, A1, A0 = _grunert_coefficients(cos_a, cos_b, cos_g, a2, b2, c2)
    amc = (a2 - c2) / b2
    if abs(A4) < 1e-300:
        return []
    scale = max(sides)
    tol = 1e-7 * scale
    keep: list[list[float]] = []
    for root in quartic_roots(A4, A3, A2, A1, A0):
        # Keep nearly-real roots too: noise can split a double root into a complex pair;
        # Newton below either pulls it onto a true root or it fails the residual check.
        if abs(root.imag) > 1e-3 * max(1.0, abs(root.real)):
            continue
        v = root.real
        den = 2 * (cos_g - v * cos_a)
        q = 1 + v * v - 2 * v * cos_b
        if v <= 0 or abs(den) < 1e-12 or q <= 0:
            continue
        u = ((-1 + amc) * v * v - 2 * amc * cos_b * v + 1 + amc) / den
        if u <= 0:
            continue
        s1 = math.sqrt(b2 / q)
        d0 = [s1 / norms[0], u * s1 / norms[1], v * s1 / norms[2]]
        d, res = _newton_depths(d0, r, sides, 3, 1e-12 * scale)
        if res > tol or min(d) <= 0:
            continue
        if all(math.dist(d, k) > 1e-5 * scale for k in keep):
            keep.append(d)
    return keep


def p3p_depths(rays: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """Every real solution of eq. 9 from Grunert's quartic (Haralick et al. 1994, sec. 2.1).

    Args:
        rays: (3, 3) rows ``[k_x, k_y, 1]`` of ``p1, p2, p5``.
        sides: ``l12, l15, l25`` [m].

    Returns:
        ``(m, 3)`` depths ``d1, d2, d5`` with all depths positive, ``m`` in 0..4, each polished
        by Newton's method to a residual below 1e-12 of the longest side.
    """
    l12, l15, l25 = (float(x) for x in sides)
    keep = _p3p_scalar(np.asarray(rays, dtype=float).tolist(), (l12, l15, l25))
    return np.array(keep, dtype=float).reshape(-1, 3)


def quartic_roots_batch(coeffs: np.ndarray) -> np.ndarray:
    """`quartic_roots` vectorised: ``(N, 5)`` coefficients ``a4 .. a0`` -> ``(N, 4)`` complex
    roots (the same formulas, evaluated with numpy's principal complex roots)."""
    c = np.asarray(coeffs, dtype=complex)
    a, b, cc, d = (c[:, k] / c[:, 0] for k in (1, 2, 3, 4))
    p = b - 3 * a * a / 8
    q = cc - a * b / 2 + a**3 / 8
    r = d - a * cc / 4 + a * a * b / 16 - 3 * a**4 / 256
    shift = -a / 4
    with np.errstate(divide="ignore", invalid="ignore"):
        # biquadratic (q = 0)
        disc2 = np.sqrt(p * p - 4 * r)
        z = np.stack([(-p + disc2) / 2, (-p - disc2) / 2], axis=-1)
        sz = np.sqrt(z)
        biq = np.stack([sz[:, 0], -sz[:, 0], sz[:, 1], -sz[:, 1]], axis=-1) + shift[:, None]
        # resolvent cubic m^3 + p m^2 + (p^2/4 - r) m - q^2/8 = 0 (Cardano), largest real root
        B, C, D = p, p * p / 4 - r, -q * q / 8
        Q = (3 * C - B * B) / 9
        R = (9 * B * C - 27 * D - 2 * B**3) / 54
        disc = np.sqrt(Q**3 + R * R)
        base = np.where(R + disc != 0, R + disc, R - disc)
        S = base ** (1 / 3)
        T = np.where(S != 0, -Q / S, 0)
        w = complex(-0.5, math.sqrt(3) / 2)
        ms = np.stack(
            [S + T - B / 3, w * S + np.conj(w) * T - B / 3, np.conj(w) * S + w * T - B / 3],
            axis=-1,
        )
        m = np.take_along_axis(ms, np.argmax(ms.real, axis=-1)[:, None], axis=-1)[:, 0]
        sm = np.sqrt(2 * m)
        out = []
        for s1 in (1, -1):
            inner = np.sqrt(-(2 * p + 2 * m + s1 * math.sqrt(2) * q / np.sqrt(m)))
            for s2 in (1, -1):
                out.append((s1 * sm + s2 * inner) / 2 + shift)
        gen = np.stack(out, axis=-1)
    return np.where((np.abs(q) < 1e-14)[:, None], biq, gen)


def p3p_depths_batch(rays: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """`p3p_depths` for ``N`` problems at once (numpy): ``rays (N, 3, 3)``, ``sides (3,)`` or
    ``(N, 3)`` -> ``(N, 4, 3)`` depths, NaN rows where a quartic root gives no solution (not
    real, depths not positive, residual too large, or a repeat of an earlier root)."""
    r = np.asarray(rays, dtype=float)
    n = r.shape[0]
    sd = np.broadcast_to(np.asarray(sides, dtype=float), (n, 3))
    norms = np.linalg.norm(r, axis=-1)  # (N, 3)
    j = r / norms[..., None]
    cos_a = np.sum(j[:, 1] * j[:, 2], axis=-1)
    cos_b = np.sum(j[:, 0] * j[:, 2], axis=-1)
    cos_g = np.sum(j[:, 0] * j[:, 1], axis=-1)
    lc, lb, la = sd[:, 0], sd[:, 1], sd[:, 2]
    a2, b2, c2 = la * la, lb * lb, lc * lc
    A = np.stack(_grunert_coefficients(cos_a, cos_b, cos_g, a2, b2, c2), axis=-1)
    amc = (a2 - c2) / b2
    ok_quartic = np.abs(A[:, 0]) >= 1e-300
    A = np.where(ok_quartic[:, None], A, 1.0)
    roots = quartic_roots_batch(A)  # (N, 4)
    v = roots.real
    ok = ok_quartic[:, None] & (np.abs(roots.imag) <= 1e-3 * np.maximum(1.0, np.abs(v)))
    with np.errstate(divide="ignore", invalid="ignore"):
        den = 2 * (cos_g[:, None] - v * cos_a[:, None])
        q = 1 + v * v - 2 * v * cos_b[:, None]
        u = ((-1 + amc[:, None]) * v * v - 2 * (amc * cos_b)[:, None] * v + 1 + amc[:, None]) / den
        s1 = np.sqrt(b2[:, None] / q)
    ok &= (v > 0) & (np.abs(den) >= 1e-12) & (q > 0) & (u > 0)
    d0 = np.stack([s1 / norms[:, :1], u * s1 / norms[:, 1:2], v * s1 / norms[:, 2:3]], axis=-1)
    d0 = np.where(ok[..., None], d0, 1.0)
    rr = np.broadcast_to(r[:, None], (n, 4, 3, 3))
    ss = np.broadcast_to(sd[:, None], (n, 4, 3))
    d = d0
    for _ in range(3):  # Newton (3x3); the closed-form roots are already close
        lens, J = _depth_jacobian(d, rr)
        F = lens - ss
        det_ok = np.abs(np.linalg.det(J)) > 1e-300
        Js = np.where(det_ok[..., None, None], J, np.eye(3))
        d = np.where(det_ok[..., None], d - np.linalg.solve(Js, F[..., None])[..., 0], d)
    res = np.linalg.norm(depth_residual(d, rr, ss), axis=-1)
    scale = sd.max(axis=-1)[:, None]
    ok &= (res <= 1e-7 * scale) & (d.min(axis=-1) > 0)
    for k in range(1, 4):  # repeats of an earlier kept root (a split double root)
        for i in range(k):
            same = ok[:, i] & (np.linalg.norm(d[:, k] - d[:, i], axis=-1) <= 1e-5 * scale[:, 0])
            ok[:, k] &= ~same
    return np.where(ok[..., None], d, np.nan)


def depth_candidates_batch(
    points_px: np.ndarray, K: np.ndarray, sides: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The closed-form depth solve and the multiple-solution check of `solve_bracket` for ``N``
    frames at once (numpy; no least-squares fallback: a frame without a real solution has no
    candidate).

    Args:
        points_px: ``(N, 4, 2)`` rows ``p1, p2, p3, p4``.
        K: 3x3 intrinsics; sides: ``l12, l15, l25`` (3,) [m].

    Returns:
        ``(N, 4, 3)`` admissible depths (NaN rows otherwise) and ``(N, 4, 2)`` where the strut
        ends fall on the reconstructed struts ``P1P5``, ``P2P5`` (fractions).
    """
    pts = np.asarray(points_px, dtype=float)
    p5, _ = strut_apex(pts)
    img = np.stack([pts[:, 0], pts[:, 1], p5], axis=1)
    rays = _homog(img) @ np.linalg.inv(K).T
    rays = rays / rays[..., 2:3]
    cands = p3p_depths_batch(rays, sides)  # (N, 4, 3)
    u4, u3 = p5 - pts[:, 0], p5 - pts[:, 1]
    lam4 = (np.sum((pts[:, 3] - pts[:, 0]) * u4, axis=-1) / np.sum(u4 * u4, axis=-1))[:, None]
    lam3 = (np.sum((pts[:, 2] - pts[:, 1]) * u3, axis=-1) / np.sum(u3 * u3, axis=-1))[:, None]
    d1, d2, d5 = cands[..., 0], cands[..., 1], cands[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        fr = np.stack(
            [lam4 * d1 / (lam4 * d1 + (1 - lam4) * d5), lam3 * d2 / (lam3 * d2 + (1 - lam3) * d5)],
            axis=-1,
        )
    ok = np.isfinite(d1) & np.all((fr > 0) & (fr < 1), axis=-1)
    return np.where(ok[..., None], cands, np.nan), np.where(ok[..., None], fr, np.nan)


def choose_depths(
    cands: np.ndarray,
    fractions: np.ndarray,
    prior_depths: np.ndarray | None = None,
    visible_fraction: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`solve_bracket`'s choice among admissible candidates, for ``N`` frames at once: the one
    nearest the prior (rows of ``prior_depths`` that are NaN: no prior), else the one whose
    strut ends are nearest ``visible_fraction``, else the first.

    Args:
        cands, fractions: from `depth_candidates_batch`.
        prior_depths: ``(N, 3)`` or None.

    Returns:
        ``(N, 3)`` depths (NaN where no admissible candidate) and ``(N,)`` admissible counts.
    """
    ok = np.isfinite(cands[..., 0])
    n = ok.shape[0]
    has_prior = np.zeros(n, bool)
    score = np.zeros(ok.shape)
    if prior_depths is not None:
        prior = np.asarray(prior_depths, dtype=float)
        has_prior = np.isfinite(prior[:, 0])
        dist = np.linalg.norm(cands - prior[:, None, :], axis=-1)
        score = np.where(has_prior[:, None], dist, 0.0)
    if visible_fraction is not None:
        frac = np.sum(np.abs(fractions - visible_fraction), axis=-1)
        score = np.where(has_prior[:, None], score, frac)
    best = np.argmin(np.where(ok, score, np.inf), axis=-1)
    count = ok.sum(axis=-1)
    depths = cands[np.arange(n), best]
    return np.where((count > 0)[:, None], depths, np.nan), count


def ant_colony_depths(
    rays: np.ndarray,
    sides: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    config: AntColonyConfig,
    rng: np.random.Generator,
    ants: int | None = None,
) -> tuple[np.ndarray, float]:
    """The paper's ant-colony search for eq. 9 (sec. 3.3; rules reconstructed, docs/bracket.md).

    Cost (eq. 10): ``F = sum f_i^2`` in mm^2 (the paper's units). Pheromone starts at
    ``tau = exp(-F)`` (eq. 11). Each iteration ``N``: the best ant makes a local move of step
    ``omega / N`` (eq. 12); every other ant ``k`` moves locally (step ``omega / N``) when its
    transition probability ``P(k) = (tau_best^alpha - tau_k^alpha) / tau_best^alpha`` is below
    ``p0`` and jumps globally (uniform over the interval width) otherwise; an ant keeps a move
    only if it shortens its path (lowers ``F``); moves are clipped to the interval; the
    pheromone is updated ``tau = (1 - rho) tau + Q exp(-F)`` (ant-cycle). Computed in the log
    domain (``exp(-F)`` underflows for ``F > 745 mm^2``).

    Args:
        ants: colony size (``config.ants`` if None).

    Returns:
        The best depths (3,) [m] and its cost [mm^2].
    """
    low = np.asarray(low, dtype=float)
    high = np.asarray(high, dtype=float)
    width = high - low
    omega = config.step_fraction * width

    def cost(x: np.ndarray) -> np.ndarray:
        f = depth_residual(x, rays, sides) * 1e3  # mm
        return np.sum(f * f, axis=-1)

    k = config.ants if ants is None else ants
    X = low + width * rng.random((k, 3))
    F = cost(X)
    # log tau; tau = exp(-F) (eq. 11)
    log_tau = -F
    for n in range(1, config.iterations + 1):
        b = int(np.argmin(F))
        if F[b] < config.stop_cost_mm2:
            break
        log_tau_best = log_tau[b]
        # P(k) = 1 - (tau_k / tau_best)^alpha, in the log domain
        P = -np.expm1(config.alpha * np.minimum(log_tau - log_tau_best, 0.0))
        local = P < config.p0
        local[b] = True
        r = rng.random((k, 3))
        step_local = omega * (2 * r - 1) / n
        step_global = width * (r - 0.5)
        cand = X + np.where(local[:, None], step_local, step_global)
        cand = np.clip(cand, low, high)
        Fc = cost(cand)
        better = Fc < F
        X = np.where(better[:, None], cand, X)
        F = np.where(better, Fc, F)
        # tau = (1 - rho) tau + Q exp(-F): log-sum-exp of the two terms
        fresh = math.log(config.pheromone_q) - F
        if config.rho >= 1.0:
            log_tau = fresh
        else:
            keep = math.log1p(-config.rho) + log_tau
            log_tau = np.logaddexp(keep, fresh)
    b = int(np.argmin(F))
    return X[b].copy(), float(F[b])


def _pose_from_inputs(
    points_px: np.ndarray, vertices: np.ndarray, K_inv: np.ndarray, depths0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched pipeline for covariance propagation: pixels + vertices -> (R, t, depths), with
    the depths polished by Newton from ``depths0`` (the solution at the nominal inputs)."""
    p5, _ = strut_apex(points_px)
    img = np.stack([points_px[..., 0, :], points_px[..., 1, :], p5], axis=-2)
    rays = _homog(img) @ K_inv.T
    rays = rays / rays[..., 2:3]
    sides = triangle_sides(vertices)
    d = refine_depths(np.broadcast_to(depths0, sides.shape).copy(), rays, sides, 4)
    cam = d[..., :, None] * rays
    cam4 = np.concatenate([cam, incentre(cam)[..., None, :]], axis=-2)
    mod4 = np.concatenate([vertices, incentre(vertices)[..., None, :]], axis=-2)
    R, t = absolute_orientation(mod4, cam4)
    return R, t, d


def pose_covariance(
    points_px: np.ndarray,
    geometry: BracketGeometry,
    K: np.ndarray,
    depths: np.ndarray,
    sigma_px: float,
    step_px: float = 1e-3,
    step_m: float = 1e-6,
) -> np.ndarray:
    """6x6 covariance ``[rotation, translation]`` (right perturbation) of the pose from the
    pixel noise (``sigma_px`` on each of the 8 coordinates) and the vertex error
    (``geometry.vertex_sigma_m`` on each of the 9 coordinates), by central differences of the
    whole solver (batched: 34 evaluations in one call)."""
    x0 = np.concatenate([np.asarray(points_px, float).ravel(), geometry.vertices_m.ravel()])
    steps = np.concatenate([np.full(8, step_px), np.full(9, step_m)])
    X = np.repeat(x0[None, :], 35, axis=0)
    idx = np.arange(17)
    X[1 + idx, idx] += steps
    X[18 + idx, idx] -= steps
    R, t, _ = _pose_from_inputs(
        X[:, :8].reshape(-1, 4, 2), X[:, 8:].reshape(-1, 3, 3), np.linalg.inv(K), depths
    )
    R0, t0 = R[0], t[0]
    dR = np.einsum("ji,njk->nik", R0, R)  # R0^T R
    rot = matrix_to_rotvec(dR)
    trans = (t - t0) @ R0  # R0^T (t - t0)
    xi = np.concatenate([rot, trans], axis=1)
    J = ((xi[1:18] - xi[18:35]) / (2 * steps[:, None])).T  # (6, 17)
    var = np.concatenate([np.full(8, sigma_px**2), np.full(9, geometry.vertex_sigma_m**2)])
    C = (J * var) @ J.T
    return 0.5 * (C + C.T)


def pose_information_bound(
    cam_from_target: Rigid3,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    sigma_px: float,
    known_ends: bool = False,
    step: float = 1e-6,
) -> np.ndarray:
    """Cramer-Rao bound of the pose from one image of the bracket.

    The measurements are the four image points ``p1, p2, p3, p4`` with white noise
    ``sigma_px``; the unknowns are the pose, the vertices (a Gaussian prior of standard
    deviation ``geometry.vertex_sigma_m`` per coordinate about the nominal ones, omitted when
    zero) and, unless ``known_ends``, where ``p3``, ``p4`` lie along their struts (a real image
    does not tell: the paper's information). With ``known_ends`` the strut ends are model
    points at ``fraction`` (more than the paper uses). No unbiased per-frame estimator on these
    measurements has a smaller covariance; the pose is exactly determined by the paper's
    information, so there the bound equals the first-order covariance of our solver.

    Args:
        cam_from_target: the true ``left_cam_from_target``.
        geometry: nominal vertices and their error.
        K: 3x3 intrinsics; fraction: where the strut ends are (``P1 + fraction (P5 - P1)``).
        sigma_px: image noise per coordinate [px].
        known_ends: treat the strut ends as known model points.
        step: central-difference step of every parameter [rad, m, 1].

    Returns:
        6x6 bound over ``[rotation (rad), translation (m)]`` with the rotation error as a
        camera-frame rotation vector (``R_est = Exp(e) R_true``) and the translation error as
        ``t_est - t_true`` (camera frame).
    """
    use_vertices = geometry.vertex_sigma_m > 0
    n = 6 + (0 if known_ends else 2) + (9 if use_vertices else 0)
    R0 = cam_from_target.R
    t0 = cam_from_target.t
    v0 = geometry.vertices_m

    def h(theta: np.ndarray) -> np.ndarray:  # (m, n) -> (m, 8)
        m = theta.shape[0]
        R = np.einsum("mij,jk->mik", rotvec_to_matrix(theta[:, :3]), R0)
        t = t0 + theta[:, 3:6]
        s = np.full((m, 2), fraction) if known_ends else fraction + theta[:, 6:8]
        v = v0 + (theta[:, -9:].reshape(m, 3, 3) if use_vertices else np.zeros((m, 3, 3)))
        P3 = v[:, 1] + s[:, :1] * (v[:, 2] - v[:, 1])
        P4 = v[:, 0] + s[:, 1:] * (v[:, 2] - v[:, 0])
        P = np.stack([v[:, 0], v[:, 1], P3, P4], axis=1)  # (m, 4, 3)
        pc = np.einsum("mij,mkj->mki", R, P) + t[:, None, :]
        uv = pc @ np.asarray(K, dtype=float).T
        return (uv[..., :2] / uv[..., 2:3]).reshape(m, 8)

    E = np.eye(n) * step
    H = ((h(E) - h(-E)) / (2 * step)).T  # (8, n)
    J = H.T @ H / sigma_px**2
    if use_vertices:
        J[-9:, -9:] += np.eye(9) / geometry.vertex_sigma_m**2
    C = np.linalg.inv(J)[:6, :6]
    return 0.5 * (C + C.T)


def solve_bracket(
    observation: BracketObservation,
    geometry: BracketGeometry,
    K: np.ndarray,
    config: BracketConfig | None = None,
    prior_depths: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> BracketResult:
    """``left_cam_from_target`` from one image of the bracket (paper sec. 3).

    Args:
        observation: image points (undistorted pixels).
        geometry: the bracket's model.
        K: 3x3 intrinsics of the undistorted image.
        config: solver settings.
        prior_depths: ``d1, d2, d5`` of the previous frame [m]: picks among P3P solutions and
            centres the ant colony's interval.
        rng: random generator of the ant colony (seeded default).

    Returns:
        A `BracketResult`; ``pose`` is None with a ``reason`` when the frame cannot be solved
        (missing points, bracket edge-on, points behind the camera, no admissible solution).
    """
    cfg = BracketConfig() if config is None else config
    missing = observation.missing()
    if missing:
        return BracketResult(
            pose=None,
            reason=f"need p1, p2 and a point on each of the struts P1P5, P2P5; missing: "
            f"{', '.join(missing)}",
        )
    pts = observation.points()
    if min(np.linalg.norm(pts[0] - pts[3]), np.linalg.norm(pts[1] - pts[2])) < 1.0:
        return BracketResult(pose=None, reason="a strut segment is shorter than 1 px")
    p5, angle = strut_apex(pts)
    if not (math.degrees(float(angle)) >= cfg.min_strut_angle_deg and np.all(np.isfinite(p5))):
        return BracketResult(
            pose=None,
            reason=f"bracket edge-on: the strut lines meet at {math.degrees(float(angle)):.2f}"
            f" deg < {cfg.min_strut_angle_deg} deg, the apex P5 is ill-defined",
        )
    K_inv = np.linalg.inv(K)
    img = np.array([pts[0], pts[1], p5])
    rays = _homog(img) @ K_inv.T
    rays = rays / rays[:, 2:3]
    sides = geometry.sides_m
    c0 = time.process_time()
    if cfg.solver == "closed-form":
        # Where the strut ends lie on the image lines p1 -> p5 and p2 -> p5 (p5 is their
        # intersection, so p4 and p3 are on them exactly).
        (x1, y1), (x2, y2), (x3, y3), (x4, y4) = pts.tolist()
        x5, y5 = p5.tolist()
        lam4 = ((x4 - x1) * (x5 - x1) + (y4 - y1) * (y5 - y1)) / ((x5 - x1) ** 2 + (y5 - y1) ** 2)
        lam3 = ((x3 - x2) * (x5 - x2) + (y3 - y2) * (y5 - y2)) / ((x5 - x2) ** 2 + (y5 - y2) ** 2)
        l12, l15, l25 = sides.tolist()
        cands = _p3p_scalar(rays.tolist(), (l12, l15, l25))
        selected_by = "unique"
        if not cands:
            # No exact solution (noise at a degenerate view): least squares from the prior or
            # from a fronto-parallel guess at the scale of the side P1P2.
            start = (
                np.asarray(prior_depths, float)
                if prior_depths is not None
                else np.full(3, sides[0] / max(np.linalg.norm(rays[0] - rays[1]), 1e-9))
            )
            cands = refine_depths(start[None, :], rays[None], sides[None], 30).tolist()
            selected_by = "least-squares"
        # Multiple-solution check. Admissible: positive depths and the visible strut ends on
        # the reconstructed struts. The point P1 + s (P5 - P1) projects to the fraction
        # lam = s d5 / ((1 - s) d1 + s d5) of the image segment p1 -> p5, so
        # s = lam d1 / (lam d1 + (1 - lam) d5) (and likewise for P2P5).
        fr = []
        for d1, d2, d5 in cands:
            s4 = lam4 * d1 / (lam4 * d1 + (1 - lam4) * d5)
            s3 = lam3 * d2 / (lam3 * d2 + (1 - lam3) * d5)
            ok = min(d1, d2, d5) > 0 and 0 < s4 < 1 and 0 < s3 < 1
            fr.append((s4, s3) if ok else None)
        admissible = [(c, f) for c, f in zip(cands, fr, strict=True) if f is not None]
        ls_index = None
        if prior_depths is not None and cfg.prior_least_squares:
            q_arr = np.asarray(prior_depths, dtype=float)
            d_ls = refine_depths(q_arr[None], rays[None], sides[None], 30)[0]
            s4 = lam4 * d_ls[0] / (lam4 * d_ls[0] + (1 - lam4) * d_ls[2])
            s3 = lam3 * d_ls[1] / (lam3 * d_ls[1] + (1 - lam3) * d_ls[2])
            res_ls = float(np.linalg.norm(depth_residual(d_ls, rays, sides)))
            if d_ls.min() > 0 and 0 < s4 < 1 and 0 < s3 < 1 and res_ls <= cfg.max_depth_cost_m:
                admissible.append((d_ls.tolist(), (s4, s3)))
                ls_index = len(admissible) - 1
        solve_s = time.process_time() - c0
        if not admissible:
            return BracketResult(
                pose=None,
                candidates=0,
                reason="no admissible depth solution: the strut ends do not fall on the struts",
                solve_cpu_s=solve_s,
            )
        n_cand = len(admissible)
        if n_cand == 1:
            best = 0
        elif prior_depths is not None:
            q = [float(x) for x in prior_depths]
            best = min(range(n_cand), key=lambda i: math.dist(admissible[i][0], q))
            selected_by = "prior"
        elif geometry.visible_fraction is not None:
            vf = geometry.visible_fraction
            best = min(
                range(n_cand),
                key=lambda i: abs(admissible[i][1][0] - vf) + abs(admissible[i][1][1] - vf),
            )
            selected_by = "fraction"
        else:
            best = 0
            selected_by = "first"
        if ls_index is not None:
            best, selected_by = ls_index, "prior-least-squares"
        d = np.array(admissible[best][0])
    else:
        generator = np.random.default_rng(0) if rng is None else rng
        if prior_depths is None:
            low = np.full(3, cfg.ant.first_interval_m[0])
            high = np.full(3, cfg.ant.first_interval_m[1])
        else:
            prior = np.asarray(prior_depths, dtype=float)
            half = np.maximum(cfg.ant.track_half_width_m, cfg.ant.track_half_width_fraction * prior)
            low = np.maximum(prior - half, 1e-3)
            high = prior + half
        ants = cfg.ant.first_ants if prior_depths is None else cfg.ant.ants
        d, _ = ant_colony_depths(rays, sides, low, high, cfg.ant, generator, ants)
        solve_s = time.process_time() - c0
        n_cand, selected_by = 1, "search"
    cost = float(np.linalg.norm(depth_residual(d, rays, sides)))
    if not cost <= cfg.max_depth_cost_m or d.min() <= 0:
        return BracketResult(
            pose=None,
            depths_m=d,
            apex_px=p5,
            candidates=n_cand,
            reason=f"eq. 9 not satisfied: residual {cost * 1e3:.1f} mm",
            solve_cpu_s=solve_s,
        )
    cam = d[:, None] * rays
    cam4 = np.vstack([cam, incentre(cam)])
    mod4 = np.vstack([geometry.vertices_m, incentre(geometry.vertices_m)])
    R, t = absolute_orientation(mod4, cam4)
    cov = pose_covariance(pts, geometry, K, d, observation.sigma_px) if cfg.covariance else None
    return BracketResult(
        pose=Rigid3(R=R, t=t),
        covariance=cov,
        depths_m=d,
        apex_px=p5,
        candidates=n_cand,
        selected_by=selected_by,
        depth_cost_m=cost,
        solve_cpu_s=solve_s,
    )


def simulate_observation(
    cam_from_target: Rigid3,
    true_vertices_m: np.ndarray,
    K: np.ndarray,
    fraction: float,
    sigma_px: float,
    rng: np.random.Generator,
) -> BracketObservation:
    """Project the (true, possibly deformed) bracket and add white pixel noise to ``p1..p4``."""
    pts = bracket_image_points(cam_from_target, true_vertices_m, K, fraction)
    pts = pts + sigma_px * rng.standard_normal(pts.shape)
    return BracketObservation(
        p1_px=pts[0], p2_px=pts[1], p3_px=pts[2], p4_px=pts[3], sigma_px=sigma_px
    )


def to_frame_measurements(result: BracketResult, frame: int, t_s: float) -> FrameMeasurements:
    """A `FrameMeasurements` carrying the bracket pose (or the failure reason) for the backend."""
    if result.pose is None or result.covariance is None:
        return FrameMeasurements(
            frame=frame, t_s=t_s, failures=(f"bracket: {result.reason or 'no covariance'}",)
        )
    try:
        pose = PoseMeasurement(
            left_cam_from_target=result.pose,
            covariance=result.covariance,
            method=PoseMethod.BRACKET,
        )
    except MeasurementError as exc:  # e.g. a singular covariance at a degenerate view
        return FrameMeasurements(frame=frame, t_s=t_s, failures=(f"bracket: {exc}",))
    return FrameMeasurements(frame=frame, t_s=t_s, pose=pose)
