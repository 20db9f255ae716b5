"""`satpose eval SEQ FILE`: TUM and CSV trajectory files matched to frames by time, scored
like a run; evo's own API reproduces the ATE."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from satpose.backend import Estimate
from satpose.backend.pose3 import adjoint
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import load_sequence
from satpose.tools.cli import main
from satpose.tools.evaluate import evaluate_file
from satpose.tools.files import ResultFileError, write_tum
from satpose.tools.trajectories import associate, read_trajectory, write_estimate_csv

FRAMES = 12
SEED = 7


@pytest.fixture
def seq(tmp_path: Path, make_sequence) -> Path:  # type: ignore[no-untyped-def]
    """12 stereo frames at 2 Hz (t = 0, 0.5, ... 5.5 s), random poses 5 m away."""
    return make_sequence(tmp_path / "seq", frames=FRAMES, seed=SEED)


def _truth(seq: Path) -> tuple[np.ndarray, list[Rigid3]]:
    truth = load_sequence(seq).truth
    assert truth is not None
    return truth.t_s, [truth.pose(r) for r in range(len(truth.t_s))]


def _perturbed(poses: list[Rigid3], rng: np.random.Generator) -> list[Rigid3]:
    """Each pose times a random 2 cm / 0.6 deg error (right perturbation)."""
    return [
        T @ Rigid3.from_rotvec(0.01 * rng.normal(size=3), 0.02 * rng.normal(size=3)) for T in poses
    ]


def _random_spd(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T * 1e-4 + np.eye(6) * 1e-5


def _estimate(t_s: np.ndarray, poses: list[Rigid3], rng: np.random.Generator) -> Estimate:
    n = len(poses)
    return Estimate(
        frame=np.arange(n),
        t_s=t_s,
        left_cam_from_target=tuple(poses),
        twist=rng.normal(size=(n, 6)),
        pose_covariance=np.stack([_random_spd(rng) for _ in range(n)]),
        twist_covariance=np.stack([_random_spd(rng) for _ in range(n)]),
    )


def _evo_ate(ref_t: np.ndarray, ref: list[Rigid3], est_file: Path, align: bool) -> float:
    """ATE with evo's own API: read the TUM file, associate by time (0.01 s, as satpose's
    default), APE of the translation part, RMSE; ``align``: SE(3) Umeyama, no scale (evo_ape
    -a), as satpose's ``ate_aligned_m``."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    est = file_interface.read_tum_trajectory_file(est_file)
    ref_traj = PoseTrajectory3D(poses_se3=[T.matrix() for T in ref], timestamps=ref_t)
    ref_traj, est = sync.associate_trajectories(ref_traj, est, max_diff=0.01)
    if align:
        est.align(ref_traj, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref_traj, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def test_evo_reproduces_the_ate_of_a_tum_file(seq: Path, tmp_path: Path) -> None:
    rng = np.random.default_rng(SEED)
    t, truth = _truth(seq)
    est = _perturbed(truth, rng)
    # another tool's clock: 3 ms late, the first frame missing, two poses after the sequence
    times = np.r_[t[1:] + 0.003, t[-1] + 10.0, t[-1] + 10.5]
    poses = [*est[1:], est[0], est[0]]
    path = tmp_path / "other_tool.tum"
    write_tum(times, poses, path)
    results, assoc = evaluate_file(seq, path)
    m = results["other_tool.tum"]
    assert m.frames == FRAMES - 1 and m.poses_unmatched == 2
    assert list(assoc.unmatched_frames) == [0] and list(assoc.unmatched_poses) == [11, 12]
    # same file, same association, same convention: equal to 1e-6 (relative)
    assert m.ate_m == pytest.approx(_evo_ate(t, truth, path, align=False), rel=1e-6)
    assert m.ate_aligned_m is not None
    assert m.ate_aligned_m == pytest.approx(_evo_ate(t, truth, path, align=True), rel=1e-6)
    assert m.nees_mean is None and m.spin_err_deg_per_frame is None  # a TUM file has neither
    assert m.spec.score > 0


def test_exported_csv_scores_like_the_estimate_with_nees_and_spin(
    seq: Path, tmp_path: Path
) -> None:
    rng = np.random.default_rng(SEED + 1)
    t, truth = _truth(seq)
    est = _estimate(t, _perturbed(truth, rng), rng)
    write_estimate_csv(est, tmp_path / "est.csv")
    write_tum(t, list(est.left_cam_from_target), tmp_path / "est.tum")
    csv_m = evaluate_file(seq, tmp_path / "est.csv")[0]["est.csv"]
    tum_m = evaluate_file(seq, tmp_path / "est.tum")[0]["est.tum"]
    # TUM holds 9 decimals: the position metrics agree to ~1e-9 m
    assert csv_m.ate_m == pytest.approx(tum_m.ate_m, abs=1e-8)
    assert csv_m.spec.score == pytest.approx(tum_m.spec.score, abs=1e-7)
    assert csv_m.nees_mean is not None and csv_m.spin_err_deg_per_frame is not None
    # the covariances read back exactly (%.17g)
    back = read_trajectory(tmp_path / "est.csv")
    assert back.pose_covariance is not None
    np.testing.assert_allclose(back.pose_covariance, est.pose_covariance, rtol=1e-15)


def test_inverse_file_gives_the_same_metrics(seq: Path, tmp_path: Path) -> None:
    """A file of target_from_left_cam with the matching covariance, read with inverse=True."""
    rng = np.random.default_rng(SEED + 2)
    t, truth = _truth(seq)
    est = _estimate(t, _perturbed(truth, rng), rng)
    write_estimate_csv(est, tmp_path / "est.csv")
    # P = T^-1, P_true = P Exp(eta) with eta = -Ad_T xi: C_P = Ad_T C Ad_T^T
    inv_cov = np.stack(
        [
            adjoint(T) @ C @ adjoint(T).T
            for T, C in zip(est.left_cam_from_target, est.pose_covariance, strict=True)
        ]
    )
    P = [T.inverse() for T in est.left_cam_from_target]
    df = pd.DataFrame(
        np.column_stack([t, [p.t for p in P], [p.quat_xyzw for p in P], inv_cov.reshape(-1, 36)]),
        columns=["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
        + [f"pose_cov_{i}{j}" for i in range(6) for j in range(6)],
    )
    df.to_csv(tmp_path / "inv.csv", index=False, float_format="%.17g")
    a = evaluate_file(seq, tmp_path / "est.csv")[0]["est.csv"]
    b = evaluate_file(seq, tmp_path / "inv.csv", inverse=True)[0]["inv.csv"]
    assert b.ate_m == pytest.approx(a.ate_m, rel=1e-9)
    assert b.rot_deg == pytest.approx(a.rot_deg, rel=1e-7)
    assert b.nees_mean == pytest.approx(a.nees_mean, rel=1e-6)
    # read as it is, the inverted file is far off (the camera seen from the target)
    c = evaluate_file(seq, tmp_path / "inv.csv")[0]["inv.csv"]
    assert c.ate_m > 100 * a.ate_m


def test_association_keeps_the_nearest_pose_per_frame() -> None:
    frames = np.array([0.0, 1.0, 2.0, 3.0])
    poses = np.array([-0.5, 0.004, 0.998, 1.003, 2.02, 3.0])
    a = associate(poses, frames, 0.01)
    assert list(a.frame_row) == [0, 1, 3] and list(a.pose_index) == [1, 2, 5]
    assert list(a.unmatched_poses) == [0, 3, 4] and list(a.unmatched_frames) == [2]


def test_cli_eval_of_a_file(seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(SEED + 3)
    t, truth = _truth(seq)
    path = tmp_path / "traj.txt"
    write_tum(t[:-2], _perturbed(truth, rng)[:-2], path)
    assert main(["eval", str(seq), str(path)]) == 0
    out = capsys.readouterr().out
    assert "| traj.txt | 10/12 |" in out and "n/a" in out and "SPEC score" in out
    assert "2 of 12 frames have no pose" in out
    metrics = json.loads((tmp_path / "traj_eval" / "metrics.json").read_text())
    assert metrics["traj.txt"]["nees_mean"] is None and metrics["traj.txt"]["spec"]["score"] > 0
    assert (tmp_path / "traj_eval" / "groundtruth.tum").is_file()


# -- bad input -------------------------------------------------------------------------------


def _one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    for w in words:
        assert w in err, (w, err)


def test_csv_without_a_time_column(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.csv"
    path.write_text("time,tx,ty,tz,qx,qy,qz,qw\n0,0,0,5,0,0,0,1\n")
    assert main(["eval", str(seq), str(path)]) == 2
    _one_line_error(capsys, str(path), "t_s (or timestamp)")
    assert not (tmp_path / "bad_eval").exists()


def test_csv_with_a_nan(seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "nan.csv"
    path.write_text("t_s,tx,ty,tz,qx,qy,qz,qw\n0,0,0,5,0,0,0,1\n0.5,nan,0,5,0,0,0,1\n")
    assert main(["eval", str(seq), str(path)]) == 2
    _one_line_error(capsys, str(path), "tx: row 2")


def test_tum_with_a_non_unit_quaternion(tmp_path: Path) -> None:
    path = tmp_path / "q.tum"
    path.write_text("0 0 0 5 0 0 0 1\n0.5 0 0 5 0 0 0 2\n")
    with pytest.raises(ResultFileError, match="line 2: quaternion is not unit norm"):
        read_trajectory(path)


def test_times_that_match_no_frame(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Times in nanoseconds where seconds were expected: no pose matches, one clear line."""
    t, truth = _truth(seq)
    path = tmp_path / "ns.tum"
    write_tum(t * 1e9 + 1e6, truth, path)
    assert main(["eval", str(seq), str(path)]) == 2
    _one_line_error(capsys, str(path), "only 0 of its 12 poses", "--max-dt")


def test_run_folder_options_are_refused(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    assert main(["eval", str(seq), str(run), "--inverse"]) == 2
    _one_line_error(capsys, "--inverse only apply to a trajectory file")
