"""SfM check: validated against renderer truth.

The rendered case is a turntable (the static rig watching the target turn 4 deg per frame
about an axis across the line of sight, 4.5 m away; 8 frames, 512x384, 4 spp, wings and
brackets masked): COLMAP registers every frame at ~0.35 px and its poses match the truth to
0.15-0.32 cm / 0.21-0.41 deg at the worst frame (three runs; COLMAP's multithreaded matching
is not bit-reproducible; tolerances 1 cm / 1 deg), so the check must accept it. Two cases it
must refuse, each shown to be wrong against the truth:

- an unsynchronised rig (right images one frame late; COLMAP still registers everything at
  ~0.7 px, but its poses are off by 1-5.5 deg): caught by the left/right rig consistency
  (median 0.44 deg and 2.5 cm, against 0.11 deg and 0.8 cm for the accepted turntable);
- a folded reconstruction (what a symmetry or a repeated texture does: half of the frames and
  their points moved rigidly, every reprojection error unchanged): caught by the neighbour
  agreement. It is made from the accepted reconstruction, because the rendered target does not
  fold COLMAP at this size (docs/checks.md).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import (
    preset,
    scaled,
)
from satpose.datasets.sequence import Sequence, SequenceWriter, load_sequence
from satpose.tools.cli import main
from satpose.tools.files import write_tum
from satpose.tools.sfmcheck import (
    ColmapRun,
    SfmCheckConfig,
    SfmCheckError,
    align_poses,
    assess,
    check_sfm,
    match_trajectory,
    neighbour_agreement,
    pose_differences,
)

FRAMES = 8
UNSYNC_FRAMES = 6  # the right image of frame k + 1 with the left one of frame k
POSITION_TOL_M = 0.01  # COLMAP vs truth, measured max 0.15-0.32 cm
ROTATION_TOL_DEG = 1.0  # measured max 0.21-0.41 deg
SHIFTED_FRAME, SHIFT_M = 3, 0.04  # perturbations of the trajectory under test
TURNED_FRAME, TURN_DEG = 6, 2.0
AHEAD = np.array([0.0, 0.0, 6.0])  # random test poses sit 6 m in front of the camera


def turntable_scenario():  # type: ignore[no-untyped-def]
    """The `turntable` preset, small: 8 frames at 512x384, 4 spp."""
    return scaled(preset("turntable"), frames=FRAMES, size=(512, 384), spp=4)


def _truth(seq: Sequence) -> list[Rigid3]:
    assert seq.truth is not None
    return [seq.truth.pose(i) for i in range(len(seq))]


@pytest.fixture(scope="module")
def turntable(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sfm") / "turntable"
    render_sequence(turntable_scenario(), out)
    return out


@pytest.fixture(scope="module")
def accepted(turntable: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``satpose check-sfm`` on the turntable against the truth with two frames perturbed."""
    seq = load_sequence(turntable)
    poses = _truth(seq)
    poses[SHIFTED_FRAME] = Rigid3(
        R=poses[SHIFTED_FRAME].R, t=poses[SHIFTED_FRAME].t + np.array([SHIFT_M, 0.0, 0.0])
    )
    turn = Rigid3.from_rotvec(np.radians([TURN_DEG, 0.0, 0.0]), [0.0, 0.0, 0.0])
    poses[TURNED_FRAME] = turn @ poses[TURNED_FRAME]
    base = tmp_path_factory.mktemp("sfm-check")
    tum = write_tum([f.t_s for f in seq], poses, base / "perturbed.tum")
    out = base / "out"
    assert main(["check-sfm", str(turntable), "--trajectory", str(tum), "--out", str(out)]) == 0
    return out


@pytest.mark.render
def test_turntable_is_ground_truth_and_matches_the_renderer(
    accepted: Path, turntable: Path
) -> None:
    report = yaml.safe_load((accepted / "sfm_report.yaml").read_text())
    assert report["verdict"] == "ground truth", report["reasons"]
    assert report["health"]["registered_frames"] == FRAMES
    assert abs(report["sim3_scale"] - 1.0) < 0.01  # the rig makes COLMAP metric
    table = pd.read_csv(accepted / "sfm_frames.csv")
    assert table["registered"].all()
    # COLMAP's poses, in the trajectory's target frame, against the exact truth.
    truth = _truth(load_sequence(turntable))
    cols = ["colmap_" + c for c in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")]
    for row, true in zip(table[cols].to_numpy(), truth, strict=True):
        colmap = Rigid3.from_quat_xyzw(row[3:], row[:3])
        assert np.linalg.norm(colmap.t - true.t) < POSITION_TOL_M
        assert math.degrees(rotation_angle(colmap.R.T @ true.R)) < ROTATION_TOL_DEG
    assert (accepted / "colmap" / "images.bin").is_file()
    assert len((accepted / "colmap_pose.tum").read_text().splitlines()) == FRAMES


@pytest.mark.render
def test_disagreement_finds_the_perturbed_frames(accepted: Path) -> None:
    """The shifted frame disagrees by its 4 cm shift, the turned one by its 2 deg turn (each
    +- COLMAP's own error); both are left out of the alignment; the rest agree."""
    t = pd.read_csv(accepted / "sfm_frames.csv").set_index("frame")
    assert abs(t.loc[SHIFTED_FRAME, "position_m"] - SHIFT_M) < POSITION_TOL_M
    assert abs(t.loc[TURNED_FRAME, "rotation_deg"] - TURN_DEG) < ROTATION_TOL_DEG / 2
    assert not t.loc[SHIFTED_FRAME, "used_in_fit"] and not t.loc[TURNED_FRAME, "used_in_fit"]
    rest = t.drop(index=[SHIFTED_FRAME, TURNED_FRAME])
    assert (rest["position_m"] < POSITION_TOL_M).all()
    assert (rest["rotation_deg"] < ROTATION_TOL_DEG).all()


def _fold(rec, image_frames: dict[int, int], fold_at: int, world_turn: Rigid3):  # type: ignore[no-untyped-def]
    """A copy of ``rec`` folded at frame position ``fold_at``: frames from there on and the
    points they see move by ``world_turn`` (points seen on both sides are split in two), so
    that every reprojection error stays the same, as in a reconstruction folded by a
    symmetry."""
    import pycolmap

    out = pycolmap.Reconstruction(rec)
    late = {iid for iid, pos in image_frames.items() if pos >= fold_at}
    for pid in list(out.points3D):
        point = out.points3D[pid]
        obs = [(e.image_id, e.point2D_idx) for e in point.track.elements]
        early_obs = [o for o in obs if o[0] not in late]
        late_obs = [o for o in obs if o[0] in late]
        moved = world_turn.apply(np.asarray(point.xyz))
        if not early_obs:
            point.xyz = moved
            continue
        if late_obs:
            xyz = np.array(point.xyz, dtype=float)  # a copy: the point is deleted next
            out.delete_point3D(pid)
            for group, where in ((early_obs, xyz), (late_obs, moved)):
                if len(group) >= 2:
                    out.add_point3D(
                        where, pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in group])
                    )
    inverse = world_turn.inverse()
    for fid in {out.images[i].frame_id for i in late}:
        frame = out.frame(fid)
        T = (
            Rigid3(
                R=np.asarray(frame.rig_from_world.rotation.matrix()),
                t=np.asarray(frame.rig_from_world.translation).ravel(),
            )
            @ inverse
        )
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(T.R), T.t.reshape(3, 1))
    return out


@pytest.mark.render
def test_folded_reconstruction_is_refused(accepted: Path, turntable: Path) -> None:
    import pycolmap

    seq = load_sequence(turntable)
    rec = pycolmap.Reconstruction(accepted / "colmap")
    names = {
        pos: (f"left/{fr.index:06d}.png", f"right/{fr.index:06d}.png") for pos, fr in enumerate(seq)
    }
    by_name = {img.name: img for img in rec.images.values()}
    image_frames = {by_name[n].image_id: pos for pos, pair in names.items() for n in pair}
    # Verified matches between consecutive frames, as COLMAP saw them: shared tracks.
    matches = {}
    for a, b in zip(range(FRAMES - 1), range(1, FRAMES), strict=True):
        for cam in range(2):
            A, B = by_name[names[a][cam]], by_name[names[b][cam]]
            pa = {p.point3D_id: i for i, p in enumerate(A.points2D) if p.has_point3D()}
            m = [(pa[p.point3D_id], j) for j, p in enumerate(B.points2D) if p.point3D_id in pa]
            matches[(A.name, B.name)] = np.array(m, np.int64)
    centre = np.asarray(rec.compute_centroid()).ravel()
    turn = Rigid3.from_rotvec(np.radians([0.0, 40.0, 0.0]), [0.0, 0.0, 0.0])
    about_centre = Rigid3(R=turn.R, t=centre - turn.R @ centre)
    folded = _fold(rec, image_frames, FRAMES // 2, about_centre)
    cfg = SfmCheckConfig()
    run = ColmapRun(
        reconstruction=rec,
        models=1,
        image_names=names,
        masked=True,
        consecutive_matches=matches,
        timings_s={},
    )
    assert seq.calibration.right_from_left is not None
    assert assess(run, seq.calibration.right_from_left, cfg).is_ground_truth
    health = assess(
        dataclasses.replace(run, reconstruction=folded), seq.calibration.right_from_left, cfg
    )
    assert len(health.reasons) == 1 and "disagree" in health.reasons[0], health.reasons
    agreement, _ = neighbour_agreement(folded, names, matches, cfg.neighbour_tolerance_px)
    fold_pair = FRAMES // 2 - 1
    others = [v for k, v in agreement.items() if k != fold_pair]
    # the fold pair far below the refusal threshold (0.8), the others far above it (measured
    # 0.253 at the fold in one clean-clone run, below 0.25 in others: COLMAP's multithreaded
    # reconstruction varies between runs)
    assert agreement[fold_pair] < 0.4 and min(others) > 0.9, agreement
    # And it is wrong: aligned to the truth, the folded poses miss it by many degrees.
    poses = [f.left_cam_from_world for f in health.frames]
    assert all(p is not None for p in poses)
    truth = _truth(seq)
    al = align_poses([p for p in poses if p is not None], truth, inlier_factor=None)
    rot = [
        math.degrees(rotation_angle(al.apply(p).R.T @ t.R))
        for p, t in zip(poses, truth, strict=True)
        if p is not None
    ]
    assert max(rot) > 10.0


@pytest.mark.render
def test_unsynchronised_rig_is_refused(turntable: Path, tmp_path: Path) -> None:
    """Right images one frame late: COLMAP registers every frame, yet the rig consistency
    refuses, and the truth shows the poses are wrong (> 1 deg median)."""
    seq = load_sequence(turntable)
    frames = UNSYNC_FRAMES
    out = tmp_path / "unsync"
    with SequenceWriter(
        out, name="unsync", kind="stereo", rate_hz=seq.rate_hz, calibration=seq.calibration
    ) as w:
        for k in range(frames):
            late = seq[k + 1]
            masks = {"left": seq[k].mask("left"), "right": late.mask("right")}
            assert masks["left"] is not None and masks["right"] is not None
            w.add_frame(
                k, seq[k].t_s, seq[k].left(), late.right(), truth=_truth(seq)[k], masks=masks
            )
    bad = load_sequence(out)
    truth = _truth(bad)
    result = check_sfm(bad, dict(enumerate(truth)), SfmCheckConfig())
    assert not result.health.is_ground_truth
    assert any("rig" in r for r in result.health.reasons), result.health.reasons
    rot = [d.rotation_deg for d in result.disagreement]
    assert len(rot) >= frames - 1 and np.median(rot) > 1.0


# --------------------------------------------------------------------------------------------
# Without COLMAP
# --------------------------------------------------------------------------------------------


def _rotations():  # type: ignore[no-untyped-def]
    return st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(
    rv=_rotations(),
    t=st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3),
    scale=st.floats(0.2, 5.0),
    seed=st.integers(0, 2**16),
)
def test_alignment_recovers_a_similarity(rv, t, scale, seed) -> None:  # type: ignore[no-untyped-def]
    """Noise-free: COLMAP poses = truth seen through world_from_target (and a scale) ->
    align_poses gives them back and the aligned poses equal the truth (1e-9); SE(3) on
    unscaled poses gives world_from_target itself."""
    rng = np.random.default_rng(seed)
    truth = [Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) + AHEAD) for _ in range(6)]
    world_from_target = Rigid3.from_rotvec(rv, t)
    # cam_from_world = cam_from_target @ target_from_world, in COLMAP units (1 / scale).
    colmap = []
    for T in truth:
        cw = T @ world_from_target.inverse()
        colmap.append(Rigid3(R=cw.R, t=cw.t / scale))
    al = align_poses(colmap, truth, with_scale=True)
    assert al.scale == pytest.approx(scale, rel=1e-9)
    for c, T in zip(colmap, truth, strict=True):
        a = al.apply(c)
        assert np.allclose(a.t, T.t, atol=1e-9) and np.allclose(a.R, T.R, atol=1e-9)
    metric = [T @ world_from_target.inverse() for T in truth]
    se3 = align_poses(metric, truth)
    assert se3.scale == 1.0
    assert np.allclose(se3.rotation, world_from_target.R, atol=1e-9)
    assert np.allclose(se3.translation, world_from_target.t, atol=1e-9)


def test_alignment_leaves_an_outlier_out() -> None:
    """One frame of the trajectory 20 cm off: the refit ignores it, so the others align
    exactly and the outlier shows its full 20 cm."""
    rng = np.random.default_rng(5)
    truth = [Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) + AHEAD) for _ in range(8)]
    A = Rigid3.from_rotvec([0.3, -0.2, 1.0], [1.0, 2.0, 3.0])
    colmap = [T @ A.inverse() for T in truth]
    traj = list(truth)
    traj[3] = Rigid3(R=truth[3].R, t=truth[3].t + np.array([0.2, 0.0, 0.0]))
    al = align_poses(colmap, traj)
    assert not al.used[3] and al.used.sum() == 7
    errs = [np.linalg.norm(al.apply(c).t - T.t) for c, T in zip(colmap, traj, strict=True)]
    assert errs[3] == pytest.approx(0.2, abs=1e-9)
    assert max(errs[:3] + errs[4:]) < 1e-9


def test_alignment_refits_until_a_hidden_outlier_shows() -> None:
    """COLMAP poses with 1 mm / 0.01 deg noise; the trajectory has one frame turned by 10 deg
    (26 cm at 6 m) and one shifted by 2 cm. The turned frame drags the first fit enough to hide
    the shifted one under 3x the median; refitting without it exposes the shift (a single refit
    does not: measured with `ALIGN_MAX_REFITS` = 1). Both end out of the fit, the shift shows
    at 2 cm +- 3 mm."""
    rng = np.random.default_rng(7)
    truth = [Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) + AHEAD) for _ in range(8)]
    A = Rigid3.from_rotvec([0.3, -0.2, 1.0], [1.0, 2.0, 3.0])
    noise = [Rigid3.from_rotvec(rng.normal(0, 2e-4, 3), rng.normal(0, 1e-3, 3)) for _ in truth]
    colmap = [n @ T @ A.inverse() for n, T in zip(noise, truth, strict=True)]
    traj = list(truth)
    traj[2] = Rigid3.from_rotvec([0.0, 0.0, math.radians(10.0)], [0.0, 0.0, 0.0]) @ truth[2]
    traj[5] = Rigid3(R=truth[5].R, t=truth[5].t + np.array([0.02, 0.0, 0.0]))
    al = align_poses(colmap, traj)
    assert list(np.flatnonzero(~al.used)) == [2, 5]
    pos, _ = pose_differences([al.apply(c) for c in colmap], traj)
    assert abs(pos[5] - 0.02) < 0.003
    assert np.delete(pos, [2, 5]).max() < 0.005


def test_trajectory_times_must_match_frames(synthetic_sequence: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    with pytest.raises(SfmCheckError, match=r"traj\.tum: time 0\.250000 s matches no frame"):
        match_trajectory(seq, np.array([0.25]), [Rigid3.identity()], "traj.tum")
    assert set(match_trajectory(seq, np.array([0.0, 1.0]), [Rigid3.identity()] * 2, "x")) == {0, 2}


def test_check_sfm_cli_errors_are_one_line(
    synthetic_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tum = write_tum([0.3], [Rigid3.identity()], tmp_path / "t.tum")
    args = ["check-sfm", str(synthetic_sequence), "--trajectory", str(tum), "--out"]
    assert main([*args, str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "matches no frame" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "bad",
    [
        {"exclude_mask_ids": (300,)},
        {"frame_step": 0},
        {"max_frames": 2},
        {"min_registered_fraction": 1.5},
        {"inlier_factor": 1.0},
    ],
)
def test_config_is_validated(bad: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        SfmCheckConfig(**bad)  # type: ignore[arg-type]
