"""The ring's front rim by the stereo depth of its own arcs (stereo generalisation).

The frontend's 3-D circle is fitted to every edge point of the ring's two ellipses. Where a
ring with a wall casts a shadow on the panel behind it, or shows its base or its outline,
some arcs of those ellipses are not the rim: they are edges *behind* the rim's plane (the
panel's depth, the base's), and they pull the circle back and tilt it (docs/frontend.md: the
lamp-lit seeds' depth bias, +3 to +11 cm at 6-9 m, is the rim's shadow on the panel).
Nothing of a ring lies in front of the plane of its front rim but bolt heads, so the rim is
the *front* of what the edges show, and each arc's own stereo depth says whether it lies on
a circle's plane or behind it.

`fit_front_arcs` measures that depth arc by arc, with no knowledge of the light or of the
ring's dimensions:

1. **Match.** Each edge point of one image, carried into the other image through a circle's
   plane, is predicted there. Its epipolar line (fixed by the rig: computed once) crosses
   the other image's edge curve (the polyline through that image's edge points); the
   crossing nearest the prediction is its match. The match's offset from the prediction
   along the epipolar line, in the direction that a point farther along the ray moves, is a
   disparity residual ``d``: > 0 behind the plane.
2. **Weigh.** An edge displaced by ``e`` along its normal moves the crossing by ``e / |cos|``
   (``cos``: the edge normal against the epipolar direction), so ``z = d |cos|`` has the edge
   noise as its scale. Points whose edge runs nearly along the epipolar line (``|cos| <
   min_cos``: top and bottom of a horizontal rig's ellipse) say little about depth and are
   not judged. The ellipse is cut into ``sectors`` arcs (angle around its centre); an arc's
   statistic is its median ``z``, with the standard error ``1.25 s / sqrt(n)``, ``s`` the
   pooled robust spread of ``z`` around each arc's median (at least ``sigma_floor_px``),
   and an arc-level floor (``arc_floor_depth_px``) in quadrature (real edges' systematic offsets
   vary from arc to arc by about a tenth of a pixel even with nothing behind the rim).
3. **Explain.** The hypotheses are "the rim is every arc but one contiguous span" (one light
   casts one shadow; the wall shows on one side): spans of 0 to ``max_span`` arcs, removed
   from both images. Each is fitted (the circle refined on the kept points of both images)
   and judged against its own fit: its kept arcs must lie on the plane (their medians'
   chi-square below its ``chi2_level`` quantile), the points of the arcs it removed, taken
   together, must lie behind it by more than ``k_sigma`` standard errors of their median,
   and none of those arcs in front of it by as much (the arcs at a span's ends may be partly
   rim, partly shadow). The shortest span that passes wins,
   the lowest chi-square among equals. The empty span passing means nothing lies behind
   (the circle stands); no span passing means the arcs do not tell (it stands too).

The tilt matters: judged against the all-points circle (which the arcs behind pull back and
tilt), rim arcs on the far side look behind as well, and labelling arcs one by one against
that circle drops the rim with the shadow (a shadow 8 cm behind over a third of the rim: 6
deg of tilt, tests/frontend/test_ring_depth.py). Each hypothesis is therefore judged against
its own fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.stats import chi2

from satpose.frontend.conics import sampson_distance
from satpose.frontend.measurements import Camera
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_rms,
    refine_circle,
)


@dataclass(frozen=True, kw_only=True)
class FrontArcsConfig:
    """The rim as the front of the ring's edge arcs (`satpose.frontend.ring_depth`).

    Attributes:
        enabled: refit every frame's 3-D circle on the arcs that lie on its plane.
        sectors: arcs the ellipse is cut into (by angle around its centre).
        max_span: the longest contiguous span of arcs that may be removed.
        k_sigma: the removed arcs' points must lie behind the plane by more than this many
            standard errors of their median (and no removed arc in front by as much).
        chi2_level: the kept arcs' medians must have a chi-square below this quantile.
        sigma_floor_px: the smallest point spread assumed.
        arc_floor_depth_px, arc_floor_image_px: an arc's systematic offset that no arc
            escapes (edge locators' bias varying along a real edge: blur phase, texture
            beside it), in its depth residual and in its distance to the circle's image,
            added in quadrature to each arc median's standard error. Measured on the
            rendered `paper-docking`, a ring with nothing behind it to confuse
            (`python benchmarks/ring_arc_floor.py`, docs/results/ring_arc_floor.md: the arc
            medians' scatter beyond their point noise, 0.12 px and 0.08 px).
        min_cos: points whose edge normal makes a smaller |cosine| with the epipolar
            direction are not judged.
        min_points: an arc with fewer judged points is not judged.
        gate_px: a crossing farther than this from the prediction is no match.
        max_rms_px: the refit's largest RMS distance of its points to the circle's images.
    """

    enabled: bool = True
    sectors: int = 12
    max_span: int = 6
    k_sigma: float = 2.5
    chi2_level: float = 0.99
    sigma_floor_px: float = 0.03
    arc_floor_depth_px: float = 0.12
    arc_floor_image_px: float = 0.08
    min_cos: float = 0.35
    min_points: int = 5
    gate_px: float = 4.0
    max_rms_px: float = 0.6

    def __post_init__(self) -> None:
        if self.sectors < 3:
            raise ValueError(f"front_arcs.sectors must be >= 3, got {self.sectors}")
        if not 0 <= self.max_span < self.sectors:
            raise ValueError(f"front_arcs.max_span must be in [0, sectors), got {self.max_span}")
        for name in (
            "k_sigma",
            "sigma_floor_px",
            "arc_floor_depth_px",
            "arc_floor_image_px",
            "gate_px",
            "max_rms_px",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"front_arcs.{name} must be > 0, got {v}")
        if not 0.0 < self.chi2_level < 1.0:
            raise ValueError(f"front_arcs.chi2_level must be in (0, 1), got {self.chi2_level}")
        if not 0.0 <= self.min_cos < 1.0:
            raise ValueError(f"front_arcs.min_cos must be in [0, 1), got {self.min_cos}")
        if self.min_points < 2:
            raise ValueError(f"front_arcs.min_points must be >= 2, got {self.min_points}")


def _group_medians(
    values: np.ndarray, groups: np.ndarray, min_points: int
) -> dict[int, tuple[float, int]]:
    """Median and count of ``values`` per group label with at least ``min_points`` members
    (one sort for all groups)."""
    order = np.lexsort((values, groups))
    v, g = values[order], groups[order]
    labels, first, counts = np.unique(g, return_index=True, return_counts=True)
    out = {}
    for q, i, n in zip(labels.tolist(), first.tolist(), counts.tolist(), strict=True):
        if n >= min_points:
            out[q] = (0.5 * float(v[i + (n - 1) // 2] + v[i + n // 2]), n)
    return out


def _pooled_spread(values: np.ndarray, groups: np.ndarray, min_points: int) -> float:
    """Robust spread (1.4826 MAD) of ``values`` around their group's median, pooled over the
    groups with at least ``min_points`` members (NaN if none)."""
    med = _group_medians(values, groups, min_points)
    dev = [values[groups == q] - m for q, (m, _) in med.items()]
    if not dev:
        return math.nan
    return 1.4826 * float(np.median(np.abs(np.concatenate(dev))))


@lru_cache(maxsize=256)
def _chi2_limit(level: float, dof: int) -> float:
    return float(chi2.ppf(level, dof))


@dataclass(frozen=True)
class ArcDepths:
    """One image's edge points judged against a circle's plane.

    Attributes:
        z: (N,) disparity residual times |cos| [px] (> 0: behind the plane); NaN unmatched.
        judged: (N,) matched, with |cos| >= ``min_cos``.
        sector: (N,) arc index of each point.
        r: (N,) signed distance of each point to the circle's image in its own camera [px].
    """

    z: np.ndarray
    judged: np.ndarray
    sector: np.ndarray
    r: np.ndarray

    def offsets(self, min_points: int) -> dict[int, tuple[float, int]]:
        """Per arc (at least ``min_points`` points): median ``r`` and count."""
        return _group_medians(self.r, self.sector, min_points)

    def image_spread(self, min_points: int) -> float:
        """Pooled robust spread of ``r`` around each arc's median [px] (NaN if none)."""
        return _pooled_spread(self.r, self.sector, min_points)

    def medians(self, min_points: int) -> dict[int, tuple[float, int]]:
        """Per judged arc (at least ``min_points`` judged points): median ``z`` and count."""
        return _group_medians(self.z[self.judged], self.sector[self.judged], min_points)

    def spread(self, min_points: int) -> float:
        """Pooled robust spread of ``z`` around each judged arc's median [px] (NaN if none)."""
        return _pooled_spread(self.z[self.judged], self.sector[self.judged], min_points)


@dataclass(frozen=True)
class FrontArcsFit:
    """A circle refitted on its front arcs: the arcs removed (sector indices, both images),
    both images' points judged against it, which points it was fitted to, its RMS [px] and
    the chi-square of its kept arcs (and their number)."""

    circle: Circle3D
    removed: tuple[int, ...]
    left: ArcDepths
    right: ArcDepths
    left_keep: np.ndarray
    right_keep: np.ndarray
    rms_px: float
    chi2: float
    dof: int


def _no_crossings() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_Matcher._crossings` when there are none: points (0, 2), line indices, |cos|."""
    return np.zeros((0, 2)), np.zeros(0, int), np.zeros(0)


class _Matcher:
    """One image's edge points against the other image's edge curve: the epipolar crossings
    (fixed by the rig) computed once, the residuals for any circle's plane on demand.
    ``depth`` False: the points' distances to the circle's image only (no crossings; ``z``
    all NaN, nothing judged)."""

    def __init__(
        self,
        rig: StereoRig,
        points: np.ndarray,
        other_points: np.ndarray,
        cam: Camera,
        config: FrontArcsConfig,
        depth: bool = True,
    ) -> None:
        self.rig, self.cam, self.config = rig, cam, config
        self.other = Camera.RIGHT if cam is Camera.LEFT else Camera.LEFT
        pts = np.asarray(points, float).reshape(-1, 2)
        self.points = pts
        self.C, self.rays = rig.rays(cam, pts)  # left frame
        centre = pts.mean(axis=0)
        angle = np.arctan2(pts[:, 1] - centre[1], pts[:, 0] - centre[0])
        self.sector = (
            np.floor((angle + math.pi) / (2 * math.pi) * config.sectors).astype(int)
            % config.sectors
        )
        if not depth:  # no crossings: nothing is judged
            self.hit_point, self.hit_index, self.hit_cos = _no_crossings()
            return
        # the epipolar line of each point: two points of its ray, projected
        near = rig.project_into(self.other, self.C + 2.0 * self.rays)
        far = rig.project_into(self.other, self.C + 200.0 * self.rays)
        direction = far - near
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
        self.away = direction
        normal = np.c_[-direction[:, 1], direction[:, 0]]
        lines = np.c_[normal, -np.sum(normal * near, axis=1)]
        self.hit_point, self.hit_index, self.hit_cos = self._crossings(
            lines, np.asarray(other_points, float).reshape(-1, 2)
        )

    def _crossings(
        self, lines: np.ndarray, curve: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every crossing of each line (N, 3) with the closed polyline through ``curve``
        (ordered by angle around its mean; segments across gaps left out): points (H, 2),
        the index of the line each belongs to (H,), and |cos| of the crossed segment's
        normal against the line's direction (H,)."""
        if len(curve) < 6:
            return _no_crossings()
        centre = curve.mean(axis=0)
        P = curve[np.argsort(np.arctan2(curve[:, 1] - centre[1], curve[:, 0] - centre[0]))]
        seg = np.roll(P, -1, axis=0) - P
        length = np.linalg.norm(seg, axis=1)
        usable = length < 4.0 * max(float(np.median(length)), 1e-9)
        s0 = P @ lines[:, :2].T + lines[:, 2]  # (M, N)
        s1 = s0 + seg @ lines[:, :2].T
        m, n = np.nonzero((np.sign(s0) != np.sign(s1)) & usable[:, None])
        t = s0[m, n] / (s0[m, n] - s1[m, n])
        X = P[m] + t[:, None] * seg[m]
        tangent = seg[m] / length[m, None]
        cos = np.abs(tangent[:, 0] * self.away[n, 1] - tangent[:, 1] * self.away[n, 0])
        return X, n, cos

    def depths(self, circle: Circle3D) -> ArcDepths:
        """Steps 1-2 of the module against ``circle``'s plane."""
        cfg = self.config
        z = np.full(len(self.points), np.nan)
        judged = np.zeros(len(self.points), bool)
        if self.hit_index.size:
            nrm = np.asarray(circle.normal, float)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = ((circle.center - self.C) @ nrm) / (self.rays @ nrm)
            pred = self.rig.project_into(self.other, self.C + s[:, None] * self.rays)
            i = self.hit_index
            dist = np.linalg.norm(self.hit_point - pred[i], axis=1)
            order = np.lexsort((dist, i))
            first = order[np.unique(i[order], return_index=True)[1]]
            first = first[dist[first] < cfg.gate_px]
            j = i[first]
            ok = s[j] > 0
            j, first = j[ok], first[ok]
            d = np.sum((self.hit_point[first] - pred[j]) * self.away[j], axis=1)
            z[j] = d * self.hit_cos[first]
            judged[j] = self.hit_cos[first] >= cfg.min_cos
        conic = self.rig.circle_conic(self.cam, circle)
        return ArcDepths(z, judged, self.sector, sampson_distance(self.points, conic))


def _verdict(
    arcs: tuple[ArcDepths, ArcDepths],
    removed: frozenset[int],
    sigma: tuple[float, float, float],
    config: FrontArcsConfig,
) -> tuple[bool, float, int]:
    """Whether a hypothesis passes, and the chi-square of its kept arcs with its degrees of
    freedom. Its terms: each kept arc's median depth residual in the left image (the right
    image's, matched to the same crossings, say the same thing and would count it twice),
    and each kept arc's median distance to the circle's image in both images (a shadow's or
    base's arc lies off the rim's image too; its depth alone a tilt can hide). ``sigma``:
    the point spreads of the depth residual and of the two images' distances. It passes
    when the kept arcs' chi-square is below the ``chi2_level`` quantile, the removed arcs'
    points taken together lie behind the plane by more than ``k_sigma`` standard errors of
    their median, and no removed arc lies in front of it by as much (the arcs at a span's
    ends may be partly rim)."""
    k, mp = config.k_sigma, config.min_points

    def se(s: float, n: int, floor: float = config.arc_floor_depth_px) -> float:
        return math.sqrt((1.25 * s) ** 2 / n + floor**2)

    t, dof = 0.0, 0
    behind: list[np.ndarray] = []
    left = arcs[0]
    for q, (m, n) in left.medians(mp).items():
        if q in removed:
            if m < -k * se(sigma[0], n):
                return False, math.inf, 0
            behind.append(left.z[left.judged & (left.sector == q)])
        else:
            t += (m / se(sigma[0], n)) ** 2
            dof += 1
    for a, s_img in zip(arcs, sigma[1:], strict=True):
        for q, (m, n) in a.offsets(mp).items():
            if q not in removed:
                t += (m / se(s_img, n, config.arc_floor_image_px)) ** 2
                dof += 1
    if removed:
        z = np.concatenate(behind) if behind else np.zeros(0)
        if z.size < mp or np.median(z) <= k * se(sigma[0], z.size):
            return False, math.inf, 0
    ok = dof == 0 or t < _chi2_limit(config.chi2_level, dof)
    return ok, t, dof


def fit_front_arcs(
    rig: StereoRig,
    circle: Circle3D,
    left_points: np.ndarray,
    right_points: np.ndarray,
    config: FrontArcsConfig,
    radius_prior: tuple[float, float] | None = None,
) -> FrontArcsFit | None:
    """``circle`` refitted without the shortest contiguous span of arcs that lies behind it
    (module docstring); None when nothing lies behind it, or when no span explains the
    arcs (the circle stands)."""
    cfg = config
    lp = np.asarray(left_points, float).reshape(-1, 2)
    rp = np.asarray(right_points, float).reshape(-1, 2)
    matchers = (
        _Matcher(rig, lp, rp, Camera.LEFT, cfg),
        # the right image's depth residuals would say what the left's say (the same
        # crossings, matched the other way round): only its image distances are counted
        _Matcher(rig, rp, lp, Camera.RIGHT, cfg, depth=False),
    )
    null = _depths(matchers, circle)
    spreads = (
        null[0].spread(cfg.min_points),
        null[0].image_spread(cfg.min_points),
        null[1].image_spread(cfg.min_points),
    )
    if not all(math.isfinite(v) for v in spreads):
        return None
    s_z, s_left, s_right = (max(v, cfg.sigma_floor_px) for v in spreads)
    sigma = (s_z, s_left, s_right)
    if _verdict(null, frozenset(), sigma, cfg)[0]:
        return None
    for span in range(1, cfg.max_span + 1):
        passed: list[tuple[float, frozenset[int]]] = []
        for start in range(cfg.sectors):
            removed = frozenset((start + k) % cfg.sectors for k in range(span))
            # the search refits in two Gauss-Newton steps from the all-points circle
            fit, _ = _refit(rig, circle, matchers, removed, 2, radius_prior)
            if fit is None:
                continue
            ok, t, _ = _verdict(_depths(matchers, fit), removed, sigma, cfg)
            if ok:
                passed.append((t, removed))
        for _, removed in sorted(passed, key=lambda p: p[0]):
            fit, keep = _refit(rig, circle, matchers, removed, 6, radius_prior)
            if fit is None:
                continue
            arcs = _depths(matchers, fit)
            ok, t, dof = _verdict(arcs, removed, sigma, cfg)
            rms = circle_rms(rig, fit, lp[keep[0]], rp[keep[1]])
            if ok and rms <= cfg.max_rms_px:
                return FrontArcsFit(
                    fit, tuple(sorted(removed)), *arcs, keep[0], keep[1], rms, t, dof
                )
        if passed:
            return None  # the span that explains the arcs does not hold once fully refitted
    return None


def _depths(matchers: tuple[_Matcher, _Matcher], circle: Circle3D) -> tuple[ArcDepths, ArcDepths]:
    """Both images' points judged against ``circle`` (left, right)."""
    return matchers[0].depths(circle), matchers[1].depths(circle)


def _refit(
    rig: StereoRig,
    circle: Circle3D,
    matchers: tuple[_Matcher, _Matcher],
    removed: frozenset[int],
    iterations: int,
    radius_prior: tuple[float, float] | None,
) -> tuple[Circle3D | None, tuple[np.ndarray, np.ndarray]]:
    """``circle`` refined on both images' points outside the ``removed`` arcs (None if too
    few are left or the fit fails), and which points those are (left, right)."""
    keep = (
        ~np.isin(matchers[0].sector, list(removed)),
        ~np.isin(matchers[1].sector, list(removed)),
    )
    if keep[0].sum() < 6 or keep[1].sum() < 6:
        return None, keep
    try:
        fit = refine_circle(
            rig,
            circle.center,
            circle.normal,
            circle.radius,
            matchers[0].points[keep[0]],
            matchers[1].points[keep[1]],
            iterations=iterations,
            radius_prior=radius_prior,
        )
    except (GeometryFailure, np.linalg.LinAlgError):
        return None, keep
    return fit, keep


def arc_depths(
    rig: StereoRig,
    circle: Circle3D,
    points: np.ndarray,
    other_points: np.ndarray,
    cam: Camera,
    config: FrontArcsConfig,
) -> ArcDepths:
    """Camera ``cam``'s edge ``points`` (N, 2) judged against ``circle``'s plane through
    their epipolar crossings with the other camera's edge curve ``other_points`` (steps 1-2
    of the module)."""
    return _Matcher(rig, points, other_points, cam, config).depths(circle)
