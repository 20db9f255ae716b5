"""run.rrd's chunk count, size and load time, with the SDK's default batching and compacted.

    python benchmarks/rerun_size.py [--sequence runs/demo/paper-docking] [--frames 40 1000]

1. Runs `satpose run` (online) on ``--sequence`` (default: the demo's 40-frame paper-docking,
   `satpose demo` renders it) twice: with ``recording.compact: false`` (the SDK's default
   micro-batching, what every run wrote before) and with the default compact batching.
2. Replays the compact run's recording calls for ``--frames`` frames (the run's own frames,
   measurements, estimates, truth and timings, cycled: `RunRecorder.log_frame` per frame, then
   `log_final`), both ways, to see how a long run grows without rendering it. A real run
   spends ~1 s per frame, far longer than the SDK's flush tick, so the default-batching
   replay flushes after every frame as the tick would.

Per recording: chunks (static ones included), rows, file size, and the time to load the file
into an in-memory chunk store (``RrdReader(path).stream().collect()``, the ingestion a viewer
does on opening it). Writes docs/results/rerun_size.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)
from rerun.chunk import RrdReader

from satpose.datasets.sequence import load_sequence
from satpose.tools.files import read_measurements
from satpose.tools.pipeline import (
    PipelineConfig,
    read_estimate_npz,
    read_provenance,
    run_pipeline,
)
from satpose.tools.recording import RecordingConfig, RunRecorder


def stats(path: Path) -> dict[str, Any]:
    chunks = list(RrdReader(str(path)).stream())
    start = time.perf_counter()
    RrdReader(str(path)).stream().collect()
    load_s = time.perf_counter() - start
    arrow = {"images": 0, "trajectories": 0, "other": 0}  # in-memory Arrow bytes
    for c in chunks:
        e = c.entity_path.lstrip("/")
        kind = (
            "images"
            if e.endswith("/image")
            else "trajectories"
            if e.startswith("world/trajectory")
            else "other"
        )
        arrow[kind] += c.to_record_batch().nbytes
    return {
        "chunks": len(chunks),
        "static": sum(c.is_static for c in chunks),
        "rows": sum(c.num_rows for c in chunks if not c.is_static),
        "entities": len({c.entity_path for c in chunks}),
        "mb": path.stat().st_size / 1e6,
        "load_s": load_s,
        **{f"{k}_mb": v / 1e6 for k, v in arrow.items()},
    }


def replay(run: Path, out: Path, frames: int, compact: bool) -> float:
    """Record ``frames`` frames with the calls `satpose run` makes, from the run folder's own
    results (cycled); returns the wall time [s]."""
    seq = load_sequence(Path(read_provenance(run)["sequence"]))
    n = len(seq)
    meas = read_measurements(run / "measurements.parquet")
    isam2 = read_estimate_npz(run / "estimate.npz")
    kalman = read_estimate_npz(run / "estimate_kalman.npz")
    finals = {
        "smoothed": read_estimate_npz(run / "estimate_offline.npz"),
        "isam2_smoothed": read_estimate_npz(run / "estimate_smoothed.npz"),
    }
    timings = pd.read_csv(run / "timings.csv")
    stages = [c for c in timings.columns if c.startswith(("frontend_", "backend_"))]
    stages = [c for c in stages if c != "frontend_total"]
    truth = seq.truth
    assert truth is not None
    dt = 1.0 / seq.rate_hz
    rec = RunRecorder(out, seq.calibration, seq.target, replace(RecordingConfig(), compact=compact))
    start = time.perf_counter()
    for k in range(frames):
        i = k % n
        frame = seq[i]
        m = replace(meas[i], frame=k, t_s=k * dt)
        poses = {
            "per_frame": m.pose.left_cam_from_target if m.pose is not None else None,
            "kalman": kalman.left_cam_from_target[i],
            "isam2": isam2.left_cam_from_target[i],
        }
        spin = {
            "kalman": float(kalman.spin_rate_deg_per_frame(dt)[i]),
            "isam2": float(isam2.spin_rate_deg_per_frame(dt)[i]),
        }
        if truth.angular_velocity is not None:
            spin["truth"] = float(np.degrees(np.linalg.norm(truth.angular_velocity[i])) * dt)
        row = timings.iloc[i]
        stage_ms = {
            c.removeprefix("frontend_"): float(row[c]) for c in stages if np.isfinite(row[c])
        }
        rec.log_frame(
            k,
            {"left": frame.left(), "right": frame.right()},
            m,
            poses,
            isam2.pose_covariance[i],
            truth.pose(i),
            spin,
            stage_ms,
        )
        if not compact:
            rec.rec.flush()  # the SDK's tick fires between two frames of a real run
    idx = [k % n for k in range(frames)]
    for name, e in finals.items():
        rec.log_final(
            name,
            list(range(frames)),
            [e.left_cam_from_target[i] for i in idx],
            [truth.pose(i) for i in idx],
            [float(e.spin_rate_deg_per_frame(dt)[i]) for i in idx],
            [k * dt for k in range(frames)],
        )
    rec.close()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", type=Path, default=Path("runs/demo/paper-docking"))
    parser.add_argument("--frames", type=int, nargs="+", default=[40, 1000])
    parser.add_argument("--root", type=Path, default=Path("runs/rerun-size"))
    parser.add_argument("--out", type=Path, default=Path("docs/results/rerun_size.md"))
    args = parser.parse_args()
    if not (args.sequence / "frames.csv").is_file():
        parser.error(f"{args.sequence}: no sequence (run `satpose demo` first)")
    rows = []
    runs = {}
    for compact in (False, True):
        label = "compact" if compact else "sdk-default"
        out = args.root / f"run-{label}"
        cfg = PipelineConfig(recording=RecordingConfig(compact=compact))
        start = time.perf_counter()
        run_pipeline(args.sequence, "online", out, cfg, overwrite=True)
        wall = time.perf_counter() - start
        runs[label] = out
        s = stats(out / "run.rrd")
        rows.append(("`satpose run`", len(load_sequence(args.sequence)), label, s, wall))
        print(rows[-1], flush=True)
    for frames in args.frames:
        for compact in (False, True):
            label = "compact" if compact else "sdk-default"
            path = args.root / f"replay-{frames}-{label}.rrd"
            path.unlink(missing_ok=True)
            wall = replay(runs["compact"], path, frames, compact)
            rows.append(("replay", frames, label, stats(path), wall))
            print(rows[-1], flush=True)
    lines = [
        "# Rerun recording size: SDK default batching vs compact",
        "",
        "Generated by `benchmarks/rerun_size.py "
        + f"--sequence {args.sequence} --frames {' '.join(map(str, args.frames))}` "
        + f"on {machine_summary(libraries=False)} (shared with other jobs).",
        "",
        "`satpose run` rows: the online run of the sequence, the recording written by the "
        "pipeline. Replay rows: the same recording calls for N frames from that run's "
        "results, cycled (the default-batching replay flushes after every frame, as the SDK's "
        "tick does in a real run that spends ~1 s per frame). Load: "
        "`RrdReader(path).stream().collect()`, an in-memory chunk store as a viewer builds "
        "on opening the file. Write: wall time of the run (frontend and estimators included) "
        "or of the replay (JPEG encoding of the images included).",
        "",
        "| recording | frames | batching | chunks (static) | entities | rows | size [MB] "
        "| images / trajectories / other [MB Arrow] | load [s] | write [s] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for what, frames, label, s, wall in rows:
        lines.append(
            f"| {what} | {frames} | {label} | {s['chunks']} ({s['static']}) | {s['entities']} "
            f"| {s['rows']} | {s['mb']:.2f} | {s['images_mb']:.1f} / {s['trajectories_mb']:.1f} "
            f"/ {s['other_mb']:.1f} | {s['load_s']:.3f} | {wall:.1f} |"
        )
    lines += [
        "",
        "Compact batching (`satpose.tools.recording.file_batcher`): each entity's rows go into "
        "one chunk until it holds 384 KiB or 4096 rows. Size: the file on disk; the Arrow "
        "column splits the in-memory size of the chunks by content (the camera images as JPEG; "
        "`world/trajectory/*`, whose line up to the current frame is logged at every frame, so "
        "it grows with the square of the frame count; everything else). Timings are wall "
        "times on a machine shared with other jobs: compare within a row pair only.",
        "",
    ]
    write_page(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
