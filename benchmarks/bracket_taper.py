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
measurement compresses it), and, by strut width, the errors over the sigma they are
weighed with (`taper_noise`: the stated sigma and the width's noise floor, ``taper_floor``
and ``taper_floor_px2``) against alternative floors: what sets the floor, the cap
``max_taper_chi`` and ``taper_min_width_px`` (docs/bracket.md, "Strut taper").

Only tuning seeds: this is where the floor was chosen. Usage::

    python benchmarks/bracket_taper.py [--seeds 0-99]
"""

from __future__ import annotations

import argparse
import math
import sys
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import (
    BracketMember,
    bracket_members,
    machine_summary,
    rows_by_member,
    tuning_seeds,
    write_page,
)

from satpose.backend.labelling import LabellingConfig
from satpose.frontend.bracket import project
from satpose.frontend.bracket_lines import (
    StrutDetectorConfig,
    _angle_between,
    partial_candidates,
    predicted_taper,
    silhouette_candidates,
)

WIDTH_BINS = ((0, 6), (6, 8), (8, 10), (10, 13), (13, 17), (17, 25), (25, 1e9))


def measure(m: BracketMember) -> list[tuple[float, ...]]:
    """(refit 0/1, strut 0-2, width px, measured, true, stated sigma) per matched strut and
    frame of one member."""
    seq, V, pts, r = m.seq, m.vertices, m.points, m.radius_m
    assert seq.truth is not None
    cam = seq.calibration.left
    cfg = StrutDetectorConfig(strut_radius_m=r)
    axes = ((V[0], V[1]), (V[0], V[2]), (V[1], V[2]))
    spans = ((0, 1), (0, 2), (1, 3))
    rows: list[tuple[float, ...]] = []
    for fr in seq.frames:
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        prep = m.undistort(fr.image("left"))
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


# the narrow-strut setting the shared bias was measured in: ``taper_floor_px2`` 2.5 px^2 and
# struts from 6 px (docs/bracket.md, "Narrow struts' tapers and a bias their frames share")
NARROW_FLOOR_PX2, NARROW_MIN_WIDTH_PX = 2.5, 6.0


def shared_section(S: np.ndarray, cfg: StrutDetectorConfig) -> list[str]:
    """How much of the struts' error (rows ``S`` after the refit, at least
    ``NARROW_MIN_WIDTH_PX`` wide, over the sigma with the ``NARROW_FLOOR_PX2`` floor) one
    strut of one member shares over its frames: one-way analysis of variance over the groups
    (member, strut) with at least 3 frames. What ``LabellingConfig.shared_variance`` 0.5
    comes from."""
    S = S[S[:, 2] >= NARROW_MIN_WIDTH_PX]
    floor = np.maximum(cfg.taper_floor, NARROW_FLOOR_PX2 / S[:, 2] ** 2)
    z = (S[:, 3] - S[:, 4]) / np.hypot(S[:, 5], floor)
    keys = S[:, 6] * 10 + S[:, 1]
    groups = [z[keys == k] for k in np.unique(keys)]
    groups = [g for g in groups if len(g) >= 3]
    n = np.array([len(g) for g in groups], dtype=float)
    within = float(sum(((g - g.mean()) ** 2).sum() for g in groups) / (n.sum() - len(groups)))
    means = np.array([g.mean() for g in groups])
    between = float(means.var(ddof=1) - within * np.mean(1.0 / n))
    return [
        "",
        "## What a strut's frames share",
        "",
        f"The errors of the struts at least {NARROW_MIN_WIDTH_PX:g} px wide over their sigma "
        f"with the floor max({cfg.taper_floor:g}, {NARROW_FLOOR_PX2:g} / w^2), grouped by "
        "member and strut "
        f"({len(groups)} groups of at least 3 frames, median {np.median(n):.0f} frames; "
        "one-way analysis of variance): the variance *within* a group (from frame to frame) "
        "and *between* groups (a bias the strut shows in every frame of its member), and "
        "their ratio to the total (intraclass correlation). `LabellingConfig.shared_variance` "
        "fits a track's tapers with a bias per strut of that variance on top of each frame's "
        f"unit variance (default {LabellingConfig().shared_variance:g}: frames independent; "
        'docs/bracket.md, "Narrow struts\' tapers and a bias their frames share").',
        "",
        "| within | between | intraclass correlation | sd of the group means (independent frames: "
        "sqrt(mean 1/n)) |",
        "|---|---|---|---|",
        f"| {within:.2f} | {between:.2f} | {between / (between + within):.2f} | "
        f"{means.std(ddof=1):.2f} ({np.sqrt(np.mean(1.0 / n)):.2f}) |",
    ]


def seed_rows(seed: int, root: Path) -> list[tuple[float, ...]]:
    """`measure` of the member ``seed`` under ``root`` (rendered there if missing), each row
    with the seed appended."""
    return [(*row, float(seed)) for _, m in bracket_members([seed], root) for row in measure(m)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=tuning_seeds, default=tuning_seeds("0-99"))
    ap.add_argument("--root", type=Path, default=Path("runs/bench/bracket-family"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/bracket_taper.md"))
    ap.add_argument(
        "--jobs", type=int, default=1, help="members measured at once, each in its own process"
    )
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: must be >= 1")
    rows: list[tuple[float, ...]] = rows_by_member(
        partial(seed_rows, root=args.root), args.seeds, args.jobs
    )
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
    S = R[R[:, 0] == 1]
    lines += [
        "## The errors over the weighed sigma (after the refit), by strut width",
        "",
        f"Weighed sigma: the stated one (the fit's own, `measure_taper`; median "
        f"{np.median(S[:, 5]):.4f}) and the floor of the strut's width `w` in quadrature "
        f"(`taper_noise`): max(`taper_floor` = {cfg.taper_floor:g}, `taper_floor_px2` / w^2 "
        f"= {cfg.taper_floor_px2:g} / w^2). Struts under `taper_min_width_px` = "
        f"{cfg.taper_min_width_px:g} px are not weighed (shown for reference). A misfit counts "
        f"as at most `max_taper_chi` = {cfg.max_taper_chi:g} sigmas (a truncated square). "
        "Each cell: rms / beyond 2 sigmas / beyond 3 sigmas (a Gaussian: 1 / 4.6 % / 0.27 %); "
        "the other columns are the alternatives the default was chosen against.",
        "",
    ]
    laws = [(cfg.taper_floor, cfg.taper_floor_px2, "default")]
    laws += [
        (cfg.taper_floor, c, f"{c:g} / w^2") for c in (2.0, 2.5, 3.0) if c != cfg.taper_floor_px2
    ]
    laws += [(0.04, 0.0, "constant 0.04")]
    lines += [
        "| width px | n | " + " | ".join(name for *_, name in laws) + " |",
        "|---|---|" + "---|" * len(laws),
    ]
    bands = ((5, 6), (6, 7), (7, 8), (8, 9), (9, 10), (10, 13), (13, 17), (17, 1e9))
    for lo, hi in [*bands, (cfg.taper_min_width_px, 1e9)]:
        m = (S[:, 2] >= lo) & (S[:, 2] < hi)
        if not m.any():
            continue
        d, sig, w = S[m, 3] - S[m, 4], S[m, 5], S[m, 2]
        cells = []
        for f0, c, _ in laws:
            z = d / np.hypot(sig, np.maximum(f0, c / w**2))
            cells.append(
                f"{np.sqrt(np.mean(z**2)):.2f} / {np.mean(np.abs(z) > 2):.1%} / "
                f"{np.mean(np.abs(z) > 3):.1%}"
            )
        label = f"{lo:g}-{hi:g}" if hi < 1e9 else f">= {lo:g}"
        if (lo, hi) == (cfg.taper_min_width_px, 1e9):
            label = f"**all weighed (>= {lo:g})**"
        lines.append(f"| {label} | {int(m.sum())} | " + " | ".join(cells) + " |")
    lines += shared_section(S, cfg)
    write_page(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
