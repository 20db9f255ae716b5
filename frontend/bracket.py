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
from typing import Literal

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
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
        ant: ant-colony settings.
    """

    solver: Literal["closed-form", "ant-colony"] = "closed-form"
    min_strut_angle_deg: float = 2.0
    max_depth_cost_m: float = 0.05
    covariance: bool = True
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
    d: list[float], r: list[list[float]], sides: tuple[float, float, float], iterations: int
) -> tuple[list[float], float]:
    """Newton on eq. 9 in pure-Python scalars (3x3, Cramer's rule); returns depths and the
    residual norm [m]."""
    pairs = ((0, 1), (0, 2), (1, 2))
    d1, d2, d3 = d
    res = math.inf
    for it in range(iterations + 1):
        dd = (d1, d2, d3)
        F = [0.0, 0.0, 0.0]
        J = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        for row, (i, j) in enumerate(pairs):
            ri, rj = r[i], r[j]
            ex = dd[i] * ri[0] - dd[j] * rj[0]
            ey = dd[i] * ri[1] - dd[j] * rj[1]
            ez = dd[i] * ri[2] - dd[j] * rj[2]
            n = math.sqrt(ex * ex + ey * ey + ez * ez)
            F[row] = n - sides[row]
            if n > 0:
                J[row][i] = (ex * ri[0] + ey * ri[1] + ez * ri[2]) / n
                J[row][j] = -(ex * rj[0] + ey * rj[1] + ez * rj[2]) / n
        res = math.sqrt(F[0] ** 2 + F[1] ** 2 + F[2] ** 2)
        if it == iterations:
            break
        (a, b, c), (e, f, g), (h, k, m) = J
        det = a * (f * m - g * k) - b * (e * m - g * h) + c * (e * k - f * h)
        if abs(det) < 1e-300:
            break
        x0 = (F[0] * (f * m - g * k) - b * (F[1] * m - g * F[2]) + c * (F[1] * k - f * F[2])) / det
        x1 = (a * (F[1] * m - g * F[2]) - F[0] * (e * m - g * h) + c * (e * F[2] - F[1] * h)) / det
        x2 = (a * (f * F[2] - F[1] * k) - b * (e * F[2] - F[1] * h) + F[0] * (e * k - f * h)) / det
        d1, d2, d3 = d1 - x0, d2 - x1, d3 - x2
    return [d1, d2, d3], res


def p3p_depths(rays: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """Every real solution of eq. 9 from Grunert's quartic (Haralick et al. 1994, sec. 2.1).

    Args:
        rays: (3, 3) rows ``[k_x, k_y, 1]`` of ``p1, p2, p5``.
        sides: ``l12, l15, l25`` [m].

    Returns:
        ``(m, 3)`` depths ``d1, d2, d5`` with all depths positive, ``m`` in 0..4, each polished
        by Newton's method.
    """
    r = rays.tolist()
    norms = [math.sqrt(x * x + y * y + z * z) for x, y, z in r]
    j = [[v / n for v in row] for row, n in zip(r, norms, strict=True)]
    # Grunert's notation: points 1, 2, 3 = P1, P2, P5; a, b, c are the sides opposite them.
    lc, lb, la = (float(x) for x in sides)
    side_t = (lc, lb, la)
    cos_a = j[1][0] * j[2][0] + j[1][1] * j[2][1] + j[1][2] * j[2][2]
    cos_b = j[0][0] * j[2][0] + j[0][1] * j[2][1] + j[0][2] * j[2][2]
    cos_g = j[0][0] * j[1][0] + j[0][1] * j[1][1] + j[0][2] * j[1][2]
    a2, b2, c2 = la * la, lb * lb, lc * lc
    amc = (a2 - c2) / b2
    apc = (a2 + c2) / b2
    A4 = (amc - 1) ** 2 - 4 * c2 / b2 * cos_a**2
    A3 = 4 * (amc * (1 - amc) * cos_b - (1 - apc) * cos_a * cos_g + 2 * c2 / b2 * cos_a**2 * cos_b)
    A2 = 2 * (
        amc**2
        - 1
        + 2 * amc**2 * cos_b**2
        + 2 * (b2 - c2) / b2 * cos_a**2
        - 4 * apc * cos_a * cos_b * cos_g
        + 2 * (b2 - a2) / b2 * cos_g**2
    )
    A1 = 4 * (-amc * (1 + amc) * cos_b + 2 * a2 / b2 * cos_g**2 * cos_b - (1 - apc) * cos_a * cos_g)
    A0 = (1 + amc) ** 2 - 4 * a2 / b2 * cos_g**2
    if abs(A4) < 1e-300:
        return np.zeros((0, 3))
    tol = 1e-7 * max(side_t)
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
        d, res = _newton_depths(d0, r, side_t, 2)
        if res > tol or min(d) <= 0:
            continue
        if all(math.dist(d, k) > 1e-5 * max(side_t) for k in keep):
            keep.append(d)
    return np.array(keep, dtype=float).reshape(-1, 3)


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


# --- absolute orientation -------------------------------------------------------------------


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


def _strut_fractions(depths: np.ndarray, rays: np.ndarray, ends: np.ndarray) -> list[float]:
    """Where the rays of the strut ends ``p4`` and ``p3`` meet the reconstructed struts ``P1P5``
    and ``P2P5`` (fraction from ``P1`` / ``P2``; -1 when the meeting point is behind the camera).

    Args:
        depths: ``d1, d2, d5``; rays: (3, 3) rows ``[k_x, k_y, 1]`` of ``p1, p2, p5``;
        ends: (2, 3) normalised rays of ``p4`` and ``p3``.
    """
    d = depths.tolist()
    r = rays.tolist()
    P = [[d[i] * c for c in r[i]] for i in range(3)]
    out = []
    for start, w in ((0, ends[0].tolist()), (1, ends[1].tolist())):
        # Closest points of the ray lam * w and the line P_s + s (P5 - P_s): 2x2 normal equations.
        e = [P[2][k] - P[start][k] for k in range(3)]
        o = P[start]
        ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        we = w[0] * e[0] + w[1] * e[1] + w[2] * e[2]
        ee = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
        wo = w[0] * o[0] + w[1] * o[1] + w[2] * o[2]
        eo = e[0] * o[0] + e[1] * o[1] + e[2] * o[2]
        det = ww * ee - we * we
        if abs(det) < 1e-300:
            out.append(-1.0)
            continue
        lam = (wo * ee - we * eo) / det
        frac = (wo * we - ww * eo) / det
        out.append(frac if lam > 0 else -1.0)
    return out


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
        ends = _homog(pts[[3, 2]]) @ K_inv.T
        cands = p3p_depths(rays, sides)
        selected_by = "unique"
        if len(cands) == 0:
            # No exact solution (noise at a degenerate view): least squares from the prior or
            # from a fronto-parallel guess at the scale of the side P1P2.
            start = (
                np.asarray(prior_depths, float)
                if prior_depths is not None
                else np.full(3, sides[0] / max(np.linalg.norm(rays[0] - rays[1]), 1e-9))
            )
            cands = refine_depths(start[None, :], rays[None], sides[None], 30)
            selected_by = "least-squares"
        # Multiple-solution check. Admissible: the visible strut ends lie on the reconstructed
        # struts (0 < fraction < 1).
        fr = np.array([_strut_fractions(d, rays, ends) for d in cands]).reshape(-1, 2)
        ok = np.all((fr > 0) & (fr < 1), axis=1) & (cands.min(axis=1) > 0)
        solve_s = time.process_time() - c0
        if not np.any(ok):
            return BracketResult(
                pose=None,
                candidates=0,
                reason="no admissible depth solution: the strut ends do not fall on the struts",
                solve_cpu_s=solve_s,
            )
        cands, fr = cands[ok], fr[ok]
        n_cand = len(cands)
        if n_cand == 1:
            best = 0
        elif prior_depths is not None:
            rel = np.linalg.norm(cands - prior_depths, axis=1)
            best = int(np.argmin(rel))
            selected_by = "prior"
        elif geometry.visible_fraction is not None:
            best = int(np.argmin(np.abs(fr - geometry.visible_fraction).sum(axis=1)))
            selected_by = "fraction"
        else:
            best = 0
            selected_by = "first"
        d = cands[best]
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
