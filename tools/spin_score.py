"""The spin-rate estimates of a sequence against its truth (seed 001, issue 19).

Used by ``benchmarks/spin_fold.py`` (docs/results/spin_fold.md) and by the campaign's spin
cells (``pipeline: spin``, `satpose.tools.campaign`), which store a `SpinStats` as columns of
the results table (`stats_columns`) and give it back (`stats_from_columns`) so that the
benchmark builds its table from a campaign.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from satpose.frontend.spin import SpinFit

WRONG_DEG_S = 1.0
"""An accepted rate this far from the truth [deg/s] took the wrong fold."""
PREFIX = "spin"


@dataclass
class SpinStats:
    """The estimates of one sequence (sliding windows) against the truth.

    Attributes:
        windows: estimates (one per frame once the buffer is full).
        status: windows per status (``ok``, ``ambiguous``, refusals).
        bias, spread: mean and std of the ok windows' error [deg/s] (wrong folds excluded).
        spread_disjoint: std over disjoint ok windows [deg/s].
        sigma: median stated sigma of the ok windows [deg/s].
        rms_z, rms_z_disjoint: RMS of error / sigma (all, disjoint ok windows).
        disjoint: how many disjoint ok windows.
        wrong: ok windows more than `WRONG_DEG_S` off.
        truth_in_candidates: ambiguous windows listing the truth (within 4 sigma + 0.05).
        z_disjoint: error / sigma of the disjoint ok windows.
        first_reason: `reason_kind` -> the first reason of that kind.
    """

    windows: int
    status: Counter[str]
    bias: float
    spread: float
    spread_disjoint: float
    sigma: float
    rms_z: float
    rms_z_disjoint: float
    disjoint: int
    wrong: int
    truth_in_candidates: int
    z_disjoint: list[float]
    first_reason: dict[str, str]


def reason_kind(f: SpinFit) -> str:
    """The status and the reason's wording without its numbers (``too-slow`` has two: theta'
    too slow, and an asymmetric outline's full-turn wobble too slow)."""
    return f"{f.status.value}: {re.sub(r'[-+]?[0-9][0-9.]*', '#', f.reason)[:50]}"


def spin_stats(fits: list[tuple[int, SpinFit]], truth_deg_s: np.ndarray) -> SpinStats:
    """Score ``fits`` (frame index into ``truth_deg_s``, the window's estimate) against the
    true ``|omega|`` per frame [deg/s]."""
    status = Counter(f.status.value for _, f in fits)
    ok = [(k, f) for k, f in fits if f.ok]
    err = np.array([math.degrees(f.rate_rad_s) - truth_deg_s[k] for k, f in ok])
    sig = np.array([math.degrees(f.sigma_rad_s) for _, f in ok])
    right = np.abs(err) <= WRONG_DEG_S
    # disjoint windows among the accepted, right ones: the next one starts after this one ends
    disjoint, until = [], -math.inf
    for i, (_, f) in enumerate(ok):
        if right[i] and f.window_start_s > until:
            disjoint.append(i)
            until = f.window_end_s
    e, s = err[right], sig[right]
    ed, sd = err[disjoint], sig[disjoint]
    truth_in = 0
    for k, f in fits:
        if f.status.value == "ambiguous":
            c = np.degrees(f.candidates_rad_s)
            tol = 4.0 * math.degrees(f.sigma_rad_s) + 0.05
            truth_in += bool(np.any(np.abs(c - truth_deg_s[k]) < tol))
    reasons: dict[str, str] = {}
    for _, f in fits:
        if not f.ok:
            reasons.setdefault(reason_kind(f), f.reason)
    nan = math.nan
    return SpinStats(
        windows=len(fits),
        status=status,
        bias=float(e.mean()) if e.size else nan,
        spread=float(e.std(ddof=1)) if e.size > 1 else nan,
        spread_disjoint=float(ed.std(ddof=1)) if ed.size > 1 else nan,
        sigma=float(np.median(s)) if s.size else nan,
        rms_z=float(np.sqrt(np.mean((e / s) ** 2))) if e.size else nan,
        rms_z_disjoint=float(np.sqrt(np.mean((ed / sd) ** 2))) if ed.size else nan,
        disjoint=int(ed.size),
        wrong=int((~right).sum()),
        truth_in_candidates=truth_in,
        z_disjoint=[float(z) for z in ed / sd],
        first_reason=reasons,
    )


_JSON = ("status", "z_disjoint", "first_reason")


def stats_columns(stats: SpinStats) -> dict[str, Any]:
    """A `SpinStats` as flat results-table columns ``spin.<field>`` (the counts, list and
    reasons as JSON text), plus ``spin.ok`` / ``spin.ambiguous`` counts for quick looks."""
    out: dict[str, Any] = {}
    for f in fields(SpinStats):
        v = getattr(stats, f.name)
        out[f"{PREFIX}.{f.name}"] = json.dumps(v) if f.name in _JSON else v
    out[f"{PREFIX}.ok"] = stats.status["ok"]
    out[f"{PREFIX}.ambiguous"] = stats.status["ambiguous"]
    return out


def stats_from_columns(row: dict[str, Any]) -> SpinStats:
    """The inverse of `stats_columns` on a results-table row."""
    kw: dict[str, Any] = {}
    for f in fields(SpinStats):
        v = row[f"{PREFIX}.{f.name}"]
        if f.name in _JSON:
            v = json.loads(v)
        elif isinstance(v, np.generic):
            v = v.item()
        kw[f.name] = v
    kw["status"] = Counter(kw["status"])
    for k in ("windows", "disjoint", "wrong", "truth_in_candidates"):
        kw[k] = int(kw[k])
    return SpinStats(**kw)
