"""The stereo frontend of seed 000: one stereo frame in, one `FrameMeasurements` out.

Per frame (timings of each stage go into ``FrameMeasurements.timings_ms``):

1. ``undistort``: grey, [0, 1], lens distortion removed (`Undistorter`).
2. ``ring``: the ring's outer front edge in each image (`RingTracker`), then the 3-D circle
   fitted to both images' sub-pixel edge points (`refine_circle`), started from both of the
   cone's circular sections (eqs. 6-8) and kept only if consistent (residuals, radius).
3. ``panel``: panel corners (`find_panel`) and dark components (`find_components`) in each
   image around the ring.
4. ``landmarks``: stereo pairs, triangulation and track ids (`LandmarkTracker`), with
   positions predicted from the previous pose and twist.
5. ``orb``: at close range or with few landmarks, ORB features as landmarks (`OrbTracker`),
   filtered by EPnP + RANSAC against the map.
6. ``pose``: the per-frame pose in the non-cooperative target frame (`TargetFrameTracker`).

Nothing here raises on bad images (black, saturated, ring out of view): the frame yields
fewer measurements and the reasons in ``failures``. Nor on a bug: an unexpected exception
inside a stage ends that frame only, as the failure ``"<stage>: internal error: <type>:
<message>"`` (traceback at DEBUG level), and the image trackers start afresh on the next
frame.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec, rotvec_to_matrix
from satpose.datasets.sequence import Calibration, Frame
from satpose.frontend.conics import ConicError, Ellipse
from satpose.frontend.edges import smoothed
from satpose.frontend.ellipses import DetectedEllipse, EllipseDetectorConfig, detect_ellipses
from satpose.frontend.landmarks import LandmarkConfig, LandmarkTracker
from satpose.frontend.measurements import (
    Camera,
    EllipseObservation,
    FrameMeasurements,
    LandmarkKind,
    LandmarkMeasurement,
    RingMeasurement,
    exception_failure,
)
from satpose.frontend.orb import OrbConfig, OrbTracker, epnp_ransac
from satpose.frontend.panel import (
    ComponentConfig,
    CornerConfig,
    PanelTrackConfig,
    PanelTracker,
)
from satpose.frontend.pose import PoseConfig, TargetFrameTracker
from satpose.frontend.preprocess import (
    PreparedImage,
    PreprocessConfig,
    Undistorter,
    dominant_colour,
)
from satpose.frontend.rim import (
    RimFit,
    RimFitConfig,
    RimImage,
    fit_outer_rim,
    projected_observation,
)
from satpose.frontend.ring import Detector, RingConfig, RingTrack, RingTracker, contrast_scale
from satpose.frontend.ring_choice import (
    coplanar_outer,
    front_choice,
    section_image,
    transferred_ellipse,
)
from satpose.frontend.ring_depth import FrontArcsConfig, fit_front_arcs
from satpose.frontend.ring_outline import (
    OutlineConfig,
    OutlineFit,
    fit_ring_outline,
    inner_edge_points,
)
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_rms,
    circle_scale,
    cone_circle_candidates,
    refine_circle,
    tangent_basis,
    triangulate,
)

log = logging.getLogger(__name__)

RingResult = tuple[list[Circle3D], dict[str, EllipseObservation], dict[str, Ellipse]]
"""The ring stage's candidate circles (best first), ellipse observations and ellipses."""


@dataclass(frozen=True, kw_only=True)
class StereoRingConfig:
    """Checks on the 3-D ring.

    Attributes:
        max_rms_px: largest RMS distance of the edge points to the fitted circle's images.
        max_pairs: when acquiring, at most this many left/right candidate pairs are tried.
        max_radius_change: once the radius is known, a circle smaller by more than this
            fraction is rejected (an inner edge); a larger one replaces the known radius (the
            outer edge, found late).
        radius_memory: frames over which the radius estimate is averaged.
        memory_reset_frames: a circle refused only for being smaller than the remembered
            radius, seen in this many frames in a row (radii within ``max_radius_change`` of
            each other) with no ring accepted in between, is taken and the memory restarts
            from it: the remembered circle was then not the rim's outer edge (a wall's base
            or a mismatched pair taken at the first sighting, tuning seed 27: 6 % too large,
            every later frame refused), and the smaller one is the rim or its concentric,
            coplanar inner edge, whose centre and normal hold either way.
        normal_sigma_floor_deg, center_sigma_floor_m, disparity_sigma_floor_px: standard
            deviations added to the fit's normal and centre (across the line of sight; along
            it, the depth error of this disparity error) for edge biases the fit cannot see
            (measured on the rendered presets, docs/frontend.md).
        behind_sigma: a larger consistent circle behind a smaller nested one by more than
            this many standard deviations is an edge behind the rim (`ring_choice`); null:
            the largest consistent pair wins.
        transfer: carry a camera's unpaired candidates into the other camera
            (`ring_choice.transferred_ellipse`).
        transfer_min_growth: a transferred circle larger than the consistent one it was
            carried through counts (as the rim's outer edge) only if it lies in that one's
            plane and is at least this much larger (`ring_choice.coplanar_outer`): a wall's
            base or outline lies a few % outside the rim and, for a short wall far away,
            within the plane test's reach.
        sweep: when one camera's acquisition finds no ring candidate at all and the other
            does, look for the other's candidates along their epipolar lines
            (`StereoFrontend._swept`): each is carried into the other image as the circle
            its cone makes at the distances of ``sweep_range_m`` (both circular sections),
            in steps of ``sweep_step_px``, and refined on edges there.
        sweep_range_m: nearest and farthest ring distance the sweep covers [m].
        sweep_step_px: the sweep's step along the epipolar line [px] (below the refinement's
            edge search half-width, so that no disparity falls between two steps).
        min_radius_m: the smallest circle taken for the ring [m]: 0.1 m is the smallest
            standard separation ring (an 8-inch motorised light band); docking rings and
            launch-adapter rings are 0.3-0.9 m. A consistent circle smaller than that is
            a closed curve of texture (foil cells) or a component's edge on a real surface,
            which stereo reconstructs as consistently as the ring (tuning seeds 31, 32, 47:
            0.07-0.10 m circles in foil taken for rings of 0.28-0.65 m, 0.6-0.7 m off).
            0: no lower bound. A stated `known_ring` is used instead.
        colour_contrast: acquire the ring on the colour images' colour contrast too
            (`Undistorter.colour_contrast`: each pixel's colour component off the pair's
            dominant colour) and track it there while it holds; at acquisition the larger
            ring of grey and colour is taken, while tracking colour is tried when grey
            loses the ring: a dyed rim (blue or gold anodising) on a neutral panel, or a
            neutral rim on gold foil, can have almost the luminance of what surrounds it
            (tuning seed 32: a blue rim on grey foil, no ring-like ellipse in grey, its
            outer rim within 0.1 px on the colour contrast), and foil texture that hides
            the rim in grey vanishes there. Grey cameras: nothing changes.
    """

    max_rms_px: float = 0.6
    max_pairs: int = 8
    max_radius_change: float = 0.04
    radius_memory: int = 20
    memory_reset_frames: int = 3
    normal_sigma_floor_deg: float = 0.7
    center_sigma_floor_m: float = 0.003
    disparity_sigma_floor_px: float = 0.12
    known_ring: KnownRing | None = None
    behind_sigma: float | None = 3.0
    transfer: bool = True
    transfer_min_growth: float = 1.06
    sweep: bool = True
    sweep_range_m: tuple[float, float] = (1.0, 30.0)
    sweep_step_px: float = 1.5
    min_radius_m: float = 0.1
    colour_contrast: bool = True

    def __post_init__(self) -> None:
        b = self.behind_sigma
        if b is not None and not (math.isfinite(b) and b > 0):
            raise ValueError(f"stereo_ring.behind_sigma must be > 0 or null, got {b}")
        g = self.transfer_min_growth
        if not (math.isfinite(g) and g >= 1.0):
            raise ValueError(f"stereo_ring.transfer_min_growth must be >= 1, got {g}")
        lo, hi = self.sweep_range_m
        if not (0 < lo < hi and math.isfinite(hi)):
            raise ValueError(f"stereo_ring.sweep_range_m must be 0 < near < far, got {lo}, {hi}")
        if not (math.isfinite(self.sweep_step_px) and self.sweep_step_px > 0):
            raise ValueError(f"stereo_ring.sweep_step_px must be > 0, got {self.sweep_step_px}")
        if not (math.isfinite(self.min_radius_m) and self.min_radius_m >= 0):
            raise ValueError(f"stereo_ring.min_radius_m must be >= 0, got {self.min_radius_m}")
        if self.memory_reset_frames < 2:
            raise ValueError(
                f"stereo_ring.memory_reset_frames must be >= 2, got {self.memory_reset_frames}"
            )


@dataclass(frozen=True, kw_only=True)
class KnownRing:
    """A ring whose dimensions the user knows (a standard launch-adapter or docking
    interface): a prior on the 3-D circle's radius in every fit, and with the wall height the
    ring's outline modelled as that cylinder (`satpose.frontend.ring_outline`).

    Attributes:
        outer_radius_m: radius of the outer front rim [m].
        radius_sigma_m: its standard deviation (manufacturing, thermal) [m].
        wall_height_m: height of the wall's outer face, front rim to base [m], or None.
        height_sigma_m: its standard deviation [m].
        inner_radius_m: radius of the rim's inner edge [m], or None. With the wall height,
            the inner edge joins the outline where the wall's outer face shows (there the
            rim's outer edge lies beside the wall, the inner edge beside the interior).
        wall_outer_radius_m: a lipped ring's wall radius below the lip [m] (None: the
            outer radius, no lip), and ``lip_thickness_m`` the lip's thickness [m].
        edge_tolerance: a circle is taken for the rim's inner edge only if its radius,
            fitted without a prior, lies within this fraction of the inner radius (one edge's
            measured radius varies by < 1 %, docs/backend.md "Circles"); a curve of another
            size near it (a shadow inside the ring) is refused, not forced to that radius.
    """

    outer_radius_m: float
    radius_sigma_m: float = 0.001
    wall_height_m: float | None = None
    height_sigma_m: float = 0.002
    inner_radius_m: float | None = None
    wall_outer_radius_m: float | None = None
    lip_thickness_m: float = 0.0
    edge_tolerance: float = 0.01

    def __post_init__(self) -> None:
        if not (math.isfinite(self.outer_radius_m) and self.outer_radius_m > 0):
            raise ValueError(f"known_ring.outer_radius_m must be > 0, got {self.outer_radius_m}")
        if not (math.isfinite(self.radius_sigma_m) and self.radius_sigma_m > 0):
            raise ValueError(f"known_ring.radius_sigma_m must be > 0, got {self.radius_sigma_m}")
        h = self.wall_height_m
        if h is not None and not (math.isfinite(h) and h >= 0):
            raise ValueError(f"known_ring.wall_height_m must be >= 0, got {h}")
        if not (math.isfinite(self.height_sigma_m) and self.height_sigma_m > 0):
            raise ValueError(f"known_ring.height_sigma_m must be > 0, got {self.height_sigma_m}")
        for name in ("inner_radius_m", "wall_outer_radius_m"):
            r = getattr(self, name)
            if r is not None and not (math.isfinite(r) and 0 < r <= self.outer_radius_m):
                raise ValueError(f"known_ring.{name} must be > 0 and <= outer_radius_m, got {r}")
        t = self.lip_thickness_m
        if not (math.isfinite(t) and t >= 0):
            raise ValueError(f"known_ring.lip_thickness_m must be >= 0, got {t}")
        e = self.edge_tolerance
        if not (math.isfinite(e) and 0 < e < 1):
            raise ValueError(f"known_ring.edge_tolerance must be in (0, 1), got {e}")

    @property
    def lip(self) -> tuple[float, float]:
        """``(width, thickness)`` of the lip [m]: zeros without one."""
        if self.wall_outer_radius_m is None:
            return (0.0, 0.0)
        return (self.outer_radius_m - self.wall_outer_radius_m, self.lip_thickness_m)


@dataclass(frozen=True, kw_only=True)
class FrontendConfig:
    """Everything the stereo frontend does, one nested config per stage."""

    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    ellipses: EllipseDetectorConfig = field(default_factory=EllipseDetectorConfig)
    ring: RingConfig = field(default_factory=RingConfig)
    stereo_ring: StereoRingConfig = field(default_factory=StereoRingConfig)
    rim: RimFitConfig = field(default_factory=RimFitConfig)
    outline: OutlineConfig = field(default_factory=OutlineConfig)
    front_arcs: FrontArcsConfig = field(default_factory=FrontArcsConfig)
    corners: CornerConfig = field(default_factory=CornerConfig)
    components: ComponentConfig = field(default_factory=ComponentConfig)
    use_components: bool = True
    panel_tracking: PanelTrackConfig = field(default_factory=PanelTrackConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)
    orb: OrbConfig = field(default_factory=OrbConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)


class _Timer:
    """Wall time per stage [ms]; ``failed``: the stage an exception left (the innermost)."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self.failed: str | None = None

    def __call__(self, name: str) -> _Stage:
        return _Stage(self, name)


class _Stage:
    def __init__(self, timer: _Timer, name: str) -> None:
        self.timer, self.name = timer, name

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, exc_type: object, *exc: object) -> None:
        dt = (time.perf_counter() - self.t0) * 1000.0
        self.timer.ms[self.name] = self.timer.ms.get(self.name, 0.0) + dt
        if exc_type is not None and self.timer.failed is None:
            self.timer.failed = self.name


def read_stereo(
    index: int, t_s: float, read: Callable[[], tuple[np.ndarray, np.ndarray]]
) -> tuple[tuple[np.ndarray, np.ndarray] | None, FrameMeasurements | None]:
    """Read a frame's two images with ``read()`` without raising: ``((left, right), None)``,
    or ``(None, measurements)`` whose one failure note says why (``"image: <SatposeError>"``
    for an unusable file, ``"image: internal error: ..."`` for anything else, e.g. a decoder
    error on a corrupt file)."""
    try:
        return read(), None
    except SatposeError as exc:
        return None, FrameMeasurements(frame=index, t_s=t_s, failures=(f"image: {exc}",))
    except Exception as exc:
        log.debug("frame %d: reading the images raised", index, exc_info=True)
        return None, FrameMeasurements(
            frame=index, t_s=t_s, failures=(exception_failure("image", exc),)
        )


class StereoFrontend:
    """Turns stereo frames into measurements, keeping the tracking state between frames.

    Args:
        calibration: a stereo calibration (sequence format).
        config: the frontend config.
        detector: an ellipse detector ``(gray8, roi) -> candidates``; default: the
            arc-support detector `satpose.frontend.ellipses.detect_ellipses`.
    """

    def __init__(
        self,
        calibration: Calibration,
        config: FrontendConfig | None = None,
        detector: Detector | None = None,
    ) -> None:
        self.config = config or FrontendConfig()
        cfg = self.config
        self.calibration = calibration
        self.rig = StereoRig.from_calibration(calibration)
        self.undistort = {
            cam: Undistorter(calibration.camera(cam), cfg.preprocess) for cam in ("left", "right")
        }
        det = detector or (lambda gray8, roi: detect_ellipses(gray8, cfg.ellipses, roi))
        mixed = (
            partial(_mixed_detection, config=cfg.ellipses, bright_level=cfg.ring.mixed_bright_level)
            if detector is None and cfg.ring.mixed_acquisition
            else None
        )
        self.rings = {
            cam: RingTracker(Camera(cam), det, cfg.ring, mixed) for cam in ("left", "right")
        }
        self.panels = {
            cam: PanelTracker(cfg.corners, cfg.components, cfg.panel_tracking)
            for cam in ("left", "right")
        }
        self.landmarks = LandmarkTracker(self.rig, cfg.landmarks)
        self.orb = OrbTracker(self.rig, cfg.orb)
        self.target = TargetFrameTracker(config=cfg.pose)
        self._history: list[tuple[float, Rigid3]] = []
        self._radii: list[float] = []
        # radii of circles refused only by the radius memory: this frame's, and one list per
        # earlier frame in a row without a ring (`StereoRingConfig.memory_reset_frames`)
        self._refused_now: list[float] = []
        self._refused: list[list[float]] = []
        self._ring_channel = "grey"  # the images the ring is tracked on: "grey" or "colour"
        self._last_ring: tuple[int, float, RingMeasurement] | None = None  # index, t_s, ring
        self._previous_index: int | None = None  # the frame before this one that came in
        self._index: int | None = None

    # ------------------------------------------------------------------------------------------

    def process_frame(self, frame: Frame) -> FrameMeasurements:
        """Measure one frame of a loaded sequence (an unreadable image is a failure, not an
        exception)."""
        images, failed = read_stereo(frame.index, frame.t_s, lambda: (frame.left(), frame.right()))
        if images is None:
            assert failed is not None
            return failed
        return self.process(frame.index, frame.t_s, *images)

    def process(
        self, index: int, t_s: float, left: np.ndarray, right: np.ndarray
    ) -> FrameMeasurements:
        """Measure one stereo frame (never raises: an unexpected exception in a stage becomes
        that frame's failure ``"<stage>: internal error: ..."`` and resets the trackers).

        Args:
            index, t_s: frame index and time [s].
            left, right: raw images as stored (grey or BGR, 8 or 16 bit, with distortion).
        """
        timer = _Timer()
        self._previous_index, self._index = self._index, index
        try:
            return self._process(index, t_s, left, right, timer)
        except Exception as exc:
            stage = timer.failed or "frontend"
            log.debug("frame %d: stage %s raised", index, stage, exc_info=True)
            self.reset_tracking()
            return FrameMeasurements(
                frame=index,
                t_s=t_s,
                failures=(exception_failure(stage, exc),),
                timings_ms=timer.ms,
            )

    def reset_tracking(self) -> None:
        """Forget the image tracks (ring, panel, ORB): the next frame acquires afresh. The
        target-frame map and the last poses are kept: they were measured before the failure,
        and the prediction from them is what tells a symmetric panel's half turns apart when
        the landmarks are re-identified (`TargetFrameTracker.relocalize`)."""
        for ring in self.rings.values():
            ring.reset()
        self._ring_channel = "grey"
        for panel in self.panels.values():
            panel.reset()
        self.orb.reset()
        self.landmarks.reset()

    def _process(
        self, index: int, t_s: float, left: np.ndarray, right: np.ndarray, timer: _Timer
    ) -> FrameMeasurements:
        failures: list[str] = []
        self._refused_now = []
        with timer("undistort"):
            try:
                imgs = {
                    "left": self.undistort["left"](left),
                    "right": self.undistort["right"](right),
                }
            except SatposeError as exc:
                return FrameMeasurements(
                    frame=index, t_s=t_s, failures=(f"image: {exc}",), timings_ms=timer.ms
                )
        for cam, img in imgs.items():
            if img.problem is not None:
                failures.append(f"image ({cam}): {img.problem}")
        predicted = self._predict(t_s)
        with timer("ring"):
            outlines, gap = self._gap_outlines(index, t_s)
            circles, obs, ellipses = self._ring(
                imgs, {"left": left, "right": right}, failures, outlines, gap, timer
            )
        landmarks: list[LandmarkMeasurement] = []
        with timer("panel"):
            detections = self._panel(imgs, ellipses, failures)
        with timer("landmarks"):
            depth = float(circles[0].center[2]) if circles else None
            pred_px = self._predicted_pixels(
                predicted,
                {tid: None for tid, mp in self.target.map.items() if mp.kind != LandmarkKind.ORB},
            )
            landmarks += self.landmarks.update(
                imgs["left"].gray8, imgs["right"].gray8, detections, depth, pred_px
            )
        if self._need_orb(circles, landmarks):
            with timer("orb"):
                # no circle: the ellipses did not agree, and one of them may lie anywhere;
                # the features are then taken over the whole lit target
                masks = ellipses if circles else {}
                landmarks += self._orb(imgs, masks, depth, predicted, failures)
        else:
            self.orb.reset()
        with timer("ring"):
            ring = self._choose_ring(circles, obs, landmarks, predicted, failures)
        if ring is not None:
            self._last_ring = (index, t_s, ring)
        keep = self.config.stereo_ring.memory_reset_frames - 1
        self._refused = [] if ring is not None else [*self._refused, self._refused_now][-keep:]
        with timer("pose"):
            if (
                ring is not None
                and self.target.anchor_id is not None
                and not any(lm.track_id in self.target.map for lm in landmarks)
            ):
                mapping = self.target.relocalize(ring, landmarks, predicted)
                if mapping:
                    self.landmarks.rename(mapping)
                    landmarks = [
                        replace(lm, track_id=mapping.get(lm.track_id, lm.track_id))
                        for lm in landmarks
                    ]
            pose, reason = self.target.update(ring, landmarks)
            if reason is not None:
                failures.append(reason)
        if pose is not None:
            self._history = [*self._history[-1:], (t_s, pose.left_cam_from_target)]
        return FrameMeasurements(
            frame=index,
            t_s=t_s,
            ring=ring,
            landmarks=tuple(landmarks),
            pose=pose,
            failures=tuple(failures),
            timings_ms=timer.ms,
        )

    # -- prediction -------------------------------------------------------------------------------

    def _predict(self, t_s: float) -> Rigid3 | None:
        """The pose at ``t_s`` extrapolated at constant twist from the last two poses."""
        if len(self._history) < 2:
            return self._history[-1][1] if self._history else None
        (t0, T0), (t1, T1) = self._history
        if t1 <= t0:
            return T1
        d = T0.inverse() @ T1
        s = (t_s - t1) / (t1 - t0)
        if s > 5:  # too long since the last pose: do not extrapolate far
            return None
        step = Rigid3(R=rotvec_to_matrix(matrix_to_rotvec(d.R) * s), t=d.t * s)
        return T1 @ step

    def _predicted_pixels(
        self, predicted: Rigid3 | None, tracks: dict
    ) -> dict[int, tuple[np.ndarray, np.ndarray]] | None:
        if predicted is None:
            return None
        # every mapped track in one projection (ORB re-identification asks for thousands)
        ids = [tid for tid in tracks if tid in self.target.map]
        if not ids:
            return {}
        P = np.array([self.target.map[tid].position for tid in ids])
        pl, pr = self.rig.project(predicted.apply(P))
        return {tid: (pl[k], pr[k]) for k, tid in enumerate(ids)}

    # -- ring -------------------------------------------------------------------------------

    def _gap_outlines(self, index: int, t_s: float) -> tuple[dict[str, np.ndarray], int]:
        """After dropped frames (frame ``index`` comes more than one after the frame this
        frontend saw before it): per camera, the ring's outline (N, 2) [px] where it is
        predicted — the last ring's circle moved by the motion predicted since (`_predict`:
        constant twist from the last two poses; without one, where it was), projected — and
        the frames since that ring. Empty without a gap: every frame of `satpose run` comes
        right after the previous one (a frame without a ring is no gap; it was looked at)."""
        previous = self._previous_index
        if self._last_ring is None or previous is None or index - previous <= 1:
            return {}, 0
        last_index, last_t, ring = self._last_ring
        gap = index - last_index
        if not self.config.ring.gap_window:
            return {}, gap
        u, v = tangent_basis(ring.normal)
        theta = np.linspace(0.0, 2.0 * math.pi, 32, endpoint=False)
        pts = ring.center_m + ring.radius_m * (
            np.outer(np.cos(theta), u) + np.outer(np.sin(theta), v)
        )
        predicted = self._predict(t_s)
        if predicted is not None and self._history and self._history[-1][0] == last_t:
            pts = (predicted @ self._history[-1][1].inverse()).apply(pts)
        if np.any(pts[:, 2] <= 0):  # behind a camera: no prediction to look at
            return {}, gap
        left, right = self.rig.project(pts)
        return {"left": left, "right": right}, gap

    def _ring(
        self,
        imgs: dict[str, PreparedImage],
        raw: dict[str, np.ndarray],
        failures: list[str],
        outlines: dict[str, np.ndarray],
        gap: int,
        timer: _Timer,
    ) -> RingResult:
        """`_ring_in` on the images the ring is tracked on (grey, or colour contrast), then,
        if that finds no ring, on the other ones (`StereoRingConfig.colour_contrast`; colour
        images only). When neither camera is tracking (acquisition), both kinds are tried
        and `_better_channel` chooses: a closed curve in foil texture can make a consistent
        small circle in grey while the rim shows only in colour (tuning seed 24: a 0.14 m
        curve in amber foil inside a dark blue 0.37 m rim). The failures reported are those
        of the grey images when neither finds the ring, and those of colour that differ."""
        order = ["grey", "colour"] if self._ring_channel == "grey" else ["colour", "grey"]
        acquiring = all(t.track is None for t in self.rings.values())
        # per channel tried: its failure notes, its result and the tracks it left
        tried: dict[str, tuple[list[str], RingResult, dict[str, RingTrack | None]]] = {}
        for channel in order:
            images = self._ring_images(channel, imgs, raw, timer)
            if images is None:
                continue
            if channel != self._ring_channel:
                for tracker in self.rings.values():
                    tracker.reset()  # the tracks follow edges of the other images
                self._ring_channel = channel
            notes: list[str] = []
            found = self._ring_in(images, notes, outlines, gap, timer)
            if found[0] and not acquiring:
                failures += notes
                return found
            tried[channel] = (notes, found, {cam: t.track for cam, t in self.rings.items()})
        rings = {c: v[1][0][0] for c, v in tried.items() if v[1][0]}
        if rings:
            channel = self._better_channel(rings)
            notes, found, tracks = tried[channel]
            for cam, tracker in self.rings.items():
                tracker.track = tracks[cam]
            self._ring_channel = channel
            failures += notes
            return found
        self._ring_channel = "grey"
        notes, found, _ = tried["grey"]
        failures += notes
        if "colour" in tried:  # what colour saw, where it differs (e.g. a refused circle)
            failures += [f"{n} (colour contrast)" for n in tried["colour"][0] if n not in notes]
        return found

    def _better_channel(self, rings: dict[str, Circle3D]) -> str:
        """Of the rings acquired on grey and on colour contrast, the channel to take: the
        larger ring where the radii differ by more than ``max_radius_change`` (another,
        larger curve: acquisition's rule), else the one measured more precisely (the
        smaller centre covariance: one curve, seen with less noise on one of them)."""
        if len(rings) == 1:
            return next(iter(rings))
        by_size = sorted(rings, key=lambda c: rings[c].radius)
        small, large = rings[by_size[0]], rings[by_size[-1]]
        if large.radius > small.radius * (1 + self.config.stereo_ring.max_radius_change):
            return by_size[-1]
        return min(rings, key=lambda c: float(np.trace(rings[c].covariance[:3, :3])))

    def _ring_images(
        self,
        channel: str,
        imgs: dict[str, PreparedImage],
        raw: dict[str, np.ndarray],
        timer: _Timer,
    ) -> dict[str, PreparedImage] | None:
        """The images of ``channel``: ``imgs`` for "grey"; for "colour", both cameras'
        colour contrast, or None (grey cameras, a colourless scene, switched off)."""
        if channel == "grey":
            return imgs
        if not self.config.stereo_ring.colour_contrast:
            return None
        with timer("colour_contrast"):
            out = {}
            dominant = dominant_colour(list(raw.values()))
            for cam, image in raw.items():
                c = self.undistort[cam].colour_contrast(image, dominant)
                if c is None or c.problem is not None:
                    return None
                out[cam] = c
        return out

    def _ring_in(
        self,
        imgs: dict[str, PreparedImage],
        failures: list[str],
        outlines: dict[str, np.ndarray],
        gap: int,
        timer: _Timer,
    ) -> RingResult:
        """Ring ellipses in both images and the candidate 3-D circles they admit (the cone's
        two-fold ambiguity survives a short baseline: both are kept, best fit first).

        A camera that is tracking follows its track; one that is not acquires candidates,
        and the largest pair that forms one consistent 3-D circle is taken. After a gap of
        ``gap`` frames (``outlines``: `_gap_outlines`) a camera looks where the ring is
        predicted (`RingTracker.reacquire`) instead of following its track; it acquires
        over the whole image when that finds nothing, or when what it found forms no
        circle. When acquisition finds no consistent circle, a fallback pass of either
        polarity with contrast-relative thresholds adds candidates (`RingTracker.acquire`
        with ``mixed=True``, `RingConfig.mixed_acquisition`)."""
        options: dict[str, list[tuple[EllipseObservation, int]]] = {}
        windowed = []
        for cam in ("left", "right"):
            tracker = self.rings[cam]
            if cam in outlines:
                # after a gap: Lucas-Kanade from an image that many frames back finds the rim
                # rarely, and a wrong edge sometimes; the 3-D prediction replaces it
                tracker.reset()
            if tracker.track is not None:
                followed, why = tracker.follow(imgs[cam])
                if followed is not None:
                    options[cam] = [followed]
                    continue
                failures.append(why or f"ring ({cam}): lost")
                tracker.reset()
            options[cam] = []
            if cam in outlines:
                with timer("ring_reacquire"):
                    options[cam] = tracker.reacquire(imgs[cam], outlines[cam], gap)
                if options[cam]:
                    windowed.append(cam)
            if not options[cam]:
                options[cam] = tracker.acquire(imgs[cam])
        acquired = any(self.rings[cam].track is None for cam in options)
        circles, chosen, last_error = self._pair(options, imgs if acquired else None)
        if not circles and windowed:  # not near the prediction: the whole image after all
            for cam in windowed:
                options[cam] = self.rings[cam].acquire(imgs[cam])
            circles, chosen, last_error = self._pair(options, imgs)
        if not circles and acquired:
            # no consistent ring of one polarity: a rim whose edge changes sign along the
            # perimeter (sunlit foil on one side, space or shadow on the other) closes only
            # when arcs of both signs are linked (`RingConfig.mixed_acquisition`)
            more = False
            for cam in options:
                if self.rings[cam].track is None:
                    new = self.rings[cam].acquire(imgs[cam], mixed=True, known=options[cam])
                    options[cam] = [*options[cam], *new]
                    more = more or bool(new)
            if more:
                circles, chosen, error = self._pair(options, imgs)
                last_error = error or last_error
                if circles:
                    circles, chosen = self._one_locator(circles, chosen, imgs)
        if not circles and acquired and self.config.stereo_ring.sweep:
            # one camera found candidates, the other nothing at all: its detector missed the
            # ring (a thin dark rim on busy foil); look along the epipolar lines instead
            with timer("ring_sweep"):
                circles, chosen = self._swept(options, imgs)
        if not circles:
            failures += [
                f"ring ({cam}): no ring-like ellipse found" for cam, o in options.items() if not o
            ]
            if last_error is not None:
                failures.append(f"ring: {last_error}")
            for tracker in self.rings.values():
                tracker.reset()
            obs = {cam: opts[0][0] for cam, opts in options.items() if opts}
        else:
            if self.config.outline.enabled or self._height_prior() is not None:
                circles, chosen = self._ring_outline(circles, imgs, chosen, failures)
            if self.config.rim.enabled:
                circles, chosen = self._outer_rim(circles, imgs, chosen, failures)
            for cam, (o, pol) in chosen.items():
                self.rings[cam].commit(o, imgs[cam], pol)
            obs = {cam: o for cam, (o, _) in chosen.items()}
        ellipses = {
            cam: Ellipse.from_params(
                [o.center_px[0], o.center_px[1], o.axes_px[0], o.axes_px[1], o.angle_rad]
            )
            for cam, o in obs.items()
        }
        return circles, obs, ellipses

    def _pair(
        self,
        options: dict[str, list[tuple[EllipseObservation, int]]],
        imgs: dict[str, PreparedImage] | None = None,
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]], Exception | None]:
        """The left/right candidate pair that makes the ring's outer front rim: of the pairs
        that make one consistent 3-D circle, the largest that no smaller consistent circle
        shows to lie behind the ring's front (`satpose.frontend.ring_choice`); its circles
        and the pair, or no circle and the last pair's error. With ``imgs`` (acquisition),
        candidates that found no partner are first carried into the other camera through
        the depth of a consistent circle (`_transferred`)."""
        cfg = self.config.stereo_ring
        last_error: Exception | None = None
        pairs = sorted(
            ((lo, ro) for lo in options["left"] for ro in options["right"]),
            key=lambda p: -float(p[0][0].axes_px.sum() + p[1][0].axes_px.sum()),
        )
        found: list[tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]] = []
        for lo, ro in pairs[: cfg.max_pairs]:
            try:
                circles = self._circles(lo[0], ro[0])
            except (GeometryFailure, ConicError, np.linalg.LinAlgError) as exc:
                last_error = exc
                continue
            found.append((circles, {"left": lo, "right": ro}))
            if cfg.behind_sigma is None:
                break  # the largest consistent pair wins
        if not found:
            return [], {}, last_error
        if imgs is not None and cfg.behind_sigma is not None and cfg.transfer:
            found += self._transferred(options, found, imgs)
        circles, pair = self._front_of(found)
        return circles, pair, None

    def _one_locator(
        self,
        circles: list[Circle3D],
        chosen: dict[str, tuple[EllipseObservation, int]],
        imgs: dict[str, PreparedImage],
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]:
        """A pair whose edges one camera locates with both signs (polarity 0) and the other
        with one sign, refined with both signs in both cameras: the ring's depth is in the
        disparity of its edges, and two edge locators can place one edge a few tenths of a
        pixel apart (tuning seed 2: the ring 1-5 cm too close over ten frames until both
        cameras used one). Kept as it was if the other camera finds no such edge or the pair
        is then no consistent circle."""
        pols = {cam: pol for cam, (_, pol) in chosen.items()}
        if (pols["left"] == 0) == (pols["right"] == 0):
            return circles, chosen
        cam = "left" if pols["left"] != 0 else "right"
        o = chosen[cam][0]
        e = Ellipse.from_params([*o.center_px, *o.axes_px, o.angle_rad])
        again = self.rings[cam].refine_at(imgs[cam], e, 0)
        if again is None:
            return circles, chosen
        pair = {**chosen, cam: again}
        try:
            return self._circles(pair["left"][0], pair["right"][0]), pair
        except (GeometryFailure, ConicError, np.linalg.LinAlgError):
            return circles, chosen

    def _transferred(
        self,
        options: dict[str, list[tuple[EllipseObservation, int]]],
        found: list[tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]],
        imgs: dict[str, PreparedImage],
    ) -> list[tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]]:
        """Consistent pairs made of a camera's candidate that paired with nothing and the
        edge found where it falls in the other camera at the depth of the largest consistent
        circle (`transferred_ellipse`, `RingTracker.refine_at`): circles smaller than that
        one (the rim inside an edge that may lie behind it), and larger ones in its plane
        around it (its outer edge: `coplanar_outer`)."""
        cfg = self.config.stereo_ring
        assert cfg.behind_sigma is not None
        used = {id(p[cam]) for _, p in found for cam in ("left", "right")}
        reference = found[0][0][0]
        out = []
        for src, dst in (("left", "right"), ("right", "left")):
            for cand in options[src]:
                if id(cand) in used:
                    continue
                try:
                    e = transferred_ellipse(self.rig, cand[0].conic, Camera(src), reference)
                    other = self.rings[dst].refine_at(imgs[dst], e, cand[1])
                    if other is None:
                        continue
                    pair = {src: cand, dst: other}
                    circles = self._circles(pair["left"][0], pair["right"][0])
                except (GeometryFailure, ConicError, np.linalg.LinAlgError):
                    continue
                if circles[0].radius < reference.radius or coplanar_outer(
                    reference, circles[0], cfg.behind_sigma, cfg.transfer_min_growth
                ):
                    # a smaller circle can show the reference to lie behind the rim; a larger
                    # one from a transferred edge only counts in the reference's own plane
                    # around it (the rim's outer edge, that this camera's detector missed):
                    # an edge beside the transferred one is stereo-consistent too, but at
                    # another depth, off that plane
                    out.append((circles, pair))
        return out

    def _swept(
        self,
        options: dict[str, list[tuple[EllipseObservation, int]]],
        imgs: dict[str, PreparedImage],
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]:
        """The ring when one camera's acquisition found candidates and the other none: each
        candidate (at most three, largest first) carried into the other image as the circle
        its cone makes at the distances of ``sweep_range_m`` (`_sweep_images`: both circular
        sections, the image's centre moving along the epipolar line in steps of
        ``sweep_step_px``), and refined on edges at every step; per candidate the consistent
        pair with the smallest RMS, and of those the one `_pair`'s rule takes (the largest
        not shown to lie behind the ring's front). Nothing when no pair is consistent."""
        found: list[tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]] = []
        for src, dst in (("left", "right"), ("right", "left")):
            if options.get(dst) or not options.get(src):
                continue
            image_s = self.rings[dst].smoothed_for_edges(imgs[dst])
            for cand, pol in options[src][:3]:
                best: tuple[float, list[Circle3D], dict[str, tuple[EllipseObservation, int]]]
                best = (math.inf, [], {})
                for e in self._sweep_images(Camera(src), cand):
                    other = self.rings[dst].refine_at(imgs[dst], e, pol, image_s)
                    if other is None:
                        continue
                    pair = {src: (cand, pol), dst: other}
                    try:
                        circles = self._circles(pair["left"][0], pair["right"][0])
                    except (GeometryFailure, ConicError, np.linalg.LinAlgError):
                        continue
                    rms = circle_rms(
                        self.rig,
                        circles[0],
                        pair["left"][0].edge_points_px,
                        pair["right"][0].edge_points_px,
                    )
                    if rms < best[0]:
                        best = (rms, circles, pair)
                if best[1]:
                    found.append((best[1], best[2]))
        if not found:
            return [], {}
        return self._front_of(found)

    def _front_of(
        self, found: list[tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]]
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]:
        """Of consistent pairs (their circles best first, and the pair), the one whose
        circle is the ring's outer front rim: the largest that no smaller one shows to lie
        behind the ring's front (`front_choice`; without ``behind_sigma``, the largest)."""
        found = sorted(found, key=lambda f: -f[0][0].radius)
        behind = self.config.stereo_ring.behind_sigma
        k = 0 if behind is None else front_choice([f[0][0] for f in found], behind)
        return found[k][0], found[k][1]

    def _sweep_images(self, src: Camera, cand: EllipseObservation) -> list[Ellipse]:
        """The images in the other camera of the circles that ``cand``'s cone makes at the
        distances of ``sweep_range_m``, for both circular sections, in steps that move the
        image's centre by ``sweep_step_px``: a tilted ring seen close has a different shape
        in each camera (tuning seed 12, 3 m: semi-minor axes 62 and 75 px), which the
        candidate's own shape shifted along the epipolar line would miss."""
        cfg = self.config.stereo_ring
        dst = Camera.RIGHT if src is Camera.LEFT else Camera.LEFT
        K_src = self.rig.intrinsics(src)
        left_from_src = self.rig.cam_from_left(src).inverse()
        near, far = cfg.sweep_range_m
        out: list[Ellipse] = []
        try:
            sections = cone_circle_candidates(K_src, cand.conic)
        except GeometryFailure:
            return out
        for n, d in sections:
            try:
                per_radius = circle_scale(K_src, cand.conic, n, d)
            except GeometryFailure:
                continue
            ends = self.rig.project_into(dst, left_from_src.apply(np.outer([near, far], d)))
            steps = max(
                2, math.ceil(float(np.linalg.norm(ends[0] - ends[1])) / cfg.sweep_step_px) + 1
            )
            for z in 1.0 / np.linspace(1.0 / far, 1.0 / near, steps):
                try:
                    out.append(section_image(self.rig, src, n, d, per_radius, float(z)))
                except GeometryFailure:
                    continue
        return out

    def _radius_prior(
        self, radius: float | None = None, depth_m: float | None = None
    ) -> tuple[float, float] | None:
        """A known ring's radius prior ``(radius, sigma)``: its outer rim's, or with a known
        inner radius the edge's nearest to ``radius`` (a circle fitted to the rim's inner
        edge is that edge, concentric and coplanar with the outer one) when the two edges lie
        apart by more than the ring's edge search (`RingConfig.edge_search_px`, either side)
        in an image at ``depth_m``: nearer, an edge's points mix both. None: no known ring."""
        known = self.config.stereo_ring.known_ring
        if known is None:
            return None
        r_in, r_out = known.inner_radius_m, known.outer_radius_m
        if radius is not None and r_in is not None and abs(radius - r_in) < abs(radius - r_out):
            reach_px = 2 * self.config.ring.edge_search_px
            if depth_m is None or (r_out - r_in) * self.rig.K_left[0, 0] > reach_px * depth_m:
                return (r_in, known.radius_sigma_m)
        return (r_out, known.radius_sigma_m)

    def _on_inner_edge(self, circle: Circle3D) -> bool:
        """Whether ``circle`` is a known ring's inner edge (`_radius_prior`)."""
        return self._is_inner_prior(self._radius_prior(circle.radius))

    def _is_inner_prior(self, prior: tuple[float, float] | None) -> bool:
        """Whether a `_radius_prior` is a known ring's inner edge's (not its outer rim's)."""
        known = self.config.stereo_ring.known_ring
        return known is not None and prior is not None and prior[0] != known.outer_radius_m

    def _height_prior(self) -> tuple[float, float] | None:
        known = self.config.stereo_ring.known_ring
        if known is None or known.wall_height_m is None:
            return None
        return (known.wall_height_m, known.height_sigma_m)

    def _ring_outline(
        self,
        circles: list[Circle3D],
        imgs: dict[str, PreparedImage],
        chosen: dict[str, tuple[EllipseObservation, int]],
        failures: list[str],
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]:
        """Each candidate circle refitted as the front rim of a cylinder whose outline the
        ring's edge points follow (`satpose.frontend.ring_outline`). The ellipses become the
        rim's images with the edge points on the outline's rim arcs. A candidate whose fit
        fails keeps its circle, and the frame says so. A known ring with its inner radius
        (and wall height) is refitted with the rim's inner edge (`inner_edge_points`)."""
        cfg = self.config
        if self._on_inner_edge(circles[0]):
            return circles, chosen  # a known ring's inner edge: no outline to fit
        pts = (chosen["left"][0].edge_points_px, chosen["right"][0].edge_points_px)
        known = cfg.stereo_ring.known_ring
        fits: list[tuple[float, Circle3D, OutlineFit]] = []
        reasons = []
        radius_prior, height_prior = self._radius_prior(), self._height_prior()
        lip = (0.0, 0.0) if known is None else known.lip

        def fit(circ: Circle3D, inner: tuple[np.ndarray, np.ndarray, float] | None) -> OutlineFit:
            return fit_ring_outline(
                self.rig,
                circ,
                pts[0],
                pts[1],
                cfg.outline,
                radius_prior=radius_prior,
                height_prior=height_prior,
                inner=inner,
                lip=lip,
            )

        images_s: tuple[np.ndarray, np.ndarray] | None = None  # smoothed once, if needed
        for circ in circles:
            try:
                outline = fit(circ, None)
                if known is not None and known.inner_radius_m is not None and height_prior:
                    width = known.outer_radius_m - known.inner_radius_m
                    if images_s is None:
                        images_s = (
                            smoothed(imgs["left"].gray, cfg.ring.edges),
                            smoothed(imgs["right"].gray, cfg.ring.edges),
                        )
                    inner = inner_edge_points(
                        self.rig, outline.circle, width, images_s, cfg.ring.edges
                    )
                    if min(len(p) for p in inner) >= 6:
                        outline = fit(outline.circle, (inner[0], inner[1], width))
            except (GeometryFailure, ConicError, np.linalg.LinAlgError) as exc:
                reasons.append(str(exc))
                continue
            fits.append(
                (outline.cost, _inflate(outline.circle, cfg.stereo_ring, self.rig), outline)
            )
        if not fits:
            failures.append(f"ring: {reasons[0]}; the all-edges circle was kept")
            return circles, chosen
        fits.sort(key=lambda x: x[0])
        best = fits[0][2]
        points = tuple(r if len(r) >= 6 else p for r, p in zip(best.rim_points, pts, strict=True))
        new_chosen = self._reprojected(fits[0][1], points, best.rms_px, chosen)
        if new_chosen is None:
            return circles, chosen
        return [c for _, c, _ in fits], new_chosen

    def _outer_rim(
        self,
        circles: list[Circle3D],
        imgs: dict[str, PreparedImage],
        chosen: dict[str, tuple[EllipseObservation, int]],
        failures: list[str],
    ) -> tuple[list[Circle3D], dict[str, tuple[EllipseObservation, int]]]:
        """Each candidate circle refitted on rim points only (`satpose.frontend.rim`): the
        edges near the ring's ellipses include the wall's base and silhouettes where the wall
        is visible. The ellipses become the refitted circle's images with the rim points.
        A candidate whose refit fails keeps its all-points fit, and the frame says so."""
        cfg = self.config
        images = tuple(
            RimImage(
                image_s=smoothed(imgs[cam].gray, cfg.ring.edges),
                raw=imgs[cam].gray,
                polarity=chosen[cam][1],
            )
            for cam in ("left", "right")
        )
        if self._on_inner_edge(circles[0]):
            return circles, chosen  # a known ring's inner edge: no outer rim to refit
        prior = self._radius_prior()
        fits: list[tuple[float, Circle3D, RimFit | None]] = []
        reasons = []
        for circ in circles:
            try:
                fit = fit_outer_rim(
                    self.rig,
                    circ,
                    (images[0], images[1]),
                    cfg.ring.edges,
                    cfg.rim,
                    radius_prior=prior,
                )
            except (GeometryFailure, ConicError, np.linalg.LinAlgError) as exc:
                reasons.append(str(exc))
                fits.append((math.inf, circ, None))
                continue
            fits.append((fit.rms_px, _inflate(fit.circle, cfg.stereo_ring, self.rig), fit))
        if all(f is None for _, _, f in fits):
            failures.append(f"ring: {reasons[0]}; the all-edges circle was kept")
            return circles, chosen
        fits.sort(key=lambda x: x[0])
        best = fits[0][2]
        assert best is not None
        new_chosen = self._reprojected(fits[0][1], best.points, best.rms_px, chosen)
        if new_chosen is None:
            return circles, chosen
        return [c for _, c, f in fits if f is not None], new_chosen

    def _front_arcs(self, circle: Circle3D, obs: dict[str, EllipseObservation]) -> Circle3D:
        """The chosen circle refitted on the arcs of the two ellipses' edge points that lie
        on its plane, not behind it (`satpose.frontend.ring_depth`: a shadow, the base or
        the outline beside the rim). The ellipses stay as measured (they are what the image
        trackers follow); a circle whose refit is refused or not needed stays as it was."""
        fit = fit_front_arcs(
            self.rig,
            circle,
            obs["left"].edge_points_px,
            obs["right"].edge_points_px,
            self.config.front_arcs,
            radius_prior=self._radius_prior(circle.radius),
        )
        return circle if fit is None else _inflate(fit.circle, self.config.stereo_ring, self.rig)

    def _reprojected(
        self,
        circle: Circle3D,
        points: tuple[np.ndarray, ...],
        rms_px: float,
        chosen: dict[str, tuple[EllipseObservation, int]],
    ) -> dict[str, tuple[EllipseObservation, int]] | None:
        """The ring observations of both cameras replaced by ``circle``'s images with the
        edge points it was fitted to (left, right), polarities kept; None if its image is not
        an ellipse in a camera."""
        out = {}
        for k, cam in enumerate(("left", "right")):
            try:
                o = projected_observation(
                    self.rig, circle, Camera(cam), points[k], rms_px, chosen[cam][0].source
                )
            except GeometryFailure:
                return None
            out[cam] = (o, chosen[cam][1])
        return out

    def _circles(self, left: EllipseObservation, right: EllipseObservation) -> list[Circle3D]:
        """Both circular sections of the left cone, each refined jointly on both images' edge
        points (seed 000 eqs. 6-8 as the start), consistent ones only, best fit first."""
        cfg = self.config.stereo_ring
        R = self.rig.right_from_left.R
        cand_r = cone_circle_candidates(self.rig.K_right, right.conic)
        out: list[tuple[float, Circle3D]] = []
        small = False
        inner: float | None = None
        for n_l, d_l in cone_circle_candidates(self.rig.K_left, left.conic):
            _, d_r = min(cand_r, key=lambda c: float(np.linalg.norm(R.T @ c[0] - n_l)))
            pl = self.rig.K_left @ d_l
            pr = self.rig.K_right @ d_r
            X, _ = triangulate(self.rig, (pl[:2] / pl[2])[None], (pr[:2] / pr[2])[None])
            if not np.all(np.isfinite(X[0])):
                continue
            radius = float(
                np.linalg.norm(X[0]) / circle_scale(self.rig.K_left, left.conic, n_l, d_l)
            )
            fit = partial(
                refine_circle,
                self.rig,
                X[0],
                n_l,
                radius,
                left.edge_points_px,
                right.edge_points_px,
                iterations=6,
            )
            # a known ring: the radius of its edge nearest this start
            prior = self._radius_prior(radius, float(X[0][2]))
            try:
                if self._is_inner_prior(prior):
                    # the inner edge only if the circle is that edge by its own radius
                    assert prior is not None and cfg.known_ring is not None
                    if abs(fit().radius - prior[0]) > cfg.known_ring.edge_tolerance * prior[0]:
                        continue
                circ = fit(radius_prior=prior)
            except GeometryFailure:
                continue
            rms = circle_rms(self.rig, circ, left.edge_points_px, right.edge_points_px)
            if rms > cfg.max_rms_px:
                continue
            if (
                cfg.known_ring is None
                and self._radii
                and circ.radius < float(np.median(self._radii)) * (1 - cfg.max_radius_change)
            ):
                # smaller than the ring seen so far: an inner edge, not the outer one, unless
                # the remembered circle is stale (`StereoRingConfig.memory_reset_frames`)
                if not self._memory_is_stale(circ.radius):
                    self._refused_now.append(circ.radius)
                    inner = float(np.median(self._radii))
                    continue
                log.info(
                    "ring: a %.3f m circle in %d frames in a row, the remembered %.3f m in "
                    "none: the radius memory restarts",
                    circ.radius,
                    cfg.memory_reset_frames,
                    float(np.median(self._radii)),
                )
                self._radii = []
            if cfg.known_ring is None and circ.radius < cfg.min_radius_m:
                small = True
                continue  # a closed curve of texture or a component, not a ring
            out.append((rms, _inflate(circ, cfg, self.rig)))
        if not out and small:
            raise GeometryFailure(
                f"the two ring ellipses make a circle smaller than min_radius_m "
                f"({cfg.min_radius_m:g} m): not a ring"
            )
        if not out and inner is not None:
            raise GeometryFailure(
                f"the two ring ellipses make a circle smaller than the ring seen so far "
                f"({inner:.3f} m): taken for an inner edge"
            )
        if not out:
            raise GeometryFailure(
                "the two ring ellipses do not make one circle consistent with the ring seen so far"
            )
        out.sort(key=lambda x: x[0])
        return [c for _, c in out]

    def _memory_is_stale(self, radius: float) -> bool:
        """Whether a circle of ``radius`` that the radius memory refuses was refused in
        each of the last ``memory_reset_frames - 1`` frames too, with no ring in between,
        at a radius within ``max_radius_change`` of it."""
        cfg = self.config.stereo_ring
        need = cfg.memory_reset_frames - 1
        if len(self._refused) < need:
            return False
        return all(
            any(abs(r - radius) <= cfg.max_radius_change * radius for r in frame)
            for frame in self._refused[-need:]
        )

    def _choose_ring(
        self,
        circles: list[Circle3D],
        obs: dict[str, EllipseObservation],
        landmarks: list[LandmarkMeasurement],
        predicted: Rigid3 | None,
        failures: list[str],
    ) -> RingMeasurement | None:
        """Resolve the circle's two-fold ambiguity: the section whose normal agrees with the
        plane of the panel landmarks (they sit on the face that carries the ring), else with
        the predicted motion, else the best fit; then refitted on its front arcs
        (`front_arcs`, `_front_arcs`)."""
        if not circles:
            return None
        chosen = circles[0]
        if len(circles) > 1:
            ref = _landmark_plane_normal(landmarks, circles[0].center)
            if ref is None and predicted is not None:
                ref = predicted.R[:, 2]
            if ref is not None:
                chosen = min(circles, key=lambda c: -abs(float(c.normal @ ref)))
            else:
                failures.append(
                    "ring: normal ambiguous (no landmarks, no motion yet); "
                    "the best-fitting section was taken"
                )
        if self.config.front_arcs.enabled:
            chosen = self._front_arcs(chosen, obs)
        cfg = self.config.stereo_ring
        if self._radii and chosen.radius > float(np.median(self._radii)) * (
            1 + cfg.max_radius_change
        ):
            # A larger circle than before: the outer front edge was missed until now (the
            # rim's inner edge is concentric and coplanar, so earlier poses stay valid).
            self._radii = []
        self._radii = [*self._radii[-(cfg.radius_memory - 1) :], chosen.radius]
        return RingMeasurement(
            ellipses=(obs["left"], obs["right"]),
            center_m=chosen.center,
            normal=chosen.normal,
            radius_m=chosen.radius,
            covariance=chosen.covariance,
        )

    # -- panel landmarks ------------------------------------------------------------------------

    def _panel(
        self, imgs: dict[str, PreparedImage], ellipses: dict[str, Ellipse], failures: list[str]
    ) -> list[tuple[LandmarkKind, np.ndarray, np.ndarray]]:
        cfg = self.config
        if len(ellipses) < 2:
            for tracker in self.panels.values():
                tracker.reset()
            return []
        corners: dict[str, np.ndarray] = {}
        comps: dict[str, np.ndarray] = {}
        for cam in ("left", "right"):
            img = imgs[cam]
            image_s = smoothed(img.gray, cfg.corners.edges)
            quad, comps[cam] = self.panels[cam].update(
                img.gray, img.gray8, image_s, ellipses[cam], cfg.use_components
            )
            corners[cam] = quad.corners[quad.visible] if quad is not None else np.zeros((0, 2))
        if len(corners["left"]) == 0:
            failures.append("panel: no corners")
        out = [(LandmarkKind.CORNER, corners["left"], corners["right"])]
        if cfg.use_components:
            out.append((LandmarkKind.COMPONENT, comps["left"], comps["right"]))
        return out

    # -- ORB --------------------------------------------------------------------------------------

    def _need_orb(self, circles: list[Circle3D], landmarks: list[LandmarkMeasurement]) -> bool:
        """ORB runs at close range (the paper's s1), with few landmarks, or while the
        landmarks in view are not yet mapped (it carries the target frame until they are)."""
        cfg = self.config.orb
        if circles and float(np.linalg.norm(circles[0].center)) < cfg.use_below_range_m:
            return True
        if len(landmarks) < cfg.min_other_landmarks:
            return True
        mapped = sum(lm.track_id in self.target.map for lm in landmarks)
        return self.target.anchor_id is not None and mapped < 2

    def _orb(
        self,
        imgs: dict[str, PreparedImage],
        ellipses: dict[str, Ellipse],
        depth: float | None,
        predicted: Rigid3 | None,
        failures: list[str],
    ) -> list[LandmarkMeasurement]:
        pred = None
        if predicted is not None:
            # the previous frame's tracks, and the earlier ones to re-identify (mapped only)
            tracks = {t.track_id: None for t in self.orb.tracks}
            if self.config.orb.reidentify:
                tracks.update(dict.fromkeys(self.orb.library))
            pred = {
                tid: px[0] for tid, px in (self._predicted_pixels(predicted, tracks) or {}).items()
            }
        feats = self.orb.update(
            imgs["left"].gray8,
            imgs["right"].gray8,
            ellipses.get("left"),
            ellipses.get("right"),
            depth,
            pred,
        )
        mapped = [f for f in feats if f.track_id in self.target.map]
        if len(mapped) >= self.config.orb.min_inliers:
            P = np.array([self.target.map[f.track_id].position for f in mapped])
            px = np.array([f.left_px for f in mapped])
            res = epnp_ransac(self.rig.K_left, P, px, self.config.orb)
            if res is None:
                failures.append("orb: EPnP found no consistent pose")
            else:
                _, inliers = res
                outliers = {f.track_id for f, ok in zip(mapped, inliers, strict=True) if not ok}
                feats = [f for f in feats if f.track_id not in outliers]
        return feats


def _mixed_detection(
    gray8: np.ndarray,
    roi: tuple[int, int, int, int] | None,
    config: EllipseDetectorConfig,
    bright_level: float,
) -> list[DetectedEllipse]:
    """The ring's fallback detection (`RingConfig.mixed_acquisition`): arcs of either polarity
    linked, Canny thresholds scaled to the image's contrast (`contrast_scale`)."""
    k = contrast_scale(gray8, bright_level)
    cfg = replace(
        config,
        mixed_polarity=True,
        canny_low=config.canny_low * k,
        canny_high=config.canny_high * k,
    )
    return detect_ellipses(gray8, cfg, roi)


def _inflate(circ: Circle3D, cfg: StereoRingConfig, rig: StereoRig) -> Circle3D:
    """Add the model floors to the fit's covariance: edge biases (foil beside the rim, the
    wall, shadows) are not in the fit's noise. Normal: ``normal_sigma_floor_deg``; centre:
    ``center_sigma_floor_m`` across the line of sight, and along it the depth error of a
    ``disparity_sigma_floor_px`` disparity error (``Z^2 s_d / (f b)``)."""
    C = circ.covariance.copy()
    s_n = math.radians(cfg.normal_sigma_floor_deg)
    u, v = tangent_basis(circ.normal)
    C[3:6, 3:6] += s_n**2 * (np.outer(u, u) + np.outer(v, v))
    z = float(np.linalg.norm(circ.center))
    f_b = float(rig.K_left[0, 0]) * float(np.linalg.norm(rig.right_from_left.t))
    s_depth = max(cfg.center_sigma_floor_m, z * z * cfg.disparity_sigma_floor_px / f_b)
    los = circ.center / z
    C[:3, :3] += np.eye(3) * cfg.center_sigma_floor_m**2 + (
        s_depth**2 - cfg.center_sigma_floor_m**2
    ) * np.outer(los, los)
    return Circle3D(center=circ.center, normal=circ.normal, radius=circ.radius, covariance=C)


def _landmark_plane_normal(
    landmarks: list[LandmarkMeasurement], center: np.ndarray
) -> np.ndarray | None:
    """Normal of the plane through the corner/component landmarks (>= 3, spread around the
    ring), oriented toward the cameras; None if they do not define a plane."""
    pts = np.array(
        [lm.point_m for lm in landmarks if lm.point_m is not None and lm.kind != LandmarkKind.ORB]
    ).reshape(-1, 3)
    if len(pts) < 3:
        return None
    m = pts.mean(axis=0)
    _, s, Vt = np.linalg.svd(pts - m)
    if s[1] < 0.2 * s[0] or s[2] > 0.2 * s[1]:  # collinear, or not a plane
        return None
    n = Vt[2]
    return -n if n @ center > 0 else n
