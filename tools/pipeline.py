"""`satpose run`: frontend + backend over a sequence, result files and the Rerun recording.

Outputs in the run folder. The folder is built next to its final place and renamed into
place when complete, so a failed or interrupted run leaves nothing (and an existing run folder,
replaced only with ``overwrite``, stays as it was):

- ``trajectory.csv``: the chosen estimator's trajectory (online and kalman: each frame's
  estimate right after that frame, i.e. causal; offline: smoothed), see `TRAJECTORY_COLUMNS`.
- ``trajectory.tum``: the same poses (``left_cam_from_target``) in TUM format.
- ``trajectory_smoothed.csv/.tum`` (online only): iSAM2's smoothed estimate at the end.
- ``estimate.npz``: the same estimate with full 6x6 covariances (``eval`` uses them for NEES).
- ``frontend_pose.tum``: the per-frame (unsmoothed) poses of the frontend.
- ``measurements.parquet``: the frontend's measurements (tools.files).
- ``timings.csv``: per frame and stage [ms]: ``frontend_<stage>``, ``frontend_total``, each
  estimator's ``add()`` (``backend_<name>``) and its own stages (``backend_<name>_<stage>``,
  e.g. ``backend_online_update``: iSAM2's update), ``recording`` (logging the frame to
  run.rrd). Wall clock (``..._cpu``: the process's CPU
  time): with run.rrd the only output that varies run to run.
- ``config.yaml``: the resolved configuration; ``run.yaml``: provenance (sequence, estimator).
- ``run.rrd``: the Rerun recording (tools.recording).

No exception inside a frame ends a run: a stage that raises (frontend, an estimator's
``add()``, the recording) becomes that frame's failure note ``"<stage>: internal error:
<type>: <message>"`` and the estimators predict through the frame. Bad frames (unusable
images, internal errors) are named on the console as they happen and counted by reason in
`RunResult.bad_frames` and run.yaml (tools.badframes).
"""

from __future__ import annotations

import logging
import sys
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import yaml

from satpose.backend import BackendConfig, BackendError, Estimate, StepReport, make_estimator
from satpose.datasets.config import to_plain, yaml_problem
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration, Frame, GroundTruth, load_sequence
from satpose.frontend.measurements import FrameMeasurements, exception_failure
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend, read_stereo
from satpose.tools.badframes import BadFrames, guarded
from satpose.tools.files import atomic_write, staged_output, write_measurements, write_tum
from satpose.tools.recording import RecordingConfig, RunRecorder

log = logging.getLogger(__name__)

EstimatorName = Literal["online", "offline", "kalman"]

TRAJECTORY_COLUMNS = [
    "frame",
    "t_s",
    "tx",
    "ty",
    "tz",
    "qx",
    "qy",
    "qz",
    "qw",
    "wx",
    "wy",
    "wz",
    "vx",
    "vy",
    "vz",
    "sigma_rx",
    "sigma_ry",
    "sigma_rz",
    "sigma_tx",
    "sigma_ty",
    "sigma_tz",
    "sigma_wx",
    "sigma_wy",
    "sigma_wz",
    "sigma_vx",
    "sigma_vy",
    "sigma_vz",
]
"""trajectory.csv: pose ``left_cam_from_target`` (t [m], quaternion xyzw); ``w`` the angular
velocity in the target frame [rad/s] and ``v`` the target-origin velocity in the left camera
frame [m/s] (groundtruth.csv's conventions); 1-sigma of the rotation about the target axes
[rad], of the position along the camera axes [m], of ``w`` (target axes) and ``v`` (camera
axes)."""


class RunError(SatposeError):
    """A run cannot be made with these inputs."""


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Everything `satpose run` does (YAML/TOML with ``--config``; unknown keys refused).

    Attributes:
        frontend: the stereo frontend.
        backend: the estimators.
        recording: what run.rrd holds.
        compare: also run the other estimators on the same measurements, for the recording
            and the report (cheap next to the frontend).
    """

    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    compare: bool = True


@dataclass(frozen=True)
class RunResult:
    """What a run produced (also on disk); ``bad_frames``: the frames named as bad."""

    out: Path
    estimator: str
    estimate: Estimate
    measurements: list[FrameMeasurements]
    others: dict[str, Estimate]
    bad_frames: BadFrames = field(default_factory=BadFrames)


def _version() -> str:
    try:
        return metadata.version("satpose")
    except metadata.PackageNotFoundError:
        return "unknown"


def estimate_frame(est: Estimate) -> pd.DataFrame:
    """trajectory.csv's table of an estimate (see `TRAJECTORY_COLUMNS`)."""
    n = len(est)
    R = np.stack([T.R for T in est.left_cam_from_target]) if n else np.zeros((0, 3, 3))
    t = np.array([T.t for T in est.left_cam_from_target]).reshape(n, 3)
    q = np.array([T.quat_xyzw for T in est.left_cam_from_target]).reshape(n, 4)
    w = est.angular_velocity
    v = est.origin_velocity_cam()
    C = est.pose_covariance
    Ct_cam = np.einsum("nij,njk,nlk->nil", R, C[:, 3:, 3:], R)
    Cv_cam = np.einsum("nij,njk,nlk->nil", R, est.twist_covariance[:, 3:, 3:], R)
    sig = lambda M: np.sqrt(np.clip(np.diagonal(M, axis1=1, axis2=2), 0, None))  # noqa: E731
    data = np.column_stack(
        [
            est.frame,
            est.t_s,
            t,
            q,
            w,
            v,
            sig(C[:, :3, :3]),
            sig(Ct_cam),
            sig(est.twist_covariance[:, :3, :3]),
            sig(Cv_cam),
        ]
    )
    df = pd.DataFrame(data, columns=TRAJECTORY_COLUMNS)
    return df.astype({"frame": "int64"})


def write_estimate(est: Estimate, out: Path, stem: str) -> None:
    """``<stem>.csv``, ``<stem>.tum`` and (for ``trajectory``) ``estimate.npz``."""
    df = estimate_frame(est)
    atomic_write(out / f"{stem}.csv", lambda tmp: df.to_csv(tmp, index=False, float_format="%.10g"))
    write_tum(est.t_s, est.left_cam_from_target, out / f"{stem}.tum")


def write_estimate_npz(est: Estimate, path: Path) -> None:
    """All arrays of an estimate, covariances included (numpy ``.npz``, byte-identical for
    identical estimates: the archive's member times are fixed, unlike `numpy.savez`'s)."""
    arrays = {
        "frame": est.frame,
        "t_s": est.t_s,
        "rotation": np.stack([T.R for T in est.left_cam_from_target]),
        "translation": np.array([T.t for T in est.left_cam_from_target]),
        "twist": est.twist,
        "pose_covariance": est.pose_covariance,
        "twist_covariance": est.twist_covariance,
    }

    def write(tmp: Path) -> None:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with zf.open(info, "w") as fh:
                    np.lib.format.write_array(fh, np.asarray(value), allow_pickle=False)

    atomic_write(path, write)


def read_estimate_npz(path: Path) -> Estimate:
    """Read back `write_estimate_npz`."""
    if not path.is_file():
        raise RunError(f"{path}: estimate file is missing (run `satpose run` first)")
    try:
        z = np.load(path)
        poses = tuple(
            Rigid3(R=R, t=t) for R, t in zip(z["rotation"], z["translation"], strict=True)
        )
        return Estimate(
            frame=z["frame"],
            t_s=z["t_s"],
            left_cam_from_target=poses,
            twist=z["twist"],
            pose_covariance=z["pose_covariance"],
            twist_covariance=z["twist_covariance"],
        )
    except (OSError, KeyError, ValueError) as exc:
        raise RunError(f"{path}: not a readable estimate ({exc})") from None


def read_provenance(run: Path) -> dict[str, Any]:
    """The run folder's run.yaml as a mapping (empty if there is none).

    Raises:
        RunError: run.yaml is not valid YAML (naming line and column) or not a mapping.
    """
    path = Path(run) / "run.yaml"
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise RunError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RunError(f"{path}: cannot read ({exc})") from None
    if not isinstance(data, dict):
        raise RunError(f"{path}: must hold a YAML mapping at the top level")
    return data


def run_pipeline(
    sequence_path: Path,
    estimator: EstimatorName,
    out: Path,
    config: PipelineConfig | None = None,
    *,
    overwrite: bool = False,
    spawn: bool = False,
    connect: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RunResult:
    """Run frontend and backend over a sequence and write the run folder (see module doc).

    Args:
        overwrite: replace an existing run folder (one holding run.yaml) once the new one is
            complete; other non-empty folders are always refused.
        spawn, connect: also stream the recording to a Rerun viewer (`RunRecorder`).
        progress: called with ``(frames done, frames total)`` after each frame.
    """
    cfg = config or PipelineConfig()
    check_estimator(estimator)
    seq = load_sequence(sequence_path)
    if seq.kind != "stereo":
        raise RunError(
            f"{sequence_path}: the stereo pipeline needs a stereo sequence (this one is {seq.kind})"
        )
    out = Path(out)
    with staged_output(out, overwrite, marker="run.yaml", what="a run", error=RunError) as stage:
        recorder = RunRecorder(
            stage / "run.rrd", seq.calibration, seq.target, cfg.recording, spawn, connect
        )
        step = FrameStep(
            seq.calibration,
            estimator,
            cfg,
            recorder,
            rate_hz=seq.rate_hz,
            truth=seq.truth,
            root=seq.root,
        )
        try:
            for k, frame in enumerate(seq):
                step(
                    frame.index,
                    frame.t_s,
                    partial(_stereo_images, frame),
                    (frame.left_path, frame.right_path),
                )
                if progress is not None:
                    progress(k + 1, len(seq))
            finals = step.finish(Path(sequence_path), len(seq))
        finally:
            recorder.close()
        result = write_run(
            stage, step, finals, provenance(Path(sequence_path), estimator, len(seq), step)
        )
    return replace(result, out=out)


def check_estimator(estimator: str) -> None:
    """Refuse an unknown estimator name (`RunError`)."""
    if estimator not in ("online", "offline", "kalman"):
        raise RunError(f"unknown estimator {estimator!r}; choose online, offline or kalman")


def _stereo_images(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    return frame.left(), frame.right()


@dataclass(frozen=True)
class Finals:
    """The estimators' results at the end of a run (`FrameStep.finish`).

    Attributes:
        estimates: every estimator's final ``estimate()`` (smoothed for online and offline),
            by name; an estimator other than the chosen one that failed is left out.
        main: the chosen estimator's final estimate.
        causal: the chosen estimator's causal estimate (each frame's right after that frame:
            ``filtered()`` for online and kalman; offline: ``main``).
    """

    estimates: dict[str, Estimate]
    main: Estimate
    causal: Estimate


class FrameStep:
    """One stereo frame through the frontend, every estimator's ``add()`` and the recording:
    the per-frame work that `run_pipeline` (every frame of a finished sequence) and
    ``satpose track --live`` (`satpose.tools.live`, the frames it does not drop) share.

    Each call appends the frame's measurements to `results` and its timings row to
    `timing_rows`, and notes a bad frame in `bad`; `finish` gets the final estimates.

    Args:
        calibration: the stereo calibration.
        estimator: the chosen estimator (with ``config.compare`` all three run).
        config: the pipeline config.
        recorder: the Rerun recording (`RunRecorder`).
        rate_hz: the sequence's nominal frame rate (spin rates per frame in the recording).
        truth: ground truth for the recording, if the sequence has it (never estimated from).
        root: the sequence folder (bad frames' files are named relative to it).
        compare_at_end: run the comparison estimators (``config.compare``) once in `finish`,
            on the measurements of every frame in order, instead of per frame (``satpose
            track --live``: a frame's step is then the frontend and the chosen estimator
            only). Their final estimates are the same either way (each sees the same
            measurements in the same order); the recording then has their trajectories at
            the end only (`RunRecorder.log_final`), not frame by frame.
    """

    def __init__(
        self,
        calibration: Calibration,
        estimator: EstimatorName,
        config: PipelineConfig,
        recorder: RunRecorder,
        *,
        rate_hz: float,
        truth: GroundTruth | None = None,
        root: Path | None = None,
        compare_at_end: bool = False,
    ) -> None:
        self.estimator = estimator
        self.config = config
        self.recorder = recorder
        self.rate_hz = rate_hz
        self.truth = truth
        names = ["online", "offline", "kalman"] if config.compare else [estimator]
        self._steps: dict[str, float] = {}  # the estimators' own stage times of the frame
        self.estimators = {
            name: make_estimator(name, calibration, config.backend, hook=self._hook)
            for name in names
        }
        self.deferred = [n for n in names if n != estimator] if compare_at_end else []
        """The estimators fed in `finish` (``compare_at_end``), not per frame."""
        self._inputs: list[FrameMeasurements] = []  # what the estimators were given, in order
        self.finish_notes: list[str] = []
        """What `finish` noted about the final estimates (run.yaml ``estimator_notes``)."""
        self.deferred_ms: dict[str, float] = {}
        """The deferred estimators' ``add()`` of every frame in `finish` [ms] (optimisation
        happens in their ``estimate()``)."""
        self.frontend = StereoFrontend(calibration, config.frontend)
        self.results: list[FrameMeasurements] = []
        self.timing_rows: list[dict[str, Any]] = []
        self.bad = BadFrames(root)

    def _hook(self, report: StepReport) -> None:
        if report.step == "add":
            for stage, ms in report.timings_ms.items():
                self._steps[f"backend_{report.estimator}_{stage}"] = ms

    def __call__(
        self,
        index: int,
        t_s: float,
        read: Callable[[], tuple[np.ndarray, np.ndarray]],
        files: tuple[Path | None, ...] = (),
    ) -> FrameMeasurements:
        """Process one frame.

        Args:
            index, t_s: the frame's index and time [s] (increasing from call to call).
            read: returns the raw ``(left, right)`` images; a `SatposeError` (or any
                exception) makes the frame bad, not the run.
            files: the frame's image files, named in a bad-frame warning.

        Returns:
            the frame's measurements, with any stage's failure notes.
        """
        t0 = time.perf_counter()
        images, failed = read_stereo(index, t_s, read)
        if images is None:
            assert failed is not None
            m = failed
        else:
            m, why = guarded("frontend", index, partial(self.frontend.process, index, t_s, *images))
            if m is None:
                m = FrameMeasurements(frame=index, t_s=t_s, failures=(str(why),))
        t1 = time.perf_counter()
        row: dict[str, Any] = {
            "frame": index,
            "t_s": t_s,
            **{f"frontend_{s}": v for s, v in m.timings_ms.items()},
            "frontend_total": (t1 - t0) * 1000.0,
        }
        self._steps.clear()
        notes: list[str] = []
        self._inputs.append(m)
        for name, est in self.estimators.items():
            if name in self.deferred:
                continue
            t2 = time.perf_counter()
            _, why = guarded(f"backend_{name}", index, partial(est.add, m))
            notes += [why] if why else []
            row[f"backend_{name}"] = (time.perf_counter() - t2) * 1000.0
        row.update(self._steps)
        self.timing_rows.append(row)
        shown = {"left": images[0], "right": images[1]} if images is not None else {}
        t3 = time.perf_counter()
        _, why = guarded("recording", index, partial(self._record, index, m, shown, row))
        row["recording"] = (time.perf_counter() - t3) * 1000.0
        notes += [why] if why else []
        if notes:
            m = replace(m, failures=(*m.failures, *notes))
        self.results.append(m)
        self.bad.note(index, m.failures, files)
        return m

    def causal(self) -> Estimate | None:
        """The chosen estimator's causal estimate so far (None before it has one, or after
        its ``add()`` failed: that frame's failure note says why, and `finish` ends the run
        with an error if it cannot recover; offline has none until `finish`)."""
        if self.estimator == "offline":
            return None
        try:
            return self.estimators[self.estimator].filtered()
        except BackendError:
            return None
        except Exception:  # e.g. iSAM2 threw in an update: the frame's note has it
            log.debug("%s estimator: filtered() raised", self.estimator, exc_info=True)
            return None

    def finish(self, sequence_path: Path, total: int) -> Finals:
        """Every estimator's final estimate, the smoothed trajectories logged to the recording.

        Args:
            sequence_path: named in the error.
            total: the number of frames of the sequence (in the bad-frame summary).

        Raises:
            RunError: the chosen estimator has no estimate (e.g. the ring was never found).
        """
        finals = {}
        self._feed_deferred()
        for name, est in self.estimators.items():
            try:
                finals[name] = est.estimate()
                note = getattr(est, "final_note", None)
                if note:
                    log.warning("%s estimator: %s", name, note)
                    self.finish_notes.append(f"{name}: {note}")
            except Exception as exc:
                text = str(exc) if isinstance(exc, BackendError) else exception_failure(name, exc)
                if not isinstance(exc, BackendError):
                    log.debug("%s estimator: estimate() raised", name, exc_info=True)
                if name == self.estimator:
                    why = f" ({self.bad.summary(total)})" if self.bad.count else ""
                    raise RunError(f"{sequence_path}: no estimate: {text}{why}") from None
                log.warning("%s estimator: %s", name, text)
        main = finals[self.estimator]
        causal = main
        if self.estimator != "offline":
            est = self.estimators[self.estimator]
            causal, why = guarded(f"backend_{self.estimator}", -1, est.filtered)
            if causal is None:
                raise RunError(f"{sequence_path}: no filtered estimate: {why}")
        logged = [("offline", "smoothed"), ("online", "isam2_smoothed")]
        if "kalman" in self.deferred and "kalman" in finals:  # its causal track, at the end
            logged.append(("kalman", "kalman"))
        for name, label in logged:
            if name in finals:
                e = finals[name]
                if label == "kalman":
                    e = self.estimators["kalman"].filtered()
                _, why = guarded(
                    "recording",
                    -1,
                    partial(
                        self.recorder.log_final,
                        label,
                        list(e.frame),
                        list(e.left_cam_from_target),
                        [_truth_pose(self.truth, int(i)) for i in e.frame],
                        list(e.spin_rate_deg_per_frame(1.0 / self.rate_hz)),
                        list(e.t_s),
                    ),
                )
                if why:
                    log.warning("run.rrd: the %s trajectory is missing: %s", label, why)
        return Finals(estimates=finals, main=main, causal=causal)

    def _feed_deferred(self) -> None:
        """Give the deferred estimators every frame's measurements, in order (as `__call__`
        gives them to the others: an exception in ``add()`` is that frame's failure note),
        once; their time [ms] in `deferred_ms`."""
        for name in self.deferred:
            if name in self.deferred_ms:
                continue
            est = self.estimators[name]
            t0 = time.perf_counter()
            for k, m in enumerate(self._inputs):
                _, why = guarded(f"backend_{name}", m.frame, partial(est.add, m))
                if why:
                    self.results[k] = replace(
                        self.results[k], failures=(*self.results[k].failures, why)
                    )
                    if m.frame not in self.bad.frames:  # counted once, as in `__call__`
                        self.bad.note(m.frame, (why,), ())
            self.deferred_ms[name] = 1e3 * (time.perf_counter() - t0)

    def _record(
        self,
        index: int,
        m: FrameMeasurements,
        images: dict[str, np.ndarray],
        timings: dict[str, Any],
    ) -> None:
        """Log one frame: images, detections, the causal estimates so far."""
        poses: dict[str, Rigid3 | None] = {
            "per_frame": m.pose.left_cam_from_target if m.pose is not None else None
        }
        cov = None
        spin: dict[str, float] = {}
        for name, key in (("kalman", "kalman"), ("online", "isam2")):
            est = self.estimators.get(name)
            if est is None or name in self.deferred:
                continue
            try:
                f = est.filtered()
            except BackendError:
                continue
            if len(f) and int(f.frame[-1]) == index:
                poses[key] = f.left_cam_from_target[-1]
                spin[key] = float(f.spin_rate_deg_per_frame(1.0 / self.rate_hz)[-1])
                if name == "online":
                    cov = f.pose_covariance[-1]
        truth = _truth_pose(self.truth, index)
        if truth is not None and self.truth is not None and self.truth.angular_velocity is not None:
            row = self.truth.row_of_frame(index)
            spin["truth"] = float(
                np.degrees(np.linalg.norm(self.truth.angular_velocity[row])) / self.rate_hz
            )
        stage_ms = {
            k2.removeprefix("frontend_"): v
            for k2, v in timings.items()
            if k2.startswith(("frontend_", "backend_")) and k2 != "frontend_total"
        }
        shown = images if self.recorder.config.images else {}
        self.recorder.log_frame(index, shown, m, poses, cov, truth, spin, stage_ms)


def provenance(sequence_path: Path, estimator: str, frames: int, step: FrameStep) -> dict[str, Any]:
    """run.yaml's content (a run's provenance and counts)."""
    return {
        "satpose": _version(),
        "sequence": str(sequence_path.resolve()),
        "estimator": estimator,
        "frames": frames,
        "frames_with_pose": sum(m.pose is not None for m in step.results),
        "bad_frames": step.bad.count,
        "bad_frames_by_reason": step.bad.as_dict(),
        **({"estimator_notes": list(step.finish_notes)} if step.finish_notes else {}),
        "command": " ".join(sys.argv),
    }


def timings_frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """timings.csv's table of `FrameStep.timing_rows`."""
    tdf = pd.DataFrame(rows)
    # a frontend stage that did not run took 0 ms; an estimator stage that did not happen
    # (e.g. iSAM2's update during its warm-up) stays empty
    front = [c for c in tdf.columns if c.startswith("frontend_")]
    tdf[front] = tdf[front].fillna(0.0)
    return tdf


def write_run(
    out: Path,
    step: FrameStep,
    finals: Finals,
    prov: dict[str, Any],
    timings: pd.DataFrame | None = None,
) -> RunResult:
    """Write a run folder's files (all but run.rrd) from a finished `FrameStep`, each
    atomically, run.yaml (``prov``) last.

    Args:
        timings: timings.csv's table (default: `timings_frame` of the step's rows).
    """
    estimator = step.estimator
    write_estimate(finals.causal, out, "trajectory")
    write_estimate_npz(finals.causal, out / "estimate.npz")
    if estimator == "online":
        write_estimate(finals.main, out, "trajectory_smoothed")
        write_estimate_npz(finals.main, out / "estimate_smoothed.npz")
    for name, e in finals.estimates.items():
        if name != estimator:
            write_estimate_npz(e, out / f"estimate_{name}.npz")
    results = step.results
    with_pose = [m for m in results if m.pose is not None]
    write_tum(
        [m.t_s for m in with_pose],
        [m.pose.left_cam_from_target for m in with_pose],
        out / "frontend_pose.tum",
    )
    write_measurements(results, out / "measurements.parquet", timings=False)
    tdf = timings_frame(step.timing_rows) if timings is None else timings
    atomic_write(out / "timings.csv", lambda tmp: tdf.to_csv(tmp, index=False, float_format="%.3f"))
    text = yaml.safe_dump(to_plain(step.config), sort_keys=False)
    atomic_write(out / "config.yaml", lambda tmp: Path(tmp).write_text(text))
    atomic_write(
        out / "run.yaml", lambda tmp: Path(tmp).write_text(yaml.safe_dump(prov, sort_keys=False))
    )
    others = {n: e for n, e in finals.estimates.items() if n != estimator}
    return RunResult(
        out=out,
        estimator=estimator,
        estimate=finals.causal,
        measurements=results,
        others=others,
        bad_frames=step.bad,
    )


def _truth_pose(truth: GroundTruth | None, frame_index: int) -> Rigid3 | None:
    if truth is None:
        return None
    try:
        return truth.pose(truth.row_of_frame(frame_index))
    except KeyError:
        return None
