"""Truth alignment: SLERP + linear interpolation onto frame times, the three conventions,
the span and gap rules."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3
from satpose.datasets.importers import HandEye, RecordingError, TruthAligner, TruthTrajectory

AXIS = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
RATE = 0.7  # rad/s about AXIS
V = np.array([0.05, -0.02, -0.4])  # m/s


def motion(t: float) -> Rigid3:
    """Rotation at a constant rate about a fixed axis from R0, translation linear in time:
    exactly what SLERP + linear interpolation reproduce between any two samples."""
    R0 = Rigid3.from_rotvec([0.2, 0.1, -0.3], [0, 0, 0]).R
    Rt = Rigid3.from_rotvec(AXIS * RATE * t, [0, 0, 0]).R
    return Rigid3(R=Rt @ R0, t=np.array([0.1, 0.2, 6.0]) + V * t)


def trajectory(poses: list[Rigid3], t: np.ndarray) -> TruthTrajectory:
    return TruthTrajectory(
        t_s=t,
        translation=np.stack([p.t for p in poses]),
        quat_xyzw=np.stack([p.quat_xyzw for p in poses]),
        path=Path("truth.tum"),
    )


def close(a: Rigid3, b: Rigid3, tol: float = 1e-12) -> None:
    np.testing.assert_allclose(a.matrix(), b.matrix(), rtol=0, atol=tol)


def test_interpolation_is_exact_for_constant_rate_motion() -> None:
    t = np.array([0.0, 0.5, 1.1, 2.0])
    aligner = TruthAligner(trajectory([motion(x) for x in t], t))
    for x in (0.0, 0.2, 0.5, 0.77, 1.9, 2.0):
        pose = aligner.pose_at(x)
        assert pose is not None
        close(pose, motion(x))  # noise-free: float rounding only


def test_target_from_left_cam_is_inverted() -> None:
    t = np.array([0.0, 1.0])
    aligner = TruthAligner(
        trajectory([motion(x).inverse() for x in t], t), frame="target_from_left_cam"
    )
    # Interpolated in the file's convention (the camera's path in the target frame), then
    # inverted: exact at the samples; between them the inverse of a linear path differs
    # from a linear path by second-order terms, so compare at the samples only.
    for x in t:
        pose = aligner.pose_at(x)
        assert pose is not None
        close(pose, motion(x))


def test_world_from_marker_with_hand_eye() -> None:
    left_cam_from_marker = Rigid3.from_rotvec([0.01, 0.02, -1.2], [0.05, -0.1, 0.02])
    world_from_target = Rigid3.from_rotvec([1.5, 0.0, 0.1], [2.0, 1.0, 0.5])
    # The marker moves so that left_cam_from_target follows `motion`:
    # world_from_marker = world_from_target @ inv(left_cam_from_target) @ left_cam_from_marker
    t = np.array([0.0, 0.4, 1.0])
    world_from_marker = [world_from_target @ motion(x).inverse() @ left_cam_from_marker for x in t]
    hand_eye = HandEye(
        left_cam_from_marker=left_cam_from_marker, world_from_target=world_from_target
    )
    aligner = TruthAligner(
        trajectory(world_from_marker, t), frame="world_from_marker", hand_eye=hand_eye
    )
    for x in t:
        pose = aligner.pose_at(x)
        assert pose is not None
        close(pose, motion(x), tol=1e-11)


def test_span_gap_and_offset() -> None:
    t = np.array([10.0, 10.1, 10.2, 11.5, 11.6])
    aligner = TruthAligner(
        trajectory([motion(x) for x in t], t), time_offset_s=-10.0, max_gap_s=0.5
    )
    assert aligner.span == (0.0, pytest.approx(1.6))
    assert aligner.pose_at(-0.01) is None and aligner.pose_at(1.61) is None
    assert aligner.pose_at(0.05) is not None
    assert aligner.pose_at(0.8) is None  # inside the 1.3 s gap
    close(aligner.pose_at(1.5), motion(11.5))  # type: ignore[arg-type]


def test_conventions_are_checked() -> None:
    traj = trajectory([motion(0.0)], np.array([0.0]))
    with pytest.raises(RecordingError, match="--hand-eye"):
        TruthAligner(traj, frame="world_from_marker")
    with pytest.raises(RecordingError, match="row 2 t"):
        trajectory([motion(0.0), motion(1.0)], np.array([1.0, 1.0]))
