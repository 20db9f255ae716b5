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
the plain circle fit. The wall height needs no prior (non-cooperative).

A known ring (`satpose.frontend.pipeline.KnownRing`: a standard interface whose dimensions
the user states) makes the model rigid: its radius and wall height are priors, a lip's width
and thickness shape the hull (the wall and base narrower than the rim, the lip's lower edge a
third circle). With the height fixed, the base's arc no longer moves toward edges that lie on
the rim, so each point beside the base's arc or a silhouette that lies nearer the rim's own
image is labelled the crease between rim and wall and measured to the rim (where the rim and
the wall differ in brightness the edge search finds that crease, not the outline). With the
inner radius, `inner_edge_points` adds the rim's inner edge where the wall's outer face shows:
there the outer edge lies beside the wall, while the inner edge lies beside the interior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from satpose.datasets.geometry import Rigid3
from satpose.frontend.conics import circle_to_conic, sampson_distance
from satpose.frontend.edges import EdgeSearchConfig, edges_of_polarity
from satpose.frontend.measurements import Camera
from satpose.frontend.rim import rim_samples, wall_facing
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


def _samples(
    c: np.ndarray,
    n: np.ndarray,
    r: float,
    h: float,
    samples: int,
    lip: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """``samples`` points of the rim, then as many of the base ((2 or 3) * samples, 3). With
    a ``lip`` ``(width, thickness)`` the wall (and base) is ``width`` narrower than the rim,
    and the lip's lower edge (the rim's circle ``thickness`` back) follows as a third circle.
    """
    u, v = tangent_basis(n)
    phi = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
    unit = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v
    width, thickness = lip
    parts = [c + r * unit, c - h * n + (r - width) * unit]
    if thickness > 0:
        parts.append(c - thickness * n + r * unit)
    return np.vstack(parts)


def outline_hull(
    K: np.ndarray,
    T: Rigid3,
    center: np.ndarray,
    normal: np.ndarray,
    radius: float,
    height: float,
    samples: int,
    lip: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """The image outline of the cylinder: hull vertices (M, 2) in counter-clockwise order of
    angle about their mean, and per vertex whether it lies on the base or the lip's lower
    edge (else on the rim)."""
    px = _project(K, T, _samples(center, normal, radius, height, samples, lip))
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


def _concentric_distances(
    K: np.ndarray, T: Rigid3, s: _State, inset: float, points: np.ndarray
) -> np.ndarray:
    """Signed distances [px] (> 0 outside) of ``points`` to the image of the circle ``inset``
    smaller than the rim, concentric, in its plane (0: the rim itself; the rim's width: its
    inner edge) in the camera ``K`` posed ``T`` (cam_from_left)."""
    u, v = tangent_basis(s.n)
    circle_frame = Rigid3(R=np.column_stack([u, v, s.n]), t=s.c)
    C = circle_to_conic(K, T @ circle_frame, max(s.r - inset, 1e-6))
    return sampson_distance(points, C)


def fit_ring_outline(
    rig: StereoRig,
    circle: Circle3D,
    left_points: np.ndarray,
    right_points: np.ndarray,
    config: OutlineConfig,
    radius_prior: tuple[float, float] | None = None,
    height_prior: tuple[float, float] | None = None,
    inner: tuple[np.ndarray, np.ndarray, float] | None = None,
    lip: tuple[float, float] = (0.0, 0.0),
) -> OutlineFit:
    """Fit the front rim and the wall height to both images' ring edge points (module doc).

    Args:
        circle: a start (the circle of all edge points).
        left_points, right_points: (N, 2) undistorted edge points near the ring's outline.
        radius_prior: ``(radius_m, sigma_m)`` of a known outer radius.
        height_prior: ``(height_m, sigma_m)`` of a known wall height (rim to base).
        inner: ``(left, right, width_m)``: undistorted edge points (N, 2) of the rim's inner
            edge, a circle concentric with the rim in its plane and ``width_m`` smaller (a
            known ring's rim width), measured by each point's distance to its image.
        lip: a known ring's lip ``(width, thickness)`` [m] (`_samples`); zeros: none.

    Raises:
        GeometryFailure: too few points, or no start converged to a finite outline.
    """
    cams = tuple(
        (rig.intrinsics(c), rig.cam_from_left(c), np.asarray(p, float).reshape(-1, 2))
        for c, p in ((Camera.LEFT, left_points), (Camera.RIGHT, right_points))
    )
    inner_pts = (
        (np.zeros((0, 2)), np.zeros((0, 2)))
        if inner is None
        else tuple(np.asarray(p, float).reshape(-1, 2) for p in inner[:2])
    )
    width = 0.0 if inner is None else float(inner[2])
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
        X = [_samples(t.c, t.n, t.r, t.h, S, lip) for t in states]
        res, kinds, jac = [], [], []
        for (K, T, p), q_in in zip(cams, inner_pts, strict=True):
            px = [_project(K, T, x) for x in X]
            idx = _hull_indices(px[0])
            hull = px[0][idx]
            seg = _segments(p, hull)
            ia, ib = idx[seg], idx[(seg + 1) % len(idx)]
            inside = hull.mean(axis=0)[None]
            r0 = _line_distances(p, px[0][ia], px[0][ib], inside)
            kind = _segment_kinds(idx >= S, seg)
            crease = np.zeros(len(p), bool)
            if height_prior is not None:
                # a known height fixes where the base's arc lies; a point beside it that lies
                # nearer the rim's own image is the crease between rim and wall (kind 4)
                d_rim = [_concentric_distances(K, T, t, 0.0, p) for t in states]
                crease = (kind != 0) & (np.abs(d_rim[0]) < np.abs(r0))
                kind = np.where(crease, 4, kind)
            res.append(np.where(crease, d_rim[0], r0) if crease.any() else r0)
            kinds.append(kind)
            if jacobian:
                cols = [
                    (_line_distances(p, q[ia], q[ib], inside) - r0) / steps[j]
                    for j, q in enumerate(px[1:])
                ]
                if crease.any():
                    cols = [
                        np.where(crease, (d_rim[j + 1] - d_rim[0]) / steps[j], col)
                        for j, col in enumerate(cols)
                    ]
                jac.append(np.stack(cols, axis=1))
            if len(q_in):
                d = [_concentric_distances(K, T, t, width, q_in) for t in states]
                res.append(d[0])
                kinds.append(np.full(len(q_in), 3))
                if jacobian:
                    jac.append(np.stack([(dk - d[0]) / steps[j] for j, dk in enumerate(d[1:])], 1))
        J = np.vstack(jac) if jacobian else np.zeros((0, 7))
        return np.concatenate(res), np.concatenate(kinds), J

    def prior_rows(s: _State, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals (k,) and Jacobian rows (k, 7) of the known radius and height,
        in units of the points' robust sigma ``scale``."""
        res, rows = [], []
        # (prior, its parameter's value, its column: log-radius 5, height / radius 6)
        for prior, value, col in ((radius_prior, s.r, 5), (height_prior, s.h, 6)):
            if prior is not None:
                row = np.zeros(7)
                row[col] = scale * s.r / prior[1]  # d value / d parameter = r for both
                res.append(scale * (value - prior[0]) / prior[1])
                rows.append(row)
        return np.asarray(res, float), np.asarray(rows, float).reshape(-1, 7)

    def weights(r: np.ndarray, sigma: float) -> np.ndarray:
        """Huber's weights; with a known height Tukey's biweight (4.685 sigma), so that what
        the rigid model does not explain (a shadow's edge beyond the outline) does not pull."""
        if height_prior is None:
            return np.minimum(1.0, config.huber_k * sigma / np.maximum(np.abs(r), 1e-12))
        u = r / (4.685 * sigma)
        return np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0)

    best: tuple[float, _State, np.ndarray, np.ndarray, float] | None = None
    # a known height is the one start; otherwise each of the config's, in ring radii
    starts = (
        [height_prior[0]]
        if height_prior is not None
        else [h * circle.radius for h in config.height_starts]
    )
    for h_start in starts:
        s = _State(np.asarray(circle.center, float), n0, float(circle.radius), h_start)
        try:
            for _ in range(config.iterations):
                r0, _, J = linearise(s, True)
                sigma = max(1.4826 * float(np.median(np.abs(r0))), 0.05)
                sw = np.sqrt(weights(r0, sigma))
                A, b = J * sw[:, None], -r0 * sw
                pres, prows = prior_rows(s, sigma)
                A, b = np.vstack([A, prows]), np.r_[b, -pres]
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
    w = weights(res, sigma)
    _, _, J = linearise(s, True)
    A = J * np.sqrt(w)[:, None]
    H = A.T @ A
    prows = prior_rows(s, sigma)[1]
    H += prows.T @ prows
    try:
        cov = np.linalg.inv(H) * sigma**2
    except np.linalg.LinAlgError:
        raise GeometryFailure("ring outline: the fit is not constrained by its points") from None
    cov7 = circle_covariance(cov[:6, :6], s.n, s.r)
    m_left = n_left + len(inner_pts[0])  # the left camera's residuals: outline, then inner
    n_right = len(cams[1][2])
    on_rim = (kinds == 0) | (kinds == 4)  # the rim's arc of the outline, or the crease
    rim_pts = (
        cams[0][2][on_rim[:n_left] & (np.abs(res[:n_left]) < 3 * sigma)],
        cams[1][2][
            on_rim[m_left : m_left + n_right] & (np.abs(res[m_left : m_left + n_right]) < 3 * sigma)
        ],
    )
    return OutlineFit(
        circle=Circle3D(center=s.c, normal=s.n, radius=s.r, covariance=cov7),
        height_m=s.h,
        height_sigma_m=float(math.sqrt(max(cov[6, 6], 0.0))) * s.r,
        rim_points=rim_pts,
        rms_px=float(np.sqrt(np.mean(np.minimum(np.abs(res), 3 * sigma) ** 2))),
        cost=cost,
    )


def inner_edge_points(
    rig: StereoRig,
    circle: Circle3D,
    width_m: float,
    images_s: tuple[np.ndarray, np.ndarray],
    edges: EdgeSearchConfig,
    *,
    samples: int = 360,
    half_px: float = 1.5,
    margin_deg: float = 5.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Per camera (left, right), the rim's inner edge where it is the ring's occluding edge.

    The inner edge is the circle ``width_m`` (a known ring's rim width) inside the rim,
    concentric, in its plane. Where the wall's outer face is turned toward a camera, its inner
    face is turned away, and the inner edge lies between the rim's face and the ring's
    interior, with no wall beside it: there (``margin_deg`` from the turn) each camera's
    smoothed image ``images_s`` is searched along the edge's normals, ``half_px`` either side,
    for an edge of either sign. Samples whose rim face is narrower than ``2 half_px + 1`` px in
    the image are skipped (the outer edge would be in reach).

    Returns:
        (N, 2) undistorted edge points per camera (N may be 0).
    """
    r_in = circle.radius - width_m
    if r_in <= 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    outer, rho = rim_samples(circle, samples)
    inner = circle.center + r_in * rho
    out = []
    for cam, image_s in zip((Camera.LEFT, Camera.RIGHT), images_s, strict=True):
        facing = wall_facing(inner, rho, rig.center(cam))
        p_in = rig.project_into(cam, inner)
        d = rig.project_into(cam, outer) - p_in
        face_px = np.linalg.norm(d, axis=1)
        keep = (facing > math.sin(math.radians(margin_deg))) & (face_px >= 2 * half_px + 1)
        if not np.any(keep):
            out.append(np.zeros((0, 2)))
            continue
        nrm = d[keep] / face_px[keep, None]
        pts = edges_of_polarity(image_s, p_in[keep], nrm, 0, half_px, edges)
        out.append(pts[np.all(np.isfinite(pts), axis=1)])
    return out[0], out[1]
