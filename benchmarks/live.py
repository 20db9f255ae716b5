"""Live tracking benchmark: `satpose track --live` on a recording written at 2, 5 and 10 Hz.

    nice -n 10 python benchmarks/live.py [--frames 81] [--rates 2 5 10] [--data runs/bench]
        [--work runs/bench-live] [--source folder|bag] [--reacquire window|whole|both]

Uses paper-docking at its default size (1024x768 stereo, 81 frames) as benchmarks/frontend.py
renders it (``--data``/paper-docking: rendered there if missing, otherwise only read), its
first ``--frames`` frames (all by default, so that the first frame's acquisition over the
whole image does not dominate: the steady state is what a live user sees). For each rate
either (``--source folder``) replays it into a fresh folder under ``--work`` with
`satpose.datasets.live.replay_sequence` (a thread, like a camera recorder: images to a
temporary name and renamed, then the frames.csv row) while
`satpose.tools.live.track_folder` tracks it in the main thread, exactly as ``satpose track
--live SEQ`` does, or (``--source bag``) writes it once as a ROS 2 bag and tracks the bag
replayed at that rate (`satpose.datasets.live.BagReplay`, ``--rate`` = rate / the recorded
rate), exactly as ``satpose track --live BAG`` does. The default pipeline config, as
``--live`` runs it: per frame the frontend, iSAM2 and run.rrd with images; the offline and
Kalman estimators for comparison once at the end.

``--reacquire both`` runs every rate twice: with the ring re-acquired after dropped frames in
the window predicted over the gap (the default, ``RingConfig.gap_window``) and over the whole
image (``gap_window: false``, the behaviour before it), to show what the window saves on the
frames that follow a gap, and compares both on the same frames.

Writes docs/results/live.md (docs/results/live_bag.md for ``--source bag``): frames processed
and dropped, latency (arrival -> end of the frame's step) median and p95 over all processed
frames and over the frames that arrived after the first pose (the start-up left out: the
first frame's acquisition and the frames that arrived during it), the idle pickup delay,
the step's CPU time over all processed frames and over those right after a gap, where the
time of a frame goes (median per stage), and the load average of the machine before and
after each run (also printed beside each result).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
import time
from datetime import date
from pathlib import Path

import numpy as np
import pandas as pd
from _common import ensure_rendered, machine_summary, write_page  # benchmarks/_common.py

from satpose.datasets.config import replace_nested
from satpose.datasets.importers.writers import write_bag
from satpose.datasets.live import BagReplay, replay_sequence
from satpose.datasets.sequence import load_sequence
from satpose.frontend.pipeline import StereoFrontend
from satpose.tools.evaluate import evaluate_run
from satpose.tools.live import LiveResult, track_bag, track_folder
from satpose.tools.pipeline import PipelineConfig, RunError, run_pipeline

OUT = {"folder": Path("docs/results/live.md"), "bag": Path("docs/results/live_bag.md")}
VARIANTS = {
    "window": ("predicted window", PipelineConfig()),
    "whole": (
        "whole image",
        replace_nested(PipelineConfig(), {"frontend": {"ring": {"gap_window": False}}}),
    ),
}
"""Re-acquisition after a gap: in the window predicted over it (default), or over the whole
image (as before the window existed)."""


COLUMNS = [
    "rate (period)",
    "re-acquisition after a gap",
    "frames",
    "processed",
    "dropped",
    "latency median [ms]",
    "latency p95 [ms]",
    "after the first pose: processed",
    "dropped",
    "latency median [ms]",
    "latency p95 [ms]",
    "pickup p95 (max) when idle [ms]",
    "step CPU median [ms]",
    "position error [cm]",
    "load (1 min) before / after",
]
"""The main table's columns (one row per rate and re-acquisition)."""


def ensure_sequence(data: Path, work: Path, frames: int | None) -> Path:
    """paper-docking at its default size under ``data`` (rendered there if missing, as
    benchmarks/frontend.py does), or a copy of its first ``frames`` frames under ``work``
    (copied once by `replay_sequence` without pacing: the same PNG bytes)."""
    full = ensure_rendered("paper-docking", data)
    if frames is None or frames >= len(load_sequence(full)):
        return full
    out = work / f"paper-docking-{frames}"
    if not (out / "frames.csv").is_file():
        shutil.rmtree(out, ignore_errors=True)
        replay_sequence(full, out, 1e6, frames=frames)
    return out


def after_first_pose(result: LiveResult) -> dict[str, float | int | None]:
    """The frames that arrived after the tracker had its first pose (the start-up left out:
    the first frame's acquisition over the whole image and the frames that arrived during
    it): how many processed and dropped, latency median and p95 [ms]."""
    with_pose = {m.frame for m in result.run.measurements if m.pose is not None}
    t = result.frames
    done = t[t["status"] == "processed"]
    first = done[done["frame"].isin(with_pose)]
    if first.empty:
        return {"processed": 0, "dropped": 0, "median": None, "p95": None}
    ready = float(first["arrival_unix_s"].iloc[0] + first["latency_ms"].iloc[0] / 1e3)
    later = t[t["arrival_unix_s"] > ready]
    lat = later[later["status"] == "processed"]["latency_ms"].dropna().to_numpy(float)
    return {
        "processed": int(lat.size),
        "dropped": int((later["status"] == "dropped").sum()),
        "median": float(np.median(lat)) if lat.size else None,
        "p95": float(np.percentile(lat, 95)) if lat.size else None,
    }


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.0f}"


def loadavg() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} / {five:.2f} / {fifteen:.2f}"


def track_bag_at(
    bag: Path, recorded_hz: float, rate_hz: float, run: Path, config: PipelineConfig
) -> tuple[LiveResult, str, str]:
    """Track ``bag`` replayed at ``rate_hz`` frames per second into ``run``: the result and
    the load average (1/5/15 min) before and after."""
    before = loadavg()
    result = track_bag(BagReplay(bag, rate=rate_hz / recorded_hz), run, config, until_idle_s=30.0)
    return result, before, loadavg()


def after_gap(result: LiveResult) -> tuple[int, float, float]:
    """The processed frames that follow a dropped one (not the first frame, an acquisition
    anyway): how many, their step CPU time and ring stage (medians [ms])."""
    t = pd.read_csv(result.out / "timings.csv")
    gap = np.r_[False, np.diff(t["frame"].to_numpy()) > 1]
    sel = t[gap]
    if sel.empty:
        return 0, np.nan, np.nan
    return len(sel), float(sel["step_cpu_ms"].median()), float(sel["frontend_ring"].median())


def ring_on_frames(seq: Path, frames: list[int]) -> list[str]:
    """Both re-acquisitions on the same frames (the frontend alone, frames in this order, the
    others skipped as a live run skipped them): per variant, the frames with a ring, the
    ring centre's and normal's error against the truth (the target frame's origin is the
    ring's outer front edge centre, z its normal) and the ring stage's time, medians over
    the frames that follow a gap. Table rows."""
    sequence = load_sequence(seq)
    assert sequence.truth is not None
    gap = [k for i, k in enumerate(frames) if i > 0 and k - frames[i - 1] > 1]
    rows = []
    for variant in ("whole", "window"):
        label, config = VARIANTS[variant]
        front = StereoFrontend(sequence.calibration, config.frontend)
        found, center_mm, normal_deg, ring_ms = 0, [], [], []
        for k in frames:
            m = front.process_frame(sequence[k])
            if k not in gap:
                continue
            ring_ms.append(m.timings_ms.get("ring", np.nan))
            if m.ring is None:
                continue
            found += 1
            T = sequence.truth.pose(k)
            center_mm.append(1e3 * float(np.linalg.norm(m.ring.center_m - T.t)))
            cos = abs(float(m.ring.normal @ T.R[:, 2]))
            normal_deg.append(float(np.degrees(np.arccos(min(cos, 1.0)))))
        rows.append(
            f"| {label} | {len(gap)} | {found} | {np.median(center_mm):.1f} | "
            f"{np.median(normal_deg):.2f} | {np.median(ring_ms):.0f} |"
        )
        print(rows[-1], flush=True)
    return rows


def position_error_cm(seq: Path, result: LiveResult) -> str:
    """The causal iSAM2 estimate's position error on the processed frames (`satpose eval`'s
    ``pos_cm`` of "online filtered"), or "-"."""
    m = evaluate_run(seq, result.out).get("online filtered")
    return "-" if m is None else f"{m.pos_cm:.2f}"


def track_at(
    seq: Path, rate_hz: float, work: Path, config: PipelineConfig, tag: str = ""
) -> tuple[LiveResult, str, str]:
    """Replay ``seq`` at ``rate_hz`` into ``work`` while tracking it: the result and the load
    average (1/5/15 min) before and after."""
    recording = work / f"recording-{rate_hz:g}hz{tag}"
    run = work / f"run-{rate_hz:g}hz{tag}"
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
    ap.add_argument("--frames", type=int, help="the first N frames (default: all 81)")
    ap.add_argument("--rates", type=float, nargs="+", default=[2.0, 5.0, 10.0])
    ap.add_argument("--data", type=Path, default=Path("runs/bench"), help="where presets render")
    ap.add_argument("--work", type=Path, default=Path("runs/bench-live"), help="scratch space")
    ap.add_argument("--source", choices=["folder", "bag"], default="folder")
    ap.add_argument("--reacquire", choices=["window", "whole", "both"], default="window")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    seq = ensure_sequence(args.data, args.work, args.frames)
    loaded = load_sequence(seq)
    n = len(loaded)
    variants = ["whole", "window"] if args.reacquire == "both" else [args.reacquire]
    rows, dropped_rows, gap_rows, stages, loads = [], [], [], {}, []
    most: list[int] = []  # the processed frames of the run that processed the most
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        bag = None
        if args.source == "bag":
            print(f"writing the {n} frames as a ROS 2 bag", flush=True)
            bag = write_bag(loaded, Path(tmp) / "paper-docking", ros=2)
        for rate in args.rates:
            for variant in variants:
                label, config = VARIANTS[variant]
                print(f"{args.source} at {rate:g} Hz, re-acquisition: {label}", flush=True)
                before = loadavg()
                try:
                    if bag is not None:
                        run = Path(tmp) / f"run-{rate:g}hz-{variant}"
                        result, before, after = track_bag_at(bag, loaded.rate_hz, rate, run, config)
                    else:
                        result, before, after = track_at(
                            seq, rate, Path(tmp), config, f"-{variant}"
                        )
                except RunError as exc:  # reported in the table, not hidden
                    after = loadavg()
                    rows.append(
                        f"| {rate:g} Hz ({1000 / rate:.0f} ms) | {label} | failed: {exc} |"
                        + " |" * (len(COLUMNS) - 3)
                        + f" {before.split(' / ')[0]} / {after.split(' / ')[0]} |"
                    )
                    loads.append(f"| {rate:g} Hz, {label} | {before} | {after} |")
                    print(f"{rows[-1]}  load average before/after: {before} -> {after}")
                    continue
                s = result.summary()
                lat, pick = s["latency_ms"], s["pickup_idle_ms"]
                steady = after_first_pose(result)
                rows.append(
                    f"| {rate:g} Hz ({1000 / rate:.0f} ms) | {label} | {s['frames_seen']} | "
                    f"{s['processed']} | {s['dropped']} | {_ms(lat['median'])} | "
                    f"{_ms(lat['p95'])} | {steady['processed']} | {steady['dropped']} | "
                    f"{_ms(steady['median'])} | {_ms(steady['p95'])} | "
                    + (f"{pick['p95']:.0f} ({pick['max']:.0f})" if pick["p95"] is not None else "-")
                    + f" | {_ms(s['step_cpu_ms']['median'])} | {position_error_cm(seq, result)} "
                    f"| {before.split(' / ')[0]} / {after.split(' / ')[0]} |"
                )
                dropped_rows.append(
                    f"| {rate:g} Hz | {label} | {s['dropped_frames'] or '-'} | "
                    + ", ".join(f"{r} {k}" for r, k in s["dropped_by_reason"].items())
                    + " |"
                )
                done = result.frames.query("status == 'processed'")["frame"].tolist()
                if len(done) > len(most):
                    most = [int(f) for f in done]
                k, cpu, ring = after_gap(result)
                gap_rows.append(
                    f"| {rate:g} Hz | {label} | {k} | "
                    + (f"{cpu:.0f} | {ring:.0f} |" if k else "- | - |")
                )
                key = f"{rate:g} Hz, {label}"
                stages[key] = stage_medians(result)
                loads.append(f"| {key} | {before} | {after} |")
                print(f"{rows[-1]}  load average before/after: {before} -> {after}", flush=True)
        same_rows: list[str] = []
        if len(variants) == 2:
            print(f"both re-acquisitions on the frames {most}", flush=True)
            before = loadavg()
            same_rows = ring_on_frames(seq, most)
            loads.append(f"| the ring on the same frames | {before} | {loadavg()} |")
        # the profile without gaps: every frame through `satpose run` (the same frontend)
        print("the same frames through satpose run (no drops)", flush=True)
        before = loadavg()
        t0 = time.perf_counter()
        run_pipeline(seq, "online", Path(tmp) / "run-all", PipelineConfig())
        wall = time.perf_counter() - t0
        loads.append(f"| run, every frame | {before} | {loadavg()} |")
        print(f"  {wall:.0f} s; load average before/after: {before} -> {loadavg()}", flush=True)
        t = pd.read_csv(Path(tmp) / "run-all" / "timings.csv")
        stages["run (every frame)"] = stage_medians_of(t)
        first = float(t["frontend_ring"].iloc[0])
        later = float(t["frontend_ring"].iloc[1:].median())
        run_total = float(t["frontend_total"].iloc[1:].median())
    keys = list(stages)
    names = list(dict.fromkeys(k for st in stages.values() for k in st))
    stage_rows = [
        f"| {name} | " + " | ".join(f"{stages[r].get(name, np.nan):.1f}" for r in keys) + " |"
        for name in names
    ]
    command = "nice -n 10 python benchmarks/live.py"
    if args.frames is not None:
        command += f" --frames {args.frames}"
    if args.source != "folder":
        command += f" --source {args.source}"
    if args.reacquire != "window":
        command += f" --reacquire {args.reacquire}"
    if args.rates != [2.0, 5.0, 10.0]:
        command += " --rates " + " ".join(f"{r:g}" for r in args.rates)
    machine = machine_summary(libraries=False)
    columns = COLUMNS
    header = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns)
    if bag is not None:
        source = f"""written once as a ROS 2 bag (`write_bag`: raw images, header
stamps) and tracked as `satpose track --live BAG --rate R` does (`BagReplay`: each stereo
pair arrives at its stamp's offset divided by R = the rate / the recorded {loaded.rate_hz:g}
Hz; decoded only when processed)"""
    else:
        source = """written into a fresh folder by `replay_sequence` at the given rate (a
thread of the same process: per frame both PNGs copied to a temporary name and renamed,
then the frames.csv row) while `track_folder` tracks it"""
    same = ""
    if same_rows:
        same_columns = [
            "re-acquisition",
            "frames after a gap",
            "with a ring",
            "centre error median [mm]",
            "normal error median [deg]",
            "ring stage median [ms]",
        ]
        same_header = "| " + " | ".join(same_columns) + " |\n|" + "---|" * len(same_columns)
        same = f"""
### The ring on the same frames

The runs above process different frames, so their position errors do not compare the two
re-acquisitions. Here both see the same frames: those processed by the run that processed
the most (frames {", ".join(map(str, most))}), through the frontend alone (the others skipped
as that run skipped them); errors against the truth on the frames that follow a gap (the
target frame's origin is the ring's outer front edge centre, z its normal).

{same_header}
{chr(10).join(same_rows)}
"""
    whole = ""
    if len(variants) == 2:
        whole = " and, for comparison, over the whole image (`frontend.ring.gap_window: false`)"
    text = f"""# Live tracking: `satpose track --live` on a recording as it arrives ({args.source})

Generated by `{command}` ({machine}, {date.today()}; {time.perf_counter() - started:.0f} s).
Do not edit by hand.

paper-docking at its default size (1024x768 stereo, 16 spp), {n} frames, {source}. The
default pipeline config as `--live` runs it: per frame the frontend, iSAM2, the
trajectory.csv row and run.rrd (JPEG images every frame); the offline smoother and the Kalman
filter once at the end on every processed frame's measurements; OpenCV with its default
threads. The ring is re-acquired after dropped frames where the motion predicts it (docs/live.md
"Re-acquiring the ring after a gap"){whole}.
**Load average**: the last column (1 min, before and after the run), all three below; the
machine has 2 cores, so a load above ~1 (this benchmark itself) stretches the wall-clock
numbers.

{header}
{chr(10).join(rows)}

Latency: from the frame's arrival (the newest modification time of its images and of
frames.csv when its row was read; for a bag, its replay time) to the end of its step
(frontend, iSAM2, run.rrd, the trajectory.csv row). "After the first pose": the frames that
arrived after the step of the first frame with a pose had ended, which leaves out the
start-up (the first frame's ring acquisition over the whole image, and the frames that
arrived during it): what a user sees once tracking runs. Pickup: arrival until the
tracker found the frame, over the frames that arrived while it was idle (a frame arriving
during another frame's step waits for it). Step CPU: the process's CPU time during a frame's
step (all threads), what the step costs without waiting for a core of a shared machine.
Dropped: complete frames that were not the newest when the tracker was free
(live_frames.csv names each with its reason). Position error: `satpose eval`'s `pos_cm` of
the causal iSAM2 estimate (trajectory.csv) on the frames processed.

| rate | re-acquisition | dropped frames | by reason |
|---|---|---|---|
{chr(10).join(dropped_rows)}

## The frames right after a gap

Processed frames whose previous frame was dropped (the first frame, an acquisition in any
case, not counted): the ring and the panel must be found again after the target moved for
the whole gap.

| rate | re-acquisition | frames after a gap | step CPU median [ms] | ring stage median [ms] |
|---|---|---|---|---|
{chr(10).join(gap_rows)}
{same}
## Where the time of a processed frame goes (median [ms])

| stage | {" | ".join(keys)} |
|---|{"---|" * len(keys)}
{chr(10).join(stage_rows)}

Frontend stages (indented) are medians over the frames where they ran (`ring_reacquire`:
the look where the ring is predicted after a gap, `RingTracker.reacquire`, part of `ring`);
`read + frontend` includes reading the two images. `run (every frame)`: the same {n} frames
through `satpose run --estimator online` (the same frontend, no frame skipped, all three
estimators per frame; {wall:.0f} s in all): read + frontend {run_total:.0f} ms (median after
the first frame); the ring stage took {first:.0f} ms on the first frame (acquisition: the
whole image searched) and {later:.0f} ms (median) on the tracked frames after it.

## Load average of the machine (1 / 5 / 15 min)

| run | before | after |
|---|---|---|
{chr(10).join(loads)}
"""
    write_page(OUT[args.source], text)


if __name__ == "__main__":
    sys.exit(main())
