"""Panel landmarks in one image: corners from edge lines, dark components from blobs.

Seed 000, section 3.2:

- corners = intersections of the 4 strongest Hough lines. On crinkled foil the strongest Hough
  lines are as often foil creases as panel edges, so the lines are searched on the target's
  silhouette (the boundary between the lit target and black space), the four are chosen as the
  best-voted quadrilateral of two line pairs that encloses the ring, and each edge is then
  refined on sub-pixel edge points (`satpose.frontend.edges`) before intersecting.
- components = small dark blobs (the paper: LoG blob detector with colour, area and curvature
  filtering), found on the panel outside the ring and located at sub-pixel precision by the
  dark-weighted centroid.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from satpose.frontend.conics import ConicError, Ellipse, fit_ellipse_direct, refine_ellipse
from satpose.frontend.edges import EdgeSearchConfig, edges_along_normals, sample_image, smoothed


@dataclass(frozen=True, kw_only=True)
class CornerConfig:
    """Panel corner detection (pixels of the undistorted image).

    Attributes:
        max_extent: the panel is searched within this many ring semi-major axes of the ring
            centre (lines, edges) — the panel surrounds the ring.
        max_search_px: the search window is downscaled to at most this size for finding lines.
        min_segment_px, min_segment_axis: line segments shorter than both this length and
            this fraction of the ring's semi-major axis are foil texture, not edges.
        max_lines: longest merged lines kept.
        nms_rho_px, nms_theta_deg: segments within this offset and angle of a line are merged
            into it.
        pair_angle_deg: the two lines of a pair are at most this far from parallel.
        min_corner_angle_deg: the pairs cross at more than this angle.
        min_side_support: fraction of a side's samples that must sit on an edge with the panel
            brighter inside (the candidate quadrilateral's sides, between its corners).
        foreground_level, min_fill, min_lit: at least ``min_fill`` of the quadrilateral's
            inside must be panel (brighter than ``foreground_level``, a fraction of full scale
            after smoothing, or a dark hole the panel encloses: the ring's bore, its shadow),
            and at least ``min_lit`` of it brighter than that.
        support_gradient: smallest accepted intensity gradient across a side [1/px].
        image_margin_px: corners closer than this to the image border are not reported.
        edge_samples: sub-pixel normals per side.
        edge_search_px: half-width of the sub-pixel search along each normal.
        min_edge_fraction: fraction of a side's normals that must find the edge.
        max_line_rms_px: a side whose sub-pixel edge points scatter more than this about the
            fitted line is not a clean edge; its corners are not reported.
        edges: sub-pixel edge settings.
    """

    max_extent: float = 4.5
    max_search_px: int = 420
    min_segment_px: float = 15.0
    min_segment_axis: float = 0.25
    max_lines: int = 24
    nms_rho_px: float = 3.0
    nms_theta_deg: float = 3.0
    pair_angle_deg: float = 25.0
    min_corner_angle_deg: float = 35.0
    min_side_support: float = 0.6
    foreground_level: float = 0.03
    min_fill: float = 0.9
    min_lit: float = 0.5
    support_gradient: float = 0.02
    image_margin_px: float = 3.0
    edge_samples: int = 60
    edge_search_px: float = 3.0
    min_edge_fraction: float = 0.4
    max_line_rms_px: float = 0.6
    edges: EdgeSearchConfig = field(default_factory=lambda: EdgeSearchConfig(min_step=0.05))


@dataclass(frozen=True, kw_only=True)
class PanelQuad:
    """The panel outline: four lines ``(a, b, c)`` with ``a x + b y + c = 0`` (unit normal,
    pointing out of the panel) in order around it, and their intersections ``corners`` (4, 2),
    corner ``i`` between lines ``i`` and ``i + 1``; ``visible`` flags corners inside the image
    whose two edges were refined. ``rms_px`` per line is the sub-pixel fit residual."""

    lines: np.ndarray
    corners: np.ndarray
    visible: np.ndarray
    rms_px: np.ndarray


def _segment_lines(
    gray8: np.ndarray, min_length: float, config: CornerConfig
) -> list[tuple[np.ndarray, float]]:
    """Straight edges of an image as lines ``(a, b, c)`` (unit normal) with their total
    segment length [px], longest first.

    Line segments come from OpenCV's LSD, which only grows a segment over pixels whose
    gradient directions agree, so the crinkled foil breaks into short pieces while panel edges
    stay long. Collinear segments (same direction within ``nms_theta_deg``, same offset within
    ``nms_rho_px``) are merged into one line fitted to all their endpoints.
    """
    segs = cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE).detect(gray8)[0]
    if segs is None:
        return []
    segs = segs.reshape(-1, 4).astype(np.float64)
    length = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    keep = length >= min_length
    segs, length = segs[keep], length[keep]
    order = np.argsort(-length)
    groups: list[list[int]] = []
    lines: list[np.ndarray] = []
    for i in order:
        d = segs[i, 2:] - segs[i, :2]
        n = np.array([-d[1], d[0]]) / length[i]
        ln = np.array([n[0], n[1], -n @ segs[i, :2]])
        for g, gl in enumerate(lines):
            cos = abs(float(gl[:2] @ n))
            if cos < math.cos(math.radians(config.nms_theta_deg)):
                continue
            # Both endpoints of the segment close to the group's line.
            if (
                max(abs(gl[:2] @ segs[i, :2] + gl[2]), abs(gl[:2] @ segs[i, 2:] + gl[2]))
                < config.nms_rho_px
            ):
                groups[g].append(int(i))
                break
        else:
            groups.append([int(i)])
            lines.append(ln)
    out = []
    for members in groups:
        pts = np.concatenate([segs[members, :2], segs[members, 2:]])
        w = np.concatenate([length[members], length[members]])
        m = (pts * w[:, None]).sum(axis=0) / w.sum()
        cov = ((pts - m).T * w) @ (pts - m)
        n = np.linalg.eigh(cov)[1][:, 0]
        out.append((np.array([n[0], n[1], -n @ m]), float(length[members].sum())))
    out.sort(key=lambda x: -x[1])
    return out[: config.max_lines]


def _line(rho: float, theta: float) -> np.ndarray:
    return np.array([math.cos(theta), math.sin(theta), -rho])


def _intersect(l1: np.ndarray, l2: np.ndarray) -> np.ndarray | None:
    a1, b1, c1 = float(l1[0]), float(l1[1]), float(l1[2])
    a2, b2, c2 = float(l2[0]), float(l2[1]), float(l2[2])
    det = a1 * b2 - a2 * b1
    if abs(det) < 1e-9:
        return None
    return np.array([(b1 * c2 - b2 * c1) / det, (a2 * c1 - a1 * c2) / det])


def find_panel(
    gray: np.ndarray, gray8: np.ndarray, ring: Ellipse, config: CornerConfig, image_s: np.ndarray
) -> PanelQuad | None:
    """The panel quadrilateral around the ring, refined on sub-pixel edges.

    Candidate lines are Hough lines of the Canny edges around the ring; candidate
    quadrilaterals are two pairs of near-parallel lines with the ring between each pair; the
    chosen one has the most edge support along its four sides *between its corners*, with the
    panel brighter inside (lines that merely pass near the panel, such as a solar wing's edge
    extended across it, have no support there). None if no quadrilateral is supported.
    """
    h, w = gray.shape
    R = config.max_extent * ring.a
    x0, y0 = max(0, int(ring.cx - R)), max(0, int(ring.cy - R))
    x1, y1 = min(w, int(ring.cx + R) + 1), min(h, int(ring.cy + R) + 1)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    roi = gray8[y0:y1, x0:x1].copy()
    # The ring and its inside carry no panel edge: flatten them before looking for lines.
    cv2.ellipse(
        roi,
        (round(ring.cx - x0), round(ring.cy - y0)),
        (int(ring.a * 1.08), int(ring.b * 1.08)),
        math.degrees(ring.theta),
        0,
        360,
        int(np.median(roi)),
        -1,
    )
    # Straight-edge detection does not need full resolution (the sub-pixel refinement uses
    # the full image): cap the window's size for speed.
    scale = min(1.0, config.max_search_px / max(roi.shape))
    small = (
        roi
        if scale == 1.0
        else cv2.resize(roi, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    )
    min_len = max(config.min_segment_px, config.min_segment_axis * ring.a) * scale
    lines = []
    for ln, length in _segment_lines(small, min_len, config):
        # Undo the scaling (pixel centres: x_full = (x_small + 0.5) / scale - 0.5).
        c = ln[2] / scale - 0.5 * (ln[0] + ln[1]) * (1 / scale - 1)
        lines.append((np.array([ln[0], ln[1], c]), length / scale))
    if len(lines) < 4:
        return None
    centre = ring.center
    ring_pts = ring.points(16)
    L = []
    for ln, _ in lines:
        ln = ln.copy()
        ln[2] -= ln[0] * x0 + ln[1] * y0  # back to full-image coordinates
        if ln[:2] @ centre + ln[2] > 0:  # orient the normal away from the ring
            ln = -ln
        if np.all(ring_pts @ ln[:2] + ln[2] < 0):  # the whole ring on the inner side
            L.append(ln)
    pairs = []
    for i, j in itertools.combinations(range(len(L)), 2):
        if float(L[i][:2] @ L[j][:2]) < -math.cos(math.radians(config.pair_angle_deg)):
            pairs.append((i, j))  # opposite outward normals: a near-parallel pair
    gx = cv2.Sobel(image_s, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(image_s, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    profiles = [_LineSupport(ln, centre, 2 * R, gx, gy, config) for ln in L]
    cos_corner = math.cos(math.radians(config.min_corner_angle_deg))
    # Quadrilaterals: two crossing pairs; or, close up, one pair and one line crossing it
    # with the fourth side beyond the image (a virtual line just outside it, opposite the
    # single line: its corners are out of view and never reported).
    quads: list[list[int]] = []  # line indices
    for (i, j), (k, m) in itertools.combinations(pairs, 2):
        if len({i, j, k, m}) == 4 and abs(float(L[i][:2] @ L[k][:2])) <= cos_corner:
            quads.append([i, k, j, m])
    n_real = len(L)
    virtual: dict[int, int] = {}
    for (i, j), k in itertools.product(pairs, range(n_real)):
        if k in (i, j) or abs(float(L[i][:2] @ L[k][:2])) > cos_corner:
            continue
        if k not in virtual:
            virtual[k] = len(L)
            L.append(_beyond_image(L[k], w, h))
            profiles.append(_LineSupport(L[-1], centre, 2 * R, gx, gy, config))
        quads.append([i, k, j, virtual[k]])
    best = None
    for idx in quads:
        order = sorted(idx, key=lambda q: math.atan2(L[q][1], L[q][0]))
        corners = [_intersect(L[order[q]], L[order[(q + 1) % 4]]) for q in range(4)]
        if any(c is None for c in corners):
            continue
        C = np.array(corners)
        real = [
            q for q in range(4) if order[q] < n_real and order[(q + 1) % 4] < n_real
        ]  # corners between two found lines
        if np.max(np.linalg.norm(C[real] - centre, axis=1)) > 2 * R:
            continue
        supported = 0.0
        visible_sides = 0
        for q in range(4):
            frac, length = profiles[order[q]].between(C[(q - 1) % 4], C[q])
            if length < 8:
                continue  # side out of view
            if frac < config.min_side_support:
                supported = -1.0
                break
            supported += frac * length
            visible_sides += 1
        if visible_sides < 2 or supported <= 0 or (best is not None and supported <= best[0]):
            continue
        filled, lit = _fill_fraction(image_s, C, config.foreground_level)
        if filled < config.min_fill or lit < config.min_lit:
            continue
        best = (supported, np.array([L[q] for q in order]), C)
    if best is None:
        return None
    quad = _innermost(best[1], L, profiles, config)
    crossings = [_intersect(quad[q], quad[(q + 1) % 4]) for q in range(4)]
    if any(c is None for c in crossings):
        return None
    return _refine_quad(image_s, quad, np.array(crossings), gray.shape, config)


def _beyond_image(line: np.ndarray, w: int, h: int, margin: float = 16.0) -> np.ndarray:
    """The line parallel to ``line`` on the far side of the image (outward normal opposite
    to ``line``'s), ``margin`` px beyond the image's farthest corner in that direction."""
    n = -line[:2]
    box = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    return np.array([n[0], n[1], -float(np.max(box @ n)) - margin])


def _innermost(
    quad: np.ndarray, L: list[np.ndarray], profiles: list[_LineSupport], config: CornerConfig
) -> np.ndarray:
    """Replace each side by the innermost parallel line that is as well supported over the
    same stretch. Seen obliquely, the bus body behind the panel (or the panel's own thickness)
    adds a parallel, well-supported outline just outside the panel's front edge."""
    out = quad.copy()
    for q in range(4):
        a = _intersect(out[(q - 1) % 4], out[q])
        b = _intersect(out[q], out[(q + 1) % 4])
        if a is None or b is None:
            continue
        mid = 0.5 * (a + b)
        k_self = next(i for i, ln in enumerate(L) if np.allclose(ln, out[q]))
        frac0, _ = profiles[k_self].between(a, b)
        best_offset = 0.0
        for i, ln in enumerate(L):
            if i == k_self or float(ln[:2] @ out[q][:2]) < math.cos(math.radians(8.0)):
                continue
            # ln lies `offset` px inside out[q] at the side's middle (normals point outward).
            offset = float(ln[:2] @ mid + ln[2]) - float(out[q][:2] @ mid + out[q][2])
            if offset <= 1.0 or offset >= best_offset + 50:
                continue
            aa = _intersect(out[(q - 1) % 4], ln)
            bb = _intersect(ln, out[(q + 1) % 4])
            if aa is None or bb is None:
                continue
            frac, length = profiles[i].between(aa, bb)
            if (
                length >= 8
                and frac >= max(config.min_side_support, 0.85 * frac0)
                and offset > best_offset
            ):
                best_offset = offset
                out[q] = ln
    return out


def _fill_fraction(image_s: np.ndarray, corners: np.ndarray, level: float) -> tuple[float, float]:
    """``(filled, lit)``: fractions of a grid of points inside the quadrilateral (shrunk by
    6 % towards its centroid, clipped to the image) that lie on the panel, and that are
    brighter than ``level``. The panel is a filled bright face, unlike a quadrilateral of
    struts or wing edges with black space inside.

    A point darker than ``level`` still lies on the panel where its dark region is enclosed
    by the quadrilateral's inside: the ring's bore and wall, the ring's shadow on the panel
    in hard sunlight, dark components. Black space inside a quadrilateral of struts or wing
    edges reaches past the quadrilateral or to the image border; the enclosed holes do not.
    (A closed frame of struts encloses its black inside too: ``lit`` tells that apart.)"""
    h, w = image_s.shape
    c = corners.mean(axis=0)
    Q = c + 0.94 * (corners - c)
    u = np.linspace(0.05, 0.95, 12)
    uu, vv = np.meshgrid(u, u)
    uu, vv = uu.ravel()[:, None], vv.ravel()[:, None]
    # Bilinear interpolation across the quadrilateral's corners 0..3.
    pts = (1 - uu) * (1 - vv) * Q[0] + uu * (1 - vv) * Q[1] + uu * vv * Q[2] + (1 - uu) * vv * Q[3]
    ok = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    if ok.sum() < 10:
        return 0.0, 0.0
    p = pts[ok].astype(np.float32)
    vals = sample_image(image_s, p[:, 0], p[:, 1], "linear")  # inside: border unused
    dark = vals <= level
    lit = 1.0 - float(np.mean(dark))
    if dark.any():
        dark[dark] = _reaches_outside(image_s, corners, level, p[dark])
    return 1.0 - float(np.mean(dark)), lit


def _reaches_outside(
    image_s: np.ndarray, corners: np.ndarray, level: float, points: np.ndarray
) -> np.ndarray:
    """For each of ``points`` (dark pixels inside the quadrilateral ``corners``): does its
    dark region (8-connected pixels at most ``level``) reach outside the quadrilateral or the
    image border?"""
    if np.abs(corners).max() > 1e6:
        return np.ones(len(points), bool)  # a degenerate quadrilateral: nothing enclosed
    h, w = image_s.shape
    inside = np.zeros((h + 2, w + 2), np.uint8)  # one pixel of frame: the image border
    shift = 8  # sub-pixel polygon vertices (fixed point)
    poly = np.round((corners + 1.0) * (1 << shift)).astype(np.int32)
    cv2.fillConvexPoly(inside, poly, 1, lineType=cv2.LINE_8, shift=shift)
    inside[0, :] = inside[-1, :] = 0
    inside[:, 0] = inside[:, -1] = 0
    open_ = np.ones((h + 2, w + 2), np.uint8)
    open_[1:-1, 1:-1] = image_s <= level
    open_[inside == 0] = 1  # everything outside is "open"
    _, labels = cv2.connectedComponents(open_, connectivity=8)
    outside_labels = np.unique(labels[inside == 0])
    q = np.round(points).astype(int)
    return np.isin(labels[q[:, 1] + 1, q[:, 0] + 1], outside_labels)


class _LineSupport:
    """Edge support along one line, sampled once every pixel so that any stretch of it can be
    scored in O(1): a sample is supported where the intensity falls outward across the line
    (within 1.5 px of it) by more than ``support_gradient``."""

    def __init__(
        self,
        line: np.ndarray,
        centre: np.ndarray,
        half_length: float,
        gx: np.ndarray,
        gy: np.ndarray,
        config: CornerConfig,
    ) -> None:
        h, w = gx.shape
        n = line[:2]
        self.d = np.array([-n[1], n[0]])
        self.p0 = centre - (centre @ n + line[2]) * n  # foot of the centre on the line
        self.s0 = -half_length
        s = np.arange(-half_length, half_length + 1.0, 1.0)
        pts = self.p0[None, :] + s[:, None] * self.d[None, :]
        inside = (pts[:, 0] > 2) & (pts[:, 0] < w - 3) & (pts[:, 1] > 2) & (pts[:, 1] < h - 3)
        best = np.full(s.size, -np.inf, dtype=np.float32)
        for off in (-1.5, -0.75, 0.0, 0.75, 1.5):
            p = (pts + off * n).astype(np.float32)
            vx = sample_image(gx, p[:, 0], p[:, 1], "linear")  # only `inside` samples count
            vy = sample_image(gy, p[:, 0], p[:, 1], "linear")
            best = np.maximum(best, -(vx * n[0] + vy * n[1]))
        good = inside & (best > config.support_gradient)
        self.cum_good = np.concatenate([[0], np.cumsum(good)])
        self.cum_in = np.concatenate([[0], np.cumsum(inside)])

    def between(self, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
        """(supported fraction, in-image length [px]) of the stretch between points a and b,
        leaving out 8 % at each end (the corners)."""
        sa = float((a - self.p0) @ self.d)
        sb = float((b - self.p0) @ self.d)
        if sa > sb:
            sa, sb = sb, sa
        span = sb - sa
        top = self.cum_in.size - 1
        ia = min(max(round(sa + 0.08 * span - self.s0), 0), top)
        ib = min(max(round(sb - 0.08 * span - self.s0), 0), top)
        length = float(self.cum_in[ib] - self.cum_in[ia])
        if length <= 0:
            return 0.0, 0.0
        return float(self.cum_good[ib] - self.cum_good[ia]) / length, length


def _refine_quad(
    image_s: np.ndarray,
    lines: np.ndarray,
    corners: np.ndarray,
    shape: tuple[int, ...],
    config: CornerConfig,
) -> PanelQuad | None:
    h, w = shape[:2]
    refined = []
    rms = []
    for k in range(4):
        a, b = corners[(k - 1) % 4], corners[k]  # line k runs between corners k-1 and k
        t = np.linspace(0.1, 0.9, config.edge_samples)
        pts = a[None, :] + t[:, None] * (b - a)[None, :]
        inside = (pts[:, 0] > 2) & (pts[:, 0] < w - 3) & (pts[:, 1] > 2) & (pts[:, 1] < h - 3)
        pts = pts[inside]
        if pts.shape[0] < 8:
            refined.append(lines[k])
            rms.append(np.inf)
            continue
        normal = np.broadcast_to(lines[k][:2], pts.shape)  # outward: bright inside -> dark out
        found, _ = edges_along_normals(
            image_s, pts, np.ascontiguousarray(normal), +1, config.edge_search_px, config.edges
        )
        P = found[np.isfinite(found[:, 0])]
        if P.shape[0] < max(8, config.min_edge_fraction * config.edge_samples * inside.mean()):
            refined.append(lines[k])
            rms.append(np.inf)
            continue
        line = lines[k]
        for _ in range(3):  # total least squares with outlier rejection
            r = P @ line[:2] + line[2]
            sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.05)
            Q = P[np.abs(r - np.median(r)) < 3 * sigma]
            if Q.shape[0] < 8:
                break
            m = Q.mean(axis=0)
            _, _, Vt = np.linalg.svd(Q - m)
            n = Vt[1] if Vt[1] @ lines[k][:2] > 0 else -Vt[1]
            line = np.array([n[0], n[1], -n @ m])
        r = Q @ line[:2] + line[2]
        refined.append(line)
        rms.append(float(np.sqrt(np.mean(r**2))))
    L = np.array(refined)
    out = []
    for k in range(4):
        c = _intersect(L[k], L[(k + 1) % 4])
        if c is None:
            return None
        out.append(c)
    C = np.array(out)
    m = config.image_margin_px
    visible = (C[:, 0] >= m) & (C[:, 0] <= w - 1 - m) & (C[:, 1] >= m) & (C[:, 1] <= h - 1 - m)
    # A corner needs both of its edges refined, each to a clean straight edge.
    rms_a = np.array(rms)
    good = rms_a <= config.max_line_rms_px
    visible &= good & np.roll(good, -1)
    return PanelQuad(lines=L, corners=C, visible=visible, rms_px=rms_a)


# --------------------------------------------------------------------------------------------
# Dark components
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class ComponentConfig:
    """Dark component (blob) detection.

    Attributes:
        min_radius_px, min_radius_fraction, max_radius_fraction: blob radius limits: at least
            ``min_radius_px`` and ``min_radius_fraction`` of the ring's semi-minor axis, at
            most ``max_radius_fraction`` of it (components are small next to the ring).
        min_ring_distance, max_ring_distance: blobs are searched between these multiples of
            the ring ellipse's size (inside it lie shadows; far outside, other structures).
        max_darkness: the blob's inside must be darker than this fraction of its surroundings
            (dark foil facets are rarely this dark next to their neighbours).
        min_edge_fraction: fraction of the blob's outline where a dark-to-bright edge is found.
        max_rms_px: largest RMS distance of those edge points to the fitted ellipse.
        size_tolerance: accepted blobs have radii within this factor of their median (one
            kind of component, one size).
        max_blobs: at most this many components per image, the darkest first.
        edges: sub-pixel edge settings.
    """

    min_radius_px: float = 3.0
    min_radius_fraction: float = 0.06
    max_radius_fraction: float = 0.35
    min_ring_distance: float = 1.08
    max_ring_distance: float = 3.5
    max_darkness: float = 0.2
    min_edge_fraction: float = 0.75
    max_rms_px: float = 1.2
    size_tolerance: float = 1.4
    max_blobs: int = 10
    edges: EdgeSearchConfig = field(
        default_factory=lambda: EdgeSearchConfig(min_step=0.04, smooth_sigma_px=0.8)
    )


def find_components(
    gray: np.ndarray,
    gray8: np.ndarray,
    ring: Ellipse,
    config: ComponentConfig,
    panel_corners: np.ndarray | None = None,
) -> np.ndarray:
    """Centres (N, 2) of small dark round blobs around the ring (inside the panel outline if
    it is known), each the centre of an ellipse fitted to sub-pixel edges of its outline."""
    h, w = gray.shape
    R = config.max_ring_distance * ring.a
    x0, y0 = max(0, int(ring.cx - R)), max(0, int(ring.cy - R))
    x1, y1 = min(w, int(ring.cx + R) + 1), min(h, int(ring.cy + R) + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return np.zeros((0, 2))
    min_r = max(config.min_radius_px, config.min_radius_fraction * ring.b)
    max_r = max(min_r + 1, config.max_radius_fraction * ring.b)
    params = cv2.SimpleBlobDetector_Params()
    params.filterByColor = True
    params.blobColor = 0
    params.minThreshold = 10
    params.maxThreshold = 130
    params.thresholdStep = 15
    params.filterByArea = True
    params.minArea = math.pi * min_r**2
    params.maxArea = math.pi * max_r**2
    params.filterByCircularity = False
    params.filterByInertia = True
    params.minInertiaRatio = 0.3
    params.filterByConvexity = True
    params.minConvexity = 0.8
    keypoints = cv2.SimpleBlobDetector_create(params).detect(gray8[y0:y1, x0:x1])
    image_s: np.ndarray | None = None
    found: list[tuple[float, float, np.ndarray]] = []
    for kp in keypoints:
        c = np.array(kp.pt) + np.array([x0, y0])
        r = kp.size / 2
        if not config.min_ring_distance < _ellipse_radius(ring, c) < config.max_ring_distance:
            continue
        if panel_corners is not None and not _inside(panel_corners, c, shrink=0.98):
            continue
        if _darkness(gray, c, r) > config.max_darkness:  # cheap test before the fit
            continue
        if image_s is None:
            image_s = smoothed(gray, config.edges)
        fit = _fit_blob(gray, image_s, c, r, ring, config)
        if fit is None:
            continue
        e, darkness = fit
        if not (min_r <= math.sqrt(e.a * e.b) <= max_r):
            continue
        found.append((darkness, math.sqrt(e.a * e.b), e.center))
    if not found:
        return np.zeros((0, 2))
    med = float(np.median([r for _, r, _ in found]))
    found = [f for f in found if med / config.size_tolerance <= f[1] <= med * config.size_tolerance]
    found.sort(key=lambda x: x[0])
    return np.array([c for _, _, c in found[: config.max_blobs]]).reshape(-1, 2)


def _inside(corners: np.ndarray, p: np.ndarray, shrink: float) -> bool:
    c = corners.mean(axis=0)
    poly = (c + shrink * (corners - c)).astype(np.float32)
    return cv2.pointPolygonTest(poly, (float(p[0]), float(p[1])), False) > 0


def _darkness(gray: np.ndarray, c: np.ndarray, r: float) -> float:
    """Mean inside 0.5 r over the median of the band 1.5-2.2 r around ``c``."""
    a = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    u = np.stack([np.cos(a), np.sin(a)], axis=1)
    inner = c + 0.5 * r * np.concatenate([u, 0.5 * u, np.zeros((1, 2))])
    outer = c + r * np.concatenate([1.5 * u, 2.2 * u])
    p = np.concatenate([inner, outer]).astype(np.float32)
    v = sample_image(gray, p[:, 0], p[:, 1], "linear")
    out = float(np.median(v[inner.shape[0] :]))
    return float(v[: inner.shape[0]].mean()) / out if out > 0 else np.inf


def _ellipse_radius(e: Ellipse, p: np.ndarray) -> float:
    """Scale factor s such that ``p`` lies on ``e`` scaled by s about its centre."""
    d = p - e.center
    c, s = math.cos(e.theta), math.sin(e.theta)
    u = c * d[0] + s * d[1]
    v = -s * d[0] + c * d[1]
    return math.hypot(u / e.a, v / e.b)


def _fit_blob(
    gray: np.ndarray,
    image_s: np.ndarray,
    c: np.ndarray,
    r: float,
    ring: Ellipse,
    config: ComponentConfig,
) -> tuple[Ellipse, float] | None:
    """Ellipse fitted to the dark-to-bright edges around a blob, and the blob's darkness
    (inside mean / surrounding median). None if the outline is not a clean ellipse."""
    ratio = ring.b / ring.a
    e0 = Ellipse(
        cx=float(c[0]),
        cy=float(c[1]),
        a=max(r / math.sqrt(ratio), 1.5),
        b=max(r * math.sqrt(ratio), 1.5),
        theta=ring.theta,
    )
    n = 32
    pts, _ = edges_along_normals(
        image_s, e0.points(n), e0.normals(n), -1, max(2.0, 0.6 * r), config.edges
    )
    ok = np.isfinite(pts[:, 0])
    if ok.sum() < config.min_edge_fraction * n:
        return None
    try:
        e = fit_ellipse_direct(pts[ok])
        e, _, rms = refine_ellipse(pts[ok], e)
    except ConicError:
        return None
    if rms > config.max_rms_px or np.linalg.norm(e.center - c) > r:
        return None
    darkness = _darkness(gray, e.center, math.sqrt(e.a * e.b))
    if darkness > config.max_darkness:
        return None
    return e, darkness


# --------------------------------------------------------------------------------------------
# Tracking: refine around the previous frame's result instead of searching the whole image
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class PanelTrackConfig:
    """Frame-to-frame tracking of the panel outline and the components.

    Attributes:
        points_per_side: points along each visible side carried by Lucas-Kanade.
        min_good_sides: a tracked outline is kept if at least this many sides refine cleanly.
        redetect_every: components are searched afresh every this many frames (tracked ones
            are refined in between); the panel is searched afresh whenever tracking fails.
        lk_window_px, lk_levels: Lucas-Kanade settings.
    """

    points_per_side: int = 6
    min_good_sides: int = 3
    redetect_every: int = 5
    lk_window_px: int = 21
    lk_levels: int = 3


def _lk(
    prev8: np.ndarray, cur8: np.ndarray, pts: np.ndarray, config: PanelTrackConfig
) -> tuple[np.ndarray, np.ndarray]:
    if len(pts) == 0:
        return pts, np.zeros(0, bool)
    out, st, _ = cv2.calcOpticalFlowPyrLK(
        prev8,
        cur8,
        pts.astype(np.float32).reshape(-1, 1, 2),
        None,
        winSize=(config.lk_window_px, config.lk_window_px),
        maxLevel=config.lk_levels,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    )
    if out is None:
        return pts, np.zeros(len(pts), bool)
    return out.reshape(-1, 2), st.reshape(-1).astype(bool)


class PanelTracker:
    """Panel corners and components in one camera, tracked between frames."""

    def __init__(
        self,
        corners: CornerConfig,
        components: ComponentConfig,
        config: PanelTrackConfig | None = None,
    ) -> None:
        self.corner_config = corners
        self.component_config = components
        self.config = config or PanelTrackConfig()
        self.quad: PanelQuad | None = None
        self.components = np.zeros((0, 2))
        self._prev8: np.ndarray | None = None
        self._frames_since_detection = self.config.redetect_every  # detect on frame one

    def reset(self) -> None:
        self.quad = None
        self.components = np.zeros((0, 2))
        self._prev8 = None
        self._frames_since_detection = self.config.redetect_every  # detect on the next frame

    def update(
        self,
        gray: np.ndarray,
        gray8: np.ndarray,
        image_s: np.ndarray,
        ring: Ellipse,
        with_components: bool,
    ) -> tuple[PanelQuad | None, np.ndarray]:
        """The panel outline (or None) and the component centres (N, 2) in this image."""
        quad = self._follow_quad(gray, gray8, image_s) if self.quad is not None else None
        if quad is None:
            quad = find_panel(gray, gray8, ring, self.corner_config, image_s)
        comps = np.zeros((0, 2))
        if with_components:
            comps = self._components(gray, gray8, image_s, ring, quad)
        self.quad = quad
        self.components = comps
        self._prev8 = gray8
        return quad, comps

    def _follow_quad(
        self, gray: np.ndarray, gray8: np.ndarray, image_s: np.ndarray
    ) -> PanelQuad | None:
        assert self.quad is not None and self._prev8 is not None
        cfg = self.config
        h, w = gray.shape
        old = self.quad
        samples, owner = [], []
        for q in range(4):
            a, b = old.corners[(q - 1) % 4], old.corners[q]
            t = np.linspace(0.15, 0.85, cfg.points_per_side)
            pts = a[None, :] + t[:, None] * (b - a)[None, :]
            ok = (pts[:, 0] > 10) & (pts[:, 0] < w - 11) & (pts[:, 1] > 10) & (pts[:, 1] < h - 11)
            samples.append(pts[ok])
            owner += [q] * int(ok.sum())
        if not owner:
            return None
        moved, st = _lk(self._prev8, gray8, np.vstack(samples), cfg)
        owner_a = np.array(owner)
        lines = old.lines.copy()
        for q in range(4):
            P = moved[(owner_a == q) & st]
            if len(P) >= 2:
                m = P.mean(axis=0)
                _, _, Vt = np.linalg.svd(P - m)
                n = Vt[1] if Vt[1] @ old.lines[q][:2] > 0 else -Vt[1]
                lines[q] = np.array([n[0], n[1], -n @ m])
        crossings = [_intersect(lines[q], lines[(q + 1) % 4]) for q in range(4)]
        if any(c is None for c in crossings):
            return None
        quad = _refine_quad(image_s, lines, np.array(crossings), gray.shape, self.corner_config)
        if quad is None:
            return None
        good = int(np.sum(quad.rms_px <= self.corner_config.max_line_rms_px))
        visible_sides = sum(len(s) > 0 for s in samples)
        if good < min(cfg.min_good_sides, visible_sides):
            return None
        return quad

    def _components(
        self,
        gray: np.ndarray,
        gray8: np.ndarray,
        image_s: np.ndarray,
        ring: Ellipse,
        quad: PanelQuad | None,
    ) -> np.ndarray:
        cfg = self.config
        ccfg = self.component_config
        kept: list[np.ndarray] = []
        if len(self.components) and self._prev8 is not None:
            moved, st = _lk(self._prev8, gray8, self.components, cfg)
            blob_s = smoothed(gray, ccfg.edges)
            r0 = max(ccfg.min_radius_px, 0.12 * ring.b)
            for c in moved[st]:
                fit = _fit_blob(gray, blob_s, c, r0, ring, ccfg)
                if fit is not None:
                    kept.append(fit[0].center)
        self._frames_since_detection += 1
        if self._frames_since_detection >= cfg.redetect_every:
            self._frames_since_detection = 0
            corners = quad.corners if quad is not None and quad.visible.all() else None
            for c in find_components(gray, gray8, ring, ccfg, corners):
                if all(np.linalg.norm(c - k) > 3.0 for k in kept):
                    kept.append(c)
        return np.array(kept).reshape(-1, 2)
