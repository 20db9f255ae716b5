"""What the stereo frontend measures as "the ring", frame by frame, on the random family.

    python benchmarks/ring_diagnosis.py --seeds 0-7 --label before --largest  # the old rule
    python benchmarks/ring_diagnosis.py --seeds 0-7 --label after              # the default
    python benchmarks/ring_diagnosis.py --seeds 0-7 --label face_after_0-7 --face-rise 0.3
                                                    # the rim-face check (docs/frontend.md)
    python benchmarks/ring_diagnosis.py --seeds 8,9,12,13,15,16,18,19,20,21,22,23,25,28,29,30 \
        --frames 6 --label sunacq_before --no-mixed  # without the fallback acquisition pass

Runs the frontend alone (no smoother) on each tuning seed's render and, per frame, names the
ring curve the reported ellipses follow: the candidate curve of the true target (projected
with the true pose into both cameras) that the reported left and right ellipses lie closest to
(mean absolute distance of 90 points of each ellipse to the curve's image, averaged over both
cameras). Candidates, from the seed's drawn ring (`satpose.datasets.random_family`):

- ``outer rim``: the outer front rim (the target frame's ring circle), the one to measure;
- ``inner rim``: the inner front rim, same plane;
- ``base``: the wall's outer circle at its base (``height_m`` behind the rim);
- ``outline``: the wall's outer outline (convex hull of the rim and the base ellipses: rim arc
  where the wall is hidden, base arc and two silhouette lines where it shows);
- ``lip edge``: for a lipped rim, the lip's back edge (``lip_thickness_m`` behind the rim);
- ``face edge``: for a rounded rim, where its flat face ends (``outer - fillet``).

A frame whose best candidate is more than ``--far`` px away is ``other``. Ties go to the
outer rim (within 0.05 px): where the wall is hidden in both cameras its outline is the rim.
Per frame also the ellipse centre error against the projected outer rim (left image), the
3-D circle's radius error [mm], normal error [deg] and depth error [cm] against the truth.
Overlays of the ``--overlays`` worst frames (by centre error) go to ``--overlay-dir``: the
undistorted left image around the ring, reported ellipse red, true outer rim green, inner rim
blue, base yellow, edge points magenta.

Writes docs/results/ring_diagnosis_<label>.md. Validation seeds are refused: this script is
for looking, and only tuning seeds may be looked at (docs/renderer.md, "Random family").
"""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from _common import (  # benchmarks/_common.py (scripts run from the root)
    machine_summary,
    tuning_seeds,
    write_page,
)

from satpose.datasets.geometry import Rigid3
from satpose.datasets.random_family import random_draw
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import rim_in_view, scaled
from satpose.datasets.sequence import load_sequence
from satpose.frontend.conics import Ellipse, circle_to_conic, conic_to_ellipse
from satpose.frontend.measurements import EllipseObservation
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
from satpose.frontend.ring_outline import outline_hull

ELLIPSE_SAMPLES = 90
CURVE_SAMPLES = 720
TIE_PX = 0.05


def candidates(ring: Any) -> dict[str, tuple[float, float]]:
    """Candidate ring curves: name -> (radius [m], offset along the normal [m], <= 0)."""
    wall_outer = ring.outer_radius_m - ring.lip_width_m
    out = {
        "outer rim": (ring.outer_radius_m, 0.0),
        "inner rim": (ring.inner_radius_m, 0.0),
        "base": (wall_outer, -ring.height_m),
    }
    if ring.lip_width_m > 0:
        out["lip edge"] = (ring.outer_radius_m, -ring.lip_thickness_m)
    if ring.rim_fillet_m > 0:
        out["face edge"] = (ring.outer_radius_m - ring.rim_fillet_m, 0.0)
    return out


def _circle_polygon(K: np.ndarray, cam_from_target: Rigid3, r: float, z: float) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * math.pi, CURVE_SAMPLES, endpoint=False)
    X = np.c_[r * np.cos(a), r * np.sin(a), np.full_like(a, z)]
    Y = cam_from_target.apply(X)
    p = Y @ K.T
    return (p[:, :2] / p[:, 2:]).astype(np.float32)


def _mean_distance(points: np.ndarray, polygon: np.ndarray) -> float:
    poly = polygon.reshape(-1, 1, 2).astype(np.float32)
    d = [abs(cv2.pointPolygonTest(poly, (float(x), float(y)), True)) for x, y in points]
    return float(np.mean(d))


def curve_distances(
    obs: tuple[EllipseObservation, EllipseObservation],
    cams: tuple[tuple[np.ndarray, Rigid3], tuple[np.ndarray, Rigid3]],
    ring: Any,
) -> dict[str, float]:
    """Per candidate curve, the mean absolute distance [px] of the reported ellipses (both
    cameras) to its image."""
    cands = candidates(ring)
    out: dict[str, list[float]] = {name: [] for name in [*cands, "outline"]}
    for o, (K, T) in zip(obs, cams, strict=True):
        e = Ellipse.from_params([*o.center_px, *o.axes_px, o.angle_rad])
        pts = e.points(ELLIPSE_SAMPLES)
        for name, (r, z) in cands.items():
            out[name].append(_mean_distance(pts, _circle_polygon(K, T, r, z)))
        hull, _ = outline_hull(
            K,
            Rigid3.identity(),
            T.t,
            T.R[:, 2],
            ring.outer_radius_m,
            ring.height_m,
            CURVE_SAMPLES,
        )
        out["outline"].append(_mean_distance(pts, hull))
    return {k: float(np.mean(v)) for k, v in out.items()}


def label(dist: dict[str, float], far_px: float) -> str:
    best = min(dist, key=lambda k: dist[k])
    if dist["outer rim"] <= dist[best] + TIE_PX:
        best = "outer rim"
    return best if dist[best] <= far_px else "other"


def _overlay(
    path: Path,
    gray8: np.ndarray,
    obs: EllipseObservation,
    K: np.ndarray,
    T: Rigid3,
    ring: Any,
) -> None:
    img = cv2.cvtColor(gray8, cv2.COLOR_GRAY2BGR)
    scale = 3
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)

    def poly(p: np.ndarray, colour: tuple[int, int, int]) -> None:
        q = np.round(p * scale + (scale - 1) / 2).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [q], True, colour, 1, cv2.LINE_AA)

    cands = candidates(ring)
    colours = {"outer rim": (0, 200, 0), "inner rim": (255, 120, 0), "base": (0, 220, 255)}
    for name, colour in colours.items():
        poly(_circle_polygon(K, T, *cands[name]), colour)
    e = Ellipse.from_params([*obs.center_px, *obs.axes_px, obs.angle_rad])
    poly(e.points(360), (0, 0, 255))
    for x, y in obs.edge_points_px:
        cv2.circle(img, (int(x * scale + 1), int(y * scale + 1)), 1, (255, 0, 255), -1)
    c = obs.center_px * scale
    half = int(max(obs.axes_px) * scale * 1.25) + 20
    x0, y0 = max(0, int(c[0]) - half), max(0, int(c[1]) - half)
    crop = img[y0 : int(c[1]) + half, x0 : int(c[0]) + half]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    cv2.imwrite(str(tmp), crop)
    tmp.replace(path)


def diagnose(seed: int, args: argparse.Namespace, cfg: FrontendConfig) -> list[dict[str, Any]]:
    draw = random_draw(seed)
    s = scaled(draw.scenario, frames=args.frames, size=args.size, spp=args.spp)
    ring = s.target.ring
    tag = f"{seed}-{s.rig.width}x{s.rig.height}-{s.render.spp}spp-{s.frames}f"
    seq_path = args.root / tag
    if not (seq_path / "frames.csv").is_file():
        render_sequence(s, seq_path, overwrite=True)
    seq = load_sequence(seq_path)
    assert seq.truth is not None
    in_view = rim_in_view(s)
    fe = StereoFrontend(seq.calibration, cfg)
    K_l, K_r = fe.rig.K_left, fe.rig.K_right
    rows = []
    for frame in seq.frames:
        m = fe.process_frame(frame)
        i = seq.truth.row_of_frame(frame.index)
        T = seq.truth.pose(i)
        T_r = fe.rig.right_from_left @ T
        row: dict[str, Any] = {
            "seed": seed,
            "frame": frame.index,
            "rim": draw.rim,
            "light": draw.light,
            "in_view": float(in_view[i].min()),
            "radius_m": ring.outer_radius_m,
        }
        if m.ring is None:
            row["label"] = "no ring"
            why = [f for f in m.failures if f.startswith("ring")]
            row["why"] = (why[0] if why else "")[:70]
            rows.append(row)
            continue
        obs = m.ring.ellipses
        dist = curve_distances(obs, ((K_l, T), (K_r, T_r)), ring)
        true = conic_to_ellipse(circle_to_conic(K_l, T, ring.outer_radius_m))
        n_true = T.R[:, 2]
        cosang = abs(float(m.ring.normal @ n_true))
        los = T.t / np.linalg.norm(T.t)
        row.update(
            label=label(dist, args.far),
            d_outer=dist["outer rim"],
            d_best=min(dist.values()),
            dist=dist,
            centre_px=float(np.hypot(*(obs[0].center_px - [true.cx, true.cy]))),
            radius_mm=1e3 * (m.ring.radius_m - ring.outer_radius_m),
            normal_deg=math.degrees(math.acos(min(1.0, cosang))),
            depth_cm=1e2 * float((m.ring.center_m - T.t) @ los),
            lateral_cm=1e2
            * float(
                np.linalg.norm((m.ring.center_m - T.t) - ((m.ring.center_m - T.t) @ los) * los)
            ),
        )
        row["_obs"], row["_T"], row["_frame"] = obs[0], T, frame
        rows.append(row)
        print(
            f"seed {seed} frame {frame.index}: {row['label']} (outer {dist['outer rim']:.2f} px, "
            f"best {row['d_best']:.2f}) centre {row['centre_px']:.2f} px radius "
            f"{row['radius_mm']:+.1f} mm normal {row['normal_deg']:.2f} deg",
            flush=True,
        )
    worst = sorted((r for r in rows if "_obs" in r), key=lambda r: -float(r["centre_px"]))[
        : args.overlays
    ]
    for r in worst:
        gray8 = fe.undistort["left"](r["_frame"].left()).gray8
        path = args.overlay_dir / f"{args.label}_seed{seed}_frame{r['frame']}.png"
        _overlay(path, gray8, r["_obs"], K_l, r["_T"], ring)
        r["overlay"] = str(path)
    for r in rows:
        for k in ("_obs", "_T", "_frame"):
            r.pop(k, None)
    return rows


def _f(x: Any, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def markdown(rows: list[dict[str, Any]], args: argparse.Namespace, minutes: float) -> str:
    eligible = [r for r in rows if r["in_view"] >= 0.8]
    counts = Counter(r["label"] for r in eligible)
    ring_rows = [r for r in eligible if "centre_px" in r]
    cmd = (
        f"python benchmarks/ring_diagnosis.py --seeds {args.seeds} --frames {args.frames} "
        f"--size {args.size[0]}x{args.size[1]} --spp {args.spp} --label {args.label}"
        + (" --outline" if args.outline else "")
        + (" --largest" if args.largest else "")
        + (f" --face-rise {args.face_rise}" if args.face_rise is not None else "")
        + (" --no-mixed" if args.no_mixed else "")
    )
    lines = [
        f"# What the frontend measures as the ring: tuning seeds ({args.label})",
        "",
        f"Generated by `{cmd}` ({machine_summary()}; {time.strftime('%Y-%m-%d')}; "
        f"{minutes:.1f} min). Do not edit by hand.",
        "",
        "Per frame, the true ring curve that the reported left and right ellipses lie closest "
        "to (mean absolute distance of the ellipses to each curve's image with the true pose, "
        f"both cameras; `other`: none within {args.far:g} px), the distance to the outer front "
        "rim, the ellipse centre error against the projected outer rim (left), and the 3-D "
        "circle's radius, normal and depth errors. Summary over frames with >= 80 % of the rim "
        "in view. Curves: docstring of benchmarks/ring_diagnosis.py.",
        "",
        "## Summary",
        "",
        "| what was measured | frames |",
        "|---|---|",
    ]
    for name, k in counts.most_common():
        lines.append(f"| {name} | {k} of {len(eligible)} |")
    if ring_rows:
        c = np.array([r["centre_px"] for r in ring_rows])
        d = np.array([r["d_outer"] for r in ring_rows])
        rad = np.array([abs(r["radius_mm"]) for r in ring_rows])
        nrm = np.array([r["normal_deg"] for r in ring_rows])
        dep = np.array([abs(r["depth_cm"]) for r in ring_rows])
        outer2 = np.mean([abs(r["radius_mm"]) < 20.0 * r["radius_m"] for r in ring_rows])
        lines += [
            "",
            "| measure (frames with a ring) | median | mean |",
            "|---|---|---|",
            f"| radius within 2 % (random_family.py's rule) | {100 * outer2:.0f} % | - |",
            f"| ellipse centre error [px] | {np.median(c):.2f} | {np.mean(c):.2f} |",
            f"| ellipse to outer rim, mean distance [px] | {np.median(d):.2f} | {np.mean(d):.2f} |",
            f"| abs radius error [mm] | {np.median(rad):.1f} | {np.mean(rad):.1f} |",
            f"| normal error [deg] | {np.median(nrm):.2f} | {np.mean(nrm):.2f} |",
            f"| abs depth error [cm] | {np.median(dep):.2f} | {np.mean(dep):.2f} |",
        ]
    lines += [
        "",
        "## Frames",
        "",
        "| seed | frame | rim | light | rim in view | measured | to outer rim [px] | "
        "to best [px] | centre [px] | radius [mm] | normal [deg] | depth [cm] | lateral [cm] |",
        "|" + "---|" * 13,
    ]
    for r in rows:
        what = r["label"] + (f" ({r['why']})" if r.get("why") else "")
        lines.append(
            "| "
            + " | ".join(
                [
                    str(r["seed"]),
                    str(r["frame"]),
                    r["rim"],
                    r["light"],
                    f"{r['in_view']:.2f}",
                    what,
                    _f(r.get("d_outer"), ".2f"),
                    _f(r.get("d_best"), ".2f"),
                    _f(r.get("centre_px"), ".2f"),
                    _f(r.get("radius_mm"), "+.1f"),
                    _f(r.get("normal_deg"), ".2f"),
                    _f(r.get("depth_cm"), "+.2f"),
                    _f(r.get("lateral_cm"), ".2f"),
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-7", help="tuning seeds, e.g. 0-7 or 0,3,5")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument(
        "--size", type=lambda s: tuple(int(v) for v in s.split("x")), default=(640, 480)
    )
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--root", type=Path, default=Path("runs/random"))
    parser.add_argument("--far", type=float, default=1.0, help="`other` beyond this [px]")
    parser.add_argument("--overlays", type=int, default=2, help="worst frames per seed")
    parser.add_argument("--overlay-dir", type=Path, default=Path("runs/ring_diagnosis"))
    parser.add_argument("--outline", action="store_true", help="outline.enabled")
    parser.add_argument(
        "--largest",
        action="store_true",
        help="the largest consistent pair wins (stereo_ring.behind_sigma: None, the old rule)",
    )
    parser.add_argument(
        "--face-rise",
        type=float,
        default=None,
        help="ring.face_rise (the rim-face check; default: the config's)",
    )
    parser.add_argument(
        "--no-mixed",
        action="store_true",
        help="ring.mixed_acquisition: false (no fallback pass of either polarity)",
    )
    parser.add_argument("--label", default="current", help="names the output page")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    cfg = FrontendConfig()
    if args.outline:
        cfg = replace(cfg, outline=replace(cfg.outline, enabled=True))
    if args.largest:
        cfg = replace(cfg, stereo_ring=replace(cfg.stereo_ring, behind_sigma=None))
    if args.face_rise is not None:
        cfg = replace(cfg, ring=replace(cfg.ring, face_rise=args.face_rise))
    if args.no_mixed:
        cfg = replace(cfg, ring=replace(cfg.ring, mixed_acquisition=False))
    start = time.perf_counter()
    rows = [r for seed in tuning_seeds(args.seeds) for r in diagnose(seed, args, cfg)]
    minutes = (time.perf_counter() - start) / 60.0
    out = args.out or Path(f"docs/results/ring_diagnosis_{args.label}.md")
    write_page(out, markdown(rows, args, minutes))


if __name__ == "__main__":
    main()
