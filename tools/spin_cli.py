"""``satpose spin SEQUENCE --out DIR``: the spin rate of a far target from one camera (seed 001).

Runs `satpose.frontend.spin.SpinFrontend` over the sequence's left (or only) images, prints the
rate series and writes into DIR (each file atomically):

- ``spin.csv``: ``t_s,rate_deg_s,sigma_deg_s,status,candidates_deg_s,reason`` — one row per
  estimate (every frame once the buffer is full); ``t_s`` is the last frame of the window;
  ``status`` is ``ok``, ``ambiguous`` (rate empty, every rate that fits in
  ``candidates_deg_s``, separated by ``;``, each with ``sigma_deg_s``) or the refusal
  (`satpose.frontend.measurements.SpinStatus`); ``reason`` says why it is not ``ok``; rate
  and sigma are empty when a refusal has no candidate.
- ``spin_angles.csv``: ``frame,t_s,theta_deg,elongation,failure`` — the per-frame silhouette
  angle ``theta'`` the rate comes from.
- ``spin.png``: ``theta'`` over the sequence with the fitted model, a close-up of the last
  window, and the rate with its 1-sigma bars (and the truth when groundtruth.csv has it).
- ``measurements.parquet`` (the frontend -> backend contract, `tools.files`) and
  ``config.yaml`` (the resolved config).

DIR is built in a staging folder and renamed at the end; an existing spin folder is replaced
only with ``--overwrite``. A frame that cannot be measured (unreadable image, an exception)
is a frame without an angle; bad frames are named as warnings and counted at the end.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from satpose.datasets.errors import SequenceError

if TYPE_CHECKING:  # the frontend (OpenCV) loads only when the command runs
    from satpose.frontend.measurements import FrameMeasurements
    from satpose.frontend.spin import SpinConfig, SpinFit, SpinStep
    from satpose.tools.badframes import BadFrames


def _bad_frames() -> BadFrames:
    from satpose.tools.badframes import BadFrames

    return BadFrames()


SPIN_CSV_COLUMNS = ("t_s", "rate_deg_s", "sigma_deg_s", "status", "candidates_deg_s", "reason")


def register(subparsers: Any) -> None:
    """Add ``satpose spin`` to the ``satpose`` command line (see `satpose.tools.cli`)."""
    p = subparsers.add_parser(
        "spin",
        help="spin rate of a far, fast-spinning target from one camera (seed 001)",
        description="Measure the spin rate of a far target from its silhouette in one "
        "camera's images (MSER region, ellipse, angle; the paper's two-sine fit over a "
        "sliding buffer). Uses the left images of a stereo sequence. Writes spin.csv, "
        "spin_angles.csv, spin.png, measurements.parquet and config.yaml into DIR.",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="sequence folder")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="YAML/TOML spin config (region, rate, preprocess; unknown keys are refused), "
        "e.g. rate: {window_frames: 30, model: projection}",
    )
    p.add_argument(
        "--max-rate",
        type=float,
        metavar="DEG_S",
        help="the highest spin rate the target may have [deg/s] (rate.max_rate_deg_s; "
        "overrides the config). Default: below 180 deg per frame; without a half-turn cue "
        "in the outline a rate and its mirror 180 deg * frame rate - rate are then both "
        "reported (ambiguous). Below 90 deg per frame (the paper's assumption) there is one",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing spin output folder (once the new one is complete)",
    )
    p.set_defaults(handler=cmd_spin)


def cmd_spin(args: argparse.Namespace) -> None:
    run_spin_on(
        args.sequence, args.out, args.config, overwrite=args.overwrite, max_rate_deg_s=args.max_rate
    )


@dataclass(frozen=True)
class SpinRun:
    """What `run_spin_on` produced: every frame's step and measurements, and the files."""

    steps: list[SpinStep]
    measurements: list[FrameMeasurements]
    files: list[Path]
    rate_hz: float = 1.0
    bad_frames: BadFrames = field(default_factory=lambda: _bad_frames())


def run_spin_on(
    sequence_path: Path,
    out: Path,
    config_path: Path | None,
    overwrite: bool = False,
    max_rate_deg_s: float | None = None,
) -> SpinRun:
    """The spin frontend over a whole sequence, with a progress bar; prints the rate series
    and a summary (accepted, ambiguous, refused by kind, the first reasons) and writes the
    result files (see the module docstring). ``max_rate_deg_s`` overrides the config's."""
    from dataclasses import replace

    from satpose.datasets.config import load_config, to_plain
    from satpose.frontend.spin import SpinConfig

    config = load_config(SpinConfig, config_path) if config_path else SpinConfig()
    if max_rate_deg_s is not None:
        from satpose.frontend.spin import RateConfig

        if not max_rate_deg_s > 0:
            raise SequenceError(
                Path(sequence_path), "--max-rate", f"must be positive, got {max_rate_deg_s}"
            )
        rate_cfg = RateConfig(**{**to_plain(config.rate), "max_rate_deg_s": max_rate_deg_s})
        config = replace(config, rate=rate_cfg)
    run = run_spin(sequence_path, out, config, overwrite=overwrite)
    print(fold_text(config.rate.max_rate_deg_s, config.rate.half_turn, run.rate_hz))
    print(rate_series_text(run.steps))
    print(f"{summary_text(run.steps)}; wrote {', '.join(str(f) for f in run.files)}")
    if run.bad_frames.count:
        print(run.bad_frames.summary(len(run.measurements)))
    return run


def run_spin(
    sequence_path: Path,
    out: Path,
    config: SpinConfig,
    *,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SpinRun:
    """The spin frontend with ``config`` over a whole sequence; writes the result files (see
    the module docstring) and returns every frame's step, without printing (`run_spin_on`
    prints). ``progress(done, total)`` after each frame (it may stop the run by raising: the
    output folder is then not written)."""
    from satpose.datasets.config import to_plain
    from satpose.datasets.sequence import load_sequence
    from satpose.frontend.spin import SpinFrontend
    from satpose.tools.badframes import BadFrames, measure_frames
    from satpose.tools.files import atomic_write, staged_output, write_measurements

    seq = load_sequence(sequence_path)
    n = config.rate.window_frames
    if len(seq) < n:
        raise SequenceError(
            seq.root / "frames.csv",
            "frame",
            f"{len(seq)} frames, but the spin buffer needs {n} (rate.window_frames)",
        )
    steps: list[SpinStep] = []
    frontend = SpinFrontend(seq.calibration.left, config, hook=steps.append)
    bad = BadFrames(seq.root)
    with staged_output(out, overwrite, marker="spin.csv", what="a spin") as stage:
        results = measure_frames(seq, "spin", frontend.process_frame, bad, progress)
        names = ["spin.csv", "spin_angles.csv", "measurements.parquet", "config.yaml", "spin.png"]
        atomic_write(stage / "spin.csv", lambda tmp: Path(tmp).write_text(spin_csv(steps)))
        atomic_write(stage / "spin_angles.csv", lambda tmp: Path(tmp).write_text(angles_csv(steps)))
        write_measurements(results, stage / "measurements.parquet")
        atomic_write(
            stage / "config.yaml",
            lambda tmp: Path(tmp).write_text(
                yaml.safe_dump({"spin": to_plain(config)}, sort_keys=False)
            ),
        )
        truth = None
        if seq.truth is not None and seq.truth.angular_velocity is not None:
            truth = (seq.truth.t_s, np.degrees(np.linalg.norm(seq.truth.angular_velocity, axis=1)))
        atomic_write(stage / "spin.png", lambda tmp: plot_spin(steps, tmp, seq.name, truth))
    files = [out / name for name in names]
    return SpinRun(steps, results, files, rate_hz=seq.rate_hz, bad_frames=bad)


def fold_text(max_rate_deg_s: float | None, half_turn: bool, rate_hz: float) -> str:
    """What the rates below assume about the fold (printed before the series)."""
    fold, full = 90.0 * rate_hz, 180.0 * rate_hz
    head = (
        f"theta' folds at 90 deg per frame ({fold:g} deg/s at {rate_hz:g} frames/s): a spin "
        f"omega and {full:g} - omega sample alike"
    )
    if max_rate_deg_s is not None and max_rate_deg_s < fold:
        return f"{head}; assumed below {max_rate_deg_s:g} deg/s (rate.max_rate_deg_s)"
    top = (
        f"up to {max_rate_deg_s:g} deg/s (rate.max_rate_deg_s)"
        if max_rate_deg_s is not None
        else f"below {full:g} deg/s (two frames per turn; rate.max_rate_deg_s sets another limit)"
    )
    cue = (
        "the outline's half-turn cue (skewness) picks one where it is consistent; "
        if half_turn
        else "the half-turn cue is off; "
    )
    return f"{head}; rates {top}: {cue}otherwise every candidate is listed (ambiguous)"


def summary_text(steps: list[SpinStep], first: int = 3) -> str:
    """How many estimates were accepted, ambiguous and refused (by kind), the accepted rates'
    mean and spread, and the first distinct refusal reasons."""
    fits = [s.fit for s in steps if s.fit is not None]
    ok = [f for f in fits if f.ok]
    amb = [f for f in fits if f.status.value == "ambiguous"]
    refused = [f for f in fits if not f.ok and f.status.value != "ambiguous"]
    text = f"{len(fits)} estimates: {len(ok)} accepted"
    if ok:
        rates = np.degrees([f.rate_rad_s for f in ok])
        text += f" (mean {rates.mean():.3f} deg/s, std {rates.std():.3f} deg/s)"
    text += f", {len(amb)} ambiguous"
    if amb:
        cands = Counter(
            " or ".join(f"{math.degrees(c):.1f}" for c in f.candidates_rad_s) for f in amb
        )
        text += f" ({cands.most_common(1)[0][0]} deg/s most often)"
    text += f", {len(refused)} refused"
    if refused:
        kinds = Counter(f.status.value for f in refused)
        text += " (" + ", ".join(f"{k} {v}" for k, v in kinds.most_common()) + ")"
        firsts: dict[str, str] = {}  # reason -> status, in order of appearance
        for f in refused:
            firsts.setdefault(f.reason, f.status.value)
        text += "; first reasons: " + " | ".join(
            f"{kind}: {why}" for why, kind in list(firsts.items())[:first]
        )
    return text


def _num(x: float, digits: int = 6) -> str:
    return f"{x:.{digits}f}" if math.isfinite(x) else ""


def spin_csv(steps: list[SpinStep]) -> str:
    """spin.csv: one row per estimate, columns `SPIN_CSV_COLUMNS`."""
    lines: list[list[str]] = [list(SPIN_CSV_COLUMNS)]
    for s in steps:
        if s.fit is None:
            continue
        f = s.fit
        cands = ";".join(_num(math.degrees(c)) for c in f.candidates_rad_s)
        lines.append(
            [
                f"{s.t_s:.6f}",
                _num(math.degrees(f.rate_rad_s)),
                _num(math.degrees(f.sigma_rad_s)),
                f.status.value,
                cands,
                f.reason,
            ]
        )
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(lines)
    return buf.getvalue()


def angles_csv(steps: list[SpinStep]) -> str:
    """spin_angles.csv: every frame's ``theta'`` [deg], elongation and failure reason."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "t_s", "theta_deg", "elongation", "failure"])
    for s in steps:
        a = s.angle
        w.writerow(
            [
                s.frame,
                f"{s.t_s:.6f}",
                _num(math.degrees(a.angle_rad), 4),
                _num(a.elongation, 4),
                a.failure or "",
            ]
        )
    return buf.getvalue()


def rate_series_text(steps: list[SpinStep]) -> str:
    """One line per estimate: time, rate +- sigma [deg/s], status and reason."""
    lines = []
    for s in steps:
        f = s.fit
        if f is None:
            continue
        if f.ok:
            lines.append(
                f"t = {s.t_s:8.2f} s  {math.degrees(f.rate_rad_s):9.4f} +- "
                f"{math.degrees(f.sigma_rad_s):.4f} deg/s  ok"
            )
        elif f.candidates_rad_s:
            listed = " or ".join(f"{math.degrees(c):.4f}" for c in f.candidates_rad_s)
            lines.append(
                f"t = {s.t_s:8.2f} s  {listed} +- {math.degrees(f.sigma_rad_s):.4f} deg/s  "
                f"{f.status.value}: {f.reason}"
            )
        else:
            cand = (
                f"{math.degrees(f.rate_rad_s):9.4f} deg/s"
                if math.isfinite(f.rate_rad_s)
                else " " * 15
            )
            lines.append(f"t = {s.t_s:8.2f} s  {cand}  {f.status.value}: {f.reason}")
    return "\n".join(lines)


def _unjoined(theta_deg: np.ndarray) -> np.ndarray:
    """NaN where the angle wraps from 180 to 0 deg, so that a line plot does not join them."""
    out = np.array(theta_deg, dtype=float)
    jumps = np.flatnonzero(np.abs(np.diff(out)) > 90.0)
    out[jumps + 1] = np.nan
    return out


def plot_spin(
    steps: list[SpinStep],
    path: str | Path,
    title: str,
    truth: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """The spin plot (PNG): ``theta'`` with the fitted model of disjoint windows, the last
    window close up, and the rate series with 1-sigma bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s.t_s for s in steps])
    theta = np.degrees([s.angle.angle_rad for s in steps])
    fits: list[tuple[float, SpinFit]] = [(s.t_s, s.fit) for s in steps if s.fit is not None]
    fig, axes = plt.subplots(3, 1, figsize=(10, 10), constrained_layout=True)
    ax = axes[0]
    ax.plot(t, theta, ".", ms=4, color="C0", label="theta' (measured)")
    bad = ~np.isfinite(theta)
    if bad.any():
        ax.plot(t[bad], np.zeros(bad.sum()), "x", color="C3", label="no angle")
    # Fitted model of windows that do not overlap (the last one always shown).
    shown_until = -math.inf
    labelled = False
    for k, (_, f) in enumerate(fits):
        if not f.model or (f.window_start_s <= shown_until and k != len(fits) - 1):
            continue
        tt = np.linspace(f.window_start_s, f.window_end_s, 400)
        ax.plot(
            tt,
            _unjoined(np.degrees(f.angle(tt))),
            "-",
            lw=0.6,
            color="C1",
            label=None if labelled else f"fit ({f.model})",
        )
        labelled = True
        shown_until = f.window_end_s
    ax.set(xlabel="t [s]", ylabel="theta' [deg]", ylim=(-5, 185), title=f"{title}: theta'")
    ax.legend(loc="upper right", fontsize=8)

    ax = axes[1]
    last = next((f for _, f in reversed(fits) if f.model), None)
    if last is not None:
        inside = (t >= last.window_start_s) & (t <= last.window_end_s)
        tt = np.linspace(last.window_start_s, last.window_end_s, 2000)
        ax.plot(tt, _unjoined(np.degrees(last.angle(tt))), "-", lw=0.8, color="C1", label="fit")
        ax.plot(t[inside], theta[inside], "o", ms=5, color="C0", label="theta'")
        rates = last.candidates_rad_s if last.candidates_rad_s else (last.rate_rad_s,)
        shown = " or ".join(f"{math.degrees(r):.4f}" for r in rates)
        ax.set_title(
            f"last window ({last.window_start_s:g}-{last.window_end_s:g} s): "
            f"{shown} deg/s, {last.status.value}"
        )
        ax.legend(loc="upper right", fontsize=8)
    ax.set(xlabel="t [s]", ylabel="theta' [deg]", ylim=(-5, 185))

    ax = axes[2]
    ok = [(tk, f) for tk, f in fits if f.ok]
    if ok:
        ax.errorbar(
            [tk for tk, _ in ok],
            [math.degrees(f.rate_rad_s) for _, f in ok],
            yerr=[math.degrees(f.sigma_rad_s) for _, f in ok],
            fmt=".",
            ms=4,
            capsize=2,
            color="C0",
            label="rate +- 1 sigma",
        )
    refused = [(tk, f) for tk, f in fits if not f.ok and math.isfinite(f.rate_rad_s)]
    if refused:
        ax.plot(
            [tk for tk, _ in refused],
            [math.degrees(f.rate_rad_s) for _, f in refused],
            "x",
            color="C3",
            label="refused (candidate)",
        )
    amb = [(tk, c) for tk, f in fits for c in f.candidates_rad_s]
    if amb:
        ax.plot(
            [tk for tk, _ in amb],
            [math.degrees(c) for _, c in amb],
            "+",
            color="C2",
            label="ambiguous (every candidate)",
        )
    if truth is not None:
        ax.plot(truth[0], truth[1], "--", color="k", lw=1, label="truth (groundtruth.csv)")
    ax.set(xlabel="t [s] (end of window)", ylabel="spin rate [deg/s]", title="spin rate")
    ax.ticklabel_format(axis="y", useOffset=False)
    if ok or refused or amb or truth is not None:
        ax.legend(loc="best", fontsize=8)
    fig.savefig(path, format="png", dpi=100)
    plt.close(fig)
