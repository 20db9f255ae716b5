"""Ring measurement variants on the random family: where the ring's 3-D centre is biased.

    python benchmarks/ring_wall.py --set tuning --count 7 --frames 10 --size 640x480 --spp 8

Per seed and frontend variant, the per-frame ring centre error split into depth (along the
line of sight; mean = bias, and its sd) and lateral (mean norm), and the radius bias, against
groundtruth.csv. Only the ring stage matters here, so the frontend runs alone (no smoother).
Variants (`satpose.frontend.pipeline.FrontendConfig`):

- ``all edges``: the default: the 3-D circle fitted to every edge near the ring's ellipses.
- ``outline``: `satpose.frontend.ring_outline` (``outline.enabled``): the edges fitted as the
  outline of a cylinder (front rim + base, the wall height free), the rim reported.
- ``rim only``: `satpose.frontend.rim` (``rim.enabled``): refitted on the samples where the
  wall's outer face is turned away from each camera.
- ``dark band``: the ring's edges re-located by moments where a thin dark band follows them
  (``ring.edges.dark_band``, `satpose.frontend.edges`).
- ``known radius``: ``stereo_ring.known_ring`` with the true outer radius, sigma 1 mm.
- ``known + rim only``: both.
- ``known + outline``: the known radius with the outline model (the wall height free).
- ``known radius+height``: the known radius, wall height and lip: the outline modelled as
  that cylinder, edges nearer the rim's image taken as the rim (`KnownRing`).
- ``known ring``: and the rim's inner radius (its inner edge where the wall shows).

Renders are shared with benchmarks/random_family.py (same cache names under ``--root``).
Validation seeds are only scored: never change a parameter because of what they show.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)

from satpose.datasets.geometry import Rigid3
from satpose.datasets.random_family import random_draw
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import scaled
from satpose.datasets.seed_split import TUNING_SEEDS, VALIDATION_SEEDS
from satpose.datasets.sequence import Ring, load_sequence
from satpose.frontend.conics import circle_to_conic, sampson_distance
from satpose.frontend.measurements import FrameMeasurements
from satpose.frontend.pipeline import FrontendConfig, KnownRing, StereoFrontend
from satpose.frontend.rim import rim_labels
from satpose.frontend.stereo import Circle3D, StereoRig

VARIANTS = (
    "all edges",
    "outline",
    "rim only",
    "dark band",
    "known radius",
    "known + rim only",
    "known + outline",
    "known radius+height",
    "known ring",
)


def config(variant: str, ring: Ring) -> FrontendConfig:
    """The frontend of ``variant``; the ``known`` variants state the true ``ring`` as a user
    of a standard interface would: its outer radius (1 mm), with ``known radius+height`` its
    wall height and lip, with ``known ring`` its inner radius too."""
    c = FrontendConfig()
    c = replace(c, rim=replace(c.rim, enabled="rim only" in variant))
    c = replace(c, outline=replace(c.outline, enabled="outline" in variant))
    if variant == "dark band":
        c = replace(c, ring=replace(c.ring, edges=replace(c.ring.edges, dark_band=True)))
    if variant.startswith("known"):
        ex = ring.extras
        full = variant in ("known radius+height", "known ring")
        known = KnownRing(
            outer_radius_m=ring.radius_m,
            radius_sigma_m=0.001,
            wall_height_m=float(ex["height_m"]) if full else None,
            inner_radius_m=float(ex["inner_radius_m"]) if variant == "known ring" else None,
            wall_outer_radius_m=ex.get("wall_outer_radius_m") if full else None,
            lip_thickness_m=float(ex.get("lip_thickness_m", 0.0)) if full else 0.0,
        )
        c = replace(c, stereo_ring=replace(c.stereo_ring, known_ring=known))
    return c


def edge_sides(m: FrameMeasurements, truth: Rigid3, radius: float, rig: StereoRig) -> dict:  # type: ignore[type-arg]
    """Signed distances [px] (> 0 outside) of the ring's edge points to the true rim's image,
    per camera, split by where the wall's outer face is hidden from that camera (``hidden``)
    or visible beside the rim (``visible``), by the true circle (`rim_labels`)."""
    assert m.ring is not None
    normal = truth.R[:, 2] if truth.R[:, 2] @ truth.t < 0 else -truth.R[:, 2]
    circle = Circle3D(center=truth.t, normal=normal, radius=radius, covariance=np.eye(7))
    P, hidden_l, hidden_r = rim_labels(circle, rig, 720, 0.0)
    proj_l, proj_r = rig.project(P)
    out = {}
    for e, K, T, hidden, proj in (
        (m.ring.ellipses[0], rig.K_left, Rigid3.identity(), hidden_l, proj_l),
        (m.ring.ellipses[1], rig.K_right, rig.right_from_left, hidden_r, proj_r),
    ):
        pts = e.edge_points_px
        d = sampson_distance(pts, circle_to_conic(K, T @ truth, radius))
        nearest = np.argmin(((pts[:, None, :] - proj[None]) ** 2).sum(-1), axis=1)
        side = hidden[nearest]
        cam = e.camera.value
        out[f"{cam} hidden"] = d[side]
        out[f"{cam} visible"] = d[~side]
    return out


def measure(seq_path: Path, variant: str) -> dict[str, Any]:
    seq = load_sequence(seq_path)
    assert seq.truth is not None and seq.target is not None and seq.target.ring is not None
    radius = seq.target.ring.radius_m
    fe = StereoFrontend(seq.calibration, config(variant, seq.target.ring))
    depth, lateral, dr = [], [], []
    sides: dict[str, list[np.ndarray]] = {}
    for frame in seq:
        m = fe.process_frame(frame)
        if m.ring is None:
            continue
        truth = seq.truth.pose(seq.truth.row_of_frame(m.frame))
        err = m.ring.center_m - truth.t
        los = truth.t / np.linalg.norm(truth.t)
        depth.append(float(err @ los))
        lateral.append(float(np.linalg.norm(err - (err @ los) * los)))
        dr.append(m.ring.radius_m - radius)
        if variant == "all edges":
            for k, v in edge_sides(m, truth, radius, fe.rig).items():
                sides.setdefault(k, []).append(v)
    if not depth:
        return {"frames": 0}
    return {
        "frames": len(depth),
        "depth_bias_cm": 100 * float(np.mean(depth)),
        "depth_sd_cm": 100 * float(np.std(depth)),
        "lateral_cm": 100 * float(np.mean(lateral)),
        "radius_bias_mm": 1e3 * float(np.mean(dr)),
        "sides": {k: np.concatenate(v) for k, v in sides.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=["tuning", "validation"], default="tuning")
    parser.add_argument("--count", type=int, default=7)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument(
        "--size", type=lambda s: tuple(int(v) for v in s.split("x")), default=(640, 480)
    )
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--root", type=Path, default=Path("runs/random"))
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--variants", default=",".join(VARIANTS), help="comma-separated subset of the variants"
    )
    args = parser.parse_args()
    seeds = list(TUNING_SEEDS if args.set == "tuning" else VALIDATION_SEEDS)[: args.count]
    start = time.time()
    rows = []
    for seed in seeds:
        draw = random_draw(seed)
        s = scaled(draw.scenario, frames=args.frames, size=args.size, spp=args.spp)
        tag = f"{seed}-{s.rig.width}x{s.rig.height}-{s.render.spp}spp-{s.frames}f"
        seq = args.root / tag
        if not (seq / "frames.csv").is_file():
            render_sequence(s, seq, overwrite=True)
        row = {
            "seed": seed,
            "scene": f"{s.target.ring.outer_radius_m:.2f}/{s.target.ring.height_m:.2f} m, "
            f"{draw.rim}, {draw.light}, tilt {s.motion.facing_tilt_deg:.0f} deg, "
            f"{float(np.linalg.norm(s.motion.start_position_m)):.1f} m",
        }
        for v in args.variants.split(","):
            row[v] = measure(seq, v)
        rows.append(row)
        print({k: (v if k != "all edges" else "...") for k, v in row.items()}, flush=True)
    out = args.out or Path(f"docs/results/ring_wall_{args.set}.md")
    write_page(out, markdown(rows, args, time.time() - start))


def _cell(r: dict[str, float]) -> str:
    if not r.get("frames"):
        return "no ring"
    return (
        f"{r['depth_bias_cm']:+.2f} / {r['depth_sd_cm']:.2f} / {r['lateral_cm']:.2f} / "
        f"{r['radius_bias_mm']:+.1f} ({r['frames']})"
    )


def markdown(rows: list[dict], args: argparse.Namespace, seconds: float) -> str:  # type: ignore[type-arg]
    variants = args.variants.split(",")
    lines = [
        f"# Ring centre bias by measurement variant: {args.set} seeds",
        "",
        f"Generated by `python benchmarks/ring_wall.py --set {args.set} --count {args.count} "
        f"--frames {args.frames} --size {args.size[0]}x{args.size[1]} --spp {args.spp}"
        + ("" if variants == list(VARIANTS) else f" --variants '{args.variants}'")
        + "` "
        f"({machine_summary()}; {time.strftime('%Y-%m-%d')}; {seconds / 60:.1f} min). "
        "Do not edit by hand.",
        "",
        "Per cell: depth bias / depth sd / mean lateral error [cm] / radius bias [mm] "
        "(frames with a ring), the ring's per-frame 3-D centre against the truth.",
        "",
        "| seed | scene (radius/wall, rim, light, tilt, range) | " + " | ".join(variants) + " |",
        "|---|---|" + "---|" * len(variants),
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['scene']} | " + " | ".join(_cell(r[v]) for v in variants) + " |"
        )
    lines += [
        "",
        "## Where the edges lie (variant `all edges`)",
        "",
        "Signed distance [px] of the ring's edge points to the true outer front rim's image "
        "(> 0: outside), mean / sd (points), per camera and by side: `hidden` where the "
        "wall's outer face is turned away from that camera (there the rim is the ring's "
        "occluding edge), `visible` where it is seen beside the rim (by the true circle and "
        "camera centres, `satpose.frontend.rim.rim_labels`). A difference between the left and "
        "right cameras on one side is a disparity error.",
        "",
        "| seed | left hidden | left visible | right hidden | right visible |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        sides = r["all edges"].get("sides", {})
        cells = []
        for k in ("left hidden", "left visible", "right hidden", "right visible"):
            d = sides.get(k)
            cells.append("-" if d is None or not len(d) else f"{d.mean():+.2f} / {d.std():.2f}")
        lines.append(f"| {r['seed']} | " + " | ".join(cells) + " |")
    lines += ["", "## Over seeds", ""]
    common = [r for r in rows if all(r[v].get("frames") for v in variants)]
    lines += [
        f"Means of the absolute depth bias and of the depth sd over the seeds where the "
        f"variant measured a ring, and over the {len(common)} seeds where every variant did "
        f"({', '.join(str(r['seed']) for r in common)}).",
        "",
        "| variant | seeds with a ring | mean abs depth bias [cm] | mean depth sd [cm] | "
        "mean lateral [cm] | same seeds: abs depth bias / sd [cm] |",
        "|---|---|---|---|---|---|",
    ]
    for v in variants:
        got = [r[v] for r in rows if r[v].get("frames")]
        b = np.mean([abs(g["depth_bias_cm"]) for g in got]) if got else math.nan
        sd = np.mean([g["depth_sd_cm"] for g in got]) if got else math.nan
        lat = np.mean([g["lateral_cm"] for g in got]) if got else math.nan
        cb = np.mean([abs(r[v]["depth_bias_cm"]) for r in common]) if common else math.nan
        csd = np.mean([r[v]["depth_sd_cm"] for r in common]) if common else math.nan
        lines.append(
            f"| {v} | {len(got)} of {len(rows)} | {b:.2f} | {sd:.2f} | {lat:.2f} | "
            f"{cb:.2f} / {csd:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
