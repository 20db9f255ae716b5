"""Campaign throughput: the plain loop, Dask with 1 worker and Dask with 2 workers, one run.

Each mode runs the same spec (default benchmarks/campaigns/scaling.yaml: 12 CPU-bound cells,
each rendering its own sequence, then run + eval) in a fresh process with a fresh output
folder, so every mode pays its own imports, renders and (for Dask) cluster start. Wall time
is measured around the whole process. The plain loop calls the campaign's own task functions
(`render_cached`, `run_cell`) one after the other in one process, with the same one-thread
settings as a worker. The three tables' metrics are compared cell by cell (deterministic
cells must agree bit for bit).

    python benchmarks/campaign_scaling.py [--spec FILE] [--root runs/bench/scaling]

writes docs/results/campaign_scaling.md. Run it on a quiet machine: the load average before
and after each mode is printed in the table, since a busy second core invalidates the
1 -> 2 worker ratio.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_summary, write_page  # noqa: E402

from satpose.tools.campaign import RESULTS, THREAD_ENV  # noqa: E402

LOOP = """
import sys, time
from pathlib import Path
import pandas as pd
from satpose.tools.campaign import render_cached, run_cell
from satpose.tools.campaign_spec import load_spec, scenario_hash, scenario_of

spec = load_spec(Path(sys.argv[1]))
out = Path(sys.argv[2]).resolve()
rows, renders = [], {}
for cell in spec.cells:
    scenario = scenario_of(cell)
    h = scenario_hash(scenario)
    if h not in renders:
        folder = out / "sequences" / f"{scenario.name}-{h}"
        renders[h] = render_cached(scenario, str(folder), spec.time_limit_s)
    rows.append(run_cell(cell, renders[h], str(out), spec.time_limit_s))
tmp = out / "results.parquet.tmp"
pd.DataFrame(rows).to_parquet(tmp)
tmp.replace(out / "results.parquet")
"""


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def run_mode(name: str, cmd: list[str], out: Path) -> dict[str, object]:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    env = {**os.environ, **THREAD_ENV}
    before = _load()
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    # CPU of the whole process tree (Dask's nannies reap their workers, the client its nannies).
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - usage.ru_utime) + (after.ru_stime - usage.ru_stime)
    df = pd.read_parquet(out / RESULTS)
    print(f"{name}: {wall:.1f} s, {len(df)} cells, {int((df['status'] == 'ok').sum())} ok")
    return {
        "mode": name,
        "wall_s": wall,
        "cells": len(df),
        "ok": int((df["status"] == "ok").sum()),
        "task_s": float(df["render_s"].fillna(0).sum() + df["total_s"].sum()),
        "cpu_s": cpu,
        "load_before": before,
        "load_after": _load(),
        "table": df,
    }


def same_metrics(a: pd.DataFrame, b: pd.DataFrame) -> tuple[int, int]:
    """(metric columns compared, columns that differ) over the cells of both tables."""
    cols = [c for c in a.columns if c.startswith(("est.", "online.")) and c in b.columns]
    a = a.set_index("cell").sort_index()
    b = b.set_index("cell").loc[a.index]
    differ = 0
    for c in cols:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        if x.dtype.kind == "f":
            if not np.array_equal(x, y, equal_nan=True):
                differ += 1
        elif not (x == y).all():
            differ += 1
    return len(cols), differ


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=ROOT / "benchmarks/campaigns/scaling.yaml")
    ap.add_argument("--root", type=Path, default=ROOT / "runs/bench/scaling")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/results/campaign_scaling.md")
    args = ap.parse_args()
    satpose = str(Path(sys.executable).with_name("satpose"))
    spec = str(args.spec.resolve())
    runs = [
        run_mode(
            "plain loop",
            [sys.executable, "-c", LOOP, spec, str(args.root / "loop")],
            args.root / "loop",
        ),
        run_mode(
            "Dask, 1 worker",
            [satpose, "campaign", spec, "--out", str(args.root / "w1"), "--workers", "1"],
            args.root / "w1",
        ),
        run_mode(
            "Dask, 2 workers",
            [satpose, "campaign", spec, "--out", str(args.root / "w2"), "--workers", "2"],
            args.root / "w2",
        ),
    ]
    loop, w1, w2 = runs
    lines = [
        "# Campaign throughput: plain loop vs Dask (1 and 2 workers)",
        "",
        "Generated by `python benchmarks/campaign_scaling.py` (do not edit by hand).",
        f"Spec: `{args.spec.relative_to(ROOT) if args.spec.is_relative_to(ROOT) else args.spec}`"
        f" ({loop['cells']} cells, each with its own render). Machine: {machine_summary()}.",
        "Each mode is one fresh process (imports, renders and cluster start included); the",
        "load average (1, 5, 15 min) is read before and after it. Task times are the cells'",
        "own render + run + eval wall times as the table records them; CPU is the user + system",
        "time of the mode's whole process tree.",
        "",
        "| mode | wall [s] | cells ok | sum of task times [s] | CPU [s] "
        "| throughput [cells/min] | load before | load after |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        lines.append(
            f"| {r['mode']} | {r['wall_s']:.1f} | {r['ok']}/{r['cells']} | {r['task_s']:.1f} "
            f"| {r['cpu_s']:.1f} "
            f"| {60 * r['cells'] / r['wall_s']:.2f} | {r['load_before']} | {r['load_after']} |"
        )
    overhead = w1["wall_s"] / loop["wall_s"] - 1  # type: ignore[operator]
    speedup = w1["wall_s"] / w2["wall_s"]  # type: ignore[operator]
    n1, d1 = same_metrics(loop["table"], w1["table"])  # type: ignore[arg-type]
    n2, d2 = same_metrics(loop["table"], w2["table"])  # type: ignore[arg-type]
    lines += [
        "",
        f"- Overhead of Dask with 1 worker over the plain loop: **{100 * overhead:+.1f} %** "
        "(target ≤ 5 %).",
        f"- Throughput from 1 to 2 workers: **{speedup:.2f}x** (target ≥ 1.8x).",
        f"- Metrics against the plain loop, cell by cell: 1 worker {d1} of {n1} metric columns "
        f"differ, 2 workers {d2} of {n2}.",
    ]
    write_page(args.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
