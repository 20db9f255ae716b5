"""The ring's outline as a cylinder: front rim and base, fitted together (stereo generalisation).

A docking or launch-adapter ring is a cylindrical wall of outer radius ``r`` whose front rim
is a circle (centre ``c``, unit normal ``n`` toward the cameras) and whose base is the same
circle moved back by the wall height: ``c - h n``. The solid cylinder between them is the convex
hull of its two end discs, and a central projection maps a convex set in front of the camera to
the convex hull of the images of its extreme points. So the ring's image outline is exactly the
convex hull of the rim's ellipse and the base's ellipse: the rim's arc where the wall's outer
face is turned away from the camera, the base's arc where it is seen beside the rim, and the
two silhouette lines, tangent to both ellipses, between them. The silhouettes are different
generator lines in each camera; the model places them in each camera from the one 3-D cylinder,
so it needs no per-camera fudge.

The strongest edges near a ring against its panel or against space are usually that outline
(the ring against what is behind it), and an ellipse fitted to them is the outline's best
ellipse, not the rim's: outward by up to the wall's projected width on the side where the wall
shows, a centre error of pixels and a depth and lateral bias of centimetres. `fit_ring_outline`
fits ``(c, n, r, h)`` to both cameras' edge points by the points' signed distances to the hull
of the two projected circles, robustly (Huber weights, the scale from the residuals' MAD),
from several starting heights, with ``h >= 0``. Where the edges follow the rim on the visible
side instead (the crease between the rim's face and the wall), the fit finds ``h = 0`` and is
the plain circle fit. The wall height needs no prior (non-cooperative); a known one
(``known ring``) can be stated as one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from satpose.datasets.geometry import Rigid3
from satpose.frontend.measurements import Camera
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_covariance,
    tangent_basis,
)


@dataclass(frozen=True, kw_only=True)
class OutlineConfig:
    """The ring's outline fitted as a cylinder (`fit_ring_outline`).

    Attributes:
        enabled: fit the outline model to the ring's edge points (False: the ring is the
            circle of all edge points near the ring's ellipse).
        samples: at most this many points per circle of the projected rim and base span the
            hull (one per ~3 px of the rim's image, at least 48).
        height_starts: starting wall heights, in ring radii; the fit with the smallest robust
            cost wins.
        max_height: the wall height's upper bound, in ring radii.
        iterations: at most this many Gauss-Newton iterations per start.
        tolerance_px: a start has converged when its last full step moved no point's predicted
            distance by more than this.
        huber_k: Huber threshold in robust standard deviations.
    """

    enabled: bool = False
    samples: int = 360
    height_starts: tuple[float, ...] = (0.0, 0.25)
    max_height: float = 1.0
    iterations: int = 10
    tolerance_px: float = 0.002
    huber_k: float = 1.5

    def __post_init__(self) -> None:
        if self.samples < 24:
            raise ValueError(f"ring outline: samples must be >= 24, got {self.samples}")
        if not self.height_starts or min(self.height_starts) < 0:
            raise ValueError("ring outline: height_starts must be non-empty and >= 0")
        if not (
            self.max_height > 0
            and self.iterations >= 1
            and self.huber_k > 0
            and self.tolerance_px > 0
        ):
            raise ValueError(
                "ring outline: max_height > 0, iterations >= 1, huber_k > 0, tolerance_px > 0"
            )


@dataclass(frozen=True)
class OutlineFit:
    """The front rim and wall height fitted to the ring's outline.

    Attributes:
        circle: the front rim (left camera frame), covariance marginalised over the height.
        height_m: the wall height, and ``height_sigma_m`` its 1-sigma.
        rim_points: per camera (left, right) the edge points on the outline's rim arc.
        rms_px: robust RMS distance of the points to the outline.
        cost: the robust cost that chose among the starts.
    """

    circle: Circle3D
    height_m: float
    height_sigma_m: float
    rim_points: tuple[np.ndarray, np.ndarray]
    rms_px: float
    cost: float


def _project(K: np.ndarray, T: Rigid3, X: np.ndarray) -> np.ndarray:
    Y = X @ T.R.T + T.t
    if np.any(Y[:, 2] <= 1e-6):
        raise GeometryFailure("the ring outline reaches behind the camera")
    p = Y @ K.T
    return p[:, :2] / p[:, 2:]


def _samples(c: np.ndarray, n: np.ndarray, r: float, h: float, samples: int) -> np.ndarray:
    """``samples`` points of the rim, then as many of the base (2 * samples, 3)."""
    u, v = tangent_basis(n)
    phi = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
    ring = r * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    return np.vstack([c + ring, c - h * n + ring])


def outline_hull(
    K: np.ndarray,
    T: Rigid3,
    center: np.ndarray,
    normal: np.ndarray,
    radius: float,
    height: float,
    samples: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The image outline of the cylinder: hull vertices (M, 2) in counter-clockwise order of
    angle about their mean, and per vertex whether it lies on the base (else on the rim)."""
    px = _project(K, T, _samples(center, normal, radius, height, samples))
    idx = _hull_indices(px)
    return px[idx], idx >= samples


def _hull_indices(px: np.ndarray) -> np.ndarray:
    """Indices of the convex hull's vertices of ``px``, ordered by angle about their mean."""
    idx = cv2.convexHull(px.astype(np.float32), returnPoints=False)
    if idx is None or len(idx) < 3:
        raise GeometryFailure("the ring outline is degenerate (ring seen edge-on)")
    idx = idx.ravel()
    hull = px[idx]
    o = hull.mean(axis=0)
    return idx[np.argsort(np.arctan2(hull[:, 1] - o[1], hull[:, 0] - o[0]))]


def _segments(points: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """Per point, the index ``k`` of the hull segment ``hull[k] -> hull[k + 1]`` that the ray
    from the hull's mean through the point crosses."""
    o = hull.mean(axis=0)
    ang = np.arctan2(hull[:, 1] - o[1], hull[:, 0] - o[0])
    q = np.arctan2(points[:, 1] - o[1], points[:, 0] - o[0])
    return np.asarray((np.searchsorted(ang, q) - 1) % len(hull))


def _line_distances(
    points: np.ndarray, a: np.ndarray, b: np.ndarray, inside: np.ndarray
) -> np.ndarray:
    """Signed distances of points to the lines through ``a``, ``b`` (rows), > 0 on the side
    away from ``inside``."""
    d = b - a
    nrm = np.c_[d[:, 1], -d[:, 0]] / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    flip = np.einsum("ij,ij->i", nrm, a - inside) < 0
    nrm[flip] *= -1.0
    return np.einsum("ij,ij->i", nrm, points - a)


def outline_distances(
    points: np.ndarray, hull: np.ndarray, base: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (> 0 outside) of points (N, 2) to the hull's boundary: to the line of
    the hull segment that the ray from the hull's mean through the point crosses; and per point
    the segment's kind: 0 rim arc, 1 base arc, 2 silhouette (a rim vertex next to a base one).
    """
    k = _segments(points, hull)
    k1 = (k + 1) % len(hull)
    dist = _line_distances(points, hull[k], hull[k1], hull.mean(axis=0)[None])
    return dist, _segment_kinds(base, k)


def _segment_kinds(base: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Kind of hull segments ``seg`` from their vertices' origins (``base``: per hull vertex,
    on the base): 0 rim arc, 1 base arc, 2 silhouette."""
    nxt = base[(seg + 1) % len(base)]
    return np.where(base[seg] != nxt, 2, base[seg].astype(int))


@dataclass
class _State:
    c: np.ndarray
    n: np.ndarray
    r: float
    h: float


def _unpack(x: np.ndarray, s: _State) -> _State:
    u, v = tangent_basis(s.n)
    n = s.n + x[3] * u + x[4] * v
    return _State(s.c + x[:3], n / np.linalg.norm(n), s.r * math.exp(x[5]), s.h + x[6] * s.r)


def fit_ring_outline(
    rig: StereoRig,
    circle: Circle3D,
    left_points: np.ndarray,
    right_points: np.ndarray,
    config: OutlineConfig,
    radius_prior: tuple[float, float] | None = None,
) -> OutlineFit:
    """Fit the front rim and the wall height to both images' ring edge points (module doc).

    Args:
        circle: a start (the circle of all edge points).
        left_points, right_points: (N, 2) undistorted edge points near the ring's outline.
        radius_prior: ``(radius_m, sigma_m)`` of a known outer radius.

    Raises:
        GeometryFailure: too few points, or no start converged to a finite outline.
    """
    cams = tuple(
        (rig.intrinsics(c), rig.cam_from_left(c), np.asarray(p, float).reshape(-1, 2))
        for c, p in ((Camera.LEFT, left_points), (Camera.RIGHT, right_points))
    )
    if min(len(p) for _, _, p in cams) < 12:
        raise GeometryFailure("ring outline: too few edge points")
    n0 = np.asarray(circle.normal, float)
    if n0 @ circle.center > 0:
        n0 = -n0  # toward the cameras: the base lies behind the rim
    steps = np.array([1e-5, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6, 1e-6])
    n_left = len(cams[0][2])
    # samples per circle: one per ~3 px of the rim's image (chord sagitta < 0.02 px), at most
    # ``config.samples``
    perimeter_px = (
        2 * math.pi * circle.radius * float(rig.K_left[0, 0]) / max(circle.center[2], 1e-6)
    )
    S = int(np.clip(perimeter_px / 3, 48, config.samples))

    def linearise(s: _State, jacobian: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals, their kinds and (if asked) the Jacobian with the hull's combinatorics
        (which samples span the segment each point is measured to) held fixed."""
        states = [s]
        if jacobian:
            for k in range(7):
                dx = np.zeros(7)
                dx[k] = steps[k]
                states.append(_unpack(dx, s))
        X = [_samples(t.c, t.n, t.r, t.h, S) for t in states]
        res, kinds, jac = [], [], []
        for K, T, p in cams:
            px = [_project(K, T, x) for x in X]
            idx = _hull_indices(px[0])
            hull = px[0][idx]
            seg = _segments(p, hull)
            ia, ib = idx[seg], idx[(seg + 1) % len(idx)]
            inside = hull.mean(axis=0)[None]
            r0 = _line_distances(p, px[0][ia], px[0][ib], inside)
            res.append(r0)
            kinds.append(_segment_kinds(idx >= S, seg))
            if jacobian:
                cols = [
                    (_line_distances(p, q[ia], q[ib], inside) - r0) / steps[j]
                    for j, q in enumerate(px[1:])
                ]
                jac.append(np.stack(cols, axis=1))
        J = np.vstack(jac) if jacobian else np.zeros((0, 7))
        return np.concatenate(res), np.concatenate(kinds), J

    def prior_row(s: _State, scale: float) -> tuple[float, np.ndarray] | None:
        if radius_prior is None:
            return None
        radius_m, sigma_m = radius_prior
        row = np.zeros(7)
        row[5] = scale * s.r / sigma_m
        return scale * (s.r - radius_m) / sigma_m, row

    best: tuple[float, _State, np.ndarray, np.ndarray, float] | None = None
    for h_start in config.height_starts:
        s = _State(
            np.asarray(circle.center, float), n0, float(circle.radius), h_start * circle.radius
        )
        try:
            for _ in range(config.iterations):
                r0, _, J = linearise(s, True)
                sigma = max(1.4826 * float(np.median(np.abs(r0))), 0.05)
                w = np.minimum(1.0, config.huber_k * sigma / np.maximum(np.abs(r0), 1e-12))
                sw = np.sqrt(w)
                A, b = J * sw[:, None], -r0 * sw
                pr = prior_row(s, sigma)
                if pr is not None:
                    A, b = np.vstack([A, pr[1]]), np.r_[b, -pr[0]]
                step = np.linalg.lstsq(A, b, rcond=None)[0]
                if not np.all(np.isfinite(step)):
                    raise GeometryFailure("ring outline: non-finite step")
                scale = max(
                    float(np.linalg.norm(step[:3])) / (0.3 * s.r),
                    float(np.linalg.norm(step[3:5])) / 0.2,
                    abs(float(step[5])) / 0.2,
                    abs(float(step[6])) / 0.2,
                    1.0,
                )
                s = _unpack(step / scale, s)
                s.h = min(max(s.h, 0.0), config.max_height * s.r)
                if scale == 1.0 and float(np.abs(J @ step).max()) < config.tolerance_px:
                    break
            res, kinds, _ = linearise(s, False)
        except (GeometryFailure, np.linalg.LinAlgError, ArithmeticError, ValueError):
            continue
        if not (np.all(np.isfinite(res)) and s.r > 0 and s.c[2] > 0):
            continue
        sigma = max(1.4826 * float(np.median(np.abs(res))), 0.05)
        a = np.abs(res)
        k = config.huber_k * sigma
        cost = float(np.sum(np.where(a < k, 0.5 * a**2, k * (a - 0.5 * k))))
        if best is None or cost < best[0]:
            best = (cost, s, res, kinds, sigma)
    if best is None:
        raise GeometryFailure("ring outline: no start converged")
    cost, s, res, kinds, sigma = best
    # covariance at the optimum (weighted Gauss-Newton), marginal over the height
    w = np.minimum(1.0, config.huber_k * sigma / np.maximum(np.abs(res), 1e-12))
    _, _, J = linearise(s, True)
    A = J * np.sqrt(w)[:, None]
    H = A.T @ A
    pr = prior_row(s, sigma)
    if pr is not None:
        H += np.outer(pr[1], pr[1])
    try:
        cov = np.linalg.inv(H) * sigma**2
    except np.linalg.LinAlgError:
        raise GeometryFailure("ring outline: the fit is not constrained by its points") from None
    cov7 = circle_covariance(cov[:6, :6], s.n, s.r)
    rim_pts = (
        cams[0][2][(kinds[:n_left] == 0) & (np.abs(res[:n_left]) < 3 * sigma)],
        cams[1][2][(kinds[n_left:] == 0) & (np.abs(res[n_left:]) < 3 * sigma)],
    )
    return OutlineFit(
        circle=Circle3D(center=s.c, normal=s.n, radius=s.r, covariance=cov7),
        height_m=s.h,
        height_sigma_m=float(math.sqrt(max(cov[6, 6], 0.0))) * s.r,
        rim_points=rim_pts,
        rms_px=float(np.sqrt(np.mean(np.minimum(np.abs(res), 3 * sigma) ** 2))),
        cost=cost,
    )
