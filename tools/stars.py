"""``satpose stars render|track|solve``: the event-camera star tracker (seed 004, docs/stars.md).

``render PRESET --out DIR`` simulates a star-tracker run into an event sequence folder
(docs/event_sequence_format.md). ``track DIR --out OUT`` runs the event (default) or frame
pipeline and the rotation graph and writes OUT/attitude.tum (``inertial_from_camera``, zero
translation), OUT/windows.csv (per-window status), OUT/attitude_error.png when the sequence
has truth, and OUT/config.yaml. ``solve IMAGE... --out DIR``: lost in space on real star
images (tools/stars_solve.py).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import yaml

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.config import to_plain
from satpose.datasets.errors import SatposeError, SequenceError
from satpose.datasets.events import Events
from satpose.datasets.geometry import matrix_to_quat_xyzw, matrix_to_rotvec
from satpose.datasets.sequence import Frame, load_calibration, load_sequence
from satpose.frontend.star_sensor import Thresholds
from satpose.frontend.stars import (
    ARCSEC,
    AttitudeSolution,
    StarTracker,
    StarTrackerConfig,
    frame_spots,
    measure_thresholds,
    relative_rotation_bearings,
    run_event_tracker,
)
from satpose.tools.badframes import BadFrames, guarded
from satpose.tools.files import staged_output

Pipeline = Literal["events", "frames"]


class StarsRunError(SatposeError):
    """`satpose stars track` cannot run with these inputs."""


@dataclass(frozen=True)
class TrackResult:
    """Frontend outputs per window and the smoothed attitude (None where not anchored)."""

    solutions: list[AttitudeSolution]
    t_s: np.ndarray
    R: np.ndarray  # smoothed (N, 3, 3); NaN rows before the first absolute attitude
    cov: np.ndarray
    estimator: str
    bad_frames: BadFrames = field(default_factory=BadFrames)  # frames pipeline only
    config: StarTrackerConfig | None = None  # the frontend's, calib.yaml's event_sensor applied
    measured: dict[str, Any] = field(default_factory=dict)  # what the tracker measured
    events: Events | None = None  # the stream the events pipeline tracked


def open_star_sequence(
    seq_dir: Path, pipeline: Pipeline
) -> tuple[PinholeCamera, tuple[Frame, ...]]:
    """The sensor and the frames of a star sequence folder. An event-only recording (no
    frames.csv: sequence.yaml, calib.yaml, events.h5) has no frames; the frames pipeline
    then has nothing to track and says so.

    Raises:
        SequenceError: naming the file and field.
    """
    root = Path(seq_dir)
    if (root / "frames.csv").is_file() or not root.is_dir():
        seq = load_sequence(root)
        return seq.calibration.left, seq.frames
    if pipeline == "frames":
        raise SequenceError(
            root / "frames.csv",
            None,
            "required file is missing: the frames pipeline needs frames (an event-only "
            "recording runs with --pipeline events)",
        )
    return load_calibration(root / "calib.yaml").left, ()


EVENT_SENSOR_KEYS = ("contrast_threshold", "threshold_sigma", "psf_sigma_px", "refractory_s")
"""Keys of the optional ``event_sensor:`` block of calib.yaml or sequence.yaml: the event
sensor's calibration the spot fit assumes (`StarTrackerConfig` fields of the same names)."""


def event_sensor_calibration(seq_dir: Path) -> dict[str, float]:
    """The ``event_sensor:`` block of ``seq_dir``'s sequence.yaml and calib.yaml (calib.yaml
    wins where both state a key): ``contrast_threshold`` (mean log-intensity threshold C),
    ``threshold_sigma`` (its pixel-to-pixel spread), ``psf_sigma_px`` (Gaussian sigma of the
    star image [px]). Empty when neither states it.

    Raises:
        SequenceError: an unknown key or a value that is not a positive number (naming the
            file and key).
    """
    out: dict[str, float] = {}
    for name in ("sequence.yaml", "calib.yaml"):
        path = Path(seq_dir) / name
        if not path.is_file():
            continue
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise SequenceError(path, None, f"cannot read ({exc})") from None
        block = data.get("event_sensor") if isinstance(data, dict) else None
        if block is None:
            continue
        if not isinstance(block, dict):
            raise SequenceError(path, "event_sensor", "must be a mapping")
        for key, value in block.items():
            if key not in EVENT_SENSOR_KEYS:
                raise SequenceError(
                    path,
                    f"event_sensor.{key}",
                    f"unknown key (known: {', '.join(EVENT_SENSOR_KEYS)})",
                )
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            if (
                not ok
                or not math.isfinite(value)
                or value < 0
                or (value == 0 and key not in ("threshold_sigma", "refractory_s"))
            ):
                raise SequenceError(
                    path, f"event_sensor.{key}", f"must be a positive number, got {value!r}"
                )
            out[key] = float(value)
    return out


def refractory_record(tracker: StarTracker, stated: bool) -> dict[str, Any]:
    """config.yaml's record of the dead time: what the stream showed and what the spot fit's
    levels used (`frontend.stars.stream_levels_dead_time`)."""
    used = round(float(tracker.refractory_used_s), 7)
    reset = tracker.dead_time_reset
    ladder = {
        True: "reset (each step C plus the rise while blind)",
        False: "plain (the fits preferred whole thresholds)",
        None: "plain (no dead time used: dead_time_levels off, or too few fits)",
    }[reset if used > 0 else None]
    if reset is not None:
        c = tracker.dead_time_costs
        ladder += f"; fit costs reset {c[0]:.0f}, plain {c[1]:.0f}"
    r = tracker.refractory
    if stated or r is None:
        src = "stated (event_sensor.refractory_s)" if stated else "configured"
        return {"used_s": used, "source": src, "levels": ladder}
    out: dict[str, Any] = {
        "measured_s": round(float(r.refractory_s), 7),
        "sigma_s": round(float(r.sigma_s), 7),
        "identified": bool(r.identified),
        "edge_blur_s": round(float(r.jitter_s), 7),
        "intervals": int(r.intervals),
        "used_s": used,
        "levels": ladder,
    }
    out["source"] = r.source + ("" if r.identified else "; 0 used")
    return out


def threshold_record(
    th: Thresholds | None, config: StarTrackerConfig, stated: bool
) -> dict[str, Any]:
    """config.yaml's record of the contrast threshold: measured (`measure_thresholds`) and
    used (the configured or stated one)."""
    out: dict[str, Any] = {
        "used": float(config.contrast_threshold),
        "source": "stated (event_sensor.contrast_threshold)" if stated else "configured",
    }
    if th is None:
        out["measured"] = "not identified (too few isolated identified stars or magnitudes)"
        return out
    out["measured"] = {
        "on": round(th.c_on, 4),
        "off": round(th.c_off, 4),
        "sigma_on": round(th.sigma_on, 4),
        "sigma_off": round(th.sigma_off, 4),
        "mean": round(th.c_mean, 4),
        "sigma_mean": round(th.sigma_mean, 4),
        "stars": th.stars,
        "passes": th.passes,
        "magnitudes": [round(th.mag_range[0], 2), round(th.mag_range[1], 2)],
        "dead_time_gain": round(th.refractory_gain, 4),
    }
    return out


def measured_coverage(res: TrackResult) -> tuple[int, float, float]:
    """How much of the recording the frontend measured (not what the smoother filled):
    ``(outputs with a measured attitude, fraction of the time they cover, duration [s])``.
    Output ``i`` covers the time since the previous output (the first: one median output
    period); a lost output's stretch is uncovered even though the smoothed attitude spans it."""
    t = np.array([s.t_s for s in res.solutions], float)
    if t.size == 0:
        return 0, 0.0, 0.0
    measured = np.array([s.R is not None for s in res.solutions])
    period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    stretch = np.diff(t, prepend=t[0] - period)
    duration = float(stretch.sum())
    frac = float(stretch[measured].sum() / duration) if duration > 0 else float(measured.all())
    return int(measured.sum()), frac, duration


def coverage_line(res: TrackResult) -> str:
    """The console's summary of `measured_coverage` and of what the smoother filled."""
    n, frac, duration = measured_coverage(res)
    smoothed = int(np.isfinite(res.R[:, 0, 0]).sum())
    return (
        f"attitude measured in {n}/{len(res.solutions)} outputs, {100 * frac:.1f} % of the "
        f"{duration:.3f} s recording; smoothed attitude at {smoothed}/{len(res.t_s)} outputs "
        f"({smoothed - n} filled by the smoother)"
    )


def windows_from_solutions(sols: list[AttitudeSolution], sigma_rad: float) -> list[Any]:
    """Rotation-graph windows: absolute attitudes and rotation-only relative rotations from the
    stars two consecutive windows share.

    An event output integrates ``span_s`` of events but comes every ``t_i - t_{i-1}``: where
    the spans overlap, consecutive outputs share events, so their errors are not independent
    as the graph assumes. Each absolute covariance (and rate information, divided) is scaled
    by the overlap ``max(1, span / output period)`` (the number of outputs each event is in).
    The attitude goes in at the time its data centre on (``data_t_s``, ``data_R``)."""
    from satpose.backend.rotation import AttitudeWindow

    out = []
    prev: AttitudeSolution | None = None
    for s in sols:
        rel_R = rel_cov = None
        if prev is not None and prev.R is not None and s.R is not None:
            common, ia, ib = np.intersect1d(prev.star_ids, s.star_ids, return_indices=True)
            if common.size >= 3:
                rel_R, rel_cov = relative_rotation_bearings(prev.b_cam[ia], s.b_cam[ib], sigma_rad)
        overlap = 1.0
        if prev is not None and s.span_s > 0 and s.t_s > prev.t_s:
            overlap = max(1.0, s.span_s / (s.t_s - prev.t_s))
        cov = None if s.cov is None else s.cov * overlap
        out.append(
            AttitudeWindow(
                t_s=s.t_s,
                R=s.R if s.data_R is None else s.data_R,
                cov=cov,
                rel_R=rel_R,
                rel_cov=rel_cov,
                t_meas_s=s.data_t_s,
                rate_rad_s=s.rate_meas_rad_s,
                rate_info=None if s.rate_info is None else s.rate_info / overlap,
            )
        )
        prev = s
    return out


def track_sequence(
    seq_dir: Path,
    pipeline: Pipeline = "events",
    estimator: str = "offline",
    config: StarTrackerConfig | None = None,
    graph_config: Any = None,
    duration_s: float | None = None,
) -> TrackResult:
    """Run the frontend and the rotation graph over an event sequence folder."""
    from satpose.backend.rotation import (
        OnlineAttitudeSmoother,
        RotationGraphConfig,
        smooth_attitudes,
    )
    from satpose.datasets.event_io import EVENT_FILE_NAMES, find_events_file, read_events
    from satpose.datasets.star_scenarios import EVENTS_FILE

    cam, frames = open_star_sequence(seq_dir, pipeline)
    stated = event_sensor_calibration(Path(seq_dir))
    config = replace(config or StarTrackerConfig(), **stated)
    if "psf_sigma_px" in stated:  # stated: not measured
        config = replace(config, psf_outputs=0)
    tracker = StarTracker(cam, config)
    ev: Events | None = None
    if pipeline == "events":
        events_file = find_events_file(seq_dir)
        if events_file is None:
            hint = " (a frames-only recording runs with --pipeline frames)" if frames else ""
            raise SequenceError(
                Path(seq_dir) / EVENTS_FILE,
                None,
                f"required file is missing: the events pipeline needs one of "
                f"{', '.join(EVENT_FILE_NAMES)}{hint}",
            )
        ev = read_events(events_file)
        if len(ev) == 0:
            raise SequenceError(events_file, "events", "no events")
        outside = (ev.x >= cam.width) | (ev.y >= cam.height)
        if outside.any():
            k = int(np.argmax(outside))
            raise SequenceError(
                events_file,
                "events/x,y",
                f"{int(outside.sum())} events outside the {cam.width}x{cam.height} sensor of "
                f"calib.yaml (first: x={int(ev.x[k])}, y={int(ev.y[k])})",
            )
        t1 = ev.t_s[-1] if duration_s is None else min(duration_s, ev.t_s[-1])
        sols = run_event_tracker(tracker, ev, 0.0, float(t1))
    bad = BadFrames(Path(seq_dir))
    if pipeline != "events":
        sols = []
        for fr in frames:
            if duration_s is not None and fr.t_s > duration_s:
                break
            try:
                image = fr.image("left")
            except SatposeError as exc:
                why: str | None = f"image: {exc}"
                sol = None
            else:
                sol, why = guarded(
                    "stars",
                    fr.index,
                    lambda image=image, t_s=fr.t_s: tracker.track_spots(
                        frame_spots(image, t_s), t_s
                    ),
                )
            if sol is None:  # a frame without an attitude: the tracker predicts through it
                sol = AttitudeSolution(fr.t_s, None, None, "lost")
            if why is not None:
                bad.note(fr.index, (why,), (fr.left_path,))
            sols.append(sol)
    windows = windows_from_solutions(sols, tracker.sigma_rad)
    # Relative factors off: between two windows that both have absolute priors they reuse
    # the priors' bearings (double counting; docs/stars.md measures both).
    gc = graph_config or RotationGraphConfig(relative_factors=False)
    n = len(windows)
    R = np.full((n, 3, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    first = next((k for k, w in enumerate(windows) if w.R is not None), None)
    if first is not None:
        if estimator == "offline":
            est = smooth_attitudes(windows[first:], gc)
            R[first:], cov[first:] = est.R, est.cov
        elif estimator == "online":
            sm = OnlineAttitudeSmoother(gc)
            for k in range(first, n):
                sm.add(windows[k])
            est = sm.estimate()
            R[first:], cov[first:] = est.R, est.cov
        elif estimator == "frontend":
            for k, s in enumerate(sols):
                if s.R is not None and s.cov is not None:
                    R[k], cov[k] = s.R, s.cov
        else:
            raise SequenceError(seq_dir, "estimator", f"unknown estimator {estimator!r}")
    measured: dict[str, Any] = {}
    if pipeline == "events":
        measured["psf_sigma_px"] = round(float(tracker.psf_sigma_px), 4)
        measured["psf_sigma_source"] = (
            "stated"
            if config.psf_outputs == 0
            else "measured"
            if tracker.psf_measured
            else "configured (too few fitted outputs to measure)"
        )
        if tracker.spot_rms_px is not None:
            measured["star_image_rms_px"] = round(float(tracker.spot_rms_px), 4)
        if tracker.stream_stats is not None:
            st = tracker.stream_stats
            measured["hot_pixels"] = int(st.hot_pixels.size)
            measured["hot_pixel_events"] = int(st.hot_events)
            measured["events_kept_by_noise_filter"] = round(float(st.kept_fraction), 4)
        measured["refractory"] = refractory_record(tracker, "refractory_s" in stated)
        measured["contrast_threshold"] = threshold_record(
            measure_thresholds(tracker, sols), config, "contrast_threshold" in stated
        )
    return TrackResult(
        sols,
        np.array([s.t_s for s in sols]),
        R,
        cov,
        estimator,
        bad,
        config,
        measured,
        ev,
    )


def attitude_errors_arcsec(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """Error rotation vectors ``Log(R_true^T R_est)`` in the camera frame [arcsec], (N, 3):
    x, y cross-boresight, z roll about the boresight."""
    return matrix_to_rotvec(np.einsum("nji,njk->nik", R_true, R_est)) / ARCSEC


def _write_outputs(res: TrackResult, out: Path, seq_dir: Path, meta: dict[str, Any]) -> None:
    from satpose.datasets.star_scenarios import ATTITUDE_TRUTH_FILE, load_attitude_truth

    ok = np.isfinite(res.R[:, 0, 0])
    q = matrix_to_quat_xyzw(res.R[ok]) if ok.any() else np.zeros((0, 4))
    tum = np.column_stack([res.t_s[ok], np.zeros((int(ok.sum()), 3)), q])
    np.savetxt(out / "attitude.tum", tum, fmt="%.9f")
    sig = np.sqrt(np.clip(np.diagonal(res.cov, axis1=1, axis2=2), 0, None)) / ARCSEC
    df = pd.DataFrame(
        {
            "window": np.arange(len(res.solutions)),
            "t_s": res.t_s,
            "status": [s.status for s in res.solutions],
            "stars": [len(s.star_ids) for s in res.solutions],
            "cpu_ms": [s.cpu_ms for s in res.solutions],
            "sigma_x_arcsec": sig[:, 0],
            "sigma_y_arcsec": sig[:, 1],
            "sigma_roll_arcsec": sig[:, 2],
        }
    )
    truth_path = seq_dir / ATTITUDE_TRUTH_FILE
    if truth_path.is_file():
        truth = load_attitude_truth(truth_path)
        err = np.full((len(res.t_s), 3), np.nan)
        if ok.any():
            err[ok] = attitude_errors_arcsec(res.R[ok], truth.at(res.t_s[ok]))
        df["err_x_arcsec"], df["err_y_arcsec"], df["err_roll_arcsec"] = err.T
        _plot_errors(df, out / "attitude_error.png", res.estimator)
    df.to_csv(out / "windows.csv", index=False, float_format="%.6g")
    (out / "config.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")


SKY = "camera/sky"
EVENTS = "camera/events"
EVENT_IMAGE = "camera/event_image"
STARS = "camera/identified_stars"
ERRORS = "error_arcsec"
RATE = "rate_deg_s"
TIMING = "timing_ms"
STAR_COUNT = "stars_used"


def stars_blueprint() -> Any:
    """The star run's layout: the camera (sky frame, event image, events, identified stars)
    left; errors vs truth, body rate, CPU per output and stars used right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="camera", name="camera (events, identified stars)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=ERRORS, name="attitude error vs truth [arcsec]"),
                rrb.TimeSeriesView(origin=RATE, name="body rate, smoothed [deg/s]"),
                rrb.TimeSeriesView(origin=TIMING, name="CPU per output [ms]"),
                rrb.TimeSeriesView(origin=STAR_COUNT, name="stars used"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def write_recording(
    res: TrackResult, seq_dir: Path, path: Path, every: int = 4, max_events: int = 4000
) -> None:
    """Rerun recording (layout `stars_blueprint`): the frames (sky image), each
    ``every``-th window's event image and events (red ON, blue OFF), the identified stars
    reprojected with the smoothed attitude, the attitude errors vs truth (when
    attitude_truth.csv exists), the smoothed body rate, each output's CPU time and stars
    used. Timeline ``time`` in seconds."""
    import rerun as rr

    from satpose.datasets.event_io import find_events_file, read_events
    from satpose.datasets.star_scenarios import (
        ATTITUDE_TRUTH_FILE,
        EVENTS_FILE,
        load_attitude_truth,
    )
    from satpose.frontend.stars import solver_catalogue

    cam, frames = open_star_sequence(seq_dir, "events")
    rec = rr.RecordingStream(application_id="satpose-stars", recording_id=None)
    rec.save(str(path))
    rec.send_blueprint(stars_blueprint())
    rec.log(
        "camera",
        rr.Pinhole(image_from_camera=cam.K, resolution=[cam.width, cam.height]),
        static=True,
    )
    for fr in frames:
        rec.set_time("time", duration=float(fr.t_s))
        img = fr.image("left").astype(np.float64)
        lo, hi = np.percentile(img, [1.0, 99.9])
        img8 = (np.clip((img - lo) / max(hi - lo, 1.0), 0, 1) * 255).astype(np.uint8)
        rec.log(SKY, rr.Image(img8, color_model="L"))
    ev = res.events
    if ev is None:  # the frames pipeline tracked: the recording's events, if any
        events_file = find_events_file(seq_dir)
        if events_file is None:
            raise SequenceError(Path(seq_dir) / EVENTS_FILE, None, "required file is missing")
        ev = read_events(events_file)
    truth_path = seq_dir / ATTITUDE_TRUTH_FILE
    truth = load_attitude_truth(truth_path) if truth_path.is_file() else None
    ok = np.isfinite(res.R[:, 0, 0])
    err = np.full((len(res.t_s), 3), np.nan)
    if truth is not None and ok.any():
        err[ok] = attitude_errors_arcsec(res.R[ok], truth.at(res.t_s[ok]))
    tracker_cfg = res.config or StarTrackerConfig()
    w = tracker_cfg.window_s
    # Body rate from consecutive smoothed attitudes (camera frame).
    rate = np.full((len(res.t_s), 3), np.nan)
    both = ok[1:] & ok[:-1] & (np.diff(res.t_s) > 0)
    if both.any():
        i = np.flatnonzero(both)
        d = np.einsum("nji,njk->nik", res.R[i], res.R[i + 1])
        rate[i + 1] = np.degrees(matrix_to_rotvec(d)) / np.diff(res.t_s)[i, None]
    for k, sol in enumerate(res.solutions):
        rec.set_time("time", duration=float(sol.t_s))
        if ok[k] and truth is not None:
            for name, v in zip(("x", "y", "roll"), err[k], strict=True):
                rec.log(f"{ERRORS}/{name}", rr.Scalars(float(v)))
        if np.isfinite(rate[k, 0]):
            for name, v in zip(("x", "y", "z"), rate[k], strict=True):
                rec.log(f"{RATE}/{name}", rr.Scalars(float(v)))
        rec.log(f"{TIMING}/tracking", rr.Scalars(float(sol.cpu_ms)))
        rec.log(f"{TIMING}/stream_share", rr.Scalars(float(sol.stream_cpu_ms)))
        rec.log(STAR_COUNT, rr.Scalars(float(len(sol.star_ids))))
        if k % every:
            continue
        win = ev.slice_time(sol.t_s - w / 2, sol.t_s + w / 2)
        # The event image of the window: ON counts red, OFF counts blue (what an
        # event-only recording shows instead of a sky frame).
        img = np.zeros((cam.height, cam.width, 3), dtype=np.uint8)
        if len(win):
            flat = win.y.astype(np.int64) * cam.width + win.x.astype(np.int64)
            for ch, pol in ((0, 1), (2, 0)):
                cnt = np.bincount(flat[win.p == pol], minlength=cam.width * cam.height)
                img[..., ch] = np.clip(cnt * 80, 0, 255).reshape(cam.height, cam.width)
        rec.log(EVENT_IMAGE, rr.Image(img, color_model="RGB"))
        if len(win):
            sel = slice(0, min(len(win), max_events))
            colors = np.where(win.p[sel, None] > 0, [[230, 60, 40]], [[40, 90, 230]])
            rec.log(
                EVENTS,
                rr.Points2D(
                    np.column_stack([win.x[sel], win.y[sel]]).astype(np.float32),
                    colors=colors.astype(np.uint8),
                    radii=rr.Radius.ui_points(1.5),
                ),
            )
        if ok[k] and sol.star_ids.size:
            cat = solver_catalogue(*_db_scales(cam), tracker_cfg.epoch_yr)
            rows = [cat.row_of[int(i)] for i in sol.star_ids]
            v = cat.unit[rows] @ res.R[k]
            px = v[:, :2] / v[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
            rec.log(
                STARS,
                rr.Points2D(
                    px.astype(np.float32), colors=[[60, 220, 90]], radii=rr.Radius.ui_points(4.0)
                ),
            )


def _db_scales(cam: Any) -> tuple[float, float]:
    hfov = math.degrees(2 * math.atan(cam.width / (2 * cam.fx)))
    vfov = math.degrees(2 * math.atan(cam.height / (2 * cam.fy)))
    dfov = math.degrees(2 * math.atan(math.hypot(cam.width, cam.height) / (2 * cam.fx)))
    return round(min(hfov, vfov), 3), round(dfov, 3)


def _plot_errors(df: pd.DataFrame, path: Path, estimator: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for ax, c, label in zip(
        axes,
        ("x", "y", "roll"),
        ("cross-boresight x", "cross-boresight y", "roll (about boresight)"),
        strict=True,
    ):
        ax.plot(df["t_s"], df[f"err_{c}_arcsec"], lw=0.8, label=f"error ({estimator})")
        s = df[f"sigma_{c}_arcsec"]
        ax.fill_between(df["t_s"], -3 * s, 3 * s, color="0.85", label="±3 sigma")
        ax.set_ylabel(f"{label} [arcsec]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("attitude error vs truth (inertial_from_camera)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _cmd_render(args: argparse.Namespace) -> None:
    from satpose.datasets.star_scenarios import render_star_sequence, star_preset

    s = star_preset(args.preset)
    kw: dict[str, Any] = {}
    if args.duration is not None:
        kw["duration_s"] = args.duration
    if args.slew_rate is not None:
        kw["slew_rate_deg_s"] = args.slew_rate
    if args.seed is not None:
        kw["seed"] = args.seed
    render_star_sequence(replace(s, **kw), args.out, overwrite=args.overwrite)
    print(f"wrote {args.out}")


def _cmd_track(args: argparse.Namespace) -> None:
    out: Path = args.out
    with staged_output(out, args.overwrite, error=StarsRunError) as tmp:
        res = track_sequence(args.sequence, args.pipeline, args.estimator)
        meta = {
            "sequence": str(args.sequence),
            "pipeline": args.pipeline,
            "estimator": args.estimator,
            "frontend": to_plain(res.config or StarTrackerConfig()),
            "measured": res.measured,
        }
        _write_outputs(res, tmp, args.sequence, meta)
        if args.rerun:
            write_recording(res, args.sequence, tmp / "stars.rrd")
    print(f"{coverage_line(res)}; wrote {out}")
    if res.bad_frames.count:
        print(res.bad_frames.summary(len(res.t_s)))


def register(subparsers: Any) -> None:
    """Add ``satpose stars`` to the CLI (tools/cli.py EXTRA_COMMANDS)."""
    from satpose.datasets.star_scenarios import PRESETS

    p = subparsers.add_parser(
        "stars",
        help="event-camera star tracker: simulate (render) and estimate attitude (track)",
        description="Event camera as a star tracker (seed 004; docs/stars.md).",
    )
    sub = p.add_subparsers(dest="stars_command", required=True, metavar="ACTION")
    r = sub.add_parser("render", help="simulate a star-tracker run into an event sequence")
    r.add_argument(
        "preset", choices=sorted(PRESETS), metavar="PRESET", help=", ".join(sorted(PRESETS))
    )
    r.add_argument("--out", type=Path, required=True, metavar="DIR")
    r.add_argument("--duration", type=float, help="seconds (default: the preset's)")
    r.add_argument("--slew-rate", type=float, help="slew rate [deg/s]")
    r.add_argument("--seed", type=int)
    r.add_argument("--overwrite", action="store_true")
    r.set_defaults(handler=_cmd_render)
    t = sub.add_parser("track", help="estimate inertial_from_camera from an event sequence")
    t.add_argument("sequence", type=Path, metavar="DIR")
    t.add_argument("--out", type=Path, required=True, metavar="OUT")
    t.add_argument("--pipeline", choices=["events", "frames"], default="events")
    t.add_argument("--estimator", choices=["offline", "online", "frontend"], default="offline")
    t.add_argument("--rerun", action="store_true", help="also write OUT/stars.rrd (Rerun)")
    t.add_argument("--overwrite", action="store_true")
    t.set_defaults(handler=_cmd_track)
    from satpose.tools.stars_solve import register_solve

    register_solve(sub)


__all__ = ["TrackResult", "attitude_errors_arcsec", "register", "track_sequence"]
