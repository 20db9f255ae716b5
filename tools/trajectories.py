"""Trajectory files another tool wrote (or we did): TUM and CSV readers, the CSV writer of an
estimate, and the association of a trajectory's poses with a sequence's frames by time.

Convention: a pose is ``left_cam_from_target`` (the target's pose in the left camera frame:
``p_cam = R p_target + t``), the pose groundtruth.csv, trajectory.tum and trajectory.csv hold.
A file holding the inverse, ``target_from_left_cam`` (the camera's pose in the target frame, as
a SLAM tool that maps the target writes it), is read with ``inverse=True``.

- TUM: ``t tx ty tz qx qy qz qw`` per line, space separated, ``#`` comments (`read_tum`).
- CSV: a header row naming the columns, in any order, others ignored: the time ``t_s`` or
  ``timestamp`` [s]; ``tx ty tz qx qy qz qw``; optional ``wx wy wz`` (angular velocity in the
  target frame [rad/s], for the spin-rate error) and the 36 ``pose_cov_<i><j>`` (row-major
  6x6 pose covariance over [rotation (rad), translation (m)], right perturbation
  ``T_true = T Exp(xi)``, GTSAM's order, for the NEES). Our trajectory.csv reads as it is;
  `satpose export --format csv` adds the covariances (`estimate_csv_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from satpose.backend import Estimate
from satpose.backend.pose3 import adjoint
from satpose.datasets.errors import shown
from satpose.datasets.geometry import Rigid3
from satpose.tools.files import ResultFileError, atomic_write, read_tum
from satpose.tools.pipeline import estimate_frame

TrajectoryFormat = Literal["tum", "csv"]

TIME_COLUMNS = ("t_s", "timestamp")
"""CSV time columns accepted, first match wins [s]."""
POSE_COLUMNS = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
POSE_COV_COLUMNS = tuple(f"pose_cov_{i}{j}" for i in range(6) for j in range(6))
"""Row-major 6x6 pose covariance over [rotation, translation] (right perturbation)."""
TWIST_COV_COLUMNS = tuple(f"twist_cov_{i}{j}" for i in range(6) for j in range(6))
"""Row-major 6x6 body-twist covariance over [omega (target axes), v (target axes)]."""
QUAT_NORM_TOL = 1e-6
"""A quaternion whose norm differs from 1 by more than this is refused (as `read_tum` does)."""


@dataclass(frozen=True, kw_only=True)
class PoseTrack:
    """Timed poses read from a file.

    Attributes:
        t_s: (N,) times [s], strictly increasing.
        poses: N poses ``left_cam_from_target``.
        pose_covariance: (N, 6, 6) over [rotation, translation] (right perturbation), or None.
        angular_velocity: (N, 3) in the target frame [rad/s], or None.
    """

    t_s: np.ndarray
    poses: tuple[Rigid3, ...]
    pose_covariance: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.poses)


def guess_format(path: Path) -> TrajectoryFormat:
    """``csv`` for a ``.csv`` file or a first data line with commas, else ``tum``."""
    if path.suffix.lower() == ".csv":
        return "csv"
    if path.suffix.lower() in (".tum", ".txt"):
        return "tum"
    try:
        with path.open(encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    return "csv" if "," in line else "tum"
    except OSError as exc:
        raise ResultFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return "tum"


def read_trajectory(
    path: str | Path, fmt: TrajectoryFormat | None = None, *, inverse: bool = False
) -> PoseTrack:
    """Read a TUM or CSV trajectory (module docstring); ``fmt`` None: `guess_format`.

    ``inverse``: the file holds ``target_from_left_cam``; the poses are inverted and a
    covariance moved to the inverse's right perturbation (``Ad_P C Ad_P^T`` for the file's
    pose ``P``); angular velocities are then dropped (they would describe the camera).

    Raises:
        ResultFileError: missing or unreadable file, a missing column, a value that is not a
            finite number, a quaternion that is not unit norm, times that do not increase
            (each naming the file, the column and the row).
    """
    p = Path(path)
    if not p.is_file():
        raise ResultFileError(f"{p}: trajectory file is missing")
    kind = fmt or guess_format(p)
    if kind == "tum":
        t, poses = read_tum(p)
        track = PoseTrack(t_s=np.asarray(t, float), poses=tuple(poses))
    elif kind == "csv":
        track = _read_csv(p)
    else:
        raise ResultFileError(f"{p}: unknown trajectory format {kind!r} (tum or csv)")
    if len(track) == 0:
        raise ResultFileError(f"{p}: holds no poses")
    steps = np.diff(track.t_s)
    if np.any(steps <= 0):
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise ResultFileError(
            f"{p}: time: pose {row + 1}: {shown(track.t_s[row])} is not later than the "
            f"previous pose's {shown(track.t_s[row - 1])}"
        )
    if not inverse:
        return track
    cov = None
    if track.pose_covariance is not None:
        A = np.stack([adjoint(P) for P in track.poses])
        cov = np.einsum("nij,njk,nlk->nil", A, track.pose_covariance, A)
    return PoseTrack(
        t_s=track.t_s, poses=tuple(P.inverse() for P in track.poses), pose_covariance=cov
    )


def _read_csv(p: Path) -> PoseTrack:
    try:
        df = pd.read_csv(p, skipinitialspace=True)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise ResultFileError(f"{p}: not a readable CSV file ({exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    time_col = next((c for c in TIME_COLUMNS if c in df.columns), None)
    missing = [c for c in POSE_COLUMNS if c not in df.columns]
    if time_col is None or missing:
        need = ([] if time_col else ["t_s (or timestamp)"]) + missing
        raise ResultFileError(
            f"{p}: missing column(s) {', '.join(need)} (a trajectory CSV names t_s or "
            f"timestamp, tx, ty, tz, qx, qy, qz, qw in its header)"
        )
    t = _numbers(df, [time_col], p)[:, 0]
    v = _numbers(df, list(POSE_COLUMNS), p)
    norms = np.linalg.norm(v[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        row = int(bad[0])
        raise ResultFileError(
            f"{p}: qx..qw: row {row + 1}: quaternion norm {norms[row]:.9g} is not 1"
        )
    poses = tuple(
        Rigid3.from_quat_xyzw(q / np.linalg.norm(q), tr)
        for q, tr in zip(v[:, 3:7], v[:, :3], strict=True)
    )
    cov = None
    if set(POSE_COV_COLUMNS) <= set(df.columns):
        cov = _numbers(df, list(POSE_COV_COLUMNS), p).reshape(-1, 6, 6)
        asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2))
        scale = np.abs(cov).max(axis=(1, 2))
        bad = np.flatnonzero(asym > 1e-9 * np.maximum(scale, 1e-300))
        if bad.size:
            raise ResultFileError(
                f"{p}: pose_cov_*: row {int(bad[0]) + 1}: the covariance is not symmetric"
            )
    w = None
    if {"wx", "wy", "wz"} <= set(df.columns):
        w = _numbers(df, ["wx", "wy", "wz"], p)
    return PoseTrack(t_s=t, poses=poses, pose_covariance=cov, angular_velocity=w)


def _numbers(df: pd.DataFrame, columns: list[str], p: Path) -> np.ndarray:
    """(N, len(columns)) finite floats, or the file, column and row of the first bad value."""
    out = np.empty((len(df), len(columns)))
    for k, c in enumerate(columns):
        values = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            row = int(bad[0])
            raise ResultFileError(
                f"{p}: {c}: row {row + 1}: value {shown(df[c].iloc[row])} is NaN, infinite "
                "or not a number"
            )
        out[:, k] = values
    return out


@dataclass(frozen=True, kw_only=True)
class Association:
    """Which poses of a trajectory belong to which frames (`associate`).

    Attributes:
        pose_index: (M,) indices into the trajectory, in frame order.
        frame_row: (M,) the matching rows of the reference times (same order).
        unmatched_poses: indices of poses with no frame within the tolerance (or whose frame
            took a nearer pose).
        unmatched_frames: rows of the reference times no pose matched.
        max_dt_s: the tolerance used [s].
    """

    pose_index: np.ndarray
    frame_row: np.ndarray
    unmatched_poses: np.ndarray
    unmatched_frames: np.ndarray
    max_dt_s: float


def associate(t_poses: np.ndarray, t_frames: np.ndarray, max_dt_s: float) -> Association:
    """Match each pose to the frame nearest in time if within ``max_dt_s`` [s]; a frame keeps
    only its nearest pose (ties: the earlier one). Both time arrays must be increasing."""
    tp = np.asarray(t_poses, float)
    tf = np.asarray(t_frames, float)
    if tf.size == 0 or tp.size == 0:
        return Association(
            pose_index=np.zeros(0, np.int64),
            frame_row=np.zeros(0, np.int64),
            unmatched_poses=np.arange(tp.size),
            unmatched_frames=np.arange(tf.size),
            max_dt_s=max_dt_s,
        )
    right = np.clip(np.searchsorted(tf, tp), 0, tf.size - 1)
    left = np.clip(right - 1, 0, tf.size - 1)
    nearest = np.where(np.abs(tf[left] - tp) <= np.abs(tf[right] - tp), left, right)
    dt = np.abs(tf[nearest] - tp)
    best: dict[int, int] = {}
    for i in np.flatnonzero(dt <= max_dt_s):
        j = int(nearest[i])
        if j not in best or dt[i] < dt[best[j]]:
            best[j] = int(i)
    rows = np.array(sorted(best), dtype=np.int64)
    poses = np.array([best[j] for j in rows], dtype=np.int64)
    return Association(
        pose_index=poses,
        frame_row=rows,
        unmatched_poses=np.setdiff1d(np.arange(tp.size), poses),
        unmatched_frames=np.setdiff1d(np.arange(tf.size), rows),
        max_dt_s=max_dt_s,
    )


# ----------------------------------------------------------------------------------------------
# Writing an estimate as CSV
# ----------------------------------------------------------------------------------------------


def estimate_csv_frame(est: Estimate) -> pd.DataFrame:
    """trajectory.csv's columns (`satpose.tools.pipeline.TRAJECTORY_COLUMNS`) followed by the
    full covariances: `POSE_COV_COLUMNS` and `TWIST_COV_COLUMNS` (row-major, the estimate's own
    [rotation, translation] / [omega, v] order, target axes)."""
    df = estimate_frame(est)
    n = len(est)
    pose = pd.DataFrame(est.pose_covariance.reshape(n, 36), columns=list(POSE_COV_COLUMNS))
    twist = pd.DataFrame(est.twist_covariance.reshape(n, 36), columns=list(TWIST_COV_COLUMNS))
    return pd.concat([df, pose, twist], axis=1)


ESTIMATE_CSV_FLOAT_FORMAT = "%.17g"
"""Round-trip precision: an exported CSV reads back to the same float64 values."""


def write_estimate_csv(est: Estimate, path: str | Path) -> Path:
    """`estimate_csv_frame` written atomically (``satpose export --format csv``)."""
    df = estimate_csv_frame(est)
    return atomic_write(
        path, lambda tmp: df.to_csv(tmp, index=False, float_format=ESTIMATE_CSV_FLOAT_FORMAT)
    )
