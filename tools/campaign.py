"""`satpose campaign SPEC.yaml --out DIR`: Monte Carlo and reprocessing campaigns on Dask.

A campaign (`satpose.tools.campaign_spec`) is the product of axes; each cell is one task
``render (synthetic, cached) -> run -> score`` on a Dask distributed cluster, the run and the
score by the cell's pipeline (`PIPELINES`): ``stereo`` (`run_pipeline` + `evaluate_run`, or
with ``estimator: frontend`` the stereo frontend alone, `satpose.tools.frontend_score`),
``spin`` (`run_spin` + `satpose.tools.spin_score`) or ``bracket`` (`run_bracket` via
`satpose.tools.bracket_score`). The cluster is
a `LocalCluster` (one single-threaded worker process per core) or an existing scheduler
(``--scheduler tcp://HOST:8786``). Files (renders, run folders) are written on the worker's
file system under DIR, so remote workers need DIR on a shared path; the results row of each
cell is shipped back to the client as data and written to ``DIR/results.parquet``
(atomically, after every cell), with ``DIR/summary.md`` and ``DIR/pos_error.png`` at the end.
A cell already in the table is skipped on a re-run (docs/campaigns.md).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from satpose.datasets.errors import SatposeError
from satpose.datasets.sequence import atomic_write
from satpose.tools.argtypes import positive_int
from satpose.tools.campaign_spec import (
    BracketMember,
    CampaignSpec,
    Cell,
    axis_order,
    is_axis,
    load_spec,
    scenario_hash,
    scenario_of,
)

log = logging.getLogger(__name__)

RESULTS = "results.parquet"
SUMMARY = "summary.md"
PLOT = "pos_error.png"
STATUSES = ("ok", "failed", "timeout")
THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}
"""Set in every LocalCluster worker process before it starts (Dask's nanny
``pre-spawn-environ``): one cell per core, so no library may start its own thread pool."""


class CampaignError(SatposeError):
    """A campaign cannot start or its output folder is unusable."""


class CellTimeout(Exception):
    """A cell exceeded its time limit (raised from the per-frame progress hooks)."""


# --------------------------------------------------------------------------------------------
# On the worker
# --------------------------------------------------------------------------------------------


def _pin_threads() -> None:
    """One thread per library in this process (OpenCV, Dr.Jit/Mitsuba; BLAS via env)."""
    import cv2

    cv2.setNumThreads(1)
    try:
        import drjit

        drjit.set_thread_count(1)
    except (ImportError, AttributeError):  # pragma: no cover - drjit ships with mitsuba
        pass


def _deadline_hook(start: float, limit_s: float, what: str) -> Callable[..., None]:
    def check(*_args: Any) -> None:
        if time.perf_counter() - start > limit_s:
            raise CellTimeout(f"{what} exceeded the time limit of {limit_s:g} s")

    return check


class PeakMemory:
    """The peak resident memory of this process while one task runs [MB].

    A worker runs cells one after another, so the process's own peak (``ru_maxrss``) only
    bounds a cell's from above. On Linux the kernel's high-water mark (``VmHWM`` in
    /proc/self/status) is reset at the start (writing ``5`` to /proc/self/clear_refs) and
    read at the end: the exact peak of this task, at no cost while it runs (the worker has one
    thread, so nothing else runs in the process meanwhile). Where that reset is not possible,
    a thread samples the resident size (psutil) every ``interval_s`` while the task runs: a
    peak shorter than the interval can be missed. ``method`` says which one measured.
    """

    def __init__(self, interval_s: float = 0.02) -> None:
        self.interval_s = interval_s
        self.method = "vmhwm"
        self._peak = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> PeakMemory:
        try:
            self._reset()
        except (OSError, ValueError):
            self.method = "sampled"
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()

    @classmethod
    def _reset(cls) -> None:
        """Reset the kernel's high-water mark to the current resident size (Linux >= 4.0)."""
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        cls._vmhwm()

    @staticmethod
    def _vmhwm() -> int:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
        raise ValueError("no VmHWM line")

    def _sample(self) -> None:
        import psutil

        proc = psutil.Process()
        while True:
            self._peak = max(self._peak, proc.memory_info().rss)
            if self._stop.wait(self.interval_s):
                return

    @property
    def peak_mb(self) -> float:
        """The peak so far [MB] (1 MB = 2^20 bytes)."""
        if self.method == "vmhwm":
            try:
                return self._vmhwm() / 2**20
            except (OSError, ValueError):
                return math.nan
        return self._peak / 2**20


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def render_cached(scenario: Any, folder: str, limit_s: float) -> dict[str, Any]:
    """Render ``scenario`` (a `Scenario`, or a `BracketMember` of the bracket family) into
    ``folder`` unless a complete render is there (the folder name is the scenario's content
    hash). Never raises: returns ``{"path", "render_s", "render_peak_rss_mb", "error",
    "status"}`` so Dask's retry is left for a worker that died."""
    _pin_threads()
    out = Path(folder)
    start = time.perf_counter()
    if (out / "sequence.yaml").is_file():
        return {"path": folder, "render_s": 0.0, "status": "ok", "error": ""}
    check = _deadline_hook(start, limit_s, "render")
    with PeakMemory() as memory:
        try:
            if isinstance(scenario, BracketMember):
                from satpose.datasets.bracket_family import render_bracket_sequence

                render_bracket_sequence(
                    scenario.seed,
                    out,
                    frames=scenario.frames,
                    size=scenario.size,
                    overwrite=True,
                    progress=check,
                )
            else:
                from satpose.datasets.render import render_sequence

                render_sequence(scenario, out, overwrite=True, progress=check)
        except CellTimeout as exc:
            return {"path": folder, "render_s": None, "status": "timeout", "error": str(exc)}
        except Exception as exc:  # a cell's failure, recorded with its message
            return {"path": folder, "render_s": None, "status": "failed", "error": _message(exc)}
    return {
        "path": folder,
        "render_s": time.perf_counter() - start,
        "render_peak_rss_mb": memory.peak_mb,
        "status": "ok",
        "error": "",
    }


def _message(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _column(name: str) -> str:
    return {"online filtered": "online", "per-frame (frontend)": "frontend"}.get(
        name, name.replace(" ", "_")
    )


def metric_columns(results: dict[str, Any], main: str) -> dict[str, Any]:
    """Flatten `evaluate_run`'s metrics into ``{trajectory}.{metric}`` columns (bands as
    ``{trajectory}.band_{label}.{metric}``, bias and the SPEC score as ``{trajectory}.bias.{term}``
    and ``{trajectory}.spec.{term}``); the chosen
    estimator's main trajectory is repeated under the prefix ``est.``."""
    out: dict[str, Any] = {}
    for name, m in results.items():
        plain = asdict(m)
        plain.pop("per_frame", None)
        bands = plain.pop("bands", {})
        nested = {key: plain.pop(key, {}) for key in ("bias", "spec")}
        flat = dict(plain)
        for label, b in bands.items():
            for k, v in b.items():
                flat[f"band_{label.replace(' ', '')}.{k}"] = v
        for key, values in nested.items():
            for k, v in values.items():
                flat[f"{key}.{k}"] = v
        prefixes = [_column(name)] + (["est"] if name == main else [])
        for prefix in prefixes:
            for k, v in flat.items():
                out[f"{prefix}.{k}"] = np.nan if v is None else v
    return out


def run_cell(
    cell: Cell,
    rendered: dict[str, Any] | None,
    out_dir: str,
    limit_s: float,
    order: int = -1,
) -> dict:
    """One cell on a worker: run its pipeline on the (rendered or recorded) sequence and score
    it. Never raises for the cell's own failures: the returned row carries ``status`` and
    ``error``. Files go to ``out_dir/cells/<cell id>/run``; ``order`` is the cell's place in
    the spec (the ``order`` column: benchmarks list their rows in the spec's order)."""
    _pin_threads()
    row: dict[str, Any] = {"cell": cell.cell_id, **cell.axes, "order": order}
    row.update(worker=_worker_name(), render_s=np.nan, run_s=np.nan, eval_s=np.nan)
    t0 = time.perf_counter()
    with PeakMemory() as memory:
        try:
            if rendered is not None:
                row["render_s"] = rendered["render_s"]
                row["render_peak_rss_mb"] = rendered.get("render_peak_rss_mb", np.nan)
                if rendered["status"] != "ok":
                    row.update(status=rendered["status"], error=f"render: {rendered['error']}")
                    return _finish(row, t0, memory)
                sequence = rendered["path"]
            else:
                sequence = "" if cell.sequence is None else str(cell.sequence)
            row["sequence_path"] = sequence
            run = Path(out_dir) / "cells" / cell.cell_id / "run"
            row["run_path"] = str(run)
            check = _deadline_hook(t0, limit_s, "run")
            runner = {
                "stereo": _frontend_cell if cell.axes.get("estimator") == "frontend" else _stereo,
                "spin": _spin_cell,
                "bracket": _bracket_cell,
                "bracket-mc": _bracket_mc_cell,
            }[cell.pipeline]
            row.update(runner(cell, Path(sequence), run, check))
            row.update(status="ok", error="")
        except CellTimeout as exc:
            row.update(status="timeout", error=str(exc))
        except Exception as exc:  # a cell's failure, recorded with its message
            row.update(status="failed", error=_message(exc))
    return _finish(row, t0, memory)


def _renders(cell: Cell) -> bool:
    """Whether the cell needs a rendered sequence (synthetic, and not a simulation)."""
    return cell.sequence is None and cell.pipeline != "bracket-mc"


def _finish(row: dict[str, Any], t0: float, memory: PeakMemory) -> dict[str, Any]:
    row["total_s"] = time.perf_counter() - t0
    row["peak_rss_mb"] = memory.peak_mb
    row["peak_rss_method"] = memory.method
    return row


Check = Callable[..., None]


def _stereo(cell: Cell, sequence: Path, run: Path, check: Check) -> dict[str, Any]:
    """``run_pipeline`` with the cell's estimator, then ``evaluate_run``: every trajectory's
    metrics (`metric_columns`)."""
    from satpose.datasets.config import from_plain
    from satpose.tools.evaluate import evaluate_run, write_metrics
    from satpose.tools.pipeline import PipelineConfig, run_pipeline

    config = from_plain(PipelineConfig, cell.config, "config")
    estimator = cell.axes["estimator"]
    start = time.perf_counter()
    result = run_pipeline(sequence, estimator, run, config, overwrite=True, progress=check)
    row: dict[str, Any] = {"run_s": time.perf_counter() - start}
    row["frames_with_pose"] = sum(m.pose is not None for m in result.measurements)
    check()
    start = time.perf_counter()
    metrics = evaluate_run(sequence, run)
    write_metrics(metrics, run, sequence)
    row["eval_s"] = time.perf_counter() - start
    main = {"online": "online filtered"}.get(estimator, estimator)
    if main not in metrics:
        raise CampaignError(f"{estimator}: no estimate matched the ground truth (< 2 frames)")
    row.update(metric_columns(metrics, main))
    return row


def _frontend_cell(cell: Cell, sequence: Path, run: Path, check: Check) -> dict[str, Any]:
    """The stereo frontend alone (``config.frontend``), scored per frame against the truth
    (`satpose.tools.frontend_score`: ring, pose and timing columns; ``est.pos_cm`` /
    ``est.rot_deg`` are the per-frame pose's mean errors). Writes ``run/measurements.parquet``
    and ``run/score.json``."""
    import json

    from satpose.datasets.config import from_plain, to_plain
    from satpose.datasets.sequence import load_sequence
    from satpose.tools.files import staged_output, write_measurements
    from satpose.tools.frontend_score import (
        pose_stats,
        ring_stats,
        run_frontend,
        score_columns,
        timing_stats,
    )
    from satpose.tools.pipeline import PipelineConfig

    config = from_plain(PipelineConfig, cell.config, "config")
    seq = load_sequence(sequence)
    start = time.perf_counter()
    results, wall, cpu = run_frontend(seq, config.frontend, progress=check)
    row: dict[str, Any] = {"run_s": time.perf_counter() - start}
    start = time.perf_counter()
    score = {
        "ring": ring_stats(seq, results),
        "pose": pose_stats(seq, results),
        "timing": timing_stats(results, wall, cpu),
    }
    with staged_output(run, True, marker="score.json", what="a frontend score") as stage:
        write_measurements(results, stage / "measurements.parquet")
        text = json.dumps(to_plain(score), indent=1, sort_keys=True)
        (stage / "score.json").write_text(text, encoding="utf-8")
    row["eval_s"] = time.perf_counter() - start
    row["frames_with_pose"] = score["pose"]["poses"]
    row["frontend_method"] = str(config.frontend.pose.method)
    row.update(score_columns(score))
    for metric in ("pos_cm", "rot_deg", "rel_pos_cm", "rel_rot_deg"):
        row[f"est.{metric}"] = score["pose"].get(metric, np.nan)
    return row


def _spin_cell(cell: Cell, sequence: Path, run: Path, check: Check) -> dict[str, Any]:
    """`run_spin` with the cell's `SpinConfig`, its windows scored against the true
    ``|omega|`` per frame (`satpose.tools.spin_score`: ``spin.*`` columns)."""
    from satpose.datasets.config import from_plain
    from satpose.datasets.sequence import load_sequence
    from satpose.frontend.spin import SpinConfig
    from satpose.tools.spin_cli import run_spin
    from satpose.tools.spin_score import spin_stats, stats_columns

    config = from_plain(SpinConfig, cell.config, "config")
    start = time.perf_counter()
    result = run_spin(sequence, run, config, overwrite=True, progress=check)
    row: dict[str, Any] = {"run_s": time.perf_counter() - start}
    start = time.perf_counter()
    truth = load_sequence(sequence).truth
    if truth is None or truth.angular_velocity is None:
        raise CampaignError(f"{sequence}: groundtruth.csv has no angular velocity to score")
    truth_deg_s = np.degrees(np.linalg.norm(truth.angular_velocity, axis=1))
    fits = [(k, s.fit) for k, s in enumerate(result.steps) if s.fit is not None]
    stats = spin_stats(fits, truth_deg_s)
    row["eval_s"] = time.perf_counter() - start
    row["spin.truth_deg_s"] = float(np.mean(truth_deg_s))
    row.update(stats_columns(stats))
    return row


def _bracket_cell(cell: Cell, sequence: Path, run: Path, check: Check) -> dict[str, Any]:
    """`run_bracket` (the cell's estimator; ``config``: `StrutDetectorConfig`) on a bracket
    sequence, each frame scored (`satpose.tools.bracket_score`): the whole score as JSON in
    ``bracket.score``, and per-member numbers (``bracket.frames_with_pose``, RMS errors of
    the correctly labelled frames, mislabelled frames) for a quick look."""
    from satpose.datasets.config import from_plain
    from satpose.frontend.bracket_lines import StrutDetectorConfig
    from satpose.tools.bracket_score import score_sequence, score_to_json

    detector = from_plain(StrutDetectorConfig, cell.config, "config")
    start = time.perf_counter()
    score = score_sequence(
        sequence, run, estimator=cell.axes["estimator"], detector=detector, progress=check
    )
    row: dict[str, Any] = {"run_s": time.perf_counter() - start}
    rows = score["rows"]
    good = [r for r in rows if "e_pos_m" in r and not r["mislabelled"]]
    row["frames_with_pose"] = sum("e_pos_m" in r for r in rows)
    row["bracket.frames"] = len(rows)
    row["bracket.mislabelled"] = sum(bool(r.get("mislabelled")) for r in rows)
    row["bracket.ambiguous_exact"] = sum(bool(r["ambiguous_exact"]) for r in rows)
    pos = [float(np.linalg.norm(r["e_pos_m"])) for r in good]
    rot = [float(np.linalg.norm(r["e_rot_deg"])) for r in good]
    row["bracket.pos_rms_mm"] = 1e3 * float(np.sqrt(np.mean(np.square(pos)))) if pos else np.nan
    row["bracket.rot_rms_deg"] = float(np.sqrt(np.mean(np.square(rot)))) if rot else np.nan
    row["est.pos_cm"] = row["bracket.pos_rms_mm"] / 10.0
    row["est.rot_deg"] = row["bracket.rot_rms_deg"]
    row["bracket.score"] = score_to_json(score)
    return row


def _bracket_mc_cell(cell: Cell, sequence: Path, run: Path, check: Check) -> dict[str, Any]:
    """One Monte Carlo run of seed 002's final approach (`run_config` with the cell's seed and
    `MonteCarloConfig`; no files): the whole `RunResult` as JSON in ``mc.result``, the
    resolved config as ``mc.<field>``, and our per-frame solver's RMS errors for a quick
    look. The time limit is checked once the run is done (a run takes about a second)."""
    from dataclasses import asdict

    from satpose.datasets.config import from_plain
    from satpose.tools.bracket_montecarlo import MonteCarloConfig, result_to_json, run_config

    config = from_plain(MonteCarloConfig, cell.config, "config")
    start = time.perf_counter()
    result = run_config(config, int(cell.axes["seed"]))
    check()
    row: dict[str, Any] = {"run_s": time.perf_counter() - start}
    row.update({f"mc.{k}": v for k, v in asdict(config).items()})
    e = result.err["ours per frame"]
    pos = 1e3 * np.linalg.norm(e[:, 3:], axis=1)
    rot = np.degrees(np.linalg.norm(e[:, :3], axis=1))
    row["mc.ours_pos_rms_mm"] = float(np.sqrt(np.nanmean(pos**2)))
    row["mc.ours_rot_rms_deg"] = float(np.sqrt(np.nanmean(rot**2)))
    row["frames_with_pose"] = int(np.isfinite(pos).sum())
    row["mc.result"] = result_to_json(result)
    return row


# --------------------------------------------------------------------------------------------
# On the client
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class CampaignOutcome:
    """What `run_campaign` did: cells in the spec, skipped (already in the table), run now,
    and the status counts of the whole table."""

    cells: int
    skipped: int
    ran: int
    statuses: dict[str, int]
    elapsed_s: float
    table: Path


def read_results(out: Path) -> pd.DataFrame:
    """The results table of a campaign folder (empty if there is none yet)."""
    path = Path(out) / RESULTS
    if not path.is_file():
        return pd.DataFrame()
    try:
        return pd.read_parquet(path)
    except Exception as exc:
        raise CampaignError(f"{path}: cannot read the results table ({_message(exc)})") from None


def _write_table(rows: list[dict[str, Any]], path: Path) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    first = ["cell", *_axes(df), "status", "error"]
    df = df[first + [c for c in df.columns if c not in first]]
    for col in df.columns:  # a column mixing strings and numbers is written as strings
        if df[col].dtype == object:
            kinds = {_kind(v) for v in df[col] if v is not None and v == v}
            if len(kinds) > 1:
                df[col] = df[col].map(lambda v: None if v is None or v != v else str(v))
    atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False))
    return df


def _kind(v: Any) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "bool"
    if isinstance(v, (int, float, np.number)):
        return "number"
    return type(v).__name__


QUIET_WORKER = {
    "distributed.worker.profile.enabled": False,
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.admin.tick.interval": "1s",
}
"""Dask settings for the LocalCluster's workers (passed on by the nanny). Dask's statistical
profiler samples every thread's stack every 10 ms under the GIL, and every process's event loop
wakes every 20 ms (the tick) to watch itself; with one CPU-bound cell per core, these and the
100 ms memory monitor take the core from the cells (docs/results/campaign_scaling.md).
Workers started by hand take the same settings from a Dask config file (docs/campaigns.md)."""


def _client(scheduler: str | None, workers: int | None) -> tuple[Any, Any]:
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        if workers is not None:
            raise CampaignError(
                "--workers sizes the LocalCluster; with --scheduler the cluster has its own"
            )
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError, ValueError) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CampaignError(f"cannot reach the Dask scheduler {scheduler}: {msg}") from None
    n = workers or os.cpu_count() or 1
    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    # None unsets: Dask's MALLOC_TRIM_THRESHOLD_ turns off glibc's dynamic mmap threshold, and
    # every image-sized array is then mmapped and page-faulted anew; that doubled the
    # pipeline's time per cell here (1.8 -> 3.5 s) and slowed renders by a fifth.
    env["MALLOC_TRIM_THRESHOLD_"] = None
    dask.config.set(
        {
            "distributed.nanny.pre-spawn-environ": {**env, **THREAD_ENV},
            # A worker that dies mid-cell: the cell is tried once more, then recorded failed.
            "distributed.scheduler.allowed-failures": 1,
            **QUIET_WORKER,
        }
    )
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",  # a free port: other clusters may hold 8787
        silence_logs=logging.ERROR,
    )
    return Client(cluster), cluster


def run_campaign(
    spec: CampaignSpec,
    out: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    retry_failed: bool = False,
    cache: Path | None = None,
    on_row: Callable[[dict[str, Any], int, int], None] | None = None,
) -> CampaignOutcome:
    """Run the cells of ``spec`` not yet in ``out/results.parquet`` on Dask; write the table
    after each finished cell, then the summary and the plot.

    Args:
        scheduler: address of a running Dask scheduler; None starts a LocalCluster.
        workers: LocalCluster worker processes (default: the number of cores).
        retry_failed: run cells recorded as failed or timeout again.
        cache: folder of the rendered sequences (default ``out/sequences``), keyed by the
            scenario's content hash.
        on_row: called with (row, cells done, cells to do) after each cell.
    """
    from distributed import as_completed

    start = time.perf_counter()
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CampaignError(
            f"{out}: cannot use as campaign folder ({exc.strerror or exc})"
        ) from None
    cache = Path(cache) if cache is not None else out / "sequences"
    old = read_results(out)
    rows: list[dict[str, Any]] = old.to_dict("records") if len(old) else []
    done = {r["cell"] for r in rows if not retry_failed or r.get("status") == "ok"}
    rows = [
        r for r in rows if r["cell"] in done or r["cell"] not in {c.cell_id for c in spec.cells}
    ]
    todo = [c for c in spec.cells if c.cell_id not in done]
    order = {c.cell_id: k for k, c in enumerate(spec.cells)}
    skipped = len(spec.cells) - len(todo)
    table = out / RESULTS
    # Scenarios first, on the client: a perturbation value the scenario refuses fails its
    # cells without a task; the others are grouped by render.
    scenarios: dict[str, Any] = {}
    for cell in list(todo):
        if _renders(cell):
            try:
                scenarios[cell.cell_id] = scenario_of(cell)
            except SatposeError as exc:
                rows.append(
                    {
                        "cell": cell.cell_id,
                        **cell.axes,
                        "order": order[cell.cell_id],
                        "status": "failed",
                        "error": f"perturb: {exc}",
                    }
                )
                todo.remove(cell)
                if on_row is not None:
                    on_row(rows[-1], 0, len(todo))
    if rows:
        _write_table(rows, table)
    if todo:
        client, cluster = _client(scheduler, workers)
        try:
            if importlib.util.find_spec("bokeh") is not None:  # the dashboard needs bokeh
                print(f"Dask dashboard: {client.dashboard_link}", file=sys.stderr)
            limit = spec.time_limit_s
            renders: dict[str, Any] = {}
            futures = []
            outdir = str(out.resolve())
            # Task keys name the output folder too: two campaigns sharing a scheduler must not
            # share each other's results.
            tag = hashlib.sha1(f"{outdir}|{cache.resolve()}".encode()).hexdigest()[:8]
            for cell in todo:
                rendered = None
                if _renders(cell):
                    scenario = scenarios[cell.cell_id]
                    h = scenario_hash(scenario)
                    if h not in renders:
                        folder = str((cache / f"{scenario.name}-{h}").resolve())
                        renders[h] = client.submit(
                            render_cached,
                            scenario,
                            folder,
                            limit,
                            key=f"render-{h}-{tag}",
                            retries=1,
                        )
                    rendered = renders[h]
                futures.append(
                    client.submit(
                        run_cell,
                        cell,
                        rendered,
                        outdir,
                        limit,
                        order[cell.cell_id],
                        key=f"cell-{cell.cell_id}-{tag}",
                        retries=1,
                    )
                )
            by_key = {f.key: c for f, c in zip(futures, todo, strict=True)}
            finished = 0
            for fut in as_completed(futures):
                cell = by_key[fut.key]
                try:
                    row = fut.result()
                except Exception as exc:  # the worker died twice, or the task was lost
                    row = {
                        "cell": cell.cell_id,
                        **cell.axes,
                        "order": order[cell.cell_id],
                        "status": "failed",
                        "error": f"worker: {_message(exc)}",
                    }
                rows.append(row)
                finished += 1
                _write_table(rows, table)
                if on_row is not None:
                    on_row(row, finished, len(todo))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    df = _write_table(rows, table) if rows else pd.DataFrame()
    write_summary(df, out, spec)
    statuses = {s: int((df["status"] == s).sum()) for s in STATUSES} if len(df) else {}
    return CampaignOutcome(
        cells=len(spec.cells),
        skipped=skipped,
        ran=len(todo),
        statuses=statuses,
        elapsed_s=time.perf_counter() - start,
        table=table,
    )


# --------------------------------------------------------------------------------------------
# Summary and plot
# --------------------------------------------------------------------------------------------

SUMMARY_METRICS = {
    "est.pos_cm": "pos [cm]",
    "est.rot_deg": "rot [deg]",
    "est.ate_m": "ATE [m]",
    "est.rpe_trans_m": "RPE [m]",
    "est.nees_in_95": "NEES in 95%",
    "ring.rate": "ring found",
    "spin.ok": "spin ok windows",
    "spin.bias": "spin bias [deg/s]",
    "spin.spread": "spin spread [deg/s]",
    "spin.sigma": "spin sigma [deg/s]",
    "bracket.mislabelled": "mislabelled",
    "mc.ours_pos_rms_mm": "ours pos RMS [mm]",
    "mc.ours_rot_rms_deg": "ours rot RMS [deg]",
    "frames_with_pose": "frames with pose",
    "total_s": "time [s]",
    "peak_rss_mb": "peak RSS [MB]",
}


def _axes(df: pd.DataFrame) -> list[str]:
    """The axis columns of a results table, in their order."""
    return axis_order([c for c in df.columns if is_axis(c)])


def _varying(df: pd.DataFrame) -> list[str]:
    return [a for a in _axes(df) if df[a].astype(str).nunique() > 1]


def write_summary(df: pd.DataFrame, out: Path, spec: CampaignSpec) -> list[Path]:
    """``summary.md`` (status counts, medians per estimator and varying axis, failures) and
    ``pos_error.png``; returns the files written."""
    lines = [f"# Campaign {spec.name}", "", f"Spec: `{spec.path}`; {len(df)} cells in the table."]
    written = []
    if len(df):
        counts = df["status"].value_counts()
        lines += ["", "| status | cells |", "|---|---|"]
        lines += [f"| {s} | {int(counts.get(s, 0))} |" for s in STATUSES]
        ok = df[df["status"] == "ok"]
        group = [a for a in _varying(df) if a != "seed"] or ["pipeline"]
        metrics = [m for m in SUMMARY_METRICS if m in ok.columns]
        if len(ok) and metrics:
            med = ok.groupby(group, dropna=False)[metrics].median(numeric_only=True)
            lines += [
                "",
                f"Medians over the ok cells (across seeds), by {', '.join(group)}:",
                "",
                "| " + " | ".join(group + [SUMMARY_METRICS[m] for m in metrics]) + " |",
                "|" + "---|" * (len(group) + len(metrics)),
            ]
            for key, vals in med.iterrows():
                keys = key if isinstance(key, tuple) else (key,)
                cells = [str(k) for k in keys] + [_fmt(vals[m]) for m in metrics]
                lines.append("| " + " | ".join(cells) + " |")
        bad = df[df["status"] != "ok"]
        if len(bad):
            lines += ["", "Cells not ok:", ""]
            for _, r in bad.iterrows():
                axes = ", ".join(f"{a}={r[a]}" for a in _axes(df))
                lines.append(f"- `{r['cell']}` ({axes}): {r['status']}: {r['error']}")
        png = plot_errors(df, out / PLOT)
        if png is not None:
            written.append(png)
            lines += ["", f"![position error]({PLOT})"]
    path = out / SUMMARY
    text = "\n".join(lines) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    return [path, *written]


def _fmt(v: Any) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3g}"


def _band_label(column: str) -> str:
    return column[len("est.band_") : -len(".pos_cm")]


def _band_top_m(label: str) -> float:
    # "7-5m" -> 7, "<3m" -> 3 (band_label without spaces): the band's far end.
    return float(label.lstrip("<").split("-")[0].rstrip("m"))


def plot_errors(df: pd.DataFrame, path: Path) -> Path | None:
    """Left: mean position error of each cell's estimate against the first varying axis
    (median and range across the other axes) per estimator. Right: its CDF across cells per
    estimator. None when no cell is ok."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    usable = {"est.pos_cm", "estimator"} <= set(df.columns)
    ok = df[(df["status"] == "ok") & df["est.pos_cm"].notna()] if usable else df.iloc[:0]
    if not len(ok):
        return None
    axis = next((a for a in _varying(ok) if a != "estimator"), "estimator")
    bands = [c for c in ok.columns if c.startswith("est.band_") and c.endswith(".pos_cm")]
    fig, axes = plt.subplots(1, 3 if bands else 2, figsize=(16 if bands else 11, 4.2))
    left, right = axes[0], axes[1]
    for est, sub in ok.groupby("estimator"):
        # Numbers sort as numbers (seed 10 after 9), anything else by its text.
        numeric = pd.api.types.is_numeric_dtype(sub[axis])
        g = sub.groupby(sub[axis] if numeric else sub[axis].astype(str))["est.pos_cm"]
        x = list(g.median().index)
        left.plot(x, g.median().to_numpy(), "o-", label=str(est))
        left.fill_between(x, g.min().to_numpy(), g.max().to_numpy(), alpha=0.15)
        v = np.sort(sub["est.pos_cm"].to_numpy(dtype=float))
        frac = np.arange(len(v) + 1) / len(v)
        right.step(np.r_[v[0], v], frac, where="post", label=str(est))
    if bands:
        # Farthest band first (labels "7-5m", "5-3m", "< 3m").
        bands.sort(key=lambda c: -_band_top_m(_band_label(c)))
        names = sorted(ok["estimator"].astype(str).unique())
        width = 0.8 / len(names)
        for i, est in enumerate(names):
            med = ok[ok["estimator"].astype(str) == est][bands].median()
            at = np.arange(len(bands)) + (i - (len(names) - 1) / 2) * width
            axes[2].bar(at, med.to_numpy(dtype=float), width, label=est)
        axes[2].set_xticks(np.arange(len(bands)), [_band_label(b) for b in bands])
        axes[2].set_xlabel("true range band")
        axes[2].set_ylabel("mean position error [cm] (median over cells)")
        axes[2].set_title("position error per range band")
    left.set_xlabel(axis)
    left.set_ylabel("mean position error [cm]")
    left.set_title(f"position error vs {axis} (median, min-max)")
    right.set_xlabel("mean position error [cm]")
    right.set_ylabel("fraction of cells")
    right.set_title("CDF across cells")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(title="estimator")
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def _handler(args: argparse.Namespace) -> None:
    import distributed  # noqa: F401  (creates its loggers, which set their own levels)
    from tqdm import tqdm

    # The in-process scheduler logs every connection at INFO: keep the console to the bar.
    level = max(logging.WARNING, logging.getLogger("satpose").getEffectiveLevel())
    for name in list(logging.root.manager.loggerDict):
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(level)
    spec = load_spec(args.spec)
    table = read_results(args.out)
    print(
        f"campaign {spec.name}: {len(spec.cells)} cells"
        + (f", {len(table)} rows already in {args.out / RESULTS}" if len(table) else ""),
        flush=True,
    )
    bar = tqdm(
        desc=f"campaign {spec.name}", unit="cell", file=sys.stderr, dynamic_ncols=True, delay=1.0
    )

    def on_row(row: dict[str, Any], done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)
        if row.get("status") != "ok":
            bar.write(f"cell {row['cell']}: {row.get('status')}: {row.get('error')}")

    try:
        result = run_campaign(
            spec,
            args.out,
            scheduler=args.scheduler,
            workers=args.workers,
            retry_failed=args.retry_failed,
            cache=args.cache,
            on_row=on_row,
        )
    finally:
        bar.close()
    counts = ", ".join(f"{n} {s}" for s, n in result.statuses.items())
    print(
        f"{result.cells} cells: {result.skipped} already done, {result.ran} run in "
        f"{result.elapsed_s:.1f} s; table: {counts}; wrote {result.table}, "
        f"{args.out / SUMMARY}"
    )


def register(subparsers: Any) -> None:
    """Add ``satpose campaign``."""
    p = subparsers.add_parser(
        "campaign",
        help="Monte Carlo / reprocessing campaign on Dask: the product of a spec's axes",
        description="Run every cell of a campaign spec (render -> run -> eval) on a Dask "
        "cluster and collect one row per cell in DIR/results.parquet, with DIR/summary.md and "
        "a plot. Cells already in the table are skipped (docs/campaigns.md).",
    )
    p.add_argument("spec", type=Path, metavar="SPEC.yaml", help="campaign spec")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="campaign folder")
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="an existing Dask scheduler (DIR must be on a path the workers share)",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        help="LocalCluster worker processes, one thread each (default: the number of cores)",
    )
    p.add_argument(
        "--cache",
        type=Path,
        metavar="DIR",
        help="rendered sequences, by scenario content hash (default: OUT/sequences)",
    )
    p.add_argument(
        "--retry-failed", action="store_true", help="run cells recorded as failed/timeout again"
    )
    p.set_defaults(handler=_handler)
