"""Sequence format v1: reader (`load_sequence`) and writer (`SequenceWriter`, `write_sequence`).

The format is specified in docs/sequence_format.md (a copy of the shared DATASET_FORMAT.md).
Every violation raises `SequenceError` naming the file and the field. Images are read lazily,
one frame at a time, and checked against calib.yaml when read (`Sequence.verify()` checks them
all up front). Writers build the folder under a temporary name and rename it into place, so a
reader never sees a half-written sequence.

Images are numpy arrays in OpenCV's channel order: ``(H, W)`` grey or ``(H, W, 3)`` BGR,
``uint8`` or ``uint16``.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import uuid
from collections import deque
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import pandas as pd
import yaml

from satpose.datasets.camera import CameraError, PinholeCamera
from satpose.datasets.config import yaml_problem
from satpose.datasets.errors import SatposeError, SequenceError, shown
from satpose.datasets.geometry import GeometryError, Rigid3, quat_xyzw_to_matrix

FORMAT_VERSION = "satpose-sequence/1"
QUAT_NORM_TOL = 1e-6
"""|‖q‖ − 1| above this is rejected as a non-unit quaternion (files carry >= 9 digits)."""
TIME_MATCH_TOL_S = 1e-6
"""groundtruth.csv t_s must equal frames.csv t_s of the same frame within this [s]."""

FRAMES_COLUMNS = {"stereo": ["frame", "t_s", "left", "right"], "mono": ["frame", "t_s", "left"]}
TRUTH_COLUMNS = ["frame", "t_s", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
TRUTH_OPTIONAL = {"angular": ["wx", "wy", "wz"], "linear": ["vx", "vy", "vz"]}

Kind = Literal["stereo", "mono"]
CameraName = Literal["left", "right"]


# --------------------------------------------------------------------------------------------
# In-memory types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Calibration:
    """calib.yaml: one or two cameras and the stereo extrinsics.

    Attributes:
        left: the left (or only) camera.
        right: the right camera (stereo only).
        right_from_left: ``x_right = R x_left + t`` (OpenCV stereoCalibrate's R, T) [m].
        pixel_noise_px: the image noise the generator added, if known [px].
    """

    left: PinholeCamera
    right: PinholeCamera | None = None
    right_from_left: Rigid3 | None = None
    pixel_noise_px: float | None = None

    def __post_init__(self) -> None:
        if (self.right is None) != (self.right_from_left is None):
            raise SatposeError("a stereo calibration needs both `right` and `right_from_left`")

    @property
    def is_stereo(self) -> bool:
        return self.right is not None

    def camera(self, name: CameraName) -> PinholeCamera:
        """The camera called ``left`` or ``right``."""
        if name == "left":
            return self.left
        if self.right is None:
            raise SatposeError("this calibration has no right camera (mono sequence)")
        return self.right

    @property
    def baseline_m(self) -> float:
        """Distance between the two camera centres [m] (0 for mono)."""
        return (
            0.0 if self.right_from_left is None else float(np.linalg.norm(self.right_from_left.t))
        )


@dataclass(frozen=True, kw_only=True)
class GroundTruth:
    """groundtruth.csv: ``left_cam_from_target`` per frame, optionally with velocities.

    Attributes:
        frame: frame indices, shape (N,).
        t_s: times [s], shape (N,).
        translation: ``left_cam_from_target.t`` [m], shape (N, 3).
        quat_xyzw: ``left_cam_from_target`` rotation, unit quaternions, shape (N, 4).
        angular_velocity: target angular velocity in the target frame [rad/s], (N, 3) or None.
        linear_velocity: target (frame origin) velocity in the left camera frame [m/s],
            (N, 3) or None.
    """

    frame: np.ndarray
    t_s: np.ndarray
    translation: np.ndarray
    quat_xyzw: np.ndarray
    angular_velocity: np.ndarray | None = None
    linear_velocity: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    def rotations(self) -> np.ndarray:
        """Rotation matrices of ``left_cam_from_target``, shape (N, 3, 3)."""
        return quat_xyzw_to_matrix(self.quat_xyzw)

    def pose(self, i: int) -> Rigid3:
        """``left_cam_from_target`` of row ``i``."""
        return Rigid3.from_quat_xyzw(self.quat_xyzw[i], self.translation[i])

    def row_of_frame(self, frame_index: int) -> int:
        """Row holding frame index ``frame_index`` (raises KeyError if absent)."""
        rows = np.flatnonzero(self.frame == frame_index)
        if rows.size == 0:
            raise KeyError(frame_index)
        return int(rows[0])


@dataclass(frozen=True, kw_only=True)
class Ring:
    """The docking ring's outer front edge in the target frame [m]."""

    radius_m: float
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    extras: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class Bracket:
    """A solar-panel triangular bracket: base vertices P1, P2 and apex P5 [m]."""

    P1: np.ndarray
    P2: np.ndarray
    P5: np.ndarray
    visible_fraction: float = 1.0


@dataclass(frozen=True, kw_only=True)
class TargetGeometry:
    """target.yaml: geometry in the target frame [m]. Truth: estimators must not read it in
    non-cooperative mode.

    Attributes:
        ring: the docking ring's outer front edge, or None.
        panel_corners: (4, 3) or None.
        components: (M, 3) centres of small dark components, or None.
        bracket: a triangular bracket (final-approach targets), or None.
        extras: every other named feature, as parsed from YAML.
    """

    ring: Ring | None = None
    panel_corners: np.ndarray | None = None
    components: np.ndarray | None = None
    bracket: Bracket | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class Frame:
    """One row of frames.csv. Images are read from disk on demand and checked against calib."""

    index: int
    t_s: float
    left_path: Path
    right_path: Path | None
    calibration: Calibration
    root: Path

    def image(self, camera: CameraName = "left") -> np.ndarray:
        """Read the ``left`` or ``right`` image: (H, W) or (H, W, 3) BGR, uint8 or uint16."""
        path = self.left_path if camera == "left" else self.right_path
        if path is None:
            raise SequenceError(self.root / "frames.csv", "right", "this is a mono sequence")
        return read_image(path, self.calibration.camera(camera))

    def left(self) -> np.ndarray:
        """The left image (see `image`)."""
        return self.image("left")

    def right(self) -> np.ndarray:
        """The right image (see `image`)."""
        return self.image("right")

    def mask_path(self, camera: CameraName = "left") -> Path | None:
        """Path of the object-id mask of this frame, or None if the sequence has none."""
        image_path = self.left_path if camera == "left" else self.right_path
        if image_path is None:
            return None
        p = self.root / "masks" / camera / image_path.name
        return p if p.is_file() else None

    def mask(self, camera: CameraName = "left") -> np.ndarray | None:
        """Object ids (H, W) uint8 (0 = background), or None if the sequence has no masks."""
        p = self.mask_path(camera)
        if p is None:
            return None
        m = read_image(p, self.calibration.camera(camera))
        if m.ndim != 2 or m.dtype != np.uint8:
            raise SequenceError(
                p,
                None,
                f"a mask must be a single-channel uint8 PNG, got {m.dtype} with shape {m.shape}",
            )
        return m


@dataclass(frozen=True, kw_only=True)
class Sequence:
    """A loaded sequence. Iterating yields `Frame` objects; images stay on disk until asked for.

    Attributes:
        root: the sequence folder.
        name, kind, rate_hz, generator: from sequence.yaml.
        calibration: from calib.yaml.
        frames: all frames in order.
        truth: groundtruth.csv, or None (real recordings).
        target: target.yaml, or None.
    """

    root: Path
    name: str
    kind: Kind
    rate_hz: float
    calibration: Calibration
    frames: tuple[Frame, ...]
    truth: GroundTruth | None = None
    target: TargetGeometry | None = None
    generator: Mapping[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    @property
    def has_masks(self) -> bool:
        return (self.root / "masks" / "left").is_dir()

    def verify(self) -> None:
        """Check every image (and mask) header against calib.yaml; raise SequenceError if not."""
        for fr in self.frames:
            cams: tuple[CameraName, ...] = ("left", "right") if self.kind == "stereo" else ("left",)
            for cam in cams:
                path = fr.left_path if cam == "left" else fr.right_path
                assert path is not None
                check_png_header(path, self.calibration.camera(cam))
                mp = fr.mask_path(cam)
                if mp is not None:
                    check_png_header(mp, self.calibration.camera(cam))


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png_header(path: Path, camera: PinholeCamera) -> tuple[int, int]:
    """Read a PNG's IHDR and check its size against ``camera``; return ``(width, height)``."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError as exc:
        raise SequenceError(path, None, f"cannot read image ({exc.strerror or exc})") from None
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise SequenceError(path, None, "not a readable PNG file")
    width, height = struct.unpack(">II", head[16:24])
    _check_size(path, width, height, camera)
    return width, height


def _check_size(path: Path, width: int, height: int, camera: PinholeCamera) -> None:
    if (width, height) != camera.size:
        raise SequenceError(
            path,
            "width/height",
            f"image is {width}x{height} but calib.yaml says {camera.width}x{camera.height}",
        )


def read_image(path: Path, camera: PinholeCamera) -> np.ndarray:
    """Read a PNG as stored (grey or BGR, 8 or 16 bit) and check its size against ``camera``."""
    if not path.is_file():
        raise SequenceError(path, None, "image file is missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise SequenceError(path, None, "not a readable PNG file")
    if img.dtype not in (np.uint8, np.uint16):
        raise SequenceError(path, None, f"pixel type {img.dtype} is not 8- or 16-bit")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    _check_size(path, img.shape[1], img.shape[0], camera)
    return img


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class SequenceHeader:
    """sequence.yaml and calib.yaml: what a sequence is before any of its frames.

    Attributes:
        root: the sequence folder.
        name, kind, rate_hz, generator: from sequence.yaml.
        calibration: from calib.yaml.
    """

    root: Path
    name: str
    kind: Kind
    rate_hz: float
    calibration: Calibration
    generator: Mapping[str, Any] = field(default_factory=dict)


def load_header(path: str | Path) -> SequenceHeader:
    """Read sequence.yaml and calib.yaml only (a folder still being recorded has no complete
    frames.csv yet; `load_sequence` reads the rest).

    Raises:
        SequenceError: naming the file and field.
    """
    root = Path(path)
    if not root.is_dir():
        raise SequenceError(root, None, "sequence folder does not exist")
    meta = _read_yaml(root / "sequence.yaml", required=True)
    meta_path = root / "sequence.yaml"
    fmt = meta.get("format")
    if fmt is None:
        raise SequenceError(meta_path, "format", f"missing; expected {FORMAT_VERSION!r}")
    if fmt != FORMAT_VERSION:
        raise SequenceError(
            meta_path,
            "format",
            f"unknown format version {fmt!r}; this satpose reads {FORMAT_VERSION!r}",
        )
    kind = meta.get("kind")
    if kind not in ("stereo", "mono"):
        raise SequenceError(meta_path, "kind", f"must be 'stereo' or 'mono', got {kind!r}")
    name = meta.get("name")
    if not isinstance(name, str) or not name:
        raise SequenceError(meta_path, "name", f"must be a non-empty string, got {name!r}")
    rate = _number(meta.get("rate_hz"), meta_path, "rate_hz")
    if rate <= 0:
        raise SequenceError(meta_path, "rate_hz", f"must be positive, got {rate}")
    generator = meta.get("generator") or {}
    if not isinstance(generator, dict):
        raise SequenceError(meta_path, "generator", "must be a mapping")
    calib = _read_calibration(root / "calib.yaml", kind)
    return SequenceHeader(
        root=root, name=name, kind=kind, rate_hz=rate, calibration=calib, generator=generator
    )


def load_sequence(path: str | Path) -> Sequence:
    """Open a sequence folder (format v1). Reads the small files now, images lazily.

    Raises:
        SequenceError: naming the file and field for every violation of the format.
    """
    head = load_header(path)
    root = head.root
    frames = _read_frames(root, head.kind, head.calibration)
    truth = _read_truth(root / "groundtruth.csv", frames)
    target = _read_target(root / "target.yaml")
    return Sequence(
        root=root,
        name=head.name,
        kind=head.kind,
        rate_hz=head.rate_hz,
        calibration=head.calibration,
        frames=frames,
        truth=truth,
        target=target,
        generator=head.generator,
    )


def _read_yaml(path: Path, required: bool) -> dict[str, Any]:
    if not path.is_file():
        if required:
            raise SequenceError(path, None, "required file is missing")
        return {}
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise SequenceError(path, None, f"not valid YAML: {yaml_problem(exc)}") from None
    except UnicodeDecodeError as exc:
        raise SequenceError(path, None, f"not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise SequenceError(path, None, "must hold a YAML mapping at the top level")
    return data


def _number(value: Any, path: Path, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SequenceError(path, name, f"must be a number, got {shown(value)}")
    out = float(value)
    if not math.isfinite(out):
        raise SequenceError(path, name, f"must be finite, got {shown(value)}")
    return out


def _vector(value: Any, n: int | None, path: Path, name: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)):
        raise SequenceError(path, name, f"must be a list of numbers, got {shown(value)}")
    if n is not None and len(value) != n:
        raise SequenceError(path, name, f"expected {n} numbers, got {len(value)}")
    return np.array([_number(v, path, f"{name}[{i}]") for i, v in enumerate(value)])


def _read_camera(raw: Any, path: Path, name: str) -> PinholeCamera:
    if not isinstance(raw, dict):
        raise SequenceError(path, name, "missing or not a mapping")
    for key in ("width", "height", "model", "K"):
        if key not in raw:
            raise SequenceError(path, f"{name}.{key}", "required key is missing")
    for key in ("width", "height"):
        if isinstance(raw[key], bool) or not isinstance(raw[key], int) or raw[key] <= 0:
            raise SequenceError(
                path, f"{name}.{key}", f"must be a positive integer, got {shown(raw[key])}"
            )
    K = _vector(raw["K"], 9, path, f"{name}.K")
    dist = _vector(raw.get("dist", [0.0] * 5), None, path, f"{name}.dist")
    try:
        return PinholeCamera(
            width=raw["width"], height=raw["height"], K=K, dist=dist, model=raw["model"]
        )
    except CameraError as exc:
        field_name = f"{name}.model" if "model" in str(exc) else f"{name}"
        raise SequenceError(path, field_name, str(exc)) from None


def load_calibration(path: str | Path, kind: str = "mono") -> Calibration:
    """calib.yaml on its own (an event-only recording has no frames to load a sequence by).

    Raises:
        SequenceError: naming the file and field.
    """
    return _read_calibration(Path(path), kind)


def load_target(path: str | Path) -> TargetGeometry:
    """target.yaml on its own (a user's target geometry before it joins a sequence).

    Raises:
        SequenceError: naming the file and field (also when the file is missing).
    """
    p = Path(path)
    if not p.is_file():
        raise SequenceError(p, None, "target file does not exist")
    target = _read_target(p)
    assert target is not None
    return target


def _read_calibration(path: Path, kind: str) -> Calibration:
    data = _read_yaml(path, required=True)
    cams = data.get("cameras")
    if not isinstance(cams, dict):
        raise SequenceError(path, "cameras", "missing or not a mapping")
    left = _read_camera(cams.get("left"), path, "cameras.left")
    right = None
    right_from_left = None
    if kind == "stereo":
        right = _read_camera(cams.get("right"), path, "cameras.right")
        rfl = data.get("right_from_left")
        if not isinstance(rfl, dict):
            raise SequenceError(
                path,
                "right_from_left",
                "stereo calibration needs right_from_left: {t: [...], quat_xyzw: [...]}",
            )
        t = _vector(rfl.get("t"), 3, path, "right_from_left.t")
        q = _vector(rfl.get("quat_xyzw"), 4, path, "right_from_left.quat_xyzw")
        _check_unit_quaternion(q, path, "right_from_left.quat_xyzw")
        right_from_left = Rigid3.from_quat_xyzw(q / np.linalg.norm(q), t)
    noise = data.get("pixel_noise_px")
    if noise is not None:
        noise = _number(noise, path, "pixel_noise_px")
        if noise < 0:
            raise SequenceError(path, "pixel_noise_px", f"must be >= 0, got {noise}")
    return Calibration(
        left=left, right=right, right_from_left=right_from_left, pixel_noise_px=noise
    )


def _check_unit_quaternion(q: np.ndarray, path: Path, name: str) -> None:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise SequenceError(path, name, f"quaternion is not unit norm (|q| = {norm:.9f})")


def _read_csv(path: Path, required: bool) -> pd.DataFrame | None:
    if not path.is_file():
        if required:
            raise SequenceError(path, None, "required file is missing")
        return None
    try:
        df = pd.read_csv(path, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise SequenceError(
            path, None, f"not a readable CSV file: {str(exc).splitlines()[0]}"
        ) from None
    df.columns = [str(c).strip() for c in df.columns]
    return df


def _check_columns(df: pd.DataFrame, path: Path, required: list[str], optional: list[str]) -> None:
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise SequenceError(
            path, ",".join(missing), f"missing column(s); expected columns {','.join(required)}"
        )
    unknown = [c for c in df.columns if c not in required and c not in optional]
    if unknown:
        raise SequenceError(
            path, ",".join(unknown), f"unknown column(s); allowed: {','.join(required + optional)}"
        )


def _numeric_column(df: pd.DataFrame, col: str, path: Path, integer: bool = False) -> np.ndarray:
    values = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        row = int(bad[0])
        raise SequenceError(
            path,
            col,
            f"row {row + 1}: value {shown(df[col].iloc[row])} is NaN, infinite or not a number",
        )
    if integer:
        if np.any(values != np.round(values)):
            row = int(np.flatnonzero(values != np.round(values))[0])
            raise SequenceError(path, col, f"row {row + 1}: {shown(values[row])} is not an integer")
        return values.astype(np.int64)
    return values


def _check_increasing(values: np.ndarray, path: Path, col: str) -> None:
    steps = np.diff(values)
    if np.any(steps <= 0):
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise SequenceError(
            path,
            col,
            f"row {row + 1}: {shown(values[row])} is not strictly greater "
            f"than the previous row's {shown(values[row - 1])}",
        )


def _read_frames(root: Path, kind: str, calib: Calibration) -> tuple[Frame, ...]:
    path = root / "frames.csv"
    df = _read_csv(path, required=True)
    assert df is not None
    columns = FRAMES_COLUMNS[kind]
    _check_columns(df, path, columns, [])
    if len(df) == 0:
        raise SequenceError(path, None, "has no frames")
    index = _numeric_column(df, "frame", path, integer=True)
    t_s = _numeric_column(df, "t_s", path)
    _check_increasing(index.astype(float), path, "frame")
    _check_increasing(t_s, path, "t_s")
    frames = []
    image_cols = columns[2:]
    for row in range(len(df)):
        paths: dict[str, Path] = {}
        for col in image_cols:
            rel = df[col].iloc[row]
            if not isinstance(rel, str) or not rel.strip():
                raise SequenceError(path, col, f"row {row + 1}: image path is empty")
            p = root / rel.strip()
            if not p.is_file():
                raise SequenceError(
                    p, None, f"image named in frames.csv ({col}, row {row + 1}) is missing"
                )
            paths[col] = p
        frames.append(
            Frame(
                index=int(index[row]),
                t_s=float(t_s[row]),
                left_path=paths["left"],
                right_path=paths.get("right"),
                calibration=calib,
                root=root,
            )
        )
    return tuple(frames)


def _read_truth(path: Path, frames: tuple[Frame, ...]) -> GroundTruth | None:
    df = _read_csv(path, required=False)
    if df is None:
        return None
    optional = TRUTH_OPTIONAL["angular"] + TRUTH_OPTIONAL["linear"]
    _check_columns(df, path, TRUTH_COLUMNS, optional)
    for group in TRUTH_OPTIONAL.values():
        present = [c for c in group if c in df.columns]
        if present and len(present) != 3:
            raise SequenceError(
                path,
                ",".join(group),
                f"give all three of {','.join(group)} or none, got {','.join(present)}",
            )
    frame = _numeric_column(df, "frame", path, integer=True)
    t_s = _numeric_column(df, "t_s", path)
    _check_increasing(frame.astype(float), path, "frame")
    _check_increasing(t_s, path, "t_s")
    expected = np.array([f.index for f in frames])
    if frame.shape != expected.shape or np.any(frame != expected):
        extra = sorted(set(frame.tolist()) ^ set(expected.tolist()))[:5]
        raise SequenceError(
            path, "frame", f"must hold one row per frame of frames.csv; frames differ, e.g. {extra}"
        )
    t_frames = np.array([f.t_s for f in frames])
    if np.any(np.abs(t_s - t_frames) > TIME_MATCH_TOL_S):
        row = int(np.flatnonzero(np.abs(t_s - t_frames) > TIME_MATCH_TOL_S)[0])
        raise SequenceError(
            path,
            "t_s",
            f"row {row + 1}: {t_s[row]} differs from frames.csv's "
            f"{t_frames[row]} for frame {frame[row]}",
        )
    trans = np.stack([_numeric_column(df, c, path) for c in ("tx", "ty", "tz")], axis=1)
    quat = np.stack([_numeric_column(df, c, path) for c in ("qx", "qy", "qz", "qw")], axis=1)
    norms = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        row = int(bad[0])
        raise SequenceError(
            path,
            "qx,qy,qz,qw",
            f"row {row + 1}: quaternion is not unit norm (|q| = {norms[row]:.9f})",
        )
    quat = quat / norms[:, None]

    def optional_block(cols: list[str]) -> np.ndarray | None:
        if cols[0] not in df.columns:
            return None
        return np.stack([_numeric_column(df, c, path) for c in cols], axis=1)

    return GroundTruth(
        frame=frame,
        t_s=t_s,
        translation=trans,
        quat_xyzw=quat,
        angular_velocity=optional_block(TRUTH_OPTIONAL["angular"]),
        linear_velocity=optional_block(TRUTH_OPTIONAL["linear"]),
    )


def _points(value: Any, path: Path, name: str, count: int | None = None) -> np.ndarray:
    if not isinstance(value, list) or (count is not None and len(value) != count):
        want = f"{count} points" if count is not None else "a list of points"
        raise SequenceError(path, name, f"must be {want} [[x, y, z], ...]")
    if not value:
        return np.zeros((0, 3))
    return np.stack([_vector(v, 3, path, f"{name}[{i}]") for i, v in enumerate(value)])


def _read_target(path: Path) -> TargetGeometry | None:
    if not path.is_file():
        return None
    data = _read_yaml(path, required=True)
    ring = None
    if "ring" in data:
        raw = data["ring"]
        if not isinstance(raw, dict) or "radius_m" not in raw:
            raise SequenceError(path, "ring.radius_m", "required key is missing")
        radius = _number(raw["radius_m"], path, "ring.radius_m")
        if radius <= 0:
            raise SequenceError(path, "ring.radius_m", f"must be positive, got {radius}")
        center = _vector(raw.get("center", [0, 0, 0]), 3, path, "ring.center")
        normal = _vector(raw.get("normal", [0, 0, 1]), 3, path, "ring.normal")
        if abs(np.linalg.norm(normal) - 1.0) > 1e-6:
            raise SequenceError(path, "ring.normal", "must be a unit vector")
        extras = {k: v for k, v in raw.items() if k not in ("radius_m", "center", "normal")}
        ring = Ring(radius_m=radius, center=center, normal=normal, extras=extras)
    corners = None
    if "panel_corners" in data:
        corners = _points(data["panel_corners"], path, "panel_corners", count=4)
    components = None
    if "components" in data:
        components = _points(data["components"], path, "components")
    bracket = None
    if "bracket" in data:
        raw = data["bracket"]
        if not isinstance(raw, dict):
            raise SequenceError(path, "bracket", "must be a mapping {P1, P2, P5, visible_fraction}")
        pts = {k: _vector(raw.get(k), 3, path, f"bracket.{k}") for k in ("P1", "P2", "P5")}
        frac = _number(raw.get("visible_fraction", 1.0), path, "bracket.visible_fraction")
        if not 0.0 < frac <= 1.0:
            raise SequenceError(path, "bracket.visible_fraction", f"must be in (0, 1], got {frac}")
        bracket = Bracket(visible_fraction=frac, **pts)
    known = ("ring", "panel_corners", "components", "bracket")
    extras = {k: v for k, v in data.items() if k not in known}
    return TargetGeometry(
        ring=ring, panel_corners=corners, components=components, bracket=bracket, extras=extras
    )


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def _camera_to_yaml(cam: PinholeCamera) -> dict[str, Any]:
    return {
        "width": cam.width,
        "height": cam.height,
        "model": cam.model,
        "K": [float(v) for v in cam.K.reshape(-1)],
        "dist": [float(v) for v in cam.dist],
    }


def calibration_to_yaml(calib: Calibration) -> dict[str, Any]:
    """calib.yaml content (plain data) of a calibration."""
    out: dict[str, Any] = {"cameras": {"left": _camera_to_yaml(calib.left)}}
    if calib.right is not None and calib.right_from_left is not None:
        out["cameras"]["right"] = _camera_to_yaml(calib.right)
        out["right_from_left"] = {
            "t": [float(v) for v in calib.right_from_left.t],
            "quat_xyzw": [float(v) for v in calib.right_from_left.quat_xyzw],
        }
    if calib.pixel_noise_px is not None:
        out["pixel_noise_px"] = float(calib.pixel_noise_px)
    return out


def target_to_yaml(target: TargetGeometry) -> dict[str, Any]:
    """target.yaml content (plain data) of a target geometry."""
    out: dict[str, Any] = {}
    if target.ring is not None:
        out["ring"] = {
            "radius_m": float(target.ring.radius_m),
            "center": [float(v) for v in target.ring.center],
            "normal": [float(v) for v in target.ring.normal],
            **target.ring.extras,
        }
    if target.panel_corners is not None:
        out["panel_corners"] = np.asarray(target.panel_corners, float).tolist()
    if target.components is not None:
        out["components"] = np.asarray(target.components, float).tolist()
    if target.bracket is not None:
        b = target.bracket
        out["bracket"] = {
            "P1": b.P1.tolist(),
            "P2": b.P2.tolist(),
            "P5": b.P5.tolist(),
            "visible_fraction": float(b.visible_fraction),
        }
    out.update(target.extras)
    return out


def _dump_yaml(data: Mapping[str, Any], path: Path) -> None:
    path.write_text(
        yaml.safe_dump(dict(data), sort_keys=False, default_flow_style=None, width=100),
        encoding="utf-8",
    )


class SequenceWriter:
    """Write a sequence folder frame by frame; it appears at ``path`` only on `close`.

    Use as a context manager: an exception inside the block removes the temporary folder and
    leaves ``path`` untouched::

        with SequenceWriter(out, name="demo", kind="stereo", rate_hz=0.2, calibration=calib) as w:
            w.add_frame(0, 0.0, left, right, truth=pose)

    Args:
        path: final folder. Must not exist unless ``overwrite``.
        name, kind, rate_hz, generator: sequence.yaml fields.
        calibration: written to calib.yaml; images are checked against it.
        target: written to target.yaml if given.
        overwrite: replace an existing folder (only after the new one is complete).
        png_compression: zlib level 0-9 of the PNGs (None: OpenCV's default, level 1 with the
            RLE strategy, the fastest that compresses); any level is lossless; 0 stores the rows
            unfiltered and uncompressed, the fastest and up to 8x larger (docs/results/import.md).
        workers: PNGs encoded and written by this many threads (OpenCV releases the GIL);
            `close` waits for them and raises the first failure.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        name: str,
        kind: Kind,
        rate_hz: float,
        calibration: Calibration,
        generator: Mapping[str, Any] | None = None,
        target: TargetGeometry | None = None,
        overwrite: bool = False,
        png_compression: int | None = None,
        workers: int = 1,
    ) -> None:
        self.path = Path(path)
        if png_compression is not None and not 0 <= png_compression <= 9:
            raise SatposeError(f"PNG compression must be 0-9, got {png_compression}")
        if workers < 1:
            raise SatposeError(f"workers must be >= 1, got {workers}")
        self._png_params = png_params(png_compression)
        self._pool = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None
        self._pending: deque[Future[None]] = deque()
        self._max_pending = 4 * workers
        if kind not in ("stereo", "mono"):
            raise SequenceError(
                self.path / "sequence.yaml", "kind", f"must be stereo or mono, got {kind!r}"
            )
        if (kind == "stereo") != calibration.is_stereo:
            raise SequenceError(
                self.path / "calib.yaml",
                "cameras",
                f"a {kind} sequence needs {'two cameras' if kind == 'stereo' else 'one camera'}",
            )
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise SequenceError(
                self.path / "sequence.yaml", "rate_hz", f"must be positive, got {rate_hz}"
            )
        if self.path.exists() and not overwrite:
            raise SequenceError(
                self.path,
                None,
                "output folder already exists (choose another folder or allow overwriting)",
            )
        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            self._tmp = parent / f".{self.path.name}.tmp-{uuid.uuid4().hex[:8]}"
            self._tmp.mkdir()
        except OSError as exc:
            raise SequenceError(
                parent, None, f"cannot create the output folder ({exc.strerror or exc})"
            ) from None
        self.name = name
        self.kind = kind
        self.rate_hz = float(rate_hz)
        self.calibration = calibration
        self.generator = dict(generator or {})
        self.target = target
        self.overwrite = overwrite
        self._frames: list[dict[str, Any]] = []
        self._truth: list[dict[str, float]] = []
        self._closed = False

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def abort(self) -> None:
        """Discard everything written so far."""
        self._closed = True
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pending.clear()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def _drain(self, keep: int) -> None:
        """Wait for queued PNG writes until at most ``keep`` are pending (re-raising the
        first failure)."""
        while len(self._pending) > keep:
            self._pending.popleft().result()

    def add_frame(
        self,
        index: int,
        t_s: float,
        left: np.ndarray,
        right: np.ndarray | None = None,
        *,
        truth: Rigid3 | None = None,
        angular_velocity: np.ndarray | None = None,
        linear_velocity: np.ndarray | None = None,
        masks: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Add one frame.

        Args:
            index: frame index (strictly increasing).
            t_s: time [s] (strictly increasing).
            left, right: images (H, W) or (H, W, 3) BGR, uint8 or uint16; right for stereo.
            truth: ``left_cam_from_target``; give it for every frame or for none.
            angular_velocity: target angular velocity in the target frame [rad/s] (3,).
            linear_velocity: target velocity in the left camera frame [m/s] (3,).
            masks: ``{"left": ids, "right": ids}`` uint8 object-id images (0 = background).
        """
        if self._closed:
            raise SatposeError("SequenceWriter is closed")
        if self._frames and (index <= self._frames[-1]["frame"] or t_s <= self._frames[-1]["t_s"]):
            raise SequenceError(
                self._tmp / "frames.csv",
                "frame,t_s",
                f"frame {index} at {t_s} s does not come after frame {self._frames[-1]['frame']}",
            )
        if not math.isfinite(t_s):
            raise SequenceError(self._tmp / "frames.csv", "t_s", f"frame {index}: not finite")
        row: dict[str, Any] = {"frame": int(index), "t_s": float(t_s)}
        cams: list[tuple[str, np.ndarray | None]] = [("left", left)]
        if self.kind == "stereo":
            if right is None:
                raise SequenceError(
                    self._tmp / "frames.csv",
                    "right",
                    f"frame {index}: a stereo sequence needs a right image",
                )
            cams.append(("right", right))
        for cam, img in cams:
            assert img is not None
            rel = f"{cam}/{index:06d}.png"
            self._write_png(self._tmp / rel, img, self.calibration.camera(cam))  # type: ignore[arg-type]
            row[cam] = rel
            if masks and cam in masks:
                m = np.asarray(masks[cam])
                if m.dtype != np.uint8 or m.ndim != 2:
                    raise SequenceError(
                        self._tmp / "masks" / rel, None, "masks must be (H, W) uint8"
                    )
                self._write_png(self._tmp / "masks" / rel, m, self.calibration.camera(cam))  # type: ignore[arg-type]
        if (truth is None) != (not self._truth) and self._frames:
            raise SequenceError(
                self._tmp / "groundtruth.csv", None, "give truth for every frame or for none"
            )
        if truth is not None:
            q = truth.quat_xyzw
            trow = {
                "frame": int(index),
                "t_s": float(t_s),
                "tx": truth.t[0],
                "ty": truth.t[1],
                "tz": truth.t[2],
                "qx": q[0],
                "qy": q[1],
                "qz": q[2],
                "qw": q[3],
            }
            for cols, vec in (
                (TRUTH_OPTIONAL["angular"], angular_velocity),
                (TRUTH_OPTIONAL["linear"], linear_velocity),
            ):
                if vec is not None:
                    v = np.asarray(vec, float).reshape(3)
                    trow.update({c: float(x) for c, x in zip(cols, v, strict=True)})
            self._truth.append(trow)
        self._frames.append(row)

    def _write_png(self, path: Path, img: np.ndarray, camera: PinholeCamera) -> None:
        a = np.asarray(img)
        if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3):
            raise SequenceError(
                path, None, f"image must be uint8 or uint16 (H, W[, 3]), got {a.dtype} {a.shape}"
            )
        _check_size(path, a.shape[1], a.shape[0], camera)
        path.parent.mkdir(parents=True, exist_ok=True)
        if self._pool is None:
            _imwrite(path, a, self._png_params)
            return
        self._drain(self._max_pending - 1)
        self._pending.append(self._pool.submit(_imwrite, path, a, self._png_params))

    def close(self) -> Path:
        """Write the small files and move the folder into place. Returns the final path."""
        if self._closed:
            return self.path
        try:
            self._drain(0)
            if self._pool is not None:
                self._pool.shutdown(wait=True)
            if not self._frames:
                raise SequenceError(
                    self.path / "frames.csv", None, "a sequence needs at least one frame"
                )
            _dump_yaml(
                {
                    "format": FORMAT_VERSION,
                    "name": self.name,
                    "kind": self.kind,
                    "rate_hz": self.rate_hz,
                    "generator": self.generator,
                },
                self._tmp / "sequence.yaml",
            )
            _dump_yaml(calibration_to_yaml(self.calibration), self._tmp / "calib.yaml")
            pd.DataFrame(self._frames, columns=FRAMES_COLUMNS[self.kind]).to_csv(
                self._tmp / "frames.csv", index=False
            )
            if self._truth:
                df = pd.DataFrame(self._truth)
                df.to_csv(self._tmp / "groundtruth.csv", index=False, float_format="%.15g")
            if self.target is not None:
                _dump_yaml(target_to_yaml(self.target), self._tmp / "target.yaml")
            replace_dir(self._tmp, self.path, self.overwrite)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path


def png_params(level: int | None) -> list[int]:
    """``cv2.imwrite`` parameters of a PNG zlib level (None: OpenCV's defaults). Level 0 also
    turns PNG's per-row filters off: without compression they only cost time (most of the
    encoding; docs/results/import.md)."""
    if level is None:
        return []
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(level)]
    if level == 0:
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    return params


def _imwrite(path: Path, img: np.ndarray, params: list[int]) -> None:
    if not cv2.imwrite(str(path), img, params):
        raise SequenceError(path, None, "could not write PNG")


def atomic_write(path: str | Path, write: Any) -> Path:
    """Call ``write(tmp_path)``, then rename the temporary file onto ``path``: readers see the
    old file or the whole new one, never a half-written one. The temporary file sits beside
    ``path`` with the same suffix (some writers pick the format by it) and is removed if
    ``write`` fails."""
    path = Path(path)
    tmp = path.parent / f".{path.stem}.tmp-{uuid.uuid4().hex[:8]}{path.suffix}"
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def replace_dir(src: Path, dst: Path, overwrite: bool) -> None:
    """Rename the finished folder ``src`` to ``dst``; with ``overwrite`` swap out an existing
    ``dst`` first (``src`` and ``dst`` must share a parent, so both renames are atomic)."""
    if dst.exists():
        if not overwrite:
            raise SequenceError(dst, None, "output folder already exists")
        backup = dst.parent / f".{dst.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(dst, backup)
        os.replace(src, dst)
        shutil.rmtree(backup, ignore_errors=True)
    else:
        os.replace(src, dst)


def write_sequence(sequence: Sequence, path: str | Path, overwrite: bool = False) -> Path:
    """Copy a sequence (e.g. one returned by `load_sequence`) to a new folder, atomically."""
    writer = SequenceWriter(
        path,
        name=sequence.name,
        kind=sequence.kind,
        rate_hz=sequence.rate_hz,
        calibration=sequence.calibration,
        generator=sequence.generator,
        target=sequence.target,
        overwrite=overwrite,
    )
    with writer:
        truth = sequence.truth
        for i, fr in enumerate(sequence.frames):
            cams: tuple[CameraName, ...] = (
                ("left", "right") if sequence.kind == "stereo" else ("left",)
            )
            masks: dict[str, np.ndarray] = {c: m for c in cams if (m := fr.mask(c)) is not None}
            kwargs: dict[str, Any] = {}
            if truth is not None:
                kwargs["truth"] = truth.pose(i)
                if truth.angular_velocity is not None:
                    kwargs["angular_velocity"] = truth.angular_velocity[i]
                if truth.linear_velocity is not None:
                    kwargs["linear_velocity"] = truth.linear_velocity[i]
            writer.add_frame(
                fr.index,
                fr.t_s,
                fr.left(),
                fr.right() if sequence.kind == "stereo" else None,
                masks=masks or None,
                **kwargs,
            )
    return writer.path


__all__ = [
    "FORMAT_VERSION",
    "Bracket",
    "Calibration",
    "Frame",
    "GeometryError",
    "GroundTruth",
    "Ring",
    "Sequence",
    "SequenceHeader",
    "SequenceWriter",
    "TargetGeometry",
    "check_png_header",
    "load_calibration",
    "load_header",
    "load_sequence",
    "load_target",
    "read_image",
    "write_sequence",
]
