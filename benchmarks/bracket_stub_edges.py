"""The two LSD edges of each visible side-strut stub on the bracket family: how far apart in
direction, and whether the short-edge pass pairs them into a bar.

For every frame of the tuning members (datasets/bracket_family.py; rendered into
runs/bench/bracket-family/ if missing), each visible stub (``P1`` or ``P2`` to its visible
end) is projected with the true pose. Among the LSD segments `satpose bracket` finds
(`line_segments`), those inside the stub's band (both ends within half its true silhouette
width + 3 px of the projected axis, within 20 deg of its direction, along it between -0.3 and
1.3 of its length) are split by side: *exterior* (away from the other base vertex) and
*interior*; the longest on each side is that edge. For a stub with both edges: their angle,
the shorter one's length ``l``, their separation ``sep`` and the *end offset* ``l tan(angle)``
over ``sep``. Where a stub leaves the base its interior edge starts in the concave corner and
leans toward the base; close up the silhouette edges also converge. The pass that pairs such
edges (`_parallel_pairs` with ``short_edge_px`` and ``short_taper``) is run on each found pair
with several ``short_taper`` values: how many stubs each would leave without a bar. Writes
docs/results/bracket_stub_edges.md (docs/bracket.md, "Short stubs").

Only tuning seeds: this is where ``short_taper`` was chosen. Usage::

    python benchmarks/bracket_stub_edges.py [--seeds 0-75]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import BracketMember, bracket_members, machine_summary, tuning_seeds, write_page

from satpose.frontend.bracket import project
from satpose.frontend.bracket_lines import (
    StrutDetectorConfig,
    _parallel_pairs,
    line_segments,
    silhouette_width_px,
)

TAPERS = (0.0, 0.3, 0.4, 0.5, 0.6)


def stub_edges(m: BracketMember, cfg: StrutDetectorConfig) -> list[tuple[float, ...]]:
    """Per visible stub and frame of one member: the number of edges found (0-2),
    true width px, angle deg, shorter length px, separation px, then 1/0 per ``TAPERS``
    (paired by the short-edge pass), NaN where fewer than two edges were found."""
    seq, V, pts, r = m.seq, m.vertices, m.points, m.radius_m
    assert seq.truth is not None
    cam = seq.calibration.left
    rows: list[tuple[float, ...]] = []
    for fr in seq.frames:
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        seg = line_segments(m.undistort(fr.image("left")).gray8, cfg)
        if len(seg) == 0:
            continue
        px = project(T, pts, cam.K)
        length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        du = (seg[:, 2:] - seg[:, :2]) / length[:, None]
        for start, end, other in ((0, 2, 1), (1, 3, 0)):  # the stubs from P1 and P2
            a, e = px[start], px[end]
            L = float(np.linalg.norm(e - a))
            if not L > 1.0:
                continue
            u = (e - a) / L
            n = np.array([-u[1], u[0]])
            inward = 1.0 if float((px[other] - a) @ n) > 0 else -1.0
            w = silhouette_width_px(
                0.5 * (a + e), T.apply(V[start][None])[0], T.rotate(V[2] - V[start]), r, cam.K
            )
            t0, t1 = (seg[:, :2] - a) @ n * inward, (seg[:, 2:] - a) @ n * inward
            s0, s1 = (seg[:, :2] - a) @ u, (seg[:, 2:] - a) @ u
            band = (
                (np.maximum(np.abs(t0), np.abs(t1)) < 0.5 * w + 3.0)
                & (np.minimum(s0, s1) > -0.3 * L)
                & (np.maximum(s0, s1) < 1.3 * L)
                & (np.abs(du @ u) > math.cos(math.radians(20.0)))
            )
            mid = 0.5 * (t0 + t1)
            found = []  # the longest segment on the exterior and on the interior side
            for side in (-1.0, 1.0):
                idx = np.where(band & (np.sign(mid) == side) & (np.abs(mid) > 1.5))[0]
                if len(idx):
                    found.append(int(idx[np.argmax(length[idx])]))
            if len(found) < 2:
                rows.append((len(found), w, *[math.nan] * (3 + len(TAPERS))))
                continue
            i, j = sorted(found)  # segment order, as `_bars` pairs them
            ang = math.degrees(math.acos(min(1.0, abs(float(du[i] @ du[j])))))
            sep = abs(float((0.5 * (seg[j, :2] + seg[j, 2:]) - seg[i, :2]) @ [-du[i, 1], du[i, 0]]))
            p, q = seg[[i, j], :2], seg[[i, j], 2:]
            pairs = [
                _parallel_pairs(p, q, du[[i, j]], length[[i, j]], cfg, cfg.short_edge_px, t)
                for t in TAPERS
            ]
            paired = [1.0 if pr else 0.0 for pr in pairs]
            rows.append((2, w, ang, float(min(length[i], length[j])), sep, *paired))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=tuning_seeds, default=tuning_seeds("0-75"))
    ap.add_argument("--root", type=Path, default=Path("runs/bench/bracket-family"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/bracket_stub_edges.md"))
    args = ap.parse_args(argv)
    cfg = StrutDetectorConfig()
    rows: list[tuple[float, ...]] = []
    for seed, member in bracket_members(args.seeds, args.root):
        rows += stub_edges(member, cfg)
        print(seed, len(rows), flush=True)
    R = np.array(rows, dtype=float)
    both = R[R[:, 0] == 2]
    ang, short, sep = both[:, 2], both[:, 3], both[:, 4]
    ratio = short * np.tan(np.radians(ang)) / sep
    long_from = cfg.short_edge_px / math.tan(math.radians(cfg.max_angle_deg))
    lines = [
        "# Side-strut stubs: their two edges' angle, and the short-edge pass",
        "",
        f"Generated by `python benchmarks/bracket_stub_edges.py --seeds {args.seeds[0]}-"
        f"{args.seeds[-1]}` ({machine_summary(libraries=False)}; never hand-edited). Tuning "
        "members, 12 frames each at 960x768; each visible stub's LSD edges found in its band "
        "around the true projected axis (exterior and interior side, the longest on each). "
        "*End offset* = shorter edge length x tan(angle between the edges), over their "
        "separation.",
        "",
        f"Stubs: {len(R)}; both edges found: {len(both)}; one: {int(np.sum(R[:, 0] == 1))}; "
        f"none: {int(np.sum(R[:, 0] == 0))}.",
        "",
        "| edges | n | angle deg: median | 95 % | 99 % | max | end offset / sep: median | 95 % "
        "| 99 % | max |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, m in (
        (f"shorter < {long_from:.0f} px", short < long_from),
        (f"shorter >= {long_from:.0f} px", short >= long_from),
        ("all", np.ones(len(both), bool)),
    ):
        if not m.any():
            continue
        a, q = ang[m], ratio[m]
        lines.append(
            f"| {label} | {int(m.sum())} | {np.median(a):.2f} | {np.percentile(a, 95):.2f} | "
            f"{np.percentile(a, 99):.2f} | {a.max():.2f} | {np.median(q):.2f} | "
            f"{np.percentile(q, 95):.2f} | {np.percentile(q, 99):.2f} | {q.max():.2f} |"
        )
    lines += [
        "",
        f"Stubs with both edges that the short-edge pass leaves unpaired (`short_edge_px` = "
        f"{cfg.short_edge_px:g}, `max_angle_deg` = {cfg.max_angle_deg:g}; the pass also needs "
        "the separation within `bar_width_px` and an overlap of half the shorter edge):",
        "",
        "| short_taper | unpaired | of |",
        "|---|---|---|",
    ]
    for k, t in enumerate(TAPERS):
        unpaired = int(np.sum(both[:, 5 + k] == 0))
        mark = " (default)" if t == cfg.short_taper else ""
        lines.append(f"| {t:g}{mark} | {unpaired} | {len(both)} |")
    write_page(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
