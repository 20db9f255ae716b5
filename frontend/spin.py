"""Spin rate of a far, fast-spinning target from one camera (seed 001).

At medium and long range the target's outline is stable while its details are not. Per frame
(timings of each stage go into ``FrameMeasurements.timings_ms``):

1. ``locate``: the target's rough box from block averages of the raw image (`locate_target`;
   a far target covers a small part of the image, and the next stages only look there).
2. ``undistort``: grey, [0, 1], lens distortion removed, in that box (`Undistorter.crop`).
3. ``region``: the target's silhouette as maximally stable extremal regions (MSER, OpenCV):
   the largest bright region away from the image border, joined by the other bright regions
   next to it (at long range the thin brackets between bus and wings may not connect them);
   its second-moment ellipse; ``theta'`` is the angle of the ellipse's major axis from the
   image x axis (x right, y down, so positive angles turn toward +y), in ``[0, pi)``. The
   elongation ``1 - b/a`` is the frame's quality: a round region has no usable angle.

Over a sliding buffer of the last ``n`` frames (seed 001: ``n = 19``):

4. ``theta'`` has period ``pi`` while the spin angle has period ``2 pi``. The doubled angle
   ``(cos 2 theta', sin 2 theta')`` is continuous (no wrap at ``pi``); its spectrum (a
   periodogram at the sample times) peaks at twice the spin rate.
5. Starting from that peak, the paper's two-sine model (eq. 9)
   ``y = a1 sin(b1 t + c1) + a2 sin(b2 t + c2)`` is fitted by least squares to both components
   with shared ``b1`` (long period: drift from lighting and geometry) and ``b2`` (short period:
   the spin), separate amplitudes and phases; the spin rate is ``omega = b2 / 2`` (eq. 10 with
   ``t`` in seconds). Its standard deviation propagates the per-frame angle noise, estimated
   from the angle residuals, through the least-squares solution. ``RateConfig.model =
   "projection"`` fits eq. 8 generalised to an oblique spin axis instead (docs/spin.md).
6. The fold: the sampled ``theta'`` of a rate ``omega`` equals that of ``180 deg * f - omega``.
   The outline's half-turn cue (its skewness along the major axis, step 3) keeps the body's
   end on one side of the fitted line for ``omega`` and flips it every frame for the mirror;
   when it does not decide, every rate up to ``max_rate_deg_s`` (default: below ``180 deg *
   f``) that fits is listed in an ``ambiguous`` estimate, never one of them as the rate. When
   it decides, the outline is asymmetric and its axis wobbles with the body's full turn: the
   window is refitted with harmonics of the chosen rate as nuisance terms (the ``full-turn``
   model, `RateConfig.full_turn_harmonics`), which gives the rate and its sigma.
7. Refusals, each with a reason: too few usable frames; the angle (or an asymmetric
   outline's full-turn wobble) turning too slowly for the window; a rate too close to the fold
   at ``90 deg * frame rate``; an angle series the spin does not explain (line of sight near
   the spin plane, target not spinning or not elongated); a fit that left the spectral peak.

numpy and OpenCV only (the frontend never imports gtsam).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError, SatposeError
from satpose.datasets.sequence import Frame
from satpose.frontend.measurements import (
    FrameMeasurements,
    SpinRateMeasurement,
    SpinStatus,
    exception_failure,
)
from satpose.frontend.preprocess import PreprocessConfig, Undistorter

_log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RegionConfig:
    """MSER region selection and the per-frame angle.

    Attributes:
        delta: MSER stability step [grey levels of the 8-bit image]. Far targets are dim
            and textured (solar cells): a small step keeps their regions.
        min_area_px: smallest region considered [px] (stars and hot pixels are smaller).
        max_area_fraction: largest region considered, as a fraction of the image.
        max_variation: MSER's largest relative area change over ``delta`` grey levels.
        min_diversity: MSER's pruning of regions too similar to their parent (OpenCV's
            default 0.2 drops the whole-target region of a dim target; 0 keeps it).
        min_contrast: a region is bright when its mean exceeds the mean of the pixels just
            outside it by at least this many grey levels.
        border_margin_px: regions reaching within this many pixels of the outermost row or
            column are cut off by the image border and are not used (OpenCV's MSER leaves the
            outermost pixels out).
        group_gap: another bright region joins the target's region when the gap between
            their bounding boxes is at most this fraction of the largest region's length
            (wings detached from the bus at long range).
        min_elongation: frames whose ellipse has ``1 - b/a`` below this have no usable angle.
        coarse_block_px: the target is first found in the image averaged over blocks of this
            size (cheap); MSER then runs on that part of the image only.
        detect_level: a block belongs to the target when it exceeds the median block by this
            fraction of full scale (8-bit: 2.5 grey levels; the sky is black).
        roi_margin: the part searched with MSER is the found blob's box grown by this
            fraction of its size (and at least two blocks) on every side.
    """

    delta: int = 2
    min_area_px: int = 30
    max_area_fraction: float = 0.25
    max_variation: float = 1.0
    min_diversity: float = 0.0
    min_contrast: float = 2.0
    border_margin_px: int = 1
    group_gap: float = 0.5
    min_elongation: float = 0.2
    coarse_block_px: int = 8
    detect_level: float = 0.01
    roi_margin: float = 0.3

    def __post_init__(self) -> None:
        if self.delta < 1 or self.min_area_px < 1 or self.border_margin_px < 0:
            raise ConfigError("spin.region: delta >= 1, min_area_px >= 1, border_margin_px >= 0")
        if not 0 < self.max_area_fraction <= 1:
            raise ConfigError("spin.region.max_area_fraction must be in (0, 1]")
        if not 0 <= self.min_diversity < 1:
            raise ConfigError("spin.region.min_diversity must be in [0, 1)")
        if not (self.max_variation > 0 and self.min_contrast >= 0 and self.group_gap >= 0):
            raise ConfigError("spin.region: max_variation > 0, min_contrast >= 0, group_gap >= 0")
        if not 0 <= self.min_elongation < 1:
            raise ConfigError("spin.region.min_elongation must be in [0, 1)")
        if self.coarse_block_px < 1 or not (self.detect_level > 0 and self.roi_margin >= 0):
            raise ConfigError(
                "spin.region: coarse_block_px >= 1, detect_level > 0, roi_margin >= 0"
            )


@dataclass(frozen=True, kw_only=True)
class RateConfig:
    """Spin rate from the angle series of a sliding buffer of frames.

    Attributes:
        window_frames: frames in the buffer (seed 001: n = 19; it asks for at least 10).
        min_samples: usable angles the buffer must hold for an estimate; more than the
            model's parameters (`MODEL_PARAMETERS`), so that the residuals give the noise.
        min_periods: the angle (period: half a spin turn) must complete at least this many
            periods within the buffer, else ``too-slow``; below ~1.5 the short and the long
            period of the model cannot be separated.
        oversampling: spectral grid points per resolution bin ``1 / window``.
        fold_guard_sigma: refuse (``aliasing``) when the rate is within this many standard
            deviations of the fold ``90 deg * frame rate``.
        max_rate_deg_s: the highest spin rate the target may have [deg/s]. None: below
            ``180 deg * frame rate`` (at least two frames per turn; beyond it no per-frame
            orientation tells a rate from its mirror ``360 deg * f - omega``). ``theta'``
            alone cannot tell ``omega`` from ``180 deg * f - omega``: unless the outline's
            half-turn cue resolves it (``half_turn``), every rate up to this limit that fits
            is listed as a candidate of an ``ambiguous`` estimate. Below ``90 deg * f`` (the
            paper's assumption, stated) there is one candidate and the rate is ``ok``.
        half_turn: resolve the fold with the outline's half-turn cue (the sign of the region's
            skewness along its major axis, `axis_skewness`): the spin rate ``omega`` keeps
            the skewed end on the same side of the fitted line, its mirror ``180 deg * f -
            omega`` flips it every frame. Off: ``theta'`` only.
        min_skewness: frames whose ``|skewness|`` is below this carry no half-turn cue (the
            symmetric ``spin-far`` outline scatters by ~0.05-0.15 at 320x256; a wing of 0.5
            instead of 1.3 m gives 0.02-0.4).
        half_turn_alpha: a hypothesis (folded or mirror) is taken when the chance that
            uninformative cue signs agree with it as well is below this (two-sided binomial
            over the frames with a cue: 8 of 8, 11 of 12, 16 of 19 at 0.01) and the other
            hypothesis' is not. On uninformative signs about 1% of windows are resolved (at
            random); on the rendered symmetric target none of 558 were, and 0.001 resolves
            27% instead of 84% of the asymmetric target's windows
            (docs/results/spin_fold.md).
        model: what is fitted to the buffer. ``two-sine``: the paper's eq. 9 on the doubled
            angle (see the module docstring). ``projection``: eq. 8 generalised to any angle
            between spin axis and line of sight, ``theta' = psi + atan2(c sin(omega t + phi),
            cos(omega t + phi))`` on the angle itself (4 parameters; docs/spin.md compares).
        min_explained: fraction of ``theta'``'s variation (about its circular mean) the fitted
            model must explain, adjusted for its parameters (``1 - (RSS / (m - p)) / (TSS /
            (m - 1))``, so that noise fitted by many parameters does not count), else
            ``geometry`` (no periodic angle: line of sight near the spin plane, target not
            spinning or round). Random angles reach at most ~0.75 with n = 19.
        max_angle_noise_deg: largest standard deviation of ``theta'`` about the fit [deg],
            else ``geometry`` (random angles scatter by 20 deg and more).
        max_axis_angle_deg: ``projection`` model only: largest fitted angle between the spin
            axis and the line of sight (``acos |c|``) [deg], else ``geometry``. Closer to the
            spin plane the outline mostly changes length, the major axis jumps between the
            wings and the bus, and the model's sigma is too small (docs/spin.md: at 78 deg
            the errors are 3-5 sigma). The two-sine model is refused there by
            ``min_explained``.
        min_spread_deg: circular standard deviation ``theta'`` must reach over the buffer
            [deg], else ``geometry`` (the angle hardly moves).
        max_peak_shift_bins: the fitted rate may leave the spectral peak by at most this many
            resolution bins, else ``no-fit``.
        cross_check: also fit the other model (``two-sine`` <-> ``projection``) to every
            window and accept only when it passes its own checks as well and the two rates
            agree within ``cross_check_sigma`` combined standard deviations, else
            ``geometry``. Each model alone accepts some windows where seed 001's conditions
            fail (spin axis near the image plane; long axis not perpendicular to the spin)
            with errors of 0.5-5 deg/s; the other refuses them (docs/spin.md). Costs the
            second fit (about 1.3 ms per frame).
        cross_check_sigma: see ``cross_check``.
        full_turn_harmonics: when the half-turn cue is decisive (an asymmetric outline), the
            estimate comes from the projection model plus these harmonics of the full-turn
            frequency (the spin rate the cue chose, ``omega`` or ``180 deg * f - omega``)
            as nuisance terms in ``theta'``: an asymmetric outline's axis wobbles with the
            body's full-turn phase (2 deg at 1 and 0.5-1 deg at 3 times the rate on the
            rendered short-wing target, against 1 deg of white noise). Counted as noise the
            wobble made sigma 1.5-2x the spread where it is fast, and biased the rate where it
            is slow (docs/spin.md). A harmonic that the window cannot tell from the projection
            model's own terms (collinear with its Jacobian) is left to the projection model;
            empty: off.
        min_full_turn_cycles: with ``full_turn_harmonics``, the fundamental (the full turn,
            aliased by the frame rate) must complete this many cycles within the window, else
            ``too-slow``: a slower wobble looks like a change of the rate (at 15 deg/s and 1
            Hz a turn takes 24 frames; 19 frames hold 0.79 of it). Slower higher harmonics
            are dropped (they are smaller; near 120 deg/s the third one aliases to a constant).
    """

    window_frames: int = 19
    min_samples: int = 12
    min_periods: float = 1.5
    oversampling: int = 16
    fold_guard_sigma: float = 3.0
    max_rate_deg_s: float | None = None
    half_turn: bool = True
    min_skewness: float = 0.07
    half_turn_alpha: float = 0.01
    model: Literal["two-sine", "projection"] = "two-sine"
    min_explained: float = 0.85
    max_angle_noise_deg: float = 15.0
    max_axis_angle_deg: float = 70.0
    min_spread_deg: float = 3.0
    max_peak_shift_bins: float = 1.0
    cross_check: bool = True
    cross_check_sigma: float = 4.0
    full_turn_harmonics: tuple[int, ...] = (1, 3)
    min_full_turn_cycles: float = 1.0

    def __post_init__(self) -> None:
        if self.window_frames < 4:
            raise ConfigError(f"spin.rate.window_frames must be >= 4, got {self.window_frames}")
        if not 4 <= self.min_samples <= self.window_frames:
            raise ConfigError(
                "spin.rate.min_samples must be in [4, window_frames], got "
                f"{self.min_samples} (window_frames {self.window_frames})"
            )
        if not (self.min_periods > 0 and self.oversampling >= 1 and self.fold_guard_sigma >= 0):
            raise ConfigError("spin.rate: min_periods > 0, oversampling >= 1, guard >= 0")
        if self.max_rate_deg_s is not None and not self.max_rate_deg_s > 0:
            raise ConfigError(
                f"spin.rate.max_rate_deg_s must be positive, got {self.max_rate_deg_s}"
            )
        if not 0 <= self.min_explained < 1 or self.min_spread_deg < 0:
            raise ConfigError("spin.rate: min_explained in [0, 1), min_spread_deg >= 0")
        if not self.max_angle_noise_deg > 0:
            raise ConfigError("spin.rate.max_angle_noise_deg must be positive")
        if not 0 < self.max_axis_angle_deg <= 90:
            raise ConfigError("spin.rate.max_axis_angle_deg must be in (0, 90]")
        if self.model not in MODEL_PARAMETERS:
            raise ConfigError(
                f"spin.rate.model must be one of {sorted(MODEL_PARAMETERS)}, got {self.model!r}"
            )
        fitted = sorted(MODEL_PARAMETERS) if self.cross_check else [self.model]
        most = max(fitted, key=MODEL_PARAMETERS.__getitem__)
        if self.min_samples <= MODEL_PARAMETERS[most]:
            raise ConfigError(
                f"spin.rate.min_samples ({self.min_samples}) must exceed the "
                f"{MODEL_PARAMETERS[most]} parameters of the {most} model"
                + (" (cross_check fits both models)" if self.cross_check else "")
            )
        if not self.max_peak_shift_bins > 0:
            raise ConfigError("spin.rate.max_peak_shift_bins must be positive")
        if not self.cross_check_sigma > 0:
            raise ConfigError("spin.rate.cross_check_sigma must be positive")
        if not (self.min_skewness >= 0 and 0 < self.half_turn_alpha < 1):
            raise ConfigError("spin.rate: min_skewness >= 0, half_turn_alpha in (0, 1)")
        ks = self.full_turn_harmonics
        if any(k < 1 for k in ks) or len(set(ks)) != len(ks):
            raise ConfigError(
                f"spin.rate.full_turn_harmonics must be distinct positive integers, got {ks}"
            )
        if not self.min_full_turn_cycles > 0:
            raise ConfigError("spin.rate.min_full_turn_cycles must be positive")


@dataclass(frozen=True, kw_only=True)
class SpinConfig:
    """The spin-rate frontend (seed 001): image checks, region and angle, rate.

    ``preprocess.dark_level`` defaults to 0 (no "too dark" check): a far target covers well
    under the 0.5 % of the image the stereo frontend's percentile test looks at; a frame
    without the target fails as "no bright region" instead.
    """

    preprocess: PreprocessConfig = field(default_factory=lambda: PreprocessConfig(dark_level=0.0))
    region: RegionConfig = field(default_factory=RegionConfig)
    rate: RateConfig = field(default_factory=RateConfig)


# --------------------------------------------------------------------------------------------
# Per frame: region and angle
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class AngleObservation:
    """The target's silhouette ellipse in one (undistorted) image.

    Attributes:
        angle_rad: ``theta'``, angle of the major axis from the image x axis, in ``[0, pi)``
            (toward +y, i.e. clockwise on screen); NaN when the frame failed.
        center_px: (2,) region centroid [undistorted px]; NaN when no region.
        axes_px: (2,) semi-axes ``(a, b)``, ``a >= b``, of the second-moment ellipse (a
            uniform ellipse has exactly these axes) [px]; NaN when no region.
        area_px: pixels in the region (0 when none).
        elongation: ``1 - b/a`` (the quality: 0 for a disc); NaN when no region.
        failure: why the frame has no usable angle, or None.
        skewness: the region's third standardised moment along the major axis, measured
            toward ``(cos theta', sin theta')``: positive when the outline reaches further (or
            has more area far out) on that side; the half-turn cue (`axis_skewness`). About 0
            for an outline symmetric about its minor axis; NaN when no region.
    """

    angle_rad: float
    center_px: np.ndarray
    axes_px: np.ndarray
    area_px: int
    elongation: float
    failure: str | None = None
    skewness: float = math.nan

    @property
    def ok(self) -> bool:
        """True when ``angle_rad`` is usable."""
        return self.failure is None

    @staticmethod
    def failed(reason: str) -> AngleObservation:
        """An observation without a region."""
        nan2 = np.full(2, np.nan)
        return AngleObservation(
            angle_rad=math.nan,
            center_px=nan2,
            axes_px=nan2,
            area_px=0,
            elongation=math.nan,
            failure=reason,
        )


def _is_bright(gray8: np.ndarray, pts: np.ndarray, min_contrast: float) -> bool:
    """Is the region (N, 2) ``x, y`` brighter than the pixels just outside it?"""
    h, w = gray8.shape
    x0, y0 = max(int(pts[:, 0].min()) - 2, 0), max(int(pts[:, 1].min()) - 2, 0)
    x1, y1 = min(int(pts[:, 0].max()) + 3, w), min(int(pts[:, 1].max()) + 3, h)
    inside = np.zeros((y1 - y0, x1 - x0), np.uint8)
    inside[pts[:, 1] - y0, pts[:, 0] - x0] = 1
    ring = (cv2.dilate(inside, np.ones((3, 3), np.uint8)) > 0) & (inside == 0)
    if not ring.any():
        return False
    patch = gray8[y0:y1, x0:x1]
    return float(patch[inside > 0].mean()) - float(patch[ring].mean()) >= min_contrast


Box = tuple[int, int, int, int]
"""``(x0, y0, x1, y1)`` pixel box: inclusive corners for regions, exclusive end for crops."""

BORDER = "spin: the target touches the image border"
"""Failure of a frame whose target is cut off by the image border."""


def _box_gap(a: Box, b: Box) -> float:
    """Gap [px] between two inclusive ``(x0, y0, x1, y1)`` boxes (0 when they overlap)."""
    dx = max(b[0] - a[2], a[0] - b[2], 0)
    dy = max(b[1] - a[3], a[1] - b[3], 0)
    return math.hypot(dx, dy)


def moment_ellipse(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Second-moment ellipse of a binary region: centre (2,) [px], semi-axes ``(a, b)`` (2,)
    [px] (``2 sqrt`` of the eigenvalues of the pixel covariance: exact for a uniform
    ellipse) and the major axis' angle from the x axis in ``[0, pi)`` [rad]."""
    m = cv2.moments(mask.astype(np.uint8), binaryImage=True)
    if m["m00"] <= 0:
        raise ConfigError("moment_ellipse: empty region")
    c = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
    mu20, mu02, mu11 = m["mu20"] / m["m00"], m["mu02"] / m["m00"], m["mu11"] / m["m00"]
    half_diff = 0.5 * (mu20 - mu02)
    root = math.hypot(half_diff, mu11)
    mean = 0.5 * (mu20 + mu02)
    axes = 2.0 * np.sqrt(np.maximum([mean + root, mean - root], 0.0))
    angle = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
    return c, axes, angle % math.pi


def axis_skewness(mask: np.ndarray, angle_rad: float) -> float:
    """Third standardised moment of a binary region's pixels along the direction
    ``(cos angle, sin angle)`` (image x right, y down): ``E[p^3] / E[p^2]^1.5`` with ``p`` the
    pixel's offset from the centroid along that direction. The sign tells which end of the
    major axis the outline's longer (or fuller) half is on, i.e. the half turn ``theta'``
    leaves open; a uniform segment gives 0, a segment with one end twice as wide ~0.3."""
    m = cv2.moments(mask.astype(np.uint8), binaryImage=True)
    if m["m00"] <= 0:
        raise ConfigError("axis_skewness: empty region")
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    m2 = (c * c * m["mu20"] + 2.0 * c * s * m["mu11"] + s * s * m["mu02"]) / m["m00"]
    m3 = (
        c**3 * m["mu30"]
        + 3.0 * c * c * s * m["mu21"]
        + 3.0 * c * s * s * m["mu12"]
        + s**3 * m["mu03"]
    ) / m["m00"]
    return float(m3 / m2**1.5) if m2 > 0 else 0.0


def locate_target(image: np.ndarray, config: RegionConfig | None = None) -> Box | None:
    """Where the target is, roughly: the box (exclusive end, pixels of ``image``) around the
    largest bright blob of the block-averaged image, grown by ``roi_margin``; None when no
    block stands out. Cheap (one colour conversion and one resize of the image).

    Args:
        image: (H, W) grey or (H, W, 3) BGR, uint8, uint16 or float in [0, 1], as stored
            (distorted: map the box through the camera before cropping an undistorted image).
        config: region settings (defaults if None).
    """
    cfg = config or RegionConfig()
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ConfigError(f"locate_target needs an (H, W[, 3]) image, got shape {img.shape}")
    full = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype, 1.0)
    h, w = img.shape
    k = cfg.coarse_block_px
    small = cv2.resize(img, (max(w // k, 1), max(h // k, 1)), interpolation=cv2.INTER_AREA)
    small = small.astype(np.float32) / np.float32(full)
    blob = (small > float(np.median(small)) + cfg.detect_level).astype(np.uint8)
    # one block of dilation joins parts a few blocks apart (wings beyond dim struts)
    blob = cv2.dilate(blob, np.ones((3, 3), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(blob, connectivity=8)
    if n < 2:
        return None
    i = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    sx, sy = w / small.shape[1], h / small.shape[0]
    x0, y0 = stats[i, cv2.CC_STAT_LEFT] * sx, stats[i, cv2.CC_STAT_TOP] * sy
    x1 = x0 + stats[i, cv2.CC_STAT_WIDTH] * sx
    y1 = y0 + stats[i, cv2.CC_STAT_HEIGHT] * sy
    pad = max(2.0 * k, cfg.roi_margin * max(x1 - x0, y1 - y0))
    return (
        max(int(x0 - pad), 0),
        max(int(y0 - pad), 0),
        min(math.ceil(x1 + pad), w),
        min(math.ceil(y1 + pad), h),
    )


def measure_angle(
    gray8: np.ndarray,
    config: RegionConfig | None = None,
    *,
    origin: tuple[int, int] = (0, 0),
    image_size: tuple[int, int] | None = None,
) -> AngleObservation:
    """The target's silhouette ellipse and ``theta'`` in a grey image or a crop of one.

    Args:
        gray8: (H, W) uint8 image (or crop), undistorted (`Undistorter`), the target bright on
            a dark sky.
        config: region settings (defaults if None).
        origin: pixel of the full image at the crop's top-left corner.
        image_size: ``(width, height)`` of the full image (default: the crop is the image);
            regions touching its border are cut off by it, and ``max_area_fraction`` refers
            to it.

    Returns:
        An `AngleObservation` in full-image pixels; ``failure`` says why there is no angle
        (no bright region, the target clipped by the image border or not elongated). Never
        raises on a bad image.
    """
    cfg = config or RegionConfig()
    img = np.ascontiguousarray(gray8)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ConfigError(f"measure_angle needs an (H, W) uint8 image, got {img.dtype} {img.shape}")
    h, w = img.shape
    ox, oy = int(origin[0]), int(origin[1])
    width, height = image_size if image_size is not None else (w, h)
    mser = cv2.MSER_create(
        delta=cfg.delta,
        min_area=cfg.min_area_px,
        # A crop is chosen with a margin around the target: a region covering half of it is
        # sky noise (and collecting the pixels of such regions would dominate the cost).
        max_area=max(
            int(min(cfg.max_area_fraction * width * height, 0.5 * w * h)), cfg.min_area_px + 1
        ),
        max_variation=cfg.max_variation,
        min_diversity=cfg.min_diversity,
    )
    regions, _ = mser.detectRegions(img)
    m = cfg.border_margin_px
    # Regions touching the image border are cut off by it (``cut``: the target is clipped).
    # Regions touching a crop edge inside the image extend beyond the crop: in the whole
    # image they are larger than anything the crop was chosen around (sky noise joined to a
    # faint halo); they are skipped like regions above ``max_area``.
    lo_x, lo_y = m - ox, m - oy
    hi_x, hi_y = width - 1 - m - ox, height - 1 - m - oy
    in_x0, in_y0 = (ox > 0), (oy > 0)  # crop edges inside the image
    in_x1, in_y1 = (ox + w < width), (oy + h < height)

    def beyond_crop(box: Box) -> bool:
        return (
            (in_x0 and box[0] <= m)
            or (in_y0 and box[1] <= m)
            or (in_x1 and box[2] >= w - 1 - m)
            or (in_y1 and box[3] >= h - 1 - m)
        )

    items = []
    for pts in regions:
        pts = np.asarray(pts).reshape(-1, 2)
        items.append((len(pts), pts))
    items.sort(key=lambda r: -r[0])
    primary = None
    cut = 0
    for area, pts in items:
        box = (
            int(pts[:, 0].min()),
            int(pts[:, 1].min()),
            int(pts[:, 0].max()),
            int(pts[:, 1].max()),
        )
        if beyond_crop(box):
            continue
        if box[0] <= lo_x or box[1] <= lo_y or box[2] >= hi_x or box[3] >= hi_y:
            if not cut and _is_bright(img, pts, cfg.min_contrast):
                cut = area
            continue
        if _is_bright(img, pts, cfg.min_contrast):
            primary = (area, box, pts)
            break
    if primary is None:
        return AngleObservation.failed(
            "spin: the target touches the image border" if cut else "spin: no bright region"
        )
    area0, box0, pts0 = primary
    if cut > area0:
        return AngleObservation.failed("spin: the target touches the image border")
    mask = np.zeros((h, w), np.uint8)
    mask[pts0[:, 1], pts0[:, 0]] = 1
    _, axes0, _ = moment_ellipse(mask)
    gap_px = cfg.group_gap * 2.0 * axes0[0]
    group = box0
    # MSER regions nest: a smaller bright region either lies inside the group already or is a
    # separate part of the target (a wing cut off by dim struts) when it is close enough to
    # the group; joining one part can bring the next within reach, so repeat until stable.
    rest = [item for item in items if item[1] is not pts0]
    bright: dict[int, bool] = {}  # region id -> brighter than its surroundings (cached)
    joined = True
    while joined and rest:
        joined = False
        remaining = []
        for area, pts in rest:
            if mask[pts[:, 1], pts[:, 0]].mean() > 0.5:
                continue  # nested in the group (or a hole of it)
            box = (
                int(pts[:, 0].min()),
                int(pts[:, 1].min()),
                int(pts[:, 0].max()),
                int(pts[:, 1].max()),
            )
            if (
                beyond_crop(box)
                or box[0] <= lo_x
                or box[1] <= lo_y
                or box[2] >= hi_x
                or box[3] >= hi_y
            ):
                continue
            if _box_gap(group, box) > gap_px:
                remaining.append((area, pts))
                continue
            if id(pts) not in bright:
                bright[id(pts)] = _is_bright(img, pts, cfg.min_contrast)
            if bright[id(pts)]:
                mask[pts[:, 1], pts[:, 0]] = 1
                group = (
                    min(group[0], box[0]),
                    min(group[1], box[1]),
                    max(group[2], box[2]),
                    max(group[3], box[3]),
                )
                joined = True
            else:
                remaining.append((area, pts))
        rest = remaining
    center, axes, angle = moment_ellipse(mask)
    elongation = 1.0 - axes[1] / axes[0] if axes[0] > 0 else 0.0
    failure = None
    if elongation < cfg.min_elongation:
        failure = (
            f"spin: the target's outline is not elongated (axis ratio {1 - elongation:.2f} > "
            f"{1 - cfg.min_elongation:.2f})"
        )
    return AngleObservation(
        angle_rad=angle if failure is None else math.nan,
        center_px=center + np.array([ox, oy], float),
        axes_px=axes,
        area_px=int(mask.sum()),
        elongation=float(elongation),
        failure=failure,
        skewness=axis_skewness(mask, angle),
    )


# --------------------------------------------------------------------------------------------
# Over a buffer: the spin rate
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class HalfTurn:
    """The half-turn vote of one window: does the outline's skewed end stay on one side of the
    fitted line (the folded rate ``omega``) or flip every frame (its mirror ``180 deg * f -
    omega``)?

    Attributes:
        frames: frames with a cue (``|skewness| >= min_skewness``).
        folded_agree: most frames agreeing on one side for the folded rate.
        mirror_agree: the same for the mirror (sides alternating frame by frame).
        p_folded, p_mirror: chance of agreeing that well with uninformative cues (two-sided
            binomial).
        verdict: ``folded``, ``mirror`` or ``""`` (undecided).
    """

    frames: int
    folded_agree: int
    mirror_agree: int
    p_folded: float
    p_mirror: float
    verdict: str

    def describe(self) -> str:
        """One phrase for reasons and logs."""
        return (
            f"half-turn cue in {self.frames} frames, sides consistent with the folded rate in "
            f"{self.folded_agree}, with its mirror in {self.mirror_agree}"
        )


@dataclass(frozen=True, kw_only=True)
class SpinFit:
    """One spin-rate estimate over a window, with the fitted model (for plots and checks).

    Attributes:
        status, reason: ``ok`` or the refusal and why (`SpinStatus`).
        rate_rad_s, sigma_rad_s: ``|omega|`` and its standard deviation [rad/s]; NaN when no
            candidate was found.
        window_start_s, window_end_s: first and last frame time of the window [s].
        samples: usable angles in the window.
        frame_interval_s: the frames' nominal interval [s] (sets the fold).
        spectral_rate_rad_s: the rate at the periodogram's peak (the fit's start) [rad/s].
        model: the fitted model (``two-sine`` or ``projection``, `RateConfig.model`; or
            ``full-turn`` when the half-turn cue decided and the window was refitted with the
            outline's full-turn wobble, `RateConfig.full_turn_harmonics`), empty when none was
            fitted.
        params: the model's parameters (`_two_sine_angle`, `_projection_angle`,
            `_full_turn_angle`), times relative to ``t_ref_s``.
        t_ref_s: time origin of the model [s] (window centre).
        angle_noise_rad: standard deviation of one ``theta'`` about the fit [rad].
        explained: fraction of ``theta'``'s variation (about its circular mean) the model
            explains, adjusted for its parameters (`RateConfig.min_explained`).
        candidates_rad_s: ``ambiguous`` only: every rate that fits (sorted) [rad/s];
            ``rate_rad_s`` is then NaN and ``sigma_rad_s`` each candidate's sigma.
        half_turn: the half-turn vote `HalfTurn` (None when not tried).
    """

    status: SpinStatus
    reason: str
    rate_rad_s: float
    sigma_rad_s: float
    window_start_s: float
    window_end_s: float
    samples: int
    frame_interval_s: float
    spectral_rate_rad_s: float = math.nan
    model: str = ""
    params: np.ndarray = field(default_factory=lambda: np.zeros(0))
    t_ref_s: float = math.nan
    angle_noise_rad: float = math.nan
    explained: float = math.nan
    candidates_rad_s: tuple[float, ...] = ()
    half_turn: HalfTurn | None = None

    @property
    def ok(self) -> bool:
        """True when the rate was accepted."""
        return self.status is SpinStatus.OK

    def angle(self, t_s: np.ndarray) -> np.ndarray:
        """The fitted model's ``theta'`` in ``[0, pi)`` at times ``t_s`` (N,) [rad]."""
        tau = np.asarray(t_s, float) - self.t_ref_s
        if self.model == "two-sine":
            return _two_sine_angle(self.params, tau) % math.pi
        if self.model == "projection":
            return _projection_angle(self.params, tau) % math.pi
        if self.model == "full-turn":
            return _full_turn_angle(self.params, tau) % math.pi
        raise ConfigError("this spin estimate has no fitted model")

    def measurement(self) -> SpinRateMeasurement:
        """The estimate as the frontend -> backend contract type."""
        return SpinRateMeasurement(
            rate_rad_s=self.rate_rad_s,
            sigma_rad_s=self.sigma_rad_s,
            status=self.status,
            reason=self.reason,
            window_start_s=self.window_start_s,
            window_end_s=self.window_end_s,
            samples=self.samples,
            candidates_rad_s=self.candidates_rad_s,
        )


def _wrap_half(a: np.ndarray) -> np.ndarray:
    """Angle differences of lines (period pi) into ``[-pi/2, pi/2)``."""
    return (np.asarray(a) + 0.5 * math.pi) % math.pi - 0.5 * math.pi


# -- the paper's two-sine model (eq. 9) on the doubled angle ----------------------------------


def _design(tau: np.ndarray, b1: float, b2: float) -> np.ndarray:
    """(N, 4) basis ``[sin b1 t, cos b1 t, sin b2 t, cos b2 t]``."""
    A = np.empty((tau.size, 4))
    x1, x2 = b1 * tau, b2 * tau
    np.sin(x1, out=A[:, 0])
    np.cos(x1, out=A[:, 1])
    np.sin(x2, out=A[:, 2])
    np.cos(x2, out=A[:, 3])
    return A


def _solve_linear(A: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares coefficients (2, 4) of both components and the residual sum of squares."""
    C, *_ = np.linalg.lstsq(A, Y, rcond=None)
    r = Y - A @ C
    return C.T, float(np.sum(r * r))


def _two_sine_angle(params: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """``theta'`` [rad] of the two-sine model ``params = [b1, b2, C_u (4), C_v (4)]``."""
    uv = _design(tau, params[0], params[1]) @ params[2:].reshape(2, 4).T
    return 0.5 * np.arctan2(uv[:, 1], uv[:, 0])


def _two_sine_jacobian(tau: np.ndarray, b1: float, b2: float, C: np.ndarray) -> np.ndarray:
    """(2N, 10) Jacobian of the stacked model ``[u; v]`` w.r.t. ``[b1, b2, C_u (4), C_v (4)]``."""
    A = _design(tau, b1, b2)
    m = tau.size
    J = np.zeros((2 * m, 10))
    for j in range(2):
        rows = slice(j * m, (j + 1) * m)
        c = C[j]
        J[rows, 0] = tau * (c[0] * np.cos(b1 * tau) - c[1] * np.sin(b1 * tau))
        J[rows, 1] = tau * (c[2] * np.cos(b2 * tau) - c[3] * np.sin(b2 * tau))
        J[rows, 2 + 4 * j : 6 + 4 * j] = A
    return J


def _two_sine_fit(
    tau: np.ndarray, th: np.ndarray, b_peak: float, bin_rad_s: float
) -> tuple[np.ndarray, float]:
    """The paper's model fitted to ``(cos 2theta', sin 2theta')`` with shared ``b1``, ``b2``.

    Amplitudes and phases are linear for given ``(b1, b2)``: ``b1`` (long period, at most one
    cycle per window) starts at the best of a few values with ``b2`` at the spectral peak,
    then Levenberg-Marquardt refines all ten parameters. Returns the parameters and the
    standard deviation of ``b2`` per unit angle noise [rad/s per rad] (the solution's
    sensitivity to each frame's angle: a frame's angle error ``d theta`` moves its
    doubled-angle components by ``2 (-sin 2theta, cos 2theta) d theta``).
    """
    Y = np.column_stack([np.cos(2.0 * th), np.sin(2.0 * th)])
    y = np.concatenate([Y[:, 0], Y[:, 1]])
    b1_lo, b1_hi = 0.05 * bin_rad_s, min(bin_rad_s, 0.5 * b_peak)
    b1 = float(
        min(
            np.linspace(b1_lo, b1_hi, 6),
            key=lambda b: _solve_linear(_design(tau, float(b), b_peak), Y)[1],
        )
    )
    b2 = b_peak
    C, cost = _solve_linear(_design(tau, b1, b2), Y)
    lam = 1e-3
    for _ in range(30):
        J = _two_sine_jacobian(tau, b1, b2, C)
        r = (_design(tau, b1, b2) @ C.T).T.ravel() - y
        H, g = J.T @ J, J.T @ r
        improved = False
        for _ in range(8):
            D = H + lam * np.diag(np.diag(H) + 1e-12)
            dp = np.linalg.solve(D, -g)
            if not b1_lo <= b1 + dp[0] <= b1_hi:
                # b1 at its bound (the long term wants a longer period): hold it there
                dp = np.concatenate([[0.0], np.linalg.solve(D[1:, 1:], -g[1:])])
            nb1 = float(np.clip(b1 + dp[0], b1_lo, b1_hi))
            nb2 = b2 + float(dp[1])
            nC = C + dp[2:].reshape(2, 4)
            new_cost = float(np.sum(((_design(tau, nb1, nb2) @ nC.T).T.ravel() - y) ** 2))
            if new_cost <= cost:
                # converged when b2 (the rate) stops moving and the cost stops falling; b1
                # and the long-period amplitudes may drift along flat directions for long
                improved = abs(dp[1]) > 1e-8 * bin_rad_s or cost - new_cost > 1e-9 * cost
                b1, b2, C, cost = nb1, nb2, nC, new_cost
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if not improved:
            break
    m = tau.size
    J = _two_sine_jacobian(tau, b1, b2, C)
    G = np.linalg.pinv(J.T @ J, rcond=1e-12) @ J.T  # d params / d [u; v]
    du = np.concatenate([-2.0 * np.sin(2.0 * th), 2.0 * np.cos(2.0 * th)])
    sens = G[1, :m] * du[:m] + G[1, m:] * du[m:]  # d b2 / d theta_k
    params = np.concatenate([[b1, b2], C.ravel()])
    return params, float(np.sqrt(np.sum(sens * sens)))


# -- the projection model: eq. 8 for any angle between spin axis and line of sight ------------


def _projection_angle(params: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """``theta' = psi + atan2(c sin(omega t + phi), cos(omega t + phi))`` [rad] for
    ``params = [psi, c, omega, phi]``: the image angle of a direction turning at ``omega`` in
    the spin plane, seen orthographically (``|c|`` = cosine of the angle between spin axis
    and line of sight, its sign the sense of rotation; ``c = 1`` is eq. 8)."""
    psi, c, w, phi = params
    x = w * tau + phi
    return psi + np.arctan2(c * np.sin(x), np.cos(x))


def _projection_jacobian(params: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(N, 4) Jacobian of `_projection_angle` w.r.t. ``[psi, c, omega, phi]``."""
    _, c, w, phi = params
    x = w * tau + phi
    s, co = np.sin(x), np.cos(x)
    d = co * co + c * c * s * s
    dx = c / d
    return np.column_stack([np.ones_like(tau), s * co / d, tau * dx, dx])


def _fit_angles(
    model: Callable[[np.ndarray, np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray],
    p: np.ndarray,
    free: np.ndarray,
    tau: np.ndarray,
    th: np.ndarray,
    iterations: int,
) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt of ``model(p, tau)`` on the angle residuals ``th`` (period pi)
    over the parameters ``free`` (``jacobian`` gives their columns; ``p[1]``, the projection's
    ``c``, kept in [-1, 1]). Converged when omega (``p[2]``) stops moving (1e-9 rad/s, far
    below any sigma) and the cost stops falling. Returns the parameters and the cost."""

    def cost_of(q: np.ndarray) -> float:
        return float(np.sum(_wrap_half(th - model(q, tau)) ** 2))

    p = p.copy()
    cost, lam = cost_of(p), 1e-3
    for _ in range(iterations):
        r = _wrap_half(th - model(p, tau))
        J = jacobian(p, tau)
        H, grad = J.T @ J, J.T @ r
        improved = False
        for _ in range(10):
            dp = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), grad)
            q = p.copy()
            q[free] += dp
            q[1] = float(np.clip(q[1], -1.0, 1.0))
            new_cost = cost_of(q)
            if new_cost <= cost:
                improved = abs(dp[2]) > 1e-9 or cost - new_cost > 1e-9 * cost
                p, cost = q, new_cost
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if not improved:
            break
    return p, cost


def _projection_fit(tau: np.ndarray, th: np.ndarray, omega0: float) -> tuple[np.ndarray, float]:
    """Least squares of `_projection_angle` on the angle residuals (period pi), started from
    the best of a grid over ``(c, phi)`` at ``omega0`` (the spectral peak) with the optimal
    ``psi`` for each. Returns the parameters and the standard deviation of ``omega`` per unit
    angle noise [rad/s per rad]."""
    cs = np.array([-1.0, -0.8, -0.5, -0.2, 0.2, 0.5, 0.8, 1.0])
    phis = np.linspace(0.0, math.pi, 8, endpoint=False)
    x = omega0 * tau[None, None, :] + phis[None, :, None]
    g = np.arctan2(cs[:, None, None] * np.sin(x), np.cos(x))
    psi = 0.5 * np.angle(np.sum(np.exp(2j * (th - g)), axis=2))
    r = _wrap_half(th - g - psi[..., None])
    i, j = np.unravel_index(np.argmin(np.sum(r * r, axis=2)), psi.shape)
    p = np.array([psi[i, j], cs[i], omega0, phis[j]])
    p, _ = _fit_angles(_projection_angle, _projection_jacobian, p, np.arange(4), tau, th, 50)
    J = _projection_jacobian(p, tau)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-12)  # per unit angle variance
    return p, float(np.sqrt(max(cov[2, 2], 0.0)))


# -- the full-turn model: the projection model plus the asymmetric outline's wobble ---------------


def _full_turn_frequency(params: np.ndarray) -> float:
    """The full-turn frequency ``Omega = base + sign * omega`` [rad/s] of full-turn parameters
    ``[psi, c, omega, phi, base, sign, (k, a, b) ...]`` (`_full_turn_angle`)."""
    return float(params[4] + params[5] * params[2])


def _full_turn_angle(params: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """``theta'`` [rad] of the projection model plus harmonics of the full turn:
    ``_projection_angle([psi, c, omega, phi]) + sum_k (a_k cos k Omega t + b_k sin k Omega t)``
    for ``params = [psi, c, omega, phi, base, sign, k1, a1, b1, k2, a2, b2, ...]`` with
    ``Omega = base + sign * omega``: ``omega`` itself (the cue chose the folded rate, ``base``
    0, ``sign`` 1) or its mirror ``pi / dt - omega`` (``base`` ``pi / dt``, ``sign`` -1)."""
    out = _projection_angle(params[:4], tau)
    big = _full_turn_frequency(params)
    for k, a, b in params[6:].reshape(-1, 3):
        x = k * big * tau
        out = out + a * np.cos(x) + b * np.sin(x)
    return out


def _full_turn_jacobian(params: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(N, 4 + 2 H) Jacobian of `_full_turn_angle` w.r.t. ``[psi, c, omega, phi, a1, b1, ...]``
    (``base``, ``sign`` and the harmonic numbers are fixed)."""
    big, sign = _full_turn_frequency(params), float(params[5])
    cols = [_projection_jacobian(params[:4], tau)]
    d_omega = np.zeros_like(tau)
    for k, a, b in params[6:].reshape(-1, 3):
        x = k * big * tau
        c, s = np.cos(x), np.sin(x)
        cols.append(np.column_stack([c, s]))
        d_omega += k * sign * tau * (b * c - a * s)
    J = np.concatenate(cols, axis=1)
    J[:, 2] += d_omega
    return J


def _aliased_cycles(freq_rad_s: float, dt: float, span_s: float) -> float:
    """Cycles a sinusoid of ``freq_rad_s`` sampled every ``dt`` appears to complete in
    ``span_s`` (its frequency folded into ``[0, 1 / (2 dt)]``)."""
    f = (abs(freq_rad_s) * dt / (2.0 * math.pi)) % 1.0  # cycles per frame
    return min(f, 1.0 - f) * span_s / dt


def _full_turn_fit(
    tau: np.ndarray,
    th: np.ndarray,
    projection: np.ndarray,
    mirror: bool,
    dt: float,
    span_s: float,
    cfg: RateConfig,
) -> tuple[np.ndarray, float, float] | str:
    """Refit a window whose half-turn cue decided the fold with the outline's full-turn wobble
    as nuisance (`RateConfig.full_turn_harmonics`), from the projection model's parameters.

    Returns ``(params, omega sigma [rad/s], angle noise [rad])`` (params of
    `_full_turn_angle`; the rate is ``|Omega|``, `_full_turn_frequency`), or why the window
    cannot separate the wobble from the rate (its fundamental completes fewer than
    ``min_full_turn_cycles`` cycles). The sigma is the angle noise left by this model
    (``m - 4 - 2 H`` degrees of freedom) times the solution's sensitivity to each angle."""
    p = np.asarray(projection, float).copy()
    if p[2] < 0:  # the same curve with omega > 0: (c, omega, phi) -> -(c, omega, phi)
        p[1:4] = -p[1:4]
    base, sign = (math.pi / dt, -1.0) if mirror else (0.0, 1.0)
    big = base + sign * p[2]
    cycles = _aliased_cycles(big, dt, span_s)
    if 1 in cfg.full_turn_harmonics and cycles < cfg.min_full_turn_cycles:
        frames = math.ceil(cfg.min_full_turn_cycles * span_s / max(cycles, 1e-9))
        return (
            f"the outline is asymmetric (the half-turn cue decided the fold) and its full-turn "
            f"wobble completes {cycles:.2f} cycles in the {span_s:g} s window (minimum "
            f"{cfg.min_full_turn_cycles:g}): it cannot be told from a change of the rate; use "
            f"a window of at least {frames} frames"
        )
    # Harmonics the window can separate from the projection model's own terms: sampled
    # cos / sin of k Omega must keep part of their norm outside the span of its Jacobian
    # (a harmonic aliased onto 2 omega is the projection model's c, onto 0 its psi).
    U, sv, _ = np.linalg.svd(_projection_jacobian(p, tau), full_matrices=False)
    U = U[:, sv > 1e-9 * sv[0]]
    dof_left = th.size - 4
    terms: list[float] = []
    for k in sorted(cfg.full_turn_harmonics):
        x = k * big * tau
        H = np.column_stack([np.cos(x), np.sin(x)])
        outside = H - U @ (U.T @ H)
        norm = np.sum(H * H, axis=0)
        fraction = np.sqrt(np.sum(outside * outside, axis=0) / np.maximum(norm, 1e-300))
        if (
            _aliased_cycles(k * big, dt, span_s) < cfg.min_full_turn_cycles
            or fraction.min() < _MIN_OUTSIDE_FRACTION
            or dof_left - 2 < _MIN_FULL_TURN_DOF
        ):
            continue
        dof_left -= 2
        terms += [float(k), 0.0, 0.0]
    p = np.concatenate([p, [base, sign], terms])
    if terms:
        # linear start for the harmonics on the projection model's residuals
        r0 = _wrap_half(th - _projection_angle(p[:4], tau))
        A = _full_turn_jacobian(p, tau)[:, 4:]
        coef, *_ = np.linalg.lstsq(A, r0, rcond=None)
        p[7::3], p[8::3] = coef[0::2], coef[1::2]
    free = np.r_[0:4, np.flatnonzero(np.arange(p.size - 6) % 3 != 0) + 6]  # not base/sign/k

    p, cost = _fit_angles(_full_turn_angle, _full_turn_jacobian, p, free, tau, th, 60)
    J = _full_turn_jacobian(p, tau)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-12)  # per unit angle variance
    noise = math.sqrt(cost / max(th.size - J.shape[1], 1))
    return p, noise * math.sqrt(max(float(cov[2, 2]), 0.0)), noise


_MIN_OUTSIDE_FRACTION = 0.3
"""A full-turn harmonic is fitted only when at least this fraction of its sampled cos and sin
lies outside the projection model's Jacobian (else that model absorbs it): 0.01-0.02 where it
aliases onto twice the folded rate (120 deg/s at 1 Hz), above 0.9 elsewhere on the rendered
sweep."""
_MIN_FULL_TURN_DOF = 3
"""Residual degrees of freedom the full-turn model keeps (harmonics beyond that are dropped)."""


# -- the estimate -------------------------------------------------------------------------------


MODEL_PARAMETERS = {"two-sine": 9, "projection": 4}
"""Free parameters of each model as seen by the angle (the residual degrees of freedom are
``samples - this``): the two-sine model has ten, but a common scale of both components does
not change the angle."""


def _window_fit(
    status: SpinStatus,
    reason: str,
    t0: float,
    t1: float,
    samples: int,
    dt: float,
    rate: float = math.nan,
    sigma: float = math.nan,
    **extra: object,
) -> SpinFit:
    """One window's answer, whatever its status (``extra``: the fitted model's fields)."""
    return SpinFit(
        status=status,
        reason=reason,
        rate_rad_s=rate,
        sigma_rad_s=sigma,
        window_start_s=t0,
        window_end_s=t1,
        samples=samples,
        frame_interval_s=dt,
        **extra,  # type: ignore[arg-type]
    )


@dataclass(frozen=True)
class _Refined:
    """A window refitted once the half-turn cue decided the fold (`_full_turn_fit`): the rate
    the cue chose and its sigma [rad/s], and the `SpinFit` fields of the refitted model."""

    rate: float
    sigma: float
    fields: dict[str, object]


@dataclass(frozen=True)
class _ModelFit:
    """One model fitted to a window: rate and sigma [rad/s], angle noise [rad], adjusted
    explained fraction, and the refusal ``(status, reason)`` its own checks give (or None)."""

    model: str
    params: np.ndarray
    rate: float
    sigma: float
    noise: float
    explained: float
    refusal: tuple[SpinStatus, str] | None


def _fit_model(
    model: str,
    tau: np.ndarray,
    th: np.ndarray,
    z: np.ndarray,
    R: float,
    b_peak: float,
    bin_rad_s: float,
    cfg: RateConfig,
) -> _ModelFit:
    """Fit ``model`` from the spectral peak ``b_peak`` (of the doubled angle) and apply the
    checks that concern the fit itself: it stays at the peak (``no-fit``), it explains
    ``theta'`` (``geometry``), and for the projection model the axis is not too far from the
    line of sight (``geometry``)."""
    m = int(th.size)
    if model == "two-sine":
        params, per_noise = _two_sine_fit(tau, th, b_peak, bin_rad_s)
        rate = 0.5 * abs(float(params[1]))
        sens = 0.5 * per_noise
        model_angle = _two_sine_angle(params, tau)
    else:
        params, sens = _projection_fit(tau, th, 0.5 * b_peak)
        rate = abs(float(params[2]))
        model_angle = _projection_angle(params, tau)
    resid = _wrap_half(th - model_angle)
    dof = max(m - MODEL_PARAMETERS[model], 1)
    noise = math.sqrt(float(resid @ resid) / dof)
    sigma = noise * sens
    deviation = 0.5 * np.angle(z * np.conj(z.mean())) if R > 0 else _wrap_half(th)
    tss = float(deviation @ deviation)
    explained = 1.0 - (float(resid @ resid) / dof) / (tss / (m - 1)) if tss > 0 else 0.0
    refusal: tuple[SpinStatus, str] | None = None
    shift_bins = abs(2.0 * rate - b_peak) / bin_rad_s
    if shift_bins > cfg.max_peak_shift_bins or not math.isfinite(sigma):
        refusal = (
            SpinStatus.NO_FIT,
            f"the {model} fit left the spectral peak ({math.degrees(0.5 * b_peak):.2f} -> "
            f"{math.degrees(rate):.2f} deg/s, {shift_bins:.1f} bins)",
        )
    elif explained < cfg.min_explained or math.degrees(noise) > cfg.max_angle_noise_deg:
        refusal = (
            SpinStatus.GEOMETRY,
            f"the {model} model explains {100 * explained:.0f}% of theta''s variation "
            f"(minimum {100 * cfg.min_explained:.0f}%), theta' scatters "
            f"{math.degrees(noise):.1f} deg about it (maximum {cfg.max_angle_noise_deg:g}): "
            "line of sight near the spin plane, or the target not spinning or not elongated",
        )
    elif model == "projection":
        axis_deg = math.degrees(math.acos(min(abs(float(params[1])), 1.0)))
        if axis_deg > cfg.max_axis_angle_deg:
            refusal = (
                SpinStatus.GEOMETRY,
                f"the spin axis is {axis_deg:.0f} deg from the line of sight (more than "
                f"{cfg.max_axis_angle_deg:g}): near the spin plane the outline mostly changes "
                "length instead of turning",
            )
    return _ModelFit(model, params, rate, sigma, noise, explained, refusal)


def estimate_spin_rate(
    t_s: np.ndarray,
    angle_rad: np.ndarray,
    config: RateConfig | None = None,
    *,
    window_s: tuple[float, float] | None = None,
    frame_interval_s: float | None = None,
    skewness: np.ndarray | None = None,
) -> SpinFit:
    """Spin rate from the silhouette angles of one window of frames (seed 001, eqs. 8-10).

    Args:
        t_s: (N,) times of the usable frames [s], strictly increasing.
        angle_rad: (N,) ``theta'`` of those frames [rad] (any representative modulo ``pi``).
        skewness: (N,) the outline's skewness along ``(cos theta', sin theta')`` of each frame
            (`AngleObservation.skewness`, taken with ``theta'`` in ``[0, pi)``: pass
            ``angle_rad`` reduced modulo ``pi``), NaN where unknown; None: no half-turn cue.
        config: rate settings (defaults if None).
        window_s: ``(first, last)`` frame time of the whole window [s] (frames without a usable
            angle included); default: the first and last of ``t_s``.
        frame_interval_s: nominal frame interval [s]; default: median of ``diff(t_s)``.

    Returns:
        A `SpinFit`: the rate ``|omega|`` [rad/s] with its standard deviation; ``ambiguous``
        with every candidate when several rates fit (``theta'`` alone cannot tell ``omega``
        from ``180 deg * f - omega``: see `RateConfig.max_rate_deg_s`); or a refusal with its
        reason (degenerate data is refused, not raised).

    Raises:
        ConfigError: times not increasing, or ``t_s`` and ``angle_rad`` of different lengths.
    """
    cfg = config or RateConfig()
    t = np.asarray(t_s, float).ravel()
    th = np.asarray(angle_rad, float).ravel()
    sk = np.full(th.shape, np.nan) if skewness is None else np.asarray(skewness, float).ravel()
    if t.shape != th.shape or sk.shape != th.shape:
        raise ConfigError(
            f"t_s, angle_rad and skewness differ in length: {t.shape}, {th.shape}, {sk.shape}"
        )
    keep = np.isfinite(t) & np.isfinite(th)
    t, th, sk = t[keep], th[keep], sk[keep]
    m = int(t.size)
    if m > 1 and not np.all(np.diff(t) > 0):
        raise ConfigError("estimate_spin_rate: times must be strictly increasing")
    if window_s is None:
        t0, t1 = (float(t[0]), float(t[-1])) if m else (0.0, 0.0)
    else:
        t0, t1 = float(window_s[0]), float(window_s[1])
    if frame_interval_s is not None:
        dt = float(frame_interval_s)
    else:
        dt = float(np.median(np.diff(t))) if m > 1 else math.nan
    if m < cfg.min_samples:
        return _window_fit(
            SpinStatus.TOO_FEW_SAMPLES,
            f"{m} usable frames in the window, {cfg.min_samples} needed",
            t0,
            t1,
            m,
            dt,
        )
    if not (math.isfinite(dt) and dt > 0):
        raise ConfigError(f"estimate_spin_rate: frame interval must be positive, got {dt}")
    span = (t1 - t0) + dt  # the window covers n frame intervals
    fold = math.pi / (2.0 * dt)  # the doubled angle reaches Nyquist at this spin rate [rad/s]
    t_ref = 0.5 * (t0 + t1)
    tau = t - t_ref

    # How much theta' moves: circular spread (half that of the doubled angle).
    z = np.exp(2j * th)
    R = float(abs(z.mean()))
    spread = 0.5 * math.sqrt(-2.0 * math.log(R)) if 0 < R < 1 else (0.0 if R >= 1 else math.inf)
    if math.degrees(spread) < cfg.min_spread_deg:
        return _window_fit(
            SpinStatus.GEOMETRY,
            f"theta' hardly changes (spread {math.degrees(spread):.1f} deg < "
            f"{cfg.min_spread_deg:g}): the target is not spinning, or spins about its long "
            "axis, or the line of sight lies in the spin plane",
            t0,
            t1,
            m,
            dt,
        )

    # Spectral estimate of the doubled angle's frequency b = 2 omega: periodogram of both
    # components at the sample times (gaps allowed), up to the Nyquist frequency.
    zc = z - z.mean()
    bin_rad_s = 2.0 * math.pi / span  # resolution of b
    b_grid = np.arange(0.5 * bin_rad_s / cfg.oversampling, 2.0 * fold, bin_rad_s / cfg.oversampling)
    E = np.exp(-1j * np.outer(b_grid, tau))
    power = np.abs(E @ zc.real) ** 2 + np.abs(E @ zc.imag) ** 2
    b_peak = float(b_grid[int(np.argmax(power))])
    spectral = 0.5 * b_peak
    b_lo = 2.0 * math.pi * cfg.min_periods / span
    if b_peak < b_lo:
        return _window_fit(
            SpinStatus.TOO_SLOW,
            f"theta' turns fewer than {cfg.min_periods:g} times in the {span:g} s window (about "
            f"{math.degrees(spectral):.1f} deg/s, minimum {math.degrees(0.5 * b_lo):.1f}): use "
            "a longer window",
            t0,
            t1,
            m,
            dt,
            spectral_rate_rad_s=spectral,
        )

    def fit(model: str) -> _ModelFit:
        return _fit_model(model, tau, th, z, R, b_peak, bin_rad_s, cfg)

    primary = fit(cfg.model)
    rate, sigma = primary.rate, primary.sigma
    projection = primary.params if cfg.model == "projection" else None
    fitted: dict[str, object] = {
        "spectral_rate_rad_s": spectral,
        "model": cfg.model,
        "params": primary.params,
        "t_ref_s": t_ref,
        "angle_noise_rad": primary.noise,
        "explained": primary.explained,
    }

    def refuse(status: SpinStatus, reason: str) -> SpinFit:
        return _window_fit(status, reason, t0, t1, m, dt, rate, sigma, **fitted)

    if primary.refusal is not None:
        return refuse(*primary.refusal)
    if fold - rate < cfg.fold_guard_sigma * sigma:
        return refuse(
            SpinStatus.ALIASING,
            f"{math.degrees(rate):.2f} deg/s is within {cfg.fold_guard_sigma:g} sigma "
            f"({math.degrees(sigma):.2f} deg/s) of the fold at {math.degrees(fold):.1f} deg/s "
            f"(90 deg per frame): {math.degrees(2 * fold - rate):.2f} deg/s fits as well",
        )
    if cfg.cross_check:
        other = fit("projection" if cfg.model == "two-sine" else "two-sine")
        if other.model == "projection":
            projection = other.params
        if other.refusal is not None:
            return refuse(
                SpinStatus.GEOMETRY,
                f"the {other.model} model refuses this window ({other.refusal[1]}), so the "
                f"{cfg.model} model's {math.degrees(rate):.2f} deg/s is not trusted",
            )
        gap = abs(rate - other.rate)
        if gap > cfg.cross_check_sigma * math.hypot(sigma, other.sigma):
            return refuse(
                SpinStatus.GEOMETRY,
                f"the {cfg.model} and {other.model} models disagree: "
                f"{math.degrees(rate):.3f} vs {math.degrees(other.rate):.3f} deg/s, more than "
                f"{cfg.cross_check_sigma:g} combined sigma ({math.degrees(sigma):.3f}, "
                f"{math.degrees(other.sigma):.3f} deg/s): the outline's angle is not that of "
                "one line turning about one axis",
            )
        # Both models passed: theta''s noise is what the better-fitting one leaves. The
        # two-sine model's residuals on an oblique view hold its mismatch (harmonics of the
        # doubled angle); counted as noise they made sigma 1.5-3x the spread over windows
        # (docs/results/spin_fold.md). What the mismatch does to the rate is bounded by the
        # two models' difference, added in quadrature (on noise-free oblique series it is
        # the error itself).
        if other.noise < primary.noise:
            sigma = math.hypot(sigma * other.noise / primary.noise, rate - other.rate)
            fitted["angle_noise_rad"] = other.noise

    def refine(mirror: bool) -> _Refined | tuple[SpinStatus, str]:
        # the half-turn cue decided: the outline is asymmetric, fit its full-turn wobble
        p0 = projection if projection is not None else fit("projection").params
        out = _full_turn_fit(tau, th, p0, mirror, dt, span, cfg)
        if isinstance(out, str):
            return SpinStatus.TOO_SLOW, out
        params, sig, noise = out
        shift_bins = abs(2.0 * float(params[2]) - b_peak) / bin_rad_s
        if shift_bins > cfg.max_peak_shift_bins or not math.isfinite(sig):
            return (
                SpinStatus.NO_FIT,
                f"the full-turn fit left the spectral peak ({math.degrees(0.5 * b_peak):.2f} "
                f"-> {math.degrees(abs(params[2])):.2f} deg/s, {shift_bins:.1f} bins)",
            )
        extra = {"model": "full-turn", "params": params, "angle_noise_rad": noise}
        return _Refined(abs(_full_turn_frequency(params)), sig, extra)

    return _resolve_fold(
        t,
        th,
        sk,
        (t0, t1),
        dt,
        rate,
        sigma,
        fitted,
        cfg,
        refuse,
        m,
        refine if cfg.full_turn_harmonics else None,
    )


def _resolve_fold(
    t: np.ndarray,
    th: np.ndarray,
    sk: np.ndarray,
    window: tuple[float, float],
    dt: float,
    rate: float,
    sigma: float,
    fitted: dict[str, object],
    cfg: RateConfig,
    refuse: Callable[[SpinStatus, str], SpinFit],
    m: int,
    refine: Callable[[bool], _Refined | tuple[SpinStatus, str]] | None = None,
) -> SpinFit:
    """The accepted folded rate (below ``90 deg * f``) -> the answer: one rate (``ok``), every
    candidate (``ambiguous``) or a refusal (the half-turn cue contradicts ``max_rate_deg_s``).

    ``theta'`` of ``omega`` and of ``180 deg * f - omega`` (and ``180 k f +- omega``) are the
    same samples. The outline's half-turn cue tells the first two apart (`HalfTurn`); the
    full-turn angle it gives repeats for ``360 deg * f - omega``, so rates above ``180 deg *
    f`` stay candidates whenever ``max_rate_deg_s`` allows them. When the cue decides,
    ``refine(mirror)`` (if given) refits the window with the asymmetric outline's full-turn
    wobble (`_full_turn_fit`): the rate it chose, its sigma and the model's fields, or a
    refusal ``(status, reason)``."""
    t0, t1 = window
    step = math.pi / dt  # 180 deg per frame [rad/s]
    limit = math.radians(cfg.max_rate_deg_s) if cfg.max_rate_deg_s is not None else None
    vote = _half_turn_vote(t, th, sk, t0, dt, fitted, cfg) if cfg.half_turn else None
    fitted = {**fitted, "half_turn": vote}
    f_hz = 1.0 / dt

    def ok(r: float) -> SpinFit:
        return _window_fit(SpinStatus.OK, "", t0, t1, m, dt, r, sigma, **fitted)

    def ambiguous(cands: list[float], why: str) -> SpinFit:
        listed = " or ".join(f"{math.degrees(c):.2f}" for c in cands)
        reason = f"{listed} deg/s fit equally well: {why}"
        return _window_fit(
            SpinStatus.AMBIGUOUS,
            reason,
            t0,
            t1,
            m,
            dt,
            math.nan,
            sigma,
            candidates_rad_s=tuple(cands),
            **fitted,
        )

    if vote is None or not vote.verdict:
        # theta' only: omega, 180 f - omega, 180 f + omega, ... up to the limit
        top = limit if limit is not None else step * (1.0 - 1e-9)
        cands = alias_rates(rate, dt, top)
        if len(cands) == 1:
            return ok(cands[0])
        if not cands:
            # the folded rate and its mirror both above the stated limit (a limit under 90 f)
            return refuse(
                SpinStatus.ALIASING,
                f"theta' fits {math.degrees(rate):.2f} or {math.degrees(step - rate):.2f} deg/s, "
                f"both above max_rate_deg_s {cfg.max_rate_deg_s:g}: the prior is wrong",
            )
        cue = "half-turn cue off" if vote is None else vote.describe()
        return ambiguous(
            cands,
            f"at {f_hz:g} frames/s theta' of a spin omega samples like 180 deg * "
            f"{f_hz:g} - omega and the outline does not tell them apart ({cue}); "
            + (
                f"rates up to max_rate_deg_s {cfg.max_rate_deg_s:g} listed"
                if limit is not None
                else f"set rate.max_rate_deg_s below {90.0 * f_hz:g} if the target cannot "
                "spin faster"
            ),
        )
    chosen = rate if vote.verdict == "folded" else step - rate
    if refine is not None:
        refined = refine(vote.verdict == "mirror")
        if isinstance(refined, tuple):
            return refuse(*refined)
        chosen, sigma = refined.rate, refined.sigma
        fitted = {**fitted, **refined.fields}
    if limit is not None and chosen > limit:
        return refuse(
            SpinStatus.ALIASING,
            f"the half-turn cue says {math.degrees(chosen):.2f} deg/s ({vote.describe()}), "
            f"above max_rate_deg_s {cfg.max_rate_deg_s:g}: the prior or the cue is wrong",
        )
    if limit is None:
        return ok(chosen)
    # the full-turn angle repeats every 360 deg per frame: k 360 f +- chosen
    cands = alias_rates(chosen, 0.5 * dt, limit)
    if len(cands) == 1:
        return ok(chosen)
    return ambiguous(
        cands,
        f"the half-turn cue fixes the rate modulo 360 deg * {f_hz:g} ({vote.describe()}); "
        f"rates up to max_rate_deg_s {cfg.max_rate_deg_s:g} listed",
    )


def _binomial_tail(agree: int, n: int) -> float:
    """Two-sided chance that ``n`` fair coin flips give ``agree`` or more of one side."""
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(agree, n + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def _half_turn_vote(
    t: np.ndarray,
    th: np.ndarray,
    sk: np.ndarray,
    t0: float,
    dt: float,
    fitted: dict[str, object],
    cfg: RateConfig,
) -> HalfTurn:
    """Which of the folded rate and its mirror the outline's skewed end follows.

    The fitted model gives a continuous line angle ``theta_c(t)`` (its ``theta'`` unwrapped on
    a grid of 32 points per frame: the folded rate turns it by less than 90 deg per frame). A
    frame's skewed end points along ``theta'_k`` or ``theta'_k + pi`` (the sign of the
    skewness); ``d_k = +1`` when that is ``theta_c(t_k)``, else -1. The folded rate keeps the
    body's end on one side of ``theta_c``: ``d_k`` constant. Its mirror turns the body 180 deg
    per frame more: ``d_k (-1)^n_k`` constant (``n_k`` the frame number). Each hypothesis is
    scored by the largest number of frames agreeing on one side."""
    cue = np.isfinite(sk) & (np.abs(sk) >= cfg.min_skewness)
    n = int(cue.sum())
    if n == 0:
        return HalfTurn(
            frames=0, folded_agree=0, mirror_agree=0, p_folded=1.0, p_mirror=1.0, verdict=""
        )
    model, t_ref = str(fitted["model"]), float(fitted["t_ref_s"])  # type: ignore[arg-type]
    params = np.asarray(fitted["params"])
    t_end = float(t[-1])
    grid = np.linspace(t0, max(t_end, t0 + dt), int(32 * max(t_end - t0, dt) / dt) + 1)
    angle_fn = _two_sine_angle if model == "two-sine" else _projection_angle
    line = 0.5 * np.unwrap(2.0 * angle_fn(params, grid - t_ref))
    theta_c = np.interp(t[cue], grid, line)
    end = (th[cue] % math.pi) + np.where(sk[cue] < 0, math.pi, 0.0)
    d = np.where(np.cos(end - theta_c) > 0, 1, -1)
    k = np.round((t[cue] - t0) / dt).astype(int)
    e = d * np.where(k % 2 == 0, 1, -1)
    a_f = int(max((d > 0).sum(), (d < 0).sum()))
    a_m = int(max((e > 0).sum(), (e < 0).sum()))
    p_f, p_m = _binomial_tail(a_f, n), _binomial_tail(a_m, n)
    alpha = cfg.half_turn_alpha
    verdict = ""
    if p_f < alpha <= p_m:
        verdict = "folded"
    elif p_m < alpha <= p_f:
        verdict = "mirror"
    return HalfTurn(
        frames=n,
        folded_agree=a_f,
        mirror_agree=a_m,
        p_folded=p_f,
        p_mirror=p_m,
        verdict=verdict,
    )


def alias_rates(rate_rad_s: float, frame_interval_s: float, max_rate_rad_s: float) -> list[float]:
    """Every spin rate up to ``max_rate_rad_s`` whose sampled ``theta'`` equals that of
    ``rate_rad_s`` (in either sense of rotation): ``k pi / dt -+ rate`` [rad/s], sorted."""
    step = math.pi / frame_interval_s  # theta' repeats every half turn: 180 deg per frame
    out: list[float] = []
    k = 0
    while k * step - rate_rad_s <= max_rate_rad_s:
        for r in (k * step - rate_rad_s, k * step + rate_rad_s):
            if 0 <= r <= max_rate_rad_s and all(abs(r - o) > 1e-12 for o in out):
                out.append(r)
        k += 1
    return sorted(out)


class SpinRateEstimator:
    """The sliding buffer: the last ``window_frames`` frames' angles, one estimate per frame
    once the buffer is full (frames without a usable angle count toward the window)."""

    def __init__(self, config: RateConfig | None = None) -> None:
        self.config = config or RateConfig()
        self._t: deque[float] = deque(maxlen=self.config.window_frames)
        self._angle: deque[float] = deque(maxlen=self.config.window_frames)
        self._skew: deque[float] = deque(maxlen=self.config.window_frames)

    def add(self, t_s: float, angle_rad: float, skewness: float = math.nan) -> SpinFit | None:
        """Add one frame at ``t_s`` [s] (``angle_rad`` NaN when it has no usable angle;
        ``skewness`` its half-turn cue, `AngleObservation.skewness`, NaN if none); the estimate
        over the buffer ending at it, or None while the buffer fills."""
        if self._t and not t_s > self._t[-1]:
            raise ConfigError(f"spin: frame time {t_s} s does not follow {self._t[-1]} s")
        self._t.append(float(t_s))
        self._angle.append(float(angle_rad))
        self._skew.append(float(skewness))
        if len(self._t) < self.config.window_frames:
            return None
        t = np.array(self._t)
        a = np.array(self._angle)
        ok = np.isfinite(a)
        return estimate_spin_rate(
            t[ok],
            a[ok],
            self.config,
            window_s=(float(t[0]), float(t[-1])),
            frame_interval_s=float(np.median(np.diff(t))),
            skewness=np.array(self._skew)[ok],
        )


# --------------------------------------------------------------------------------------------
# The frontend
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class SpinStep:
    """What the spin frontend saw in one frame (handed to the optional hook).

    Attributes:
        frame, t_s: the frame.
        angle: the silhouette ellipse and ``theta'``.
        fit: the estimate over the buffer ending at this frame, or None while buffering.
    """

    frame: int
    t_s: float
    angle: AngleObservation
    fit: SpinFit | None


class SpinFrontend:
    """One camera's frames in, `FrameMeasurements` with ``spin`` out (seed 001).

    Args:
        camera: the camera (its distortion is removed first).
        config: settings (defaults if None).
        hook: optional callable receiving a `SpinStep` per frame (plots, diagnostics).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        config: SpinConfig | None = None,
        hook: Callable[[SpinStep], None] | None = None,
    ) -> None:
        self.config = config or SpinConfig()
        self.undistort = Undistorter(camera, self.config.preprocess)
        self.rate = SpinRateEstimator(self.config.rate)
        self.hook = hook

    def _angle(self, image: np.ndarray, timings: dict[str, float]) -> AngleObservation:
        """Locate (block averages of the raw image), undistort the box around the target,
        MSER and ellipse there."""
        t0 = time.perf_counter()
        cam = self.undistort.camera
        raw_box = locate_target(image, self.config.region)
        t1 = time.perf_counter()
        timings["locate"] = 1e3 * (t1 - t0)
        if raw_box is None:
            timings["undistort"] = timings["region"] = 0.0
            return AngleObservation.failed("spin: no bright region")
        box = self._undistorted_box(raw_box)
        prepared = self.undistort.crop(image, box)
        t2 = time.perf_counter()
        timings["undistort"] = 1e3 * (t2 - t1)
        if prepared.problem is not None:
            timings["region"] = 0.0
            return AngleObservation.failed(f"spin: image {prepared.problem}")
        size = (cam.width, cam.height)
        obs = measure_angle(
            prepared.gray8, self.config.region, origin=(box[0], box[1]), image_size=size
        )
        timings["region"] = 1e3 * (time.perf_counter() - t2)
        return obs

    def _undistorted_box(self, raw: Box) -> Box:
        """The box (exclusive end) of the undistorted image covering the raw image's box."""
        cam = self.undistort.camera
        x0, y0, x1, y1 = raw
        s = np.linspace(0.0, 1.0, 5)
        edge = np.concatenate(
            [
                np.c_[x0 + s * (x1 - x0), np.full(5, y0)],
                np.c_[x0 + s * (x1 - x0), np.full(5, y1)],
                np.c_[np.full(5, x0), y0 + s * (y1 - y0)],
                np.c_[np.full(5, x1), y0 + s * (y1 - y0)],
            ]
        )
        if cam.has_distortion:
            edge = self.undistort.undistort_points(edge)
        lo = np.floor(edge.min(axis=0)) - 1
        hi = np.ceil(edge.max(axis=0)) + 2
        return (
            max(int(lo[0]), 0),
            max(int(lo[1]), 0),
            min(int(hi[0]), cam.width),
            min(int(hi[1]), cam.height),
        )

    def process_frame(self, frame: Frame) -> FrameMeasurements:
        """`process` on a sequence frame (its left, or only, image); an unreadable image is
        a frame without an angle (failure ``"image: ..."``), not an exception."""
        try:
            image = frame.left()
        except SatposeError as exc:
            return self.process(frame.index, frame.t_s, None, failure=f"image: {exc}")
        return self.process(frame.index, frame.t_s, image)

    def process(
        self, frame: int, t_s: float, image: np.ndarray | None, failure: str | None = None
    ) -> FrameMeasurements:
        """One frame: ``image`` (H, W) grey or (H, W, 3) BGR, uint8 or uint16, as stored;
        None with a ``failure`` note for a frame without a usable image. An unexpected
        exception while measuring the angle or the rate is the frame's failure
        (``"spin: internal error: ..."``, traceback at DEBUG), not the caller's.

        Returns:
            The frame's measurements: ``spin`` once the buffer is full (accepted or refused),
            ``failures`` when the frame has no usable angle, per-stage ``timings_ms``.
        """
        timings: dict[str, float] = {}
        notes: list[str] = []
        if image is None:
            obs = AngleObservation.failed(failure or "image: missing")
        else:
            try:
                obs = self._angle(image, timings)
            except Exception as exc:
                _log.debug("frame %d: spin angle raised", frame, exc_info=True)
                obs = AngleObservation.failed(exception_failure("spin", exc))
        t0 = time.perf_counter()
        fit: SpinFit | None = None
        try:
            fit = self.rate.add(t_s, obs.angle_rad, obs.skewness)
        except Exception as exc:
            _log.debug("frame %d: spin rate raised", frame, exc_info=True)
            notes.append(exception_failure("spin_rate", exc))
        timings["rate"] = 1e3 * (time.perf_counter() - t0)
        if self.hook is not None:
            self.hook(SpinStep(frame=frame, t_s=t_s, angle=obs, fit=fit))
        failures = tuple(([obs.failure] if obs.failure is not None else []) + notes)
        return FrameMeasurements(
            frame=frame,
            t_s=t_s,
            failures=failures,
            timings_ms=timings,
            spin=None if fit is None else fit.measurement(),
        )
