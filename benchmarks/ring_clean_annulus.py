"""The ring's depth bias with nothing but the rim: an emissive front face, no light, no wall.

    python benchmarks/ring_clean_annulus.py [--count 3 --frames 0,5]

For random-family tuning seeds, the ring's front face alone is rendered as a uniform emitter
(the renderer's truth mode: no wall, no panel, no shading, no shadows) at 640x480 with the
seed's own rig and pose, four ways: with the seed's lens distortion and the renderer's
bilinear resampling of its pinhole canvas (``render.resampling: linear``), with cubic-spline
resampling instead (``cubic``), with each pixel integrating its distorted footprint over 3 x 3
sub-pixels of a 3x finer canvas (``area``), and without lens distortion (no resampling at
all). The frontend's ring tracker acquires the ring in each image and the 3-D
circle is fitted to its edge points (`satpose.frontend.stereo.refine_circle`); the table gives
the centre's depth error (along the line of sight), the lateral error and the radius error
against groundtruth.csv and target.yaml. What differs between the rows is only how the image
was resampled, so any difference is the edge measurement's sensitivity to the blur of
resampling (the renderer's geometry itself is checked to ~0.01 px by
`satpose.datasets.render_check.marker_errors`). Tuning seeds only.

Writes docs/results/ring_clean_annulus.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)

from satpose.datasets.random_family import random_draw
from satpose.datasets.render import StereoRenderer
from satpose.datasets.scenarios import Scenario, scaled, trajectory
from satpose.datasets.seed_split import TUNING_SEEDS
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
from satpose.frontend.stereo import refine_circle

VARIANTS = (
    "distortion, bilinear (as rendered)",
    "distortion, cubic spline",
    "distortion, area (3x3 sub-pixels)",
    "no distortion",
)


def variant(s: Scenario, name: str) -> Scenario:
    if name.startswith("no distortion"):
        return replace(s, rig=replace(s.rig, dist_left=(0.0,) * 5, dist_right=(0.0,) * 5))
    if "cubic" in name:
        return replace(s, render=replace(s.render, resampling="cubic"))
    if "area" in name:
        return replace(s, render=replace(s.render, resampling="area"))
    return s


def measure(s: Scenario, frame: int) -> dict[str, float] | None:
    """Depth / lateral / radius error of the clean annulus' circle at ``frame``."""
    pose = trajectory(s).left_cam_from_target[frame]
    calib = s.rig.calibration()
    rad = StereoRenderer(s, parts={"ring_front": 1.0}).radiance(frame, pose)
    fe = StereoFrontend(calib, FrontendConfig())
    obs = {}
    for cam in ("left", "right"):
        g = rad[cam] @ np.array([0.2126, 0.7152, 0.0722])
        img = np.clip(np.rint(255 * (0.15 + 0.6 * g / max(float(g.max()), 1e-9))), 0, 255)
        cands = fe.rings[cam].acquire(fe.undistort[cam](img.astype(np.uint8)))
        if not cands:
            return None
        obs[cam] = max(cands, key=lambda o: float(o[0].axes_px.sum()))[0]
    radius = s.target.ring.outer_radius_m
    n = pose.R[:, 2] if pose.R[:, 2] @ pose.t < 0 else -pose.R[:, 2]
    circ = refine_circle(
        fe.rig, pose.t + 0.01, n, radius, obs["left"].edge_points_px, obs["right"].edge_points_px
    )
    e = circ.center - pose.t
    los = pose.t / np.linalg.norm(pose.t)
    return {
        "depth_cm": 100 * float(e @ los),
        "lateral_cm": 100 * float(np.linalg.norm(e - (e @ los) * los)),
        "radius_mm": 1000 * (circ.radius - radius),
        "range_m": float(np.linalg.norm(pose.t)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=3, help="first N tuning seeds")
    parser.add_argument("--frames", default="0,5", help="comma-separated frame indices")
    parser.add_argument("--out", type=Path, default=Path("docs/results/ring_clean_annulus.md"))
    args = parser.parse_args()
    frames = [int(f) for f in args.frames.split(",")]
    start = time.time()
    rows = []
    for seed in list(TUNING_SEEDS)[: args.count]:
        draw = random_draw(seed)
        s = scaled(draw.scenario, frames=max(frames) + 1, size=(640, 480), spp=8)
        for f in frames:
            row: dict[str, object] = {"seed": seed, "frame": f, "tilt": s.motion.facing_tilt_deg}
            for v in VARIANTS:
                row[v] = measure(variant(s, v), f)
            rows.append(row)
            print(row, flush=True)
    write_page(args.out, markdown(rows, args, time.time() - start))


def _cell(m: object) -> str:
    if not isinstance(m, dict):
        return "no ring"
    return f"{m['depth_cm']:+.2f} / {m['lateral_cm']:.2f} / {m['radius_mm']:+.1f}"


def markdown(rows: list[dict[str, object]], args: argparse.Namespace, seconds: float) -> str:
    lines = [
        "# The ring with nothing but the rim: depth bias by how the image was resampled",
        "",
        f"Generated by `python benchmarks/ring_clean_annulus.py --count {args.count} "
        f"--frames {args.frames}` ({machine_summary()}; {time.strftime('%Y-%m-%d')}; "
        f"{seconds / 60:.1f} min). Do not edit by hand.",
        "",
        "The ring's front face alone, a uniform emitter on black, 640x480, tuning seeds' rigs and "
        "poses (benchmarks/ring_clean_annulus.py says how). Per cell: the fitted circle's depth "
        "error [cm] / lateral error [cm] / radius error [mm] against the truth.",
        "",
        "| seed | frame | range [m] | tilt [deg] | " + " | ".join(VARIANTS) + " |",
        "|---|---|---|---|" + "---|" * len(VARIANTS),
    ]
    for r in rows:
        rng = next((m["range_m"] for v in VARIANTS if isinstance(m := r[v], dict)), float("nan"))
        lines.append(
            f"| {r['seed']} | {r['frame']} | {rng:.1f} | {float(r['tilt']):.0f} | "  # type: ignore[arg-type]
            + " | ".join(_cell(r[v]) for v in VARIANTS)
            + " |"
        )
    lines += ["", "Mean depth error over the rows where every variant found the ring:", ""]
    common = [r for r in rows if all(isinstance(r[v], dict) for v in VARIANTS)]
    for v in VARIANTS:
        d = [r[v]["depth_cm"] for r in common]  # type: ignore[index]
        if d:
            lines.append(f"- {v}: {np.mean(d):+.2f} cm (mean |.| {np.mean(np.abs(d)):.2f} cm)")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
