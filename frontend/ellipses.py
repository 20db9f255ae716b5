"""Ellipse detection from arc-support line segments (Lu et al., IEEE TIP 2019), vectorised.

The method of C. Lu, S. Xia, M. Shao, Y. Fu, "Arc-Support Line Segments Revisited: An
Efficient High-Quality Ellipse Detection", IEEE Trans. Image Processing 29 (2019), built from
numpy/scipy/OpenCV primitives so that a full 1024x768 image takes tens of milliseconds on one
core. docs/ellipse_detector.md explains every stage, its parameters and the measured results.

1. **Edges.** Gaussian blur, Sobel gradient, Canny (OpenCV, all int16). Every edge pixel
   gets its unit gradient (pointing from dark to bright) and a sub-pixel position on the edge
   (Devernay's parabola through the gradient magnitude along the dominant gradient axis).
2. **Arc-support line segments.** 8-neighbour edge pixels whose gradient directions differ by
   less than `chain_angle_deg` are linked (m-adjacency; junction pixels are cut out) into
   simple chains, which are ordered by a breadth-first search from one end. Along each chain
   the smoothed, unwrapped gradient direction is cut every `segment_turn_deg` (the
   angle tolerance of LSD's line-support regions), with hysteresis against noise. A piece is
   an *arc-support* segment when it bends consistently: the curvature of a quadratic fit to its
   sub-pixel points (its sign relative to the gradient gives the paper's polarity: is the bright
   side the inside of the arc?), a small fit residual, and a gradient turning the same way.
   Straight pieces and corners are dropped.
3. **Grouping.** The end of one segment is linked to the start of another (of the same
   polarity unless `mixed_polarity`) if they are close (`link_gap_px`) and the direction turns
   the convex way, by at most `link_max_turn_deg` and by no more than the two segments'
   own curvature explains (`link_turn_ratio`); mutually best links form ordered groups.
4. **Initial ellipses.** A direct least-squares fit (Fitzgibbon/Halir-Flusser, batched over
   moment sums, closed-form eigenvector) to every group that turns by at least
   `salient_coverage_deg`, and to every pair of groups that lie on the inner side of each
   other's tangents (the paper's "region limitation") and close enough for their curvature.
   A fit is kept when its segments' sample points lie within `pair_tolerance_px` of it with
   gradients along its normal.
5. **Clustering.** Mode seeking (quick shift, then one mean-shift step) in a parameter space
   where every coordinate is a boundary displacement in pixels.
6. **Screen.** A cheap look-up of every strong cluster's perimeter in a dilated
   orientation bit-mask of the edges ranks them; at most `max_candidates`, within a
   perimeter budget, go on.
7. **Verification.** Edge pixels within a distance tolerance of a candidate whose gradient lies
   within `normal_tolerance_deg` of the ellipse normal (either sign) support it. The perimeter
   is cut into bins of `support_bin_px`; runs of supported bins shorter than `min_run_px` are
   discarded (the paper's connectivity analysis). Support = supported fraction of the
   perimeter; coverage = fraction of `coverage_sectors` sectors supported. Candidates short of
   support first try to grow (gather within `grow_fraction` of their size and refit); then
   gather within `gather_tolerance_px`, refit, gather within `inlier_tolerance_px`, accept
   with enough support and coverage, suppress duplicates.
8. **Refinement.** The inliers are moved back by the smoothing's curvature bias and fitted by
   geometric (orthogonal-distance) least squares (`satpose.frontend.conics.refine_ellipse`);
   then the final support statistics.

Conventions: images are undistorted; pixel (0, 0) is the centre of the top-left pixel
(OpenCV); ellipses are `satpose.frontend.conics.Ellipse` ``(cx, cy, a, b, theta)`` in pixels.
Gradients point from dark to bright, so an edge whose gradient points into the ellipse is
brighter inside (polarity +1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from satpose.datasets.errors import SatposeError
from satpose.frontend.conics import ConicError, Ellipse, refine_ellipse

__all__ = [
    "DetectedEllipse",
    "EllipseDetectionError",
    "EllipseDetectorConfig",
    "detect_ellipses",
]


class EllipseDetectionError(SatposeError):
    """The input of the ellipse detector is invalid (not a 2-D image, NaNs, bad ROI)."""


@dataclass(frozen=True, kw_only=True)
class EllipseDetectorConfig:
    """Thresholds of `detect_ellipses`. Grey levels are on the 8-bit scale whatever the input
    type (uint16 and float images are rescaled first); gradients are in grey levels per pixel.

    Attributes:
        blur_sigma_px: Gaussian pre-blur [px]. Removes sensor noise and the finest foil
            texture; much more would merge the 1-3 px apart concentric ring edges of a far
            ring and shift edges of small ellipses.
        canny_low, canny_high: Canny hysteresis thresholds on the gradient magnitude
            [grey/px]. The ring's rim edges have 20-60 grey/px; noise after the blur stays
            below ~1 grey/px. Low values keep weak, partly shadowed rim arcs connected.
        float_full_scale: value of full scale for float images (1.0: images in [0, 1]).
        chain_angle_deg: two 8-neighbour edge pixels belong to one chain if their gradient
            directions differ by less than this [deg]. Cuts chains at foil-facet junctions
            (which meet at large angles) but not along a smooth curve.
        segment_turn_deg: a chain is cut into segments whose gradient direction spans this
            angle [deg] (LSD's region growing tolerance is 22.5 deg).
        min_segment_px: shortest segment kept [edge pixels].
        min_arc_turn_deg: a segment is arc-support when it bends by at least this [deg] over
            half its length (from the curvature of its sub-pixel points; Lu et al. require the
            gradient directions of the halves to turn by 2.25 deg each); a 22.5 deg piece of
            any circle turns ~11 deg, a straight edge ~0. It may not turn by more than
            `segment_turn_deg`, and its gradient not by more than this against the bend.
        mixed_polarity: link and pair arcs whatever their polarity (only their convexity must
            agree) instead of Lu et al.'s rule (one polarity per group and pair). The ring's
            outer front edge is brighter or darker than the foil beyond it depending on the
            facet, but on the rendered sequences the rule still finds it more often and with
            fewer false positives (docs/ellipse_detector.md).
        max_arc_rms_px: largest RMS residual of a segment's pixels from a quadratic curve
            [px]; rim arcs have 0.05-0.2 px, pieces spanning a foil corner 0.5 px and more.
        link_gap_px: largest gap between the end of a segment and the start of the next one in
            a group [px] (Lu et al. search a 4x4 window beyond the end point; junctions with
            foil edges cut a few pixels out of the rim's chains).
        link_max_turn_deg: largest turn of direction between consecutive segments of a group
            [deg] (3 pi / 8 in Lu et al.); a turn against the group's sense of curvature is
            allowed up to `min_arc_turn_deg` (noise).
        link_turn_ratio: the turn between linked segments may be at most this multiple of
            their own half spans (plus `min_arc_turn_deg`): curvature continuity, which keeps
            the corners of the foil's polygonal facets out of the arcs.
        salient_coverage_deg: a group turning by at least this [deg] is fitted alone (80 deg
            in Lu et al.); smaller groups only pair up with others.
        min_group_px: groups with fewer edge pixels do not take part in pairing.
        max_pair_groups: at most this many groups (the longest) are paired, which bounds the
            quadratic pairing cost in cluttered images.
        pair_tolerance_px: a segment sample point supports an initial ellipse within this
            distance [px] (3 * 2 px in Lu et al.'s rectangles); also the slack of the region
            limitation test.
        pair_min_fraction: fraction of a group's pixels (by segment) that must support an
            initial ellipse fitted to it.
        min_semi_minor_px: smallest semi-minor axis reported [px]. On the rendered sequences
            every detection below 8 px was a round foil speckle (docs/ellipse_detector.md).
        max_semi_major_px: largest semi-major axis [px]; None means the larger image side.
        min_axis_ratio: smallest b / a accepted (a circle seen at 73 deg incidence); false
            detections on foil are elongated (median b / a 0.47), the ring is > 0.6.
        cluster_center_px: initial ellipses closer than this [px] ...
        cluster_rel: ... plus this fraction of the smaller semi-minor axis are neighbours in
            the clustering, in a space where each coordinate moves the boundary by a pixel:
            ``[cx, cy, a, b, (a - b) cos 2 theta, (a - b) sin 2 theta]``.
        max_candidates: at most this many clusters are verified exactly (the strongest and
            salient ones, then by screen score, within a perimeter budget).
        normal_tolerance_deg: an edge pixel supports an ellipse when its gradient is within
            this angle [deg] of the ellipse normal, either sign (22.5 deg in Lu et al.).
        grow_fraction: a candidate short of support gathers edge pixels within this fraction of
            its semi-major axis (at least `gather_tolerance_px`, at most 8 px) and refits; the
            result is kept if it is better supported: an initial ellipse from a 110 deg arc of
            the ring can be 5-10 px off on the far side.
        gather_tolerance_px: distance tolerance of the first (loose) verification pass [px].
        inlier_tolerance_px: distance tolerance of the acceptance and final passes [px].
        support_bin_px: perimeter bin length for the support fraction [px]; 2 px so that the
            8-connected pixels of a continuous edge (spacing up to sqrt 2) fill every bin.
        min_run_px: supported perimeter runs shorter than this [px] are discarded (stray
            inliers of clutter crossing the ellipse at a shallow angle).
        min_support: smallest supported fraction of the perimeter accepted. A 180 deg arc has
            0.5; the ring's outer front edge typically 0.6-0.95, false detections ~0.5.
        min_coverage: smallest fraction of angular sectors with support.
        coverage_sectors: number of sectors of equal perimeter length for the coverage.
        mixed_polarity_fraction: the polarity is reported as 0 (mixed) when the minority
            polarity has more than this fraction of the inliers.
        duplicate_center_px, duplicate_axis_px: after verification, a candidate this close to
            a better supported one (centre, each semi-axis) [px] is a duplicate.
        max_shared_inliers: a candidate sharing more than this fraction of its inliers with a
            better supported one is a duplicate (a false ellipse built on a real one's arc).
        refine_iterations: Gauss-Newton iterations of the geometric refinement (0: keep the
            algebraic fit).
    """

    blur_sigma_px: float = 1.0
    canny_low: float = 4.0
    canny_high: float = 10.0
    float_full_scale: float = 1.0
    chain_angle_deg: float = 22.5
    segment_turn_deg: float = 22.5
    min_segment_px: int = 6
    min_arc_turn_deg: float = 3.0
    max_arc_rms_px: float = 0.4
    mixed_polarity: bool = False
    link_gap_px: float = 8.0
    link_max_turn_deg: float = 67.5
    link_turn_ratio: float = 2.0
    salient_coverage_deg: float = 80.0
    min_group_px: int = 20
    max_pair_groups: int = 200
    pair_tolerance_px: float = 3.0
    pair_min_fraction: float = 0.8
    min_semi_minor_px: float = 8.0
    max_semi_major_px: float | None = None
    min_axis_ratio: float = 0.3
    cluster_center_px: float = 2.0
    cluster_rel: float = 0.02
    max_candidates: int = 24
    normal_tolerance_deg: float = 22.5
    grow_fraction: float = 0.06
    gather_tolerance_px: float = 2.0
    inlier_tolerance_px: float = 1.0
    support_bin_px: float = 2.0
    min_run_px: float = 6.0
    min_support: float = 0.45
    min_coverage: float = 0.45
    coverage_sectors: int = 36
    mixed_polarity_fraction: float = 0.2
    duplicate_center_px: float = 1.5
    duplicate_axis_px: float = 1.5
    max_shared_inliers: float = 0.5
    refine_iterations: int = 2

    def __post_init__(self) -> None:
        positive = {
            "canny_high": self.canny_high,
            "float_full_scale": self.float_full_scale,
            "chain_angle_deg": self.chain_angle_deg,
            "segment_turn_deg": self.segment_turn_deg,
            "link_gap_px": self.link_gap_px,
            "max_arc_rms_px": self.max_arc_rms_px,
            "link_max_turn_deg": self.link_max_turn_deg,
            "link_turn_ratio": self.link_turn_ratio,
            "pair_tolerance_px": self.pair_tolerance_px,
            "min_semi_minor_px": self.min_semi_minor_px,
            "normal_tolerance_deg": self.normal_tolerance_deg,
            "gather_tolerance_px": self.gather_tolerance_px,
            "inlier_tolerance_px": self.inlier_tolerance_px,
            "support_bin_px": self.support_bin_px,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise EllipseDetectionError(
                    f"EllipseDetectorConfig.{name} must be > 0, got {value}"
                )
        non_negative = {
            "blur_sigma_px": self.blur_sigma_px,
            "canny_low": self.canny_low,
            "min_arc_turn_deg": self.min_arc_turn_deg,
            "salient_coverage_deg": self.salient_coverage_deg,
            "cluster_center_px": self.cluster_center_px,
            "cluster_rel": self.cluster_rel,
            "min_run_px": self.min_run_px,
            "grow_fraction": self.grow_fraction,
            "duplicate_center_px": self.duplicate_center_px,
            "duplicate_axis_px": self.duplicate_axis_px,
        }
        for name, value in non_negative.items():
            if not (math.isfinite(value) and value >= 0):
                raise EllipseDetectionError(
                    f"EllipseDetectorConfig.{name} must be >= 0, got {value}"
                )
        if self.canny_low > self.canny_high:
            raise EllipseDetectionError("EllipseDetectorConfig: canny_low must be <= canny_high")
        fractions = {
            "pair_min_fraction": self.pair_min_fraction,
            "min_axis_ratio": self.min_axis_ratio,
            "min_support": self.min_support,
            "min_coverage": self.min_coverage,
            "mixed_polarity_fraction": self.mixed_polarity_fraction,
            "max_shared_inliers": self.max_shared_inliers,
        }
        for name, value in fractions.items():
            if not (0.0 <= value <= 1.0):
                raise EllipseDetectionError(
                    f"EllipseDetectorConfig.{name} must be in [0, 1], got {value}"
                )
        counts = {
            "min_segment_px": self.min_segment_px,
            "min_group_px": self.min_group_px,
            "max_pair_groups": self.max_pair_groups,
            "max_candidates": self.max_candidates,
            "coverage_sectors": self.coverage_sectors,
        }
        for name, value in counts.items():
            if int(value) != value or value < 1:
                raise EllipseDetectionError(
                    f"EllipseDetectorConfig.{name} must be a positive integer, got {value}"
                )
        if int(self.refine_iterations) != self.refine_iterations or self.refine_iterations < 0:
            raise EllipseDetectionError(
                "EllipseDetectorConfig.refine_iterations must be a non-negative integer"
            )
        if self.max_semi_major_px is not None and not self.max_semi_major_px > 0:
            raise EllipseDetectionError("EllipseDetectorConfig.max_semi_major_px must be > 0")
        if self.segment_turn_deg >= 90 or self.chain_angle_deg >= 90:
            raise EllipseDetectionError(
                "EllipseDetectorConfig: segment_turn_deg and chain_angle_deg must be < 90"
            )


@dataclass(frozen=True, kw_only=True)
class DetectedEllipse:
    """One detected ellipse.

    Attributes:
        ellipse: the ellipse in undistorted full-image pixels.
        support: fraction of the perimeter with consistent edge support, 0..1.
        coverage: fraction of angular sectors (of equal perimeter length) with support, 0..1.
        polarity: +1 brighter inside, -1 darker inside, 0 mixed.
        inliers: (N, 2) sub-pixel edge positions supporting it [px], full-image coordinates.
    """

    ellipse: Ellipse
    support: float
    coverage: float
    polarity: int
    inliers: np.ndarray


# ---------------------------------------------------------------------------------------------
# Public entry point
# ---------------------------------------------------------------------------------------------

_MIN_SIDE_PX = 8
"""Images (or ROIs) narrower than this cannot hold a verifiable ellipse: return []."""


def detect_ellipses(
    gray: np.ndarray,
    config: EllipseDetectorConfig = EllipseDetectorConfig(),
    roi: tuple[int, int, int, int] | None = None,
) -> list[DetectedEllipse]:
    """Detect ellipses in a grey image.

    Args:
        gray: (H, W) image, uint8, uint16 or float (float: `config.float_full_scale` is full
            scale), undistorted.
        config: thresholds (see `EllipseDetectorConfig`).
        roi: ``(x0, y0, x1, y1)`` search window [px], ``x1``/``y1`` exclusive; only edges
            inside it are used, results stay in full-image coordinates. None: whole image.

    Returns:
        Detections sorted by decreasing support. A black, saturated, tiny or featureless image
        gives ``[]``.

    Raises:
        EllipseDetectionError: ``gray`` is not a 2-D array of a supported type, holds NaN or
            infinite values, or ``roi`` is malformed.
    """
    img = _as_levels(gray, config)
    H, W = img.shape
    box = _roi_box(roi, W, H)
    if box is None:
        return []
    x0, y0, x1, y1 = box
    if x1 - x0 < _MIN_SIDE_PX or y1 - y0 < _MIN_SIDE_PX:
        return []
    # Process a crop with a margin so that blur and gradients inside the ROI match the full
    # image's; edges in the margin are dropped.
    margin = math.ceil(3 * config.blur_sigma_px) + 2
    cx0, cy0 = max(0, x0 - margin), max(0, y0 - margin)
    cx1, cy1 = min(W, x1 + margin), min(H, y1 + margin)
    crop = img[cy0:cy1, cx0:cx1]
    inner = (x0 - cx0, y0 - cy0, x1 - cx0, y1 - cy0)
    max_a = config.max_semi_major_px if config.max_semi_major_px is not None else float(max(W, H))

    edges = _edge_pixels(crop, inner, config)
    if edges.n < _MIN_SIDE_PX:
        return []
    segs = _arc_segments(edges, config)
    if segs.m == 0:
        return []
    groups = _group_segments(segs, config)
    cands, weights, salient = _initial_ellipses(segs, groups, config, max_a)
    if len(cands) == 0:
        return []
    cands, weights, salient = _cluster(cands, weights, salient, config)
    index = _EdgeIndex.build(edges)
    cands = _screen(cands, weights, salient, index, config)
    found = _verify(cands, index, config, max_a)
    out = []
    for f in found:
        e = f.ellipse
        shifted = Ellipse(cx=e.cx + cx0, cy=e.cy + cy0, a=e.a, b=e.b, theta=e.theta)
        inl = f.inliers + np.array([cx0, cy0], dtype=float)
        out.append(
            DetectedEllipse(
                ellipse=shifted,
                support=f.support,
                coverage=f.coverage,
                polarity=f.polarity,
                inliers=inl,
            )
        )
    return out


_LEVELS = 16.0
"""Images are processed as int16 at 1/16 grey level (8-bit scale): full scale is 4080, and the
Sobel response (scaled by 1/8) of any edge fits int16 with 1/16 grey/px resolution."""


def _as_levels(gray: np.ndarray, config: EllipseDetectorConfig) -> np.ndarray:
    """Validate the input and return it as int16 in 1/16 grey levels of the 8-bit scale."""
    if not isinstance(gray, np.ndarray):
        raise EllipseDetectionError(f"gray must be a numpy array, got {type(gray).__name__}")
    if gray.ndim != 2:
        raise EllipseDetectionError(
            f"gray must be a 2-D (H, W) grey image, got shape {gray.shape} "
            "(convert colour images with cv2.cvtColor first)"
        )
    if gray.dtype == np.uint8:
        return gray.astype(np.int16) << 4
    if gray.dtype == np.uint16:
        scale = 255.0 * _LEVELS / 65535.0
    elif np.issubdtype(gray.dtype, np.floating):
        if not np.all(np.isfinite(gray)):
            raise EllipseDetectionError("gray holds NaN or infinite values")
        scale = 255.0 * _LEVELS / config.float_full_scale
    else:
        raise EllipseDetectionError(f"gray must be uint8, uint16 or float, got {gray.dtype}")
    levels = np.clip(gray.astype(np.float32) * np.float32(scale), -32767, 32767)
    return np.rint(levels).astype(np.int16)


def _roi_box(
    roi: tuple[int, int, int, int] | None, W: int, H: int
) -> tuple[int, int, int, int] | None:
    """The ROI clipped to the image, or None if it misses the image."""
    if roi is None:
        return 0, 0, W, H
    try:
        vals = [float(v) for v in roi]
    except (TypeError, ValueError):
        raise EllipseDetectionError(f"roi must be (x0, y0, x1, y1), got {roi!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise EllipseDetectionError(f"roi must be 4 finite numbers (x0, y0, x1, y1), got {roi!r}")
    x0, y0, x1, y1 = (round(v) for v in vals)
    if x1 <= x0 or y1 <= y0:
        raise EllipseDetectionError(f"roi must have x1 > x0 and y1 > y0, got {roi!r}")
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


# ---------------------------------------------------------------------------------------------
# 1. Edge pixels
# ---------------------------------------------------------------------------------------------


@dataclass
class _Edges:
    """Canny edge pixels of the processed crop, (N,) arrays."""

    ix: np.ndarray  # int32 column
    iy: np.ndarray  # int32 row
    x: np.ndarray  # float64 sub-pixel position
    y: np.ndarray
    gx: np.ndarray  # float64 unit gradient, dark -> bright
    gy: np.ndarray
    shape: tuple[int, int]

    @property
    def n(self) -> int:
        return int(self.ix.size)


def _edge_pixels(
    img: np.ndarray, inner: tuple[int, int, int, int], cfg: EllipseDetectorConfig
) -> _Edges:
    """Canny edges inside ``inner`` with unit gradients and sub-pixel positions.

    ``img`` is int16 in 1/16 grey levels (`_as_levels`); everything full-size stays int16,
    magnitudes are computed at edge pixels only.
    """
    H, W = img.shape
    if cfg.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    # scale 1/8: the Sobel response of a ramp of slope s [grey/px] is s (here in 1/16 units).
    dx = cv2.Sobel(img, cv2.CV_16S, 1, 0, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE)
    dy = cv2.Sobel(img, cv2.CV_16S, 0, 1, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE)
    edges = cv2.Canny(dx, dy, cfg.canny_low * _LEVELS, cfg.canny_high * _LEVELS, L2gradient=True)
    # Sub-pixel interpolation needs both neighbours: drop the crop's outer pixel ring, and
    # everything outside the ROI.
    x0, y0, x1, y1 = inner
    x0, y0, x1, y1 = max(x0, 1), max(y0, 1), min(x1, W - 1), min(y1, H - 1)
    nz = cv2.findNonZero(edges[y0:y1, x0:x1]) if x1 > x0 and y1 > y0 else None
    if nz is None:
        empty_i = np.zeros(0, np.int32)
        empty_f = np.zeros(0)
        return _Edges(empty_i, empty_i, empty_f, empty_f, empty_f, empty_f, (H, W))
    nz = nz.reshape(-1, 2)  # (N, 1, 2) in OpenCV 4, (N, 2) in OpenCV 5
    ix = nz[:, 0].astype(np.int32) + x0
    iy = nz[:, 1].astype(np.int32) + y0
    # Flat gathers (np.take) are several times faster than 2-D fancy indexing.
    dxf, dyf = dx.ravel(), dy.ravel()
    flat = iy.astype(np.intp) * W + ix
    ex = np.take(dxf, flat).astype(np.float64)
    ey = np.take(dyf, flat).astype(np.float64)
    m0 = _norm(ex, ey)
    keep = m0 > 0
    if not keep.all():
        ix, iy, ex, ey, m0, flat = ix[keep], iy[keep], ex[keep], ey[keep], m0[keep], flat[keep]
    # Devernay (1995): a parabola through the magnitude at the pixel and its two neighbours
    # along the dominant gradient axis puts the point on the edge curve (not on the normal
    # through the pixel centre), which is what an ellipse fit needs.
    horiz = np.abs(ex) >= np.abs(ey)
    step = np.where(horiz, 1, W)
    lo, hi = flat - step, flat + step
    mm = _norm(np.take(dxf, lo).astype(np.float64), np.take(dyf, lo).astype(np.float64))
    mp = _norm(np.take(dxf, hi).astype(np.float64), np.take(dyf, hi).astype(np.float64))
    den = mm - 2.0 * m0 + mp
    off = np.where(den < 0, 0.5 * (mm - mp) / np.where(den < 0, den, -1.0), 0.0)
    off = np.clip(off, -0.5, 0.5)
    sx = np.where(horiz, off, 0.0)
    sy = np.where(horiz, 0.0, off)
    return _Edges(ix, iy, ix + sx, iy + sy, ex / m0, ey / m0, (H, W))


# ---------------------------------------------------------------------------------------------
# 2. Arc-support line segments
# ---------------------------------------------------------------------------------------------

_NEIGHBOURS = ((0, 1), (1, -1), (1, 0), (1, 1))
"""Forward 8-neighbour offsets (dy, dx): each unordered pixel pair is visited once."""

_EXP = [(i, j) for i in range(5) for j in range(5 - i)]
"""Exponents (i, j) of the moments sum(x^i y^j) up to order 4 (15 of them)."""
_EXP_INDEX = {e: k for k, e in enumerate(_EXP)}
_DESIGN = [(2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0)]
"""Monomials of the conic design vector [x^2, xy, y^2, x, y, 1]."""
_S_INDEX = np.array(
    [[_EXP_INDEX[(p[0] + q[0], p[1] + q[1])] for q in _DESIGN] for p in _DESIGN], dtype=np.intp
)
"""Scatter matrix S = sum d d^T of the design vectors as moment indices (6, 6)."""


@dataclass
class _Segments:
    """Arc-support segments, (M,) arrays unless noted."""

    n: np.ndarray  # edge pixels
    cx: np.ndarray  # centroid [px]
    cy: np.ndarray
    tx: np.ndarray  # unit direction d: along it the arc turns clockwise (image coordinates)
    ty: np.ndarray
    length: np.ndarray  # extent along d [px]
    turn: np.ndarray  # half the turn across the segment [rad], > 0 (curvature x length / 2)
    polarity: np.ndarray  # +1 brighter on the inner (concave) side, -1 darker
    start: np.ndarray  # (M, 2) first pixel along d
    end: np.ndarray  # (M, 2) last pixel
    samples: np.ndarray  # (M, 3, 2) start, middle, end pixel positions
    sample_grad: np.ndarray  # (M, 3, 2) their unit gradients
    moments: np.ndarray  # (M, 15) sum dx^i dy^j about the centroid

    @property
    def m(self) -> int:
        return int(self.n.size)


def _components(i: np.ndarray, j: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components of the undirected graph with edges (i, j) on n nodes."""
    graph = coo_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(n, n))
    ncomp, labels = connected_components(graph, directed=False)
    return int(ncomp), labels


def _norm(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """sqrt(x^2 + y^2) (np.hypot guards against overflow and is several times slower)."""
    return np.sqrt(x * x + y * y)


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def _arc_segments(E: _Edges, cfg: EllipseDetectorConfig) -> _Segments:
    """Simple chains of slowly turning gradient, cut into pieces, kept if arc-support."""
    I, J = _chain_links(E, cfg)
    order, path_start = _order_chains(I, J, E.n, cfg.min_segment_px)
    n = order.size
    if n == 0:
        return _empty_segments()
    # Along each ordered chain: smooth the unit gradient over +-2 px, unwrap its direction
    # and cut wherever it has turned by another `segment_turn_deg` (a piece spans at most that
    # angle, like an LSD line-support region; smoothing stops noise flicking pixels between
    # pieces at a cut).
    gx, gy = E.gx[order], E.gy[order]
    first = np.zeros(n, dtype=bool)
    first[path_start] = True
    path = np.cumsum(first) - 1
    sgx = _path_box_sum(gx, path, path_start, 2)
    sgy = _path_box_sum(gy, path, path_start, 2)
    psi = np.arctan2(sgy, sgx)
    step = _wrap(np.diff(psi, prepend=0.0))
    step[first] = 0.0
    cum = np.cumsum(step)
    psi_u = cum - cum[path_start][path]
    w = math.radians(cfg.segment_turn_deg)
    piece = np.floor(psi_u / w + 0.5).astype(np.int64)
    change = first | (np.diff(piece, prepend=piece[0] - 1) != 0)
    seg = _absorb_short_runs(np.cumsum(change) - 1, path, cfg.min_segment_px)
    nseg = int(seg[-1]) + 1 if n else 0
    cnt = np.bincount(seg, minlength=nseg)
    keep_seg = cnt >= cfg.min_segment_px
    pix = np.flatnonzero(keep_seg[seg])
    if pix.size == 0:
        return _empty_segments()
    new_id = np.cumsum(keep_seg) - 1
    s = new_id[seg[pix]]
    m = int(keep_seg.sum())
    src = order[pix]
    x, y, gx, gy = E.x[src], E.y[src], E.gx[src], E.gy[src]
    cntf = np.bincount(s, minlength=m).astype(float)
    cx = np.bincount(s, x, minlength=m) / cntf
    cy = np.bincount(s, y, minlength=m) / cntf
    mgx = np.bincount(s, gx, minlength=m)
    mgy = np.bincount(s, gy, minlength=m)
    norm = np.hypot(mgx, mgy)
    norm[norm == 0] = 1.0
    tx, ty = -mgy / norm, mgx / norm
    # Pixels are in chain order inside every segment: first, middle and last by position.
    bounds = np.concatenate([[0], np.cumsum(np.bincount(s, minlength=m))])
    i0, i1 = bounds[:-1], bounds[1:] - 1
    imid = (i0 + i1) // 2
    # Orient every segment along its tangent (gradient rotated by +90 deg).
    u0 = (x[i0] - cx) * tx + (y[i0] - cy) * ty
    u1 = (x[i1] - cx) * tx + (y[i1] - cy) * ty
    flip = u0 > u1
    i0, i1 = np.where(flip, i1, i0), np.where(flip, i0, i1)
    length = np.abs(u1 - u0)
    # Turning between the halves (chain order, oriented along t): angle from the first half's
    # mean gradient to the second half's. Near the ring the foil perturbs the gradient
    # direction by ~5 deg over 5-10 px, so on short pieces this only detects corners (a turn
    # larger than a piece can span) and contradictions.
    pos = np.arange(s.size) - bounds[s]
    half = cntf[s] / 2
    second = np.where(flip[s], pos < half, pos >= half)
    lx = np.bincount(s, np.where(second, 0.0, gx), minlength=m)
    ly = np.bincount(s, np.where(second, 0.0, gy), minlength=m)
    hx = np.bincount(s, np.where(second, gx, 0.0), minlength=m)
    hy = np.bincount(s, np.where(second, gy, 0.0), minlength=m)
    grad_turn = np.arctan2(lx * hy - ly * hx, lx * hx + ly * hy)
    # The curvature itself comes from the sub-pixel positions: a quadratic v = c0 + c1 u +
    # c2 u^2 in the frame (u along t, v along the mean gradient). c2 > 0 bends the piece
    # towards its gradient, i.e. its centre of curvature is on the bright side. Half the turn
    # across the piece is c2 * length (a 24 px piece of a 64 px circle: 1.1 px sagitta,
    # measured to ~0.15 px).
    u = (x - cx[s]) * tx[s] + (y - cy[s]) * ty[s]
    v = (x - cx[s]) * ty[s] - (y - cy[s]) * tx[s]
    uu = u * u
    sums = [np.bincount(s, w_, minlength=m) for w_ in (u, uu, uu * u, uu * uu, v, u * v, uu * v)]
    su, su2, su3, su4, sv, suv, su2v = sums
    A = np.stack(
        [
            np.stack([cntf, su, su2], axis=1),
            np.stack([su, su2, su3], axis=1),
            np.stack([su2, su3, su4], axis=1),
        ],
        axis=1,
    )
    rhs = np.stack([sv, suv, su2v], axis=1)
    ok_fit = np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(su4 * su2 * cntf, 1e-300)
    A[~ok_fit] = np.eye(3)
    coef = np.linalg.solve(A, rhs[..., None])[..., 0]
    sv2 = np.bincount(s, v * v, minlength=m)
    rms = np.sqrt(np.maximum(sv2 - np.einsum("ij,ij->i", coef, rhs), 0.0) / cntf)
    turn = coef[:, 2] * length
    pol_geo = np.where(turn > 0, 1.0, -1.0)
    # Arc-support: bent by more than noise, no more than a piece can span, smooth (a corner
    # or a wiggle leaves residuals), the gradient turns neither against the bend nor by more
    # than a piece, and the chord is not much shorter than the pixel count.
    arc = (
        ok_fit
        & (np.abs(turn) >= math.radians(cfg.min_arc_turn_deg))
        & (np.abs(turn) <= w)
        & (np.abs(grad_turn) <= w)
        & (pol_geo * grad_turn <= math.radians(cfg.min_arc_turn_deg))
        & (rms <= cfg.max_arc_rms_px)
        & (length >= cfg.min_segment_px - 1)
    )
    if not arc.any():
        return _empty_segments()
    keep = np.flatnonzero(arc)
    # Moments about the centroid, of arc-support segments only (for the batched fits).
    on = arc[s]
    relabel = np.cumsum(arc) - 1
    moments = _moment_sums(x[on] - cx[s[on]], y[on] - cy[s[on]], relabel[s[on]], keep.size)
    pts = np.stack([x, y], axis=1)
    grd = np.stack([gx, gy], axis=1)
    # Polarity: a bright-inside arc (c2 > 0: gradient towards its centre of curvature) turns
    # clockwise in image coordinates (y down) when followed along t = gradient rotated by
    # +90 deg; a dark-inside arc turns counter-clockwise. Followed along d = polarity * t
    # instead, every arc of a convex curve turns clockwise whatever its polarity, and its inner
    # normal is d rotated by -90 deg: the geometry used from here on.
    pol = np.where(turn[keep] > 0, 1, -1).astype(np.int64)
    k0, k1 = i0[keep], i1[keep]
    rev = pol < 0
    k0, k1 = np.where(rev, k1, k0), np.where(rev, k0, k1)
    idx3 = np.stack([k0, imid[keep], k1], axis=1)
    return _Segments(
        n=cntf[keep],
        cx=cx[keep],
        cy=cy[keep],
        tx=pol * tx[keep],
        ty=pol * ty[keep],
        length=length[keep],
        turn=np.abs(turn[keep]),
        polarity=pol,
        start=pts[k0],
        end=pts[k1],
        samples=pts[idx3],
        sample_grad=grd[idx3],
        moments=moments,
    )


def _absorb_short_runs(run: np.ndarray, path: np.ndarray, min_len: int) -> np.ndarray:
    """Hysteresis for the cuts: a run shorter than ``min_len`` joins the last long run before
    it on its path (or the first one after it at the start of a path). On a large circle the
    direction turns slowly (0.2 deg/px at 300 px radius), so noise moves pixels back and forth
    across a cut for several pixels; without this they would form tiny dropped pieces and
    leave gaps between the segments.

    Args:
        run: (n,) non-decreasing run label of every pixel in chain order.
        path: (n,) path label of every pixel (runs never straddle paths).

    Returns:
        (n,) non-decreasing segment labels 0, 1, ... .
    """
    if run.size == 0:
        return run
    nrun = int(run[-1]) + 1
    length = np.bincount(run, minlength=nrun)
    rpath = np.zeros(nrun, dtype=np.int64)
    rpath[run] = path
    idx = np.arange(nrun)
    long_ = length >= min_len
    prev_long = np.maximum.accumulate(np.where(long_, idx, -1))
    next_long = np.minimum.accumulate(np.where(long_, idx, nrun)[::-1])[::-1]
    ok_prev = (prev_long >= 0) & (rpath[np.maximum(prev_long, 0)] == rpath)
    ok_next = (next_long < nrun) & (rpath[np.minimum(next_long, nrun - 1)] == rpath)
    target = np.where(ok_prev, prev_long, np.where(ok_next, next_long, idx))
    new = target[run]
    return np.cumsum(np.diff(new, prepend=new[0] - 1) != 0) - 1


def _chain_links(E: _Edges, cfg: EllipseDetectorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Links (I, J) between edge pixels that form simple chains.

    Two 8-neighbours are linked when their gradient directions differ by less than
    `chain_angle_deg`; a diagonal link is dropped when the two pixels are also joined through
    a common 4-neighbour (m-adjacency: a staircase is a path, not a triangle); pixels left with
    three or more links are junctions and lose all of them.
    """
    H, W = E.shape
    n = E.n
    # Flat indices into a (H + 2) x (W + 2) padded grid: neighbours are fixed offsets.
    Wp = W + 2
    flat = (E.iy.astype(np.intp) + 1) * Wp + E.ix + 1
    index = np.full((H + 2) * Wp, -1, dtype=np.int32)
    index[flat] = np.arange(n, dtype=np.int32)
    cos_chain = math.cos(math.radians(cfg.chain_angle_deg))
    links = {}
    for dy, dx in _NEIGHBOURS:
        j = np.take(index, flat + (dy * Wp + dx))
        i = np.flatnonzero(j >= 0)
        j = j[i]
        ok = E.gx[i] * E.gx[j] + E.gy[i] * E.gy[j] >= cos_chain
        links[(dy, dx)] = (i[ok], j[ok])
    # 4-links as flat images: right[p] links p to p + 1, down[p] links p to p + Wp.
    right = np.zeros((H + 2) * Wp, dtype=bool)
    down = np.zeros((H + 2) * Wp, dtype=bool)
    right[flat[links[(0, 1)][0]]] = True
    down[flat[links[(1, 0)][0]]] = True
    i, j = links[(1, 1)]
    q = flat[i]
    keep = ~((right[q] & down[q + 1]) | (down[q] & right[q + Wp]))
    links[(1, 1)] = (i[keep], j[keep])
    i, j = links[(1, -1)]
    q = flat[i]
    keep = ~((right[q - 1] & down[q - 1]) | (down[q] & right[q + Wp - 1]))
    links[(1, -1)] = (i[keep], j[keep])
    I = np.concatenate([v[0] for v in links.values()])
    J = np.concatenate([v[1] for v in links.values()])
    deg = np.bincount(I, minlength=n) + np.bincount(J, minlength=n)
    ok = (deg[I] <= 2) & (deg[J] <= 2)
    return I[ok], J[ok]


def _order_chains(
    I: np.ndarray, J: np.ndarray, n: int, min_len: int
) -> tuple[np.ndarray, np.ndarray]:
    """Order the nodes of a graph of simple paths and cycles (degree <= 2) along each path.

    Returns:
        ``order``: node indices of the paths with at least ``min_len`` nodes, path after path,
        each from one end to the other (a cycle is opened at its lowest node), and
        ``path_start`` (P,): position in ``order`` where each path begins.
    """
    ncomp, comp = _components(I, J, n)
    sizes = np.bincount(comp, minlength=ncomp)
    long_ = sizes >= min_len
    keep = long_[comp[I]]
    I, J = I[keep], J[keep]
    deg = np.bincount(I, minlength=n) + np.bincount(J, minlength=n)
    # One start per long path: its lowest end (degree 1), or for a cycle (no end) its lowest
    # node, one of whose two links is cut.
    src = np.full(ncomp, n, dtype=np.int64)
    ends = np.flatnonzero((deg <= 1) & long_[comp])
    np.minimum.at(src, comp[ends], ends)
    cyc = (src == n) & long_
    if cyc.any():
        np.minimum.at(src, comp, np.where(cyc[comp], np.arange(n), n))
        heads = np.zeros(n, dtype=bool)
        heads[src[cyc]] = True
        touch = heads[I] | heads[J]
        # Cut one link per cycle head: the first listed.
        k = np.flatnonzero(touch)
        head_of = np.where(heads[I[k]], I[k], J[k])
        _, first = np.unique(head_of, return_index=True)
        cut = np.ones(I.size, dtype=bool)
        cut[k[first]] = False
        I, J = I[cut], J[cut]
    # Breadth-first search from a super-source linked to every start: within one path the
    # visiting order is the order along the path.
    starts = src[long_]
    gi = np.concatenate([I, np.full(starts.size, n)])
    gj = np.concatenate([J, starts])
    graph = coo_matrix((np.ones(gi.size, dtype=np.int8), (gi, gj)), shape=(n + 1, n + 1))
    visit = breadth_first_order(graph.tocsr(), n, directed=False, return_predecessors=False)
    visit = visit[visit < n]
    order = visit[np.argsort(comp[visit], kind="stable")]
    path_start = np.concatenate([[0], np.cumsum(sizes[long_])[:-1]])
    return order, path_start


def _path_box_sum(v: np.ndarray, path: np.ndarray, path_start: np.ndarray, h: int) -> np.ndarray:
    """Sum of ``v`` over a window of +-h positions, clipped to each path (v in path order)."""
    n = v.size
    c = np.concatenate([[0.0], np.cumsum(v)])
    ends = np.concatenate([path_start[1:], [n]])
    k = np.arange(n)
    lo = np.maximum(k - h, path_start[path])
    hi = np.minimum(k + h + 1, ends[path])
    return c[hi] - c[lo]


def _empty_segments() -> _Segments:
    z = np.zeros(0)
    z2 = np.zeros((0, 2))
    z3 = np.zeros((0, 3, 2))
    return _Segments(
        n=z,
        cx=z,
        cy=z,
        tx=z,
        ty=z,
        length=z,
        turn=z,
        polarity=np.zeros(0, np.int64),
        start=z2,
        end=z2,
        samples=z3,
        sample_grad=z3,
        moments=np.zeros((0, 15)),
    )


def _moment_sums(dx: np.ndarray, dy: np.ndarray, labels: np.ndarray, m: int) -> np.ndarray:
    """(m, 15) sums of dx^i dy^j (i + j <= 4) per label."""
    px = [np.ones_like(dx), dx, dx * dx]
    px += [px[2] * dx, px[2] * px[2]]
    py = [np.ones_like(dy), dy, dy * dy]
    py += [py[2] * dy, py[2] * py[2]]
    out = np.empty((m, len(_EXP)))
    for k, (i, j) in enumerate(_EXP):
        out[:, k] = np.bincount(labels, px[i] * py[j], minlength=m)
    return out


def _translate_moments(M: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Moments about an origin o -> moments about o - (dx, dy), i.e. of points shifted by
    (+dx, +dy): sum (x + dx)^i (y + dy)^j, binomially. M (K, 15), dx, dy (K,)."""
    pdx = [np.ones_like(dx), dx, dx * dx, dx**3, dx**4]
    pdy = [np.ones_like(dy), dy, dy * dy, dy**3, dy**4]
    out = np.zeros_like(M)
    for t, (i, j) in enumerate(_EXP):
        for k in range(i + 1):
            for l in range(j + 1):
                c = math.comb(i, k) * math.comb(j, l)
                out[:, t] += c * pdx[i - k] * pdy[j - l] * M[:, _EXP_INDEX[(k, l)]]
    return out


def _scale_moments(M: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Moments of points divided by ``scale`` (K,)."""
    order = np.array([i + j for i, j in _EXP])
    return M / scale[:, None] ** order[None, :]


# ---------------------------------------------------------------------------------------------
# 3. Grouping
# ---------------------------------------------------------------------------------------------


@dataclass
class _Groups:
    """Ordered chains of arc-support segments, (G,) arrays unless noted."""

    order: np.ndarray  # (M,) segment indices, grouped, in chain order
    offset: np.ndarray  # (G + 1,) group g owns order[offset[g]:offset[g + 1]]
    polarity: np.ndarray
    npix: np.ndarray
    length: np.ndarray  # summed segment lengths [px]
    coverage: np.ndarray  # turn of the direction along the group [rad]
    cx: np.ndarray  # centroid [px]
    cy: np.ndarray
    moments: np.ndarray  # (G, 15) about the centroid
    first: np.ndarray  # first, middle and last segment
    middle: np.ndarray
    last: np.ndarray

    @property
    def g(self) -> int:
        return int(self.npix.size)


def _group_segments(S: _Segments, cfg: EllipseDetectorConfig) -> _Groups:
    """Link segments end-to-start into ordered groups that turn one way (and have one
    polarity, unless `mixed_polarity`)."""
    m = S.m
    alpha = np.arctan2(S.ty, S.tx)
    succ = np.full(m, -1, dtype=np.intp)
    pred = np.full(m, -1, dtype=np.intp)
    turn_in = np.zeros(m)  # turn from the predecessor [rad], in the group's sense
    if m > 1:
        ends = cKDTree(S.end)
        starts = cKDTree(S.start)
        pairs = ends.sparse_distance_matrix(starts, cfg.link_gap_px, output_type="ndarray")
        i = pairs["i"].astype(np.intp)
        j = pairs["j"].astype(np.intp)
        gap = pairs["v"]
        ok = i != j
        if not cfg.mixed_polarity:
            ok &= S.polarity[i] == S.polarity[j]
        i, j, gap = i[ok], j[ok], gap[ok]
        # Along d an arc of a convex curve turns clockwise: the turn in that sense is -turn.
        tau = -_wrap(alpha[j] - alpha[i])
        txi, tyi = S.tx[i], S.ty[i]
        ahead_start = (S.start[j, 0] - S.end[i, 0]) * txi + (S.start[j, 1] - S.end[i, 1]) * tyi
        ahead_end = (S.end[j, 0] - S.end[i, 0]) * txi + (S.end[j, 1] - S.end[i, 1]) * tyi
        # Curvature continuity: on a smooth curve the turn between two segments is about the
        # sum of their half spans (|turn| each) plus what a gap skips; a polygon corner between
        # two nearly straight sides turns much more.
        own = np.abs(S.turn[i]) + np.abs(S.turn[j])
        gap_turn = gap * own / np.maximum(S.length[i] + S.length[j], 1.0)
        ok = (
            (tau >= -math.radians(cfg.min_arc_turn_deg))
            & (tau <= math.radians(cfg.link_max_turn_deg))
            & (tau <= cfg.link_turn_ratio * (own + gap_turn) + math.radians(cfg.min_arc_turn_deg))
            & (ahead_start >= -2.0)
            & (ahead_end > 0)
        )
        i, j, gap, tau = i[ok], j[ok], gap[ok], tau[ok]
        if i.size:
            # Mutually best links (smallest gap), so every segment has <= 1 successor and
            # <= 1 predecessor.
            o = np.argsort(gap, kind="stable")
            i, j, tau = i[o], j[o], tau[o]
            best_j = np.full(m, -1, dtype=np.intp)
            best_i = np.full(m, -1, dtype=np.intp)
            best_j[i[::-1]] = j[::-1]  # the last write (= first in sorted order) wins
            best_i[j[::-1]] = i[::-1]
            mutual = (best_j[i] == j) & (best_i[j] == i)
            i, j, tau = i[mutual], j[mutual], tau[mutual]
            succ[i] = j
            pred[j] = i
            turn_in[j] = tau
    has = succ >= 0
    _, gid = _components(np.flatnonzero(has), succ[has], m)
    ng = int(gid.max()) + 1 if m else 0
    # Break cycles (a closed ellipse) at their lowest-index segment.
    has_head = np.zeros(ng, dtype=bool)
    has_head[gid[pred < 0]] = True
    if not has_head.all():
        lowest = np.full(ng, m, dtype=np.intp)
        np.minimum.at(lowest, gid, np.arange(m))
        heads = lowest[~has_head]
        succ[pred[heads]] = -1
        pred[heads] = -1
        turn_in[heads] = 0.0
    # Rank along each chain by pointer jumping (Wyllie's list ranking).
    rank = (pred >= 0).astype(np.int64)
    nxt = pred.copy()
    while True:
        live = np.flatnonzero(nxt >= 0)
        if live.size == 0:
            break
        new_rank = rank.copy()
        new_rank[live] += rank[nxt[live]]
        new_nxt = nxt.copy()
        new_nxt[live] = nxt[nxt[live]]
        rank, nxt = new_rank, new_nxt
    order = np.lexsort((rank, gid))
    size = np.bincount(gid, minlength=ng)
    offset = np.concatenate([[0], np.cumsum(size)])
    first = order[offset[:-1]]
    last = order[offset[1:] - 1]
    middle = order[offset[:-1] + size // 2]
    npix = np.bincount(gid, S.n, minlength=ng)
    length = np.bincount(gid, S.length, minlength=ng)
    cx = np.bincount(gid, S.n * S.cx, minlength=ng) / npix
    cy = np.bincount(gid, S.n * S.cy, minlength=ng) / npix
    # Total turn: half of the first and last segments' spans plus the turns between them.
    coverage = (
        np.bincount(gid, np.maximum(turn_in, 0.0), minlength=ng) + S.turn[first] + S.turn[last]
    )
    # A group's polarity is its segments' when they all agree, else 0 (mixed).
    pol_sum = np.bincount(gid, S.polarity, minlength=ng)
    polarity = np.where(np.abs(pol_sum) == size, np.sign(pol_sum), 0).astype(np.int64)
    shifted = _translate_moments(S.moments, S.cx - cx[gid], S.cy - cy[gid])
    moments = np.stack([np.bincount(gid, shifted[:, k], minlength=ng) for k in range(15)], 1)
    return _Groups(
        order=order,
        offset=offset,
        polarity=polarity,
        npix=npix,
        length=length,
        coverage=coverage,
        cx=cx,
        cy=cy,
        moments=moments,
        first=first,
        middle=middle,
        last=last,
    )


# ---------------------------------------------------------------------------------------------
# 4. Initial ellipses: salient groups and pairs of groups
# ---------------------------------------------------------------------------------------------


def _initial_ellipses(
    S: _Segments, G: _Groups, cfg: EllipseDetectorConfig, max_a: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial ellipses (K, 5) ``[cx, cy, a, b, theta]``, their weights (pixels used) and
    whether each comes from a single salient group (K,) bool."""
    tol = cfg.pair_tolerance_px
    # Salient single groups.
    single = np.flatnonzero(
        (G.coverage >= math.radians(cfg.salient_coverage_deg)) & (G.npix >= cfg.min_group_px)
    )
    # Pairs of groups of one polarity.
    pool = np.flatnonzero(G.npix >= cfg.min_group_px)
    if pool.size > cfg.max_pair_groups:
        pool = pool[np.argsort(-G.npix[pool], kind="stable")[: cfg.max_pair_groups]]
    a_idx, b_idx = np.triu_indices(pool.size, k=1)
    g1, g2 = pool[a_idx], pool[b_idx]
    # No farther apart than an ellipse through both allows (and of one polarity unless
    # `mixed_polarity`): two points of
    # an ellipse are at most 2a apart, and a <= the largest radius of curvature a^2 / b,
    # estimated from each group's length and turn (generously: short arcs turn noisily).
    radius = G.length / np.maximum(G.coverage, 1e-3)
    dist = np.hypot(G.cx[g1] - G.cx[g2], G.cy[g1] - G.cy[g2])
    ok = dist <= 3.0 * np.maximum(radius[g1], radius[g2]) + 2 * tol
    if not cfg.mixed_polarity:
        ok &= G.polarity[g1] == G.polarity[g2]
    g1, g2 = g1[ok], g2[ok]
    if g1.size:
        ok = _region_limitation(S, G, g1, g2, tol) & _region_limitation(S, G, g2, g1, tol)
        g1, g2 = g1[ok], g2[ok]
    # Fit all hypotheses at once from moment sums.
    h1 = np.concatenate([single, g1])
    h2 = np.concatenate([np.full(single.size, -1), g2])
    if h1.size == 0:
        return np.zeros((0, 5)), np.zeros(0), np.zeros(0, dtype=bool)
    w1 = G.npix[h1]
    w2 = np.where(h2 >= 0, G.npix[np.maximum(h2, 0)], 0.0)
    ox = (w1 * G.cx[h1] + w2 * G.cx[np.maximum(h2, 0)]) / (w1 + w2)
    oy = (w1 * G.cy[h1] + w2 * G.cy[np.maximum(h2, 0)]) / (w1 + w2)
    M = _translate_moments(G.moments[h1], G.cx[h1] - ox, G.cy[h1] - oy)
    pair = h2 >= 0
    M[pair] += _translate_moments(
        G.moments[h2[pair]], G.cx[h2[pair]] - ox[pair], G.cy[h2[pair]] - oy[pair]
    )
    spread = np.sqrt(
        np.maximum((M[:, _EXP_INDEX[(2, 0)]] + M[:, _EXP_INDEX[(0, 2)]]) / M[:, 0], 1e-12)
    )
    params, valid = _fit_moments(_scale_moments(M, spread))
    params[:, 0] = params[:, 0] * spread + ox
    params[:, 1] = params[:, 1] * spread + oy
    params[:, 2:4] *= spread[:, None]
    valid &= _plausible(params, cfg, max_a)
    h1, h2, params, w = h1[valid], h2[valid], params[valid], (w1 + w2)[valid]
    if h1.size == 0:
        return np.zeros((0, 5)), np.zeros(0), np.zeros(0, dtype=bool)
    good = _validate_hypotheses(S, G, h1, h2, params, cfg)
    return params[good], w[good], (h2 < 0)[good]


def _region_limitation(
    S: _Segments, G: _Groups, ga: np.ndarray, gb: np.ndarray, tol: float
) -> np.ndarray:
    """True where the start, middle and end points of groups ``gb`` lie on the inner side of
    the tangent lines of the first, middle and last segments of groups ``ga`` (an ellipse
    lies inside all its tangents)."""
    ok = np.ones(ga.size, dtype=bool)
    pts = [S.start[G.first[gb]], S.samples[G.middle[gb], 1], S.end[G.last[gb]]]
    for seg in (G.first[ga], G.middle[ga], G.last[ga]):
        nx, ny = S.ty[seg], -S.tx[seg]  # inner normal: d rotated by -90 deg
        for q in pts:
            ok &= (q[:, 0] - S.cx[seg]) * nx + (q[:, 1] - S.cy[seg]) * ny >= -tol
    return ok


def _plausible(params: np.ndarray, cfg: EllipseDetectorConfig, max_a: float) -> np.ndarray:
    a, b = params[:, 2], params[:, 3]
    return (
        np.all(np.isfinite(params), axis=1)
        & (b >= cfg.min_semi_minor_px)
        & (a <= max_a)
        & (b >= cfg.min_axis_ratio * a)
    )


def _validate_hypotheses(
    S: _Segments,
    G: _Groups,
    h1: np.ndarray,
    h2: np.ndarray,
    params: np.ndarray,
    cfg: EllipseDetectorConfig,
) -> np.ndarray:
    """Lu et al.'s check of an initial ellipse: the segments it was fitted to must lie on it
    with gradients along its normal. Per group, the pixels of segments with >= 2 of 3 sample
    points within `pair_tolerance_px` and `normal_tolerance_deg` must reach
    `pair_min_fraction`."""
    K = h1.size
    hyp_groups = [h1, h2]
    ok = np.ones(K, dtype=bool)
    cos_tol = math.cos(math.radians(cfg.normal_tolerance_deg))
    for side in (0, 1):
        g = hyp_groups[side]
        has = np.flatnonzero(g >= 0)
        if has.size == 0:
            continue
        gg = g[has]
        nseg = G.offset[gg + 1] - G.offset[gg]
        hyp = np.repeat(has, nseg)
        pos = np.repeat(G.offset[gg] - np.concatenate([[0], np.cumsum(nseg)[:-1]]), nseg)
        seg = G.order[pos + np.arange(hyp.size)]
        P = params[hyp]
        pol = S.polarity[seg]
        passed = np.zeros(seg.size, dtype=np.int64)
        for k in range(3):
            d, cosn, _ = _ellipse_eval(P, S.samples[seg, k, 0], S.samples[seg, k, 1])
            gxn = S.sample_grad[seg, k, 0] * cosn[0] + S.sample_grad[seg, k, 1] * cosn[1]
            # Bright inside (+1): the gradient points inwards, against the outward normal.
            passed += (np.abs(d) <= cfg.pair_tolerance_px) & (-pol * gxn >= cos_tol)
        good_pix = np.bincount(hyp, S.n[seg] * (passed >= 2), minlength=K)
        all_pix = np.bincount(hyp, S.n[seg], minlength=K)
        ok[has] &= good_pix[has] >= cfg.pair_min_fraction * all_pix[has]
    return ok


def _ellipse_eval(
    P: np.ndarray, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Per point: first-order (Sampson) signed distance to the ellipse ``P[k]`` (K, 5)
    [px, > 0 outside], the outward unit normal (nx, ny), and the eccentric anomaly [rad]."""
    c, s = np.cos(P[:, 4]), np.sin(P[:, 4])
    dx, dy = x - P[:, 0], y - P[:, 1]
    u = c * dx + s * dy
    v = -s * dx + c * dy
    ia2, ib2 = 1.0 / P[:, 2] ** 2, 1.0 / P[:, 3] ** 2
    f = u * u * ia2 + v * v * ib2 - 1.0
    nu, nv = 2.0 * u * ia2, 2.0 * v * ib2
    gn = np.maximum(_norm(nu, nv), 1e-12)
    d = f / gn
    nx = (c * nu - s * nv) / gn
    ny = (s * nu + c * nv) / gn
    t = np.arctan2(v / P[:, 3], u / P[:, 2])
    return d, (nx, ny), t


def _fit_moments(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched direct least-squares ellipse fit (Fitzgibbon et al. 1999 in the numerically
    stable form of Halir & Flusser 1998) from moment sums (K, 15) of well-scaled points.

    Returns:
        (K, 5) ``[cx, cy, a, b, theta]`` (NaN where invalid) and a (K,) validity mask.
    """
    S = M[:, _S_INDEX]
    S1, S2, S3 = S[:, :3, :3], S[:, :3, 3:], S[:, 3:, 3:]
    det3 = np.linalg.det(S3)
    scale3 = np.maximum(np.abs(S3).max(axis=(1, 2)), 1e-300) ** 3
    valid = np.isfinite(det3) & (det3 > 1e-10 * scale3)
    S3 = np.where(valid[:, None, None], S3, np.eye(3))
    S2 = np.where(valid[:, None, None], S2, 0.0)
    S1 = np.where(valid[:, None, None], S1, np.eye(3))
    T = -np.linalg.solve(S3, np.swapaxes(S2, 1, 2))
    Mr = S1 + S2 @ T
    Mp = np.stack([Mr[:, 2] / 2, -Mr[:, 1], Mr[:, 0] / 2], axis=1)
    ok = np.all(np.isfinite(Mp), axis=(1, 2))
    valid &= ok
    Mp = np.where(ok[:, None, None], Mp, np.eye(3))
    a1, found = _positive_eigenvector(Mp)
    # Fall back to a general eigen-solver where the closed form failed (near-repeated roots).
    bad = np.flatnonzero(~found & valid)
    if bad.size:
        w, V = np.linalg.eig(Mp[bad])
        V = V.real
        cond = 4 * V[:, 0, :] * V[:, 2, :] - V[:, 1, :] ** 2
        score = np.where(cond > 0, np.abs(w.real), np.inf)
        pick = np.argmin(score, axis=1)
        a1[bad] = V[np.arange(bad.size), :, pick]
        found[bad] = np.isfinite(score[np.arange(bad.size), pick])
    valid &= found
    a2 = np.einsum("kij,kj->ki", T, a1)
    params, ok = _conic_to_params(a1[:, 0], a1[:, 1], a1[:, 2], a2[:, 0], a2[:, 1], a2[:, 2])
    valid &= ok
    params[~valid] = np.nan
    return params, valid


def _positive_eigenvector(Mp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvector of the largest eigenvalue of each reduced Fitzgibbon matrix (K, 3, 3), in
    closed form.

    ``Mp = C1^-1 (S1 + S2 T)`` is similar to a symmetric matrix (the Schur complement of the
    scatter matrix is positive definite), so its eigenvalues are real; the ellipse
    (4 A C - B^2 > 0) belongs to the only positive one, the largest. The roots of the
    characteristic cubic come from the trigonometric formula, the eigenvector from the
    cross product of two rows of ``Mp - lambda I``. Returns (K, 3) vectors and a (K,) mask of
    those that are finite and satisfy the ellipse condition.
    """
    tr = Mp[:, 0, 0] + Mp[:, 1, 1] + Mp[:, 2, 2]
    minors = (
        Mp[:, 0, 0] * Mp[:, 1, 1]
        - Mp[:, 0, 1] * Mp[:, 1, 0]
        + Mp[:, 0, 0] * Mp[:, 2, 2]
        - Mp[:, 0, 2] * Mp[:, 2, 0]
        + Mp[:, 1, 1] * Mp[:, 2, 2]
        - Mp[:, 1, 2] * Mp[:, 2, 1]
    )
    det = np.linalg.det(Mp)
    # lambda = x + tr / 3 turns lambda^3 - tr lambda^2 + minors lambda - det into
    # x^3 + p x + q.
    p = minors - tr * tr / 3.0
    q = -2.0 * tr**3 / 27.0 + tr * minors / 3.0 - det
    with np.errstate(invalid="ignore", divide="ignore"):
        m = 2.0 * np.sqrt(np.maximum(-p / 3.0, 0.0))
        arg = np.clip(3.0 * q / (p * m), -1.0, 1.0)
        lam = tr / 3.0 + m * np.cos(np.arccos(arg) / 3.0)
    R = Mp - lam[:, None, None] * np.eye(3)
    cands = np.stack(
        [np.cross(R[:, 0], R[:, 1]), np.cross(R[:, 0], R[:, 2]), np.cross(R[:, 1], R[:, 2])],
        axis=1,
    )
    norms = np.linalg.norm(cands, axis=2)
    v = cands[np.arange(Mp.shape[0]), np.argmax(norms, axis=1)]
    v = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    ok = np.all(np.isfinite(v), axis=1) & (4 * v[:, 0] * v[:, 2] - v[:, 1] ** 2 > 0)
    ok &= norms.max(axis=1) > 1e-12 * np.maximum(np.abs(Mp).max(axis=(1, 2)) ** 2, 1e-300)
    return np.where(ok[:, None], v, 0.0), ok


def _conic_to_params(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, E: np.ndarray, F: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ellipse parameters (K, 5) of conics ``A x^2 + B xy + C y^2 + D x + E y + F = 0``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        den = 4 * A * C - B * B
        x0 = (B * E - 2 * C * D) / den
        y0 = (B * D - 2 * A * E) / den
        k = -(F + 0.5 * (D * x0 + E * y0))  # (p - c)^T M (p - c) = k
        sgn = np.where(k < 0, -1.0, 1.0)
        A, B, C, k = A * sgn, B * sgn, C * sgn, k * sgn
        half_tr = 0.5 * (A + C)
        r = np.hypot(0.5 * (A - C), 0.5 * B)
        l1, l2 = half_tr - r, half_tr + r  # l1 <= l2; the major axis goes with l1
        ok = (den > 0) & (l1 > 0) & (k > 0)
        a = np.sqrt(k / l1)
        b = np.sqrt(k / l2)
        theta = (0.5 * np.arctan2(B, A - C) + 0.5 * np.pi) % np.pi
    params = np.stack([x0, y0, a, b, theta], axis=1)
    ok &= np.all(np.isfinite(params), axis=1)
    return params, ok


# ---------------------------------------------------------------------------------------------
# 5. Clustering
# ---------------------------------------------------------------------------------------------


def _cluster(
    params: np.ndarray, weight: np.ndarray, salient: np.ndarray, cfg: EllipseDetectorConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cluster initial ellipses by mode seeking (quick shift) in parameter space.

    Each ellipse is embedded as ``[cx, cy, a, b, (a - b) cos 2 theta, (a - b) sin 2 theta]``
    [px]: every coordinate is roughly a displacement of the ellipse's boundary, and the
    orientation fades out for near-circles. Two ellipses are neighbours when their distance is
    below `cluster_center_px` + `cluster_rel` * (smaller b). The density of an ellipse is the
    summed weight of itself and its neighbours; each ellipse points to its densest neighbour
    and the roots of these trees are the modes. A mode is replaced by the weighted mean of
    itself and its neighbours (one mean-shift step).

    Returns:
        (C, 5) cluster ellipses, (C,) cluster weights (summed over the members) and (C,)
        whether a member came from a salient group, by decreasing weight.
    """
    K = params.shape[0]
    cx, cy, a, b, th = params.T
    e = a - b
    z = np.stack([cx, cy, a, b, e * np.cos(2 * th), e * np.sin(2 * th)], axis=1)
    tol_max = cfg.cluster_center_px + cfg.cluster_rel * float(b.max())
    pairs = cKDTree(z).query_pairs(tol_max, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d = np.linalg.norm(z[i] - z[j], axis=1)
    ok = d <= cfg.cluster_center_px + cfg.cluster_rel * np.minimum(b[i], b[j])
    I = np.concatenate([i[ok], j[ok]])
    J = np.concatenate([j[ok], i[ok]])
    dens = weight + np.bincount(I, weight[J], minlength=K)
    by_rank = np.argsort(-dens, kind="stable")
    rank = np.empty(K, dtype=np.int64)
    rank[by_rank] = np.arange(K)
    best = rank.copy()
    np.minimum.at(best, I, rank[J])
    root = by_rank[best]
    while True:
        nxt = root[root]
        if np.array_equal(nxt, root):
            break
        root = nxt
    modes = np.flatnonzero(root == np.arange(K))
    w_cluster = np.bincount(root, weight, minlength=K)[modes]
    s_cluster = np.bincount(root, salient, minlength=K)[modes] > 0
    # One mean-shift step at every mode: weighted mean over the mode and its neighbours.
    is_mode = np.zeros(K, dtype=bool)
    is_mode[modes] = True
    m = is_mode[I]
    Im, Jm = np.concatenate([modes, I[m]]), np.concatenate([modes, J[m]])
    wj = weight[Jm]
    sw = np.bincount(Im, wj, minlength=K)[modes]
    mean = np.stack(
        [np.bincount(Im, wj * params[Jm, k], minlength=K)[modes] / sw for k in range(4)], axis=1
    )
    s2 = np.bincount(Im, wj * np.sin(2 * th[Jm]), minlength=K)[modes]
    c2 = np.bincount(Im, wj * np.cos(2 * th[Jm]), minlength=K)[modes]
    ang = (0.5 * np.arctan2(s2, c2)) % np.pi
    out = np.concatenate([mean, ang[:, None]], axis=1)
    order = np.argsort(-w_cluster, kind="stable")
    return out[order], w_cluster[order], s_cluster[order]


# ---------------------------------------------------------------------------------------------
# 6. Verification and 7. refinement
# ---------------------------------------------------------------------------------------------

_CELL_SHIFT = 2
"""Edge pixels are bucketed in 4x4 px cells for the verification look-ups."""


@dataclass
class _EdgeIndex:
    """All edge pixels sorted by 4x4 cell, for gathering those near an ellipse."""

    x: np.ndarray
    y: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    ix: np.ndarray
    iy: np.ndarray
    cell_start: np.ndarray  # (ncells + 1,)
    ncx: int
    ncy: int
    shape: tuple[int, int]

    @staticmethod
    def build(E: _Edges) -> _EdgeIndex:
        H, W = E.shape
        ncx = (W >> _CELL_SHIFT) + 1
        ncy = (H >> _CELL_SHIFT) + 1
        cell = (E.iy >> _CELL_SHIFT) * ncx + (E.ix >> _CELL_SHIFT)
        o = np.argsort(cell, kind="stable")
        counts = np.bincount(cell, minlength=ncx * ncy)
        start = np.concatenate([[0], np.cumsum(counts)])
        return _EdgeIndex(
            E.x[o], E.y[o], E.gx[o], E.gy[o], E.ix[o], E.iy[o], start, ncx, ncy, (H, W)
        )


@dataclass
class _Found:
    ellipse: Ellipse
    support: float
    coverage: float
    polarity: int
    inliers: np.ndarray


@dataclass
class _Pass:
    """Result of one verification pass over K candidates."""

    support: np.ndarray  # (K,)
    coverage: np.ndarray
    plus: np.ndarray  # inliers with the gradient pointing inwards (brighter inside)
    minus: np.ndarray
    cand: np.ndarray  # (N,) candidate of each kept inlier
    pix: np.ndarray  # (N,) edge index of each kept inlier


_DETECTOR_VARIANCE_PX2 = 0.5
"""Smoothing variance of the edge detector besides the Gaussian pre-blur [px^2] (see
`_unbend`)."""

_REFINE_POINTS = 200
"""At most about this many inliers (evenly strided along the gather order) enter the
geometric refinement."""

_GROW_MIN_SUPPORT = 0.2
"""Growth is tried on candidates whose loose support is at least this (something to grow
from) and below `min_support` ..."""
_GROW_MAX_PX = 8.0
"""... with a band of at most +-this [px] ..."""
_GROW_MAX_CANDIDATES = 8
"""... on at most this many candidates (the best supported)."""

_ALWAYS_VERIFIED = 6
"""The clusters with the largest weight per pixel of perimeter skip the screen's threshold."""

_VERIFY_PERIMETER_BUDGET = 6.0
"""Candidates are verified in screen order until their summed perimeter reaches this many
times (image width + height)."""

_SCREEN_PER_CANDIDATE = 5
"""The screen looks at up to this many clusters per candidate it passes on."""

_ORIENTATION_CLASSES = 8
"""Edge orientations (mod 180 deg) are coded in 8 classes of 22.5 deg for the screen."""


def _screen(
    cands: np.ndarray,
    weight: np.ndarray,
    salient: np.ndarray,
    index: _EdgeIndex,
    cfg: EllipseDetectorConfig,
) -> np.ndarray:
    """Cheap first look at the clustered candidates; the `max_candidates` best go on to the
    exact verification.

    Clusters with a fit to a single salient group (a long smooth arc: strong evidence, but its
    fit may be off by more than the screen's 2 px elsewhere, see `grow_fraction`) and the
    `_ALWAYS_VERIFIED` clusters with the largest weight per pixel of perimeter go on whatever
    their score, up to half of `max_candidates`. Of the others, at most
    `_SCREEN_PER_CANDIDATE` * `max_candidates` are looked at, those with the largest weight
    per pixel of perimeter first. Each is sampled every ~3 px along its
    perimeter; a sample is supported when an edge pixel whose gradient orientation is within
    one class (22.5 deg) of the ellipse normal's class lies within +-2 px (a 5x5 dilation of
    an orientation bit-mask image). The score is the supported fraction; candidates scoring
    below 0.7 `min_support` are dropped, and the list is cut at a perimeter budget
    (`_VERIFY_PERIMETER_BUDGET`).
    """
    if cands.shape[0] == 0:
        return cands
    # Look first at the clusters whose initial fits explain most of their perimeter: the
    # ring's cluster collects many pairs of long arcs, clutter pairs of short arcs.
    a, b = cands[:, 2], cands[:, 3]
    order = np.argsort(-weight / (np.pi * (a + b)), kind="stable")
    strong = np.zeros(cands.shape[0], dtype=bool)
    strong[order[:_ALWAYS_VERIFIED]] = True
    strong |= salient
    first = np.concatenate([order[strong[order]], order[~strong[order]]])
    n_strong = min(int(strong.sum()), max(cfg.max_candidates // 2, 1))
    first = first[: n_strong + _SCREEN_PER_CANDIDATE * cfg.max_candidates]
    H, W = index.shape
    # The screen's cost is also proportional to the perimeter: a budget of
    # `_SCREEN_PER_CANDIDATE` times the verification's.
    perim = np.pi * (a[first] + b[first])
    budget = _SCREEN_PER_CANDIDATE * _VERIFY_PERIMETER_BUDGET * (H + W)
    first = first[: max(n_strong, int(np.searchsorted(np.cumsum(perim), budget, side="right")))]
    cands = cands[first]
    K = cands.shape[0]
    nc = _ORIENTATION_CLASSES
    cls = (np.floor((np.arctan2(index.gy, index.gx) % np.pi) / (np.pi / nc)).astype(np.int64)) % nc
    mask = np.zeros((H + 4, W + 4), dtype=np.uint8)
    mask[index.iy + 2, index.ix + 2] = (1 << cls).astype(np.uint8)
    # 5x5 OR-dilation, separably.
    hor = mask.copy()
    for o in (1, 2):
        hor[:, o:] |= mask[:, :-o]
        hor[:, :-o] |= mask[:, o:]
    dil = hor.copy()
    for o in (1, 2):
        dil[o:, :] |= hor[:-o, :]
        dil[:-o, :] |= hor[o:, :]
    a, b = cands[:, 2], cands[:, 3]
    ns = np.maximum(np.ceil(np.pi * (a + b) / 3.0).astype(np.int64), 8)
    kk = np.repeat(np.arange(K), ns)
    t = (np.arange(kk.size) - np.repeat(np.cumsum(ns) - ns, ns)) * (2 * np.pi / ns[kk])
    ck, sk = np.cos(cands[:, 4]), np.sin(cands[:, 4])
    c, s = ck[kk], sk[kk]
    ex, ey = a[kk] * np.cos(t), b[kk] * np.sin(t)
    px = np.rint(cands[kk, 0] + c * ex - s * ey).astype(np.int64) + 2
    py = np.rint(cands[kk, 1] + s * ex + c * ey).astype(np.int64) + 2
    # Normal direction mod pi: theta + atan2(a sin t, b cos t) = theta + atan2(a^2 ey, b^2 ex).
    phi = ((cands[kk, 4] + np.arctan2(a[kk] ** 2 * ey, b[kk] ** 2 * ex)) % np.pi) / (np.pi / nc)
    k0 = np.floor(phi).astype(np.int64) % nc
    want = (1 << k0) | (1 << ((k0 + 1) % nc)) | (1 << ((k0 - 1) % nc))
    inside = (px >= 0) & (px < W + 4) & (py >= 0) & (py < H + 4)
    hit = np.zeros(kk.size, dtype=bool)
    flat = py[inside] * (W + 4) + px[inside]
    hit[inside] = (np.take(dil.ravel(), flat) & want[inside]) != 0
    score = np.bincount(kk, hit, minlength=K) / ns
    rest = np.flatnonzero(score >= 0.7 * cfg.min_support)
    rest = rest[rest >= n_strong]
    rest = rest[np.argsort(-score[rest], kind="stable")]
    good = np.concatenate([np.arange(n_strong), rest])[: cfg.max_candidates]
    # Verification costs in proportion to the perimeter: stop at a budget of a few times the
    # image's size (room for six ring-sized ellipses), keeping at least the first candidate.
    perim = np.pi * (cands[good, 2] + cands[good, 3])
    budget = _VERIFY_PERIMETER_BUDGET * (H + W)
    good = good[: max(1, int(np.searchsorted(np.cumsum(perim), budget, side="right")))]
    return cands[good]


def _verify(
    cands: np.ndarray, index: _EdgeIndex, cfg: EllipseDetectorConfig, max_a: float
) -> list[_Found]:
    """Gather-and-fit passes, acceptance, duplicate suppression, refinement, final statistics."""
    P = cands.copy()
    gtol = cfg.gather_tolerance_px
    # Pass 1 (loose): collect inliers within `gather_tolerance_px`.
    r = _gather(P, index, gtol, cfg)
    # Growth: an initial ellipse fitted to one or two arcs can be several pixels off elsewhere
    # on its perimeter (the arcs' own sub-pixel deviations are extrapolated), so a candidate
    # short of support gathers within a tolerance proportional to its size, refits (one ICP
    # step), and keeps the result only if that raises its loose support. Only such
    # candidates: on a good one the wide band would pull in parallel edges nearby.
    tol0 = np.clip(cfg.grow_fraction * P[:, 2], gtol, _GROW_MAX_PX)
    grow = np.flatnonzero(
        (r.support < cfg.min_support) & (r.support >= _GROW_MIN_SUPPORT) & (tol0 > gtol)
    )
    grow = grow[np.argsort(-r.support[grow], kind="stable")[:_GROW_MAX_CANDIDATES]]
    if grow.size:
        Pg = P[grow]
        rg = _gather(Pg, index, tol0[grow], cfg)
        Pg = _refit(Pg, rg, index, rg.support >= 0.5 * cfg.min_support, tol0[grow])
        rg = _gather(Pg, index, gtol, cfg)
        better = rg.support > r.support[grow] + 0.05
        if better.any():
            P[grow[better]] = Pg[better]
            r = _splice(r, grow[better], _select(Pg, rg, better)[1])
    keep = r.support >= 0.7 * cfg.min_support
    P = _refit(P, r, index, keep, cfg.gather_tolerance_px)
    keep &= _plausible(P, cfg, max_a)
    P = P[keep]
    if P.shape[0] == 0:
        return []
    # Pass 2 (tight): the acceptance test; duplicates go before the refinement.
    r = _gather(P, index, cfg.inlier_tolerance_px, cfg)
    acc = (r.support >= cfg.min_support) & (r.coverage >= cfg.min_coverage)
    P, r = _select(P, r, acc)
    P, r = _suppress_duplicates(P, r, cfg)
    if P.shape[0] == 0:
        return []
    # Refinement on the tight inliers (geometric, or algebraic when refine_iterations is 0),
    # then the final statistics.
    if cfg.refine_iterations > 0:
        for k in range(P.shape[0]):
            sel = r.pix[r.cand == k]
            # An evenly strided subset bounds the cost on large ellipses; a few hundred points
            # pin the five parameters far below the edge noise. Sorted by position first, so
            # that the subset does not depend on the gather order (nor on a ROI).
            if sel.size > _REFINE_POINTS:
                sel = sel[np.lexsort((index.x[sel], index.y[sel]))]
                sel = sel[:: sel.size // _REFINE_POINTS]
            pts = np.stack([index.x[sel], index.y[sel]], axis=1)
            pts = _unbend(pts, P[k], cfg.blur_sigma_px)
            try:
                e, _, _ = refine_ellipse(
                    pts, Ellipse.from_params(P[k]), iterations=cfg.refine_iterations
                )
            except (ConicError, np.linalg.LinAlgError):
                continue
            new = e.params
            if np.all(np.isfinite(new)) and _close(new, P[k], 2 * cfg.inlier_tolerance_px):
                P[k] = new
    else:
        P = _refit(P, r, index, np.ones(P.shape[0], dtype=bool), cfg.inlier_tolerance_px)
    P = P[_plausible(P, cfg, max_a)]
    r = _gather(P, index, cfg.inlier_tolerance_px, cfg)
    acc = (r.support >= cfg.min_support) & (r.coverage >= cfg.min_coverage)
    P, r = _select(P, r, acc)
    P, r = _suppress_duplicates(P, r, cfg)
    found = []
    for k in np.argsort(-r.support, kind="stable"):
        try:
            e = Ellipse.from_params(P[k])
        except ConicError:
            continue
        sel = r.pix[r.cand == k]
        plus, minus = float(r.plus[k]), float(r.minus[k])
        tot = max(plus + minus, 1.0)
        if minus <= cfg.mixed_polarity_fraction * tot:
            pol = 1
        elif plus <= cfg.mixed_polarity_fraction * tot:
            pol = -1
        else:
            pol = 0
        found.append(
            _Found(
                ellipse=e,
                support=float(r.support[k]),
                coverage=float(r.coverage[k]),
                polarity=pol,
                inliers=np.stack([index.x[sel], index.y[sel]], axis=1),
            )
        )
    return found


def _unbend(pts: np.ndarray, p: np.ndarray, blur_sigma_px: float) -> np.ndarray:
    """Undo the smoothing bias of edge points on a curved edge.

    Smoothing an edge of curvature kappa with an isotropic kernel of variance s^2 moves the
    gradient-magnitude maximum towards the centre of curvature by s^2 kappa / 2 (to first
    order). Each point is moved back along the normal of the ellipse ``p`` (already within
    ~0.1 px) by that amount, with s^2 = blur_sigma^2 + `_DETECTOR_VARIANCE_PX2` (Sobel's
    smoothing, the pixel's area, the sub-pixel interpolation; calibrated on anti-aliased
    synthetic ellipses). Matters for small or eccentric ellipses: 0.05 px at a 20 px radius
    of curvature.
    """
    cx, cy, a, b, th = p
    c, s = math.cos(th), math.sin(th)
    dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
    t = np.arctan2((c * dy - s * dx) / b, (c * dx + s * dy) / a)
    ct, st = np.cos(t), np.sin(t)
    speed2 = (a * st) ** 2 + (b * ct) ** 2
    kappa = a * b / speed2**1.5
    nu, nv = b * ct, a * st  # outward normal in the ellipse frame (unnormalised)
    nn = np.sqrt(nu * nu + nv * nv)
    shift = 0.5 * (blur_sigma_px**2 + _DETECTOR_VARIANCE_PX2) * kappa / nn
    return np.stack(
        [pts[:, 0] + shift * (c * nu - s * nv), pts[:, 1] + shift * (s * nu + c * nv)], 1
    )


def _splice(r: _Pass, rows: np.ndarray, sub: _Pass) -> _Pass:
    """``r`` with the candidates ``rows`` replaced by the (equally many) candidates of
    ``sub``, in order."""
    drop = np.zeros(r.support.size, dtype=bool)
    drop[rows] = True
    m = ~drop[r.cand]
    support, coverage = r.support.copy(), r.coverage.copy()
    plus, minus = r.plus.copy(), r.minus.copy()
    support[rows], coverage[rows] = sub.support, sub.coverage
    plus[rows], minus[rows] = sub.plus, sub.minus
    return _Pass(
        support=support,
        coverage=coverage,
        plus=plus,
        minus=minus,
        cand=np.concatenate([r.cand[m], rows[sub.cand]]),
        pix=np.concatenate([r.pix[m], sub.pix]),
    )


def _close(p: np.ndarray, q: np.ndarray, tol: float) -> bool:
    """Two ellipses agree in centre and axes within ``tol`` px (+ 10 % of the minor axis)."""
    t = tol + 0.1 * min(p[3], q[3])
    return bool(
        math.hypot(p[0] - q[0], p[1] - q[1]) <= t
        and abs(p[2] - q[2]) <= t
        and abs(p[3] - q[3]) <= t
    )


def _select(P: np.ndarray, r: _Pass, keep: np.ndarray) -> tuple[np.ndarray, _Pass]:
    """Keep candidates ``keep`` (bool (K,)) and renumber the inlier lists."""
    new_id = np.cumsum(keep) - 1
    m = keep[r.cand]
    return P[keep], _Pass(
        support=r.support[keep],
        coverage=r.coverage[keep],
        plus=r.plus[keep],
        minus=r.minus[keep],
        cand=new_id[r.cand[m]],
        pix=r.pix[m],
    )


def _suppress_duplicates(
    P: np.ndarray, r: _Pass, cfg: EllipseDetectorConfig
) -> tuple[np.ndarray, _Pass]:
    """Drop candidates that repeat a better supported one (parameters or shared inliers)."""
    K = P.shape[0]
    if K <= 1:
        return P, r
    order = np.argsort(-r.support, kind="stable")
    claimed = np.zeros(int(r.pix.max()) + 1 if r.pix.size else 1, dtype=bool)
    by_cand = np.argsort(r.cand, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(r.cand, minlength=K))])
    keep = np.zeros(K, dtype=bool)
    kept: list[int] = []
    for k in order:
        pk = P[k]
        dup = False
        for j in kept:
            pj = P[j]
            if (
                math.hypot(pk[0] - pj[0], pk[1] - pj[1]) <= cfg.duplicate_center_px
                and abs(pk[2] - pj[2]) <= cfg.duplicate_axis_px
                and abs(pk[3] - pj[3]) <= cfg.duplicate_axis_px
            ):
                dup = True
                break
        pix = r.pix[by_cand[starts[k] : starts[k + 1]]]
        if not dup and pix.size and claimed[pix].mean() > cfg.max_shared_inliers:
            dup = True
        if not dup:
            keep[k] = True
            kept.append(int(k))
            claimed[pix] = True
    return _select(P, r, keep)


def _refit(
    P: np.ndarray, r: _Pass, index: _EdgeIndex, keep: np.ndarray, tol: float | np.ndarray
) -> np.ndarray:
    """Algebraic refit of every kept candidate to its inliers (batched over moment sums);
    a refit that jumps away from the candidate is ignored."""
    K = P.shape[0]
    P = P.copy()
    cnt = np.bincount(r.cand, minlength=K)
    fit = keep & (cnt >= 6)
    if not fit.any():
        return P
    sel = fit[r.cand]
    k = r.cand[sel]
    s = P[:, 2]
    dx = (index.x[r.pix[sel]] - P[k, 0]) / s[k]
    dy = (index.y[r.pix[sel]] - P[k, 1]) / s[k]
    M = _moment_sums(dx, dy, k, K)[fit]
    new, ok = _fit_moments(M)
    idx = np.flatnonzero(fit)
    new[:, 0] = new[:, 0] * s[idx] + P[idx, 0]
    new[:, 1] = new[:, 1] * s[idx] + P[idx, 1]
    new[:, 2:4] *= s[idx, None]
    tolk = np.broadcast_to(np.asarray(tol, dtype=float), (K,))
    for n, kk in enumerate(idx):
        if ok[n] and _close(new[n], P[kk], 2 * float(tolk[kk])):
            P[kk] = new[n]
    return P


def _gather(
    P: np.ndarray, index: _EdgeIndex, tol: float | np.ndarray, cfg: EllipseDetectorConfig
) -> _Pass:
    """Edge support of K candidate ellipses, all at once.

    Edge pixels in the 4x4 cells crossed by a band of +-(tol + 0.5) px around each ellipse are
    tested for distance (<= tol, a scalar or one per candidate) and gradient direction
    (within `normal_tolerance_deg` of the normal, either sign). Inliers are binned along the
    perimeter (bins of ~`support_bin_px` of arc length); runs of supported bins shorter than
    `min_run_px` are discarded.
    """
    K = P.shape[0]
    if K == 0:
        z = np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return _Pass(z, z, z, z, zi, zi)
    a, b = P[:, 2], P[:, 3]
    h = ((a - b) / (a + b)) ** 2
    perim = np.pi * (a + b) * (1 + 3 * h / (10 + np.sqrt(4 - 3 * h)))
    # Cells: sample every ellipse at <= 2 px spacing, on it and +-(tol + 0.5) px off it.
    ns = np.maximum(np.ceil(np.pi * a).astype(np.int64), 8)
    kk = np.repeat(np.arange(K), ns)
    t = (np.arange(kk.size) - np.repeat(np.cumsum(ns) - ns, ns)) * (2 * np.pi / ns[kk])
    c, s = np.cos(P[:, 4]), np.sin(P[:, 4])
    ex, ey = a[kk] * np.cos(t), b[kk] * np.sin(t)
    px = P[kk, 0] + c[kk] * ex - s[kk] * ey
    py = P[kk, 1] + s[kk] * ex + c[kk] * ey
    nx, ny = b[kk] * np.cos(t), a[kk] * np.sin(t)
    nn = _norm(nx, ny)
    nx, ny = (c[kk] * nx - s[kk] * ny) / nn, (s[kk] * nx + c[kk] * ny) / nn
    tolk = np.broadcast_to(np.asarray(tol, dtype=float), (K,))
    # Offsets across the band at <= 3 px steps, so that no 4x4 cell in it is skipped.
    nstep = math.ceil(float(tolk.max() + 0.5) / 3.0)
    off = (tolk[kk] + 0.5) / nstep
    ncell = index.ncx * index.ncy
    cells = []
    for o in range(-nstep, nstep + 1):
        cx = np.floor(px + o * off * nx + 0.5).astype(np.int64) >> _CELL_SHIFT
        cy = np.floor(py + o * off * ny + 0.5).astype(np.int64) >> _CELL_SHIFT
        inside = (cx >= 0) & (cx < index.ncx) & (cy >= 0) & (cy < index.ncy)
        cells.append((kk * ncell + cy * index.ncx + cx)[inside])
    key = _sorted_unique(np.concatenate(cells))
    ck, cc = key // ncell, key % ncell
    lo, hi = index.cell_start[cc], index.cell_start[cc + 1]
    ln = hi - lo
    cand = np.repeat(ck, ln)
    pix = np.repeat(lo - (np.cumsum(ln) - ln), ln) + np.arange(int(ln.sum()))
    # Distance (first order) and direction tests, in each candidate's frame.
    dx = index.x[pix] - P[cand, 0]
    dy = index.y[pix] - P[cand, 1]
    cc_, ss_ = c[cand], s[cand]
    u = cc_ * dx + ss_ * dy
    v = cc_ * dy - ss_ * dx
    ia2, ib2 = 1.0 / a[cand] ** 2, 1.0 / b[cand] ** 2
    nu, nv = u * ia2, v * ib2
    gn = np.maximum(_norm(nu, nv), 1e-12)
    d = (u * nu + v * nv - 1.0) / (2.0 * gn)
    # Gradient against the outward normal, rotated into the ellipse frame.
    gu = cc_ * index.gx[pix] + ss_ * index.gy[pix]
    gv = cc_ * index.gy[pix] - ss_ * index.gx[pix]
    cosn = (gu * nu + gv * nv) / gn
    inl = (np.abs(d) <= tolk[cand]) & (
        np.abs(cosn) >= math.cos(math.radians(cfg.normal_tolerance_deg))
    )
    cand, pix, inward = cand[inl], pix[inl], cosn[inl] < 0
    tt = np.arctan2(v[inl] / b[cand], u[inl] / a[cand])
    # Perimeter position: eccentric anomaly -> arc-length fraction via a 64-step table.
    nt = 64
    grid = np.linspace(0.0, 2 * np.pi, nt + 1)
    speed = np.sqrt((a[:, None] * np.sin(grid)) ** 2 + (b[:, None] * np.cos(grid)) ** 2)
    cum = np.concatenate(
        [np.zeros((K, 1)), np.cumsum(0.5 * (speed[:, 1:] + speed[:, :-1]), axis=1)], axis=1
    )
    cum /= cum[:, -1:]
    tf = (tt % (2 * np.pi)) * (nt / (2 * np.pi))
    j = np.minimum(tf.astype(np.int64), nt - 1)
    frac = cum[cand, j] + (tf - j) * (cum[cand, j + 1] - cum[cand, j])
    nb = np.maximum(np.round(perim / cfg.support_bin_px).astype(np.int64), 8)
    offset = np.concatenate([[0], np.cumsum(nb)])
    total = int(offset[-1])
    local = np.minimum((frac * nb[cand]).astype(np.int64), nb[cand] - 1)
    flat = offset[cand] + local
    occ = np.bincount(flat, minlength=total) > 0
    kept_bins = _long_runs(occ, offset, nb, cfg.min_run_px / cfg.support_bin_px)
    sel = kept_bins[flat]
    cand, pix, inward, flat = cand[sel], pix[sel], inward[sel], flat[sel]
    owner = np.repeat(np.arange(K), nb)
    support = np.bincount(owner, kept_bins, minlength=K) / nb
    # Coverage: sectors of equal perimeter length holding a supported bin.
    # (Fewer sectors than bins on small ellipses, so that every sector can be covered.)
    nsec = cfg.coverage_sectors
    nsk = np.minimum(nb, nsec)
    kb = np.flatnonzero(kept_bins)
    ok_ = owner[kb]
    sector = ((kb - offset[ok_]) * nsk[ok_]) // nb[ok_]
    covered = _sorted_unique(ok_ * nsec + sector)
    coverage = np.bincount(covered // nsec, minlength=K) / nsk
    plus = np.bincount(cand, inward, minlength=K)
    minus = np.bincount(cand, ~inward, minlength=K)
    return _Pass(support, coverage, plus, minus, cand, pix)


def _sorted_unique(v: np.ndarray) -> np.ndarray:
    """Sorted distinct values (np.unique's hash path is slower for these int arrays)."""
    v = np.sort(v)
    return v[np.concatenate([[True], v[1:] != v[:-1]])] if v.size else v


def _long_runs(occ: np.ndarray, offset: np.ndarray, nb: np.ndarray, min_run: float) -> np.ndarray:
    """Occupied bins that belong to circular runs of at least ``min_run`` bins; candidate k
    owns bins ``offset[k]:offset[k + 1]``."""
    K = nb.size
    owner = np.repeat(np.arange(K), nb)
    local = np.arange(occ.size) - offset[owner]
    # Rotate every candidate's bins to start at an empty bin, so no run wraps around.
    big = np.where(occ, np.iinfo(np.int64).max, local)
    first_empty = np.minimum.reduceat(big, offset[:-1]) if K else np.zeros(0, np.int64)
    full = first_empty == np.iinfo(np.int64).max
    rot = np.where(full, 0, first_empty)
    src = offset[owner] + (local + rot[owner]) % nb[owner]
    o = occ[src]
    prev = np.concatenate([[False], o[:-1]])
    prev[offset[:-1]] = False
    start = o & ~prev
    rid = np.cumsum(start) - 1
    nruns = int(rid[-1]) + 1 if occ.size else 0
    rlen = np.bincount(rid[o], minlength=nruns)
    long_ = np.zeros(occ.size, dtype=bool)
    long_[o] = rlen[rid[o]] >= min_run
    keep = np.zeros(occ.size, dtype=bool)
    keep[src] = long_ | full[owner]
    return keep
