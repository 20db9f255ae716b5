"""How well the struts' taper is measured on the bracket family: measured against true.

For every frame of the tuning members (datasets/bracket_family.py; rendered into
runs/bench/bracket-family/ if missing), the strut candidates `satpose bracket` would search
(`partial_candidates` without and with the silhouette refit) are matched to the true struts
(the candidate with the longest support whose centre line lies within 3 px and 2 deg of the
projected true axis: the base ``P1P2`` and the visible stubs), their taper is measured
(`measure_taper`) and compared with what the true pose predicts over the same span
(`predicted_taper`, the exact silhouette widths). Writes docs/results/bracket_taper.md: the
error by strut width (median and 90th / 95th percentile of its size, mean, robust spread,
and the median ratio measured / true where the true taper exceeds 0.05: below 1 the
measurement compresses it), and, for the struts that `_verify` weighs (at least
``taper_min_width_px`` wide), the errors over their stated sigma with the noise floor
``taper_floor`` (and neighbouring floors): what sets the floor and the Huber threshold
(docs/bracket.md, "Strut taper").

Only tuning seeds: this is where the floor was chosen. Usage::

    python benchmarks/bracket_taper.py [--seeds 0-35]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine_summary, write_page

from satpose.datasets.bracket_family import measured_points_b, render_bracket_sequence
from satpose.datasets.seed_split import TUNING_SEEDS
from satpose.datasets.sequence import load_sequence
from satpose.frontend.bracket import project
from satpose.frontend.bracket_lines import (
    StrutDetectorConfig,
    _angle_between,
    partial_candidates,
    predicted_taper,
    silhouette_candidates,
)
from satpose.frontend.preprocess import Undistorter

WIDTH_BINS = ((0, 6), (6, 8), (8, 10), (10, 13), (13, 17), (17, 25), (25, 1e9))


def seeds_arg(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def measure(seq_path: Path) -> list[tuple[float, ...]]:
    """(refit 0/1, strut 0-2, width px, measured, true, stated sigma) per matched strut and
    frame of one member."""
    seq = load_sequence(seq_path)
    assert seq.target is not None and seq.target.bracket is not None and seq.truth is not None
    b = seq.target.bracket
    V = np.array([b.P1, b.P2, b.P5])
    cam = seq.calibration.left
    und = Undistorter(cam)
    r = float(seq.target.extras["bracket_strut_width_m"]) / 2
    cfg = StrutDetectorConfig(strut_radius_m=r)
    pts = measured_points_b(V, b.visible_fraction)  # P1, P2, stub end from P1, from P2
    axes = ((V[0], V[1]), (V[0], V[2]), (V[1], V[2]))
    spans = ((0, 1), (0, 2), (1, 3))
    rows: list[tuple[float, ...]] = []
    for fr in seq.frames:
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        prep = und(fr.image("left"))
        raw = partial_candidates(prep.gray8, cfg, silhouette=False)
        if not isinstance(raw, tuple):
            continue
        px = project(T, pts, cam.K)
        for refit, (_, cands) in ((0, raw), (1, silhouette_candidates(prep.gray8, raw, cfg))):
            for k, (ia, ib) in enumerate(spans):
                a, e = px[ia], px[ib]
                u = (e - a) / np.linalg.norm(e - a)
                n = np.array([-u[1], u[0]])
                near = [
                    c
                    for c in cands
                    if _angle_between(c.direction, u) <= 2.0 and abs(float((c.point - a) @ n)) <= 3
                ]
                if not near:
                    continue
                st = max(near, key=lambda c: c.support_px)
                if not math.isfinite(st.taper):
                    continue
                true = predicted_taper(st, T, axes[k], cam.K, r)
                if math.isfinite(true):
                    rows.append((refit, k, st.width_px, st.taper, true, st.taper_sigma))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-35"))
    ap.add_argument("--root", type=Path, default=Path("runs/bench/bracket-family"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/bracket_taper.md"))
    args = ap.parse_args(argv)
    bad = [s for s in args.seeds if s not in TUNING_SEEDS]
    if bad:
        raise SystemExit(f"--seeds: only tuning seeds may be looked at here, not {bad}")
    rows: list[tuple[float, ...]] = []
    for seed in args.seeds:
        seq = args.root / f"seed-{seed}"
        if not (seq / "frames.csv").is_file():
            print(f"rendering seed {seed}", flush=True)
            render_bracket_sequence(seed, seq, frames=12, size=(960, 768), overwrite=True)
        rows += measure(seq)
        print(seed, len(rows), flush=True)
    R = np.array(rows, dtype=float)
    cfg = StrutDetectorConfig()
    lines = [
        "# Strut taper: measured against true on the bracket family",
        "",
        f"Generated by `python benchmarks/bracket_taper.py --seeds {args.seeds[0]}-"
        f"{args.seeds[-1]}` ({machine_summary(libraries=False)}; never hand-edited). Tuning "
        f"members, 12 frames each at 960x768; every strut candidate matched to a true strut "
        "(base, stub from P1, stub from P2), its taper (`measure_taper`: log ratio of the "
        "image widths at the two ends of its measured span) against the true pose's "
        "(`predicted_taper`, exact silhouette widths). *error* = measured - true.",
        "",
    ]
    for refit, title in ((0, "bars as found"), (1, "after the silhouette refit")):
        S = R[R[:, 0] == refit]
        lines += [
            f"## Candidates {title} ({len(S)} strut measurements)",
            "",
            "| width px | n | median abs error | 90 % | 95 % | mean | robust sd "
            "| measured / true (true > 0.05) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for lo, hi in WIDTH_BINS:
            m = (S[:, 2] >= lo) & (S[:, 2] < hi)
            if not m.any():
                continue
            d = S[m, 3] - S[m, 4]
            big = m & (np.abs(S[:, 4]) > 0.05)
            ratio = float(np.median(S[big, 3] / S[big, 4])) if big.any() else math.nan
            label = f"{lo}-{hi:.0f}" if hi < 1e9 else f">= {lo}"
            lines.append(
                f"| {label} | {int(m.sum())} | {np.median(np.abs(d)):.3f} | "
                f"{np.percentile(np.abs(d), 90):.3f} | {np.percentile(np.abs(d), 95):.3f} | "
                f"{d.mean():+.3f} | {1.4826 * np.median(np.abs(d - np.median(d))):.3f} | "
                f"{ratio:.2f} |"
            )
        lines.append("")
    S = R[(R[:, 0] == 1) & (R[:, 2] >= cfg.taper_min_width_px)]
    d = S[:, 3] - S[:, 4]
    lines += [
        f"## The weighed struts (after the refit, >= {cfg.taper_min_width_px:g} px wide: "
        f"{len(S)}): error over hypot(stated sigma, floor)",
        "",
        f"Median stated sigma (the fit's own): {np.median(S[:, 5]):.4f}. The default floor "
        f"is `taper_floor` = {cfg.taper_floor:g}; beyond 2 sigmas the misfit costs linearly "
        "(Huber): the tails below are heavier than a Gaussian's (4.6 % beyond 2, 0.27 % "
        "beyond 3).",
        "",
        "| floor | rms | robust sd | beyond 2 | beyond 3 |",
        "|---|---|---|---|---|",
    ]
    for fl in sorted({0.015, 0.02, 0.025, 0.03, 0.04, cfg.taper_floor}):
        z = d / np.hypot(S[:, 5], fl)
        lines.append(
            f"| {fl:g}{' (default)' if fl == cfg.taper_floor else ''} | "
            f"{np.sqrt(np.mean(z**2)):.2f} | {1.4826 * np.median(np.abs(z)):.2f} | "
            f"{np.mean(np.abs(z) > 2):.1%} | {np.mean(np.abs(z) > 3):.1%} |"
        )
    write_page(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
