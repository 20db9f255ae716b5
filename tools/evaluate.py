"""`satpose eval`: a run's trajectories against groundtruth.csv, in seed 000's terms and evo's.

For every trajectory in the run folder (the chosen estimator, the other estimators run for
comparison, the frontend's per-frame poses):

- mean position error of the ring centre (the target-frame origin) [cm];
- mean rotation error after one constant body-frame rotation [deg] (the estimator chooses its
  own x axis) and without it;
- inter-frame (relative) errors [cm, deg];
- all of the above per range band (7-5 m, 5-3 m, below 3 m);
- ATE and RPE as evo defines them: ATE = RMSE of the position error, both as estimated
  (``evo_ape tum GT EST``: the estimate lives in the real left camera frame, so no alignment is
  needed) and after an SE(3) Umeyama alignment of the positions (``evo_ape tum GT EST -a``;
  undefined, like in evo, when the positions are collinear: a straight-line approach leaves
  the rotation about the line free); RPE = RMSE of the translation (and
  rotation) of the relative pose error between consecutive frames (``evo_rpe``, delta 1
  frame), computed on the estimate expressed in the truth's body axes (``T_est R_off``);
- NEES of the 6-D pose error (with the body-frame offset applied) and the fraction of frames
  inside the 95 % chi-square(6) interval, where a covariance exists;
- the spin rate error [deg per frame] where the truth has angular velocities;
- the ESA SPEC score (`satpose.tools.metrics.spec_score`: relative translation plus rotation
  error, each zeroed below its threshold; rotation after the body-frame offset, like the
  rotation errors above).

`evaluate_file` measures the same for one TUM or CSV trajectory file another tool wrote
(`satpose.tools.trajectories`): its poses are matched to the sequence's frames by time within
a tolerance (`associate`; unmatched poses and frames are counted), the NEES needs the CSV's
``pose_cov_*`` columns and the spin-rate error its ``wx wy wz`` (reported n/a otherwise).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

from satpose.backend import Estimate
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import GroundTruth, Sequence, load_sequence
from satpose.tools.files import atomic_write, read_tum, write_tum
from satpose.tools.metrics import (
    RANGE_BANDS_M,
    SignedErrors,
    SpecScore,
    band_label,
    band_mask,
    body_rotation_offset,
    pose_errors,
    relative_errors,
    signed_errors,
    spec_score,
)
from satpose.tools.pipeline import read_estimate_npz, read_provenance
from satpose.tools.trajectories import (
    Association,
    TrajectoryFormat,
    associate,
    read_trajectory,
)


class EvalError(SatposeError):
    """A run cannot be evaluated (no ground truth, missing files)."""


COMPARISON_FILES = {
    "estimate_smoothed.npz": "online smoothed",
    "estimate_online.npz": "online smoothed",
    "estimate_offline.npz": "offline",
    "estimate_kalman.npz": "kalman",
}
"""Trajectories `satpose run` writes besides the chosen estimator's (estimate.npz)."""


DEFAULT_MAX_DT_S = 0.01
"""`evaluate_file`'s default time tolerance when matching poses to frames [s] (evo's
``--t_max_diff`` default)."""


@dataclass(frozen=True)
class Trajectory:
    """Poses matched to ground-truth rows: ``poses[k]`` belongs to ``truth_rows[k]``.

    ``pose_covariance`` (6x6 over [rotation, translation] per pose) and ``angular_velocity``
    (target axes [rad/s]) where the source had them; ``unmatched`` poses matched no frame."""

    name: str
    poses: list[Rigid3]
    truth_rows: list[int]
    pose_covariance: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None
    unmatched: int = 0


def ate_rmse(est: list[Rigid3], truth: list[Rigid3], align: bool = False) -> float | None:
    """evo's ATE: RMSE of the position error (``evo_ape tum GT EST``); with ``align`` after
    the SE(3) Umeyama alignment of the estimated positions onto the true ones
    (``evo_ape ... -a``), or None where evo refuses that alignment (cross-covariance of rank
    below 2: collinear positions)."""
    P = np.array([T.t for T in est])
    Q = np.array([T.t for T in truth])
    if not align:
        return float(np.sqrt(np.mean(np.sum((P - Q) ** 2, axis=1))))
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, d, Vt = np.linalg.svd((Q - mq).T @ (P - mp) / len(P))
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        return None
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    t = mq - R @ mp
    return float(np.sqrt(np.mean(np.sum((P @ R.T + t - Q) ** 2, axis=1))))


def rpe_rmse(est: list[Rigid3], truth: list[Rigid3]) -> tuple[float, float]:
    """evo's RPE with delta 1 frame: RMSE of the translation [m] and of the rotation angle
    [deg] of ``(Q_i^-1 Q_i+1)^-1 (P_i^-1 P_i+1)``."""
    dt, dr = [], []
    for k in range(len(est) - 1):
        E = (truth[k].inverse() @ truth[k + 1]).inverse() @ (est[k].inverse() @ est[k + 1])
        dt.append(float(np.linalg.norm(E.t)))
        dr.append(float(np.degrees(np.linalg.norm(matrix_to_rotvec(E.R)))))
    return float(np.sqrt(np.mean(np.square(dt)))), float(np.sqrt(np.mean(np.square(dr))))


def nees(
    poses: list[Rigid3], covariances: np.ndarray, truth: list[Rigid3], offset: np.ndarray
) -> np.ndarray:
    """Per-frame pose NEES with the estimate re-expressed in the truth's body frame:
    ``T_est R_off``, covariance (N, 6, 6) over [rotation, translation] rotated by the adjoint
    of ``R_off``."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = offset.T
    out = []
    for T, C, G in zip(poses, covariances, truth, strict=True):
        Ta = T @ Rigid3(R=offset, t=np.zeros(3))
        d = Ta.inverse() @ G
        xi = np.concatenate([matrix_to_rotvec(d.R), d.t])
        Ca = A @ C @ A.T
        try:
            out.append(float(xi @ np.linalg.solve(Ca, xi)))
        except np.linalg.LinAlgError:
            out.append(float("nan"))
    return np.array(out)


def _from_estimate(name: str, est: Estimate, truth: GroundTruth) -> Trajectory:
    """An estimate's poses on the truth rows of its frame indices."""
    keep, rows = [], []
    for k, f in enumerate(est.frame):
        try:
            rows.append(truth.row_of_frame(int(f)))
            keep.append(k)
        except KeyError:
            pass
    return Trajectory(
        name,
        [est.left_cam_from_target[k] for k in keep],
        rows,
        est.pose_covariance[keep],
        est.angular_velocity[keep],
        unmatched=len(est) - len(keep),
    )


def _load(run: Path, truth: GroundTruth) -> list[Trajectory]:
    out = []
    estimator = "estimate"
    estimator = str(read_provenance(run).get("estimator", estimator))
    main = {"online": "online filtered", "kalman": "kalman"}.get(estimator, estimator)
    files = {"estimate.npz": main, **COMPARISON_FILES}
    seen = set()
    for fname, name in files.items():
        p = run / fname
        if p.is_file() and name not in seen:
            seen.add(name)
            out.append(_from_estimate(name, read_estimate_npz(p), truth))
    if (run / "frontend_pose.tum").is_file():
        t, poses = read_tum(run / "frontend_pose.tum")  # frames by their exact times
        times = {round(float(ts), 6): i for i, ts in enumerate(truth.t_s)}
        found = [(k, times.get(round(float(ts), 6))) for k, ts in enumerate(t)]
        matched = [(k, r) for k, r in found if r is not None]
        out.append(
            Trajectory(
                "per-frame (frontend)",
                [poses[k] for k, _ in matched],
                [int(r) for _, r in matched],
                unmatched=len(found) - len(matched),
            )
        )
    if not out:
        raise EvalError(f"{run}: no trajectory found (expected estimate.npz from `satpose run`)")
    return out


@dataclass(frozen=True, kw_only=True)
class Bias:
    """The systematic and the random part of the signed errors (`signed_errors`) over one
    trajectory: means and standard deviations of depth [cm], lateral [cm] (the mean lateral
    vector's length; the deviations' RMS distance from it) and tilt [deg]. A bias larger than a
    third of its random part is a defect (``defects``)."""

    depth_cm: float
    depth_sd_cm: float
    lateral_cm: float
    lateral_sd_cm: float
    tilt_deg: float
    tilt_sd_deg: float

    @staticmethod
    def of(e: SignedErrors) -> Bias:
        lat = 100 * e.lateral_m
        mean_lat = lat.mean(axis=0)
        return Bias(
            depth_cm=100 * float(e.depth_m.mean()),
            depth_sd_cm=100 * float(e.depth_m.std(ddof=1)) if len(e.depth_m) > 1 else 0.0,
            lateral_cm=float(np.linalg.norm(mean_lat)),
            lateral_sd_cm=float(np.sqrt(np.sum((lat - mean_lat) ** 2, axis=1).mean())),
            tilt_deg=float(e.tilt_deg.mean()),
            tilt_sd_deg=float(e.tilt_deg.std(ddof=1)) if len(e.tilt_deg) > 1 else 0.0,
        )

    def defects(self) -> list[str]:
        """The error terms whose bias exceeds a third of their random part."""
        pairs = {
            "depth": (self.depth_cm, self.depth_sd_cm),
            "lateral": (self.lateral_cm, self.lateral_sd_cm),
            "tilt": (self.tilt_deg, self.tilt_sd_deg),
        }
        return [name for name, (b, sd) in pairs.items() if abs(b) > sd / 3.0]


@dataclass(frozen=True, kw_only=True)
class BandMetrics:
    """Errors of the frames in one range band."""

    frames: int
    pos_cm: float
    rot_deg: float
    rel_pos_cm: float | None
    rel_rot_deg: float | None


@dataclass(frozen=True, kw_only=True)
class TrajectoryMetrics:
    """Everything `evaluate_run` measures for one trajectory (see the module docstring)."""

    frames: int
    frames_in_sequence: int
    pos_cm: float
    rot_deg: float
    rot_raw_deg: float
    body_offset_deg: float
    rel_pos_cm: float
    rel_rot_deg: float
    ate_m: float
    ate_aligned_m: float | None
    rpe_trans_m: float
    rpe_rot_deg: float
    bands: dict[str, BandMetrics]
    nees_mean: float | None
    nees_in_95: float | None
    spin_err_deg_per_frame: float | None
    bias: Bias
    per_frame: pd.DataFrame
    spec: SpecScore
    poses_unmatched: int = 0


def _truth_of(sequence_path: Path) -> tuple[Sequence, GroundTruth]:
    seq = load_sequence(sequence_path)
    if seq.truth is None:
        raise EvalError(
            f"{sequence_path}: has no groundtruth.csv: nothing to evaluate against "
            "(a real recording; see `satpose check-sfm` for an independent check)"
        )
    return seq, seq.truth


def evaluate_run(sequence_path: Path, run: Path) -> dict[str, TrajectoryMetrics]:
    """Metrics of every trajectory in ``run`` against the sequence's ground truth."""
    seq, truth = _truth_of(sequence_path)
    results: dict[str, TrajectoryMetrics] = {}
    for traj in _load(run, truth):
        m = _metrics(seq, truth, traj)
        if m is not None:
            results[traj.name] = m
    return results


def evaluate_file(
    sequence_path: Path,
    path: Path,
    *,
    fmt: TrajectoryFormat | None = None,
    inverse: bool = False,
    max_dt_s: float = DEFAULT_MAX_DT_S,
) -> tuple[dict[str, TrajectoryMetrics], Association]:
    """Metrics of one TUM/CSV trajectory file (`satpose.tools.trajectories.read_trajectory`:
    ``fmt``, ``inverse``) against the sequence's ground truth, its poses matched to frames by
    time within ``max_dt_s`` [s]. Returns the metrics (keyed by the file name) and the
    association (which poses and frames went unmatched).

    Raises:
        EvalError: no ground truth, or fewer than two poses matched a frame.
        ResultFileError: the file is missing or malformed.
    """
    if not (max_dt_s >= 0 and np.isfinite(max_dt_s)):
        raise EvalError(f"time tolerance must be a finite number >= 0 s, got {max_dt_s}")
    seq, truth = _truth_of(sequence_path)
    track = read_trajectory(path, fmt, inverse=inverse)
    a = associate(track.t_s, truth.t_s, max_dt_s)
    idx = list(a.pose_index)
    traj = Trajectory(
        Path(path).name,
        [track.poses[k] for k in idx],
        [int(r) for r in a.frame_row],
        None if track.pose_covariance is None else track.pose_covariance[idx],
        None if track.angular_velocity is None else track.angular_velocity[idx],
        unmatched=int(a.unmatched_poses.size),
    )
    m = _metrics(seq, truth, traj)
    if m is None:
        raise EvalError(
            f"{path}: only {len(idx)} of its {len(track)} poses (times {track.t_s[0]:.6f} to "
            f"{track.t_s[-1]:.6f} s) lie within {max_dt_s:g} s of a frame of {sequence_path} "
            f"(frames {truth.t_s[0]:.6f} to {truth.t_s[-1]:.6f} s): at least 2 are needed "
            "(check the time origin and units, or --max-dt)"
        )
    return {traj.name: m}, a


def _metrics(seq: Sequence, truth: GroundTruth, traj: Trajectory) -> TrajectoryMetrics | None:
    """Everything `TrajectoryMetrics` holds for matched poses (None below two matches)."""
    if len(traj.poses) < 2:
        return None
    truth_rows = traj.truth_rows
    est = traj.poses
    gt = [truth.pose(r) for r in truth_rows]
    offset = body_rotation_offset(est, gt)
    err = pose_errors(est, gt, offset)
    dt, dr = relative_errors(est, gt, offset)
    # RPE compares motions expressed in the body frame: use the estimate in the truth's
    # body axes (T_est R_off), or a non-cooperative frame choice would count as error.
    off = Rigid3(R=offset, t=np.zeros(3))
    rpe_t, rpe_r = rpe_rmse([T @ off for T in est], gt)
    bands = {}
    for band in RANGE_BANDS_M:
        sel = band_mask(err.range_m, band)
        if sel.any():
            rel = sel[:-1] & sel[1:]
            bands[band_label(band)] = BandMetrics(
                frames=int(sel.sum()),
                pos_cm=100 * float(err.position_m[sel].mean()),
                rot_deg=float(err.rotation_deg[sel].mean()),
                rel_pos_cm=100 * float(dt[rel].mean()) if rel.any() else None,
                rel_rot_deg=float(dr[rel].mean()) if rel.any() else None,
            )
    nees_mean = nees_in = spin_err = None
    if traj.pose_covariance is not None:
        n = nees(est, traj.pose_covariance, gt, offset)
        lo, hi = chi2.ppf([0.025, 0.975], 6)
        nees_mean = float(np.nanmean(n))
        nees_in = float(np.mean((n > lo) & (n < hi)))
    if traj.angular_velocity is not None and truth.angular_velocity is not None:
        dtf = 1.0 / seq.rate_hz
        true_rate = np.degrees(np.linalg.norm(truth.angular_velocity[truth_rows], axis=1)) * dtf
        est_rate = np.degrees(np.linalg.norm(traj.angular_velocity, axis=1)) * dtf
        spin_err = float(np.mean(np.abs(est_rate - true_rate)))
    signed = signed_errors(est, gt)
    per_frame = pd.DataFrame(
        {
            "frame": truth.frame[truth_rows],
            "range_m": err.range_m,
            "pos_err_cm": 100 * err.position_m,
            "rot_err_deg": err.rotation_deg,
            "depth_err_cm": 100 * signed.depth_m,
            "lateral_x_err_cm": 100 * signed.lateral_m[:, 0],
            "lateral_y_err_cm": 100 * signed.lateral_m[:, 1],
            "tilt_err_deg": signed.tilt_deg,
            "normal_err_deg": signed.normal_deg,
        }
    )
    return TrajectoryMetrics(
        frames=len(est),
        frames_in_sequence=len(seq),
        pos_cm=100 * float(err.position_m.mean()),
        rot_deg=float(err.rotation_deg.mean()),
        rot_raw_deg=float(err.rotation_raw_deg.mean()),
        body_offset_deg=err.offset_deg,
        rel_pos_cm=100 * float(dt.mean()),
        rel_rot_deg=float(dr.mean()),
        ate_m=float(ate_rmse(est, gt)),  # type: ignore[arg-type]
        ate_aligned_m=ate_rmse(est, gt, align=True),
        rpe_trans_m=rpe_t,
        rpe_rot_deg=rpe_r,
        bands=bands,
        nees_mean=nees_mean,
        nees_in_95=nees_in,
        spin_err_deg_per_frame=spin_err,
        bias=Bias.of(signed),
        per_frame=per_frame,
        spec=spec_score(est, gt, offset),
        poses_unmatched=traj.unmatched,
    )


def table(results: dict[str, TrajectoryMetrics]) -> str:
    """The printed summary (markdown)."""
    head = (
        "| trajectory | frames | pos [cm] | rot [deg] | rot raw [deg] | inter-frame "
        "[cm / deg] | ATE [cm] | ATE -a [cm] | RPE [cm / deg] | NEES (in 95 %) "
        "| spin err [deg/frame] | SPEC score |"
    )
    lines = [head, "|---" * 12 + "|"]
    for name, m in results.items():
        nees_txt = (
            "n/a"
            if m.nees_mean is None
            else (f"{m.nees_mean:.1f} ({100 * (m.nees_in_95 or 0):.0f} %)")
        )
        aligned = "-" if m.ate_aligned_m is None else f"{100 * m.ate_aligned_m:.2f}"
        spin = "n/a" if m.spin_err_deg_per_frame is None else f"{m.spin_err_deg_per_frame:.3f}"
        lines.append(
            f"| {name} | {m.frames}/{m.frames_in_sequence} | {m.pos_cm:.2f} | {m.rot_deg:.3f} | "
            f"{m.rot_raw_deg:.2f} | {m.rel_pos_cm:.2f} / {m.rel_rot_deg:.3f} | "
            f"{100 * m.ate_m:.2f} | {aligned} | {100 * m.rpe_trans_m:.2f} / {m.rpe_rot_deg:.3f} | "
            f"{nees_txt} | {spin} | {m.spec.score:.4f} |"
        )
    bands = [band_label(b) for b in RANGE_BANDS_M]
    lines += ["", "| trajectory | " + " | ".join(bands) + " |", "|---" * (len(bands) + 1) + "|"]
    for name, m in results.items():
        cells = []
        for b in bands:
            v = m.bands.get(b)
            cells.append("-" if v is None else f"{v.pos_cm:.2f} cm / {v.rot_deg:.3f} deg")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_metrics(
    results: dict[str, TrajectoryMetrics], run: Path, sequence_path: Path | None = None
) -> None:
    """metrics.json (summaries), metrics.csv (per-frame errors, long format) and, given the
    sequence, groundtruth.tum (the true ``left_cam_from_target``, so that
    ``evo_ape tum groundtruth.tum trajectory.tum -a`` reproduces the ATE)."""
    if sequence_path is not None:
        truth = load_sequence(sequence_path).truth
        if truth is not None:
            write_tum(
                truth.t_s, [truth.pose(r) for r in range(len(truth.t_s))], run / "groundtruth.tum"
            )
    summary = {
        name: {k: v for k, v in asdict(m).items() if k != "per_frame"}
        for name, m in results.items()
    }
    text = json.dumps(summary, indent=2)
    atomic_write(run / "metrics.json", lambda tmp: Path(tmp).write_text(text))
    df = pd.concat(
        [m.per_frame.assign(trajectory=name) for name, m in results.items()], ignore_index=True
    )[
        [
            "trajectory",
            "frame",
            "range_m",
            "pos_err_cm",
            "rot_err_deg",
            "depth_err_cm",
            "lateral_x_err_cm",
            "lateral_y_err_cm",
            "tilt_err_deg",
            "normal_err_deg",
        ]
    ]
    atomic_write(run / "metrics.csv", lambda tmp: df.to_csv(tmp, index=False, float_format="%.6g"))
