"""`satpose report`: PNG plots of a run (matplotlib, no screen needed).

- ``range.png``: true and estimated range per frame (seed 000's Figs. 3-4);
- ``rotation.png``: true and estimated rotation angle about the spin axis per frame
  (Figs. 5-6), estimates in the truth's body axes;
- ``errors.png``: position and rotation errors per frame with the estimator's 3-sigma bounds;
- ``spin.png``: estimated and true spin rate [deg per frame];
- ``timing.png``: time per stage and frame.

Truth comes from the sequence named in the run's run.yaml (or ``--sequence``); without truth
the error plots are skipped and the others show the estimates alone.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import Sequence, load_sequence
from satpose.tools.files import atomic_write, read_tum
from satpose.tools.metrics import body_rotation_offset, pose_errors
from satpose.tools.pipeline import read_estimate_npz, read_provenance


class ReportError(SatposeError):
    """A run folder cannot be plotted."""


def _save(fig: plt.Figure, path: Path) -> Path:
    def write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")

    atomic_write(path, write)
    plt.close(fig)
    return path


def _sequence(run: Path, sequence: Path | None) -> Sequence | None:
    if sequence is not None:
        return load_sequence(sequence)
    p = read_provenance(run).get("sequence")
    if p and Path(p).is_dir():
        return load_sequence(p)
    return None


def make_report(run: Path, sequence: Path | None = None) -> list[Path]:
    """Write the PNG plots of a run folder; returns their paths."""
    if not (run / "estimate.npz").is_file():
        raise ReportError(f"{run}: no estimate.npz (is this a `satpose run` folder?)")
    est = read_estimate_npz(run / "estimate.npz")
    seq = _sequence(run, sequence)
    truth: list[Rigid3] | None = None
    if seq is not None and seq.truth is not None:
        truth = [seq.truth.pose(seq.truth.row_of_frame(int(f))) for f in est.frame]
    others = {}
    for fname, label in (
        ("estimate_smoothed.npz", "iSAM2 smoothed"),
        ("estimate_offline.npz", "offline smoothed"),
        ("estimate_kalman.npz", "Kalman"),
    ):
        if (run / fname).is_file():
            others[label] = read_estimate_npz(run / fname)
    per_frame = None
    if (run / "frontend_pose.tum").is_file():
        per_frame = read_tum(run / "frontend_pose.tum")
    estimator = read_provenance(run).get("estimator", "run")
    label = "online (filtered)" if estimator == "online" else estimator
    out = [
        _range_plot(run, est, label, others, per_frame, truth, seq),
        _rotation_plot(run, est, label, others, truth),
        _spin_plot(run, est, label, others, seq),
    ]
    if truth is not None:
        out.append(_error_plot(run, est, label, truth))
    if (run / "timings.csv").is_file():
        out.append(_timing_plot(run))
    return out


COLORS = {
    "truth": "black",
    "per-frame (frontend)": "0.55",
    "online": "tab:blue",
    "offline": "tab:orange",
    "kalman": "tab:red",
    "iSAM2 smoothed": "tab:purple",
    "offline smoothed": "tab:orange",
    "Kalman": "tab:red",
}
"""One colour per trajectory in every plot (the truth black)."""


def _color(name: str) -> str | None:
    return COLORS.get(name, COLORS.get(name.split()[0]))


def _value_and_error_axes(with_error: bool) -> tuple[plt.Figure, np.ndarray]:
    """A value panel and, when the truth is known, an error panel below it (shared x)."""
    rows = 2 if with_error else 1
    fig, axes = plt.subplots(
        rows,
        1,
        figsize=(8, 3 + 2.5 * (rows - 1)),
        sharex=True,
        squeeze=False,
        gridspec_kw={"height_ratios": [3, 2][:rows]},
    )
    return fig, axes


def _range_plot(run: Path, est, label, others, per_frame, truth, seq) -> Path:
    fig, axes = _value_and_error_axes(truth is not None)
    ax = axes[0, 0]
    series = {name: e for name, e in others.items()}
    series[label] = est
    true_range = None
    if truth is not None:
        true_range = np.array([np.linalg.norm(T.t) for T in truth])
        ax.plot(est.t_s, true_range, "-", color=COLORS["truth"], lw=2, label="truth")
    if per_frame is not None:
        t, poses = per_frame
        r = np.array([np.linalg.norm(T.t) for T in poses])
        ax.plot(t, r, ".", ms=3, color=COLORS["per-frame (frontend)"], label="per-frame (frontend)")
        if true_range is not None:
            r_true = np.interp(t, est.t_s, true_range)
            axes[1, 0].plot(t, 100 * (r - r_true), ".", ms=3, color=COLORS["per-frame (frontend)"])
    for name, e in series.items():
        r = np.array([np.linalg.norm(T.t) for T in e.left_cam_from_target])
        color = _color(name)
        lw = 1.6 if e is est else 1.0
        ax.plot(e.t_s, r, "-", lw=lw, color=color, label=name)
        if true_range is not None:
            axes[1, 0].plot(e.t_s, 100 * (r - true_range), "-", lw=lw, color=color)
    ax.set_ylabel("range to the ring centre [m]")
    ax.set_title("Range: true and estimated (cf. seed 000, Figs. 3-4)")
    ax.legend(fontsize=8)
    if true_range is not None:
        axes[1, 0].axhline(0.0, color="black", lw=0.8)
        axes[1, 0].set_ylabel("estimate - truth [cm]")
    axes[-1, 0].set_xlabel("time [s]")
    for a in axes[:, 0]:
        a.grid(alpha=0.3)
    return _save(fig, run / "range.png")


def _rotation_plot(run: Path, est, label, others, truth) -> Path:
    fig, axes = _value_and_error_axes(truth is not None)
    ax = axes[0, 0]
    poses = list(est.left_cam_from_target)
    w = est.angular_velocity[len(est) // 2]
    axis = w / np.linalg.norm(w) if np.linalg.norm(w) > 0 else np.array([0.0, 0.0, 1.0])
    if truth is not None:
        off = Rigid3(R=body_rotation_offset(poses, truth), t=np.zeros(3))
        poses = [T @ off for T in poses]
        axis = off.R.T @ axis
        ax.plot(
            est.t_s, _angle_series(truth, axis), "-", color=COLORS["truth"], lw=2, label="truth"
        )
        for name, e in {**others, label: est}.items():
            p = list(e.left_cam_from_target)
            err = pose_errors(p, truth, body_rotation_offset(p, truth)).rotation_deg
            lw = 1.6 if e is est else 1.0
            axes[1, 0].plot(e.t_s, err, "-", lw=lw, color=_color(name), label=name)
        axes[1, 0].set_ylabel("rotation error [deg]")
        axes[1, 0].legend(fontsize=8)
    ax.plot(est.t_s, _angle_series(poses, axis), "-", color=_color(label), lw=1.2, label=label)
    axes[-1, 0].set_xlabel("time [s]")
    ax.set_ylabel("rotation about the spin\naxis since frame 0 [deg]")
    ax.set_title("Rotation angle: true and estimated (cf. seed 000, Figs. 5-6)")
    for a in axes[:, 0]:
        a.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, run / "rotation.png")


def _angle_series(poses: list[Rigid3], axis: np.ndarray) -> np.ndarray:
    """Accumulated rotation about ``axis`` (target frame), frame to frame, [deg]."""
    total = [0.0]
    for a, b in itertools.pairwise(poses):
        total.append(total[-1] + float(np.degrees(matrix_to_rotvec(a.R.T @ b.R) @ axis)))
    return np.array(total)


def _error_plot(run: Path, est, label, truth) -> Path:
    poses = list(est.left_cam_from_target)
    R_off = body_rotation_offset(poses, truth)
    off = Rigid3(R=R_off, t=np.zeros(3))
    err = np.array(
        [
            np.concatenate([matrix_to_rotvec(G.R.T @ (T @ off).R), T.t - G.t])
            for T, G in zip(poses, truth, strict=True)
        ]
    )
    # Rotation sigmas about the truth's body axes (the estimate's axes turned by the offset).
    C_rot = np.einsum("ji,njk,kl->nil", R_off, est.pose_covariance[:, :3, :3], R_off)
    sig = np.sqrt(np.clip(np.diagonal(C_rot, axis1=1, axis2=2), 0, None))
    # Position sigmas in camera axes (covariance is in target axes).
    Ct = np.einsum(
        "nij,njk,nlk->nil",
        np.stack([T.R for T in poses]),
        est.pose_covariance[:, 3:, 3:],
        np.stack([T.R for T in poses]),
    )
    sig_t = np.sqrt(np.diagonal(Ct, axis1=1, axis2=2))
    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharex=True)
    for k, name in enumerate("xyz"):
        ax = axes[0, k]
        ax.plot(est.t_s, 100 * err[:, 3 + k], color="tab:blue", lw=1)
        ax.fill_between(
            est.t_s,
            -300 * sig_t[:, k],
            300 * sig_t[:, k],
            color="tab:blue",
            alpha=0.15,
            label="3-sigma",
        )
        ax.set_title(f"position error {name} (camera) [cm]")
        ax.grid(alpha=0.3)
        ax = axes[1, k]
        ax.plot(est.t_s, np.degrees(err[:, k]), color="tab:red", lw=1)
        s = np.degrees(sig[:, k])
        ax.fill_between(est.t_s, -3 * s, 3 * s, color="tab:red", alpha=0.15, label="3-sigma")
        ax.set_title(f"rotation error about target {name} [deg]")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(
        f"{label}: error (estimate - truth) with 3-sigma bounds "
        f"(body-frame offset {np.degrees(np.linalg.norm(matrix_to_rotvec(R_off))):.1f} deg removed)"
    )
    return _save(fig, run / "errors.png")


def _spin_plot(run: Path, est, label, others, seq) -> Path:
    fig, ax = plt.subplots(figsize=(8, 4))
    dt = 1.0 / seq.rate_hz if seq is not None else est.frame_interval_s()
    if seq is not None and seq.truth is not None and seq.truth.angular_velocity is not None:
        ax.plot(
            seq.truth.t_s,
            np.degrees(np.linalg.norm(seq.truth.angular_velocity, axis=1)) * dt,
            "-",
            color=COLORS["truth"],
            lw=2,
            label="truth",
        )
    for name, e in others.items():
        ax.plot(e.t_s, e.spin_rate_deg_per_frame(dt), "-", lw=1, color=COLORS.get(name), label=name)
    rate = est.spin_rate_deg_per_frame(dt)
    s = np.degrees(est.spin_rate_sigma_rad_s()) * dt
    ax.plot(est.t_s, rate, "-", color=_color(label), lw=1.2, label=label)
    ax.fill_between(
        est.t_s,
        rate - 3 * s,
        rate + 3 * s,
        color=_color(label),
        alpha=0.15,
        label=f"{label} 3-sigma",
    )
    finite = rate[np.isfinite(rate)]
    if finite.size:
        mid = float(np.median(finite))
        ax.set_ylim(mid - max(1.0, 0.3 * abs(mid)), mid + max(1.0, 0.3 * abs(mid)))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("spin rate [deg per frame]")
    ax.set_title("Spin rate from the estimated twist")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, run / "spin.png")


def _timing_plot(run: Path) -> Path:
    df = pd.read_csv(run / "timings.csv")
    stages = [c for c in df.columns if c.startswith("frontend_") and c != "frontend_total"]
    backends = [
        c for c in df.columns if c in ("backend_online", "backend_offline", "backend_kalman")
    ]
    if "backend_online_update" in df.columns:
        backends.append("backend_online_update")
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.stackplot(
        df["frame"],
        *[df[c] for c in stages],
        labels=[c.removeprefix("frontend_") for c in stages],
        alpha=0.8,
    )
    for c in backends:
        label = c.removeprefix("backend_").replace("_", " ") + (
            " add()" if c.count("_") == 1 else ""
        )
        ax.plot(df["frame"], df[c], lw=1, label=label)
    ax.set_xlabel("frame")
    ax.set_ylabel("time [ms]")
    ax.set_title("Time per frame: frontend stages (stacked) and backend updates")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, run / "timing.png")
