"""`import_recording`: any supported recording to a sequence folder (format v1), atomically.

The steps: read ``--calib`` if given (it overrides what the recording carries), open the
source (`open_source`: the kind is told from the path), take the first frame to learn the
image sizes, check them against the calibration (an error names the calibration file and its
size field), then stream every frame into a `SequenceWriter` (a staging folder renamed into
place at the end), with truth interpolated onto the frame times if given. Whatever goes wrong
on the way — a corrupt message, a size change, too many unpaired images, a video shorter than
its timestamps — leaves nothing at the output path.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from itertools import chain
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from satpose.datasets.errors import SequenceError
from satpose.datasets.importers.bag import BagSource
from satpose.datasets.importers.calib import read_calibration_file
from satpose.datasets.importers.common import (
    DEFAULT_MAX_UNPAIRED,
    DEFAULT_TOLERANCE_S,
    FrameSource,
    RecordingError,
    SourceCalibration,
    SourceCamera,
    nominal_rate_hz,
    to_grey,
)
from satpose.datasets.importers.euroc import EurocSource, euroc_root
from satpose.datasets.importers.files import VIDEO_SUFFIXES, FolderSource, VideoSource
from satpose.datasets.importers.truth import TruthAligner
from satpose.datasets.sequence import Calibration, SequenceWriter, TargetGeometry, load_target

log = logging.getLogger(__name__)

SourceKind = Literal["rosbag1", "rosbag2", "euroc", "video", "folder"]
IMPORT_TOOL = "satpose-import"


def default_png_workers() -> int:
    """PNG-writing threads of an import: the machine's cores, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


@dataclass(frozen=True, kw_only=True)
class ImportOptions:
    """How to read a recording (every field has the CLI option of the same name).

    Attributes:
        left, right: bag image topics (None: picked, see `BagSource`).
        mono: import the left camera only.
        calib, calib_right: calibration file(s) overriding the recording's own
            (``calib_right``: a second ROS camera-info YAML for the right camera).
        timestamps, rate_hz: frame times of a video or image folder.
        pair_tolerance_s: the largest stamp difference of a stereo pair [s].
        max_unpaired: the largest fraction of images without a partner.
        grey: write grey images (colour converted with OpenCV's luma weights).
        max_frames: import only the first N frames (that have truth, with truth).
        name: sequence.yaml's name (default: the source's name).
        target: a target.yaml to copy in (validated).
        overwrite: replace an existing output folder.
        png_compression: zlib level 0-9 of the written PNGs (None: OpenCV's default).
        workers: threads encoding PNGs (`SequenceWriter`; OpenCV releases the GIL while it
            encodes): default the machine's cores, at most 4 (docs/results/import.md: 171
            stereo frames/s with one, 306 with two on 2 cores).
    """

    left: str | None = None
    right: str | None = None
    mono: bool = False
    calib: Path | None = None
    calib_right: Path | None = None
    timestamps: Path | None = None
    rate_hz: float | None = None
    pair_tolerance_s: float = DEFAULT_TOLERANCE_S
    max_unpaired: float = DEFAULT_MAX_UNPAIRED
    grey: bool = False
    max_frames: int | None = None
    name: str | None = None
    target: Path | None = None
    overwrite: bool = False
    png_compression: int | None = None
    workers: int = field(default_factory=default_png_workers)

    def __post_init__(self) -> None:
        if not self.pair_tolerance_s >= 0:
            raise RecordingError(Path("--pair-tolerance-ms"), None, "must be >= 0")
        if not 0.0 <= self.max_unpaired <= 1.0:
            raise RecordingError(Path("--max-unpaired"), None, "must be in [0, 1]")


@dataclass
class ImportReport:
    """What an import did (printed by the CLI, one fact per line).

    Attributes:
        path: the sequence folder written.
        kind: stereo or mono.
        source_kind: what the recording was.
        frames: frames written.
        t_span_s: first and last frame time [s].
        notes: one line per fact (topics, pairing, resampled lenses, frames without truth).
        truth_frames: frames with truth (0 without ``--truth``).
    """

    path: Path
    kind: str
    source_kind: SourceKind
    frames: int = 0
    t_span_s: tuple[float, float] = (0.0, 0.0)
    notes: list[str] = field(default_factory=list)
    truth_frames: int = 0


def source_kind(path: Path) -> SourceKind:
    """What a recording path is: a bag (ROS 1 ``.bag``; ROS 2 folder, ``.db3``, ``.mcap``),
    an EuRoC folder, a video file or an image folder."""
    if not path.exists():
        raise RecordingError(path, None, "does not exist")
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix == ".bag":
            return "rosbag1"
        if suffix in (".db3", ".mcap"):
            return "rosbag2"
        if suffix in VIDEO_SUFFIXES:
            return "video"
        raise RecordingError(
            path,
            None,
            "unknown recording: expected a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder), "
            f"an EuRoC folder, an image folder or a video ({', '.join(VIDEO_SUFFIXES)})",
        )
    if (path / "metadata.yaml").is_file():
        return "rosbag2"
    if euroc_root(path) is not None:
        return "euroc"
    return "folder"


def open_source(
    paths: list[Path], options: ImportOptions, calib: SourceCalibration | None
) -> tuple[FrameSource, SourceKind]:
    """The `FrameSource` for one recording path (two for a stereo pair of videos/folders)."""
    if not 1 <= len(paths) <= 2:
        raise RecordingError(Path(" ".join(map(str, paths))), None, "give one or two sources")
    kind = source_kind(paths[0])
    second = paths[1] if len(paths) == 2 else None
    if second is not None and kind not in ("video", "folder"):
        raise RecordingError(
            second, None, f"a second source goes with videos or folders, not a {kind}"
        )
    if second is not None and source_kind(second) != kind:
        raise RecordingError(second, None, f"is not a {kind} like {paths[0]}")
    if kind not in ("video", "folder") and (
        options.timestamps is not None or options.rate_hz is not None
    ):
        raise RecordingError(
            paths[0],
            "--timestamps/--rate",
            f"a {kind} has its own clock; these are for videos and image folders",
        )
    if kind in ("rosbag1", "rosbag2"):
        return (
            BagSource(
                paths[0],
                left=options.left,
                right=options.right,
                mono=options.mono,
                tolerance_s=options.pair_tolerance_s,
                max_unpaired=options.max_unpaired,
                prefer_topics=calib.topics if calib is not None else (),
            ),
            kind,
        )
    if options.left is not None or options.right is not None:
        raise RecordingError(paths[0], "--left/--right", "topics are for bags")
    if kind == "euroc":
        src: FrameSource = EurocSource(
            paths[0],
            mono=options.mono,
            tolerance_s=options.pair_tolerance_s,
            max_unpaired=options.max_unpaired,
        )
        return src, kind
    if kind == "video":
        right = None if options.mono else second
        return VideoSource(
            paths[0], right, timestamps=options.timestamps, rate_hz=options.rate_hz
        ), kind
    return (
        FolderSource(
            paths[0],
            None if options.mono else second,
            timestamps=options.timestamps,
            rate_hz=options.rate_hz,
            mono=options.mono,
        ),
        kind,
    )


def _resolve_calibration(
    src: FrameSource, calib: SourceCalibration, sizes: list[tuple[int, int]]
) -> tuple[Calibration, list[tuple[np.ndarray, np.ndarray] | None], list[str]]:
    """Format v1's calibration for the first frame's image sizes, the resampling maps of
    lenses format v1 cannot express, and notes."""
    cams: list[SourceCamera] = [calib.left]
    if src.kind == "stereo":
        if calib.right is None:
            raise RecordingError(
                calib.path,
                "cameras",
                f"one camera, but the recording is stereo ({src.image_origin('left')} and "
                f"{src.image_origin('right')}): give a stereo calibration with --calib, or --mono",
            )
        if calib.right_from_left is None:
            raise RecordingError(
                calib.path,
                f"{calib.right.field} R/P",
                "the camera infos carry no stereo baseline: give the extrinsic with --calib "
                "(a Kalibr camchain or OpenCV stereo YAML)",
            )
        cams.append(calib.right)
    sized = [c.with_size(s) for c, s in zip(cams, sizes, strict=True)]
    notes = []
    if src.kind == "mono" and calib.is_stereo:
        notes.append(f"mono import: the left camera of the stereo calibration {calib.path}")
    maps = []
    for name, cam in zip(("left", "right"), sized, strict=False):
        maps.append(cam.undistort_maps())
        if cam.needs_resampling:
            notes.append(
                f"{name} camera: {cam.model} lens ({cam.path}: {cam.field}) resampled onto a "
                "pinhole camera with the same K and no distortion (format v1 is pinhole-radtan)"
            )
    pinholes = [c.pinhole() for c in sized]
    return (
        Calibration(
            left=pinholes[0],
            right=pinholes[1] if len(pinholes) == 2 else None,
            right_from_left=calib.right_from_left if len(pinholes) == 2 else None,
        ),
        maps,
        notes,
    )


def _size(img: np.ndarray) -> tuple[int, int]:
    return int(img.shape[1]), int(img.shape[0])


def recording_calibration(
    src: FrameSource, override: SourceCalibration | None
) -> tuple[SourceCalibration, str]:
    """The calibration to use: ``override`` (``--calib``) or what the recording carries, and
    a note saying which. Raises `RecordingError` when there is none."""
    if override is not None:
        return override, f"calibration: {override.path} (--calib)"
    calib = src.calibration()
    if calib is None:
        raise RecordingError(
            src.path,
            "calibration",
            "the recording carries none: give --calib FILE (Kalibr camchain, OpenCV "
            "YAML/XML, ROS camera-info YAML or satpose calib.yaml)",
        )
    return calib, f"calibration: from the recording ({calib.path})"


def first_frame_calibration(
    src: FrameSource,
    calib: SourceCalibration,
    first: tuple[float, np.ndarray, np.ndarray | None],
    grey: bool,
) -> tuple[
    Calibration, list[tuple[np.ndarray, np.ndarray] | None], list[tuple[int, int]], list[str]
]:
    """Format v1's calibration of ``calib`` (`recording_calibration`), sized by the
    recording's first frame.

    Returns:
        the calibration, each camera's resampling maps (None: the images stay as they are),
        the image sizes ``(width, height)`` of the first frame (after ``grey``) and notes
        (lenses resampled).

    Raises:
        RecordingError: a calibration whose size disagrees with the images, or that does not
        fit the recording (mono for a stereo recording, no stereo extrinsic).
    """
    _, left0, right0 = first
    if grey:
        left0 = to_grey(left0)
        right0 = to_grey(right0) if right0 is not None else None
    sizes = [_size(left0)] + ([_size(right0)] if right0 is not None else [])
    calibration, maps, notes = _resolve_calibration(src, calib, sizes)
    return calibration, maps, sizes, notes


def prepare_images(
    src: FrameSource,
    t_s: float,
    images: list[np.ndarray],
    sizes: list[tuple[int, int]],
    maps: list[tuple[np.ndarray, np.ndarray] | None],
    grey: bool,
) -> list[np.ndarray]:
    """A frame's images as format v1 stores them: grey if asked, the first frame's size
    (else `RecordingError` naming the camera's origin and the time), resampled where the
    lens needs it (`first_frame_calibration`'s maps)."""
    out = []
    for k, (cam, img) in enumerate(zip(("left", "right"), images, strict=False)):
        if grey:
            img = to_grey(img)
        if _size(img) != sizes[k]:
            raise RecordingError(
                Path(src.image_origin(cam)),
                "image size",
                f"the image at t = {t_s:.9f} s is {_size(img)[0]}x{_size(img)[1]}, the "
                f"first one was {sizes[k][0]}x{sizes[k][1]}",
            )
        m = maps[k]
        if m is not None:
            img = cv2.remap(img, m[0], m[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        out.append(img)
    return out


def import_recording(
    sources: list[Path],
    out: Path,
    options: ImportOptions | None = None,
    *,
    truth: TruthAligner | None = None,
    progress: Callable[[int], None] | None = None,
) -> ImportReport:
    """Import a recording into the sequence folder ``out`` (format v1), atomically.

    Args:
        sources: the recording: one path (bag, EuRoC folder, video, image folder) or two
            (left and right videos or image folders).
        out: the sequence folder to write (must not exist unless ``options.overwrite``).
        options: how to read it (`ImportOptions`).
        truth: ground truth to interpolate onto the frame times (frames without truth are
            left out and counted).
        progress: called with the number of frames written so far, after each frame.

    Returns:
        What was written (`ImportReport`).

    Raises:
        RecordingError / SequenceError: one line naming the file and field; nothing is left
        at ``out``.
    """
    opts = options or ImportOptions()
    out = Path(out)
    if out.is_dir() and not any(out.iterdir()):
        opts = replace(opts, overwrite=True)  # an empty folder is as good as none
    if out.exists() and not opts.overwrite:
        raise SequenceError(
            out, None, "output folder already exists (choose another or --overwrite)"
        )
    override = (
        read_calibration_file(opts.calib, opts.calib_right) if opts.calib is not None else None
    )
    target = load_target(opts.target) if opts.target is not None else None
    src, kind = open_source([Path(s) for s in sources], opts, override)
    report = ImportReport(path=out, kind=src.kind, source_kind=kind)
    frames: Iterator[tuple[float, np.ndarray, np.ndarray | None]] = src.frames()
    try:
        calib, note = recording_calibration(src, override)
        report.notes.append(note)
        first = next(frames, None)
        if first is None:
            src.check()
            raise RecordingError(src.path, None, "holds no frames")
        calibration, maps, sizes, lens_notes = first_frame_calibration(src, calib, first, opts.grey)
        report.notes.extend(lens_notes)
        _write(
            src, frames, first, out, opts, calibration, maps, sizes, target, truth, report, progress
        )
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()
        src.close()
    report.notes[:0] = src.notes()
    return report


def _write(
    src: FrameSource,
    frames: Iterator[tuple[float, np.ndarray, np.ndarray | None]],
    first: tuple[float, np.ndarray, np.ndarray | None],
    out: Path,
    opts: ImportOptions,
    calibration: Calibration,
    maps: list[tuple[np.ndarray, np.ndarray] | None],
    sizes: list[tuple[int, int]],
    target: TargetGeometry | None,
    truth: TruthAligner | None,
    report: ImportReport,
    progress: Callable[[int], None] | None,
) -> None:
    name = opts.name or src.path.name.removesuffix(".bag") or "imported"
    writer = SequenceWriter(
        out,
        name=name,
        kind=src.kind,
        rate_hz=src.rate_hz() or 1.0,
        calibration=calibration,
        target=target,
        overwrite=opts.overwrite,
        png_compression=opts.png_compression,
        workers=opts.workers,
    )
    times: list[float] = []
    no_truth: list[float] = []
    with writer:
        for t, left, right in chain([first], frames):
            pose = None
            if truth is not None:
                pose = truth.pose_at(t)
                if pose is None:
                    no_truth.append(t)
                    continue
            imgs = prepare_images(
                src, t, [left] + ([right] if right is not None else []), sizes, maps, opts.grey
            )
            if times and t <= times[-1]:
                raise RecordingError(
                    Path(src.image_origin("left")),
                    "time",
                    f"{t} s does not come after {times[-1]} s",
                )
            writer.add_frame(
                len(times), t, imgs[0], imgs[1] if len(imgs) == 2 else None, truth=pose
            )
            times.append(t)
            if progress is not None:
                progress(len(times))
            if opts.max_frames is not None and len(times) >= opts.max_frames:
                break
        else:
            src.check()
        if not times:
            assert truth is not None
            a, b = truth.span
            raise RecordingError(
                truth.trajectory.path,
                "t",
                f"no frame has truth: the truth spans {a:.6f} to {b:.6f} s, the frames "
                f"{no_truth[0]:.6f} to {no_truth[-1]:.6f} s (a clock offset? --truth-time-offset)",
            )
        t_arr = np.array(times)
        writer.rate_hz = src.rate_hz() or nominal_rate_hz(t_arr)
        generator: dict[str, object] = {
            "tool": IMPORT_TOOL,
            "source": kind_provenance(src, report),
        }
        if truth is not None:
            generator["truth"] = truth.provenance()
        writer.generator = generator
    report.frames = len(times)
    report.t_span_s = (times[0], times[-1])
    if truth is not None:
        report.truth_frames = len(times)
        if no_truth:
            report.notes.append(_no_truth_note(no_truth, truth))


def kind_provenance(src: FrameSource, report: ImportReport) -> dict[str, object]:
    """sequence.yaml's ``generator.source``: what was imported and how."""
    from importlib.metadata import version

    out: dict[str, object] = {"kind": report.source_kind, **src.provenance()}
    out["satpose_version"] = version("satpose")
    return out


def _no_truth_note(times: list[float], truth: TruthAligner) -> str:
    """How many frames were left out for want of truth, and where they were."""
    a, b = truth.span
    before = sum(t < a for t in times)
    after = sum(t > b for t in times)
    gaps = len(times) - before - after
    parts = [f"{before} before the truth starts ({a:.6f} s)", f"{after} after it ends ({b:.6f} s)"]
    if gaps:
        parts.append(f"{gaps} in gaps longer than {truth.max_gap_s} s")
    return f"{len(times)} frames without truth left out: " + ", ".join(parts)
