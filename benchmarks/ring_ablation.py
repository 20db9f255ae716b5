"""Which part of a random-family scene biases the ring's depth: one factor changed at a time.

    python benchmarks/ring_ablation.py [--seeds 0,6,7 --frames 3 --variants ...]

For lamp-lit tuning seeds whose ring the frontend measures on the right curve but centimetres
too far (docs/frontend.md, "A ring with a wall"), the drawn `Scenario` (`random_draw`) is
rendered at 640x480, 8 spp, as drawn and with one factor changed (``VARIANTS``):

- ``as drawn``: the scene as the random family draws it.
- ``no distortion``: both lenses without distortion (no resampling of the render).
- ``no wall``: the wall 3 mm high (the panel just behind the rim: no wall face, no base edge,
  and the rim's cast shadow shifted by a tenth of what it was).
- ``matte``: the ring, its wall and the panel all painted (Lambertian, grey 0.5 ring and
  0.8 panel; no polished metal, no foil).
- ``exposure / 2``: the metered white level halved (nothing saturates near the rim).
- ``lamp at left cam`` / ``lamp at right cam`` / ``lamp between cams``: the lamp moved into
  the left camera's centre, the right one's, or half-way. A lamp at a camera's centre casts
  no shadow that camera can see; the other camera sees the rim's shadow on the panel beside
  it, on the side away from the lamp.
- ``matte + lamp between``: the last two together.

Each rendering is measured twice: with the default frontend, and with the ring refitted where
no shadow of it shows beside the rim (``lit rim``: `satpose.frontend.rim.lit_labels`, the
variant's lamp stated in the config; docs/frontend.md).

Per cell: the ring's per-frame 3-D centre error along the line of sight (depth, mean over
frames), the radius error, and per camera how the edge points the frontend fitted lie against
the true rim's image: their signed distances (> 0 outside) fitted as ``g + s . n`` over the
curve's outward normal ``n``, i.e. a growth ``g`` [px] and a shift ``s`` of the curve [px];
the difference of the two cameras' shifts along the baseline is the disparity error that
makes the depth bias (``d_disp`` = left x-shift - right x-shift: < 0 is farther). ``clip`` is
the fraction of pixels within 3 px of the ring's mask that read full scale.

Tuning seeds only (`satpose.datasets.seed_split.TUNING_SEEDS`). Writes
docs/results/ring_ablation.md; renders are kept under runs/ring_ablation/.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)
from random_family import lit_rim  # benchmarks/random_family.py

from satpose.datasets.geometry import Rigid3
from satpose.datasets.random_family import random_draw
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import Scenario, scaled
from satpose.datasets.seed_split import TUNING_SEEDS
from satpose.datasets.sequence import load_sequence
from satpose.datasets.target import MetalConfig
from satpose.frontend.conics import circle_to_conic, sampson_distance
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
from satpose.frontend.rim import camera_centers
from satpose.frontend.stereo import StereoRig
from satpose.tools.pipeline import PipelineConfig

VARIANTS = (
    "as drawn",
    "no distortion",
    "no wall",
    "matte",
    "exposure / 2",
    "lamp at left cam",
    "lamp at right cam",
    "lamp between cams",
    "matte + lamp between",
)


def variant(s: Scenario, name: str) -> Scenario:
    """``s`` with the one factor of ``name`` changed (see the module docstring)."""
    t = s.target
    right = camera_centers(StereoRig.from_calibration(s.rig.calibration()))[1]
    lamp = {
        "lamp at left cam": np.zeros(3),
        "lamp at right cam": right,
        "lamp between cams": 0.5 * right,
        "matte + lamp between": 0.5 * right,
    }
    if name == "no distortion":
        return replace(s, rig=replace(s.rig, dist_left=(0.0,) * 5, dist_right=(0.0,) * 5))
    if name == "no wall":
        return replace(s, target=replace(t, ring=replace(t.ring, height_m=0.003)))
    if name.startswith("matte"):
        ring = replace(
            t.ring, material=MetalConfig(finish="painted", diffuse_rgb=(0.5,) * 3), wall_foil=None
        )
        panel = replace(t.panel, paint=MetalConfig(finish="painted", diffuse_rgb=(0.8,) * 3))
        s = replace(s, target=replace(t, ring=ring, panel=panel))
    if name == "exposure / 2":
        return replace(s, sensor=replace(s.sensor, white_level=0.5 * s.sensor.white_level))
    if name in lamp:
        if s.light.kind != "point":
            raise SystemExit(f"{s.name}: variant {name!r} needs a lamp-lit seed")
        p = lamp[name]
        return replace(s, light=replace(s.light, position_m=(float(p[0]), float(p[1]), 0.0)))
    return s


def curve_fit(d: np.ndarray, n: np.ndarray) -> tuple[float, np.ndarray]:
    """Growth [px] and shift (2,) [px] of a curve whose points lie ``d`` (N,) outside the true
    one along its outward normals ``n`` (N, 2): least squares of ``d = g + s . n``."""
    A = np.c_[np.ones(len(d)), n]
    sol = np.linalg.lstsq(A, d, rcond=None)[0]
    return float(sol[0]), sol[1:]


def outward_normals(conic: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Unit normals (N, 2) of the conic's level sets at ``pts``, pointing outward."""
    g = np.c_[pts, np.ones(len(pts))] @ conic
    nrm = g[:, :2] / np.linalg.norm(g[:, :2], axis=1, keepdims=True)
    # the conic is negative inside (up to its overall sign): flip to point where it grows
    # away from the curve's centre
    c = np.linalg.solve(conic[:2, :2], -conic[:2, 2])
    flip = np.einsum("ij,ij->i", nrm, pts - c) < 0
    nrm[flip] *= -1
    return nrm


def clipped_near_ring(frame: Any, camera: str) -> float:
    """Fraction of pixels within 3 px of the ring's mask (both sides) at full scale."""
    mask_path = frame.mask_path(camera)
    if mask_path is None or not mask_path.is_file():
        return float("nan")
    ring = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) == 3
    img = frame.image(camera)
    top = 255 if img.dtype == np.uint8 else 65535
    full = (img >= top - 1).any(axis=2) if img.ndim == 3 else img >= top - 1
    k = np.ones((7, 7), np.uint8)
    band = cv2.dilate(ring.astype(np.uint8), k) > cv2.erode(ring.astype(np.uint8), k)
    return float(full[band].mean()) if band.any() else float("nan")


def measure(seq_path: Path, config: FrontendConfig | None = None) -> dict[str, Any]:
    """Per-frame ring errors of the frontend on a rendered sequence, and where its edges lie."""
    seq = load_sequence(seq_path)
    assert seq.truth is not None and seq.target is not None and seq.target.ring is not None
    radius = seq.target.ring.radius_m
    fe = StereoFrontend(seq.calibration, config or FrontendConfig())
    rig = fe.rig
    depth, dr, clip = [], [], []
    fits: dict[str, list[np.ndarray]] = {"left": [], "right": []}
    for frame in seq:
        clip += [clipped_near_ring(frame, c) for c in ("left", "right")]
        m = fe.process_frame(frame)
        if m.ring is None:
            continue
        truth = seq.truth.pose(seq.truth.row_of_frame(m.frame))
        err = m.ring.center_m - truth.t
        depth.append(float(err @ truth.t / np.linalg.norm(truth.t)))
        dr.append(m.ring.radius_m - radius)
        for e, K, T in (
            (m.ring.ellipses[0], rig.K_left, Rigid3.identity()),
            (m.ring.ellipses[1], rig.K_right, rig.right_from_left),
        ):
            conic = circle_to_conic(K, T @ truth, radius)
            pts = e.edge_points_px
            g, sh = curve_fit(sampson_distance(pts, conic), outward_normals(conic, pts))
            fits[e.camera.value].append(np.r_[g, sh])
    out: dict[str, Any] = {"frames": len(depth), "clip": float(np.nanmean(clip))}
    if depth:
        fl, fr = np.mean(fits["left"], axis=0), np.mean(fits["right"], axis=0)
        out |= {
            "depth_cm": 100 * float(np.mean(depth)),
            "depth_sd_cm": 100 * float(np.std(depth)),
            "radius_mm": 1e3 * float(np.mean(dr)),
            "left": fl,
            "right": fr,
            "d_disp": float(fl[1] - fr[1]),
        }
    return out


def render(s: Scenario, root: Path, tag: str) -> Path:
    out = root / tag
    if not (out / "frames.csv").is_file():
        render_sequence(s, out, overwrite=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,6,7", help="comma-separated tuning seeds")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--root", type=Path, default=Path("runs/ring_ablation"))
    parser.add_argument("--out", type=Path, default=Path("docs/results/ring_ablation.md"))
    args = parser.parse_args()
    seeds = [int(v) for v in args.seeds.split(",")]
    if not set(seeds) <= set(TUNING_SEEDS):
        raise SystemExit(
            f"only tuning seeds may be looked at: {sorted(set(seeds) - set(TUNING_SEEDS))}"
        )
    names = args.variants.split(",")
    start = time.time()
    rows = []
    for seed in seeds:
        draw = random_draw(seed)
        s = scaled(draw.scenario, frames=args.frames, size=(640, 480), spp=8)
        r = s.target.ring
        row: dict[str, Any] = {
            "seed": seed,
            "scene": f"{r.outer_radius_m:.2f} m, rim {r.outer_radius_m - r.inner_radius_m:.3f} m, "
            f"wall {r.height_m:.2f} m, {draw.rim}, {draw.light}, "
            f"tilt {s.motion.facing_tilt_deg:.0f} deg, "
            f"{float(np.linalg.norm(s.motion.start_position_m)):.1f} m",
        }
        for name in names:
            slug = name.replace(" ", "_").replace("/", "over").replace("+_", "")
            tag = f"{seed}-{slug}-{args.frames}f"
            v = variant(s, name)
            seq = render(v, args.root, tag)
            row[name] = measure(seq)
            row[name + " lit"] = measure(seq, lit_rim(PipelineConfig(), v.light).frontend)
            print(seed, name, _cell(row[name]), "| lit-rim:", _cell(row[name + " lit"]), flush=True)
        rows.append(row)
    write_page(args.out, markdown(rows, names, args, time.time() - start))


def _cell(m: dict[str, Any]) -> str:
    if not m.get("frames"):
        return f"no ring (clip {m.get('clip', float('nan')):.2f})"
    fl, fr = m["left"], m["right"]
    return (
        f"{m['depth_cm']:+.2f} / {m['radius_mm']:+.1f} / {m['d_disp']:+.2f} / "
        f"L {fl[0]:+.2f} ({fl[1]:+.2f},{fl[2]:+.2f}) R {fr[0]:+.2f} ({fr[1]:+.2f},{fr[2]:+.2f}) / "
        f"{m['clip']:.2f}"
    )


def markdown(
    rows: list[dict[str, Any]], names: list[str], args: argparse.Namespace, seconds: float
) -> str:
    cmd = f"python benchmarks/ring_ablation.py --seeds {args.seeds} --frames {args.frames}"
    if names != list(VARIANTS):
        cmd += f" --variants '{args.variants}'"
    lines = [
        "# Ring depth bias by scene factor: random-family tuning seeds",
        "",
        f"Generated by `{cmd}` ({machine_summary()}; {time.strftime('%Y-%m-%d')}; "
        f"{seconds / 60:.1f} min). Do not edit by hand.",
        "",
        "640x480, 8 spp, the first frames of each seed, the default frontend. Per cell: depth "
        "error [cm] / radius error [mm] / disparity error of the edges `d_disp` [px] (left "
        "x-shift - right x-shift; < 0: farther) / per camera the edges' growth [px] and shift "
        "(x, y) [px] against the true rim's image / fraction of pixels at full scale within "
        "3 px of the ring (benchmarks/ring_ablation.py says how). The last column: the same "
        "with the ring refitted by the light (`rim.labels: light`, the shadow band modelled); "
        "its `d_disp` is of the edge points that refit used, which with the band modelled "
        "rather than removed are much the default's.",
        "",
    ]
    for r in rows:
        lines += [
            f"## Seed {r['seed']} ({r['scene']})",
            "",
            "| variant | depth [cm] | radius [mm] "
            "| d_disp [px] | left growth / shift [px] | right growth / shift [px] | clip "
            "| lit rim: depth [cm] / radius [mm] / d_disp [px] |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for n in names:
            m = r[n]
            lit = r[n + " lit"]
            lit_cell = (
                f"{lit['depth_cm']:+.2f} / {lit['radius_mm']:+.1f} / {lit['d_disp']:+.3f}"
                if lit.get("frames")
                else "no ring"
            )
            if not m.get("frames"):
                lines.append(
                    f"| {n} | no ring | | | | | {m.get('clip', float('nan')):.3f} | {lit_cell} |"
                )
                continue
            fl, fr = m["left"], m["right"]
            lines.append(
                f"| {n} | {m['depth_cm']:+.2f} | {m['radius_mm']:+.1f} | {m['d_disp']:+.3f} | "
                f"{fl[0]:+.2f} / ({fl[1]:+.2f}, {fl[2]:+.2f}) | "
                f"{fr[0]:+.2f} / ({fr[1]:+.2f}, {fr[2]:+.2f}) | {m['clip']:.3f} | {lit_cell} |"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
