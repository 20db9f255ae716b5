"""Measurement types: the contract between the frontend and the backend.

The frontend turns one frame into a `FrameMeasurements`; the backend turns each measurement
into factors. Everything is numpy, frozen and validated on construction (shapes, finiteness,
symmetric positive semi-definite covariances); invalid values raise `MeasurementError`.

Conventions (docs/measurements.md):

- Pixel coordinates are **undistorted** ("ideal") pixels of the camera named in the
  measurement: the frontend removes lens distortion, so a point ``X`` in camera ``c`` is
  observed at ``K_c @ X / X_z`` with calib.yaml's ``K_c``. Pixel (0, 0) is the centre of the
  top-left pixel (OpenCV).
- 3-D quantities are in the **left camera frame** [m].
- Pose covariances are 6x6 over GTSAM's Pose3 tangent ``[rotation (rad), translation (m)]``
  with right perturbation: ``T_true = T_est * Exp(xi)``.
- A frame where something fails yields fewer measurements and a reason in ``failures``,
  never an exception.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3


class MeasurementError(SatposeError):
    """A measurement was built from invalid numbers."""


INTERNAL_ERROR = "internal error"
"""Marks the failure note of a stage that raised an unexpected exception (`exception_failure`)."""


def exception_failure(stage: str, exc: BaseException) -> str:
    """The failure note of a stage that raised ``exc`` unexpectedly, for ``failures``:
    ``"<stage>: internal error: <ExceptionType>: <first line of the message>"``. The type and
    message are kept so that the bug stays findable (the traceback goes to the DEBUG log)."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else ""
    return f"{stage}: {INTERNAL_ERROR}: {type(exc).__name__}" + (f": {first}" if first else "")


def _array(value: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.array(value, dtype=float)
    if a.shape != shape:
        raise MeasurementError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise MeasurementError(f"{name}: holds NaN or infinite values")
    a.setflags(write=False)
    return a


def _covariance(value: object, n: int, name: str, rank_deficient: bool = False) -> np.ndarray:
    C = _array(value, (n, n), name)
    if not np.allclose(C, C.T, rtol=1e-6, atol=1e-12 * max(1.0, float(np.abs(C).max()))):
        raise MeasurementError(f"{name}: covariance is not symmetric")
    w = np.linalg.eigvalsh(0.5 * (C + C.T))
    if w.min() < -1e-9 * max(1.0, float(w.max())):
        raise MeasurementError(f"{name}: covariance is not positive semi-definite")
    if not rank_deficient and w.min() <= 0.0:
        raise MeasurementError(f"{name}: covariance is singular")
    return C


class Camera(StrEnum):
    """Which camera of the rig an observation comes from."""

    LEFT = "left"
    RIGHT = "right"


class LandmarkKind(StrEnum):
    """What a tracked point is on the target."""

    CORNER = "corner"  # panel corner: intersection of two panel edge lines
    COMPONENT = "component"  # centre of a small dark component (LoG blob)
    ORB = "orb"  # ORB feature (close range)


@dataclass(frozen=True, kw_only=True)
class EllipseObservation:
    """The docking ring's outer front edge seen by one camera (undistorted pixels).

    Attributes:
        camera: left or right.
        center_px: ellipse centre (2,).
        axes_px: semi-axes ``(a, b)`` with ``a >= b`` (2,).
        angle_rad: angle of the major axis from the image x axis, in ``[0, pi)``.
        conic: 3x3 symmetric conic matrix ``C`` with ``p^T C p = 0`` on the ellipse
            (homogeneous undistorted pixels), normalised to unit Frobenius norm.
        covariance: 5x5 covariance of ``[cx, cy, a, b, angle]`` [px, px, px, px, rad].
        edge_points_px: (N, 2) sub-pixel edge points the ellipse was fitted to.
        sigma_px: standard deviation of one edge point's distance to the ellipse [px].
        source: ``detected`` (ellipse detector) or ``tracked`` (fitted to LK-tracked points).
    """

    camera: Camera
    center_px: np.ndarray
    axes_px: np.ndarray
    angle_rad: float
    conic: np.ndarray
    covariance: np.ndarray
    edge_points_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    sigma_px: float = 0.3
    source: str = "detected"

    def __post_init__(self) -> None:
        object.__setattr__(self, "camera", Camera(self.camera))
        object.__setattr__(self, "center_px", _array(self.center_px, (2,), "center_px"))
        axes = _array(self.axes_px, (2,), "axes_px")
        if not (axes[0] >= axes[1] > 0):
            raise MeasurementError(f"axes_px must satisfy a >= b > 0, got {axes}")
        object.__setattr__(self, "axes_px", axes)
        if not (np.isfinite(self.angle_rad) and 0.0 <= self.angle_rad < np.pi):
            raise MeasurementError(f"angle_rad must be in [0, pi), got {self.angle_rad}")
        conic = _array(self.conic, (3, 3), "conic")
        if not np.allclose(conic, conic.T, atol=1e-9):
            raise MeasurementError("conic must be symmetric")
        object.__setattr__(self, "conic", conic)
        object.__setattr__(
            self, "covariance", _covariance(self.covariance, 5, "ellipse covariance")
        )
        pts = np.array(self.edge_points_px, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise MeasurementError("edge_points_px holds NaN or infinite values")
        pts.setflags(write=False)
        object.__setattr__(self, "edge_points_px", pts)
        if not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise MeasurementError(f"sigma_px must be positive, got {self.sigma_px}")
        if self.source not in ("detected", "tracked"):
            raise MeasurementError(f"source must be 'detected' or 'tracked', got {self.source!r}")


@dataclass(frozen=True, kw_only=True)
class RingMeasurement:
    """The docking ring: its image ellipses and the 3-D circle reconstructed from them.

    Attributes:
        ellipses: one `EllipseObservation` per camera that saw the ring.
        center_m: circle centre in the left camera frame (3,).
        normal: unit circle normal in the left camera frame, pointing out of the target's
            front face (toward the camera side: ``normal @ center_m < 0``) (3,).
        radius_m: circle radius.
        covariance: 7x7 covariance of ``[center (3), normal (3), radius]``; the normal block
            has rank 2 (no variance along the normal itself).
    """

    ellipses: tuple[EllipseObservation, ...]
    center_m: np.ndarray
    normal: np.ndarray
    radius_m: float
    covariance: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "ellipses", tuple(self.ellipses))
        object.__setattr__(self, "center_m", _array(self.center_m, (3,), "center_m"))
        n = _array(self.normal, (3,), "normal")
        if abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise MeasurementError("ring normal must be a unit vector")
        object.__setattr__(self, "normal", n)
        if not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise MeasurementError(f"radius_m must be positive, got {self.radius_m}")
        object.__setattr__(
            self, "covariance", _covariance(self.covariance, 7, "ring covariance", True)
        )


@dataclass(frozen=True, kw_only=True)
class LandmarkMeasurement:
    """A tracked point on the target seen in one or both cameras.

    Attributes:
        track_id: stable across frames for as long as the point is tracked; never reused.
        kind: corner, component or ORB feature.
        left_px: undistorted pixel in the left image (2,).
        right_px: undistorted pixel in the right image (2,), or None (left only).
        sigma_px: standard deviation of each pixel coordinate.
        point_m: triangulated point in the left camera frame (3,), or None without a right
            observation.
        covariance: 3x3 covariance of ``point_m`` propagated from ``sigma_px``, or None.
    """

    track_id: int
    kind: LandmarkKind
    left_px: np.ndarray
    right_px: np.ndarray | None = None
    sigma_px: float = 0.5
    point_m: np.ndarray | None = None
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.track_id < 0:
            raise MeasurementError(f"track_id must be >= 0, got {self.track_id}")
        object.__setattr__(self, "kind", LandmarkKind(self.kind))
        object.__setattr__(self, "left_px", _array(self.left_px, (2,), "left_px"))
        if self.right_px is not None:
            object.__setattr__(self, "right_px", _array(self.right_px, (2,), "right_px"))
        if not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise MeasurementError(f"sigma_px must be positive, got {self.sigma_px}")
        if (self.point_m is None) != (self.covariance is None):
            raise MeasurementError("point_m and covariance come together")
        if self.point_m is not None:
            object.__setattr__(self, "point_m", _array(self.point_m, (3,), "point_m"))
            object.__setattr__(
                self, "covariance", _covariance(self.covariance, 3, "landmark covariance")
            )


class PoseMethod(StrEnum):
    """How a per-frame pose was computed."""

    RING_LANDMARK = "ring+landmark"  # seed 000 eq. 9: ring + one panel landmark
    RING_LANDMARKS = "ring+landmarks"  # ring + every mapped landmark (in-plane Procrustes)
    RING_ORB = "ring+orb"  # seed 000 eq. 10: EPnP on ORB features fused with the ring
    ORB = "orb"  # EPnP on ORB features alone (ring lost)
    BRACKET = "bracket"  # seed 002: depths of the solar-panel bracket + absolute orientation


@dataclass(frozen=True, kw_only=True)
class PoseMeasurement:
    """A per-frame pose of the target (loosely coupled measurement).

    Attributes:
        left_cam_from_target: the target's pose in the left camera frame.
        covariance: 6x6 over ``[rotation, translation]`` (right perturbation).
        method: how it was computed.
    """

    left_cam_from_target: Rigid3
    covariance: np.ndarray
    method: PoseMethod

    def __post_init__(self) -> None:
        if not isinstance(self.left_cam_from_target, Rigid3):
            raise MeasurementError("left_cam_from_target must be a Rigid3")
        object.__setattr__(self, "covariance", _covariance(self.covariance, 6, "pose covariance"))
        object.__setattr__(self, "method", PoseMethod(self.method))


class SpinStatus(StrEnum):
    """Outcome of one spin-rate estimate (seed 001): ``ok`` or why it was refused."""

    OK = "ok"
    TOO_FEW_SAMPLES = "too-few-samples"  # fewer usable frames in the window than required
    TOO_SLOW = "too-slow"  # the angle's period is not short enough for the window
    ALIASING = "aliasing"  # the rate is within the noise of a fold (or above the stated prior)
    AMBIGUOUS = "ambiguous"  # several rates fit equally well: all listed in ``candidates_rad_s``
    GEOMETRY = "geometry"  # the angle does not show the spin (view near the spin plane, ...)
    NO_FIT = "no-fit"  # the least-squares fit failed or moved away from the spectral peak


@dataclass(frozen=True, kw_only=True)
class SpinRateMeasurement:
    """The target's spin rate from one camera over a window of frames (seed 001).

    The rate is the magnitude of the angular velocity, ``|omega|`` (any frame: the magnitude is
    frame-free), averaged over the window; its sign (sense of rotation) is not observed. Only
    rates below ``90 deg * frame rate`` are unambiguous (the silhouette's angle repeats every
    half turn), see docs/spin.md.

    Attributes:
        rate_rad_s: spin rate ``|omega|`` [rad/s], >= 0; NaN when refused without a candidate.
        sigma_rad_s: its standard deviation [rad/s] (from the fit residuals); NaN when refused
            without a candidate.
        status: ``ok`` or the kind of refusal (`SpinStatus`).
        reason: why it was refused (one sentence); empty when ``ok``.
        window_start_s, window_end_s: times of the first and last frame of the window [s].
        samples: frames in the window whose angle was usable.
        candidates_rad_s: ``ambiguous`` only: every rate [rad/s] that explains the window
            equally well (sorted, at least two; ``rate_rad_s`` is then NaN and ``sigma_rad_s``
            the standard deviation each candidate has); empty otherwise.
    """

    rate_rad_s: float
    sigma_rad_s: float
    status: SpinStatus
    window_start_s: float
    window_end_s: float
    samples: int
    reason: str = ""
    candidates_rad_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", SpinStatus(self.status))
        cands = tuple(sorted(float(c) for c in self.candidates_rad_s))
        object.__setattr__(self, "candidates_rad_s", cands)
        if self.status is SpinStatus.AMBIGUOUS:
            if len(cands) < 2 or not all(np.isfinite(c) and c >= 0 for c in cands):
                raise MeasurementError(
                    f"an ambiguous spin rate needs at least two finite candidates >= 0, got {cands}"
                )
        elif cands:
            raise MeasurementError(f"only an ambiguous spin rate lists candidates ({self.status})")
        object.__setattr__(self, "rate_rad_s", float(self.rate_rad_s))
        object.__setattr__(self, "sigma_rad_s", float(self.sigma_rad_s))
        if not (np.isfinite(self.window_start_s) and np.isfinite(self.window_end_s)):
            raise MeasurementError("spin window times must be finite")
        if self.window_end_s < self.window_start_s:
            raise MeasurementError(
                f"spin window ends ({self.window_end_s} s) before it starts "
                f"({self.window_start_s} s)"
            )
        if self.samples < 0:
            raise MeasurementError(f"spin samples must be >= 0, got {self.samples}")
        if self.status is SpinStatus.OK:
            if not (np.isfinite(self.rate_rad_s) and self.rate_rad_s >= 0):
                raise MeasurementError(f"spin rate must be finite and >= 0, got {self.rate_rad_s}")
            if not (np.isfinite(self.sigma_rad_s) and self.sigma_rad_s > 0):
                raise MeasurementError(
                    f"spin sigma must be finite and positive, got {self.sigma_rad_s}"
                )
            if self.reason:
                raise MeasurementError("an accepted spin rate carries no refusal reason")
        else:
            if not self.reason:
                raise MeasurementError(f"a refused spin rate ({self.status}) needs a reason")
            for name in ("rate_rad_s", "sigma_rad_s"):
                v = getattr(self, name)
                if not (np.isnan(v) or v >= 0):
                    raise MeasurementError(f"spin {name} must be NaN or >= 0, got {v}")

    @property
    def ok(self) -> bool:
        """True when the rate was accepted (``status == ok``)."""
        return self.status is SpinStatus.OK


@dataclass(frozen=True, kw_only=True)
class PlaneNormalMeasurement:
    """The normal of a plane of the target seen through a rectangular grid of straight lines
    on it (a solar array's cells), from the grid's two vanishing directions
    (`satpose.frontend.grid_plane.measure_grid_plane`).

    A direction in the camera frame, up to sign (the grid does not say which side is in
    front); where the plane is rigid with the rest of the target its normal is a fixed
    direction of the target frame, whatever that direction is.

    Attributes:
        normal: unit normal in the left camera frame (3,), the sign with ``normal[2] < 0``
            (toward the camera).
        sigma_rad: standard deviation of its direction [rad] (isotropic, about each axis
            perpendicular to it).
        lines: grid lines (each fitted to its segments) behind each of the two vanishing
            directions.
        skew_deg: how far the two vanishing directions are from perpendicular [deg] (a
            rectangular grid's are at 90 deg; the measurement's own check).
    """

    normal: np.ndarray
    sigma_rad: float
    lines: tuple[int, int]
    skew_deg: float

    def __post_init__(self) -> None:
        n = np.array(self.normal, dtype=float).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise MeasurementError(f"plane normal must be a finite non-zero 3-vector, got {n}")
        n = n / np.linalg.norm(n)
        object.__setattr__(self, "normal", -n if n[2] > 0 else n)
        if not (math.isfinite(self.sigma_rad) and self.sigma_rad > 0):
            raise MeasurementError(f"plane normal sigma must be > 0, got {self.sigma_rad}")
        if not math.isfinite(self.skew_deg):
            raise MeasurementError(f"plane normal skew must be finite, got {self.skew_deg}")
        object.__setattr__(self, "lines", tuple(int(k) for k in self.lines))


@dataclass(frozen=True, kw_only=True)
class FrameMeasurements:
    """Everything the frontend measured in one frame.

    Attributes:
        frame: frame index (frames.csv).
        t_s: frame time [s].
        ring: the docking ring, or None.
        landmarks: tracked points (corners, components, ORB features).
        pose: the paper-style per-frame pose, or None.
        failures: why something is missing (``"ring: no ellipse near the prediction"``, ...).
        timings_ms: time per frontend stage [ms] (diagnostics, not a measurement).
        spin: the spin rate over a window of frames ending at this one (seed 001, one
            camera), accepted or refused, or None (no spin frontend, or still buffering).
    """

    frame: int
    t_s: float
    ring: RingMeasurement | None = None
    landmarks: tuple[LandmarkMeasurement, ...] = ()
    pose: PoseMeasurement | None = None
    failures: tuple[str, ...] = ()
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    spin: SpinRateMeasurement | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.t_s):
            raise MeasurementError(f"t_s must be finite, got {self.t_s}")
        if self.spin is not None and not isinstance(self.spin, SpinRateMeasurement):
            raise MeasurementError("spin must be a SpinRateMeasurement or None")
        object.__setattr__(self, "landmarks", tuple(self.landmarks))
        object.__setattr__(self, "failures", tuple(self.failures))
        ids = [lm.track_id for lm in self.landmarks]
        if len(ids) != len(set(ids)):
            raise MeasurementError(f"frame {self.frame}: duplicate landmark track ids")
