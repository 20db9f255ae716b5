"""Ground truth from another system (motion capture, a robot's encoders) onto the frame times.

A truth trajectory is a list of timed poses in one stated convention (`TruthFrame`):

- ``left_cam_from_target``: the target's pose in the left camera frame (format v1's own
  ``groundtruth.csv`` convention), written as it is;
- ``target_from_left_cam``: the left camera's pose in the target frame, inverted;
- ``world_from_marker``: motion capture tracking a marker body on the camera rig while the
  target mock-up stands still in the mocap world; ``left_cam_from_target =
  left_cam_from_marker @ inv(world_from_marker(t)) @ world_from_target`` with the hand-eye
  transform ``left_cam_from_marker`` and the target's fixed pose ``world_from_target`` given
  in a small YAML file (`read_hand_eye`).

Alignment: truth time + ``time_offset_s`` = frame time. The pose at a frame time is
interpolated between the two samples around it in the file's own convention (where the
samples were measured): SLERP for the rotation, linear for the translation. A frame before
the first sample, after the last, or between two samples more than ``max_gap_s`` apart gets
no truth; format v1 wants truth for every frame or for none, so such frames are left out of
the imported sequence and counted (docs/import.md, "Truth").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from satpose.datasets.config import yaml_problem
from satpose.datasets.geometry import GeometryError, Rigid3
from satpose.datasets.importers.common import RecordingError

TruthFrame = Literal["left_cam_from_target", "target_from_left_cam", "world_from_marker"]
TRUTH_FRAMES: tuple[str, ...] = get_args(TruthFrame)


@dataclass(frozen=True, kw_only=True)
class HandEye:
    """The constant transforms of the ``world_from_marker`` convention [m]."""

    left_cam_from_marker: Rigid3
    world_from_target: Rigid3


def _pose(raw: Any, path: Path, field: str) -> Rigid3:
    if not isinstance(raw, dict) or "t" not in raw or "quat_xyzw" not in raw:
        raise RecordingError(path, field, "must be {t: [x, y, z], quat_xyzw: [qx, qy, qz, qw]}")
    try:
        t = np.array(raw["t"], dtype=float).reshape(3)
        q = np.array(raw["quat_xyzw"], dtype=float).reshape(4)
    except (TypeError, ValueError):
        raise RecordingError(path, field, "t needs 3 numbers and quat_xyzw 4") from None
    norm = float(np.linalg.norm(q))
    if not np.all(np.isfinite(t)) or not np.isfinite(norm) or abs(norm - 1.0) > 1e-6:
        raise RecordingError(path, f"{field}.quat_xyzw", f"not a unit quaternion (|q| = {norm})")
    return Rigid3.from_quat_xyzw(q / norm, t)


def read_hand_eye(path: Path) -> HandEye:
    """A YAML file with ``left_cam_from_marker`` and ``world_from_target``, each
    ``{t: [x, y, z], quat_xyzw: [qx, qy, qz, qw]}`` [m]."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise RecordingError(path, None, f"not valid YAML: {yaml_problem(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(path, None, f"cannot read ({exc})") from None
    if not isinstance(data, dict):
        raise RecordingError(path, None, "must hold a YAML mapping")
    return HandEye(
        left_cam_from_marker=_pose(data.get("left_cam_from_marker"), path, "left_cam_from_marker"),
        world_from_target=_pose(data.get("world_from_target"), path, "world_from_target"),
    )


@dataclass(frozen=True, kw_only=True)
class TruthTrajectory:
    """Timed poses as a file states them.

    Attributes:
        t_s: sample times [s], strictly increasing, shape (N,).
        translation: (N, 3) [m]; quat_xyzw: (N, 4) unit quaternions (the file's convention).
        path: the file, for messages.
    """

    t_s: np.ndarray
    translation: np.ndarray
    quat_xyzw: np.ndarray
    path: Path

    def __post_init__(self) -> None:
        n = self.t_s.shape[0]
        if n < 1 or self.translation.shape != (n, 3) or self.quat_xyzw.shape != (n, 4):
            raise RecordingError(self.path, None, "needs at least one pose (t, 3 + 4 numbers)")
        steps = np.diff(self.t_s)
        if np.any(steps <= 0):
            k = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise RecordingError(
                self.path, f"row {k + 1} t", f"time {self.t_s[k]} does not increase"
            )


class TruthAligner:
    """``left_cam_from_target`` at any frame time (module docstring).

    Args:
        trajectory: the samples.
        frame: the file's convention.
        hand_eye: the constant transforms (``world_from_marker`` only).
        time_offset_s: added to the truth times to get frame times [s].
        max_gap_s: the largest sample spacing interpolated across [s] (None: any).
    """

    def __init__(
        self,
        trajectory: TruthTrajectory,
        *,
        frame: TruthFrame = "left_cam_from_target",
        hand_eye: HandEye | None = None,
        time_offset_s: float = 0.0,
        max_gap_s: float | None = None,
    ) -> None:
        if frame not in TRUTH_FRAMES:
            raise RecordingError(trajectory.path, "--truth-frame", f"unknown convention {frame!r}")
        if (frame == "world_from_marker") != (hand_eye is not None):
            raise RecordingError(
                trajectory.path,
                "--hand-eye",
                "the world_from_marker convention needs --hand-eye (and only it does)",
            )
        self.trajectory = trajectory
        self.frame = frame
        self.hand_eye = hand_eye
        self.t_s = trajectory.t_s + float(time_offset_s)
        self.time_offset_s = float(time_offset_s)
        self.max_gap_s = max_gap_s
        q = trajectory.quat_xyzw / np.linalg.norm(trajectory.quat_xyzw, axis=1, keepdims=True)
        self._rot = Rotation.from_quat(q)  # scipy: scalar last, like the files

    @property
    def span(self) -> tuple[float, float]:
        """First and last sample time on the frame clock [s]."""
        return float(self.t_s[0]), float(self.t_s[-1])

    def sample(self, t: float) -> Rigid3 | None:
        """The file's pose at frame time ``t`` (interpolated), or None without truth there."""
        ts = self.t_s
        if not ts[0] <= t <= ts[-1]:
            return None
        k = int(np.searchsorted(ts, t, side="right")) - 1
        if ts[k] == t:
            R = self._rot[k].as_matrix()
            tr = self.trajectory.translation[k]
        else:
            t0, t1 = ts[k], ts[k + 1]
            if self.max_gap_s is not None and t1 - t0 > self.max_gap_s:
                return None
            a = (t - t0) / (t1 - t0)
            r0 = self._rot[k]
            # SLERP: R0 * exp(a * log(R0^-1 R1)), the shorter arc.
            R = (
                r0 * Rotation.from_rotvec(a * (r0.inv() * self._rot[k + 1]).as_rotvec())
            ).as_matrix()
            p = self.trajectory.translation
            tr = (1.0 - a) * p[k] + a * p[k + 1]
        try:
            return Rigid3(R=R, t=tr)
        except GeometryError as exc:
            raise RecordingError(self.trajectory.path, f"row {k + 1}", str(exc)) from None

    def pose_at(self, t: float) -> Rigid3 | None:
        """``left_cam_from_target`` at frame time ``t`` [s], or None without truth there."""
        P = self.sample(t)
        if P is None:
            return None
        if self.frame == "left_cam_from_target":
            return P
        if self.frame == "target_from_left_cam":
            return P.inverse()
        assert self.hand_eye is not None
        return self.hand_eye.left_cam_from_marker @ P.inverse() @ self.hand_eye.world_from_target

    def provenance(self) -> dict[str, object]:
        out: dict[str, object] = {
            "file": str(self.trajectory.path),
            "frame": self.frame,
            "time_offset_s": self.time_offset_s,
            "interpolation": "slerp rotation, linear translation, in the file's convention",
        }
        if self.max_gap_s is not None:
            out["max_gap_s"] = self.max_gap_s
        return out
