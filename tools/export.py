"""`satpose export`: a run's estimate as a TUM file, a CSV file or a ROS 2 bag.

- ``tum``: ``t tx ty tz qx qy qz qw`` of ``left_cam_from_target`` (`write_tum`, 9 decimals, as
  trajectory.tum; evo reads it).
- ``csv``: trajectory.csv's columns plus the full 6x6 pose and twist covariances
  (`satpose.tools.trajectories.estimate_csv_frame`), at full float64 precision;
  `satpose eval SEQ FILE.csv` reads it back and then reports the NEES and spin error too.
- ``rosbag2``: a ROS 2 bag folder (rosbag2 format version 8, sqlite3 storage, the Jazzy
  message definitions; written with the ``rosbags`` library, no ROS install needed) with one
  message per frame on each of two topics:

  - `POSE_TOPIC`, ``geometry_msgs/msg/PoseWithCovarianceStamped``: the target's pose in the
    left camera frame (``header.frame_id`` = `CAMERA_FRAME_ID`; position = ``t``,
    orientation = the rotation of ``left_cam_from_target``). Covariance: ROS's row-major 6x6
    over ``[x, y, z, rotation about X, Y, Z]``, all about the axes of ``header.frame_id``
    (`ros_pose_covariance`: the estimate's right-perturbation covariance over [rotation,
    translation] in target axes, re-ordered and rotated into the camera axes; first order).
  - `TWIST_TOPIC`, ``geometry_msgs/msg/TwistWithCovarianceStamped``: the body twist in the
    target frame (``header.frame_id`` = `TARGET_FRAME_ID`; ``linear`` = velocity of the target
    origin in target axes [m/s], ``angular`` = angular velocity [rad/s]), covariance over
    ``[vx, vy, vz, wx, wy, wz]`` (`ros_twist_covariance`, a re-ordering only), as
    nav_msgs/Odometry gives its twist in the child frame.

  ``header.stamp`` and the bag's receive time are the frame time ``t_s`` in nanoseconds.

Every output appears complete or not at all: files are written to a temporary path and
renamed, a bag is built in a hidden folder next to ``--out`` and renamed into place.
"""

from __future__ import annotations

import argparse
import shutil
import uuid
from pathlib import Path
from typing import Any, Literal

import numpy as np

from satpose.backend import Estimate
from satpose.backend.pose3 import ROT, TRANS
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import replace_dir
from satpose.tools.files import ResultFileError, check_out, write_tum
from satpose.tools.pipeline import read_estimate_npz
from satpose.tools.trajectories import write_estimate_csv

ExportFormat = Literal["tum", "csv", "rosbag2"]
EXPORT_FORMATS: tuple[str, ...] = ("tum", "csv", "rosbag2")

ESTIMATE_FILES = {
    "main": "estimate.npz",
    "smoothed": "estimate_smoothed.npz",
    "offline": "estimate_offline.npz",
    "online": "estimate_online.npz",
    "kalman": "estimate_kalman.npz",
}
"""``--estimate`` choices: the run's chosen estimator (as trajectory.csv: causal for online
and kalman), iSAM2's smoothed estimate, and the comparison estimators' (`satpose run`)."""

POSE_TOPIC = "/satpose/target/pose"
TWIST_TOPIC = "/satpose/target/twist"
CAMERA_FRAME_ID = "left_camera"
"""``header.frame_id`` of the pose: the left camera (OpenCV axes: x right, y down, z forward)."""
TARGET_FRAME_ID = "target"
"""``header.frame_id`` of the twist: the target's body frame."""
POSE_MSGTYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TWIST_MSGTYPE = "geometry_msgs/msg/TwistWithCovarianceStamped"
ROSBAG2_VERSION: Literal[8, 9] = 8


class ExportError(ResultFileError):
    """A run cannot be exported (missing estimate, existing output)."""


def ros_pose_covariance(T: Rigid3, covariance: np.ndarray) -> np.ndarray:
    """ROS's pose covariance (6x6 over ``[x, y, z, rx, ry, rz]``, camera axes) from the
    estimate's (``[rotation, translation]``, right perturbation ``T_true = T Exp(xi)``, target
    axes): to first order the position error in camera axes is ``R xi_t`` and the rotation
    error about the camera axes ``R xi_r`` (``R Exp(xi_r) = Exp(R xi_r) R``), so
    ``C_ros = J C J^T`` with ``J = [[0, R], [R, 0]]``."""
    J = np.zeros((6, 6))
    J[0:3, TRANS] = T.R
    J[3:6, ROT] = T.R
    C = J @ np.asarray(covariance, float) @ J.T
    return 0.5 * (C + C.T)


def ros_twist_covariance(covariance: np.ndarray) -> np.ndarray:
    """ROS's twist covariance (over ``[vx, vy, vz, wx, wy, wz]``) from the estimate's body-twist
    covariance (over ``[omega, v]``, both in target axes): a re-ordering."""
    J = np.zeros((6, 6))
    J[0:3, TRANS] = np.eye(3)
    J[3:6, ROT] = np.eye(3)
    return J @ np.asarray(covariance, float) @ J.T


def stamp_ns(t_s: float) -> int:
    """A frame time [s] as integer nanoseconds (the bag's and the header's clock)."""
    return round(float(t_s) * 1e9)


def load_run_estimate(run: Path, which: str = "main") -> Estimate:
    """The estimate ``which`` (`ESTIMATE_FILES`) of a run folder."""
    run = Path(run)
    if not run.is_dir():
        raise ExportError(f"{run}: not a run folder (satpose run --out)")
    name = ESTIMATE_FILES.get(which)
    if name is None:
        raise ExportError(f"unknown estimate {which!r}; choose from {', '.join(ESTIMATE_FILES)}")
    path = run / name
    if not path.is_file():
        present = [k for k, f in ESTIMATE_FILES.items() if (run / f).is_file()]
        raise ExportError(
            f"{path}: missing (this run has: {', '.join(present) or 'no estimate at all'})"
        )
    est = read_estimate_npz(path)
    if len(est) == 0:
        raise ExportError(f"{path}: the estimate holds no frames")
    return est


def export_run(
    run: Path,
    fmt: ExportFormat,
    out: Path,
    *,
    which: str = "main",
    overwrite: bool = False,
) -> Path:
    """Write the run's estimate ``which`` as ``fmt`` to ``out`` (`export_estimate`)."""
    return export_estimate(load_run_estimate(run, which), fmt, out, overwrite=overwrite)


def export_estimate(
    est: Estimate, fmt: ExportFormat, out: Path, *, overwrite: bool = False
) -> Path:
    """Write ``est`` as ``fmt`` to ``out`` (module docstring); an existing ``out`` is replaced
    only with ``overwrite`` (a folder only if it is a bag)."""
    out = Path(out)
    if fmt in ("tum", "csv"):
        if out.is_dir():
            raise ExportError(f"{out}: is a folder (give a file name)")
        if out.exists() and not overwrite:
            raise ExportError(f"{out}: exists already (choose another name or --overwrite)")
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            if fmt == "tum":
                write_tum(est.t_s, est.left_cam_from_target, out)
            else:
                write_estimate_csv(est, out)
        except OSError as exc:
            raise ExportError(f"{out}: cannot write ({exc.strerror or exc})") from None
        return out
    if fmt == "rosbag2":
        return write_rosbag2(est, out, overwrite=overwrite)
    raise ExportError(f"unknown export format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}")


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def write_rosbag2(est: Estimate, out: Path, *, overwrite: bool = False) -> Path:
    """The estimate as a ROS 2 bag folder ``out`` (module docstring), built next to it and
    renamed into place."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.errors import WriterError

    check_out(out, overwrite, marker="metadata.yaml", what="a rosbag2", error=ExportError)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExportError(f"{out}: cannot create the folder ({exc.strerror or exc})") from None
    # the bag is built as <hidden staging folder>/<out's name>, because the Writer names its
    # storage file after the bag folder (metadata.yaml refers to it by that name)
    stage = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    bag = stage / out.name
    store = _typestore()
    types = store.types
    try:
        stage.mkdir()
        with Writer(bag, version=ROSBAG2_VERSION) as writer:
            pose_conn = writer.add_connection(POSE_TOPIC, POSE_MSGTYPE, typestore=store)
            twist_conn = writer.add_connection(TWIST_TOPIC, TWIST_MSGTYPE, typestore=store)
            for k, T in enumerate(est.left_cam_from_target):
                ns = stamp_ns(est.t_s[k])
                stamp = types["builtin_interfaces/msg/Time"](
                    sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
                )
                q = T.quat_xyzw
                pose = types[POSE_MSGTYPE](
                    header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=CAMERA_FRAME_ID),
                    pose=types["geometry_msgs/msg/PoseWithCovariance"](
                        pose=types["geometry_msgs/msg/Pose"](
                            position=types["geometry_msgs/msg/Point"](
                                x=float(T.t[0]), y=float(T.t[1]), z=float(T.t[2])
                            ),
                            orientation=types["geometry_msgs/msg/Quaternion"](
                                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                            ),
                        ),
                        covariance=ros_pose_covariance(T, est.pose_covariance[k]).ravel(),
                    ),
                )
                w = est.twist[k, ROT]
                v = est.twist[k, TRANS]
                twist = types[TWIST_MSGTYPE](
                    header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=TARGET_FRAME_ID),
                    twist=types["geometry_msgs/msg/TwistWithCovariance"](
                        twist=types["geometry_msgs/msg/Twist"](
                            linear=types["geometry_msgs/msg/Vector3"](
                                x=float(v[0]), y=float(v[1]), z=float(v[2])
                            ),
                            angular=types["geometry_msgs/msg/Vector3"](
                                x=float(w[0]), y=float(w[1]), z=float(w[2])
                            ),
                        ),
                        covariance=ros_twist_covariance(est.twist_covariance[k]).ravel(),
                    ),
                )
                writer.write(pose_conn, ns, store.serialize_cdr(pose, POSE_MSGTYPE))
                writer.write(twist_conn, ns, store.serialize_cdr(twist, TWIST_MSGTYPE))
        replace_dir(bag, out, overwrite=True)
        shutil.rmtree(stage, ignore_errors=True)
    except (OSError, WriterError) as exc:
        shutil.rmtree(stage, ignore_errors=True)
        raise ExportError(f"{out}: cannot write the bag ({exc})") from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return out


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------


def register(subparsers: Any) -> None:
    """Add ``satpose export`` to the CLI."""
    p = subparsers.add_parser(
        "export",
        help="a run's estimate as TUM, CSV (with covariances) or a ROS 2 bag",
        description="Write a run's estimate for other tools: tum (t tx ty tz qx qy qz qw of "
        "left_cam_from_target), csv (trajectory.csv's columns plus the 6x6 pose and twist "
        "covariances) or rosbag2 (geometry_msgs/PoseWithCovarianceStamped on "
        f"{POSE_TOPIC} and TwistWithCovarianceStamped on {TWIST_TOPIC}; docs/pipeline.md).",
    )
    p.add_argument("run", type=Path, metavar="RUN", help="run folder (satpose run --out)")
    p.add_argument("--format", choices=EXPORT_FORMATS, required=True, help="output format")
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="PATH",
        help="output file (tum, csv) or bag folder (rosbag2)",
    )
    p.add_argument(
        "--estimate",
        choices=list(ESTIMATE_FILES),
        default="main",
        help="which estimate: main (the run's estimator, as trajectory.csv; default), "
        "smoothed (iSAM2's at the end), offline, online or kalman (the comparison runs)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(handler=cmd_export)


def cmd_export(args: argparse.Namespace) -> None:
    est = load_run_estimate(args.run, args.estimate)
    out = export_estimate(est, args.format, args.out, overwrite=args.overwrite)
    what = {
        "tum": "poses",
        "csv": "poses, twists and covariances",
        "rosbag2": f"{POSE_TOPIC} and {TWIST_TOPIC} messages",
    }[args.format]
    print(f"wrote {len(est)} frames ({what}) of {args.run}'s {args.estimate} estimate to {out}")
