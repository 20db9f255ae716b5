"""What every importer shares: the error type, the calibration as a source states it, the
frame-source base class, image conversions (Bayer, grey, lens resampling) and timestamp files.

A source's calibration is kept in its own terms (`SourceCamera`: the lens model and
coefficients the file gives, the image size if the file gives one, and where each came from)
until the first images are seen. Only then is it turned into format v1's `Calibration`, so a
size disagreement is reported against the calibration file's own field, and a lens model that
format v1 cannot express (equidistant fisheye, OpenCV's rational model with k4..k6) is
resampled onto an undistorted pinhole camera with the same K (docs/import.md, "Lens models").
"""

from __future__ import annotations

import abc
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, TypeVar

import cv2
import numpy as np

from satpose.datasets.camera import CameraError, PinholeCamera
from satpose.datasets.errors import SequenceError
from satpose.datasets.geometry import Rigid3

T = TypeVar("T")

LensModel = Literal["radtan", "equidistant", "rational"]
"""``radtan``: OpenCV's 5 coefficients ``k1 k2 p1 p2 [k3]`` (ROS plumb_bob, Kalibr radtan);
``rational``: OpenCV's 8/12/14 coefficients (ROS rational_polynomial); ``equidistant``:
OpenCV's fisheye ``k1 k2 k3 k4`` (Kalibr pinhole-equidistant, ROS equidistant)."""

StereoFrame = tuple[float, np.ndarray, np.ndarray | None]
"""``(t_s, left, right)``: time [s] and images as OpenCV arrays (grey or BGR, uint8/uint16);
``right`` is None for a mono source."""


DEFAULT_TOLERANCE_S = 0.005
"""Largest stamp difference of a stereo pair by default [s] (hardware-triggered cameras stamp
both images alike; software-synchronised ones within a few ms)."""
DEFAULT_MAX_UNPAIRED = 0.05
"""Largest fraction of a stereo recording's images that may find no partner by default."""


class RecordingError(SequenceError):
    """A recording (bag, folder, video, calibration or truth file) cannot be imported. Names
    the file and the field like every `SequenceError`."""


@dataclass(frozen=True, kw_only=True)
class SourceCamera:
    """One camera's intrinsics as a calibration source states them.

    Attributes:
        K: 3x3 intrinsic matrix [px] (pixel (0, 0) is the centre of the top-left pixel).
        model: lens model of ``coeffs`` (see `LensModel`).
        coeffs: distortion coefficients in OpenCV's order for ``model``.
        size: ``(width, height)`` [px] if the source states it, else None (taken from images).
        path: the file the camera comes from.
        field: the field holding this camera (``cam0``, ``cameras.left``, a topic, ...).
        size_field: the field holding the image size, for error messages.
    """

    K: np.ndarray
    model: LensModel = "radtan"
    coeffs: np.ndarray = field(default_factory=lambda: np.zeros(5))
    size: tuple[int, int] | None = None
    path: Path
    field: str
    size_field: str = "resolution"

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=float)
        coeffs = np.asarray(self.coeffs, dtype=float).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise RecordingError(self.path, self.field, "camera matrix must be 3x3 finite numbers")
        if not np.all(np.isfinite(coeffs)):
            raise RecordingError(self.path, self.field, "distortion holds a NaN or infinity")
        counts = {"radtan": (4, 5), "rational": (8, 12, 14), "equidistant": (4,)}[self.model]
        if coeffs.size == 0:
            coeffs = np.zeros(counts[-1] if self.model == "radtan" else counts[0])
        if coeffs.size not in counts:
            raise RecordingError(
                self.path,
                self.field,
                f"{self.model} distortion needs {' or '.join(map(str, counts))} coefficients, "
                f"got {coeffs.size}",
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "coeffs", coeffs)

    @property
    def needs_resampling(self) -> bool:
        """True when format v1's pinhole-radtan model cannot express this lens."""
        if self.model == "radtan":
            return False
        if self.model == "rational":
            return bool(np.any(self.coeffs[5:] != 0.0))
        return bool(np.any(self.coeffs != 0.0))

    def with_size(self, size: tuple[int, int]) -> SourceCamera:
        """This camera with ``size`` filled in (or checked, if the source states one)."""
        if self.size is not None and tuple(self.size) != tuple(size):
            raise RecordingError(
                self.path,
                self.size_field,
                f"{self.field} is {self.size[0]}x{self.size[1]} but the images are "
                f"{size[0]}x{size[1]}",
            )
        return SourceCamera(
            K=self.K,
            model=self.model,
            coeffs=self.coeffs,
            size=(int(size[0]), int(size[1])),
            path=self.path,
            field=self.field,
            size_field=self.size_field,
        )

    def pinhole(self) -> PinholeCamera:
        """Format v1's camera: radtan coefficients kept, any other lens resampled (dist = 0)."""
        if self.size is None:
            raise RecordingError(self.path, self.size_field, "image size is not known")
        dist = np.zeros(5) if self.needs_resampling else self.coeffs[:5]
        try:
            return PinholeCamera(width=self.size[0], height=self.size[1], K=self.K, dist=dist)
        except CameraError as exc:
            raise RecordingError(self.path, self.field, str(exc)) from None

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``cv2.remap`` maps from this lens to `pinhole` (same K, no distortion), or None
        when the images are written as they are."""
        if not self.needs_resampling:
            return None
        assert self.size is not None
        if self.model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(
                self.K, self.coeffs, np.eye(3), self.K, self.size, cv2.CV_32FC1
            )
        return cv2.initUndistortRectifyMap(
            self.K, self.coeffs, np.eye(3), self.K, self.size, cv2.CV_32FC1
        )


@dataclass(frozen=True, kw_only=True)
class SourceCalibration:
    """One or two `SourceCamera` and the stereo extrinsics, as read from ``path``.

    Attributes:
        left, right: the cameras (``right`` None for mono).
        right_from_left: ``x_right = R x_left + t`` [m] (Kalibr's ``T_cn_cnm1`` of cam1,
            OpenCV stereoCalibrate's R, T), or None.
        path: the file (or bag) it was read from.
        topics: image topics the file names (Kalibr ``rostopic``), left then right.
    """

    left: SourceCamera
    right: SourceCamera | None = None
    right_from_left: Rigid3 | None = None
    path: Path
    topics: tuple[str, ...] = ()

    @property
    def is_stereo(self) -> bool:
        return self.right is not None


class FrameSource(abc.ABC):
    """A recording that yields frames in time order.

    Subclasses open the recording in ``__init__`` (raising `RecordingError` for anything
    unreadable there) and stream it with `frames`; `notes` tells what the import should
    report (pairing, dropped frames, topic choices) once the stream is exhausted, and `check`
    raises when what was seen makes the recording unusable (too many unpaired frames).
    """

    path: Path
    kind: Literal["stereo", "mono"]

    @abc.abstractmethod
    def frames(self) -> Iterator[StereoFrame]:
        """``(t_s, left, right)`` in increasing time."""

    def calibration(self) -> SourceCalibration | None:
        """The calibration the recording carries, or None."""
        return None

    def image_origin(self, camera: Literal["left", "right"]) -> str:
        """Where this camera's images come from, for messages (a topic, a folder)."""
        return f"{self.path} ({camera})"

    def notes(self) -> list[str]:
        """One line per fact the import reports (after `frames` is exhausted)."""
        return []

    def close(self) -> None:  # noqa: B027 (optional hook: most sources hold nothing open)
        """Release what the source holds open (also when `frames` was never started)."""

    def check(self) -> None:  # noqa: B027 (optional hook: most sources have nothing to check)
        """Raise `RecordingError` if what `frames` saw makes the recording unusable."""

    def provenance(self) -> dict[str, object]:
        """Free-form facts for sequence.yaml's ``generator``."""
        return {}

    def rate_hz(self) -> float | None:
        """The rate the recording states, if any [Hz]."""
        return None


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------

BAYER_TO_BGR = {
    "rggb": cv2.COLOR_BayerRGGB2BGR,
    "bggr": cv2.COLOR_BayerBGGR2BGR,
    "gbrg": cv2.COLOR_BayerGBRG2BGR,
    "grbg": cv2.COLOR_BayerGRBG2BGR,
}
"""ROS's Bayer pattern names (the 2x2 block at the top-left pixel, row by row) to OpenCV's
demosaicing codes of the same name (OpenCV's ``RGGB`` aliases state the top-left block too;
tests/datasets/test_import_images.py checks it on a mosaic made here)."""


def debayer(raw: np.ndarray, pattern: str, path: Path, field: str) -> np.ndarray:
    """Demosaic a single-channel Bayer image (8 or 16 bit) to BGR with OpenCV's bilinear
    demosaicing; ``pattern`` is ``rggb``, ``bggr``, ``gbrg`` or ``grbg``."""
    code = BAYER_TO_BGR.get(pattern)
    if code is None:
        raise RecordingError(path, field, f"unknown Bayer pattern {pattern!r}")
    if raw.ndim != 2:
        raise RecordingError(path, field, f"a Bayer image must have one channel, got {raw.shape}")
    return cv2.cvtColor(np.ascontiguousarray(raw), code)


def to_grey(img: np.ndarray) -> np.ndarray:
    """BGR (or grey) to grey, keeping the bit depth (OpenCV's luma weights)."""
    if img.ndim == 2:
        return img
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def check_image(img: np.ndarray, path: Path, field: str) -> np.ndarray:
    """An image format v1 can store: (H, W) or (H, W, 3), uint8 or uint16, contiguous."""
    if img.dtype not in (np.uint8, np.uint16):
        raise RecordingError(path, field, f"pixel type {img.dtype} is not 8- or 16-bit")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) or img.size == 0:
        raise RecordingError(path, field, f"image shape {img.shape} is not grey or colour")
    return np.ascontiguousarray(img)


def read_image_file(path: Path) -> np.ndarray:
    """An image file as stored (grey or BGR, 8 or 16 bit), or `RecordingError`."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise RecordingError(path, None, "not a readable image file")
    return check_image(img, path, "pixels")


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".pnm")


def image_files(folder: Path) -> list[Path]:
    """The image files directly in ``folder``, in natural order (``2.png`` before ``10.png``)."""

    def key(p: Path) -> tuple[object, ...]:
        stem = p.stem
        return (0, int(stem), "") if stem.isdigit() else (1, 0, stem)

    return sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=key,
    )


# --------------------------------------------------------------------------------------------
# Timestamp files
# --------------------------------------------------------------------------------------------

_NS_COLUMNS = ("t_ns", "timestamp_ns", "timestamp [ns]", "#timestamp [ns]", "#timestamp")
_S_COLUMNS = ("t_s", "t", "time", "timestamp", "#t_s", "# t_s")


def read_timestamps(path: Path) -> np.ndarray:
    """Frame times [s] from a file: one number per line (seconds), or a CSV whose header
    names a seconds column (``t_s``, ``t``, ``time``, ``timestamp``) or a nanoseconds column
    (``t_ns``, ``timestamp [ns]``, EuRoC's ``#timestamp [ns]``; integers, read exactly).
    Lines starting with ``#`` before the data are comments unless they are the header."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(path, None, f"cannot read timestamps ({exc})") from None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise RecordingError(path, None, "timestamps file is empty")
    first = [c.strip().lower() for c in lines[0].split(",")]
    scale = 1.0
    column = 0
    body = lines
    try:
        float(first[0].lstrip("#"))
        header = False
    except ValueError:
        header = True
    if header:
        body = lines[1:]
        for i, name in enumerate(first):
            if name in _NS_COLUMNS:
                column, scale = i, 1e-9
                break
            if name in _S_COLUMNS:
                column, scale = i, 1.0
                break
        else:
            raise RecordingError(
                path,
                "header",
                f"no time column among {first}; name it t_s (seconds) or t_ns (nanoseconds)",
            )
    out = np.empty(len(body))
    for k, line in enumerate(body):
        cells = [c.strip() for c in (line.split(",") if "," in line else line.split())]
        try:
            cell = cells[column]
            # Nanosecond integers are read exactly before scaling (a float64 of 1.7e18 ns
            # would lose the last digits).
            # (Python's int / int is correctly rounded.)
            value = (
                int(cell) / 1_000_000_000
                if scale != 1.0 and cell.isdigit()
                else float(cell) * scale
            )
        except (IndexError, ValueError):
            raise RecordingError(path, f"line {k + 1 + header}", f"not a time: {line!r}") from None
        if not math.isfinite(value):
            raise RecordingError(path, f"line {k + 1 + header}", f"not finite: {line!r}")
        out[k] = value
    if out.size == 0:
        raise RecordingError(path, None, "timestamps file has no rows")
    steps = np.diff(out)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise RecordingError(
            path,
            f"line {k + 1 + header}",
            f"time {float(out[k])!r} does not come after the previous {float(out[k - 1])!r}",
        )
    return out


def nominal_rate_hz(t_s: np.ndarray) -> float:
    """1 / the median frame interval [Hz] (1 Hz for a single frame)."""
    if t_s.size < 2:
        return 1.0
    return float(1.0 / np.median(np.diff(t_s)))


# --------------------------------------------------------------------------------------------
# Stereo pairing
# --------------------------------------------------------------------------------------------


@dataclass
class TopicStats:
    """What one camera's stream delivered to the pairing (``topic``: its name in messages)."""

    topic: str
    messages: int = 0
    paired: int = 0
    unpaired: int = 0
    out_of_order: int = 0
    last_ns: int = -1


def pair_by_stamp(
    items: Iterator[tuple[str, int, T]], tol_ns: int, left: TopicStats, right: TopicStats
) -> Iterator[tuple[int, T, T]]:
    """Pair a merged stream of ``(camera, stamp_ns, payload)`` (``camera`` ``left`` or
    ``right``, stamps increasing per camera) into ``(left_stamp_ns, left, right)``.

    A left and a right item pair when their stamps differ by at most ``tol_ns`` and neither
    has a closer partner in the other camera's next item (mutual nearest neighbours with a
    one-item lookahead, so a late item on one side does not steal its neighbour's partner).
    Items that pair with nothing are counted in the stats' ``unpaired``; ``paired`` counts
    the rest. Streaming: holds at most a few items per camera.
    """
    queues: dict[str, deque[tuple[int, T]]] = {"left": deque(), "right": deque()}
    stats = {"left": left, "right": right}

    def drop(cam: str) -> None:
        queues[cam].popleft()
        stats[cam].unpaired += 1

    def ready(final: bool) -> Iterator[tuple[int, T, T]]:
        L, R = queues["left"], queues["right"]
        while L and R:
            tl, tr = L[0][0], R[0][0]
            if tl < tr - tol_ns:
                drop("left")
                continue
            if tr < tl - tol_ns:
                drop("right")
                continue
            # Within tolerance: the later side's next item cannot be closer; the earlier
            # side's next one may be (wait for it unless the stream has ended).
            early, other_t = (L, tr) if tl <= tr else (R, tl)
            if len(early) < 2 and not final:
                return
            if len(early) >= 2 and abs(early[1][0] - other_t) < abs(tl - tr):
                drop("left" if early is L else "right")
                continue
            (_, pl), (_, pr) = L.popleft(), R.popleft()
            left.paired += 1
            right.paired += 1
            yield tl, pl, pr

    for cam, ns, payload in items:
        queues[cam].append((ns, payload))
        yield from ready(final=False)
    yield from ready(final=True)
    for cam in ("left", "right"):
        stats[cam].unpaired += len(queues[cam])
        queues[cam].clear()


def pairing_note(left: TopicStats, right: TopicStats, tolerance_s: float) -> str:
    """One line: how many pairs, how many unpaired images per camera."""
    return (
        f"pairing within {tolerance_s * 1e3:g} ms: {left.paired} pairs; unpaired "
        f"{left.unpaired} of {left.messages} left, {right.unpaired} of {right.messages} right"
    )


def check_pairing(
    path: Path, left: TopicStats, right: TopicStats, tolerance_s: float, max_unpaired: float
) -> None:
    """Refuse a stereo recording with no pair, or where more than ``max_unpaired`` of all
    images found no partner (cameras not synchronised, or at different rates)."""
    total = left.messages + right.messages
    unpaired = left.unpaired + right.unpaired
    if left.paired > 0 and unpaired <= max_unpaired * total:
        return
    worst, other = (right, left) if right.unpaired >= left.unpaired else (left, right)
    raise RecordingError(
        path,
        worst.topic,
        f"{worst.unpaired} of {worst.messages} images have no partner on {other.topic} "
        f"within {tolerance_s * 1e3:g} ms ({other.messages} images there; {left.paired} "
        "pairs): the cameras are not synchronised or run at different rates; widen "
        "--pair-tolerance-ms or accept more with --max-unpaired",
    )
