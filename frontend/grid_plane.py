"""The normal of a plane seen through a rectangular grid of straight lines on it.

A solar array's cells form two families of parallel lines on a plane. In the image each
family converges to a vanishing point ``v``; its 3-D direction is ``K^-1 v`` (normalised) in
the camera frame, and the plane's normal is the cross product of the two directions. The
bracket of the paper's view (seed 002) is rigid with its array, so the array's normal is a
fixed direction of the target frame: a pose hypothesis that puts the bracket's vertices on
the same pixels but tilts the target differently (another P3P solution) moves that direction
from frame to frame, the true pose does not (`satpose.backend.labelling.fit_track`).

Steps (`measure_grid_plane`): line segments (OpenCV's LSD) longer than ``min_length_px``,
their ends undistorted; the first vanishing point by RANSAC over pairs of segments (a
segment votes when the line from its midpoint to the vanishing point passes within
``inlier_px`` of its ends; votes weighed by length), then the second among the segments
left. A family's segments are grouped into the grid lines they lie on (LSD breaks a cell
line at every crossing) and each line is fitted to all its pieces; the vanishing point is
then the one that the lines' ends miss least (Gauss-Newton) among the lines that agree with
the most line length (RANSAC over pairs of lines: the array's frame bar along its edge, a
few degrees off the cells, is left out). Checks: at least
``min_segments`` segments on ``min_lines`` lines per family (a strut's two edges are not a
grid), and the two directions perpendicular within ``max_skew_deg`` (a rectangular grid's
are). The normal's sigma: the spread of the normal over ``bootstrap`` resamplings of the
lines, times ``sigma_scale``, with ``sigma_floor_deg`` and ``skew_factor`` times the skew in
quadrature (what the lines' scatter does not show: the calibration, a line's edges that err
together, a wrong line in a family, which the skew betrays; the numbers come from the
bracket family's tuning seeds, docs/bracket.md "The array's plane"). A grid whose cells
are smaller than about 10 px gives too few segments: no normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.frontend.measurements import MeasurementError, PlaneNormalMeasurement


@dataclass(frozen=True, kw_only=True)
class GridPlaneConfig:
    """Settings of `measure_grid_plane`.

    Attributes:
        min_length_px: segments shorter than this [px] are not used.
        inlier_px: a segment belongs to a vanishing point when the line from its midpoint
            to the point passes within this distance of its ends [px].
        min_segments: segments each family needs.
        min_lines: distinct lines (offsets more than ``line_gap_px`` apart) each family needs.
        line_gap_px: two segments of a family lie on distinct lines beyond this offset [px].
        line_outlier_px: a grid line agrees with its family's vanishing point when its ends
            lie within this distance [px] of the line through its centre and the point (a
            clean family's lines: 0.02 px median, 0.25 px the largest on the bracket
            family's tuning seeds).
        max_skew_deg: the two directions must be perpendicular within this [deg].
        ransac_iterations: pairs of segments tried per vanishing point.
        bootstrap: resamplings of the segments for the sigma.
        sigma_scale, sigma_floor_deg, skew_factor: the stated sigma, ``hypot(sigma_scale *
            spread, sigma_floor_deg, skew_factor * skew)``: the bootstrap spread of the
            normal, a floor, and the grid's own misfit (its directions' departure from
            perpendicular, an error the lines' scatter does not show).
        seed: the random generator's seed (RANSAC and bootstrap: the same image gives the
            same measurement).
    """

    min_length_px: float = 8.0
    inlier_px: float = 0.75
    min_segments: int = 20
    min_lines: int = 6
    line_gap_px: float = 2.0
    line_outlier_px: float = 0.3
    max_skew_deg: float = 0.5
    ransac_iterations: int = 300
    bootstrap: int = 30
    sigma_scale: float = 1.0
    sigma_floor_deg: float = 0.1
    skew_factor: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "min_length_px",
            "inlier_px",
            "line_gap_px",
            "line_outlier_px",
            "max_skew_deg",
            "sigma_scale",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise MeasurementError(f"grid_plane.{name} must be positive, got {v}")
        for name in ("sigma_floor_deg", "skew_factor"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise MeasurementError(f"grid_plane.{name} must be >= 0, got {v}")
        if min(self.min_segments, self.min_lines, self.ransac_iterations, self.bootstrap) < 2:
            raise MeasurementError(
                "grid_plane.min_segments, min_lines, ransac_iterations and bootstrap must be >= 2"
            )


@dataclass(frozen=True)
class _Segments:
    """Undistorted segments: homogeneous lines (a, b normalised), midpoints, unit
    directions, lengths."""

    lines: np.ndarray
    mid: np.ndarray
    direction: np.ndarray
    length: np.ndarray

    def take(self, idx: np.ndarray) -> _Segments:
        return _Segments(self.lines[idx], self.mid[idx], self.direction[idx], self.length[idx])


def _segments(gray: np.ndarray, camera: PinholeCamera, min_length_px: float) -> _Segments:
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    found = lsd.detect(gray)[0]
    seg = np.zeros((0, 4)) if found is None else found.reshape(-1, 4).astype(float)
    raw_len = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    seg = seg[raw_len >= min_length_px]
    if len(seg) == 0:
        z = np.zeros((0, 3))
        return _Segments(z, z[:, :2], z[:, :2], np.zeros(0))
    ends = cv2.undistortPoints(
        seg.reshape(-1, 1, 2), camera.K, np.asarray(camera.dist, float), P=camera.K
    ).reshape(-1, 4)
    a, c = ends[:, :2], ends[:, 2:]
    lines = np.cross(np.c_[a, np.ones(len(a))], np.c_[c, np.ones(len(c))])
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    length = np.linalg.norm(c - a, axis=1)
    return _Segments(lines, (a + c) / 2, (c - a) / length[:, None], length)


def _offsets(
    centre: np.ndarray, direction: np.ndarray, length: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """Per segment or line (``centre``, unit ``direction``, ``length``), how far its ends lie
    from the line through its centre and the (homogeneous) point ``x`` [px], signed: half its
    length times the sine of the angle between (half its length where the point is its
    centre)."""
    if abs(x[2]) > 1e-12:
        to = x[:2] / x[2] - centre
    else:
        to = np.broadcast_to(x[:2], centre.shape).copy()
    norm = np.linalg.norm(to, axis=1)
    ok = norm > 1e-9
    sin = np.ones(len(to))
    cross = to[:, 0] * direction[:, 1] - to[:, 1] * direction[:, 0]
    sin[ok] = cross[ok] / norm[ok]
    return np.asarray(0.5 * length * sin)


def _consensus(
    homog: np.ndarray,
    centre: np.ndarray,
    direction: np.ndarray,
    length: np.ndarray,
    tol_px: float,
    rng: np.random.Generator,
    iterations: int,
) -> np.ndarray:
    """RANSAC for a vanishing point: the intersection of two of the (homogeneous) lines
    ``homog``, drawn with probability by length; which ones agree (`_offsets` within
    ``tol_px``) with the point that the largest total length agrees with (boolean)."""
    n = len(length)
    best, best_in = -1.0, np.zeros(n, dtype=bool)
    p = length / length.sum()
    for _ in range(iterations):
        i, j = rng.choice(n, 2, replace=False, p=p)
        v = np.cross(homog[i], homog[j])
        if np.linalg.norm(v) < 1e-12:
            continue
        agree = np.abs(_offsets(centre, direction, length, v / np.linalg.norm(v))) < tol_px
        score = float(length[agree].sum())
        if score > best:
            best, best_in = score, agree
    return best_in


def _fit_point(s: _Segments) -> np.ndarray:
    """Least-squares vanishing point (unit homogeneous 3-vector) of segments weighed by
    length."""
    _, _, vt = np.linalg.svd(s.lines * np.sqrt(s.length)[:, None], full_matrices=False)
    return np.asarray(vt[-1])


def _ransac(s: _Segments, cfg: GridPlaneConfig, rng: np.random.Generator) -> np.ndarray:
    """Inliers (boolean) of the segments' vanishing point (`_consensus`), refined by least
    squares and chosen again."""
    args = (s.mid, s.direction, s.length)
    best_in = _consensus(s.lines, *args, cfg.inlier_px, rng, cfg.ransac_iterations)
    if best_in.sum() >= 2:
        v = _fit_point(s.take(np.flatnonzero(best_in)))
        best_in = np.abs(_offsets(*args, v)) < cfg.inlier_px
    return best_in


def _line_groups(s: _Segments, v: np.ndarray, gap_px: float) -> list[np.ndarray]:
    """The family's segments grouped by the line they lie on: the line through the
    vanishing point ``v`` and a segment's midpoint, by its signed distance from the image's
    origin (sorted, a new line where two neighbours are more than ``gap_px`` apart)."""
    m = np.c_[s.mid, np.ones(len(s.mid))]
    lines = np.cross(np.broadcast_to(v, m.shape), m)
    ab = np.linalg.norm(lines[:, :2], axis=1)
    # orient every line like the family's first (the distance's sign)
    sign = np.sign(lines[:, :2] @ lines[0, :2])
    sign[sign == 0] = 1.0
    rho = sign * lines[:, 2] / np.maximum(ab, 1e-12)
    order = np.argsort(rho)
    cuts = np.flatnonzero(np.diff(rho[order]) > gap_px) + 1
    return [np.asarray(g) for g in np.split(order, cuts)]


@dataclass(frozen=True)
class _Lines:
    """A family's lines, each fitted to all its segments: centre, unit direction, length
    (the extent of its segments)."""

    centre: np.ndarray
    direction: np.ndarray
    length: np.ndarray

    def take(self, idx: np.ndarray) -> _Lines:
        return _Lines(self.centre[idx], self.direction[idx], self.length[idx])


def _fit_lines(s: _Segments, groups: list[np.ndarray]) -> _Lines:
    """Each group's line: total least squares through its segments' ends and midpoints,
    weighed by segment length."""
    centres, dirs, lengths = [], [], []
    for g in groups:
        half = 0.5 * s.length[g][:, None] * s.direction[g]
        pts = np.vstack([s.mid[g] - half, s.mid[g], s.mid[g] + half])
        w = np.tile(s.length[g], 3)
        c = (w[:, None] * pts).sum(axis=0) / w.sum()
        d = pts - c
        _, _, vt = np.linalg.svd(d * np.sqrt(w)[:, None], full_matrices=False)
        u = vt[0]
        along = d @ u
        centres.append(c + 0.5 * (along.max() + along.min()) * u)
        dirs.append(u)
        lengths.append(float(along.max() - along.min()))
    return _Lines(np.array(centres), np.array(dirs), np.array(lengths))


def _robust_point(
    ln: _Lines, start: np.ndarray, tol_px: float, rng: np.random.Generator, iterations: int
) -> tuple[np.ndarray, _Lines]:
    """The vanishing point of the family's lines (at least two) that is consistent with most
    of their length: `_consensus` over pairs of lines, then `_fit_point_lines` on the
    agreeing lines, chosen again and refitted. A long edge nearly parallel to the grid (the
    array's frame along its edge, a few degrees off the cells) meets the grid's lines
    elsewhere, and its length would pull a fit of all. Returns the point and the lines
    kept."""
    n = len(ln.length)
    homog = np.cross(np.c_[ln.centre, np.ones(n)], np.c_[ln.direction, np.zeros(n)])
    args = (ln.centre, ln.direction, ln.length)
    keep = _consensus(homog, *args, tol_px, rng, iterations)
    v = start
    for _ in range(2):
        if keep.sum() < 2:
            break
        v = _fit_point_lines(ln.take(np.flatnonzero(keep)), v)
        keep = np.abs(_offsets(*args, v)) < tol_px
    kept = ln.take(np.flatnonzero(keep))
    return (_fit_point_lines(kept, v) if len(kept.length) >= 2 else v), kept


def _fit_point_lines(ln: _Lines, start: np.ndarray) -> np.ndarray:
    """The vanishing point (unit homogeneous 3-vector) that minimises the lines' end
    offsets: per line, half its length times the sine of the angle between its direction
    and the direction from its centre to the point (Gauss-Newton on the sphere from
    ``start``)."""
    v = start / np.linalg.norm(start)
    args = (ln.centre, ln.direction, ln.length)
    for _ in range(10):
        B = np.linalg.svd(v[None])[2][1:].T  # tangent basis of v
        r = _offsets(*args, v)
        J = np.empty((len(r), 2))
        for k in range(2):
            e = v + 1e-7 * B[:, k]
            J[:, k] = (_offsets(*args, e / np.linalg.norm(e)) - r) / 1e-7
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        v = v + B @ step
        v /= np.linalg.norm(v)
        if float(np.linalg.norm(step)) < 1e-10:
            break
    return v


def _normal(K_inv: np.ndarray, v1: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane's unit normal and the skew of the two directions [deg]."""
    d1, d2 = K_inv @ v1, K_inv @ v2
    d1, d2 = d1 / np.linalg.norm(d1), d2 / np.linalg.norm(d2)
    n = np.cross(d1, d2)
    skew = abs(90.0 - math.degrees(math.acos(min(1.0, abs(float(d1 @ d2))))))
    return n / np.linalg.norm(n), skew


def measure_grid_plane(
    gray: np.ndarray, camera: PinholeCamera, config: GridPlaneConfig | None = None
) -> tuple[PlaneNormalMeasurement | None, str]:
    """The normal of the plane of the image's dominant rectangular line grid (module
    docstring), or None and why not (one sentence).

    Args:
        gray: the image, (H, W) uint8 (other types are scaled to 8 bits; BGR is converted).
        camera: its calibration (``K`` and the distortion).
        config: settings.
    """
    cfg = GridPlaneConfig() if config is None else config
    img = np.asarray(gray)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        top = float(np.nanmax(img)) if img.size else 0.0
        img = np.clip(np.nan_to_num(img.astype(float)) * (255.0 / top if top > 0 else 0.0), 0, 255)
        img = img.astype(np.uint8)
    s = _segments(img, camera, cfg.min_length_px)
    if len(s.length) < 2 * cfg.min_segments:
        return (
            None,
            f"grid plane: {len(s.length)} line segments (a grid needs {2 * cfg.min_segments})",
        )
    rng = np.random.default_rng(cfg.seed)
    families: list[tuple[_Lines, np.ndarray]] = []
    left = np.ones(len(s.length), dtype=bool)
    for _ in range(2):
        idx = np.flatnonzero(left)
        if len(idx) < cfg.min_segments:
            return None, f"grid plane: {len(idx)} segments left for the second direction"
        inl = idx[_ransac(s.take(idx), cfg, rng)]
        fam = s.take(inl)
        v = _fit_point(fam)
        lines = _fit_lines(fam, _line_groups(fam, v, cfg.line_gap_px))
        if len(inl) < cfg.min_segments or len(lines.length) < cfg.min_lines:
            return None, (
                f"grid plane: a direction with {len(inl)} segments on {len(lines.length)} "
                f"lines (needs {cfg.min_segments} on {cfg.min_lines})"
            )
        v, lines = _robust_point(lines, v, cfg.line_outlier_px, rng, cfg.ransac_iterations)
        if len(lines.length) < cfg.min_lines:
            return None, f"grid plane: a direction with {len(lines.length)} consistent lines"
        families.append((lines, v))
        left[inl] = False
    K_inv = np.linalg.inv(camera.K)
    n, skew = _normal(K_inv, families[0][1], families[1][1])
    if skew > cfg.max_skew_deg:
        return None, f"grid plane: the two directions are {skew:.2f} deg from perpendicular"
    boots = []
    for _ in range(cfg.bootstrap):
        vs = [
            _fit_point_lines(f.take(rng.integers(0, len(f.length), len(f.length))), v)
            for f, v in families
        ]
        nb, _ = _normal(K_inv, vs[0], vs[1])
        boots.append(nb if nb @ n >= 0 else -nb)
    dev = np.array(boots) - n  # small: the tangent components of each resampled normal
    spread = math.sqrt(float(np.mean(np.sum(dev**2, axis=1))) / 2.0)
    sigma = math.hypot(
        cfg.sigma_scale * spread,
        math.radians(cfg.sigma_floor_deg),
        cfg.skew_factor * math.radians(skew),
    )
    counts = (int(families[0][0].length.size), int(families[1][0].length.size))
    return (
        PlaneNormalMeasurement(
            normal=n,
            sigma_rad=sigma,
            lines=counts,
            skew_deg=skew,
        ),
        "",
    )
