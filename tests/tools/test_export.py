"""`satpose export`: TUM, CSV and ROS 2 bag files of a run's estimate, read back with the
readers of other tools (rosbags for the bag)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from satpose.backend import Estimate
from satpose.datasets.geometry import Rigid3, quat_xyzw_to_matrix
from satpose.tools import export
from satpose.tools.cli import main
from satpose.tools.files import read_tum
from satpose.tools.pipeline import TRAJECTORY_COLUMNS, write_estimate_npz
from satpose.tools.trajectories import read_trajectory

N = 9


def _spd(rng: np.random.Generator, scale: float) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return scale * (A @ A.T + 0.1 * np.eye(6))


@pytest.fixture
def estimate() -> Estimate:
    """Random poses, twists and full (correlated) covariances at 4 Hz from t = 12.5 s."""
    rng = np.random.default_rng(11)
    return Estimate(
        frame=np.arange(N) + 3,
        t_s=12.5 + 0.25 * np.arange(N),
        left_cam_from_target=tuple(
            Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) + np.array([0.0, 0.0, 6.0]))
            for _ in range(N)
        ),
        twist=rng.normal(size=(N, 6)),
        pose_covariance=np.stack([_spd(rng, 1e-4) for _ in range(N)]),
        twist_covariance=np.stack([_spd(rng, 1e-3) for _ in range(N)]),
    )


@pytest.fixture
def run(tmp_path: Path, estimate: Estimate) -> Path:
    """A run folder holding only the estimate (what export reads)."""
    folder = tmp_path / "run"
    folder.mkdir()
    write_estimate_npz(estimate, folder / "estimate.npz")
    return folder


def _read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message of a ROS 2 bag, by topic, with rosbags' own reader and typestore."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    out: dict[str, list[tuple[int, object]]] = {}
    with Reader(path) as reader:
        for conn, ts, raw in reader.messages():
            out.setdefault(conn.topic, []).append((ts, store.deserialize_cdr(raw, conn.msgtype)))
    return out


def test_rosbag2_reads_back_with_covariances(run: Path, estimate: Estimate, tmp_path: Path) -> None:
    bag = tmp_path / "out" / "bag"
    assert main(["export", str(run), "--format", "rosbag2", "--out", str(bag)]) == 0
    msgs = _read_bag(bag)
    assert set(msgs) == {export.POSE_TOPIC, export.TWIST_TOPIC}
    assert len(msgs[export.POSE_TOPIC]) == len(msgs[export.TWIST_TOPIC]) == N
    for k, ((ts, pose), (ts2, twist)) in enumerate(
        zip(msgs[export.POSE_TOPIC], msgs[export.TWIST_TOPIC], strict=True)
    ):
        T = estimate.left_cam_from_target[k]
        R = T.R
        # times: nanoseconds of t_s, in the bag and in the header (1 ns)
        assert ts == ts2 == round(estimate.t_s[k] * 1e9)
        h = pose.header  # type: ignore[attr-defined]
        assert h.stamp.sec + 1e-9 * h.stamp.nanosec == pytest.approx(estimate.t_s[k], abs=1e-9)
        assert h.frame_id == export.CAMERA_FRAME_ID
        assert twist.header.frame_id == export.TARGET_FRAME_ID  # type: ignore[attr-defined]
        p = pose.pose.pose  # type: ignore[attr-defined]
        np.testing.assert_allclose([p.position.x, p.position.y, p.position.z], T.t, atol=1e-9)
        q = [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
        np.testing.assert_allclose(quat_xyzw_to_matrix(np.array(q)), R, atol=1e-9)
        # ROS order [x y z rx ry rz] about the camera axes, built here block by block from the
        # estimate's [rotation, translation] blocks in target axes
        C = estimate.pose_covariance[k]
        want = np.zeros((6, 6))
        want[:3, :3] = R @ C[3:, 3:] @ R.T
        want[3:, 3:] = R @ C[:3, :3] @ R.T
        want[:3, 3:] = R @ C[3:, :3] @ R.T
        want[3:, :3] = R @ C[:3, 3:] @ R.T
        got = np.asarray(pose.pose.covariance).reshape(6, 6)  # type: ignore[attr-defined]
        np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())
        tw = twist.twist  # type: ignore[attr-defined]
        np.testing.assert_allclose(
            [tw.twist.linear.x, tw.twist.linear.y, tw.twist.linear.z],
            estimate.twist[k, 3:],
            atol=1e-9,
        )
        np.testing.assert_allclose(
            [tw.twist.angular.x, tw.twist.angular.y, tw.twist.angular.z],
            estimate.twist[k, :3],
            atol=1e-9,
        )
        Ct = estimate.twist_covariance[k]
        want_t = np.block([[Ct[3:, 3:], Ct[3:, :3]], [Ct[:3, 3:], Ct[:3, :3]]])
        np.testing.assert_allclose(np.asarray(tw.covariance).reshape(6, 6), want_t, atol=1e-12)
    assert not [p.name for p in bag.parent.iterdir() if p.name.startswith(".")]
    assert sorted(p.name for p in bag.iterdir()) == ["bag.db3", "metadata.yaml"]


def test_rotation_variance_lands_on_the_camera_axis() -> None:
    """By hand: a variance about the target's z axis only, the target turned 90 deg about the
    camera's x axis (target z = camera -y): ROS sees it about y, at index (4, 4)."""
    T = Rigid3.from_rotvec([np.pi / 2, 0.0, 0.0], [0.0, 0.0, 5.0])
    C = np.zeros((6, 6))
    C[2, 2] = 0.01  # rotation about target z, GTSAM order [rx ry rz tx ty tz]
    C[3, 3] = 0.04  # translation along target x = camera x
    got = export.ros_pose_covariance(T, C)
    want = np.zeros((6, 6))
    want[4, 4] = 0.01
    want[0, 0] = 0.04
    np.testing.assert_allclose(got, want, atol=1e-15)


def test_tum_and_csv_read_back(run: Path, estimate: Estimate, tmp_path: Path) -> None:
    assert main(["export", str(run), "--format", "tum", "--out", str(tmp_path / "a.tum")]) == 0
    t, poses = read_tum(tmp_path / "a.tum")
    np.testing.assert_allclose(t, estimate.t_s, atol=1e-9)  # 9 decimals
    for P, T in zip(poses, estimate.left_cam_from_target, strict=True):
        np.testing.assert_allclose(P.t, T.t, atol=1e-9)
        np.testing.assert_allclose(P.R, T.R, atol=1e-8)
    assert main(["export", str(run), "--format", "csv", "--out", str(tmp_path / "a.csv")]) == 0
    df = pd.read_csv(tmp_path / "a.csv")
    assert list(df.columns[: len(TRAJECTORY_COLUMNS)]) == TRAJECTORY_COLUMNS
    back = read_trajectory(tmp_path / "a.csv")
    np.testing.assert_array_equal(back.t_s, estimate.t_s)  # %.17g: exact
    assert back.pose_covariance is not None and back.angular_velocity is not None
    np.testing.assert_array_equal(back.pose_covariance, estimate.pose_covariance)
    np.testing.assert_array_equal(back.angular_velocity, estimate.twist[:, :3])
    tw = df[[f"twist_cov_{i}{j}" for i in range(6) for j in range(6)]].to_numpy()
    np.testing.assert_array_equal(tw.reshape(-1, 6, 6), estimate.twist_covariance)


# -- bad input and atomic output -----------------------------------------------------------------


def _one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    for w in words:
        assert w in err, (w, err)


def test_existing_outputs_are_kept(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keep = tmp_path / "keep.tum"
    keep.write_text("mine\n")
    assert main(["export", str(run), "--format", "tum", "--out", str(keep)]) == 2
    _one_line_error(capsys, str(keep), "--overwrite")
    assert keep.read_text() == "mine\n"
    folder = tmp_path / "notabag"
    folder.mkdir()
    (folder / "x.txt").write_text("mine")
    assert main(["export", str(run), "--format", "rosbag2", "--out", str(folder)]) == 2
    _one_line_error(capsys, str(folder), "metadata.yaml")
    bag = tmp_path / "bag"
    assert main(["export", str(run), "--format", "rosbag2", "--out", str(bag)]) == 0
    assert main(["export", str(run), "--format", "rosbag2", "--out", str(bag)]) == 2
    _one_line_error(capsys, str(bag), "--overwrite")
    args = ["export", str(run), "--format", "rosbag2", "--out", str(bag), "--overwrite"]
    assert main(args) == 0
    assert len(_read_bag(bag)[export.POSE_TOPIC]) == N


def test_missing_estimate(run: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    args = ["export", str(run), "--format", "csv", "--out", str(tmp_path / "x.csv")]
    assert main([*args, "--estimate", "smoothed"]) == 2
    _one_line_error(capsys, "estimate_smoothed.npz", "this run has: main")
    assert not (tmp_path / "x.csv").exists()


def test_interrupted_bag_leaves_nothing(
    run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C after a few messages: neither the bag nor its staging folder remains."""
    calls = {"n": 0}
    real = export.ros_twist_covariance

    def interrupt_at_the_fourth(C: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(C)

    monkeypatch.setattr(export, "ros_twist_covariance", interrupt_at_the_fourth)
    bag = tmp_path / "bag"
    assert main(["export", str(run), "--format", "rosbag2", "--out", str(bag)]) == 130
    assert calls["n"] == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
