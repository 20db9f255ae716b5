"""``satpose track``: the online estimator on frames as they arrive, and ``record-replay``.

``satpose track SEQ --live --out RUN`` watches a sequence folder that a recorder is still
writing (`satpose.datasets.live.FolderSource`: when a frame counts as complete is defined
there) and runs each frame it takes through the same per-frame step as ``satpose run``
(`satpose.tools.pipeline.FrameStep`: frontend, iSAM2, the recording; the comparison
estimators run once at the end, ``compare_at_end``). It never falls behind: after each
frame it takes the newest complete frame and drops the older ones that arrived meanwhile
(counted and named). Without ``--live`` it is
``satpose run --estimator online`` on a finished folder.

The run folder is written while tracking (docs/live.md):

- ``run.yaml`` first, with ``state: running``; at the end replaced by the complete
  provenance with ``state: complete`` and the live summary (``live:``).
- ``trajectory.csv``: one row per frame as soon as iSAM2 has its estimate (appended and
  flushed, so a crash leaves a readable prefix); rewritten atomically at the end with the
  same rows (`satpose.tools.pipeline.TRAJECTORY_COLUMNS`).
- ``live_frames.csv``: one row per frame of the recording, processed or dropped, appended as
  it happens (`LIVE_COLUMNS`).
- ``run.rrd``: streamed (and to a viewer with ``--spawn``/``--connect``).
- at the end, each atomically: every other file of a ``satpose run`` folder (the offline and
  Kalman estimates from every processed frame's measurements, fed to them then), timings.csv
  with the latency columns.

Latency of a frame: from its arrival (when it became complete on disk) to the end of its
step (pose estimated, logged to Rerun and appended to trajectory.csv).
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import shutil
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import pandas as pd
import yaml

from satpose.backend import Estimate
from satpose.datasets.errors import SatposeError
from satpose.datasets.importers import source_kind
from satpose.datasets.importers.common import DEFAULT_MAX_UNPAIRED, DEFAULT_TOLERANCE_S
from satpose.datasets.live import (
    POLL_S,
    ArrivedFrame,
    BagReplay,
    FolderSource,
    FrameSource,
    replay_sequence,
    wait_for_header,
)
from satpose.tools.argtypes import positive_factor, positive_hz, positive_int, positive_seconds
from satpose.tools.files import atomic_write, check_out, write_measurements
from satpose.tools.import_cli import add_recording_options, recording_options
from satpose.tools.pipeline import (
    TRAJECTORY_COLUMNS,
    FrameStep,
    PipelineConfig,
    RunError,
    RunResult,
    estimate_frame,
    provenance,
    timings_frame,
    write_run,
)
from satpose.tools.recording import RunRecorder, viewer_url

log = logging.getLogger(__name__)

LIVE_COLUMNS = [
    "frame",
    "t_s",
    "status",
    "reason",
    "arrival_unix_s",
    "pickup_ms",
    "wait_ms",
    "latency_ms",
    "busy",
    "cpu_ms",
]
"""live_frames.csv: ``status`` ``processed`` or ``dropped`` (``reason``: ``behind`` — a newer
frame was complete when the tracker was free; ``before start`` — already complete when
tracking started, and not the newest; ``incomplete: ...`` — its images never became whole
before a newer frame did, or before the end); ``arrival_unix_s`` when it became complete (Unix
time); ``pickup_ms`` from then until the tracker saw it; ``wait_ms`` from then until its step
started; ``latency_ms`` until its step ended (empty for dropped frames); ``busy``: 1 if it
arrived while another frame was being processed (its pickup then includes that wait);
``cpu_ms`` the CPU time of the process during its step (all threads: what the step costs
without waiting for a shared machine's cores)."""


@dataclass(frozen=True)
class LiveResult:
    """What a live run did (also in run.yaml's ``live:`` and live_frames.csv).

    Attributes:
        out: the run folder.
        run: the run's estimate and measurements (as `satpose.tools.pipeline.run_pipeline`).
        frames: one row per frame of the recording (`LIVE_COLUMNS`).
        stopped_by: why tracking stopped.
        notes: what the source reports about the recording (`FrameSource.notes`: a bag's
            topics, calibration and pairing counts).
    """

    out: Path
    run: RunResult
    frames: pd.DataFrame
    stopped_by: str
    notes: tuple[str, ...] = ()

    @property
    def processed(self) -> int:
        return int((self.frames["status"] == "processed").sum())

    @property
    def dropped(self) -> list[int]:
        return self.frames.loc[self.frames["status"] == "dropped", "frame"].astype(int).tolist()

    def summary(self) -> dict[str, Any]:
        """run.yaml's ``live:`` mapping (see `live_summary`)."""
        return live_summary(self.frames, self.stopped_by)


def _stats(values: pd.Series) -> dict[str, float | None]:
    v = values.dropna().to_numpy(dtype=float)
    if v.size == 0:
        return {"median": None, "p95": None, "max": None}
    return {
        "median": round(float(np.median(v)), 1),
        "p95": round(float(np.percentile(v, 95)), 1),
        "max": round(float(v.max()), 1),
    }


def frame_ranges(frames: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    parts: list[str] = []
    for i in sorted(frames):
        if parts and parts[-1].split("-")[-1] == str(i - 1):
            parts[-1] = f"{parts[-1].split('-')[0]}-{i}"
        else:
            parts.append(str(i))
    return ", ".join(parts)


def live_summary(frames: pd.DataFrame, stopped_by: str) -> dict[str, Any]:
    """The counts and latency statistics of live_frames.csv's table: frames seen, processed,
    dropped (by reason, and which), latency and pickup [ms] (median, p95, max; pickup over the
    frames that arrived while the tracker was idle), the step's CPU time, why it stopped."""
    done = frames[frames["status"] == "processed"]
    dropped = frames[frames["status"] == "dropped"]
    reasons = Counter(str(r).split(":")[0] for r in dropped["reason"])
    idle = done[done["busy"] == 0]
    return {
        "stopped_by": stopped_by,
        "frames_seen": len(frames),
        "processed": len(done),
        "dropped": len(dropped),
        "dropped_by_reason": dict(reasons.most_common()),
        "dropped_frames": frame_ranges(dropped["frame"].astype(int).tolist()),
        "latency_ms": _stats(done["latency_ms"]),
        "pickup_idle_ms": _stats(idle["pickup_ms"]),
        "step_cpu_ms": _stats(done["cpu_ms"]),
    }


def summary_line(summary: dict[str, Any]) -> str:
    """One line for the console: processed, dropped (by reason, which), latency."""
    lat = summary["latency_ms"]
    text = f"{summary['processed']} of {summary['frames_seen']} frames processed"
    if summary["dropped"]:
        reasons = ", ".join(f"{r} {k}" for r, k in summary["dropped_by_reason"].items())
        text += f", {summary['dropped']} dropped ({reasons}: frames {summary['dropped_frames']})"
    else:
        text += ", none dropped"
    if lat["median"] is not None:
        text += f"; latency median {lat['median']:.0f} ms, p95 {lat['p95']:.0f} ms"
    return f"{text}; stopped: {summary['stopped_by']}"


@contextmanager
def ctrl_c_stops() -> Iterator[Callable[[], bool]]:
    """Within the block, Ctrl-C (SIGINT) only sets a flag (the returned callable reads it), so
    that the frame in progress finishes and the run folder is written whole; a second Ctrl-C
    interrupts at once (KeyboardInterrupt). Outside the main thread nothing is installed."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag.is_set
        return

    def handler(signum: int, frame: Any) -> None:
        flag.set()
        signal.signal(signal.SIGINT, previous)
        log.warning("Ctrl-C: stopping after the current frame (again to abort)")

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield flag.is_set
    finally:
        signal.signal(signal.SIGINT, previous)


class _Appender:
    """A CSV file written row by row, each row flushed (a crash leaves whole lines)."""

    def __init__(self, path: Path, columns: list[str]) -> None:
        self.path = path
        self.fh: TextIO = open(path, "w", encoding="utf-8", newline="")
        self.writer = csv.writer(self.fh, lineterminator="\n")
        self.writer.writerow(columns)
        self.fh.flush()

    def frame(self, df: pd.DataFrame, float_format: str) -> None:
        df.to_csv(self.fh, header=False, index=False, float_format=float_format)
        self.fh.flush()

    def row(self, values: list[Any]) -> None:
        self.writer.writerow(values)
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()


@dataclass
class _Tracker:
    """The state of one live run (see `track_live`)."""

    step: FrameStep
    out: Path
    start_s: float
    rows: list[dict[str, Any]] = field(default_factory=list)
    written: int = 0  # trajectory rows appended so far
    busy_until: float = 0.0

    def __post_init__(self) -> None:
        self.trajectory = _Appender(self.out / "trajectory.csv", TRAJECTORY_COLUMNS)
        self.frames = _Appender(self.out / "live_frames.csv", LIVE_COLUMNS)

    def _log(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        self.frames.row(["" if _missing(row.get(c)) else row.get(c) for c in LIVE_COLUMNS])

    def drop(self, index: int, t_s: float, reason: str, f: ArrivedFrame | None = None) -> None:
        row: dict[str, Any] = {"frame": index, "t_s": t_s, "status": "dropped", "reason": reason}
        if f is not None:
            row.update(
                arrival_unix_s=round(f.arrival_s, 6),
                pickup_ms=1e3 * (f.seen_s - f.arrival_s),
                busy=int(f.arrival_s < self.busy_until),
            )
        self._log(row)

    def process(self, f: ArrivedFrame) -> None:
        begin, cpu = time.time(), time.process_time()
        self.step(f.index, f.t_s, f.read, f.files)
        causal = self.step.causal()
        if causal is not None and len(causal) > self.written:
            self.trajectory.frame(estimate_frame(_tail(causal, self.written)), "%.10g")
            self.written = len(causal)
        end = time.time()
        self._log(
            {
                "frame": f.index,
                "t_s": f.t_s,
                "status": "processed",
                "reason": "",
                "arrival_unix_s": round(f.arrival_s, 6),
                "pickup_ms": 1e3 * (f.seen_s - f.arrival_s),
                "wait_ms": 1e3 * (begin - f.arrival_s),
                "latency_ms": 1e3 * (end - f.arrival_s),
                "busy": int(f.arrival_s < self.busy_until),
                "cpu_ms": 1e3 * (time.process_time() - cpu),
            }
        )
        self.busy_until = end

    def close(self) -> None:
        self.trajectory.close()
        self.frames.close()

    def table(self) -> pd.DataFrame:
        df = pd.DataFrame(self.rows, columns=LIVE_COLUMNS)
        return df.sort_values("frame", kind="stable").reset_index(drop=True)


def _missing(v: Any) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v))


def _tail(est: Estimate, start: int) -> Estimate:
    """The rows ``start:`` of an estimate."""
    return Estimate(
        frame=est.frame[start:],
        t_s=est.t_s[start:],
        left_cam_from_target=est.left_cam_from_target[start:],
        twist=est.twist[start:],
        pose_covariance=est.pose_covariance[start:],
        twist_covariance=est.twist_covariance[start:],
    )


def track_live(
    source: FrameSource,
    out: Path,
    config: PipelineConfig | None = None,
    *,
    overwrite: bool = False,
    spawn: bool = False,
    connect: str | None = None,
    until_idle_s: float | None = None,
    poll_s: float = POLL_S,
    stop: Callable[[], bool] | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> LiveResult:
    """Track the frames of ``source`` as they arrive with the online estimator (iSAM2) and
    write the run folder ``out`` as it goes (module doc).

    The loop: poll the source; if frames arrived, process the newest and drop the others;
    otherwise stop if the recording ended, nothing arrived for ``until_idle_s`` or ``stop()``
    says so, else sleep ``poll_s``.

    Args:
        source: the frames (`satpose.datasets.live.FolderSource`, or another `FrameSource`).
        out: the run folder; an existing run folder is replaced (when tracking starts) only
            with ``overwrite``.
        config: the pipeline config (as ``satpose run``'s).
        spawn, connect: also stream to a Rerun viewer (run.rrd is always written).
        until_idle_s: stop when no frame arrived for this long [s] (None: never).
        poll_s: the idle polling period [s].
        stop: returns True to stop (Ctrl-C; `ctrl_c_stops`), checked between frames.
        progress: called after each processed frame with the counts so far (``processed``,
            ``dropped``, ``latency_ms`` of the frame).

    Returns:
        the run and the live statistics.

    Raises:
        RunError: ``out`` may not be written, or tracking stopped before the estimator had an
            estimate (the run folder then holds the measurements, timings and
            live_frames.csv, and run.yaml says why).
    """
    cfg = config or PipelineConfig()
    head = source.header
    if head.kind != "stereo":
        raise RunError(f"{head.root}: live tracking needs a stereo sequence (this is {head.kind})")
    out = Path(out)
    check_out(out, overwrite, marker="run.yaml", what="a run", error=RunError)
    if out.exists() and any(out.iterdir()):
        shutil.rmtree(out)  # ours (check_out saw its run.yaml), and --overwrite was given
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunError(f"{out}: cannot create the run folder ({exc.strerror or exc})") from None
    prov = provenance_live(head.root, state="running")
    atomic_write(out / "run.yaml", lambda tmp: Path(tmp).write_text(yaml.safe_dump(prov)))
    recorder = RunRecorder(
        out / "run.rrd", head.calibration, None, cfg.recording, spawn=spawn, connect=connect
    )
    # a step is what an online user needs per frame: the frontend, iSAM2, the trajectory row
    # and the recording; the comparison estimators (config.compare) run once at the end
    step = FrameStep(
        head.calibration,
        "online",
        cfg,
        recorder,
        rate_hz=head.rate_hz,
        root=head.root,
        compare_at_end=True,
    )
    start = time.time()
    tracker = _Tracker(step=step, out=out, start_s=start)
    last_seen = time.monotonic()
    stopped_by = ""
    try:
        while True:
            if stop is not None and stop():
                stopped_by = "Ctrl-C"
                break
            frames, skipped = source.poll()
            for s in skipped:
                tracker.drop(s.index, s.t_s, s.reason)
            if frames:
                last_seen = time.monotonic()
                newest = frames[-1]
                for f in frames[:-1]:
                    reason = "before start" if f.arrival_s <= start else "behind"
                    tracker.drop(f.index, f.t_s, reason, f)
                tracker.process(newest)
                if progress is not None:
                    progress(
                        {
                            "processed": sum(r["status"] == "processed" for r in tracker.rows),
                            "dropped": sum(r["status"] == "dropped" for r in tracker.rows),
                            "latency_ms": tracker.rows[-1]["latency_ms"],
                        }
                    )
                continue
            if source.ended():
                stopped_by = "the recording ended"
                break
            if until_idle_s is not None and time.monotonic() - last_seen >= until_idle_s:
                stopped_by = f"no new frame for {until_idle_s:g} s"
                break
            time.sleep(poll_s)
        for s in source.incomplete():
            tracker.drop(s.index, s.t_s, f"{s.reason} at the stop")
        tracker.close()
        table = tracker.table()
        summary = live_summary(table, stopped_by)
        notes = source.notes()
        if notes:
            summary["notes"] = notes
        try:
            t_end = time.perf_counter()
            finals = step.finish(head.root, len(table))
            summary["end_of_run_ms"] = round(1e3 * (time.perf_counter() - t_end), 1)
            if step.deferred:
                summary["compared_at_end"] = list(step.deferred)
        except RunError as exc:
            _write_partial(out, step, table, head.root, summary, str(exc))
            raise
    except SatposeError as exc:  # e.g. frames.csv's header is wrong: say so in run.yaml
        if not isinstance(exc, RunError):
            prov = provenance_live(head.root, state=f"failed: {exc}")
            atomic_write(out / "run.yaml", lambda tmp: Path(tmp).write_text(yaml.safe_dump(prov)))
        raise
    finally:
        tracker.close()
        recorder.close()
    atomic_write(out / "live_frames.csv", lambda tmp: table.to_csv(tmp, index=False))
    prov = {
        **provenance(head.root, "online", len(table), step),
        "mode": "live",
        "state": "complete",
        "live": summary,
    }
    run = write_run(out, step, finals, prov, timings=_timings(step, table))
    return LiveResult(out=out, run=run, frames=table, stopped_by=stopped_by, notes=tuple(notes))


def provenance_live(root: Path, state: str) -> dict[str, Any]:
    """run.yaml while a live run is in progress."""
    return {
        "sequence": str(Path(root).resolve()),
        "estimator": "online",
        "mode": "live",
        "state": state,
        "command": " ".join(sys.argv),
    }


def _timings(step: FrameStep, table: pd.DataFrame) -> pd.DataFrame:
    """timings.csv: the step's rows with the live columns of the processed frames."""
    tdf = timings_frame(step.timing_rows)
    live = table[table["status"] == "processed"][
        ["frame", "arrival_unix_s", "pickup_ms", "wait_ms", "latency_ms", "cpu_ms"]
    ].rename(columns={"cpu_ms": "step_cpu_ms"})
    return tdf.merge(live, on="frame", how="left")


def _write_partial(
    out: Path,
    step: FrameStep,
    table: pd.DataFrame,
    root: Path,
    summary: dict[str, Any],
    why: str,
) -> None:
    """The run folder of a live run that ended without an estimate: what there is, and
    run.yaml saying so."""
    atomic_write(out / "live_frames.csv", lambda tmp: table.to_csv(tmp, index=False))
    if step.results:
        write_measurements(step.results, out / "measurements.parquet", timings=False)
        tdf = _timings(step, table)
        atomic_write(
            out / "timings.csv", lambda tmp: tdf.to_csv(tmp, index=False, float_format="%.3f")
        )
    prov = {**provenance_live(root, state=why), "live": summary}
    atomic_write(
        out / "run.yaml", lambda tmp: Path(tmp).write_text(yaml.safe_dump(prov, sort_keys=False))
    )


def track_folder(
    sequence: Path,
    out: Path,
    config: PipelineConfig | None = None,
    *,
    until_idle_s: float | None = None,
    overwrite: bool = False,
    spawn: bool = False,
    connect: str | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> LiveResult:
    """`track_live` on a folder a recorder is writing: waits for its sequence.yaml and
    calib.yaml (up to ``until_idle_s``), then tracks until the recorder's end marker, the idle
    timeout or Ctrl-C (`ctrl_c_stops`)."""
    with ctrl_c_stops() as stopped:
        head = wait_for_header(sequence, until_idle_s, stop=stopped)
        if head is None:
            raise RunError(f"{sequence}: stopped before the recording started")
        source = FolderSource(sequence, head)
        return track_live(
            source,
            out,
            config,
            overwrite=overwrite,
            spawn=spawn,
            connect=connect,
            until_idle_s=until_idle_s,
            stop=stopped,
            progress=progress,
        )


def track_bag(
    source: BagReplay,
    out: Path,
    config: PipelineConfig | None = None,
    *,
    until_idle_s: float | None = None,
    overwrite: bool = False,
    spawn: bool = False,
    connect: str | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> LiveResult:
    """`track_live` on a ROS bag replayed at its recorded rate
    (`satpose.datasets.live.BagReplay`, opened with the topics, calibration, pairing options
    and replay speed: ``BagReplay(bag, ImportOptions(...), rate=2.0)``) until the bag's end,
    the idle timeout or Ctrl-C (`ctrl_c_stops`). Closes the bag.

    Raises:
        RecordingError: the bag turned out unreadable (one line naming the file and field).
        RunError: as `track_live`.
    """
    with ctrl_c_stops() as stopped:
        try:
            return track_live(
                source,
                out,
                config,
                overwrite=overwrite,
                spawn=spawn,
                connect=connect,
                until_idle_s=until_idle_s,
                stop=stopped,
                progress=progress,
            )
        finally:
            source.close()


def is_bag(path: Path) -> bool:
    """``path`` names a ROS bag (``.bag``, ``.db3``, ``.mcap``, a folder with metadata.yaml),
    whether or not it exists; anything else is taken for a sequence folder."""
    if path.suffix.lower() in (".bag", ".db3", ".mcap"):
        return True
    return path.is_dir() and source_kind(path) == "rosbag2"


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def register(subparsers: Any) -> None:
    """Add ``track`` and ``record-replay`` to the ``satpose`` command line."""
    p = subparsers.add_parser(
        "track",
        help="online estimate of a recording as it is written or replayed (--live), or of a "
        "finished one",
        description="With --live: process the frames of a sequence folder as a recorder "
        "writes them (a frame counts once its frames.csv row ends with a newline and its "
        "PNGs are whole), or of a ROS 1/ROS 2 bag replayed at its recorded rate (header "
        "stamps; topics, calibration and pairing as `satpose import` reads them), always the "
        "newest frame that arrived (older ones that arrived meanwhile are dropped and named), "
        "with the online estimator (iSAM2); write the run folder as it goes and stream to "
        "Rerun. Stops when the recorder writes recording.done or the bag ends, after "
        "--until-idle seconds without a new frame, or at Ctrl-C (the run folder is then "
        "written whole). Without --live: the same as `satpose run --estimator online` on a "
        "finished folder. See docs/live.md.",
    )
    p.add_argument(
        "sequence",
        type=Path,
        metavar="SEQUENCE|BAG",
        help="sequence folder, or a ROS bag (.bag, .db3, .mcap, ROS 2 bag folder) with --live",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="run folder")
    p.add_argument(
        "--live",
        action="store_true",
        help="track the folder while it is written, or the bag as it replays",
    )
    p.add_argument(
        "--until-idle",
        type=positive_seconds,
        metavar="SECONDS",
        help="--live: stop when no new frame arrived for this long (default: wait until the "
        "recorder's recording.done or Ctrl-C); also how long to wait for sequence.yaml and "
        "calib.yaml",
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="YAML/TOML pipeline config, as for `satpose run`",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing run folder (--live: when tracking starts)",
    )
    p.add_argument("--spawn", action="store_true", help="also stream to a new Rerun viewer")
    p.add_argument(
        "--connect",
        nargs="?",
        const="",
        metavar="ADDR",
        help="also stream to a running Rerun viewer (HOST:PORT or rerun+http:// URL; "
        "default 127.0.0.1:9876)",
    )
    g = p.add_argument_group("a bag (--live), read as `satpose import` reads it")
    g.add_argument(
        "--rate",
        type=positive_factor,
        metavar="FACTOR",
        help="replay at this multiple of the recorded rate (as `rosbag play --rate`; default 1)",
    )
    add_recording_options(g, g)
    p.set_defaults(handler=cmd_track)

    p = subparsers.add_parser(
        "record-replay",
        help="copy a finished sequence into a new folder frame by frame, like a recorder",
        description="Write a finished sequence into a new folder at RATE frames per second of "
        "wall time, as a recorder would: sequence.yaml, calib.yaml, then per frame the images "
        "(temporary name, then renamed) and the frames.csv row, at the end groundtruth.csv "
        "and the marker recording.done. Timestamps stay as recorded. For trying "
        "`satpose track --live` (in another terminal) on a known sequence.",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="finished sequence folder")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="new sequence folder")
    p.add_argument(
        "--rate", type=positive_hz, required=True, metavar="HZ", help="frames per second"
    )
    p.add_argument("--frames", type=positive_int, help="copy only the first N frames")
    p.set_defaults(handler=cmd_record_replay)


def cmd_track(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from satpose.datasets.config import load_config

    connect = viewer_url(args.connect) if args.connect is not None else None
    bag = is_bag(args.sequence)
    if not bag and _bag_options_given(args):
        raise SatposeError(
            f"{args.sequence}: --rate, --left, --right, --calib, --grey, --pair-tolerance-ms "
            "and --max-unpaired go with a bag (this is taken for a sequence folder)"
        )
    if bag and not args.live:
        raise SatposeError(
            f"{args.sequence}: a bag is tracked as it replays: add --live (or `satpose import` "
            "it and track the sequence folder)"
        )
    if not args.live:  # a finished folder: exactly `satpose run --estimator online`
        if args.until_idle is not None:
            raise SatposeError("--until-idle needs --live")
        from satpose.tools.cli import cmd_run

        cmd_run(argparse.Namespace(**{**vars(args), "estimator": "online", "connect": connect}))
        return
    config = load_config(PipelineConfig, args.config) if args.config else PipelineConfig()
    idle = f", after {args.until_idle:g} s without a frame" if args.until_idle else ""
    replay = None
    if bag:  # opened before anything is said or written: a bad bag is one line
        rate = 1.0 if args.rate is None else args.rate
        replay = BagReplay(args.sequence, recording_options(args), rate=rate)
        speed = "" if args.rate in (None, 1.0) else f" x {args.rate:g}"
        what = f"replaying {args.sequence} at its recorded rate{speed}"
        end = f"(stops at the bag's end{idle} or Ctrl-C)"
    else:
        what = f"tracking {args.sequence} as it is written"
        end = f"(stops at {args.sequence}/recording.done{idle} or Ctrl-C)"
    print(f"{what} -> {args.out} {end}", file=sys.stderr, flush=True)
    bar = tqdm(desc="track", unit="frame", file=sys.stderr, dynamic_ncols=True, delay=0.5)

    def progress(status: dict[str, Any]) -> None:
        bar.update(1)
        bar.set_postfix(
            dropped=status["dropped"], latency_ms=f"{status['latency_ms']:.0f}", refresh=False
        )

    common: dict[str, Any] = {
        "until_idle_s": args.until_idle,
        "overwrite": args.overwrite,
        "spawn": args.spawn,
        "connect": connect,
        "progress": progress,
    }
    try:
        if replay is not None:
            result = track_bag(replay, args.out, config, **common)
        else:
            result = track_folder(args.sequence, args.out, config, **common)
    finally:
        bar.close()
    for note in result.notes:
        print(f"  {note}")
    print(summary_line(result.summary()))
    print(
        f"online estimate of {len(result.run.estimate)} frames in {args.out}/trajectory.csv; "
        f"per frame: {args.out}/live_frames.csv; recording {args.out}/run.rrd"
    )
    if result.run.bad_frames.count:
        print(result.run.bad_frames.summary(result.processed))


def _bag_options_given(args: argparse.Namespace) -> bool:
    return (
        any(getattr(args, k) is not None for k in ("rate", "left", "right", "calib"))
        or args.grey
        or args.pair_tolerance_ms != DEFAULT_TOLERANCE_S * 1e3
        or args.max_unpaired != DEFAULT_MAX_UNPAIRED
    )


def cmd_record_replay(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    bar = tqdm(desc="record-replay", unit="frame", file=sys.stderr, dynamic_ncols=True, delay=0.5)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    with ctrl_c_stops() as stopped:
        try:
            n = replay_sequence(
                args.sequence,
                args.out,
                args.rate,
                frames=args.frames,
                progress=progress,
                stop=stopped,
            )
        finally:
            bar.close()
    if stopped():
        print(f"stopped after {n} frames in {args.out} (no recording.done: like a dead recorder)")
    else:
        print(f"wrote {n} frames to {args.out} at {args.rate:g} Hz, then recording.done")


__all__ = [
    "LIVE_COLUMNS",
    "LiveResult",
    "ctrl_c_stops",
    "live_summary",
    "register",
    "track_bag",
    "track_folder",
    "track_live",
]
