"""Live tracking benchmark: `satpose track --live` on a recording written at 2, 5 and 10 Hz.

    nice -n 10 python benchmarks/live.py [--frames 25] [--rates 2 5 10] [--root runs/bench-live]

Renders paper-docking at its default size (1024x768 stereo) once (the first ``--frames``
frames, kept under ``--root`` and reused), then for each rate replays it into a fresh folder
with `satpose.datasets.live.replay_sequence` (a thread, like a camera recorder: images to a
temporary name and renamed, then the frames.csv row) while `satpose.tools.live.track_folder`
tracks it in the main thread, exactly as ``satpose track --live`` does (the default pipeline
config: iSAM2 plus the offline and Kalman estimators for comparison, run.rrd with images).
Writes docs/results/live.md: frames processed and dropped, latency (arrival -> end of the
frame's step) median and p95, the idle pickup delay, where the time of a frame goes (median
per stage), and the load average of the shared machine before and after each run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from datetime import date
from pathlib import Path

import numpy as np
import pandas as pd
from _common import machine_summary, write_page  # benchmarks/_common.py

from satpose.datasets.live import replay_sequence
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset, scaled
from satpose.datasets.sequence import load_sequence
from satpose.tools.live import LiveResult, track_folder
from satpose.tools.pipeline import PipelineConfig, run_pipeline

OUT = Path("docs/results/live.md")


def ensure_sequence(root: Path, frames: int) -> Path:
    """paper-docking, default size and spp, its first ``frames`` frames (rendered once)."""
    out = root / f"paper-docking-{frames}"
    if not (out / "frames.csv").is_file():
        print(f"rendering {frames} frames of paper-docking into {out}", flush=True)
        render_sequence(scaled(preset("paper-docking"), frames=frames), out, overwrite=True)
    return out


def loadavg() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} / {five:.2f} / {fifteen:.2f}"


def track_at(
    seq: Path, rate_hz: float, work: Path, config: PipelineConfig
) -> tuple[LiveResult, str, str]:
    """Replay ``seq`` at ``rate_hz`` into ``work`` while tracking it: the result and the load
    average (1/5/15 min) before and after."""
    recording, run = work / f"recording-{rate_hz:g}hz", work / f"run-{rate_hz:g}hz"
    before = loadavg()
    errors: list[BaseException] = []

    def record() -> None:
        try:
            time.sleep(0.5)  # the tracker is waiting for sequence.yaml first
            replay_sequence(seq, recording, rate_hz)
        except BaseException as exc:  # reported after the join
            errors.append(exc)

    thread = threading.Thread(target=record)
    thread.start()
    try:
        result = track_folder(recording, run, config, until_idle_s=30.0)
    finally:
        thread.join()
    if errors:
        raise errors[0]
    return result, before, loadavg()


def stage_medians(result: LiveResult) -> dict[str, float]:
    """Median time per stage of the processed frames [ms]."""
    return stage_medians_of(pd.read_csv(result.out / "timings.csv"))


def stage_medians_of(t: pd.DataFrame) -> dict[str, float]:
    """Median time per stage of a timings.csv table [ms]."""
    cols = {
        "read + frontend": "frontend_total",
        "iSAM2 add": "backend_online",
        "offline add": "backend_offline",
        "kalman add": "backend_kalman",
        "recording": "recording",
    }
    out = {k: float(t[c].median()) for k, c in cols.items() if c in t}
    for c in t.columns:
        if c.startswith("frontend_") and c != "frontend_total":
            ran = t[c][t[c] > 0]
            if len(ran):
                out[f"  {c.removeprefix('frontend_')}"] = float(ran.median())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=25)
    ap.add_argument("--rates", type=float, nargs="+", default=[2.0, 5.0, 10.0])
    ap.add_argument("--root", type=Path, default=Path("runs/bench-live"))
    args = ap.parse_args()
    seq = ensure_sequence(args.root, args.frames)
    n = len(load_sequence(seq))
    config = PipelineConfig()
    rows, stages, loads = [], {}, []
    with tempfile.TemporaryDirectory(dir=args.root) as tmp:
        for rate in args.rates:
            print(f"replaying {n} frames at {rate:g} Hz while tracking", flush=True)
            result, before, after = track_at(seq, rate, Path(tmp), config)
            s = result.summary()
            lat, pick = s["latency_ms"], s["pickup_idle_ms"]
            rows.append(
                f"| {rate:g} Hz ({1000 / rate:.0f} ms) | {s['frames_seen']} | {s['processed']} | "
                f"{s['dropped']} | {s['dropped_frames'] or '-'} | {lat['median']:.0f} | "
                f"{lat['p95']:.0f} | "
                + (f"{pick['p95']:.0f} ({pick['max']:.0f})" if pick["p95"] is not None else "-")
                + f" | {s['step_cpu_ms']['median']:.0f} | {len(result.run.estimate)} |"
            )
            stages[rate] = stage_medians(result)
            loads.append(f"| {rate:g} Hz | {before} | {after} |")
            print(rows[-1], flush=True)
        # the profile without gaps: every frame through `satpose run` (the same step)
        print("the same frames through satpose run (no drops)", flush=True)
        before = loadavg()
        t0 = time.perf_counter()
        run_pipeline(seq, "online", Path(tmp) / "run-all", config)
        wall = time.perf_counter() - t0
        loads.append(f"| run, every frame | {before} | {loadavg()} |")
        t = pd.read_csv(Path(tmp) / "run-all" / "timings.csv")
        stages["run"] = stage_medians_of(t)
        first = float(t["frontend_ring"].iloc[0])
        later = float(t["frontend_ring"].iloc[1:].median())
    columns_rates = [*args.rates, "run"]
    names = list(dict.fromkeys(k for st in stages.values() for k in st))
    stage_rows = [
        f"| {name} | "
        + " | ".join(f"{stages[r].get(name, np.nan):.1f}" for r in columns_rates)
        + " |"
        for name in names
    ]
    rate_cols = " | ".join(f"{r:g} Hz" for r in args.rates) + " | run (every frame)"
    command = f"nice -n 10 python benchmarks/live.py --frames {args.frames}"
    machine = machine_summary(libraries=False)
    columns = [
        "rate (period)",
        "frames",
        "processed",
        "dropped",
        "dropped frames",
        "latency median [ms]",
        "latency p95 [ms]",
        "pickup p95 (max) when idle [ms]",
        "step CPU median [ms]",
        "frames in trajectory",
    ]
    header = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns)
    text = f"""# Live tracking: `satpose track --live` on a recording as it is written

Generated by `{command}` ({machine}, {date.today()}). Do not edit by hand.

paper-docking at its default size (1024x768 stereo, 16 spp), the first {n} frames, written into
a fresh folder by `replay_sequence` at the given rate (a thread of the same process: per frame
both PNGs copied to a temporary name and renamed, then the frames.csv row) while
`track_folder` tracks it (the default pipeline config: iSAM2, the offline and Kalman
estimators for comparison, run.rrd with JPEG images; OpenCV with its default threads). The
machine is shared with other jobs: the load average is below.

{header}
{chr(10).join(rows)}

Latency: from the frame's arrival (the newest modification time of its images and of
frames.csv when its row was read) to the end of its step (frontend, the three estimators,
run.rrd, the trajectory.csv row). Pickup: arrival until the tracker found the frame, over the
frames that arrived while it was idle (a frame arriving during another frame's step waits for
it). Step CPU: the process's CPU time during a frame's step (all threads), what the step costs
without waiting for a core of the shared machine. Dropped: complete frames that were not the
newest when the tracker was free (live_frames.csv names each with its reason).

## Where the time of a processed frame goes (median [ms])

| stage | {rate_cols} |
|---|{"---|" * len(columns_rates)}
{chr(10).join(stage_rows)}

Frontend stages (indented) are medians over the frames where they ran; `read + frontend`
includes reading the two PNGs. `run (every frame)`: the same {n} frames through `satpose run
--estimator online` (the same `FrameStep`, no frame skipped; {wall:.0f} s in all): the ring
stage took {first:.0f} ms on the first frame (acquisition: the whole image searched) and
{later:.0f} ms (median) on the tracked frames after it.

## Load average of the machine (1 / 5 / 15 min)

| run | before | after |
|---|---|---|
{chr(10).join(loads)}
"""
    write_page(OUT, text)


if __name__ == "__main__":
    sys.exit(main())
