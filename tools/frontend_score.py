"""The stereo frontend alone against the truth (seed 000): ring detection, per-frame pose and
time per stage.

Used by ``benchmarks/frontend.py`` (docs/results/frontend.md, frontend_variations.md) and by
the campaign's frontend cells (``estimator: frontend``, `satpose.tools.campaign`), which store
the same numbers as columns of the results table (`score_columns`) and give them back
(`score_from_columns`) so that the benchmark builds its table from a campaign.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from satpose.datasets.sequence import Sequence
from satpose.frontend.measurements import FrameMeasurements
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
from satpose.tools.metrics import (
    RANGE_BANDS_M,
    band_label,
    band_mask,
    pose_errors,
    relative_errors,
)

PREFIXES = ("ring", "pose", "timing")
"""The three groups of a score and their column prefixes."""


def run_frontend(
    seq: Sequence,
    config: FrontendConfig,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[FrameMeasurements], list[float], list[float]]:
    """The stereo frontend over the sequence: measurements, wall and CPU time per frame [ms]
    (reading the PNGs is not the frontend's time). ``progress(done, total)`` after each
    frame."""
    fe = StereoFrontend(seq.calibration, config)
    out, wall, cpu = [], [], []
    for frame in seq:
        left, right = frame.left(), frame.right()
        t0, c0 = time.perf_counter(), time.process_time()
        out.append(fe.process(frame.index, frame.t_s, left, right))
        wall.append((time.perf_counter() - t0) * 1000.0)
        cpu.append((time.process_time() - c0) * 1000.0)
        if progress is not None:
            progress(len(out), len(seq))
    return out, wall, cpu


def ring_stats(seq: Sequence, results: list[FrameMeasurements]) -> dict[str, float]:
    """Ring detection rate and the ellipse-centre error against the true outer front edge,
    both cameras [px]; an ellipse more than 2 px off (centre or an axis) is wrong."""
    from satpose.frontend.conics import circle_to_conic, conic_to_ellipse

    calib = seq.calibration
    if seq.truth is None or seq.target is None or seq.target.ring is None:
        raise ValueError(f"{seq.root}: the ring score needs groundtruth.csv and a target ring")
    errs, wrong, found = [], 0, 0
    for i, m in enumerate(results):
        if m.ring is None:
            continue
        found += 1
        T = seq.truth.pose(i)
        for e in m.ring.ellipses:
            cam = calib.camera(e.camera.value)
            cam_from_target = T if e.camera.value == "left" else calib.right_from_left @ T
            true = conic_to_ellipse(
                circle_to_conic(cam.K, cam_from_target, seq.target.ring.radius_m)
            )
            d = float(np.linalg.norm(e.center_px - true.center))
            axes = float(np.abs(e.axes_px - [true.a, true.b]).max())
            errs.append(d)
            wrong += int(d > 2.0 or axes > 2.0)
    e = np.array(errs) if errs else np.array([np.nan])
    return {
        "frames": len(results),
        "found": found,
        "rate": found / len(results),
        "centre_median_px": float(np.median(e)),
        "centre_p95_px": float(np.percentile(e, 95)),
        "wrong_ellipses": wrong,
    }


def pose_stats(seq: Sequence, results: list[FrameMeasurements]) -> dict[str, Any]:
    """Per-frame pose errors (mean, RMS, inter-frame; per range band ``bands``: label ->
    (frames, pos cm, rot deg)) and how many frames each pose method made (``methods``)."""
    if seq.truth is None:
        raise ValueError(f"{seq.root}: the pose score needs groundtruth.csv")
    idx = [i for i, m in enumerate(results) if m.pose is not None]
    est = [results[i].pose.left_cam_from_target for i in idx]
    truth = [seq.truth.pose(i) for i in idx]
    out: dict[str, Any] = {"poses": len(idx), "frames": len(results)}
    if len(idx) < 2:
        return out
    err = pose_errors(est, truth)
    dt, dr = relative_errors(est, truth)
    out.update(
        pos_cm=100 * err.position_m.mean(),
        rot_deg=err.rotation_deg.mean(),
        rot_raw_deg=err.rotation_raw_deg.mean(),
        offset_deg=err.offset_deg,
        rel_pos_cm=100 * dt.mean(),
        rel_rot_deg=dr.mean(),
        rms_pos_cm=100 * np.sqrt(np.mean(err.position_m**2)),
        rms_rot_deg=np.sqrt(np.mean(err.rotation_deg**2)),
    )
    bands = {}
    for band in RANGE_BANDS_M:
        m = band_mask(err.range_m, band)
        if m.any():
            bands[band_label(band)] = (
                int(m.sum()),
                100 * err.position_m[m].mean(),
                err.rotation_deg[m].mean(),
            )
    out["bands"] = bands
    methods: dict[str, int] = {}
    for i in idx:
        method = results[i].pose.method.value
        methods[method] = methods.get(method, 0) + 1
    out["methods"] = methods
    return out


def timing_stats(
    results: list[FrameMeasurements], wall: list[float], cpu: list[float]
) -> dict[str, float]:
    """Median time per stage over the frames where it ran (``<stage>_runs`` of them), and the
    whole frame's wall and CPU time (median, p95) [ms]."""
    stages: dict[str, list[float]] = {}
    for m in results:
        for k, v in m.timings_ms.items():
            stages.setdefault(k, []).append(v)
    out = {k: float(np.median(v)) for k, v in stages.items()}
    out.update({f"{k}_runs": float(len(v)) for k, v in stages.items()})
    out["frames"] = float(len(results))
    out["total_median"] = float(np.median(wall))
    out["total_p95"] = float(np.percentile(wall, 95))
    out["cpu_median"] = float(np.median(cpu))
    out["cpu_p95"] = float(np.percentile(cpu, 95))
    return out


def score_columns(score: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``{"ring": ..., "pose": ..., "timing": ...}`` as flat results-table columns
    (``ring.rate``, ``pose.pos_cm``, ...; the pose's ``bands`` and ``methods`` as JSON text)."""
    out: dict[str, Any] = {}
    for prefix in PREFIXES:
        for k, v in score[prefix].items():
            if isinstance(v, dict):
                v = json.dumps(v, sort_keys=True)
            out[f"{prefix}.{k}"] = v
    return out


def score_from_columns(row: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The inverse of `score_columns` on a results-table row (missing values dropped)."""
    out: dict[str, dict[str, Any]] = {p: {} for p in PREFIXES}
    for col, v in row.items():
        prefix, dot, key = str(col).partition(".")
        if not dot or prefix not in out or v is None or (isinstance(v, float) and v != v):
            continue
        if key in ("bands", "methods"):
            v = {k: tuple(x) if isinstance(x, list) else x for k, x in json.loads(v).items()}
        elif isinstance(v, np.generic):
            v = v.item()
        out[prefix][key] = v
    for k in ("frames", "found", "wrong_ellipses"):
        if k in out["ring"]:
            out["ring"][k] = int(out["ring"][k])
    for k in ("poses", "frames"):
        if k in out["pose"]:
            out["pose"][k] = int(out["pose"][k])
    return out
