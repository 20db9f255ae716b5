"""Backend benchmark: accuracy, consistency and speed of the three estimators.

Writes docs/results/backend_simulated.md (or ``--out``). Every table compares methods on the
same measurements in one run. The measurement source is pluggable (`Run`): by default the
frontend's simulator on the presets' exact truth (``frame = truth``, Gaussian pixel noise, no
rendering); ``--sequence DIR --frontend MODULE:ATTR`` runs a rendered sequence through a frontend
instead (docs/backend.md, "Rendered sequences").

    python benchmarks/backend_simulated.py            # full run, ~2-4 min on 2 busy cores
    python benchmarks/backend_simulated.py --quick    # shorter sequences, no sweeps
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from scipy.stats import chi2

from satpose.backend import BackendConfig, Estimate, MeasurementConfig, MotionConfig, make_estimator
from satpose.backend.estimate import StepReport
from satpose.backend.factors import ring_factor, ring_radius_factor
from satpose.backend.keys import RADIUS, V, X
from satpose.backend.motion import constant_twist_factor, psd, sample_trajectory
from satpose.backend.pose3 import exp, local_error, tangent, to_state
from satpose.datasets.geometry import Rigid3
from satpose.datasets.scenarios import preset, trajectory
from satpose.datasets.sequence import Calibration
from satpose.datasets.target import geometry
from satpose.frontend.measurements import FrameMeasurements, PoseMeasurement
from satpose.frontend.pose import PoseConfig
from satpose.frontend.simulate import SimulationConfig, simulate_measurements

OUT = Path("docs/results/backend_simulated.md")

SPEED = """
Per-frame cost of `add()`; `update` is iSAM2's update (for the first frames a batch warm-up
instead, see docs/backend.md); `add() total` also builds the factors and reads the filtered
estimate and its marginal covariances. Python factors: time spent inside the Python
`CustomFactor`s (motion prior, ring, gauge), which hold the GIL.
"""

CONSISTENCY = """
The presets' truth is deterministic (constant body spin, straight-line centroid), so the
prior's random accelerations over-cover it and the NEES above is below 6 (conservative). Here
the truth is drawn from the motion prior itself (`backend.motion.sample_trajectory`, default
noise), measured by the same frontend simulator (`frame='truth'`; its map is then exact, so
its per-frame pose covariance gets no map-error term, `PoseConfig(map_sigma_m=1e-6)`) and
solved without robust kernel. Joint NEES: the error of the whole trajectory against the
smoother's joint covariance, chi-square with 6N (12N) degrees of freedom when consistent: the
exact test for correlated frames.
"""


def _prose(text: str) -> str:
    return " ".join(text.split())


# --------------------------------------------------------------------------------------------
# Measurement sources
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    """What a measurement source returns: measurements of every frame plus the truth."""

    name: str
    calib: Calibration
    t_s: np.ndarray
    truth: list[Rigid3]
    twists: np.ndarray | None  # (N, 6) body twists [omega, v] (target frame), or None
    measurements: list[FrameMeasurements]


def simulated(
    name: str,
    frames: int | None = None,
    sigma_px: float = 0.5,
    seed: int = 1,
    truth: str = "preset",
    frame: str = "truth",
    map_sigma_m: float | None = None,
) -> Run:
    """The frontend's simulator on a preset's exact kinematics, or on a trajectory drawn from the
    backend's motion prior starting there (``truth = "sampled"``). ``frame``: the simulator's
    target frame, ``truth`` (landmark map seeded from target.yaml) or ``bootstrap`` (fixed from
    the first noisy frame, map learnt, as on real data). ``map_sigma_m`` overrides the
    frontend's map-error term of its per-frame pose covariance."""
    s = preset(name) if frames is None else replace(preset(name), frames=frames)
    tr = trajectory(s)
    poses = list(tr.left_cam_from_target)
    twists = np.array(
        [
            np.r_[w, T.R.T @ v]
            for w, v, T in zip(tr.angular_velocity, tr.linear_velocity, poses, strict=True)
        ]
    )
    label = f"{name} ({len(poses)} frames)"
    if truth == "sampled":
        poses, twists = sample_trajectory(
            poses[0], twists[0], tr.t_s, MotionConfig(), np.random.default_rng(seed)
        )
        label += ", truth drawn from the motion prior"
    if frame == "bootstrap":
        label += ", frame=bootstrap"
    ms = simulate_measurements(
        poses,
        tr.t_s,
        s.rig.calibration(),
        geometry(s.target),
        SimulationConfig(
            sigma_px=sigma_px,
            frame=frame,
            pose=PoseConfig() if map_sigma_m is None else PoseConfig(map_sigma_m=map_sigma_m),
        ),
        seed=seed,
    )
    return Run(label, s.rig.calibration(), tr.t_s, poses, twists, ms)


def from_sequence(path: Path, frontend: str) -> Run:
    """A recorded/rendered sequence through a frontend. ``frontend`` is ``MODULE:ATTR`` where
    ``ATTR`` is either a function ``(sequence) -> list[FrameMeasurements]`` or a class built
    with the sequence's calibration that has ``process_frame(frame) -> FrameMeasurements``."""
    from satpose.datasets.sequence import load_sequence

    seq = load_sequence(path)
    if seq.truth is None:
        raise SystemExit(f"{path}: no groundtruth.csv, nothing to compare with")
    module, _, attr = frontend.partition(":")
    obj: Any = getattr(importlib.import_module(module), attr)
    if isinstance(obj, type):
        fe = obj(seq.calibration)
        ms = [fe.process_frame(frame) for frame in seq]
    else:
        ms = list(obj(seq))
    gt = seq.truth
    poses = [gt.pose(i) for i in range(len(gt))]
    twists = None
    if gt.angular_velocity is not None and gt.linear_velocity is not None:
        twists = np.array(
            [
                np.r_[w, T.R.T @ v]
                for w, v, T in zip(gt.angular_velocity, gt.linear_velocity, poses, strict=True)
            ]
        )
    return Run(
        f"{seq.name} ({len(poses)} frames, rendered)", seq.calibration, gt.t_s, poses, twists, ms
    )


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------


def per_frame_estimate(run: Run) -> Estimate:
    """The frontend's per-frame poses as an `Estimate` (frames without a pose dropped; no twist:
    zeros with unit covariance, never reported)."""
    rows = [(k, m) for k, m in enumerate(run.measurements) if m.pose is not None]
    return Estimate(
        frame=[k for k, _ in rows],
        t_s=[run.t_s[k] for k, _ in rows],
        left_cam_from_target=tuple(m.pose.left_cam_from_target for _, m in rows),
        twist=np.zeros((len(rows), 6)),
        pose_covariance=np.array([m.pose.covariance for _, m in rows]),
        twist_covariance=np.tile(np.eye(6), (len(rows), 1, 1)),
    )


def metrics(est: Estimate, run: Run, with_twist: bool = True) -> dict[str, float]:
    """Errors against the truth: absolute (mean/RMS), inter-frame, NEES, spin rate."""
    idx = np.asarray(est.frame)
    truth = [run.truth[k] for k in idx]
    e = np.array([local_error(p, T) for p, T in zip(est.left_cam_from_target, truth, strict=True)])
    pos = np.array(
        [np.linalg.norm(p.t - T.t) for p, T in zip(est.left_cam_from_target, truth, strict=True)]
    )
    rot = np.degrees(np.linalg.norm(e[:, :3], axis=1))
    # inter-frame (seed 000's "relative" error): the estimated motion between consecutive
    # frames against the true one
    rel_pos, rel_rot = [], []
    for a in range(len(idx) - 1):
        if idx[a + 1] != idx[a] + 1:
            continue
        d_est = est.left_cam_from_target[a].inverse() @ est.left_cam_from_target[a + 1]
        d_true = truth[a].inverse() @ truth[a + 1]
        d = local_error(d_est, d_true)
        rel_pos.append(np.linalg.norm((d_est.inverse() @ d_true).t))
        rel_rot.append(np.degrees(np.linalg.norm(d[:3])))
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(est.pose_covariance, e[..., None])[..., 0])
    out = {
        "pos_mean_cm": 100 * pos.mean(),
        "pos_rms_cm": 100 * np.sqrt(np.mean(pos**2)),
        "rot_mean_deg": rot.mean(),
        "rot_rms_deg": np.sqrt(np.mean(rot**2)),
        "rot_mean_late_deg": float(rot[idx >= 10].mean()) if np.any(idx >= 10) else np.nan,
        "rel_pos_cm": 100 * float(np.mean(rel_pos)),
        "rel_rot_deg": float(np.mean(rel_rot)),
        "nees": float(nees.mean()),
        "n": float(len(idx)),
    }
    if with_twist and run.twists is not None:
        tw = run.twists[idx]
        te = tw - est.twist
        out["twist_nees"] = float(
            np.einsum(
                "ni,ni->n", te, np.linalg.solve(est.twist_covariance, te[..., None])[..., 0]
            ).mean()
        )
        dt = float(np.median(np.diff(run.t_s)))
        rate_err = np.abs(
            est.spin_rate_deg_per_frame(dt) - np.degrees(np.linalg.norm(tw[:, :3], axis=1)) * dt
        )
        out["spin_mean"] = float(rate_err.mean())
        out["spin_max"] = float(rate_err[idx >= 5].max())  # after the first 5 frames
        out["spin_last"] = float(rate_err[-1])
    return out


def nees_interval(n_frames: int, dof: int = 6) -> tuple[float, float]:
    """95% interval of the average of ``n_frames`` independent chi2(dof) NEES values."""
    lo, hi = chi2.ppf([0.025, 0.975], dof * n_frames)
    return lo / n_frames, hi / n_frames


# --------------------------------------------------------------------------------------------
# Running the estimators
# --------------------------------------------------------------------------------------------


@dataclass
class Result:
    estimate: Estimate
    filtered: Estimate | None
    reports: list[StepReport]
    seconds: float
    estimator: Any


def run_estimator(
    name: str, run: Run, config: BackendConfig, ms: Sequence[FrameMeasurements] | None = None
) -> Result:
    reports: list[StepReport] = []
    est = make_estimator(name, run.calib, config, hook=reports.append)
    t0 = time.perf_counter()
    for m in run.measurements if ms is None else ms:
        est.add(m)
    out = est.estimate()
    seconds = time.perf_counter() - t0
    filtered = est.filtered() if hasattr(est, "filtered") else None
    return Result(out, filtered, reports, seconds, est)


def config(coupling: str, **kw: Any) -> BackendConfig:
    meas = {k: v for k, v in kw.items() if k in ("robust", "ring_radius", "robust_quantile")}
    motion = {k: v for k, v in kw.items() if k.endswith("_rthz")}
    return BackendConfig(
        measurements=MeasurementConfig(coupling=coupling, **meas),
        motion=MotionConfig(**motion),
    )


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def fmt(x: float | None, digits: int = 3) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    return f"{x:.{digits}f}"


def accuracy_section(run: Run) -> tuple[str, dict[str, dict[str, float]]]:
    results: dict[str, dict[str, float]] = {}
    results["per-frame poses (frontend)"] = metrics(per_frame_estimate(run), run, with_twist=False)
    results["kalman (paper baseline)"] = metrics(
        run_estimator("kalman", run, config("loose")).estimate, run
    )
    for coupling in ("loose", "tight"):
        on = run_estimator("online", run, config(coupling))
        assert on.filtered is not None
        results[f"online iSAM2 filtered, {coupling}"] = metrics(on.filtered, run)
        results[f"online iSAM2 final, {coupling}"] = metrics(on.estimate, run)
        results[f"offline batch, {coupling}"] = metrics(
            run_estimator("offline", run, config(coupling)).estimate, run
        )
    n = len(run.truth)
    lo, hi = nees_interval(n)
    rows = []
    for label, r in results.items():
        rows.append(
            [
                label,
                fmt(r["pos_mean_cm"]),
                fmt(r["pos_rms_cm"]),
                fmt(r["rot_mean_deg"]),
                fmt(r["rot_rms_deg"]),
                fmt(r["rot_mean_late_deg"]),
                fmt(r["rel_pos_cm"]),
                fmt(r["rel_rot_deg"]),
                fmt(r["nees"], 2),
                fmt(r.get("twist_nees"), 2),
                fmt(r.get("spin_mean"), 4),
                fmt(r.get("spin_max"), 4),
                fmt(r.get("spin_last"), 4),
            ]
        )
    text = table(
        [
            "method",
            "pos mean [cm]",
            "pos RMS [cm]",
            "rot mean [deg]",
            "rot RMS [deg]",
            "rot mean, frames >= 10 [deg]",
            "inter-frame pos [cm]",
            "inter-frame rot [deg]",
            "pose NEES",
            "twist NEES",
            "spin err mean [deg/frame]",
            "spin err max, frames >= 5",
            "spin err, last frame",
        ],
        rows,
    )
    text += (
        f"\n\nNEES: average over the {n} frames; 6 if consistent. 95% interval for {n} "
        f"independent frames: [{lo:.2f}, {hi:.2f}] (frames of a smoother or filter are correlated, "
        "which widens the true interval)."
    )
    return text, results


def targets_section(res: dict[str, dict[str, dict[str, float]]], timing: dict[str, float]) -> str:
    rows = []
    for run_name, r in res.items():
        pf = r["per-frame poses (frontend)"]
        kf = r["kalman (paper baseline)"]
        for coupling in ("loose", "tight"):
            off = r[f"offline batch, {coupling}"]
            on = r[f"online iSAM2 filtered, {coupling}"]
            for q, unit in (("pos_mean_cm", "position"), ("rot_mean_deg", "rotation")):
                rows.append(
                    [
                        run_name,
                        coupling,
                        unit,
                        f"{pf[q] / off[q]:.2f}x",
                        "yes" if pf[q] / off[q] >= 2 else "**no**",
                        "yes" if off[q] < kf[q] else "**no**",
                        "yes" if on[q] < kf[q] else "**no**",
                    ]
                )
            spin = max(
                off.get("spin_max", np.nan),
                r[f"online iSAM2 final, {coupling}"].get("spin_max", np.nan),
            )
            rows.append(
                [
                    run_name,
                    coupling,
                    "spin rate, offline and online final, frames >= 5",
                    f"max err {spin:.4f} deg/frame",
                    "yes (< 0.1)" if spin < 0.1 else "**no**",
                    "",
                    f"filtered: max err {on['spin_max']:.4f}",
                ]
            )
    text = table(
        [
            "sequence",
            "coupling",
            "quantity",
            "per-frame / offline",
            "offline >= 2x better",
            "offline < kalman",
            "online filtered < kalman",
        ],
        rows,
    )
    text += "\n\n" + "\n".join(
        f"- iSAM2 update, {k}: median {v:.2f} ms per frame (target <= 10 ms)"
        for k, v in timing.items()
    )
    return text


def timing_section(run: Run) -> tuple[str, dict[str, float]]:
    rows = []
    medians: dict[str, float] = {}
    for coupling in ("loose", "tight"):
        on = run_estimator("online", run, config(coupling))
        steps = [r for r in on.reports if "update" in r.timings_ms]
        upd = np.array([r.timings_ms["update"] for r in steps])
        # disjoint stages only (python_factors lies inside build/update, *_cpu is CPU time)
        tot = np.array(
            [
                sum(
                    v
                    for k, v in r.timings_ms.items()
                    if k in ("build", "update", "warm_up", "estimate")
                )
                for r in on.reports
            ]
        )
        cpu = np.array([r.timings_ms["update_cpu"] for r in steps])
        py = np.array([r.timings_ms.get("python_factors", 0.0) for r in steps])
        medians[f"{coupling}, {len(run.truth)} frames"] = float(np.median(upd))
        rows.append(
            [
                f"online iSAM2, {coupling}",
                fmt(np.median(upd), 2),
                fmt(np.median(cpu), 2),
                fmt(np.percentile(upd, 95), 2),
                fmt(np.median(upd[-10:]), 2),
                fmt(np.median(tot), 2),
                f"{100 * py.sum() / upd.sum():.0f}%",
                fmt(on.seconds, 2),
            ]
        )
        off = run_estimator("offline", run, config(coupling))
        opt = [r for r in off.reports if r.step == "optimize"][-1]
        rows.append(
            [
                f"offline batch, {coupling}",
                "",
                "",
                "",
                "",
                "",
                f"{100 * opt.timings_ms['python_factors'] / opt.timings_ms['optimize']:.0f}%",
                f"{off.seconds:.2f} ({opt.iterations} LM iterations, "
                f"marginals {opt.timings_ms['marginals'] / 1e3:.2f} s)",
            ]
        )
    kf = run_estimator("kalman", run, config("loose"))
    ku = np.array([r.timings_ms["update"] for r in kf.reports])
    rows.append(
        [
            "kalman",
            fmt(np.median(ku), 3),
            "",
            fmt(np.percentile(ku, 95), 3),
            "",
            "",
            "0%",
            fmt(kf.seconds, 3),
        ]
    )
    text = table(
        [
            "estimator",
            "update median [ms]",
            "update CPU median [ms]",
            "update p95 [ms]",
            "update median, last 10 frames [ms]",
            "add() total median [ms]",
            "time in Python factors",
            "whole sequence [s]",
        ],
        rows,
    )
    return text, medians


def _time_linearize(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, calls: int = 2000
) -> float:
    best = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(calls):
            factor.linearize(values)
        best.append((time.perf_counter() - t0) / calls * 1e6)
    return float(np.median(best))


def custom_factor_section(run: Run) -> str:
    """Linearisation cost of the Python factors against comparable C++ factors."""
    cfg = MotionConfig()
    T0, T1 = run.truth[0], run.truth[1]
    dt = float(run.t_s[1] - run.t_s[0])
    xi = run.twists[0] if run.twists is not None else np.zeros(6)
    v_state = gtsam.Values()
    v_state.insert(X(0), to_state(T0))
    v_state.insert(X(1), to_state(T1))
    v_state.insert(V(0), xi)
    v_state.insert(V(1), xi)
    v_state.insert(RADIUS, np.array([0.3]))
    v_pose = gtsam.Values()  # the C++ WNOA factor acts on T directly
    v_pose.insert(X(0), gtsam.Pose3(gtsam.Rot3(T0.R), T0.t))
    v_pose.insert(X(1), gtsam.Pose3(gtsam.Rot3(T1.R), T1.t))
    v_pose.insert(V(0), xi)
    v_pose.insert(V(1), xi)
    ring = next(m.ring for m in run.measurements if m.ring is not None)
    noise6 = gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)
    entries = [
        (
            "constant-twist motion prior (Python CustomFactor)",
            constant_twist_factor(0, 1, dt, cfg),
            v_state,
        ),
        (
            "GTSAM WnoaMotionFactorPose3 (C++, same keys and residual size)",
            gtsam.WnoaMotionFactorPose3(
                gtsam.StateData(X(0), V(0), 0.0), gtsam.StateData(X(1), V(1), dt), psd(cfg)
            ),
            v_pose,
        ),
        (
            "ring centre/normal factor (Python CustomFactor, 5-D)",
            ring_factor(ring, 0, MeasurementConfig()),
            v_state,
        ),
        (
            "ring radius factor (Python CustomFactor, 1-D)",
            ring_radius_factor(ring, 0, 0, MeasurementConfig()),
            v_state,
        ),
        (
            "GTSAM PriorFactorPose3 (C++, 6-D)",
            gtsam.PriorFactorPose3(X(0), to_state(T0), noise6),
            v_state,
        ),
        (
            "GTSAM BetweenFactorPose3 (C++, 6-D)",
            gtsam.BetweenFactorPose3(X(0), X(1), gtsam.Pose3(), noise6),
            v_state,
        ),
    ]
    times = {label: _time_linearize(f, v) for label, f, v in entries}
    base = times["GTSAM BetweenFactorPose3 (C++, 6-D)"]
    rows = [[label, fmt(t, 1), f"{t / base:.0f}x"] for label, t in times.items()]
    return table(["factor", "linearize [us]", "vs BetweenFactorPose3"], rows)


def sensitivity_section(runs: list[Run]) -> str:
    rows = []
    for run in runs:
        for qa in (1e-5, 1e-4, 1e-3):
            for ql in (1e-4, 2e-4, 1e-3):
                for coupling in ("loose", "tight"):
                    r = metrics(
                        run_estimator(
                            "offline",
                            run,
                            config(
                                coupling,
                                angular_accel_noise_rad_s2_rthz=qa,
                                linear_accel_noise_m_s2_rthz=ql,
                            ),
                        ).estimate,
                        run,
                    )
                    rows.append(
                        [
                            run.name,
                            f"{qa:g}",
                            f"{ql:g}",
                            coupling,
                            fmt(r["pos_mean_cm"]),
                            fmt(r["rot_mean_deg"]),
                            fmt(r["nees"], 2),
                            fmt(r["twist_nees"], 2),
                            fmt(r["spin_max"], 4),
                        ]
                    )
    return table(
        [
            "sequence",
            "angular [rad/s^2/rtHz]",
            "linear [m/s^2/rtHz]",
            "coupling",
            "pos mean [cm]",
            "rot mean [deg]",
            "pose NEES",
            "twist NEES",
            "spin err max [deg/frame]",
        ],
        rows,
    )


def radius_section(runs: list[Run]) -> str:
    """Tight coupling with and without the shared ring-radius variable."""
    rows = []
    for run in runs:
        for shared in (True, False):
            r = metrics(
                run_estimator("offline", run, config("tight", ring_radius=shared)).estimate, run
            )
            rows.append(
                [run.name, "yes" if shared else "no", fmt(r["pos_mean_cm"]), fmt(r["rot_mean_deg"])]
            )
    return table(["sequence", "shared ring radius", "pos mean [cm]", "rot mean [deg]"], rows)


def robust_section(run: Run) -> str:
    """Kernels on outlier-free data and with one injected outlier pose per 10 frames."""
    ms = list(run.measurements)
    outlier = list(ms)
    rng = np.random.default_rng(0)
    bad = set(range(5, len(ms), 10))
    for k in bad:
        m = ms[k]
        if m.pose is None:
            continue
        xi = tangent(np.radians(rng.uniform(-5, 5, 3)), rng.uniform(-0.2, 0.2, 3))
        outlier[k] = replace(
            m,
            pose=PoseMeasurement(
                left_cam_from_target=exp(m.pose.left_cam_from_target, xi),
                covariance=m.pose.covariance,
                method=m.pose.method,
            ),
        )
    rows = []
    for data, label in ((ms, "clean"), (outlier, f"{len(bad)} outlier poses")):
        for kernel in ("none", "huber", "cauchy"):
            for name in ("offline", "online"):
                res = run_estimator(name, run, config("loose", robust=kernel), data)
                for which, est in (("final", res.estimate), ("filtered", res.filtered)):
                    if est is None:
                        continue
                    r = metrics(est, run)
                    rows.append(
                        [
                            label,
                            kernel,
                            f"{name} {which}",
                            fmt(r["pos_mean_cm"]),
                            fmt(r["rot_mean_deg"]),
                            fmt(r["nees"], 2),
                        ]
                    )
    return table(
        [
            "data (loose coupling)",
            "kernel",
            "estimator",
            "pos mean [cm]",
            "rot mean [deg]",
            "pose NEES",
        ],
        rows,
    )


def consistency_section(runs: list[Run]) -> str:
    rows = []
    for run in runs:
        for coupling in ("loose", "tight"):
            res = run_estimator("offline", run, config(coupling, robust="none"))
            est = res.estimator
            e = np.array(
                [
                    local_error(p, T)
                    for p, T in zip(res.estimate.left_cam_from_target, run.truth, strict=True)
                ]
            )
            assert run.twists is not None
            te = run.twists - res.estimate.twist
            out = []
            for which, err in (("pose", e), ("state", np.hstack([e, te]))):
                v = err.reshape(-1)
                nees = float(v @ np.linalg.solve(est.joint_covariance(which), v)) / v.size
                lo, hi = chi2.ppf([0.025, 0.975], v.size) / v.size
                out.append(f"{nees:.3f} [{lo:.3f}, {hi:.3f}]")
            r = metrics(res.estimate, run)
            rows.append([run.name, coupling, *out, fmt(r["nees"], 2), fmt(r["twist_nees"], 2)])
    return table(
        [
            "sequence",
            "coupling",
            "joint pose NEES / dof [95% interval]",
            "joint pose+twist NEES / dof [95% interval]",
            "average pose NEES",
            "average twist NEES",
        ],
        rows,
    )


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    load = os.getloadavg()[0]
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--quick", action="store_true", help="30-frame sequences, no sweeps")
    p.add_argument("--sigma-px", type=float, default=0.5)
    p.add_argument("--sequence", type=Path, action="append", help="rendered sequence folder(s)")
    p.add_argument(
        "--frontend",
        default="satpose.frontend.pipeline:StereoFrontend",
        help="MODULE:ATTR turning a sequence into measurements (with --sequence)",
    )
    args = p.parse_args(argv)
    frames = 30 if args.quick else None
    t_start = time.perf_counter()

    sources: list[Callable[[], Run]]
    if args.sequence:
        sources = [partial(from_sequence, path, args.frontend) for path in args.sequence]
    else:
        sources = [
            partial(simulated, n, frames, args.sigma_px, frame=f)
            for f in ("truth", "bootstrap")
            for n in ("paper-docking", "tumble")
        ]
    runs = [src() for src in sources]

    parts = [
        "# Backend: accuracy, consistency and speed",
        "",
        f"Generated by `python benchmarks/backend_simulated.py{' --quick' if args.quick else ''}` "
        f"(machine: {platform.machine()}, {_cores()} cores shared with other jobs, "
        f"{datetime.date.today().isoformat()}, gtsam {_gtsam_version()}, load average "
        f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end). Do not edit by hand. "
        "Times are wall clock unless marked CPU; other jobs inflate them.",
        "",
        "Measurements: "
        + (
            "the frontend's simulator, `simulate_measurements(..., "
            f"SimulationConfig(sigma_px={args.sigma_px}, frame=...))`: the preset's exact truth "
            "projected with Gaussian pixel noise, then the frontend's own ellipse fit, stereo "
            "circle fit, triangulation and per-frame pose. With `frame='truth'` the frontend's "
            "landmark map is seeded from target.yaml: per-frame poses, the Kalman filter and loose "
            "coupling see an exact map, while tight coupling must estimate the landmarks (which "
            "shows in its filtered rotation over the first ~10 frames). With `frame='bootstrap'` "
            "the frontend fixes the target frame from the first noisy frame and learns its map, as "
            "on real data; the truth is still the target.yaml frame, so any error in that first "
            "frame stays in every per-frame pose."
            if not args.sequence
            else f"rendered sequences through `{args.frontend}`."
        )
        + " Same measurements for every method; estimators start from the measurements. "
        "Default `BackendConfig` unless a table says otherwise.",
        "",
    ]
    res: dict[str, dict[str, dict[str, float]]] = {}
    for run in runs:
        text, r = accuracy_section(run)
        res[run.name] = r
        parts += [f"## Accuracy: {run.name}", "", text, ""]

    timing_run = (
        runs[0] if args.sequence or args.quick else simulated("paper-docking", 100, args.sigma_px)
    )
    ttext, medians = timing_section(timing_run)
    parts += ["## Targets", "", targets_section(res, medians), ""]
    parts += [
        f"## Speed: {timing_run.name}",
        "",
        _prose(SPEED),
        "",
        ttext,
        "",
        "## Cost of a Python CustomFactor",
        "",
        "`linearize()` of one factor, median of 5 x 2000 calls, first frame of the sequence.",
        "",
        custom_factor_section(runs[0]),
        "",
    ]
    if not args.sequence:
        consistency_runs = [
            simulated(n, frames or 40, args.sigma_px, seed=3, truth="sampled", map_sigma_m=1e-6)
            for n in ("paper-docking", "tumble")
        ]
        parts += [
            "## Consistency on a truth drawn from the motion prior",
            "",
            _prose(CONSISTENCY),
            "",
            consistency_section(consistency_runs),
            "",
        ]
    if not args.quick and not args.sequence:
        parts += [
            "## Sensitivity to the process noise (offline)",
            "",
            sensitivity_section([r for r in runs if "bootstrap" not in r.name]),
            "",
            "## Shared ring radius (offline, tight)",
            "",
            radius_section([r for r in runs if "bootstrap" not in r.name]),
            "",
            "## Robust kernels",
            "",
            robust_section(runs[0]),
            "",
        ]
    parts.append(f"Total benchmark time: {time.perf_counter() - t_start:.0f} s.")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(parts) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


def _cores() -> int:
    import os

    return os.cpu_count() or 0


def _gtsam_version() -> str:
    from importlib.metadata import version

    return version("gtsam")


if __name__ == "__main__":
    raise SystemExit(main())
