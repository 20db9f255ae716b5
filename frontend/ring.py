"""The docking ring's outer front edge in one camera: selection, tracking, sub-pixel refinement.

Seed 000, section 3.1: at the first frame, the ellipse with the largest sum of axes; 16 points
on it tracked by pyramidal Lucas-Kanade; afterwards the detected ellipse nearest the tracked
points (mean distance below ``max_track_distance_px``, the paper's s2), else an ellipse fitted
to the tracked points.

A ring is a wall with height: an image shows several nearly concentric ellipses (outer and
inner front edge, the wall's base, a cast shadow). Taking the largest one mixes them, which
costs centimetres in depth. The outer front edge is the outer boundary of the rim's front
face, a band of uniform brightness: brighter than what lies just outside it along most of
the perimeter when lit, darker when in shade (`inside_dominance`). Every chosen ellipse is
refined on sub-pixel edges of that polarity with a blurred-step fit that barely looks past
the edge (`satpose.frontend.edges`), because crinkled foil beside the rim otherwise moves the
edge by tenths of a pixel — differently in the two cameras, i.e. a depth bias.

When tracking is healthy the detector only searches a window around the prediction. When it
is not, `acquire` returns every plausible candidate and the stereo frontend keeps the pair
that forms one 3-D circle (`satpose.frontend.pipeline`). After dropped frames (a live tracker
that fell behind) the frontend first looks for the ring where it predicts it over the gap
(`RingTracker.reacquire`), and acquires over the whole image only if that fails.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from satpose.frontend.conics import (
    ConicError,
    Ellipse,
    fit_ellipse_direct,
    refine_ellipse,
    sampson_distance,
)
from satpose.frontend.edges import (
    EdgeSearchConfig,
    edges_of_polarity,
    sample_image,
    smoothed,
)
from satpose.frontend.measurements import Camera, EllipseObservation
from satpose.frontend.preprocess import PreparedImage
from satpose.frontend.ring_bands import BandSeedConfig, band_seeds


class EllipseCandidate(Protocol):
    """What the ring tracker needs from an ellipse detector's output."""

    ellipse: Ellipse
    support: float
    polarity: int


Detector = Callable[[np.ndarray, "tuple[int, int, int, int] | None"], Sequence[EllipseCandidate]]
"""``detector(gray8, roi) -> candidates``: an ellipse detector on an undistorted uint8 image,
searching the whole image or a window ``(x0, y0, x1, y1)``."""


@dataclass(frozen=True, kw_only=True)
class RingConfig:
    """Ring selection and tracking (all distances in pixels of the undistorted image).

    Attributes:
        track_points: points on the ellipse tracked by Lucas-Kanade (seed 000: 16).
        lk_window_px, lk_levels: pyramidal LK window size and pyramid levels.
        max_track_distance_px: the paper's s2: a detection farther than this (mean distance
            of the tracked points to it) is rejected and the tracked fit used instead.
        detect_every: while tracking, the detector searches the window around the prediction
            every this many frames (1 = every frame, as the paper); in between the ellipse
            fitted to the tracked points is refined directly on sub-pixel edges.
        min_tracked_points: fewer surviving LK points than this and the track is lost.
        roi_margin: the search window is the predicted ellipse's box grown by this fraction
            of its major axis plus ``roi_margin_px``.
        min_axis_px: smallest semi-minor axis accepted as a ring.
        max_axis_ratio: most elongated ellipse accepted (a / b), i.e. at most ~75 deg tilt.
        min_candidate_support: detector support below this is ignored.
        min_bright_inside: fraction of the perimeter where the band just inside must differ
            from the band just outside in the rim's sense (brighter for a lit rim, darker for
            a rim in shade); `inside_dominance`.
        edge_points: normals sampled for the sub-pixel refinement.
        edge_search_px: half-width of the search along each normal.
        min_edge_fraction: fraction of normals that must find an edge of the right polarity.
        max_refine_rms_px: largest accepted RMS distance of the inliers to the ellipse.
        outlier_sigma: inliers are within this many robust standard deviations.
        edges: sub-pixel edge settings.
        outer_search_scales: at acquisition, when the detector finds no larger concentric
            ellipse around a candidate, sub-pixel edges are searched around the candidate
            scaled by these factors (`RingTracker._outer_by_search`). 1.0 re-fits the
            candidate itself on clean edges of each polarity: a small ring's detection can mix
            arcs of its inner and outer edges (6 px apart at 7 m) into one ellipse that fits
            neither, and which arcs it mixes changes with the last bits of the image.
        outer_search_coverage: fraction of the ``edge_points`` normals such a fit must keep.
        bands: seeds from thin dark or bright bands when the detector gives no candidate
            (`satpose.frontend.ring_bands`).
        gap_window: after dropped frames (a live tracker that fell behind), look for the
            ring first where it is predicted (`reacquire`: the detection nearest the
            predicted ellipse in a window around it), and acquire over the whole image only
            if that finds no ring.
        gap_margin_per_frame: the window's margin, and how far a detection may lie from the
            prediction, grow by this fraction of the predicted ellipse's major axis per frame
            of the gap (on top of ``roi_margin`` and ``max_track_distance_px``): the
            prediction's error grows with the time it bridges.
        gap_max_area: a window larger than this fraction of the image is not worth a first
            try: the whole image is searched at once.
        face_rise: the rim-face check (`face_rise`): an edge point whose inner side rises
            toward it by more than this fraction of its own contrast above the median rise
            of all the fit's points (and by more than ``outlier_sigma`` robust standard
            deviations of the rise: noisy edges) bounds a band beside the rim (a sunlit wall face
            brighter than the rim, or a shadow darker than it), not the rim's face, and is
            left out of the fit. None: no check.
        face_depth_px: how far inside each edge point the rim face is sampled (every px
            from 2 px on): past the widest band beside the rim that the check should see.
        mixed_acquisition: when the candidates of one polarity make no stereo-consistent
            ring, acquisition runs the detector once more linking arcs of either polarity
            (`acquire` with ``mixed=True``; the caller passes the tracker a
            ``mixed_detector``). A rim between sunlit foil and black space or shadow is
            darker than its surroundings on one side and brighter on the other: its outer
            edge changes sign along the perimeter, and one-polarity arcs never close it.
        mixed_bright_level: the mixed pass also scales the detector's Canny thresholds
            (absolute, grey levels per px) by the image's bright level (its 99th percentile,
            grey levels of 255) over this, when it is lower, down to a fifth: a dim scene's
            rim (10 grey levels on black under a grazing sun) has gradients below the
            absolute thresholds, and the thresholds follow the image's contrast instead.
    """

    track_points: int = 16
    lk_window_px: int = 21
    lk_levels: int = 3
    max_track_distance_px: float = 3.0
    detect_every: int = 5
    min_tracked_points: int = 8
    roi_margin: float = 0.25
    roi_margin_px: int = 12
    min_axis_px: float = 8.0
    max_axis_ratio: float = 4.0
    min_candidate_support: float = 0.35
    min_bright_inside: float = 0.55
    edge_points: int = 240
    edge_search_px: float = 3.0
    min_edge_fraction: float = 0.5
    max_refine_rms_px: float = 0.6
    outlier_sigma: float = 3.0
    edges: EdgeSearchConfig = field(
        default_factory=lambda: EdgeSearchConfig(
            smooth_sigma_px=0.6, step_px=0.25, locate="model", model_window_px=(-2.0, 0.5)
        )
    )
    outer_search_scales: tuple[float, ...] = (1.0, 1.06, 1.13, 1.21, 1.3, 1.4, 1.5)
    outer_search_coverage: float = 0.7
    bands: BandSeedConfig = field(default_factory=BandSeedConfig)
    gap_window: bool = True
    gap_margin_per_frame: float = 0.05
    gap_max_area: float = 0.5
    face_rise: float | None = None
    face_depth_px: float = 3.0
    mixed_acquisition: bool = True
    mixed_bright_level: float = 128.0

    def __post_init__(self) -> None:
        if self.face_rise is not None and not self.face_rise > 0:
            raise ValueError(f"ring.face_rise must be > 0 or null, got {self.face_rise}")
        if not self.face_depth_px >= 2.0:
            raise ValueError(f"ring.face_depth_px must be >= 2, got {self.face_depth_px}")
        if not (math.isfinite(self.mixed_bright_level) and self.mixed_bright_level > 0):
            raise ValueError(f"ring.mixed_bright_level must be > 0, got {self.mixed_bright_level}")


@dataclass
class RingTrack:
    """Per-camera tracking state (mutable; owned by `RingTracker`)."""

    ellipse: Ellipse
    points: np.ndarray  # (n, 2) the tracked points on it
    gray8: np.ndarray  # the image they were sampled in
    polarity: int  # +1: the rim is brighter than its surroundings, -1: darker, 0: mixed
    age: int = 0  # frames followed since acquisition


def inside_dominance(
    image_s: np.ndarray, e: Ellipse, polarity: int, n: int = 72, band_px: float = 2.5
) -> float:
    """Fraction of the perimeter where the image just inside ``e`` is brighter
    (``polarity = +1``) or darker (``-1``) than just outside (bands at ``band_px``), or
    differs from it in either sense (``0``: a rim of mixed polarity)."""
    p = e.points(n)
    nrm = e.normals(n)
    both = np.concatenate([p - band_px * nrm, p + band_px * nrm]).astype(np.float32)
    vals = sample_image(image_s, both[:, 0], both[:, 1], "linear")
    step = vals[:n] - vals[n:]
    return float(np.mean((polarity * step if polarity != 0 else np.abs(step)) > 0.01))


def contrast_scale(gray8: np.ndarray, bright_level: float, floor: float = 0.2) -> float:
    """Factor in [``floor``, 1] for absolute edge thresholds on a uint8 image: its bright
    level (99th percentile, grey levels) over ``bright_level`` when lower, else 1."""
    level = float(np.percentile(gray8, 99))
    return float(np.clip(level / bright_level, floor, 1.0))


def face_rise(
    image_s: np.ndarray, points: np.ndarray, normals: np.ndarray, depth_px: float
) -> np.ndarray:
    """Per edge point, how much the image rises from the face inside it toward the edge,
    in units of the edge's own contrast (N,): ``max_t s (I(-1) - I(t)) / |I(-1) - I(+1)|``
    over ``t = -2, -3, ..., -depth_px``, with ``I(t)`` sampled ``t`` px along the outward
    ``normals`` (N, 2) from ``points`` (N, 2) in the smoothed image and ``s`` the edge's sign
    (+1: brighter inside).

    At the rim's own edge the face inside is uniform: about 0. Where a band lies between
    the rim and the edge found (the wall's outer face lit brighter than the rim, with an edge
    of the tracked polarity against the panel beyond it), the band is the edge's inner side
    and the rim face beyond it differs: up to about 1 once ``depth_px`` reaches past the band.
    Along a thin rim band (narrower than ``depth_px``) every point rises alike; the caller
    compares each point with the median over the curve, not with 0."""
    nrm = np.asarray(normals, float)
    pts = np.asarray(points, float)
    k = pts.shape[0]
    depths = np.arange(2.0, max(depth_px, 2.0) + 1e-9, 1.0)
    offsets = np.concatenate([[-1.0, 1.0], -depths])
    taps = np.concatenate([pts + t * nrm for t in offsets])
    v = sample_image(image_s, taps[:, 0], taps[:, 1], "linear").astype(np.float64)
    v = v.reshape(len(offsets), k)
    inner, outer, face = v[0], v[1], v[2:]
    contrast = inner - outer
    sign = np.where(contrast >= 0, 1.0, -1.0)
    rise = np.max(sign * (inner - face), axis=0)
    return rise / np.maximum(np.abs(contrast), 1e-3)


class RingTracker:
    """Finds and follows the ring's outer front edge in one camera.

    Two modes: `follow` while a track exists (LK prediction, detection in a window, nearest
    detection or the tracked fit), `acquire` otherwise (every plausible ellipse of the whole
    image, refined; the caller picks the pair that makes one 3-D circle in both cameras).
    Neither mode changes the track: the caller `commit`s the observation it keeps.
    ``mixed_detector``: the same detector linking arcs of either polarity, for
    `acquire(..., mixed=True)` (`RingConfig.mixed_acquisition`); None: no such pass.
    """

    def __init__(
        self,
        camera: Camera,
        detector: Detector,
        config: RingConfig | None = None,
        mixed_detector: Detector | None = None,
    ) -> None:
        self.camera = Camera(camera)
        self.detector = detector
        self.mixed_detector = mixed_detector
        self.config = config or RingConfig()
        self.track: RingTrack | None = None

    def reset(self) -> None:
        self.track = None

    def prediction(self, image: PreparedImage) -> Ellipse | None:
        """Where the ring should be in ``image`` from the LK-tracked points, or None."""
        if self.track is None:
            return None
        cfg = self.config
        p0 = self.track.points.astype(np.float32).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            self.track.gray8,
            image.gray8,
            p0,
            None,
            winSize=(cfg.lk_window_px, cfg.lk_window_px),
            maxLevel=cfg.lk_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        if p1 is None:
            return None
        good = p1.reshape(-1, 2)[st.reshape(-1) == 1]
        if good.shape[0] < max(cfg.min_tracked_points, 5):
            return None
        try:
            return fit_ellipse_direct(good)
        except ConicError:
            return None

    def _roi(self, e: Ellipse, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
        m = self.config.roi_margin * e.a + self.config.roi_margin_px
        x0 = max(0, int(e.cx - e.a - m))
        y0 = max(0, int(e.cy - e.a - m))
        x1 = min(shape[1], math.ceil(e.cx + e.a + m))
        y1 = min(shape[0], math.ceil(e.cy + e.a + m))
        return x0, y0, x1, y1

    def _plausible(
        self,
        image: PreparedImage,
        roi: tuple[int, int, int, int] | None,
        image_s: np.ndarray,
        polarity: int | None,
        mixed: bool = False,
    ) -> list[tuple[Ellipse, int]]:
        """Detected ellipses that could be the outer front edge with the rim's polarity
        (``+1`` brighter inside, ``-1`` darker; ``None``: whichever dominates), largest first.
        ``mixed``: detected by the ``mixed_detector``, and where neither sign dominates, an
        edge of either sign all round is ring-like too (polarity 0)."""
        cfg = self.config
        out = []
        detector = self.mixed_detector if mixed and self.mixed_detector else self.detector
        for c in detector(image.gray8, roi):
            e = c.ellipse
            if c.support < cfg.min_candidate_support:
                continue
            if e.b < cfg.min_axis_px or e.a / e.b > cfg.max_axis_ratio:
                continue
            pols = (polarity,) if polarity is not None else (+1, -1)
            dom, pol = max((inside_dominance(image_s, e, p), p) for p in pols)
            if dom < cfg.min_bright_inside and mixed and polarity is None:
                # the mixed pass: an edge all round whose sign changes along the perimeter
                dom, pol = inside_dominance(image_s, e, 0), 0
            if dom < cfg.min_bright_inside:
                continue
            out.append((e, pol))
        return sorted(out, key=lambda ep: -(ep[0].a + ep[0].b))

    def _observation(
        self, refined: tuple[Ellipse, np.ndarray, float, np.ndarray], source: str
    ) -> EllipseObservation:
        ell, cov, rms, inliers = refined
        return EllipseObservation(
            camera=self.camera,
            center_px=ell.center,
            axes_px=[ell.a, ell.b],
            angle_rad=ell.theta,
            conic=ell.conic(),
            covariance=cov,
            edge_points_px=inliers,
            sigma_px=max(rms, 0.02),
            source=source,
        )

    def follow(
        self, image: PreparedImage
    ) -> tuple[tuple[EllipseObservation, int] | None, str | None]:
        """Measure the ring near where the track predicts it: ``((observation, polarity),
        None)``, or ``(None, reason)`` if the track is lost (the caller then acquires).

        When the detector runs, a larger concentric ring-like ellipse (of either polarity)
        replaces the tracked one: the outer front edge is the largest of the rim's concentric
        edges, and acquisition may have started on the inner one."""
        if self.track is None:
            return None, f"ring ({self.camera.value}): not tracking"
        if image.problem is not None:
            return None, f"ring ({self.camera.value}): image {image.problem}"
        cfg = self.config
        image_s = smoothed(image.gray, cfg.edges)
        predicted = self.prediction(image)
        if predicted is None:
            return None, f"ring ({self.camera.value}): track lost (Lucas-Kanade)"
        pol = self.track.polarity
        chosen, source = predicted, "tracked"
        self.track.age += 1
        if self.track.age % cfg.detect_every == 0:
            roi = self._roi(
                Ellipse(
                    cx=predicted.cx,
                    cy=predicted.cy,
                    a=predicted.a * 1.3,
                    b=predicted.b * 1.3,
                    theta=predicted.theta,
                ),
                image.gray.shape,
            )
            found = self._plausible(image, roi, image_s, None)
            pts = predicted.points(64)
            best = cfg.max_track_distance_px
            for e, p in found:
                if p != pol:
                    continue
                d = float(np.mean(np.abs(_distance(pts, e))))
                if d < best:
                    chosen, best, source = e, d, "detected"
            larger = self._larger_concentric(image, image_s, predicted, found)
            if larger is not None:
                return larger, None
        refined = self._refine(image_s, image.gray, chosen, pol)
        if refined is None:
            return None, f"ring ({self.camera.value}): weak edge support around the prediction"
        return (self._observation(refined, source), pol), None

    def acquire(
        self,
        image: PreparedImage,
        max_candidates: int = 6,
        mixed: bool = False,
        known: Sequence[tuple[EllipseObservation, int]] = (),
    ) -> list[tuple[EllipseObservation, int]]:
        """Every plausible ring edge in the whole image, refined, largest first, with its
        polarity; at most ``max_candidates``.

        ``mixed``: the candidates of the ``mixed_detector`` instead (arcs of either polarity
        linked; `RingConfig.mixed_acquisition`), whose ring-likeness may hold with either
        sign along the perimeter (polarity 0: each normal keeps the stronger edge); [] without
        a mixed detector. The band seeds are not looked for again, and candidates that repeat
        one of ``known`` (found before) are left out."""
        if image.problem is not None:
            return []
        cfg = self.config
        if mixed and self.mixed_detector is None:
            return []
        image_s = smoothed(image.gray, cfg.edges)
        out: list[tuple[EllipseObservation, int]] = []
        found = self._plausible(image, None, image_s, None, mixed)
        for e, pol in found:
            self._add_candidates(image, image_s, e, pol, out)
            if len(out) >= max_candidates:
                break
        if mixed:
            return [c for c in out if not _known(c[0], list(known))][:max_candidates]
        if not out and cfg.bands.enabled:
            # no arc-based candidate: a rim seen as a thin band on a busy panel
            # (`satpose.frontend.ring_bands`); its seeds are refined and verified the same way
            seeds = band_seeds(
                image.gray8,
                lambda g: self.detector(g, None),
                cfg.min_axis_px,
                cfg.max_axis_ratio,
                cfg.bands,
            )
            for e in seeds:
                dom, pol = max((inside_dominance(image_s, e, p), p) for p in (+1, -1))
                if dom < cfg.min_bright_inside:
                    continue
                self._add_candidates(image, image_s, e, pol, out)
                if len(out) >= max_candidates:
                    break
        return out[:max_candidates]

    def _add_candidates(
        self,
        image: PreparedImage,
        image_s: np.ndarray,
        e: Ellipse,
        pol: int,
        out: list[tuple[EllipseObservation, int]],
    ) -> None:
        """Append to ``out`` what a starting ellipse ``e`` gives: itself refined on edges, the
        larger concentric detection and the outer edge found by search around it."""
        # the whole-image pass can miss the outer edge of a small ring next to the inner
        # one, or mix arcs of both into one ellipse; a larger concentric detection and a
        # search around each candidate both find it (as `follow` does later). Both are
        # kept: a mixed detection refined on edges can pass as the larger one.
        # The search starts from the candidate refined on edges when it can be (a clean
        # fit of one edge), else from the detection.
        refined = self._refine(image_s, image.gray, e, pol)
        for larger in (
            self._larger_concentric(image, image_s, e),
            self._outer_by_search(image, image_s, e if refined is None else refined[0]),
        ):
            if larger is not None and not _known(larger[0], out):
                out.append(larger)
        if refined is not None:
            obs = self._observation(refined, "detected")
            if not _known(obs, out):
                out.append((obs, pol))

    def reacquire(
        self, image: PreparedImage, outline_px: np.ndarray, gap_frames: int
    ) -> list[tuple[EllipseObservation, int]]:
        """The ring after ``gap_frames`` frames without a measurement, where it is predicted:
        ``outline_px`` (N, 2) is the predicted outline of the outer front edge. Like a
        `follow` whose prediction comes from the 3-D motion instead of Lucas-Kanade: the
        detections in the window around the prediction (`gap_window`), the one nearest the
        prediction (mean distance within ``max_track_distance_px`` plus
        ``gap_margin_per_frame`` of its major axis per frame of the gap) — or a larger
        concentric one — refined on edges. Skips the outer-edge search of `acquire` (the
        edge predicted is already the outer one), which is most of an acquisition's cost.

        Returns:
            ``[(observation, polarity)]``, or ``[]`` when nothing near the prediction is a
            ring (the caller then acquires over the whole image).
        """
        if image.problem is not None:
            return []
        roi = self.gap_window(outline_px, gap_frames, image.gray.shape)
        if roi is None:
            return []
        try:
            predicted = fit_ellipse_direct(outline_px)
        except ConicError:
            return []
        cfg = self.config
        image_s = smoothed(image.gray, cfg.edges)
        found = self._plausible(image, roi, image_s, None)
        pts = predicted.points(64)
        best = cfg.max_track_distance_px + cfg.gap_margin_per_frame * predicted.a * max(
            gap_frames - 1, 0
        )
        chosen: tuple[Ellipse, int] | None = None
        for e, p in found:
            d = float(np.mean(np.abs(_distance(pts, e))))
            if d < best:
                chosen, best = (e, p), d
        if chosen is None:
            return []
        larger = self._larger_concentric(image, image_s, chosen[0], found)
        if larger is not None:
            return [larger]
        refined = self._refine(image_s, image.gray, chosen[0], chosen[1])
        if refined is None:
            return []
        return [(self._observation(refined, "detected"), chosen[1])]

    def gap_window(
        self, points_px: np.ndarray, gap_frames: int, shape: tuple[int, ...]
    ) -> tuple[int, int, int, int] | None:
        """Where to acquire first after ``gap_frames`` frames without a measurement (1: the
        previous frame): the box of ``points_px`` (N, 2), the ring's outline predicted for
        this frame, grown by ``roi_margin`` plus ``gap_margin_per_frame`` per frame of the gap
        (of its major axis) and ``roi_margin_px``, clipped to the image. None when the
        prediction is off the image or the window would exceed ``gap_max_area``."""
        cfg = self.config
        if not cfg.gap_window or not np.all(np.isfinite(points_px)):
            return None
        lo, hi = points_px.min(axis=0), points_px.max(axis=0)
        a = 0.5 * float(np.max(hi - lo))
        m = (cfg.roi_margin + cfg.gap_margin_per_frame * max(gap_frames - 1, 0)) * a
        m += cfg.roi_margin_px
        x0, y0 = max(0, int(lo[0] - m)), max(0, int(lo[1] - m))
        x1, y1 = min(shape[1], math.ceil(hi[0] + m)), min(shape[0], math.ceil(hi[1] + m))
        if x1 - x0 < 2 * cfg.min_axis_px or y1 - y0 < 2 * cfg.min_axis_px:
            return None  # off the image (or nearly)
        if (x1 - x0) * (y1 - y0) > cfg.gap_max_area * shape[0] * shape[1]:
            return None
        return x0, y0, x1, y1

    def _larger_concentric(
        self,
        image: PreparedImage,
        image_s: np.ndarray,
        e0: Ellipse,
        found: list[tuple[Ellipse, int]] | None = None,
    ) -> tuple[EllipseObservation, int] | None:
        """The largest ring-like ellipse concentric with ``e0`` and up to 1.6 times its size
        (of either polarity), refined: the outer front edge is the largest of the rim's
        concentric edges. ``found``: the detections in a window around ``e0`` if already
        made."""
        if found is None:
            grown = Ellipse(cx=e0.cx, cy=e0.cy, a=e0.a * 1.3, b=e0.b * 1.3, theta=e0.theta)
            found = self._plausible(image, self._roi(grown, image.gray.shape), image_s, None)
        for e, p in found:  # largest first
            if _grown_concentric(e, e0):
                refined = self._refine(image_s, image.gray, e, p)
                if refined is not None:
                    return self._observation(refined, "detected"), p
        return None

    def _outer_by_search(
        self, image: PreparedImage, image_s: np.ndarray, e0: Ellipse
    ) -> tuple[EllipseObservation, int] | None:
        """The largest concentric edge found by refining scaled copies of ``e0`` directly on
        sub-pixel edges (either polarity, or mixed: `_edges`), for when the detector misses
        the outer edge: of a small ring next to its inner one, or of a rim in side light whose
        outer edge is brighter than the foil on one side and darker on the other. Only a
        well-covered fit counts (a closed edge all round, not foil texture)."""
        cfg = self.config
        best: tuple[EllipseObservation, int] | None = None
        for scale in cfg.outer_search_scales:
            start = Ellipse(cx=e0.cx, cy=e0.cy, a=e0.a * scale, b=e0.b * scale, theta=e0.theta)
            for pol in (+1, -1, 0):
                refined = self._refine(image_s, image.gray, start, pol)
                if refined is None or not _grown_concentric(refined[0], e0, min_growth=0.99):
                    continue
                if refined[3].shape[0] < cfg.outer_search_coverage * cfg.edge_points:
                    continue
                obs = self._observation(refined, "detected")
                if best is None or obs.axes_px.sum() > best[0].axes_px.sum() + 1.0:
                    best = (obs, pol)
        return best

    def refine_at(
        self,
        image: PreparedImage,
        e: Ellipse,
        polarity: int,
        image_s: np.ndarray | None = None,
    ) -> tuple[EllipseObservation, int] | None:
        """The edge near a given ellipse ``e`` (e.g. another camera's candidate transferred
        through 3-D), refined like a detection: with ``polarity``, else with mixed polarity;
        None where no well-supported edge lies within ``edge_search_px``. ``image_s``: the
        image smoothed for edges, if already made (`smoothed_for_edges`)."""
        if image.problem is not None:
            return None
        if image_s is None:
            image_s = self.smoothed_for_edges(image)
        for pol in dict.fromkeys((polarity, 0)):
            refined = self._refine(image_s, image.gray, e, pol)
            if refined is not None:
                return self._observation(refined, "detected"), pol
        return None

    def smoothed_for_edges(self, image: PreparedImage) -> np.ndarray:
        """The image as the sub-pixel edge search reads it (for repeated `refine_at`)."""
        return smoothed(image.gray, self.config.edges)

    def commit(self, obs: EllipseObservation, image: PreparedImage, polarity: int) -> None:
        """Keep ``obs`` as the track for the next frame."""
        ell = Ellipse.from_params(
            [obs.center_px[0], obs.center_px[1], obs.axes_px[0], obs.axes_px[1], obs.angle_rad]
        )
        age = self.track.age if self.track is not None else 0
        self.track = RingTrack(
            ellipse=ell,
            points=ell.points(self.config.track_points),
            gray8=image.gray8,
            polarity=polarity,
            age=age,
        )

    def _refine(
        self, image_s: np.ndarray, raw: np.ndarray, e: Ellipse, polarity: int
    ) -> tuple[Ellipse, np.ndarray, float, np.ndarray] | None:
        """Sub-pixel edges of the given polarity near ``e`` and a robust geometric fit
        (iteratively dropping points beyond ``outlier_sigma`` robust standard deviations).
        None if too few edges support it or the fit is poor."""
        cfg = self.config
        n = cfg.edge_points
        half = cfg.edge_search_px
        rms = np.inf
        cov = np.eye(5)
        keep = np.zeros(0, bool)
        P = np.zeros((0, 2))
        for _ in range(2):
            pts = edges_of_polarity(
                image_s, e.points(n), e.normals(n), polarity, half, cfg.edges, raw=raw
            )
            found = np.isfinite(pts[:, 0])
            if cfg.face_rise is not None and found.any():
                rise = face_rise(image_s, pts[found], e.normals(n)[found], cfg.face_depth_px)
                # a band beside the rim: its points rise above the curve's own level, by
                # more than ``face_rise`` and than the rise's own scatter (noisy edges)
                level = float(np.median(rise))
                spread = 1.4826 * float(np.median(np.abs(rise - level)))
                found[found] = rise <= level + max(cfg.face_rise, cfg.outlier_sigma * spread)
            P = pts[found]
            if P.shape[0] < cfg.min_edge_fraction * n:
                return None
            ell = e
            try:
                for _ in range(2):
                    r = _distance(P, ell)
                    sigma = max(1.4826 * float(np.median(np.abs(r))), 0.05)
                    keep = np.abs(r) < cfg.outlier_sigma * sigma
                    if keep.sum() < cfg.min_edge_fraction * n:
                        return None
                    ell, cov, rms = refine_ellipse(P[keep], ell)
            except ConicError:
                return None
            moved = float(np.abs(ell.params - e.params)[:4].max())
            e = ell
            half = 1.5  # later passes search close to the refined ellipse
            if moved < 0.05:
                break
        if rms > cfg.max_refine_rms_px or e.b < cfg.min_axis_px:
            return None
        return e, cov, rms, P[keep]


def _grown_concentric(e: Ellipse, e0: Ellipse, min_growth: float = 1.03) -> bool:
    """``e`` could be an outer concentric edge of the rim whose edge ``e0`` is: ``min_growth``
    (3 %) to 60 % larger, the same centre (within a tenth of the major axis) and shape."""
    grows = min_growth < (e.a + e.b) / (e0.a + e0.b) < 1.6
    concentric = float(np.linalg.norm(e.center - e0.center)) < 0.1 * e0.a
    return grows and concentric and abs(e.b / e.a - e0.b / e0.a) < 0.1


def _known(
    obs: EllipseObservation, found: list[tuple[EllipseObservation, int]], tol_px: float = 0.5
) -> bool:
    """``obs`` repeats one of ``found`` (centre and axes within ``tol_px``)."""
    return any(
        float(np.abs(o.center_px - obs.center_px).max()) < tol_px
        and float(np.abs(o.axes_px - obs.axes_px).max()) < tol_px
        for o, _ in found
    )


def _distance(points: np.ndarray, e: Ellipse) -> np.ndarray:
    return sampson_distance(points, e.conic())
