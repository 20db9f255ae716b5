"""Find the bracket's struts in a mono image and emit the points `solve_bracket` needs (seed 002).

1. Line segments: OpenCV's LSD (``cv2.createLineSegmentDetector``) on the lightly smoothed
   image.
2. Bars: a strut is a bright cylinder, so it shows as two nearly parallel segments of opposite
   gradient with brighter pixels between them. Pairs of segments 0.6-25 strut-widths apart
   (in pixels: ``bar_width_px``), overlapping along their length, become bars with a centre
   line; collinear bars are merged into strut candidates (centre line, extent, support).
3. Which candidates are the base ``P1P2`` and the struts ``P1P5``, ``P2P5``: with a predicted
   pose (the previous frame), the candidate closest to each projected centre line; without one,
   every ordered triple of the longest candidates is tried: the base must meet both struts near
   its ends, the struts must start there, the depths must solve (`solve_bracket`) and the camera
   must be on the bracket's known face (``face_sign``; it tells apart the two labellings of a
   symmetric bracket). The hypothesis with the largest supporting length wins.
4. Output: ``p1 = base ∩ strut1``, ``p2 = base ∩ strut2`` and the far visible ends of the two
   struts as ``p4``, ``p3``, with ``sigma_px`` from the scatter of the supporting segment
   endpoints about the fitted centre lines.

The paper's view (base strut and the first part of the side struts, the apex hidden behind a
solar array with its own grid of straight lines): `detect_partial` (hypothesise and verify
with the known visible fraction and strut width; an ambiguous frame is refused) and
`partial_hypotheses` (every consistent pose weighed for the decision over frames,
`satpose.backend.labelling`); docs/bracket.md, "The paper's view".

No truth is read: only the image, the intrinsics and the bracket's known geometry.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from satpose.datasets.geometry import Rigid3, absolute_orientation, rotvec_to_matrix
from satpose.frontend.bracket import (
    BracketConfig,
    BracketGeometry,
    BracketObservation,
    BracketResult,
    incentre,
    p3p_depths,
    project,
    solve_bracket,
    strut_apex,
    triangle_sides,
)


@dataclass(frozen=True, kw_only=True)
class StrutDetectorConfig:
    """Settings of `detect_struts`.

    Attributes:
        blur_sigma_px: Gaussian smoothing before LSD (rendering / sensor noise) [px].
        min_segment_px: shortest LSD segment kept [px].
        max_angle_deg: two edges of one bar, or two pieces of one strut, differ by at most this.
        short_edge_px: paper's view, the short-edge pass only (`partial_candidates` with
            ``short_edges``): two edges of one bar may also differ in direction by
            ``atan(short_edge_px / l)``, ``l`` the shorter edge's length [px]: the offset at
            its end that the terminator's curve and the taper make on a thick short stub
            (a strut 16 px wide and 40 px long: its two LSD edges 4-5 deg apart, bracket
            family tuning seed 20). Longer than ``short_edge_px / tan(max_angle_deg)``
            (76 px at the defaults), ``max_angle_deg`` holds as before.
        short_taper: the short-edge pass also lets that offset reach this fraction of the
            bar's width: its width changes along a short edge by a fraction of itself, not
            by a fixed number of pixels. A close strut's silhouette edges converge toward its
            axis's vanishing point (length x cot(angle to the line of sight) / f of the
            width; tuning seed 70, 0.95 m: a stub 22 px wide whose 75 px edges lie 3.4 deg
            apart), and where a stub leaves the base its interior edge (often the terminator
            of its lit part) starts in the concave corner and leans toward the base (seed 70
            at 1.5 m: a 10 px bar, 60 px edges 4.3 deg apart, 0.44 of its width at the end).
            On the tuning seeds' stubs (`benchmarks/bracket_stub_edges.py`, 1508 with both
            edges found) that end offset over the separation has its 99th percentile at
            0.45 on edges under 76 px (0.44 on all); 0.3 left 16 unpaired, 0.5 leaves 13,
            each of them within the angle (they fail the overlap or width test).
        bar_width_px: (min, max) distance between the two edges of a strut [px].
        merge_distance_px: collinear bars closer than this (centre lines) are one strut [px].
        merge_width_ratio: ... if their widths differ by at most this factor (the paper's
            view, `partial_candidates`: a short stub in line with a solar array's cell-grid
            bars is not one of them).
        candidates: the longest this many strut candidates enter the hypothesis search.
        end_tolerance: how far (fraction of the base length) an intersection may lie from the
            observed end of a strut.
        track_distance_px: with a predicted pose, a candidate farther than this from the
            projected centre line is not that strut [px].
        face_sign: +1 / -1: the camera is on the side of ``(P2 - P1) x (P5 - P1)`` / opposite.
        min_sigma_px: floor of the emitted point noise [px].
        strut_radius_m: the struts' radius (known bracket geometry): their apparent width
            tells apart the P3P solutions on a frame without a prior [m]; None: not used.
        yoke_weight: weight of `yoke_ratio` (strut-like brightness just beyond the apex, where
            the yoke to the wing is) in the hypothesis score: it tells the base from the side
            struts of a near-equilateral bracket.
        min_yoke_margin: without a predicted pose or a reference (and ``yoke_weight > 0``),
            the best hypothesis's `yoke_ratio` must exceed that of every hypothesis with
            another labelling (a pose more than ``relabel_angle_deg`` away), and 0 (no yoke
            seen), by this much, else the frame is refused as ambiguous: a near-equilateral
            bracket fits its three cyclic labellings equally well, only the yoke tells them
            apart, and a wrong one is off by ~120 deg.
        relabel_angle_deg: two hypotheses whose attitudes differ by more than this are
            different labellings (the same labelling from two pieces of one strut differs by
            a few degrees).
        base_candidates: paper's view (`detect_partial`): the longest this many candidates
            are tried as the base strut.
        stub_candidates: paper's view: at each end of a base, the this many candidates
            starting nearest that end are tried as its side strut.
        end_sigma_px, end_sigma_rel: paper's view: the noise of a visible strut end along its
            strut (where the array hides it), ``end_sigma_px + end_sigma_rel * length`` [px].
        max_end_chi: a hypothesis whose visible strut ends lie farther than this many of those
            sigmas from where the known visible fraction puts them is rejected.
        width_ratio_range: measured over predicted (``f 2 r / z``) strut width allowed (edge
            detection on a shaded cylinder measures it narrower than its silhouette).
        max_width_spread: each strut's log width ratio (measured over ``f 2 r / z``) is
            weighed by its deviation from the three's mean (one scale for all three) with a
            standard deviation of half this, and a deviation counts as at most this: beyond
            it the misfit grows no more (a truncated quadratic). A bar is the part of its
            strut brighter than the background, and with the sun to one side that is a
            different fraction of each strut's silhouette (the true struts as found, at
            their true pose, on the bracket family's tuning seeds 0-75: log spread above
            0.35 in 11 % of the frames, 99th percentile 0.64; seed 74, 1.35 m: a stub lit
            on a 6 px sliver of its 14 px silhouette).
        width_spread_gate: a hypothesis whose strut widths spread further than this (log
            ratio to their mean) is rejected: a factor 2 between a strut's lit fraction and
            the mean of the three.
        taper_floor: the noise of a wide strut's taper (`measure_taper`) that its own scatter
            does not show, added in quadrature (a shaded limb, the lit part of a side-lit strut
            and the blur change a little along a strut): the spread of measured minus true
            tapers on the bracket family's tuning seeds (docs/bracket.md, "Strut taper").
        taper_floor_px2: > 0: below ``sqrt(taper_floor_px2 / taper_floor)`` px the floor is
            ``taper_floor_px2 / w**2`` for a strut ``w`` px wide (`taper_noise`): the blur
            merges a narrow strut's edges, so its taper's error grows faster than ``1 / w``.
            2.5 px^2 (11 px) makes the measured minus true tapers over their sigma have an
            rms of 1 in every width band from 5 to 10 px on the tuning seeds 0-99, where the
            constant floor leaves 1.2-1.6 at 8-10 px (docs/results/bracket_taper.md). Not
            the default: with it (and ``taper_min_width_px`` 6) the decision over frames
            on tuning 76-99 lost more frames than it gained (docs/bracket.md, "Narrow
            struts' tapers and a bias their frames share").
        max_taper_chi: a strut's taper misfit counts as at most this many sigmas (a truncated
            square, in the single frame's verification and in the fits of
            `PartialImageModel`: an outlying measurement, e.g. a cell line along a strut,
            cannot veto the true pose; what tells the poses apart is the sum over struts and
            frames).
        taper_min_width_px: a strut narrower than this [px] has its taper ignored: there the
            blur merges its two edges and the measured taper is compressed (two thirds of the
            true one at 5-6 px on the family's tuning seeds 0-99) and noisy (robust spread
            0.07-0.09 at 5-8 px, 0.03-0.05 at 8-10 px).
        use_taper: weigh the struts' tapers (with a known ``strut_radius_m``); False: the
            hypotheses are verified and weighed as before the taper was measured.
        gate_deg, gate_rel: tracking: a pose farther than ``gate_deg`` in attitude or
            ``gate_rel`` x range (+ 2 cm) in position from the predicted (or reference) pose
            is refused ("departs from the prediction").
        rival_deg, rival_rel: paper's view without a prediction: a second consistent
            hypothesis (another labelling, or another P3P solution of the same labelling)
            whose pose differs from the best by more than ``rival_deg`` in attitude or
            ``rival_rel`` x range in position makes the frame ambiguous (refused).
    """

    blur_sigma_px: float = 1.2
    min_segment_px: float = 15.0
    max_angle_deg: float = 3.0
    short_edge_px: float = 4.0
    short_taper: float = 0.5
    bar_width_px: tuple[float, float] = (3.0, 120.0)
    merge_distance_px: float = 4.0
    merge_width_ratio: float = 1.5
    candidates: int = 8
    end_tolerance: float = 0.12
    track_distance_px: float = 25.0
    face_sign: int = 1
    min_sigma_px: float = 0.3
    strut_radius_m: float | None = 0.015
    yoke_weight: float = 2.0
    min_yoke_margin: float = 0.25
    relabel_angle_deg: float = 30.0
    base_candidates: int = 150
    stub_candidates: int = 4
    end_sigma_px: float = 3.0
    end_sigma_rel: float = 0.05
    max_end_chi: float = 3.0
    width_ratio_range: tuple[float, float] = (0.35, 1.8)
    max_width_spread: float = 0.35
    width_spread_gate: float = 0.7
    taper_floor: float = 0.02
    taper_floor_px2: float = 0.0
    max_taper_chi: float = 3.0
    taper_min_width_px: float = 8.0
    use_taper: bool = True
    gate_deg: float = 15.0
    gate_rel: float = 0.25
    rival_deg: float = 8.0
    rival_rel: float = 0.05
    vertex_sigma_px: float = 2.0
    direction_sigma_deg: float = 0.35


@dataclass(frozen=True)
class Strut:
    """A strut candidate: centre line ``point + s * direction`` observed over ``[s0, s1]``.

    ``taper`` (`measure_taper`): the log ratio of its image widths at ``s = taper_span[1]``
    and ``taper_span[0]`` with its standard deviation ``taper_sigma``; NaN: not measured.

    ``edges``: a bar of the short-edge pass whose two edges differ in direction by more than
    ``max_angle_deg``: its two edge lines ``(2, 4)``, rows ``x, y, ux, uy`` (a point and the
    unit direction); None otherwise. Which of them is the stub's silhouette is told by the
    stub's role in a hypothesis (`_exterior_stub`).
    """

    point: np.ndarray
    direction: np.ndarray
    s0: float
    s1: float
    support_px: float
    residual_px: float
    width_px: float = 0.0
    taper: float = math.nan
    taper_sigma: float = math.nan
    taper_span: tuple[float, float] = (math.nan, math.nan)
    edges: np.ndarray | None = None

    def end(self, which: int) -> np.ndarray:
        return self.point + (self.s0 if which == 0 else self.s1) * self.direction

    @property
    def length(self) -> float:
        return self.s1 - self.s0


@dataclass(frozen=True)
class StrutDetection:
    """What `detect_struts` found.

    Attributes:
        observation: the four points with their noise, or None.
        struts: (base, strut from P1, strut from P2) when found.
        segments: every LSD segment (N, 4) ``x1, y1, x2, y2`` (for overlays).
        candidates: every strut candidate.
        result: the pose solved while choosing the hypothesis (no covariance), or None.
        reason: why ``observation`` is None ("" when found).
        hypotheses: how many hypotheses were solved.
        alternatives: `detect_partial` without a prediction: one detection per distinct
            consistent pose, best first (several: the frame is refused as ambiguous; they
            are the candidates the decision over frames weighs, `partial_hypotheses`).
        image_chi2: `detect_partial`: the verification's misfit of this hypothesis (squared
            normalised misfits of the visible strut ends and the strut widths; `_verify`),
            NaN otherwise.
    """

    observation: BracketObservation | None
    struts: tuple[Strut, Strut, Strut] | None
    segments: np.ndarray
    candidates: tuple[Strut, ...] = ()
    result: BracketResult | None = None
    reason: str = ""
    hypotheses: int = field(default=0)
    alternatives: tuple[StrutDetection, ...] = ()
    image_chi2: float = math.nan


# the struts as pairs of bracket vertices (P1, P2, P5): the base, from P1, from P2
STRUT_AXES = ((0, 1), (0, 2), (1, 2))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _angle_between(d1: np.ndarray, d2: np.ndarray) -> float:
    c = abs(float(d1 @ d2))
    return math.degrees(math.acos(min(1.0, c)))


def _fit_line(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted total-least-squares line: (point, unit direction, RMS perpendicular residual)."""
    w = weights / weights.sum()
    c = w @ points
    X = (points - c) * np.sqrt(w)[:, None]
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    d = _canonical_direction(Vt[0])
    n = np.array([-d[1], d[0]])
    res = float(np.sqrt(w @ ((points - c) @ n) ** 2))
    return c, d, res


def _canonical_direction(d: np.ndarray) -> np.ndarray:
    """``d`` or ``-d``, whichever points to +x (to +y when vertical): a line's direction
    must not depend on the sign an SVD or a detector happens to return."""
    return -d if (d[0] < 0 or (d[0] == 0 and d[1] < 0)) else d


def canonical_segments(seg: np.ndarray) -> np.ndarray:
    """Segments ``(N, 4)`` ``x1, y1, x2, y2``, each oriented by `_canonical_direction` and the
    rows sorted: the order and direction conventions of a line detector (LSD orients a
    segment by its gradient, in an order of its own) then cannot change what is built from
    them."""
    s = np.asarray(seg, dtype=float).reshape(-1, 4).copy()
    d = s[:, 2:] - s[:, :2]
    flip = (d[:, 0] < 0) | ((d[:, 0] == 0) & (d[:, 1] < 0))
    s[flip] = s[flip][:, [2, 3, 0, 1]]
    return s[np.lexsort(s.T[::-1])]


def _intersect(a: Strut, b: Strut) -> np.ndarray | None:
    A = np.stack([a.direction, -b.direction], axis=1)
    if abs(np.linalg.det(A)) < 1e-6:
        return None
    s, _ = np.linalg.solve(A, b.point - a.point)
    return a.point + s * a.direction


def line_segments(image: np.ndarray, config: StrutDetectorConfig) -> np.ndarray:
    """LSD segments ``(N, 4)`` of a grey image (uint8/uint16/float), at least
    ``min_segment_px`` long, in `canonical_segments` order and direction."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    f = img.astype(np.float32)
    f = 255.0 * f / max(float(f.max()), 1e-6)
    f = cv2.GaussianBlur(f, (0, 0), config.blur_sigma_px)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    lines = lsd.detect(f.astype(np.uint8))[0]
    if lines is None:
        return np.zeros((0, 4))
    seg = canonical_segments(lines)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    return seg[length >= config.min_segment_px]


def _bars(
    image: np.ndarray, seg: np.ndarray, config: StrutDetectorConfig, short_edges: bool = False
) -> list[Strut]:
    """Bright bars: pairs of parallel segments with brighter pixels between them (the same
    bars whatever the order and direction of ``seg``'s rows). ``short_edges``: two short
    edges may differ in direction by more than ``max_angle_deg`` (``short_edge_px``)."""
    seg = canonical_segments(seg)
    h, w = image.shape[:2]
    img = image.astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), config.blur_sigma_px)

    def sample(p: np.ndarray) -> float:
        # nearest pixel, clipped (Python scalars: np.clip per call dominated the search time)
        x = min(max(round(float(p[0])), 0), w - 1)
        y = min(max(round(float(p[1])), 0), h - 1)
        return float(img[y, x])

    p = seg[:, :2]
    q = seg[:, 2:]
    d = q - p
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    bars: list[Strut] = []
    end_px = config.short_edge_px if short_edges else 0.0
    taper = config.short_taper if short_edges else 0.0
    for i, j in _parallel_pairs(p, q, u, length, config, end_px, taper):
        ui = u[i]
        n = np.array([-ui[1], ui[0]])
        mid_j = 0.5 * (p[j] + q[j])
        sep = float((mid_j - p[i]) @ n)
        if not config.bar_width_px[0] <= abs(sep) <= config.bar_width_px[1]:
            continue
        # overlap along ui
        a = sorted([0.0, float(length[i])])
        b = sorted([float((p[j] - p[i]) @ ui), float((q[j] - p[i]) @ ui)])
        lo, hi = max(a[0], b[0]), min(a[1], b[1])
        if hi - lo < 0.5 * min(length[i], length[j]):
            continue
        # brighter between the two edges than just outside them
        s_mid = 0.5 * (lo + hi)
        base = p[i] + s_mid * ui
        centre = base + 0.5 * sep * n
        outside_i = base - 0.35 * sep * n
        outside_j = base + 1.35 * sep * n
        vc = sample(centre)
        if not (vc > sample(outside_i) + 8.0 and vc > sample(outside_j) + 8.0):
            continue
        pts = np.array([p[i], q[i], p[j], q[j]]) - 0.0
        pts_c = pts + np.array([0.5, 0.5, -0.5, -0.5])[:, None] * sep * n
        c, dirn, res = _fit_line(pts_c, np.array([length[i]] * 2 + [length[j]] * 2))
        s = (pts_c - c) @ dirn
        skew = short_edges and abs(float(u[i] @ u[j])) < math.cos(
            math.radians(config.max_angle_deg)
        )
        bars.append(
            Strut(
                point=c,
                direction=dirn,
                s0=float(s.min()),
                s1=float(s.max()),
                support_px=float(hi - lo),
                residual_px=res,
                width_px=abs(sep),
                edges=np.array([[*p[i], *u[i]], [*p[j], *u[j]]]) if skew else None,
            )
        )
    return bars


def _parallel_pairs(
    p: np.ndarray,
    q: np.ndarray,
    u: np.ndarray,
    length: np.ndarray,
    config: StrutDetectorConfig,
    end_px: float = 0.0,
    taper: float = 0.0,
) -> list[tuple[int, int]]:
    """Index pairs ``i < j`` of segments that are parallel within ``max_angle_deg`` (or,
    with ``end_px`` > 0, within ``atan(max(end_px, taper * sep) / l)``, ``l`` the shorter
    one's length and ``sep`` their separation, if that is more), whose separation is within
    ``bar_width_px`` and that overlap along ``i`` by at least half the shorter one: the
    cheap tests of `_bars`, in numpy, in the order of ``itertools.combinations``
    (a solar array's cell grid gives thousands of segments)."""
    n = len(p)
    if n < 2:
        return []
    max_rad = math.radians(config.max_angle_deg)
    out: list[tuple[int, int]] = []
    normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
    mid = 0.5 * (p + q)
    for i in range(n - 1):
        j = np.arange(i + 1, n)
        shorter = np.minimum(length[i], length[j])
        sep = np.abs((mid[j] - p[i]) @ normal[i])
        tol = (
            np.maximum(max_rad, np.arctan2(np.maximum(end_px, taper * sep), shorter))
            if end_px > 0
            else max_rad
        )
        ok = np.abs(u[j] @ u[i]) >= np.cos(tol)
        ok &= (sep >= config.bar_width_px[0]) & (sep <= config.bar_width_px[1])
        a = (p[j] - p[i]) @ u[i]
        b = (q[j] - p[i]) @ u[i]
        lo = np.maximum(0.0, np.minimum(a, b))
        hi = np.minimum(length[i], np.maximum(a, b))
        ok &= hi - lo >= 0.5 * np.minimum(length[i], length[j]) - 1e-9
        out.extend((i, int(k)) for k in j[ok])
    return out


def _merge(bars: list[Strut], config: StrutDetectorConfig, by_width: bool = False) -> list[Strut]:
    """Collinear bars -> one strut each (greedy, longest first). ``by_width``: only bars whose
    widths agree within ``merge_width_ratio`` (the paper's view, where short stubs lie in line
    with a cell grid; `detect_struts`, the whole triangle, merges as before)."""
    order = sorted(bars, key=lambda b: -b.length)
    used = [False] * len(order)
    out: list[Strut] = []
    cos_max = math.cos(math.radians(config.max_angle_deg))
    for i, b in enumerate(order):
        if used[i]:
            continue
        group = [b]
        used[i] = True
        n = np.array([-b.direction[1], b.direction[0]])
        for j in range(i + 1, len(order)):
            o = order[j]
            if used[j] or abs(float(o.direction @ b.direction)) < cos_max:
                continue
            if abs(float((o.point - b.point) @ n)) > config.merge_distance_px:
                continue
            wide, narrow = max(o.width_px, b.width_px), min(o.width_px, b.width_px)
            if by_width and wide > config.merge_width_ratio * narrow:
                continue
            group.append(o)
            used[j] = True
        pts = np.concatenate([np.array([g.end(0), g.end(1)]) for g in group])
        wts = np.repeat([g.support_px for g in group], 2)
        c, dirn, res = _fit_line(pts, wts)
        s = (pts - c) @ dirn
        out.append(
            Strut(
                point=c,
                direction=dirn,
                s0=float(s.min()),
                s1=float(s.max()),
                support_px=float(sum(g.support_px for g in group)),
                residual_px=max(res, max(g.residual_px for g in group)),
                width_px=float(
                    sum(g.width_px * g.support_px for g in group) / sum(g.support_px for g in group)
                ),
                edges=group[0].edges if len(group) == 1 else None,
            )
        )
    return out


def _oriented(strut: Strut, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The strut's (near end, far end) as seen from ``start``."""
    e0, e1 = strut.end(0), strut.end(1)
    if np.linalg.norm(e0 - start) <= np.linalg.norm(e1 - start):
        return e0, e1
    return e1, e0


def _observation(
    base: Strut, s1: Strut, s2: Strut, config: StrutDetectorConfig
) -> BracketObservation | None:
    p1 = _intersect(base, s1)
    p2 = _intersect(base, s2)
    if p1 is None or p2 is None:
        return None
    _, p4 = _oriented(s1, p1)
    _, p3 = _oriented(s2, p2)
    # A strut that runs into the apex is detected up to half a width beyond it; its visible
    # end cannot lie past the apex: keep p3, p4 short of it (only their line matters).
    p5 = _intersect(s1, s2)
    if p5 is not None:
        for start, name in ((p1, "p4"), (p2, "p3")):
            end = p4 if name == "p4" else p3
            full = float(np.linalg.norm(p5 - start))
            along = float((end - start) @ _unit(p5 - start)) if full > 0 else 0.0
            if along > 0.97 * full:
                clamped = start + 0.97 * (p5 - start)
                if name == "p4":
                    p4 = clamped
                else:
                    p3 = clamped
    sigma = max(config.min_sigma_px, base.residual_px, s1.residual_px, s2.residual_px)
    return BracketObservation(p1_px=p1, p2_px=p2, p3_px=p3, p4_px=p4, sigma_px=sigma)


def _exterior_stub(stub: Strut, inside: np.ndarray) -> Strut:
    """A short-edge bar (``stub.edges`` set) as a side strut whose triangle lies toward the
    image point ``inside``: its centre line along the *exterior* edge, half its width in.
    On a thick short stub the interior edge is the one that bends: where a stub leaves the
    base its interior edge meets the base's in a concave corner (the two struts' images and
    shading overlap over about a strut width), and on a side-lit stub it can be the
    terminator of the lit half. Over a stub two or three widths long that turns the whole
    LSD edge (bracket family tuning seed 20: interior edges 4.6 and 5.4 deg off, toward the
    base's direction; exterior 0.1 and 1.2 deg; their mean 2.4-3.0 deg off, and the apex,
    five stub lengths on, moves with it). Other candidates are returned as they are."""
    if stub.edges is None:
        return stub
    n = np.array([-stub.direction[1], stub.direction[0]])
    side_in = 1.0 if float((inside - stub.point) @ n) > 0 else -1.0
    offs = [float((e[:2] - stub.point) @ n) * side_in for e in stub.edges]
    e = stub.edges[int(np.argmin(offs))]  # the edge farthest from the inside
    u = e[2:] if float(e[2:] @ stub.direction) > 0 else -e[2:]
    m = np.array([-u[1], u[0]])
    m = m if float((inside - e[:2]) @ m) > 0 else -m
    point = e[:2] + 0.5 * stub.width_px * m
    ends = np.array([stub.end(0), stub.end(1)])
    s = (ends - point) @ u
    return replace(stub, point=point, direction=u, s0=float(s.min()), s1=float(s.max()), edges=None)


def _plausible(base: Strut, s1: Strut, s2: Strut, config: StrutDetectorConfig) -> bool:
    """The base meets both struts near its observed ends; each strut is seen from its base
    vertex (the paper's partly visible struts) or up to the apex (a whole triangle in view
    whose strut is broken near the base vertex), and does not reach past either."""
    p1 = _intersect(base, s1)
    p2 = _intersect(base, s2)
    if p1 is None or p2 is None:
        return False
    L = float(np.linalg.norm(p2 - p1))
    if L < 2 * config.min_segment_px:
        return False
    tol = config.end_tolerance * L + 2 * config.merge_distance_px
    b0, b1 = base.end(0), base.end(1)
    ends_ok = (np.linalg.norm(b0 - p1) < tol and np.linalg.norm(b1 - p2) < tol) or (
        np.linalg.norm(b1 - p1) < tol and np.linalg.norm(b0 - p2) < tol
    )
    if not ends_ok:
        return False
    near1, far1 = _oriented(s1, p1)
    near2, far2 = _oriented(s2, p2)
    p5 = _intersect(s1, s2)
    for near, far, start in ((near1, far1, p1), (near2, far2, p2)):
        if np.linalg.norm(near - start) <= tol:
            continue
        if p5 is None or np.linalg.norm(far - p5) > tol:
            return False
        # anchored at the apex only: it must lie between the base vertex and the apex
        full = float(np.linalg.norm(p5 - start))
        u = (p5 - start) / full if full > 0 else p5 - start
        if float((near - start) @ u) < 0 or float((far - start) @ u) > full + tol:
            return False
    # the struts leave the base on the same side
    n = np.array([-(p2 - p1)[1], (p2 - p1)[0]])
    return float((far1 - p1) @ n) * float((far2 - p2) @ n) > 0


def _face_ok(pose: Rigid3, geometry: BracketGeometry, sign: int) -> bool:
    v = geometry.vertices_m
    normal = pose.rotate(np.cross(v[1] - v[0], v[2] - v[0]))
    centre = pose.apply(v.mean(axis=0)[None])[0]
    # camera at the origin: it is on the normal's side if (0 - centre) . normal > 0
    return sign * float(-centre @ normal) > 0


def _apex_rays(obs: BracketObservation, K: np.ndarray) -> np.ndarray:
    pts = obs.points()
    p5, _ = strut_apex(pts)
    rays = np.c_[np.array([pts[0], pts[1], p5]), np.ones(3)] @ np.linalg.inv(K).T
    return rays / rays[:, 2:3]


def width_prior(
    obs: BracketObservation,
    struts: tuple[Strut, Strut, Strut],
    geometry: BracketGeometry,
    K: np.ndarray,
    radius_m: float,
) -> np.ndarray | None:
    """Depths ``d1, d2, d5`` of the P3P solution whose struts' apparent widths (``~ f 2 r / z``
    at the middle of each strut's visible part) have the measured ratios, or None."""
    rays = _apex_rays(obs, K)
    cands = p3p_depths(rays, geometry.sides_m)
    if len(cands) == 0:
        return None
    K_inv = np.linalg.inv(K)
    f = float(K[0, 0])
    best, best_cost = None, math.inf
    measured = np.log([max(st.width_px, 1e-6) for st in struts])
    for d in cands:
        P = d[:, None] * rays
        predicted = []
        for strut, (a, b) in zip(struts, STRUT_AXES, strict=True):
            mid = 0.5 * (strut.end(0) + strut.end(1))
            w = K_inv @ np.array([mid[0], mid[1], 1.0])
            e = P[b] - P[a]
            A = np.stack([w, -e], axis=1)
            sol, *_ = np.linalg.lstsq(A, P[a], rcond=None)
            z = float((sol[0] * w)[2])
            predicted.append(f * 2 * radius_m / z if z > 0 else 1e-9)
        # Scale-free: edge detection on a shaded cylinder measures it narrower than its
        # silhouette by a common factor; compare the width *ratios* only.
        diff = measured - np.log(predicted)
        cost = float(np.sum((diff - diff.mean()) ** 2))
        if cost < best_cost:
            best, best_cost = d, cost
    return best


def _mean_along(img: np.ndarray, a: np.ndarray, b: np.ndarray, n: int = 24) -> float:
    """Median grey value on the segment ``a -> b`` (nearest pixel, clipped to the image)."""
    h, w = img.shape[:2]
    t = np.linspace(0.0, 1.0, n)[:, None]
    p = a + t * (b - a)
    x = np.clip(np.round(p[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(p[:, 1]).astype(int), 0, h - 1)
    inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    if not np.any(inside):
        return math.nan
    return float(np.median(img[y[inside], x[inside]]))


def yoke_ratio(
    img: np.ndarray, p1: np.ndarray, p2: np.ndarray, p5: np.ndarray, struts: tuple[Strut, ...]
) -> float:
    """Grey level just beyond the apex, outward (where the yoke to the wing is), over the grey
    level on the struts' centre lines: ~1 at the true apex (the yoke is strut material), lower
    beyond a base vertex (foil or space). NaN when the apex is outside the image."""
    width = float(np.mean([s.width_px for s in struts]))
    out = _unit(p5 - 0.5 * (p1 + p2))
    beyond = _mean_along(img, p5 + 1.0 * width * out, p5 + 3.0 * width * out)
    on = np.nanmedian([_mean_along(img, s.end(0), s.end(1)) for s in struts])
    if not (np.isfinite(beyond) and on > 0):
        return math.nan
    return beyond / float(on)


def detect_struts(
    image: np.ndarray,
    K: np.ndarray,
    geometry: BracketGeometry,
    config: StrutDetectorConfig | None = None,
    predicted: Rigid3 | None = None,
    reference: Rigid3 | None = None,
) -> StrutDetection:
    """The bracket's three struts and the points `solve_bracket` needs.

    Args:
        image: grey (or BGR) undistorted image.
        K: its 3x3 intrinsics.
        geometry: the bracket (target frame).
        config: detector settings.
        predicted: ``left_cam_from_target`` predicted for this frame (tracking), or None.
        reference: without ``predicted``: a recent pose (a lost track); among the consistent
            hypotheses the one with the closest attitude wins instead of the yoke cue.

    Returns:
        A `StrutDetection`; ``observation`` is None with a ``reason`` when the struts are not
        found (never an exception for image content).
    """
    cfg = StrutDetectorConfig() if config is None else config
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.size == 0 or float(img.max()) <= float(img.min()):
        return StrutDetection(None, None, np.zeros((0, 4)), reason="empty or uniform image")
    seg = line_segments(img, cfg)
    if len(seg) < 2:
        return StrutDetection(None, None, seg, reason=f"only {len(seg)} line segments")
    scaled = img.astype(np.float32) * (255.0 / float(img.max()))
    cands = _merge(_bars(scaled, seg, cfg), cfg)
    cands = sorted(cands, key=lambda c: -c.support_px)
    if len(cands) < 3:
        return StrutDetection(
            None, None, seg, tuple(cands), reason=f"{len(cands)} strut candidates (need 3)"
        )
    solver = BracketConfig(covariance=False)
    if predicted is not None:
        v = geometry.vertices_m
        pix = project(predicted, v, K)
        picks: list[Strut] = []
        for a, b in STRUT_AXES:
            d = _unit(pix[b] - pix[a])
            n = np.array([-d[1], d[0]])
            best: Strut | None = None
            best_cost = math.inf
            for c in cands:
                if _angle_between(c.direction, d) > 4 * cfg.max_angle_deg:
                    continue
                dist = abs(float((c.point - pix[a]) @ n))
                # the longest candidate along the predicted line (a short piece near it may be
                # a shadow edge or the strut's other half)
                if dist < cfg.track_distance_px and -c.support_px < best_cost:
                    best, best_cost = c, -c.support_px
            if best is None or any(best is p for p in picks):
                return StrutDetection(
                    None, None, seg, tuple(cands), reason="a strut is not near its prediction"
                )
            picks.append(best)
        base, s1, s2 = picks
        obs = _observation(base, s1, s2, cfg)
        if obs is None:
            return StrutDetection(None, None, seg, tuple(cands), reason="struts parallel")
        # among several P3P solutions the one nearest the prediction's depths (z of P1, P2, P5)
        res = solve_bracket(
            obs, geometry, K, solver, prior_depths=predicted.apply(geometry.vertices_m)[:, 2]
        )
        if res.pose is not None and not _within_gate(
            res.pose, predicted, cfg, geometry.vertices_m.mean(axis=0)
        ):
            # the candidates nearest the projected struts gave a pose the motion cannot
            # explain (a neighbouring edge taken for a strut): refused, the caller searches
            ang, dist = _pose_distance(res.pose, predicted, geometry.vertices_m.mean(axis=0))
            return StrutDetection(
                None,
                None,
                seg,
                tuple(cands),
                reason=f"tracked pose departs from the prediction by {ang:.1f} deg, "
                f"{1e3 * dist:.0f} mm",
                hypotheses=1,
            )
        return StrutDetection(obs, (base, s1, s2), seg, tuple(cands), res, res.reason, 1)
    best_det: StrutDetection | None = None
    best_score = -math.inf
    scored: list[tuple[float, Rigid3]] = []  # (yoke ratio, pose) of every consistent hypothesis
    blurred = cv2.GaussianBlur(scaled, (0, 0), cfg.blur_sigma_px)
    tried = 0
    top = cands[: cfg.candidates]
    for base, s1, s2 in itertools.permutations(top, 3):
        if not _plausible(base, s1, s2, cfg):
            continue
        obs = _observation(base, s1, s2, cfg)
        if obs is None:
            continue
        tried += 1
        struts = (base, s1, s2)
        prior = (
            width_prior(obs, struts, geometry, K, cfg.strut_radius_m)
            if cfg.strut_radius_m is not None
            else None
        )
        res = solve_bracket(obs, geometry, K, solver, prior_depths=prior)
        if res.pose is None or not _face_ok(res.pose, geometry, cfg.face_sign):
            continue
        score = 0.0
        if reference is not None:
            # re-acquisition after a lost track: stay closest to the last attitude
            dR = reference.R.T @ res.pose.R
            score = -math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2))))
        elif res.apex_px is not None:
            pts = obs.points()
            ratio = yoke_ratio(blurred, pts[0], pts[1], res.apex_px, struts)
            ratio = ratio if np.isfinite(ratio) else 0.0
            score = cfg.yoke_weight * ratio
            scored.append((ratio, res.pose))
        score += (base.support_px + s1.support_px + s2.support_px) / 1e6  # tie-break
        if score > best_score:
            best_score = score
            best_det = StrutDetection(obs, struts, seg, tuple(cands), res, "", tried)
    if best_det is None:
        return StrutDetection(
            None,
            None,
            seg,
            tuple(cands),
            reason=f"no consistent bracket among {len(top)} strut candidates ({tried} tried)",
        )
    if (
        reference is not None
        and best_det.result is not None
        and best_det.result.pose is not None
        and not _within_gate(best_det.result.pose, reference, cfg, geometry.vertices_m.mean(axis=0))
    ):
        # the re-detection's closest labelling is still far from the last pose: no
        # labelling in this frame is consistent with the track (seen: 342 mm / 21 deg)
        ang, dist = _pose_distance(
            best_det.result.pose, reference, geometry.vertices_m.mean(axis=0)
        )
        return StrutDetection(
            None,
            None,
            seg,
            tuple(cands),
            reason=f"re-detection departs from the last pose by {ang:.1f} deg, {1e3 * dist:.0f} mm",
            hypotheses=tried,
        )
    if (
        reference is None
        and cfg.yoke_weight > 0
        and best_det.result is not None
        and best_det.result.pose is not None
    ):
        margin = _labelling_margin(best_det.result.pose, scored, cfg.relabel_angle_deg)
        if margin < cfg.min_yoke_margin:
            return StrutDetection(
                None,
                None,
                seg,
                tuple(cands),
                reason=(
                    f"labelling ambiguous: the best labelling's yoke ratio exceeds another's "
                    f"(or none) by {margin:.2f} (need {cfg.min_yoke_margin:.2f})"
                ),
                hypotheses=tried,
            )
    return best_det


def _rotation_deg(a: Rigid3, b: Rigid3) -> float:
    c = (float(np.trace(a.R.T @ b.R)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _labelling_margin(best: Rigid3, scored: list[tuple[float, Rigid3]], angle_deg: float) -> float:
    """Yoke ratio of ``best`` minus the largest yoke ratio of a hypothesis with another
    labelling (attitude more than ``angle_deg`` away), or minus 0 (no yoke) if larger."""
    own = max((r for r, pose in scored if _rotation_deg(pose, best) <= angle_deg), default=0.0)
    other = [r for r, pose in scored if _rotation_deg(pose, best) > angle_deg]
    return own - max([0.0, *other])


# --- the paper's view: base strut and two stubs, the apex hidden -------------------------------


def _strut_widths_predicted(
    pose: Rigid3,
    struts: tuple[Strut, Strut, Strut],
    geometry: BracketGeometry,
    K: np.ndarray,
    radius_m: float,
) -> np.ndarray:
    """Apparent width ``f 2 r / z`` [px] of each strut at the middle of its detected part,
    ``z`` where that pixel's ray meets the posed strut's axis."""
    P = pose.apply(geometry.vertices_m)
    K_inv = np.linalg.inv(K)
    f = float(K[0, 0])
    out = []
    for strut, (a, b) in zip(struts, STRUT_AXES, strict=True):
        mid = 0.5 * (strut.end(0) + strut.end(1))
        w = K_inv @ np.array([mid[0], mid[1], 1.0])
        A = np.stack([w, -(P[b] - P[a])], axis=1)
        sol, *_ = np.linalg.lstsq(A, P[a], rcond=None)
        z = float((sol[0] * w)[2])
        out.append(f * 2 * radius_m / z if z > 0 else math.nan)
    return np.array(out)


def _verify(
    obs: BracketObservation,
    struts: tuple[Strut, Strut, Strut],
    pose: Rigid3,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    radius_m: float | None,
    cfg: StrutDetectorConfig,
) -> tuple[float, str]:
    """Consistency of a solved hypothesis with the known geometry: ``(cost, "")`` or
    ``(inf, why)``. The cost sums the squared normalised misfits of the visible strut ends
    (where the known visible fraction puts them, along each strut) and of the strut widths
    (one common scale: ``f 2 r / z``)."""
    if not _face_ok(pose, geometry, cfg.face_sign):
        return math.inf, "camera on the bracket's wrong face"
    v = geometry.vertices_m
    cost = 0.0
    if fraction < 1.0:
        ends = np.array([v[0] + fraction * (v[2] - v[0]), v[1] + fraction * (v[2] - v[1])])
        pix = project(pose, ends, K)
        for strut, start, e_pred in (
            (struts[1], obs.p1_px, pix[0]),
            (struts[2], obs.p2_px, pix[1]),
        ):
            assert start is not None
            _, far = _oriented(strut, start)
            length = float(np.linalg.norm(far - start))
            if length < 1.0:
                return math.inf, "a side strut shorter than 1 px"
            u = (far - start) / length
            sigma = cfg.end_sigma_px + cfg.end_sigma_rel * length
            e = float((far - e_pred) @ u) / sigma
            if abs(e) > cfg.max_end_chi:
                return math.inf, f"a visible strut end is {abs(e):.1f} sigma off the fraction"
            cost += e * e
    if radius_m is not None:
        pred = _strut_widths_predicted(pose, struts, geometry, K, radius_m)
        if not np.all(np.isfinite(pred)) or np.any(pred <= 0):
            return math.inf, "a strut behind the camera"
        lr = np.log(np.maximum([s.width_px for s in struts], 1e-6) / pred)
        lo, hi = (math.log(x) for x in cfg.width_ratio_range)
        mean = float(lr.mean())
        if not lo <= mean <= hi:
            return math.inf, f"strut width {math.exp(mean):.2f} x the predicted"
        spread = float(np.max(np.abs(lr - mean)))
        if spread > cfg.width_spread_gate:
            return math.inf, f"strut widths inconsistent (log spread {spread:.2f})"
        dev = np.minimum(np.abs(lr - mean), cfg.max_width_spread)
        cost += float(np.sum((dev / (cfg.max_width_spread / 2)) ** 2))
        for strut, (i, j) in zip(struts, STRUT_AXES, strict=True):
            if not _taper_used(strut, cfg):
                continue
            pred_t = predicted_taper(strut, pose, (v[i], v[j]), K, radius_m)
            if not math.isfinite(pred_t):
                return math.inf, "a strut's axis behind the camera"
            e = (strut.taper - pred_t) / taper_noise(strut, cfg)
            cost += float(_truncated_whitened(np.asarray(e), cfg.max_taper_chi) ** 2)
    return cost, ""


def _taper_used(strut: Strut, cfg: StrutDetectorConfig) -> bool:
    """Whether `_verify` weighs ``strut``'s taper: measured, wide enough, and switched on."""
    return cfg.use_taper and math.isfinite(strut.taper) and strut.width_px >= cfg.taper_min_width_px


def taper_noise(strut: Strut, cfg: StrutDetectorConfig) -> float:
    """The sigma with which ``strut``'s taper is weighed: its own (``taper_sigma``) and the
    floor of its width in quadrature, the floor ``max(taper_floor, taper_floor_px2 / w**2)``
    (`StrutDetectorConfig`)."""
    w = float(strut.width_px)
    floor = max(cfg.taper_floor, cfg.taper_floor_px2 / w**2) if w > 0 else math.inf
    return math.hypot(strut.taper_sigma, floor)


def _pose_distance(a: Rigid3, b: Rigid3, centre: np.ndarray | None = None) -> tuple[float, float]:
    """(attitude difference [deg], difference of where the two poses put ``centre``, the
    bracket's centroid in the target frame [m]; the target origin when None)."""
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
    return _rotation_deg(a, b), float(np.linalg.norm(a.apply(c[None])[0] - b.apply(c[None])[0]))


def _within_gate(
    pose: Rigid3, ref: Rigid3, cfg: StrutDetectorConfig, centre: np.ndarray | None = None
) -> bool:
    """``pose`` within ``gate_deg`` and ``gate_rel`` x range (+ 2 cm) of ``ref``, positions and
    range taken at ``centre`` (target frame)."""
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
    ang, dist = _pose_distance(pose, ref, c)
    return (
        ang <= cfg.gate_deg
        and dist <= cfg.gate_rel * float(np.linalg.norm(ref.apply(c[None])[0])) + 0.02
    )


def partial_image_quantities(
    pose: Rigid3, vertices: np.ndarray, K: np.ndarray, fraction: float, stubs: bool = True
) -> np.ndarray:
    """What `detect_partial` measures, as functions of the pose: ``p1, p2`` [px], the image
    directions of the struts ``P1P5``, ``P2P5`` at their base vertices [rad] and (``stubs``
    and ``fraction`` < 1) the lengths of the visible stubs [px]; (6,) or (8,)."""
    V = np.asarray(vertices, dtype=float)
    ends = np.array([V[0] + fraction * (V[2] - V[0]), V[1] + fraction * (V[2] - V[1])])
    px = project(pose, np.vstack([V, ends]), K)
    d1 = px[2] - px[0]
    d2 = px[2] - px[1]
    out = [*px[0], *px[1], math.atan2(d1[1], d1[0]), math.atan2(d2[1], d2[0])]
    if stubs and fraction < 1:
        out += [float(np.linalg.norm(px[3] - px[0])), float(np.linalg.norm(px[4] - px[1]))]
    return np.array(out)


def partial_pose_covariance(
    pose: Rigid3,
    vertices: np.ndarray,
    K: np.ndarray,
    fraction: float,
    sigma_px: float,
    sigma_dir_rad: float,
    sigma_end_px: float | None = None,
) -> np.ndarray:
    """Covariance (6x6, ``[rotation (rad), translation (m)]``, right perturbation ``T Exp(xi)``,
    the `PoseMeasurement` convention) of the pose from `partial_image_quantities` with white
    errors: ``p1``, ``p2`` (``sigma_px`` per coordinate), the two strut directions
    (``sigma_dir_rad``) and, with ``sigma_end_px`` and ``fraction`` < 1, the two stub lengths;
    exact bracket. Without the stub lengths the pose is exactly determined by the six numbers
    and this is the first-order covariance of each P3P solution (every solution at its own
    pose); with them it is the Cramer-Rao bound. ``(J^T W J)^-1`` by central differences."""
    stubs = sigma_end_px is not None and fraction < 1
    J = []
    eps = 1e-6
    for i in range(6):
        e = np.zeros(6)
        e[i] = eps

        def moved(sign: float, e: np.ndarray = e) -> Rigid3:
            d = Rigid3(R=rotvec_to_matrix(sign * e[:3]), t=sign * e[3:])
            return pose @ d

        hp = partial_image_quantities(moved(1.0), vertices, K, fraction, stubs)
        hm = partial_image_quantities(moved(-1.0), vertices, K, fraction, stubs)
        d = hp - hm
        d[4:6] = (d[4:6] + math.pi) % (2 * math.pi) - math.pi  # angles: no wrap at +-pi
        J.append(d / (2 * eps))
    Jm = np.array(J).T
    sig = [sigma_px] * 4 + [sigma_dir_rad] * 2 + ([sigma_end_px] * 2 if stubs else [])
    W = np.diag(1.0 / np.square(np.asarray(sig, dtype=float)))
    C = np.linalg.pinv(Jm.T @ W @ Jm)
    return 0.5 * (C + C.T)


def partial_measured_quantities(obs: BracketObservation, fraction: float) -> np.ndarray:
    """`partial_image_quantities` as measured: ``p1, p2``, the directions ``p1 -> p4`` and
    ``p2 -> p3`` and (``fraction`` < 1) the stub lengths ``|p4 - p1|``, ``|p3 - p2|``."""
    p1, p2, p3, p4 = obs.points()
    d1, d2 = p4 - p1, p3 - p2
    out = [*p1, *p2, math.atan2(d1[1], d1[0]), math.atan2(d2[1], d2[0])]
    if fraction < 1:
        out += [float(np.linalg.norm(d1)), float(np.linalg.norm(d2))]
    return np.array(out)


def _quantity_sigmas(
    z: np.ndarray, sigma_px: float, sigma_dir_rad: float, cfg: StrutDetectorConfig
) -> np.ndarray:
    ends = [cfg.end_sigma_px + cfg.end_sigma_rel * float(x) for x in z[6:]]
    return np.array([sigma_px] * 4 + [sigma_dir_rad] * 2 + ends)


@dataclass(frozen=True)
class PartialImageModel:
    """The whitened misfit of one frame's measured quantities (`partial_measured_quantities`)
    as a function of the pose: ``r(T) = (z - h(T)) / sigma`` with ``h`` =
    `partial_image_quantities`, noise ``sigma_px`` per vertex coordinate, ``sigma_dir_rad``
    per strut direction and the verification's ``end_sigma_px + end_sigma_rel * length`` per
    stub length; then the struts' tapers (`measure_taper`), ``(taper - predicted(T)) /
    taper_noise`` clipped at ``taper_cap`` (``max_taper_chi``: the
    truncated square of the single frame's verification, `_truncated_whitened`).
    ``residual_and_jacobian`` is what a smoother needs to
    weigh the image itself (not a Gaussian approximation of the pose) against the motion
    (`satpose.backend.labelling`): near a double P3P root the likelihood of the pose is far
    from Gaussian, and the tapers are what tells those roots apart."""

    z: np.ndarray
    sigma: np.ndarray
    vertices: np.ndarray
    K: np.ndarray
    fraction: float
    tapers: tuple[TaperMeasurement, ...] = ()
    taper_cap: float = StrutDetectorConfig.max_taper_chi

    @staticmethod
    def of(
        z: np.ndarray,
        vertices: np.ndarray,
        K: np.ndarray,
        fraction: float,
        config: StrutDetectorConfig,
        struts: tuple[Strut, Strut, Strut] | None = None,
    ) -> PartialImageModel:
        """The model of quantities ``z`` with ``config``'s noise levels, and the tapers of
        ``struts`` (base, from P1, from P2) that `_verify` weighs."""
        zz = np.asarray(z, dtype=float)
        sig = _quantity_sigmas(
            zz, config.vertex_sigma_px, math.radians(config.direction_sigma_deg), config
        )
        tapers: list[TaperMeasurement] = []
        if struts is not None and config.strut_radius_m is not None:
            for st, axis in zip(struts, STRUT_AXES, strict=True):
                if _taper_used(st, config):
                    tapers.append(
                        TaperMeasurement(
                            value=st.taper,
                            sigma=taper_noise(st, config),
                            px=np.array([st.point + s * st.direction for s in st.taper_span]),
                            axis=axis,
                            radius_m=config.strut_radius_m,
                        )
                    )
        return PartialImageModel(
            zz,
            sig,
            np.asarray(vertices, float),
            np.asarray(K),
            fraction,
            tuple(tapers),
            config.max_taper_chi,
        )

    @property
    def dim(self) -> int:
        return len(self.z) + len(self.tapers)

    @property
    def shared_groups(self) -> tuple[int, ...]:
        """Per residual: -1 for the quantities ``z``, the strut (0 base, 1 from P1, 2 from
        P2: `STRUT_AXES`) for its taper, measured through the same shading and blur in
        every frame (`satpose.backend.labelling.fit_track`)."""
        return (-1,) * len(self.z) + tuple(STRUT_AXES.index(m.axis) for m in self.tapers)

    @property
    def shared_cap(self) -> float:
        """The tapers' truncation (``taper_cap``) for `satpose.backend.labelling.fit_track`."""
        return self.taper_cap

    @cached_property
    def _taper_arrays(
        self,
    ) -> tuple[list[int], list[int], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The tapers as arrays: axis vertex indices, radii, homogeneous points (m, 2, 3),
        values, sigmas, and the inverse intrinsics."""
        return (
            [m.axis[0] for m in self.tapers],
            [m.axis[1] for m in self.tapers],
            np.array([m.radius_m for m in self.tapers]),
            np.stack([np.c_[m.px, np.ones(2)] for m in self.tapers]),
            np.array([m.value for m in self.tapers]),
            np.array([m.sigma for m in self.tapers]),
            np.linalg.inv(self.K),
        )

    def _taper_residuals(self, P: np.ndarray) -> np.ndarray:
        """Whitened (truncated) taper residuals (k, m) for the posed vertices ``P`` (k, 3, 3) of
        k poses; a large prediction (1e3) where an axis end lies behind the camera or the
        camera inside the cylinder, so a fit is pushed back."""
        i0, i1, radii, x, value, sigma, K_inv = self._taper_arrays
        w = _widths_on_lines(_silhouette_lines(P[:, i0], P[:, i1], radii, K_inv), x)
        ok = (P[:, i0, 2] > 0) & (P[:, i1, 2] > 0) & np.all(w > 0, axis=-1)
        w = np.where(ok[..., None], w, 1.0)
        pred = np.where(ok, np.log(w[..., 1] / w[..., 0]), 1e3)
        return _truncated_whitened((value - pred) / sigma, self.taper_cap)

    def residual(self, pose: Rigid3) -> np.ndarray:
        """Whitened ``(z - h(pose)) / sigma``, angles wrapped, then the tapers'."""
        r = self.z - partial_image_quantities(
            pose, self.vertices, self.K, self.fraction, len(self.z) > 6
        )
        r[4:6] = (r[4:6] + math.pi) % (2 * math.pi) - math.pi
        if not self.tapers:
            return r / self.sigma
        P = pose.apply(self.vertices)[None]
        return np.concatenate([r / self.sigma, self._taper_residuals(P)[0]])

    def residual_and_jacobian(self, pose: Rigid3) -> tuple[np.ndarray, np.ndarray]:
        """``r`` and ``dr/dxi`` (m x 6) for the right perturbation ``pose Exp(xi)``,
        ``xi = [rotation, translation]`` (analytic: ``dP/dxi = [-R [X]x, R]`` for a model
        point ``X`` seen at ``P = R X + t``, through the pinhole and the quantities; the
        tapers' by central differences, 1e-6 rad / 1e-6 m)."""
        V = self.vertices
        f = self.fraction
        X = np.array([V[0], V[1], V[2], V[0] + f * (V[2] - V[0]), V[1] + f * (V[2] - V[1])])
        R, t = pose.R, pose.t
        P = X @ R.T + t
        fx, fy = float(self.K[0, 0]), float(self.K[1, 1])
        x, y, zc = P[:, 0], P[:, 1], P[:, 2]
        u = np.stack([fx * x / zc + self.K[0, 2], fy * y / zc + self.K[1, 2]], axis=1)
        # d(pixel)/dP (5, 2, 3) and dP/dxi (5, 3, 6)
        dU = np.zeros((5, 2, 3))
        dU[:, 0, 0] = fx / zc
        dU[:, 0, 2] = -fx * x / zc**2
        dU[:, 1, 1] = fy / zc
        dU[:, 1, 2] = -fy * y / zc**2
        dP = np.zeros((5, 3, 6))
        RX = np.einsum("ij,njk->nik", R, _skews(X))
        dP[:, :, :3] = -RX
        dP[:, :, 3:] = R
        Ju = np.einsum("nab,nbc->nac", dU, dP)  # (5, 2, 6)
        h = [u[0, 0], u[0, 1], u[1, 0], u[1, 1]]
        J = [Ju[0, 0], Ju[0, 1], Ju[1, 0], Ju[1, 1]]
        for a in (0, 1):  # strut directions toward the apex
            d = u[2] - u[a]
            dd = Ju[2] - Ju[a]
            h.append(math.atan2(d[1], d[0]))
            J.append((d[0] * dd[1] - d[1] * dd[0]) / float(d @ d))
        if len(self.z) > 6:
            for a, e in ((0, 3), (1, 4)):  # stub lengths
                d = u[e] - u[a]
                n = float(np.linalg.norm(d))
                h.append(n)
                J.append((d[0] * (Ju[e, 0] - Ju[a, 0]) + d[1] * (Ju[e, 1] - Ju[a, 1])) / n)
        r = self.z - np.array(h)
        r[4:6] = (r[4:6] + math.pi) % (2 * math.pi) - math.pi
        r = r / self.sigma
        Jq = -np.array(J) / self.sigma[:, None]
        if not self.tapers:
            return r, Jq
        # the vertices under the pose and its 12 central-difference steps (13, 3, 3): every
        # taper of every step in one evaluation
        Pk = np.einsum("ij,kaj->kai", R, np.einsum("kij,aj->kai", _STEP_ROT, V) + _STEP_T[:, None])
        Pk = Pk + t
        res = self._taper_residuals(Pk)  # (13, m)
        rt = res[0]
        Jt = ((res[1:7] - res[7:13]) / (2 * _STEP)).T
        return np.concatenate([r, rt]), np.vstack([Jq, Jt])


def _truncated_whitened(r: np.ndarray, cap: float) -> np.ndarray:
    """Whitened residuals ``r`` clipped at ``+-cap``: a least-squares fit of them minimises
    the truncated square ``min(r^2, cap^2)``, the cost the single frame's verification gives
    a taper (`_verify`). The measured tapers' tails are far heavier than a Gaussian's (a
    side-lit strut's lit part over a mottled panel, a cell line along a strut: 12-15 sigmas
    at the truth on tuning seed 29's closest frames), and a taper beyond a few sigmas is an
    outlier, not evidence in proportion to its size: under Huber's linear cost three such
    tapers (about 75 of half chi-square at the truth) pulled the frame's fit 6 deg off and
    the true track could not take those frames (docs/bracket.md, "Strut taper")."""
    return np.clip(r, -cap, cap)


# central-difference steps of the right perturbation ``T Exp(xi)`` for the tapers' Jacobian:
# index 0 the pose itself, 1-6 ``+_STEP`` along each of ``xi = [rotation, translation]``,
# 7-12 ``-_STEP`` (the rotation steps as matrices, the translation steps in the body frame)
_STEP = 1e-6
_STEP_XI = np.vstack([np.zeros(6), _STEP * np.eye(6), -_STEP * np.eye(6)])
_STEP_ROT = np.array([rotvec_to_matrix(x[:3]) for x in _STEP_XI])
_STEP_T = _STEP_XI[:, 3:]


@dataclass(frozen=True)
class TaperMeasurement:
    """One strut's measured taper in `PartialImageModel`: ``value`` with its noise ``sigma``
    (floor included), measured between the image points ``px`` (2, 2) of a strut whose axis
    runs between the bracket vertices ``axis`` (indices into P1, P2, P5), ``radius_m``."""

    value: float
    sigma: float
    px: np.ndarray
    axis: tuple[int, int]
    radius_m: float


def _skews(v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) cross-product matrices of the rows of ``v`` (n, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _moved(T: Rigid3, xi: np.ndarray) -> Rigid3:
    """``T`` perturbed on the right by ``xi = [rotation, translation]`` (first order equal to
    ``T Exp(xi)``)."""
    return T @ Rigid3(R=rotvec_to_matrix(xi[:3]), t=xi[3:])


def refine_partial_pose(
    pose: Rigid3, model: PartialImageModel, iterations: int = 5
) -> tuple[Rigid3, np.ndarray, float]:
    """The pose that best fits every measured quantity of ``model``, started from ``pose``
    (a P3P solution, which fits ``p1, p2`` and the strut directions exactly and ignores the
    stub lengths): Gauss-Newton with step halving. Returns ``(pose, covariance (6x6,
    [rotation, translation], right perturbation), chi2)``: the local maximum of this frame's
    likelihood, its first-order covariance and the residual chi-square (``model.dim - 6``
    degrees of freedom; without the stub lengths the pose is exactly determined: chi2 0)."""
    T = pose
    r, J = model.residual_and_jacobian(T)
    for _ in range(iterations):
        # r(T Exp(d)) ~ r + J d
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        # a step along the weakly determined tilt can be long: halve it until it helps
        for _halving in range(8):
            T_new = _moved(T, step)
            r_new = model.residual(T_new)
            if float(r_new @ r_new) <= float(r @ r):
                break
            step = 0.5 * step
        else:
            break
        done = float(r @ r) - float(r_new @ r_new) < 1e-10
        T = T_new
        r, J = model.residual_and_jacobian(T)
        if done:
            break
    C = np.linalg.pinv(J.T @ J)
    return T, 0.5 * (C + C.T), float(r @ r)


def width_chi2(
    struts: tuple[Strut, Strut, Strut],
    pose: Rigid3,
    geometry: BracketGeometry,
    K: np.ndarray,
    config: StrutDetectorConfig,
) -> float:
    """The strut widths' part of `_verify`'s misfit (2 degrees of freedom: three widths, one
    common scale); inf when they fail the check, 0 without a known strut radius."""
    if config.strut_radius_m is None:
        return 0.0
    obs = BracketObservation(
        p1_px=struts[0].end(0), p2_px=struts[0].end(1), p3_px=None, p4_px=None, sigma_px=1.0
    )
    no_taper = replace(config, use_taper=False)  # the tapers are in `PartialImageModel`
    return _verify(obs, struts, pose, geometry, K, 1.0, config.strut_radius_m, no_taper)[0]


def decided_frame_pose(
    start: Rigid3,
    model: PartialImageModel,
    decided: Rigid3 | None,
    agree: Callable[[Rigid3, Rigid3], bool],
) -> tuple[Rigid3, np.ndarray] | None:
    """The pose a frame reports once the decision over frames (`satpose.backend.labelling`)
    chose its labelling: the frame's own maximum of the likelihood in that basin, started
    from ``start`` (the decided track's pose there, else the hypothesis's), and its
    covariance; None when it is another answer than the decided track's pose ``decided``
    (``agree``: the decision's rival distance; None: no track pose to compare with).

    Without the struts' tapers first: they choose the basin, but as a pose measurement they
    are biased (measured / true 1.02-1.16 on the bracket family's tuning members,
    docs/bracket.md "Strut taper"; tuning seed 1 was reported 5-8 deg off with them). With
    them only where the points alone have no maximum near the decided track: where the
    stubs are short their directions hardly constrain the apex, and the tapers are what
    holds the pose (tuning seed 50, visible fraction 0.18: without them the refit slid 12-16
    deg off in 10 of 12 frames, with them it stays 0.8-4.2 deg from the truth). If neither
    stays near the track, the true pair of P3P roots turned complex in noise and the refit
    slid to another root: that pose is not reported (tuning seed 8, frame 0: track 12 deg,
    the frame's maximum 23 deg off)."""
    pose, cov, _ = refine_partial_pose(start, replace(model, tapers=()))
    if decided is None or agree(decided, pose):
        return pose, cov
    if model.tapers:
        pose, cov, _ = refine_partial_pose(start, model)
        if agree(decided, pose):
            return pose, cov
    return None


@dataclass(frozen=True)
class PartialHypothesis:
    """One consistent pose of a frame in the paper's view, weighed for the decision over
    frames (`satpose.backend.labelling`).

    Attributes:
        pose: the per-frame pose that is reported if this hypothesis is chosen (the
            detector's P3P / least-squares solution).
        refined: the local maximum of the likelihood of every measured quantity near
            ``pose`` (`refine_partial_pose`).
        covariance: its 6x6 covariance (``[rotation, translation]``, right perturbation).
        image_chi2: the misfit of the over-determined quantities at ``refined``: the stub
            lengths (fraction < 1) and the strut widths.
        image_dim: their number (2 per kind).
        model: the frame's measured quantities as a function of the pose.
        width_chi2: the strut widths' part of ``image_chi2`` (2 dof with a known radius).
        detection: the detection it came from (None: noise-free).
    """

    pose: Rigid3
    refined: Rigid3
    covariance: np.ndarray
    image_chi2: float
    image_dim: int
    model: PartialImageModel
    width_chi2: float = 0.0
    detection: StrutDetection | None = None


def _weigh(
    poses: list[tuple[Rigid3, StrutDetection | None]],
    obs: list[BracketObservation],
    struts: list[tuple[Strut, Strut, Strut]],
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    cfg: StrutDetectorConfig,
) -> list[PartialHypothesis]:
    """`PartialHypothesis` of each pose; poses that refine to the same one (1 deg / 1 % of
    the range) are one hypothesis, represented by the pose nearest its refinement."""
    V = geometry.vertices_m
    ctr = V.mean(axis=0)
    out: list[PartialHypothesis] = []
    for (pose, det), o, st in zip(poses, obs, struts, strict=True):
        model = PartialImageModel.of(
            partial_measured_quantities(o, fraction), V, K, fraction, cfg, st
        )
        ref, C, chi = refine_partial_pose(pose, model)
        w = width_chi2(st, ref, geometry, K, cfg)
        if not math.isfinite(w):
            w = width_chi2(st, pose, geometry, K, cfg)  # the refinement left the width check
        widths = 2 if cfg.strut_radius_m is not None else 0
        dim = (2 if fraction < 1 else 0) + widths + len(model.tapers)
        h = PartialHypothesis(pose, ref, C, chi + w, dim, model, w, det)
        range_m = float(np.linalg.norm(ref.apply(ctr[None])[0]))
        same = [
            i
            for i, q in enumerate(out)
            if _rotation_deg(ref, q.refined) <= 1.0
            and _pose_distance(ref, q.refined, ctr)[1] <= 0.01 * range_m
        ]
        if not same:
            out.append(h)
            continue
        q = out[same[0]]
        if sum(_pose_distance(pose, ref, ctr)) < sum(_pose_distance(q.pose, q.refined, ctr)):
            out[same[0]] = h
    return out


def partial_hypotheses(
    det: StrutDetection,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    config: StrutDetectorConfig | None = None,
    extra: list[StrutDetection] | None = None,
) -> list[PartialHypothesis]:
    """Every consistent pose of a `detect_partial` result (its ``alternatives``, or the one
    pose) and of ``extra`` detections of the same image (searches near predicted poses),
    weighed with ``config.vertex_sigma_px`` / ``direction_sigma_deg`` and the verification's
    stub-end noise; [] when the frame has none."""
    cfg = StrutDetectorConfig() if config is None else config
    dets = list(det.alternatives) if det.alternatives else [det]
    dets += list(extra or [])
    dets = [
        d
        for d in dets
        if d.result is not None
        and d.result.pose is not None
        and d.observation is not None
        and d.struts is not None
    ]
    return _weigh(
        [(d.result.pose, d) for d in dets if d.result is not None and d.result.pose is not None],
        [d.observation for d in dets if d.observation is not None],
        [d.struts for d in dets if d.struts is not None],
        geometry,
        K,
        fraction,
        cfg,
    )


def quantity_hypotheses(
    z: np.ndarray,
    widths_px: np.ndarray | None,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    config: StrutDetectorConfig | None = None,
    include: Rigid3 | None = None,
    taper_pose: Rigid3 | None = None,
) -> list[PartialHypothesis]:
    """The consistent poses of measured quantities ``z`` (`partial_measured_quantities`:
    ``p1, p2``, the strut directions and, ``fraction`` < 1, the stub lengths) with the three
    strut widths ``widths_px`` (base, from P1, from P2; None: not checked), as
    `detect_partial` verifies them and `partial_hypotheses` weighs them: each P3P solution
    of ``p1, p2`` and the apex (where the two strut lines meet) whose camera is on the known
    face, whose visible stub ends lie within ``max_end_chi`` sigmas of the measured ones and
    whose widths agree. ``include``: a pose tried first besides the P3P solutions (the truth,
    for noise-free analysis). ``taper_pose``: the struts' tapers are the ones this pose
    predicts (`exact_taper`; with ``widths_px``). No image: for analysis and tests on
    projections."""
    cfg = StrutDetectorConfig() if config is None else config
    if widths_px is None:
        cfg = replace(cfg, strut_radius_m=None)
    V = np.asarray(geometry.vertices_m, dtype=float)
    z = np.asarray(z, dtype=float)
    p1, p2 = z[0:2], z[2:4]
    u1 = np.array([math.cos(z[4]), math.sin(z[4])])
    u2 = np.array([math.cos(z[5]), math.sin(z[5])])
    A = np.stack([u1, -u2], axis=1)
    if abs(float(np.linalg.det(A))) < 1e-9:
        return []
    s1, _ = np.linalg.solve(A, p2 - p1)
    apex = p1 + s1 * u1
    e1, e2 = (p1 + z[6] * u1, p2 + z[7] * u2) if fraction < 1 else (apex, apex)
    w = np.zeros(3) if widths_px is None else np.asarray(widths_px, dtype=float)

    def strut(a: np.ndarray, b: np.ndarray, width: float) -> Strut:
        length = float(np.linalg.norm(b - a))
        return Strut(
            point=a,
            direction=(b - a) / max(length, 1e-12),
            s0=0.0,
            s1=length,
            support_px=length,
            residual_px=0.0,
            width_px=float(width),
        )

    struts = (strut(p1, p2, w[0]), strut(p1, e1, w[1]), strut(p2, e2, w[2]))
    if taper_pose is not None and cfg.use_taper and cfg.strut_radius_m is not None:
        r = cfg.strut_radius_m
        base, s1, s2 = (
            exact_taper(st, taper_pose, (V[i], V[j]), K, r)
            for st, (i, j) in zip(struts, STRUT_AXES, strict=True)
        )
        struts = (base, s1, s2)
    obs = BracketObservation(p1_px=p1, p2_px=p2, p3_px=e2, p4_px=e1, sigma_px=cfg.min_sigma_px)
    rays = np.c_[np.array([p1, p2, apex]), np.ones(3)] @ np.linalg.inv(K).T
    rays = rays / rays[:, 2:3]
    model = np.vstack([V, incentre(V)])
    ctr = V.mean(axis=0)
    poses: list[Rigid3] = []
    found = [include] if include is not None else []
    try:
        roots = p3p_depths(rays, triangle_sides(V))
    except (ValueError, np.linalg.LinAlgError, ZeroDivisionError):
        roots = np.zeros((0, 3))
    for d in roots:
        cam = d[:, None] * rays
        R, t = absolute_orientation(model, np.vstack([cam, incentre(cam)]))
        found.append(Rigid3(R=R, t=t))
    for cand in found:
        range_m = float(np.linalg.norm(cand.apply(ctr[None])[0]))
        if any(
            _rotation_deg(cand, q) <= 1.0 and _pose_distance(cand, q, ctr)[1] <= 0.01 * range_m
            for q in poses
        ):
            continue  # a repeated root
        if cand is include or math.isfinite(
            _verify(obs, struts, cand, geometry, K, fraction, cfg.strut_radius_m, cfg)[0]
        ):
            poses.append(cand)
    n = len(poses)
    return _weigh([(p, None) for p in poses], [obs] * n, [struts] * n, geometry, K, fraction, cfg)


def exact_widths(
    pose: Rigid3, geometry: BracketGeometry, K: np.ndarray, fraction: float, radius_m: float
) -> np.ndarray:
    """The three struts' apparent widths ``f 2 r / z`` [px] at the middle of their visible
    parts (base, from P1, from P2)."""
    V = np.asarray(geometry.vertices_m, dtype=float)
    ends = np.array([V[0] + fraction * (V[2] - V[0]), V[1] + fraction * (V[2] - V[1])])
    depth = pose.apply(np.vstack([V, ends]))[:, 2]
    f = float(K[0, 0])
    mid = [0.5 * (depth[0] + depth[1]), 0.5 * (depth[0] + depth[3]), 0.5 * (depth[1] + depth[4])]
    return np.array([f * 2 * radius_m / z for z in mid])


def noise_free_hypotheses(
    pose: Rigid3,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
    config: StrutDetectorConfig | None = None,
) -> list[PartialHypothesis]:
    """Every pose the *exact* image of the bracket at ``pose`` admits (`quantity_hypotheses`
    of the noise-free quantities and widths; the strut widths checked when
    ``config.strut_radius_m`` is set, and then their tapers too); the truth first (its
    image_chi2 is 0). What no
    detector can do better than on one frame: noise-free projections, no image."""
    cfg = StrutDetectorConfig() if config is None else config
    z = partial_image_quantities(pose, geometry.vertices_m, K, fraction)
    r = cfg.strut_radius_m
    widths = None if r is None else exact_widths(pose, geometry, K, fraction, r)
    return quantity_hypotheses(z, widths, geometry, K, fraction, cfg, include=pose, taper_pose=pose)


def _stubs_at(end: np.ndarray, base: Strut, cands: list[Strut], tol: float, n: int) -> list[Strut]:
    """Candidates that start (one of their ends) within ``tol`` of ``end`` and cross the base
    at more than 10 deg, nearest first (at most ``n``)."""
    scored = []
    for c in cands:
        if c is base or _angle_between(c.direction, base.direction) < 10.0:
            continue
        d = min(float(np.linalg.norm(c.end(0) - end)), float(np.linalg.norm(c.end(1) - end)))
        if d < tol:
            scored.append((d, c))
    scored.sort(key=lambda x: x[0])
    return [c for _, c in scored[:n]]


def _partial_triples(
    cands: list[Strut],
    cfg: StrutDetectorConfig,
    predicted: Rigid3 | None,
    geometry: BracketGeometry,
    K: np.ndarray,
    fraction: float,
) -> list[tuple[Strut, Strut, Strut]]:
    """(base, strut from P1, strut from P2) hypotheses: around the projected struts with a
    predicted pose; else every base among the longest candidates with the candidates starting
    near its ends, in both labellings (which end is P1)."""
    if predicted is not None:
        v = geometry.vertices_m
        model = np.array(
            [v[0], v[1], v[0] + fraction * (v[2] - v[0]), v[1] + fraction * (v[2] - v[1])]
        )
        pix = project(predicted, model, K)
        roles = []
        for a, b in ((0, 1), (0, 2), (1, 3)):
            d = _unit(pix[b] - pix[a])
            near = []
            for c in cands:
                if _angle_between(c.direction, d) > 4 * cfg.max_angle_deg:
                    continue
                cn = np.array([-c.direction[1], c.direction[0]])
                dist = max(abs(float((pix[a] - c.point) @ cn)), abs(float((pix[b] - c.point) @ cn)))
                if dist < cfg.track_distance_px:
                    near.append((dist - 1e-3 * c.support_px, c))
            near.sort(key=lambda x: x[0])
            roles.append([c for _, c in near[: cfg.stub_candidates]])
        return [
            (b, s1, s2)
            for b in roles[0]
            for s1 in roles[1]
            for s2 in roles[2]
            if b is not s1 and b is not s2 and s1 is not s2
        ]
    out = []
    for base in cands[: cfg.base_candidates]:
        tol = cfg.end_tolerance * base.length + 2 * cfg.merge_distance_px
        at0 = _stubs_at(base.end(0), base, cands, tol, cfg.stub_candidates)
        at1 = _stubs_at(base.end(1), base, cands, tol, cfg.stub_candidates)
        for sa in at0:
            for sb in at1:
                if sa is sb:
                    continue
                out.append((base, sa, sb))
                out.append((base, sb, sa))
    return out


def _cross_profiles(
    img: np.ndarray,
    strut: Strut,
    ss: np.ndarray,
    offs: np.ndarray,
    n: np.ndarray,
    interpolation: int,
) -> np.ndarray:
    """``img`` sampled across ``strut``: one row per position ``ss`` along its centre line,
    one column per offset ``offs`` along the unit normal ``n`` [px] (``img``'s dtype)."""
    centre = strut.point[None, :] + ss[:, None] * strut.direction[None, :]
    P = centre[:, None, :] + offs[None, :, None] * n[None, None, :]
    return cv2.remap(img, P[..., 0].astype(np.float32), P[..., 1].astype(np.float32), interpolation)


def _side_silhouette(prof: np.ndarray, noise: float) -> float:
    """How far [px] a strut's silhouette lies beyond a bar's edge, from the cross profile
    ``prof`` sampled every pixel from that edge outward; 0 when the edge is the silhouette.
    The background is the median of the last 5 samples (it must be flat: else 0). The strut
    continues beyond the edge while the profile differs from the background by more than
    ``4 noise`` (at least 3 DN), contiguously from the edge; the silhouette is the steepest
    point of that shoulder's outer step. 0 too when the shoulder reaches the background's
    window, when it is only the blurred foot of the edge itself (its step less than 2 px
    beyond the edge), or when that step is less than the threshold high (a background that
    drifts slowly, e.g. a glint's flank)."""
    far = prof[-5:]
    if float(np.ptp(far)) > 8 * noise + 3.0:
        return 0.0
    b = float(np.median(far))
    tau = max(4.0 * noise, 3.0)
    off = np.abs(prof[:-5] - b) > tau
    if not off[0]:
        return 0.0
    run = int(np.argmin(off)) if not np.all(off) else len(off)  # first sample on background
    if run >= len(off):
        return 0.0
    o_s = run - 1  # the outermost sample still on the strut
    # the silhouette: the steepest point of the shoulder's outer step (a blurred step's
    # gradient peaks at the step; the last sample above the threshold is its foot), a local
    # maximum of |gradient| at least 2 px out (nearer, it is the bar's own edge), sub-pixel
    # by a parabola; the shoulder must lie at least 2 px beyond the edge
    g = np.abs(np.diff(prof))  # g[i]: between samples i and i + 1
    peaks = [
        i for i in range(max(2, o_s - 4), min(o_s + 1, len(g) - 1)) if g[i - 1] <= g[i] >= g[i + 1]
    ]
    if not peaks:
        return 0.0
    i = max(peaks, key=lambda j: g[j])
    # a step, not a drift of the background: at least the threshold across 3 px
    if abs(float(prof[i - 1]) - float(prof[min(i + 2, len(prof) - 1)])) < tau:
        return 0.0
    den = g[i - 1] - 2 * g[i] + g[i + 1]
    out = i + 0.5 + (0.5 * (g[i - 1] - g[i + 1]) / den if den < 0 else 0.0)
    return out if out >= 2.0 else 0.0


def _silhouette_refit(img: np.ndarray, strut: Strut) -> Strut:
    """``strut`` with its centre line and width moved to the strut's silhouette. A bar is two
    edges of opposite gradient with brighter pixels between; on a cylinder lit from the side
    one of them can be the *terminator* (lit to shaded) rather than the silhouette, so the
    bar is the lit part only: its centre line lies a quarter to a half of the strut's width
    toward the light and its width is a fraction of ``f 2 r / z`` (against dark space the
    shaded side is dim, not absent; bracket family tuning seed 24: base and stubs 5-6 px
    off, no consistent pose in 9 of 12 frames). The mean cross profile over the middle half
    of the strut (``img`` blurred, bilinear) is searched beyond each edge, out to
    ``2.5 w + 6`` px, for a shoulder (`_side_silhouette`); where one is seen, that side's
    edge moves to its silhouette."""
    w = float(strut.width_px)
    if strut.length < 8.0 or w <= 0:
        return strut
    reach = math.ceil(2.5 * w + 6.0)
    ts = strut.s0 + strut.length * np.linspace(0.25, 0.75, 9)
    n = np.array([-strut.direction[1], strut.direction[0]])
    ext = []
    for sign in (1.0, -1.0):
        offs = sign * (0.5 * w + np.arange(reach + 5, dtype=float))
        rows = _cross_profiles(img, strut, ts, offs, n, cv2.INTER_LINEAR)
        # noise of the mean profile: the background's spread along the strut over sqrt(9)
        noise = float(np.median(np.std(rows[:, -5:], axis=0))) / 3.0
        ext.append(_side_silhouette(rows.mean(axis=0), noise))
    if ext[0] == 0.0 and ext[1] == 0.0:
        return strut
    shift = 0.5 * (ext[0] - ext[1])
    return replace(strut, point=strut.point + shift * n, width_px=w + ext[0] + ext[1])


def _profile_gradient(rows: np.ndarray, step: float) -> np.ndarray:
    """The gradient magnitude along each cross profile (rows x samples ``step`` px apart),
    smoothed along the profile (0.5 px): the derivative of an interpolated profile ripples
    with the pixel period, and a ripple on a step's flank would pass for an outer peak."""
    return np.abs(gaussian_filter1d(rows.astype(np.float64), 0.5 / step, axis=1, order=1))


def _parabola_offset(y0: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Sub-sample offset (within +-0.5) of the vertex of the parabola through three evenly
    spaced samples ``y0, y1, y2`` around a peak ``y1``; 0 where they do not curve down."""
    den = y0 - 2.0 * y1 + y2
    frac = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    return np.clip(frac, -0.5, 0.5)


def _theil_sen_slope(x: np.ndarray, y: np.ndarray) -> float:
    """The median of the slopes between every pair of points ``(x, y)``; 0 with fewer than
    two points."""
    i, j = np.triu_indices(len(x), 1)
    if not len(i):
        return 0.0
    return float(np.median((y[j] - y[i]) / (x[j] - x[i])))


def _outer_edges(g: np.ndarray, offs: np.ndarray, rel: float) -> np.ndarray:
    """Per cross profile (``g`` its `_profile_gradient`, rows x samples at the evenly
    spaced ``offs``), the outermost edge
    on each side (n, 2): scanning inward, the first local maximum of the gradient magnitude
    that reaches ``rel`` of the profile's largest, sub-sample by a parabola; NaN where there
    is none. The outermost step is the silhouette whatever the shading inside it (a lit
    part's ramp, a dim shaded limb), and a blurred step's steepest point does not move with
    the blur."""
    step = offs[1] - offs[0]
    n, m = g.shape
    tau = rel * g.max(axis=1, keepdims=True)
    peak = np.zeros_like(g, dtype=bool)
    peak[:, 1:-1] = (g[:, 1:-1] >= tau) & (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] > g[:, 2:])
    peak_r = np.zeros_like(peak)
    peak_r[:, 1:-1] = (g[:, 1:-1] >= tau) & (g[:, 1:-1] > g[:, :-2]) & (g[:, 1:-1] >= g[:, 2:])
    r = np.arange(n)
    out = np.full((n, 2), np.nan)
    for side, mask in ((0, peak), (1, peak_r[:, ::-1])):
        k = np.argmax(mask, axis=1)
        ok = mask[r, k]
        k = k if side == 0 else m - 1 - k
        k = np.clip(k, 1, m - 2)
        frac = _parabola_offset(g[r, k - 1], g[r, k], g[r, k + 1])
        out[:, side] = np.where(ok, offs[k] + frac * step, np.nan)
    return out


def _outer_edge_lines(g: np.ndarray, offs: np.ndarray, rel: float, max_drift: float) -> np.ndarray:
    """Per cross profile (``g`` its `_profile_gradient`, rows along a strut x samples at the
    evenly spaced ``offs``), each
    side's silhouette (n, 2; NaN where a profile has none near it), chosen *once for the
    whole strut*: the outermost maximum of the mean gradient magnitude over all profiles
    that reaches ``rel`` of its steepest; on every profile the gradient peak nearest to it
    within ``max_drift / 2 + 1`` px (the edge's drift along the strut: its taper and the centre
    line's tilt); a robust straight line (Theil-Sen) through those; and on every profile the
    gradient peak within 1 px of that line (sub-sample, by a parabola).

    A profile-by-profile outermost peak (`_outer_edges`) is unstable where the limb has no
    step: a Lambertian strut lit from near the view direction fades into a panel of its
    limb's brightness, and the outermost peak of such a dome is a ripple of the panel's
    texture on its foot on some profiles and the flank's on others, so the width jumps
    by a third along the strut (bracket family tuning seed 29: a base 15-16 px wide
    measured 14.6 px over its first half and 11 px over its second, taper -0.28 for +0.09).
    The mean over the strut keeps a silhouette step that runs its whole length, however
    faint, and averages a texture's ripples away."""
    step = float(offs[1] - offs[0])
    n, m = g.shape
    r = np.arange(n)
    mean = g.mean(axis=0)
    tau = rel * float(mean.max())
    peak = np.zeros(m, dtype=bool)
    peak[1:-1] = (mean[1:-1] >= tau) & (mean[1:-1] >= mean[:-2]) & (mean[1:-1] > mean[2:])
    out = np.full((n, 2), np.nan)
    if n < 2:
        return out
    local = np.zeros_like(g, dtype=bool)
    local[:, 1:-1] = (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] >= g[:, 2:]) & (g[:, 1:-1] > 0)
    idx = r[:: max(1, n // 100)]
    for side, order in ((0, np.arange(m)), (1, np.arange(m)[::-1])):
        ks = [k for k in order if peak[k]]
        if not ks:
            continue
        centre = np.full(n, float(ks[0]))
        for final, reach in ((False, 0.5 * max_drift + 1.0), (True, 1.0)):
            # each profile's peak nearest to the line so far, within ``reach`` px of it
            dist = np.abs(np.arange(m)[None, :] - centre[:, None])
            near = local & (dist <= reach / step)
            j = np.argmin(np.where(near, dist, np.inf), axis=1)
            ok = near[r, j]
            if int(ok.sum()) < max(2, n // 2):
                break
            jj = np.clip(j, 1, m - 2)
            pos = np.where(ok, jj + _parabola_offset(g[r, jj - 1], g[r, jj], g[r, jj + 1]), np.nan)
            if final:
                out[:, side] = offs[0] + pos * step
                break
            # Theil-Sen line of the positions over the profile index
            sub = idx[ok[idx]]
            slope = _theil_sen_slope(sub, pos[sub])
            icpt = float(np.median(pos[ok] - slope * r[ok]))
            centre = icpt + slope * r
    return out


def _taper_span(strut: Strut, min_span_px: float = 12.0) -> tuple[float, float] | None:
    """The part of ``strut`` where `measure_taper` measures its width: ``max(2 w, 4)`` px
    clear of each end; None when shorter than ``max(min_span_px, TAPER_MIN_SPAN_WIDTHS w)``."""
    w = float(strut.width_px)
    if not w > 0:
        return None
    trim = max(2.0 * w, 4.0)
    lo, hi = strut.s0 + trim, strut.s1 - trim
    return (lo, hi) if hi - lo >= max(min_span_px, TAPER_MIN_SPAN_WIDTHS * w) else None


def exact_taper(
    strut: Strut, pose: Rigid3, ends_m: tuple[np.ndarray, np.ndarray], K: np.ndarray, r: float
) -> Strut:
    """``strut`` with the taper ``pose`` predicts over the span `measure_taper` would measure
    (``taper_sigma`` 0: the floor weighs it), for noise-free analysis; unchanged (NaN) where
    that span is too short."""
    span = _taper_span(strut)
    if span is None:
        return strut
    st = replace(strut, taper=0.0, taper_sigma=0.0, taper_span=span)
    t = predicted_taper(st, pose, ends_m, K, r)
    return replace(st, taper=t) if math.isfinite(t) else strut


# the shortest clear span [strut widths] whose taper `measure_taper` reports: over shorter
# spans (the stubs of a small visible fraction) the measured tapers' errors had three times
# the tails (90th percentile 0.19-0.22 against 0.05-0.07 beyond 12 widths; tuning members)
TAPER_MIN_SPAN_WIDTHS = 12.0

# `measure_taper`'s edges: the outermost gradient peak at least this fraction of the
# profile's steepest (low: a side-lit strut's dim shaded limb, ~10 % of the lit part's
# steepest, still counts; 0.15 missed it on tuning seeds 14, 24, 31)
TAPER_EDGE = 0.06


def _taper_reach(
    blurred: np.ndarray, strut: Strut, ss: np.ndarray, n: np.ndarray
) -> tuple[float, float]:
    """How far from ``strut``'s centre line `measure_taper` looks for its silhouette on each
    side (against ``n``, along ``n``) [px]: ``w / 2 + max(2.5, w / 3)``, or farther where
    the strut's cross profiles have not fallen to the background there (a strut's shaded
    limb in ambient light is a long dim ramp that the bar's width ``w`` leaves out: tuning
    seeds 66 and 73, silhouettes 13-15 px from a centre line whose reach was 8-10 px, so
    the edge found was a point of the ramp and the taper 0.1-0.7 off). On each of up to 25
    profiles along ``ss``, the distance from its peak (within the usual reach) to where it
    first comes within ``TAPER_EDGE`` of that side's lowest value; the reach is the 90th
    percentile of those plus 1.5 px (the strut widens along its length), at most
    ``2 w + 2.5`` px."""
    w = float(strut.width_px)
    reach = 0.5 * w + max(2.5, w / 3.0)
    wide = 2.0 * w + 2.5
    offs = np.arange(-wide, wide + 1e-9, 0.5)
    sub = ss[:: max(1, len(ss) // 24)]
    rows = _cross_profiles(blurred, strut, sub, offs, n, cv2.INTER_LINEAR).astype(np.float64)
    first = int(np.flatnonzero(np.abs(offs) <= reach)[0])
    inner = rows[:, np.abs(offs) <= reach]
    far: list[list[float]] = [[], []]
    for row, k in zip(rows, first + np.argmax(inner, axis=1), strict=True):
        for side, (sign, part) in enumerate(((-1.0, row[k::-1]), (1.0, row[k:]))):
            floor = float(part.min())
            low = np.flatnonzero(part <= floor + TAPER_EDGE * (float(part[0]) - floor))
            if len(low):
                far[side].append(sign * float(offs[k]) + 0.5 * float(low[0]))
    out = [
        float(min(max(reach, float(np.percentile(d, 90)) + 1.5), wide)) if d else reach for d in far
    ]
    return out[0], out[1]


# `measure_taper`'s slope from block means: the clear span in this many equal parts
TAPER_BLOCKS = 8


def _block_slope_sd(x: np.ndarray, width: np.ndarray, blocks: int = TAPER_BLOCKS) -> float:
    """The standard deviation of a width line's slope from the means of ``blocks`` equal
    parts of the span (``x`` the positions, centred; ``width`` the widths there): the scatter
    of the block means about their own line, with ``blocks - 2`` degrees of freedom; 0 with
    fewer than four parts holding a width.

    The scatter of single widths about the line (the fit's own sigma) holds only while
    neighbouring widths err independently and the widths do lie on a line. Neither holds
    where the outermost edge on one side is a point of a shading ramp rather than a
    silhouette step (a strut lit from near the view direction fading into a panel of its
    limb's brightness): there the edge found jumps between a ripple of the panel's texture
    and the flank from one stretch of the strut to the next (bracket family tuning seed
    29, frame 9: a base 15-16 px wide measured 14.6 px over its first half and 11 px over
    its second, taper -0.28 +- 0.02 for a true +0.09). The block means see such a jump as
    scatter about the line; on independent scatter they give the fit's sigma on average."""
    lo, hi = float(x.min()), float(x.max())
    if not hi > lo:
        return 0.0
    part = np.minimum(((x - lo) / (hi - lo) * blocks).astype(int), blocks - 1)
    cnt = np.bincount(part, minlength=blocks)
    have = cnt > 0
    if int(have.sum()) < 4:
        return 0.0
    xm = np.bincount(part, weights=x, minlength=blocks)[have] / cnt[have]
    wm = np.bincount(part, weights=width, minlength=blocks)[have] / cnt[have]
    xc = xm - xm.mean()
    sxx = float(xc @ xc)
    slope = float(xc @ (wm - wm.mean())) / sxx
    e = wm - wm.mean() - slope * xc
    return math.sqrt(float(e @ e) / (len(xm) - 2) / sxx)


# `measure_taper`'s two edge sets disagree when their tapers differ by more than this many
# sigmas of the difference (each set's own sigma and the floor in quadrature)
TAPER_AGREE = 3.0

# `measure_taper`'s check of the kept edges: each side's foot, where the gradient magnitude
# outside the edge has fallen to this fraction of the edge's (`_outer_feet`), ...
TAPER_FOOT = 0.5
# ... looked for up to this much beyond the edges' reach [px] (a blurred step's half-height
# foot lies 1.18 blur sigmas outside it: 1.6 px at the 1.35 px of the detector's blur on a
# rendered edge)
TAPER_FOOT_PAD_PX = 3.0

WidthLine = tuple[float, float, tuple[float, float]]


def _taper_of_two_sets(a: WidthLine | None, b: WidthLine | None, floor: float) -> WidthLine | None:
    """The taper of two edge sets' width lines ``(taper, sigma, span)`` (None: no fit): the
    one whose widths lie on their line best (the smaller sigma); where the two tapers differ
    by more than ``TAPER_AGREE`` times ``hypot(sigma_a, sigma_b, floor)``, one set has failed
    and its fit does not say which, so the kept taper's sigma grows to ``hypot(sigma,
    difference)``: a claim that covers the other set's value.

    The smaller sigma picks the wrong set where one side's edges follow a constant offset
    instead of a converging silhouette: on a 7-10 px strut whose limb is a long smooth ramp
    (no silhouette step), the edges chosen once per strut (`_outer_edge_lines`) lock onto
    the lit dome's inner flank, lie on a straight line well and give a taper 0.07-0.15 low
    with a sigma of 0.008-0.019 (bracket family tuning seed 42, docs/bracket.md). On the
    taper benchmark (tuning 0-35) the rule leaves every taper as it was and halves the weighed
    struts' normalised errors beyond 3 sigmas (3.0 -> 1.5 %)."""
    fits = [f for f in (a, b) if f is not None]
    if not fits:
        return None
    best = min(fits, key=lambda f: f[1])
    return _covering(best, b if best is a else a, floor)


def _covering(kept: WidthLine, other: WidthLine | None, floor: float) -> WidthLine:
    """``kept`` as it is where ``other`` (None: no fit) agrees with it: their tapers within
    ``TAPER_AGREE`` times ``hypot(sigma_kept, sigma_other, floor)``; else with its sigma grown
    to ``hypot(sigma, difference)``, a claim that covers the other's value."""
    if other is None:
        return kept
    d = abs(kept[0] - other[0])
    if d > TAPER_AGREE * math.hypot(kept[1], other[1], floor):
        return (kept[0], math.hypot(kept[1], d), kept[2])
    return kept


def measure_taper(
    blurred: np.ndarray,
    strut: Strut,
    min_span_px: float = 12.0,
    floor: float = StrutDetectorConfig.taper_floor,
) -> Strut:
    """``strut`` with its ``taper`` measured: how its image width changes along it.

    A strut is a cylinder of one radius, so its image narrows with depth: the width at two
    points of its centre line is in the inverse ratio of their depths (`predicted_taper`), a
    ratio that tells apart poses which put the same vertices on the same pixels but tilt the
    struts differently (the P3P solutions of the paper's view). Both edges are located on a
    cross profile at every pixel along the strut, ``max(2 w, 4)`` px clear of each end
    (where another strut or the array crosses it), out to the reach of `_taper_reach` (at
    least ``w / 2 + max(2.5, w / 3)`` px of its centre line, ``w`` its width), in two ways:
    on each profile the outermost gradient peak of at least ``TAPER_EDGE`` of its steepest
    (`_outer_edges`: the silhouette, whether the limb beside it is lit or only dimly shaded;
    a blurred step's steepest point stays put), and each side's edge chosen once for the
    whole strut (`_outer_edge_lines`: steady where the limb has no step and the outermost
    peak of a profile is a ripple). Each set of widths is fitted by a straight line in
    ``s`` (a Theil-Sen start, then least squares three times without the points beyond 3
    robust standard deviations), and the set whose widths lie on their line best (the
    smaller ``taper_sigma``) is kept; where the two disagree beyond their sigmas and the
    ``floor`` (the config's ``taper_floor``), its sigma grows to cover the other's taper
    (`_taper_of_two_sets`). The kept taper is then checked against the widths between its
    edges' feet (`_outer_feet`: outside each edge, where the gradient has fallen to
    ``TAPER_FOOT`` of the edge's): where the shading moves the edges along a narrow strut
    (a highlight that brightens along it) the feet keep to the limb, and where their taper
    disagrees beyond ``TAPER_AGREE`` sigmas the kept sigma grows to cover it (`_covering`).
    The feet's own taper is not reported: they lie about a blur outside the limb, which
    compresses it (measured / true 0.83-0.90 on tuning members 0-35 against 1.01-1.21 for
    the edges, docs/bracket.md). What changes the edges' offset from the silhouette
    (shading, a lit part only) is nearly the same all along a strut, so the *ratio* keeps
    the depth's. ``taper_sigma`` comes from the scatter of the widths about the line, or of
    the means of eight parts of the span about theirs where that is larger
    (`_block_slope_sd`: neighbouring widths err together, and an edge can jump); NaN when
    the clear span is shorter than ``max(min_span_px, TAPER_MIN_SPAN_WIDTHS w)`` or the fit
    fails."""
    strut = replace(strut, taper=math.nan, taper_sigma=math.nan, taper_span=(math.nan, math.nan))
    span = _taper_span(strut, min_span_px)
    if span is None:
        return strut
    w = float(strut.width_px)
    ss = np.arange(span[0], span[1] + 1e-9, 1.0)
    n = np.array([-strut.direction[1], strut.direction[0]])
    before, after = _taper_reach(blurred, strut, ss, n)
    step = 0.25
    offs = np.arange(-before, after + 1e-9, step)
    # the profiles reach TAPER_FOOT_PAD_PX farther on each side for the feet
    pad = round(TAPER_FOOT_PAD_PX / step)
    offs_wide = np.arange(-before - pad * step, after + pad * step + 1e-9, step)
    rows_wide = _cross_profiles(blurred, strut, ss, offs_wide, n, cv2.INTER_CUBIC)
    g = _profile_gradient(rows_wide[:, pad : pad + len(offs)], step)
    profile_wise_edges = _outer_edges(g, offs, TAPER_EDGE)
    once_edges = _outer_edge_lines(g, offs, TAPER_EDGE, 0.25 * w + 2.0)
    profile_wise, once = (
        _width_line(ss, edges[:, 1] - edges[:, 0], w) for edges in (profile_wise_edges, once_edges)
    )
    best = _taper_of_two_sets(profile_wise, once, floor)
    if best is None:
        return strut
    # the widths between the edges' feet (`_outer_feet`): their taper is the silhouette's
    # where the shading draws the edges along the strut; where the two disagree beyond
    # their sigmas, the kept sigma covers the feet's taper
    feet = _outer_feet(
        _profile_gradient(rows_wide, step),
        offs_wide,
        np.where(np.isfinite(once_edges), once_edges, profile_wise_edges),
        TAPER_FOOT,
    )
    best = _covering(best, _width_line(ss, feet[:, 1] - feet[:, 0], w), floor)
    return replace(strut, taper=best[0], taper_sigma=best[1], taper_span=best[2])


def _outer_feet(g: np.ndarray, offs: np.ndarray, edges: np.ndarray, frac: float) -> np.ndarray:
    """Per cross profile (``g`` its `_profile_gradient`, rows x samples at the evenly spaced
    ``offs``), each side's *foot* (n, 2): from that side's edge ``edges`` (n, 2; its
    gradient peak within 2 samples), outward to where the gradient magnitude first falls to
    ``frac`` of the peak's, linearly interpolated; NaN where the edge is NaN or the profile
    ends first.

    A strut's gradient peak is where its shading is steepest, and on a narrow domed strut
    that is inside the silhouette by an amount the shading sets: a specular core that
    brightens along the strut steepens the inner flank and draws both peaks inward, so the
    widths between the peaks shrink faster than the silhouette (bracket family tuning seed
    98, frame 5: an 11-12 px base measured 2.5 px narrow at one end and 3.0 px at the
    other, taper -0.24 for -0.09). The outer flank of the gradient is the limb's blurred step,
    which that shading hardly moves: the widths between the feet overshoot the silhouette by
    about the blur and keep its taper there (-0.11)."""
    step = float(offs[1] - offs[0])
    n, m = g.shape
    r = np.arange(n)
    idx = np.arange(m)
    out = np.full((n, 2), np.nan)
    if m < 5:
        return out
    for side in (0, 1):
        e = edges[:, side]
        found = np.isfinite(e)
        k = np.round((np.where(found, e, offs[0]) - offs[0]) / step).astype(int)
        k = np.clip(k, 2, m - 3)
        near = np.stack([g[r, k + d] for d in (-2, -1, 0, 1, 2)], axis=1)
        k = k + np.argmax(near, axis=1) - 2
        thr = frac * g[r, k]
        if side == 0:
            below = (g <= thr[:, None]) & (idx[None, :] < k[:, None])
            j = m - 1 - np.argmax(below[:, ::-1], axis=1)
            inner = np.minimum(j + 1, m - 1)
        else:
            below = (g <= thr[:, None]) & (idx[None, :] > k[:, None])
            j = np.argmax(below, axis=1)
            inner = np.maximum(j - 1, 0)
        ok = found & below[r, j]
        hi, lo = g[r, inner], g[r, j]
        t = np.where(hi > lo, (thr - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0)
        pos = j + t * (inner - j)
        out[:, side] = np.where(ok, offs[0] + pos * step, np.nan)
    return out


def _width_line(ss: np.ndarray, width: np.ndarray, w: float) -> WidthLine | None:
    """(taper, its sigma, span) of the widths ``width`` at ``ss`` along a strut ``w`` px
    wide (`measure_taper`); None when too few are kept or an end's width is not positive."""
    keep = np.isfinite(width) & (width > 0.25 * w)
    width = np.where(keep, width, 0.0)
    if int(keep.sum()) >= max(8, len(ss) // 2):
        # a robust start (Theil-Sen over at most 100 widths): where another strut joins or
        # an occluder's edge crosses, a run of widths at one end is off, and a least-squares
        # start's slope follows it so far that the clipping below keeps the run (tuning
        # seed 73: a stub widened by 3 px over its first 25 px, taper -0.19 for -0.06)
        idx = np.flatnonzero(keep)[:: max(1, int(keep.sum()) // 100)]
        slope = _theil_sen_slope(ss[idx], width[idx])
        res = width - slope * ss
        res -= float(np.median(res[keep]))
        mad = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = keep & (np.abs(res) <= max(3.0 * mad, 0.05))
    for it in range(3):
        if int(keep.sum()) < max(8, len(ss) // 2):
            return None
        x = ss[keep] - ss[keep].mean()
        A = np.stack([np.ones_like(x), x], axis=1)
        coef, *_ = np.linalg.lstsq(A, width[keep], rcond=None)
        res = width - (coef[0] + coef[1] * (ss - ss[keep].mean()))
        if it == 2:
            break
        mad = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = keep & (np.abs(res) <= max(3.0 * mad, 0.05))
    m = len(x)
    sd = float(np.sqrt(np.sum(res[keep] ** 2) / max(m - 2, 1)))
    ends = coef[0] + coef[1] * (np.array([ss[keep].min(), ss[keep].max()]) - ss[keep].mean())
    if not np.all(ends > 0):
        return None
    sxx = float(x @ x)
    extent = float(ss[keep].max() - ss[keep].min())
    # var of the slope sd^2 / sxx, or the blocks' where the widths are not a line with
    # independent scatter (`_block_slope_sd`); the log ratio is slope x extent / mean width
    slope_sd = max(sd / math.sqrt(max(sxx, 1e-12)), _block_slope_sd(x, width[keep]))
    sigma = slope_sd * extent / float(coef[0])
    return (
        float(math.log(ends[1] / ends[0])),
        sigma,
        (float(ss[keep].min()), float(ss[keep].max())),
    )


def silhouette_width_px(
    point: np.ndarray, axis_point: np.ndarray, axis_dir: np.ndarray, radius_m: float, K: np.ndarray
) -> float:
    """The exact image width [px] at image ``point`` of a cylinder of ``radius_m`` whose axis
    passes through ``axis_point`` along ``axis_dir`` (camera frame): the sum of the distances
    from ``point`` to the images of its two silhouette lines, the tangent planes through the
    camera centre parallel to the axis (``m . Q = +-r``, ``Q`` the axis point nearest the
    centre). NaN when the camera is inside the cylinder."""
    A = np.asarray(axis_point, dtype=float)
    lines = _silhouette_lines(A, A + np.asarray(axis_dir, dtype=float), radius_m, np.linalg.inv(K))
    return float(_widths_on_lines(lines, np.array([[point[0], point[1], 1.0]]))[0])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) arrays (np.cross's axis handling costs more than
    the arithmetic at these sizes)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _silhouette_lines(
    P0: np.ndarray, P1: np.ndarray, r: np.ndarray | float, K_inv: np.ndarray
) -> np.ndarray:
    """The image lines (..., 2, 3) of the two silhouette lines of cylinders of radius ``r``
    (broadcast against ``P0[..., 0]``) whose axes run through ``P0`` and ``P1`` (..., 3),
    camera frame: the tangent planes through the camera centre parallel to the axis
    (`silhouette_width_px`), as rows ``m K^-1`` (``K_inv`` the inverse intrinsics); NaN
    where the centre is inside a cylinder."""
    a = P1 - P0
    a = a / np.sqrt(np.sum(a * a, axis=-1, keepdims=True))
    Q = P0 - np.sum(P0 * a, axis=-1, keepdims=True) * a
    d = np.sqrt(np.sum(Q * Q, axis=-1, keepdims=True))
    e1 = Q / d
    e2 = _cross(a, e1)
    c = np.asarray(r, dtype=float)[..., None] / d
    s = np.sqrt(np.where(c < 1.0, 1.0 - c * c, np.nan))
    m = np.stack([c * e1 + s * e2, c * e1 - s * e2], axis=-2)
    return m @ K_inv


def _widths_on_lines(lines: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Image widths (..., n) at the homogeneous points ``x`` (..., n, 3) between each pair
    of ``lines`` (..., 2, 3): the sum of the distances to the two."""
    num = np.abs(lines @ np.swapaxes(x, -1, -2))  # (..., 2, n)
    den = np.sqrt(lines[..., 0] ** 2 + lines[..., 1] ** 2)[..., None]
    return (num / den).sum(axis=-2)


def taper_between(
    px: np.ndarray, pose: Rigid3, ends_m: tuple[np.ndarray, np.ndarray], K: np.ndarray, r: float
) -> float:
    """The log ratio of a posed strut's exact silhouette widths (`silhouette_width_px`) at
    the image points ``px[1]`` and ``px[0]``, its axis running from ``ends_m[0]`` to
    ``ends_m[1]`` (target frame), radius ``r``. NaN when an end lies behind the camera or
    the camera inside the cylinder."""
    P = pose.apply(np.asarray(ends_m, dtype=float))
    if not np.all(P[:, 2] > 0):
        return math.nan
    x = np.c_[np.asarray(px, dtype=float), np.ones(len(px))]
    w = _widths_on_lines(_silhouette_lines(P[0], P[1], r, np.linalg.inv(K)), x)
    if not (np.all(np.isfinite(w)) and np.all(w > 0)):
        return math.nan
    return float(math.log(w[1] / w[0]))


def predicted_taper(
    strut: Strut, pose: Rigid3, ends_m: tuple[np.ndarray, np.ndarray], K: np.ndarray, r: float
) -> float:
    """The taper (`measure_taper`) that ``pose`` predicts for ``strut``, whose axis runs from
    ``ends_m[0]`` to ``ends_m[1]`` (target frame): `taper_between` the image points
    ``taper_span`` of its centre line. NaN when unmeasured or a ray misses the axis."""
    if not math.isfinite(strut.taper):
        return math.nan
    px = np.array([strut.point + s * strut.direction for s in strut.taper_span])
    return taper_between(px, pose, ends_m, K, r)


def _scaled(gray: np.ndarray) -> np.ndarray:
    """A grey image as float32 scaled to a maximum of 255 (what the bar finder measures)."""
    return gray.astype(np.float32) * (255.0 / float(gray.max()))


def _finished(
    scaled: np.ndarray, cands: list[Strut], config: StrutDetectorConfig, silhouette: bool
) -> list[Strut]:
    """Every candidate (``silhouette``: first moved to its strut's silhouette,
    `_silhouette_refit`) with its taper measured (`measure_taper`), on the blurred ``scaled``
    image; their order kept: neither changes the support."""
    blurred = cv2.GaussianBlur(scaled, (0, 0), config.blur_sigma_px)
    if silhouette:
        cands = [_silhouette_refit(blurred, c) for c in cands]
    return [measure_taper(blurred, c, floor=config.taper_floor) for c in cands]


def silhouette_candidates(
    image: np.ndarray, prepared: tuple[np.ndarray, list[Strut]], config: StrutDetectorConfig
) -> tuple[np.ndarray, list[Strut]]:
    """The candidates of ``prepared`` (`partial_candidates` of this grey ``image`` with
    ``silhouette=False``) moved to their struts' silhouettes: the same as
    `partial_candidates` with ``silhouette=True``, without finding the segments and bars
    again."""
    seg, cands = prepared
    return seg, _finished(_scaled(np.asarray(image)), cands, config, silhouette=True)


def partial_candidates(
    image: np.ndarray,
    config: StrutDetectorConfig,
    silhouette: bool = True,
    short_edges: bool = False,
) -> tuple[np.ndarray, list[Strut]] | StrutDetection:
    """LSD segments and strut candidates (longest support first) of a grey (or BGR) image,
    or a `StrutDetection` with the reason when there are too few. ``silhouette``: each
    candidate moved to the strut's silhouette where its bar is only the lit part
    (`_silhouette_refit`); False: the bars as found. ``short_edges``: two short edges may
    pair into a bar at a larger angle (``config.short_edge_px``: a thick short stub)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.size == 0 or float(img.max()) <= float(img.min()):
        return StrutDetection(None, None, np.zeros((0, 4)), reason="empty or uniform image")
    seg = line_segments(img, config)
    if len(seg) < 2:
        return StrutDetection(None, None, seg, reason=f"only {len(seg)} line segments")
    scaled = _scaled(img)
    cands = sorted(
        _merge(_bars(scaled, seg, config, short_edges), config, by_width=True),
        key=lambda c: -c.support_px,
    )
    cands = _finished(scaled, cands, config, silhouette)
    if len(cands) < 3:
        return StrutDetection(
            None, None, seg, tuple(cands), reason=f"{len(cands)} strut candidates (need 3)"
        )
    return seg, cands


def detect_partial(
    image: np.ndarray,
    K: np.ndarray,
    geometry: BracketGeometry,
    fraction: float,
    config: StrutDetectorConfig | None = None,
    predicted: Rigid3 | None = None,
    prepared: tuple[np.ndarray, list[Strut]] | StrutDetection | None = None,
) -> StrutDetection:
    """The bracket in the paper's view: the base strut ``P1P2`` and the first ``fraction`` of
    the two side struts (the apex hidden), among many other straight edges (solar-cell grid,
    array and bus edges, glints). Hypothesise and verify: every base candidate with the
    candidates starting at its ends, both labellings, every admissible P3P solution; a
    hypothesis stands if the camera is on the known face, the visible strut ends lie where the
    known ``fraction`` puts them and the strut widths agree with ``f 2 r / z``
    (``config.strut_radius_m``). Without a prediction, two consistent hypotheses whose poses
    differ (by more than ``rival_deg`` or ``rival_rel`` x range: another labelling, or
    another P3P solution) make the frame *refused* as ambiguous. With a prediction (tracking), only
    candidates near the projected struts are tried and the pose must lie inside the gate
    around the prediction, else the frame is refused.

    Args:
        image: grey (or BGR) undistorted image.
        K: its 3x3 intrinsics.
        geometry: the bracket (target frame).
        fraction: the visible part of ``P1P5`` and ``P2P5`` (0, 1]; 1: the whole triangle.
        config: detector settings.
        predicted: ``left_cam_from_target`` predicted for this frame, or None.
        prepared: `partial_candidates` of this image and config (several calls on one
            image), or None.

    Returns:
        A `StrutDetection`; ``observation`` None with a ``reason`` when refused.
    """
    cfg = StrutDetectorConfig() if config is None else config
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    prep = partial_candidates(image, cfg) if prepared is None else prepared
    if isinstance(prep, StrutDetection):
        return prep
    seg, cands = prep
    geo = BracketGeometry(
        vertices_m=geometry.vertices_m,
        vertex_sigma_m=geometry.vertex_sigma_m,
        visible_fraction=fraction if fraction < 1 else None,
    )
    # least squares from each start: near a double root noise turns the true pair complex
    solver = BracketConfig(covariance=False, prior_least_squares=True)
    triples = _partial_triples(cands, cfg, predicted, geo, K, fraction)
    hyps: list[tuple[float, StrutDetection]] = []
    why: Counter[str] = Counter()
    for base, s1, s2 in triples:
        if not _plausible(base, s1, s2, cfg):
            why["implausible"] += 1
            continue
        if s1.edges is not None or s2.edges is not None:
            # a thick short stub of the short-edge pass: along its exterior edge; the
            # triangle lies toward the other base vertex
            q1, q2 = _intersect(base, s1), _intersect(base, s2)
            if q1 is not None and q2 is not None:
                s1, s2 = _exterior_stub(s1, q2), _exterior_stub(s2, q1)
        obs = _observation(base, s1, s2, cfg)
        if obs is None:
            continue
        try:
            rays = _apex_rays(obs, K)
            starts = [*p3p_depths(rays, geo.sides_m)]
        except (ValueError, np.linalg.LinAlgError, ZeroDivisionError):
            continue
        # also from a fronto-parallel guess at the base's scale, and from the prediction
        starts.append(
            np.full(3, geo.sides_m[0] / max(float(np.linalg.norm(rays[0] - rays[1])), 1e-9))
        )
        if predicted is not None:
            starts.append(predicted.apply(geo.vertices_m)[:, 2])
        for d in starts:
            res = solve_bracket(obs, geo, K, solver, prior_depths=d)
            if res.pose is None:
                why[res.reason.split(":")[0]] += 1
                continue
            cost, reason = _verify(
                obs, (base, s1, s2), res.pose, geo, K, fraction, cfg.strut_radius_m, cfg
            )
            if not math.isfinite(cost):
                why[reason.split(" (")[0]] += 1
                continue
            image_chi2 = cost
            if predicted is not None:
                ang, dist = _pose_distance(res.pose, predicted, geometry.vertices_m.mean(axis=0))
                gate_m = cfg.gate_rel * float(np.linalg.norm(predicted.t)) + 0.02
                if ang > cfg.gate_deg or dist > gate_m:
                    why[f"departs from the prediction by {ang:.0f} deg, {1e3 * dist:.0f} mm"] += 1
                    continue
                cost += (ang / cfg.gate_deg) ** 2 + (dist / gate_m) ** 2
            hyps.append(
                (
                    cost,
                    StrutDetection(
                        obs, (base, s1, s2), seg, tuple(cands), res, "", 0, image_chi2=image_chi2
                    ),
                )
            )
    if not hyps:
        detail = "; ".join(f"{k} ({n})" for k, n in why.most_common(2))
        head = (
            "tracked struts not consistent with the prediction"
            if predicted is not None
            else f"no consistent bracket among {len(cands)} strut candidates"
        )
        return StrutDetection(
            None,
            None,
            seg,
            tuple(cands),
            reason=f"{head} ({len(triples)} hypotheses{': ' + detail if detail else ''})",
            hypotheses=len(triples),
        )
    hyps.sort(key=lambda h: h[0])
    best_cost, best = hyps[0]
    assert best.result is not None and best.result.pose is not None
    bp = best.result.pose
    distinct: list[StrutDetection] = []
    if predicted is None:
        ctr = geo.vertices_m.mean(axis=0)
        range_m = float(np.linalg.norm(bp.apply(ctr[None])[0]))
        # distinct poses at a fine resolution (the tracker follows each of them: merging two
        # nearby P3P solutions would let a track hop from one to the other) ...
        for _, h in hyps:
            assert h.result is not None and h.result.pose is not None
            p = h.result.pose
            if all(
                _rotation_deg(p, q.result.pose) > 1.0
                or _pose_distance(p, q.result.pose, ctr)[1] > 0.01 * range_m
                for q in distinct
                if q.result is not None and q.result.pose is not None
            ):
                distinct.append(replace(h, hypotheses=len(triples)))
        # ... and the frame ambiguous if any of them is a rival of the best
        rivals = [
            q
            for q in distinct[1:]
            if q.result is not None
            and q.result.pose is not None
            and (
                _rotation_deg(bp, q.result.pose) > cfg.rival_deg
                or _pose_distance(bp, q.result.pose, ctr)[1] > cfg.rival_rel * range_m
            )
        ]
        if rivals:
            return StrutDetection(
                None,
                None,
                seg,
                tuple(cands),
                reason=(
                    f"labelling ambiguous: {len(rivals) + 1} consistent poses "
                    f"(costs {best_cost:.1f} and {hyps[1][0]:.1f})"
                ),
                hypotheses=len(triples),
                alternatives=tuple(distinct),
            )
    return StrutDetection(
        best.observation,
        best.struts,
        seg,
        tuple(cands),
        best.result,
        "",
        len(triples),
        tuple(distinct),
        best.image_chi2,
    )
