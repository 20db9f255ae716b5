"""``satpose import SOURCE [SOURCE2] --out SEQ``: a lab's recording into a sequence folder.

SOURCE is a ROS 1 bag (``.bag``), a ROS 2 bag (folder, ``.db3`` or ``.mcap``), an EuRoC/ASL
folder, a video file (a second one for the right camera) or a folder of images (a second
folder, or ``left/`` + ``right/`` inside, for stereo). The calibration comes from the
recording (bag CameraInfo, EuRoC sensor.yaml) unless ``--calib`` gives a file (Kalibr
camchain, OpenCV FileStorage YAML/XML, ROS camera-info YAML, satpose calib.yaml). Truth
(``--truth``: TUM or CSV, in the convention ``--truth-frame``) is interpolated onto the frame
times. The library function is `satpose.datasets.importers.import_recording`; the formats,
keys and conventions are in docs/import.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from satpose.datasets.importers import (
    TRUTH_FRAMES,
    ImportOptions,
    RecordingError,
    TruthAligner,
    TruthTrajectory,
    import_recording,
    read_hand_eye,
)
from satpose.datasets.importers.common import DEFAULT_MAX_UNPAIRED, DEFAULT_TOLERANCE_S
from satpose.tools.argtypes import positive_int
from satpose.tools.files import ResultFileError, check_out, read_tum

_TIME_S = ("t_s", "t", "time", "timestamp", "#t_s", "# t_s", "#t", "# t")
_TIME_NS = ("t_ns", "#timestamp [ns]", "timestamp [ns]", "#timestamp", "timestamp_ns")
_POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
_EUROC = {
    "p_rs_r_x [m]": "tx",
    "p_rs_r_y [m]": "ty",
    "p_rs_r_z [m]": "tz",
    "q_rs_x []": "qx",
    "q_rs_y []": "qy",
    "q_rs_z []": "qz",
    "q_rs_w []": "qw",
}
"""EuRoC's ground-truth columns (``world_from_body``: R the world, S the body)."""


def read_trajectory(path: Path) -> TruthTrajectory:
    """A truth trajectory file: TUM (``t tx ty tz qx qy qz qw`` per line, space separated,
    ``#`` comments) or CSV with a header naming a time column (``t_s``/``t``/``time``/
    ``timestamp`` in seconds, or ``t_ns``/``#timestamp [ns]`` in nanoseconds) and ``tx, ty, tz,
    qx, qy, qz, qw`` (EuRoC's ``p_RS_R_x [m] … q_RS_w []`` also)."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(path, None, "truth file does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(path, None, f"cannot read ({exc})") from None
    first = next((ln for ln in text.splitlines() if ln.strip()), "")
    if "," not in first:
        try:
            t, poses = read_tum(path)
        except ResultFileError as exc:
            raise RecordingError(path, None, str(exc).removeprefix(f"{path}: ")) from None
        if not poses:
            raise RecordingError(path, None, "holds no poses")
        return TruthTrajectory(
            t_s=np.asarray(t, dtype=float),
            translation=np.stack([p.t for p in poses]),
            quat_xyzw=np.stack([p.quat_xyzw for p in poses]),
            path=path,
        )
    return _read_csv(path, text)


def _read_csv(path: Path, text: str) -> TruthTrajectory:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    header = [c.strip().lower() for c in lines[0].split(",")]
    names = [_EUROC.get(h, h) for h in header]
    scale, tcol = None, None
    for i, h in enumerate(names):
        if h in _TIME_NS:
            scale, tcol = 1e-9, i
            break
        if h in _TIME_S:
            scale, tcol = 1.0, i
            break
    if tcol is None or scale is None:
        raise RecordingError(path, "header", f"no time column (t_s or t_ns) among {header}")
    missing = [c for c in _POSE if c not in names]
    if missing:
        raise RecordingError(path, ",".join(missing), f"missing column(s); header is {header}")
    cols = [names.index(c) for c in _POSE]
    t = np.empty(len(lines) - 1)
    v = np.empty((len(lines) - 1, 7))
    for k, line in enumerate(lines[1:]):
        cells = [c.strip() for c in line.split(",")]
        try:
            tc = cells[tcol]
            t[k] = int(tc) / 1_000_000_000 if scale != 1.0 and tc.isdigit() else float(tc) * scale
            v[k] = [float(cells[c]) for c in cols]
        except (IndexError, ValueError):
            raise RecordingError(path, f"line {k + 2}", f"not a pose row: {line!r}") from None
    if t.size == 0:
        raise RecordingError(path, None, "holds no poses")
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1) | ~np.isfinite(t))
    if bad.size:
        raise RecordingError(path, f"line {int(bad[0]) + 2}", "holds a NaN or infinity")
    norms = np.linalg.norm(v[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
    if bad.size:
        k = int(bad[0])
        raise RecordingError(
            path, f"line {k + 2} qx,qy,qz,qw", f"quaternion is not unit norm (|q| = {norms[k]:.9f})"
        )
    return TruthTrajectory(t_s=t, translation=v[:, :3], quat_xyzw=v[:, 3:], path=path)


def _handler(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    if args.truth is None and (args.truth_frame != "left_cam_from_target" or args.hand_eye):
        raise RecordingError(Path("--truth-frame"), None, "goes with --truth FILE")
    options = recording_options(
        args,
        mono=args.mono,
        timestamps=args.timestamps,
        rate_hz=args.rate,
        max_frames=args.frames,
        name=args.name,
        target=args.target,
        overwrite=args.overwrite,
        png_compression=args.png_compression,
        **({} if args.workers is None else {"workers": args.workers}),
    )
    truth = None
    if args.truth is not None:
        truth = TruthAligner(
            read_trajectory(args.truth),
            frame=args.truth_frame,
            hand_eye=read_hand_eye(args.hand_eye) if args.hand_eye else None,
            time_offset_s=args.truth_time_offset,
            max_gap_s=args.truth_max_gap,
        )
    # Replace only a sequence folder (or an empty one), never someone's other files.
    check_out(args.out, args.overwrite, marker="sequence.yaml", what="a sequence")
    start = time.perf_counter()
    with tqdm(desc="import", unit="frame", file=sys.stderr, dynamic_ncols=True, delay=0.5) as bar:
        report = import_recording(
            args.source, args.out, options, truth=truth, progress=lambda _n: bar.update(1)
        )
    elapsed = time.perf_counter() - start
    for note in report.notes:
        print(f"  {note}")
    truth_text = f", truth for all {report.truth_frames}" if truth is not None else ""
    print(
        f"wrote {report.frames} {report.kind} frames ({report.t_span_s[0]:.6f} to "
        f"{report.t_span_s[1]:.6f} s{truth_text}) from the {report.source_kind} to "
        f"{report.path} in {elapsed:.1f} s ({report.frames / max(elapsed, 1e-9):.0f} frames/s)"
    )


def recording_options(args: argparse.Namespace, **fields: Any) -> ImportOptions:
    """`ImportOptions` from the options `add_recording_options` added (and ``fields``)."""
    calib = args.calib or []
    if len(calib) > 2:
        raise RecordingError(Path(calib[2]), "--calib", "give one file, or two ROS camera infos")
    return ImportOptions(
        left=args.left,
        right=args.right,
        calib=calib[0] if calib else None,
        calib_right=calib[1] if len(calib) == 2 else None,
        pair_tolerance_s=args.pair_tolerance_ms / 1e3,
        max_unpaired=args.max_unpaired,
        grey=args.grey,
        **fields,
    )


def add_recording_options(cameras: Any, timing: Any) -> None:
    """The options that say how a recording's frames are read — image topics, calibration,
    grey, stereo pairing — shared by ``satpose import`` and ``satpose track BAG --live``
    (`recording_options` reads them). ``cameras``, ``timing``: argparse groups (or parsers)."""
    cameras.add_argument(
        "--left", metavar="TOPIC", help="bag: the left (or only) camera's image topic"
    )
    cameras.add_argument("--right", metavar="TOPIC", help="bag: the right camera's image topic")
    cameras.add_argument(
        "--calib",
        type=Path,
        action="append",
        metavar="FILE",
        help="calibration overriding the recording's: Kalibr camchain, OpenCV YAML/XML, ROS "
        "camera-info YAML (twice: left then right), satpose calib.yaml",
    )
    cameras.add_argument(
        "--grey", action="store_true", help="grey images (colour converted as they are read)"
    )
    timing.add_argument(
        "--pair-tolerance-ms",
        type=_nonneg,
        default=DEFAULT_TOLERANCE_S * 1e3,
        metavar="MS",
        help=f"largest stamp difference of a stereo pair (default {DEFAULT_TOLERANCE_S * 1e3:g})",
    )
    timing.add_argument(
        "--max-unpaired",
        type=_fraction,
        default=DEFAULT_MAX_UNPAIRED,
        metavar="FRACTION",
        help=f"largest fraction of unpaired images accepted (default {DEFAULT_MAX_UNPAIRED:g})",
    )


def _nonneg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def _positive(text: str) -> float:
    v = _nonneg(text)
    if v == 0:
        raise argparse.ArgumentTypeError("expected a positive number, got 0")
    return v


def _fraction(text: str) -> float:
    v = _nonneg(text)
    if v > 1:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1], got {text!r}")
    return v


def register(subparsers: Any) -> None:
    """Add ``satpose import``."""
    p = subparsers.add_parser(
        "import",
        help="a lab's recording (ROS bag, EuRoC folder, video, images) into a sequence folder",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument(
        "source",
        type=Path,
        nargs="+",
        metavar="SOURCE",
        help="bag (.bag, ROS 2 folder, .db3, .mcap), EuRoC folder, video or image folder; "
        "a second video or folder is the right camera",
    )
    p.add_argument("--out", type=Path, required=True, metavar="SEQ", help="sequence folder")
    g = p.add_argument_group("cameras and calibration")
    t = p.add_argument_group("time")
    add_recording_options(g, t)
    g.add_argument("--mono", action="store_true", help="import the left camera only")
    t.add_argument(
        "--timestamps", type=Path, metavar="FILE", help="video/images: one time per frame"
    )
    t.add_argument("--rate", type=_positive, metavar="HZ", help="video/images: the frame rate")
    t.add_argument("--frames", type=positive_int, metavar="N", help="import the first N frames")
    r = p.add_argument_group("truth and target")
    r.add_argument("--truth", type=Path, metavar="FILE", help="TUM or CSV trajectory")
    r.add_argument(
        "--truth-frame",
        choices=TRUTH_FRAMES,
        default="left_cam_from_target",
        help="what the truth poses are (default left_cam_from_target)",
    )
    r.add_argument(
        "--hand-eye",
        type=Path,
        metavar="FILE",
        help="world_from_marker: YAML with left_cam_from_marker and world_from_target",
    )
    r.add_argument(
        "--truth-time-offset",
        type=float,
        default=0.0,
        metavar="S",
        help="added to the truth's times to put them on the camera clock",
    )
    r.add_argument(
        "--truth-max-gap",
        type=_positive,
        metavar="S",
        help="do not interpolate across truth samples further apart than this",
    )
    r.add_argument("--target", type=Path, metavar="FILE", help="target.yaml to copy in")
    o = p.add_argument_group("output")
    o.add_argument(
        "--png-compression",
        type=int,
        choices=range(10),
        metavar="0-9",
        help="zlib level of the PNGs (default OpenCV's 1; 0 is fastest and largest; "
        "docs/results/import.md)",
    )
    o.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="threads writing PNGs (default: the machine's cores, at most 4)",
    )
    p.add_argument("--name", help="sequence name (default: the source's name)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.set_defaults(handler=_handler)
