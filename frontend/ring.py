"""The docking ring's outer front edge in one camera: selection, tracking, sub-pixel refinement.

Seed 000, section 3.1: at the first frame, the ellipse with the largest sum of axes; 16 points
on it tracked by pyramidal Lucas-Kanade; afterwards the detected ellipse nearest the tracked
points (mean distance below ``max_track_distance_px``, the paper's s2), else an ellipse fitted
to the tracked points.

A ring is a wall with height: an image shows several nearly concentric ellipses (outer and
inner front edge, the wall's base, a cast shadow). Taking the largest one mixes them, which
costs centimetres in depth. The outer front edge is the outer boundary of the bright front face
(the rim): brighter inside than outside along most of the perimeter, with the rim's inner edge
(darker inside) a little further in. Candidates are scored on exactly that, and every chosen
ellipse is refined on sub-pixel edges of the right polarity (`satpose.frontend.edges`).

When tracking is healthy the detector only searches a window around the prediction.
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
from satpose.frontend.edges import EdgeSearchConfig, edges_along_normals, smoothed
from satpose.frontend.measurements import Camera, EllipseObservation
from satpose.frontend.preprocess import PreparedImage


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
        min_tracked_points: fewer surviving LK points than this and the track is lost.
        roi_margin: the search window is the predicted ellipse's box grown by this fraction
            of its major axis plus ``roi_margin_px``.
        min_axis_px: smallest semi-minor axis accepted as a ring.
        max_axis_ratio: most elongated ellipse accepted (a / b), i.e. at most ~75 deg tilt.
        min_candidate_support: detector support below this is ignored.
        min_bright_inside: fraction of the perimeter where the band just inside must be
            brighter than the band just outside (the rim is bright).
        min_rim_ratio: smallest inner/outer size ratio of the rim searched for.
        min_rim_score: fraction of the perimeter where the rim's inner edge must be found at
            a consistent ratio (`rim_score`).
        edge_points: normals sampled for the sub-pixel refinement.
        edge_search_px: half-width of the search along each normal.
        min_edge_fraction: fraction of normals that must find an edge of the right polarity.
        max_refine_rms_px: largest accepted RMS distance of the inliers to the ellipse.
        outlier_sigma: inliers are within this many robust standard deviations.
        edges: sub-pixel edge settings.
    """

    track_points: int = 16
    lk_window_px: int = 21
    lk_levels: int = 3
    max_track_distance_px: float = 3.0
    min_tracked_points: int = 8
    roi_margin: float = 0.25
    roi_margin_px: int = 12
    min_axis_px: float = 8.0
    max_axis_ratio: float = 4.0
    min_candidate_support: float = 0.35
    min_bright_inside: float = 0.6
    min_rim_ratio: float = 0.6
    min_rim_score: float = 0.5
    edge_points: int = 360
    edge_search_px: float = 3.0
    min_edge_fraction: float = 0.5
    max_refine_rms_px: float = 0.6
    outlier_sigma: float = 3.0
    edges: EdgeSearchConfig = field(
        default_factory=lambda: EdgeSearchConfig(
            smooth_sigma_px=0.6, step_px=0.25, locate="model", model_window_px=(-2.0, 0.5)
        )
    )


@dataclass
class RingTrack:
    """Per-camera tracking state (mutable; owned by `RingTracker`)."""

    ellipse: Ellipse
    points: np.ndarray  # (n, 2) the tracked points on it
    gray8: np.ndarray  # the image they were sampled in


def bright_inside_fraction(
    image_s: np.ndarray, e: Ellipse, n: int = 72, band_px: float = 2.5
) -> float:
    """Fraction of the perimeter where the image just inside ``e`` is brighter than just
    outside (bands at ``band_px`` on each side)."""
    p = e.points(n)
    nrm = e.normals(n)
    both = np.concatenate([p - band_px * nrm, p + band_px * nrm]).astype(np.float32)
    vals = cv2.remap(
        image_s, both[:, 0:1], both[:, 1:2], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )[:, 0]
    return float(np.mean(vals[:n] > vals[n:] + 0.01))


def rim_score(
    image_s: np.ndarray, e: Ellipse, min_ratio: float, n: int = 90
) -> tuple[float, float]:
    """How much ``e`` looks like the outer edge of a bright rim: a band just inside it that is
    brighter than what lies further in, ending at an inner edge at a constant fraction of the
    size (the rim's inner edge, a concentric ellipse scaled by ``r_in / r_out``).

    Profiles run from the centre outward at scale factors ``f`` in ``[min_ratio, 1]``; for
    each angle the strongest dark-to-bright step going outward (bright rim outside it) gives
    ``f_i``.

    Returns:
        (fraction of angles whose ``f_i`` lies within 0.03 of the median, the median ratio).
    """
    f = np.linspace(min_ratio, 0.995, 48, dtype=np.float32)
    p = e.points(n) - e.center
    pos = e.center[None, None, :] + f[None, :, None] * p[:, None, :]  # (n, F, 2)
    prof = cv2.remap(
        image_s,
        pos[..., 0].astype(np.float32),
        pos[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    step = prof[:, 2:] - prof[:, :-2]  # brighter outward = rising
    k = np.argmax(step, axis=1)
    strong = step[np.arange(n), k] > 0.04
    fi = f[1:-1][k]
    if strong.sum() < n // 3:
        return 0.0, 0.0
    med = float(np.median(fi[strong]))
    # The band between the inner edge and the candidate must be bright compared with inside.
    return float(np.mean(strong & (np.abs(fi - med) < 0.03))), med


class RingTracker:
    """Finds and follows the ring's outer front edge in one camera."""

    def __init__(
        self, camera: Camera, detector: Detector, config: RingConfig | None = None
    ) -> None:
        self.camera = Camera(camera)
        self.detector = detector
        self.config = config or RingConfig()
        self.track: RingTrack | None = None
        self._raw: np.ndarray | None = None

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

    def _roi(self, e: Ellipse, shape: tuple[int, int]) -> tuple[int, int, int, int]:
        m = self.config.roi_margin * e.a + self.config.roi_margin_px
        x0 = max(0, int(e.cx - e.a - m))
        y0 = max(0, int(e.cy - e.a - m))
        x1 = min(shape[1], math.ceil(e.cx + e.a + m))
        y1 = min(shape[0], math.ceil(e.cy + e.a + m))
        return x0, y0, x1, y1

    def candidates(
        self, image: PreparedImage, roi: tuple[int, int, int, int] | None, image_s: np.ndarray
    ) -> list[Ellipse]:
        """Detected ellipses that could be the outer front edge, largest first."""
        cfg = self.config
        out = []
        for c in self.detector(image.gray8, roi):
            e = c.ellipse
            if c.support < cfg.min_candidate_support or c.polarity < 0:
                continue
            if e.b < cfg.min_axis_px or e.a / e.b > cfg.max_axis_ratio:
                continue
            if bright_inside_fraction(image_s, e) < cfg.min_bright_inside:
                continue
            if rim_score(image_s, e, cfg.min_rim_ratio)[0] < cfg.min_rim_score:
                continue
            out.append(e)
        return sorted(out, key=lambda e: -(e.a + e.b))

    def update(self, image: PreparedImage) -> tuple[EllipseObservation | None, str | None]:
        """Measure the ring in this camera's new image; returns ``(observation, None)`` or
        ``(None, reason)``. The track is kept across frames."""
        if image.problem is not None:
            self.reset()
            return None, f"ring ({self.camera.value}): image {image.problem}"
        cfg = self.config
        image_s = smoothed(image.gray, cfg.edges)
        self._raw = image.gray
        predicted = self.prediction(image)
        source = "detected"
        if predicted is None:
            self.reset()
            found = self.candidates(image, None, image_s)
            chosen = None
            for e in found:  # largest first; the first that refines cleanly wins
                if self._refine(image_s, e) is not None:
                    chosen = e
                    break
            if chosen is None:
                return None, f"ring ({self.camera.value}): no bright ellipse found"
        else:
            found = self.candidates(image, self._roi(predicted, image.gray.shape), image_s)
            pts = predicted.points(64)
            chosen = None
            best = cfg.max_track_distance_px
            for e in found:
                d = float(np.mean(np.abs(_distance(pts, e))))
                if d < best:
                    chosen, best = e, d
            if chosen is None:
                chosen, source = predicted, "tracked"
        refined = self._refine(image_s, chosen)
        if refined is None:
            self.reset()
            return None, f"ring ({self.camera.value}): weak edge support around the ellipse"
        ell, cov, rms, inliers = refined
        self.track = RingTrack(ellipse=ell, points=ell.points(cfg.track_points), gray8=image.gray8)
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
        ), None

    def _refine(
        self, image_s: np.ndarray, e: Ellipse
    ) -> tuple[Ellipse, np.ndarray, float, np.ndarray] | None:
        """Sub-pixel edges of the bright-inside boundary near ``e`` and a robust geometric fit
        (iteratively dropping points beyond ``outlier_sigma`` robust standard deviations).
        None if too few edges support it or the fit is poor."""
        cfg = self.config
        n = cfg.edge_points
        half = cfg.edge_search_px
        for _ in range(3):
            pts, _ = edges_along_normals(
                image_s, e.points(n), e.normals(n), +1, half, cfg.edges, raw=self._raw
            )
            P = pts[np.isfinite(pts[:, 0])]
            if P.shape[0] < cfg.min_edge_fraction * n:
                return None
            ell = e
            try:
                for _ in range(3):
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


def _distance(points: np.ndarray, e: Ellipse) -> np.ndarray:
    return sampson_distance(points, e.conic())
