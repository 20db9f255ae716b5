"""`satpose campaign` on a separately started Dask cluster, with a worker killed mid-cell, and
the 40-cell campaign (issue 21's targets), on this machine.

    nice python benchmarks/campaign_cluster.py [--skip-forty]

1. ``satpose campaign benchmarks/campaigns/smoke.yaml`` on its default LocalCluster (2 workers).
2. ``dask scheduler`` and ``dask worker --nworkers 2 --nthreads 1`` started as their own
   processes on loopback (with docs/campaigns.md's worker settings, read from a Dask config
   folder through ``DASK_CONFIG``), the same spec with ``--scheduler``: its table must equal
   the LocalCluster's in every metric column, bit for bit (renders redone).
3. The same cluster, a fresh output folder: once the first cell is in the table and a cell is
   running, that cell's worker process is killed (SIGKILL); the campaign must complete with
   every cell ok, keep every cell finished before the kill, and again equal the LocalCluster's
   metrics.
4. ``benchmarks/campaigns/coupling.yaml``: 40 cells (10 renders), LocalCluster, 2 workers.

Writes docs/results/campaign_cluster.md; the work goes under ``--work`` (default
runs/bench/campaign-cluster, removed and redone on every run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from _common import machine_summary, write_page  # benchmarks/_common.py (run from the root)

from satpose.tools.campaign import read_results

HERE = Path(__file__).resolve().parent
SMOKE = HERE / "campaigns" / "smoke.yaml"
FORTY = HERE / "campaigns" / "coupling.yaml"
BIN = Path(sys.executable).parent
NOT_METRICS = {
    "worker",
    "sequence_path",
    "run_path",
    "render_s",
    "run_s",
    "eval_s",
    "total_s",
    "peak_rss_mb",
    "render_peak_rss_mb",
    "peak_rss_method",
}
"""Columns that are not results: where a cell ran, what it wrote where, time and memory."""
WORKER_CONFIG = """\
distributed:
  nanny:
    pre-spawn-environ:
      MALLOC_TRIM_THRESHOLD_: null
      OMP_NUM_THREADS: 1
      OPENBLAS_NUM_THREADS: 1
      MKL_NUM_THREADS: 1
      OPENCV_FOR_THREADS_NUM: 1
  worker:
    profile:
      enabled: false
    memory:
      monitor-interval: 1s
  admin:
    tick:
      interval: 1s
    system-monitor:
      interval: 2s
      gil:
        enabled: false
"""
"""docs/campaigns.md's settings for `dask worker` on another machine."""


def campaign(spec: Path, out: Path, *extra: str) -> tuple[float, pd.DataFrame]:
    """``satpose campaign SPEC --out OUT ...`` as a user runs it: wall time and the table."""
    cmd = [str(BIN / "satpose"), "campaign", str(spec), "--out", str(out), *extra]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0, read_results(out)


def statuses(df: pd.DataFrame) -> str:
    return ", ".join(f"{k} {v}" for k, v in df["status"].value_counts().items())


def metric_columns(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c not in NOT_METRICS and not c.startswith("timing.")]


def same_metrics(a: pd.DataFrame, b: pd.DataFrame) -> tuple[int, list[str]]:
    """(metric columns compared, those not equal bit for bit); rows matched by cell id, NaN
    equal to NaN, a column missing from one table NaN there (a table holds the columns of
    the cells written so far: no ``kalman.*`` before a kalman cell is done)."""
    a, b = a.set_index("cell").sort_index(), b.set_index("cell").sort_index()
    if list(a.index) != list(b.index):
        return 0, ["cell ids differ"]
    cols = sorted(set(metric_columns(a.reset_index())) | set(metric_columns(b.reset_index())))
    cols = [c for c in cols if c != "cell"]
    differ = []
    for c in cols:
        nan = np.full(len(a), np.nan)
        x = a[c].to_numpy() if c in a else nan
        y = b[c].to_numpy() if c in b else nan
        if x.dtype.kind == "f" and y.dtype.kind == "f":
            equal = np.array_equal(x, y, equal_nan=True)
        else:
            equal = all(
                (u == v) or (u is None and v is None) or (_nan(u) and _nan(v))
                for u, v in zip(x, y, strict=True)
            )
        if not equal:
            differ.append(c)
    return len(cols), differ


def _nan(v: Any) -> bool:
    return isinstance(v, float) and math.isnan(v)


class Cluster:
    """``dask scheduler`` + ``dask worker`` as separate processes on loopback (each in its own
    session, stopped by its process group id)."""

    def __init__(self, work: Path, workers: int) -> None:
        config = work / "dask-config"
        config.mkdir(parents=True, exist_ok=True)
        (config / "satpose.yaml").write_text(WORKER_CONFIG)
        env = {**os.environ, "DASK_CONFIG": str(config)}
        file = work / "scheduler.json"
        file.unlink(missing_ok=True)
        dask = str(BIN / "dask")
        scheduler = [dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard"]
        worker = [dask, "worker", "--nworkers", str(workers), "--nthreads", "1", "--no-dashboard"]
        self.logs = [open(work / n, "w") for n in ("scheduler.log", "worker.log")]
        self.procs = [
            subprocess.Popen(
                [*scheduler, "--scheduler-file", str(file)],
                env=env,
                stdout=self.logs[0],
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        ]
        deadline = time.time() + 60
        while not file.is_file() and time.time() < deadline:
            time.sleep(0.2)
        self.address = json.loads(file.read_text())["address"]
        self.procs.append(
            subprocess.Popen(
                [*worker, self.address],
                env=env,
                stdout=self.logs[1],
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        )
        from distributed import Client

        self.client = Client(self.address, timeout="30s")
        self.client.wait_for_workers(workers, timeout=120)

    def close(self) -> None:
        self.client.close()
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
        for f in self.logs:
            f.close()


def kill_mid_cell(cluster: Cluster, out: Path) -> dict[str, Any]:
    """The smoke spec on ``cluster``; once a cell is in the table and another is running, the
    running cell's worker process gets SIGKILL. What was in the table then, and after."""
    cmd = [str(BIN / "satpose"), "campaign", str(SMOKE), "--out", str(out)]
    cmd += ["--scheduler", cluster.address]
    print("$", " ".join(cmd), "(a worker killed mid-cell)", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    killed: dict[str, Any] = {}
    while proc.poll() is None and not killed:
        time.sleep(0.2)
        before = read_results(out)
        if not len(before):
            continue
        running = [
            (w, str(k))
            for w, keys in cluster.client.processing().items()
            for k in keys
            if str(k).startswith("cell-")
        ]
        if not running:
            continue
        worker, key = running[0]
        pid = cluster.client.run(os.getpid, workers=[worker])[worker]
        os.kill(pid, signal.SIGKILL)
        before.to_parquet(out.parent / "kill_before.parquet")  # what the table held
        killed = {"worker": worker, "pid": pid, "key": key, "before": before}
        killed["at_s"] = time.perf_counter() - t0
        print(f"killed worker {worker} (pid {pid}) running {key}", flush=True)
    rc = proc.wait()
    killed["rc"] = rc
    killed["wall_s"] = time.perf_counter() - t0
    killed["after"] = read_results(out)
    return killed


def markdown(r: dict[str, Any], command: str, load: str) -> str:
    local, loop, kill = r["local"], r["loopback"], r["kill"]
    out = [
        "# Campaigns on a separately started Dask cluster, a killed worker, 40 cells (issue 21)",
        "",
        f"Generated by `{command}` (do not edit by hand). Machine: {machine_summary()}; "
        f"load average before / after: {load}. Wall times on a shared machine.",
        "",
        "| run | command | cells | status | wall [s] | result |",
        "|---|---|---|---|---|---|",
        f"| LocalCluster (2 workers) | `satpose campaign benchmarks/campaigns/smoke.yaml "
        f"--out OUT` | {len(local[1])} | {statuses(local[1])} | {local[0]:.0f} | the reference |",
    ]
    n, differ = r["loopback_same"]
    out.append(
        f"| `dask scheduler` + `dask worker --nworkers 2 --nthreads 1` on loopback | "
        f"`satpose campaign ... --scheduler tcp://127.0.0.1:PORT` | {len(loop[1])} | "
        f"{statuses(loop[1])} | {loop[0]:.0f} | {n - len(differ)} of {n} metric columns "
        f"bit-identical to the LocalCluster's"
        + (f"; differ: {', '.join(differ[:8])}" if differ else "")
        + " |"
    )
    after = kill["after"]
    if "key" in kill:
        before = kill["before"]
        kept = set(before["cell"]) <= set(after["cell"])
        kept_same = same_metrics(before, after[after["cell"].isin(before["cell"])])
        n2, differ2 = r["kill_same"]
        result = (
            f"SIGKILL to the worker process (pid {kill['pid']}) running "
            f"`{kill['key'].split('-')[1][:12]}...` at {kill['at_s']:.0f} s, with "
            f"{len(before)} cell(s) in the table; exit status {kill['rc']}; the "
            f"{len(before)} cell(s) finished before the kill "
            + (
                "kept unchanged"
                if kept and not kept_same[1]
                else f"**not kept** ({'; '.join(kept_same[1][:5]) or 'missing'})"
            )
            + "; "
            f"{n2 - len(differ2)} of {n2} metric columns bit-identical to the LocalCluster's"
        )
    else:
        result = f"**no cell was seen running after the first finished** (exit {kill['rc']})"
    out.append(
        f"| the same cluster, a worker killed mid-cell | the same | {len(after)} | "
        f"{statuses(after)} | {kill['wall_s']:.0f} | {result} |"
    )
    if r.get("forty") is not None:
        wall, df = r["forty"]
        # every cell carries its render's time: count each rendered sequence once
        renders = int((df.drop_duplicates("sequence_path")["render_s"] > 0).sum())
        cells_per = ", ".join(str(n) for n in sorted(set(df["sequence_path"].value_counts())))
        out.append(
            f"| LocalCluster (2 workers), 40 cells | `satpose campaign "
            f"benchmarks/campaigns/coupling.yaml --out OUT` | {len(df)} | {statuses(df)} | "
            f"{wall:.0f} | {renders} renders, {cells_per} cells each |"
        )
    out += [
        "",
        "Metric columns: every column of the table except where and when a cell ran "
        "(`worker`, `sequence_path`, `run_path`, `*_s` times, `peak_rss_*`, `timing.*`); rows "
        "matched by cell id, NaN equal to NaN. The worker settings are docs/campaigns.md's "
        "(`MALLOC_TRIM_THRESHOLD_` unset, BLAS/OpenMP/OpenCV on one thread), given to "
        "`dask worker` by a Dask config folder (`DASK_CONFIG`). The killed worker is "
        "restarted by its nanny; the scheduler hands its cell to a worker again (its "
        "`allowed-failures`, default 3).",
    ]
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("runs/bench/campaign-cluster"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/campaign_cluster.md"))
    ap.add_argument("--skip-forty", action="store_true", help="leave out the 40-cell campaign")
    args = ap.parse_args()
    load0 = "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    r: dict[str, Any] = {}
    r["local"] = campaign(SMOKE, args.work / "local", "--workers", "2")
    cluster = Cluster(args.work, workers=2)
    try:
        r["loopback"] = campaign(SMOKE, args.work / "loopback", "--scheduler", cluster.address)
        r["kill"] = kill_mid_cell(cluster, args.work / "kill")
    finally:
        cluster.close()
    r["loopback_same"] = same_metrics(r["local"][1], r["loopback"][1])
    r["kill_same"] = same_metrics(r["local"][1], r["kill"]["after"])
    if not args.skip_forty:
        r["forty"] = campaign(FORTY, args.work / "forty", "--workers", "2")
    load = f"{load0} / " + "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    command = "python benchmarks/campaign_cluster.py " + " ".join(sys.argv[1:])
    write_page(args.out, markdown(r, command.strip(), load))


if __name__ == "__main__":
    main()
