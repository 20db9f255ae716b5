"""The stereo pipeline on the random scene family: accuracy, bias and honesty per sequence.

    python benchmarks/random_family.py --set validation --count 40 --jobs 2   # the issue's table
    python benchmarks/random_family.py --set tuning --count 8 --frames 10 --spp 8
    python benchmarks/random_family.py --set tuning --count 8 --frames 10 --size 640x480 --spp 8

Renders each member (`satpose.datasets.random_family`, cached under ``--root``), runs
`satpose run` (frontend, iSAM2, and the offline smoother and Kalman filter on the same
measurements) and `satpose eval`, and writes docs/results/random_family_<set>[_from_<seed>]
[_<size>].md (the size only when it is not the family's own 1024x768): per sequence
the scene (ring radius, wall height, rim, light, motion, tilt, range), frames with a ring and
a pose, the per-frame (frontend) and offline errors, the signed error terms' bias and random
part (depth, lateral, tilt; a bias above a third of the random part is flagged as a defect),
the NEES in-band fractions, the ring's radius error and its ellipse centre error against the
projected true outer front rim (frames with >= 80 % of the rim in view), and any exception.
The summary gives the medians over sequences against the targets of the stereo
generalisation issue.

Validation seeds are only scored: never change a parameter because of what they show
(docs/renderer.md, "Random family").
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)

from satpose.datasets.config import load_config
from satpose.datasets.errors import SatposeError
from satpose.datasets.random_family import random_draw
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import LightConfig, RigConfig, Scenario, rim_in_view, scaled
from satpose.datasets.seed_split import TUNING_SEEDS, VALIDATION_SEEDS
from satpose.datasets.sequence import load_sequence
from satpose.frontend.conics import circle_to_conic, conic_to_ellipse
from satpose.frontend.pipeline import KnownRing
from satpose.tools.evaluate import evaluate_run
from satpose.tools.files import read_measurements
from satpose.tools.pipeline import PipelineConfig, run_pipeline

TARGETS = {
    "per-frame pos [cm]": 1.0,
    "per-frame rot [deg]": 0.5,
    "offline pos [cm]": 0.4,
    "offline rot [deg]": 0.2,
    "ellipse centre [px]": 0.3,
}
DEFAULT_SIZE = (RigConfig().width, RigConfig().height)  # the family's rig: 1024x768
PAPER = (1.74, 0.94)  # seed 000's per-frame mean errors, 7-3 m [cm, deg]


def ring_checks(seq_path: Path, run: Path, scenario: Any) -> dict[str, float]:
    """Ring radius and ellipse-centre errors over frames with >= 80 % of the rim in view."""
    seq = load_sequence(seq_path)
    assert seq.truth is not None and seq.target is not None and seq.target.ring is not None
    radius = seq.target.ring.radius_m
    in_view = rim_in_view(scenario)
    K = seq.calibration.left.K
    radius_err, centre_err, eligible, outer = [], [], 0, 0
    for m in read_measurements(run / "measurements.parquet"):
        row = seq.truth.row_of_frame(m.frame)
        if in_view[row].min() < 0.8:
            continue
        eligible += 1
        if m.ring is None:
            continue
        radius_err.append(m.ring.radius_m - radius)
        outer += abs(m.ring.radius_m - radius) < 0.02 * radius
        true = conic_to_ellipse(circle_to_conic(K, seq.truth.pose(row), radius))
        centre_err.append(float(np.hypot(*(m.ring.ellipses[0].center_px - [true.cx, true.cy]))))
    return {
        "eligible": eligible,
        "ring_frames": len(radius_err),
        "outer_frac": outer / eligible if eligible else math.nan,
        "radius_bias_mm": 1e3 * float(np.mean(radius_err)) if radius_err else math.nan,
        "centre_px": float(np.median(centre_err)) if centre_err else math.nan,
    }


def lit_rim(c: PipelineConfig, light: LightConfig) -> PipelineConfig:
    """``c`` with the ring refitted where no shadow of it shows beside the rim
    (`satpose.frontend.rim.lit_labels`), the light stated as a user would: the rig's lamp
    position or the sun's direction in the left camera frame."""
    if light.rotation_deg_s != 0.0:
        raise SystemExit("--lit-rim: a turning light is not a fixed light in the rig frame")
    where = (
        {"light_position_m": tuple(light.position_m)}
        if light.kind == "point"
        else {"sun_direction": tuple(light.direction)}
    )
    rim = replace(c.frontend.rim, enabled=True, labels="light", **where)
    return replace(c, frontend=replace(c.frontend, rim=rim))


def known_ring(scenario: Scenario, what: str) -> KnownRing:
    """The member's ring as its user would state it (`KnownRing`, default sigmas): its outer
    radius (``what`` = ``radius``), or (``full``) also its inner radius, wall height, and a
    lip's width and thickness."""
    r = scenario.target.ring
    if what == "radius":
        return KnownRing(outer_radius_m=r.outer_radius_m)
    return KnownRing(
        outer_radius_m=r.outer_radius_m,
        wall_height_m=r.height_m,
        inner_radius_m=r.inner_radius_m,
        wall_outer_radius_m=r.outer_radius_m - r.lip_width_m if r.lip_width_m > 0 else None,
        lip_thickness_m=r.lip_thickness_m if r.lip_width_m > 0 else 0.0,
    )


def pipeline_config(args: argparse.Namespace, scenario: Scenario) -> PipelineConfig:
    """The default `satpose run` configuration (or ``--config``'s), with
    ``--disparity-bias``, ``--largest-ring``, ``--known-ring`` and ``--lit-rim`` (the light
    from ``scenario``: a lamp's with ``lamp``, a lamp's or the sun's with ``all``) if given."""
    c = load_config(PipelineConfig, args.config) if args.config else PipelineConfig()
    if args.interpolation is not None:
        pre = replace(c.frontend.preprocess, interpolation=args.interpolation)
        c = replace(c, frontend=replace(c.frontend, preprocess=pre))
    if args.lit_rim == "all" or (args.lit_rim == "lamp" and scenario.light.kind == "point"):
        c = lit_rim(c, scenario.light)
    if args.largest_ring:
        sr = replace(c.frontend.stereo_ring, behind_sigma=None)
        c = replace(c, frontend=replace(c.frontend, stereo_ring=sr))
    if args.known_ring:
        sr = replace(c.frontend.stereo_ring, known_ring=known_ring(scenario, args.known_ring))
        c = replace(c, frontend=replace(c.frontend, stereo_ring=sr))
    if args.disparity_bias is None and args.landmark_bias is None and args.consider is None:
        return c
    m = replace(
        c.backend.measurements,
        ring_disparity_bias_px=args.disparity_bias,
        landmark_disparity_bias_px=args.landmark_bias,
        ring_disparity_consider_px=args.consider,
    )
    return replace(c, backend=replace(c.backend, measurements=m))


def variant_words(args: argparse.Namespace) -> list[str]:
    """The words that name a scored variant in its run folders and its page's name (the
    options that change what is run: ``--lit-rim``, ``--known-ring``, ``--interpolation``,
    ``--consider``, ``--config``)."""
    return [
        w
        for w in (
            f"lit_rim_{args.lit_rim}" if args.lit_rim else "",
            f"known_{args.known_ring}" if args.known_ring else "",
            args.interpolation or "",
            "consider" if args.consider is not None else "",
            args.config.stem if args.config is not None else "",
        )
        if w
    ]


def member(seed: int, args: argparse.Namespace) -> tuple[Scenario, dict[str, Any]]:
    """The family member ``seed`` at the benchmark's frames, size and samples, and the
    start of its table row (the scene)."""
    draw = random_draw(seed)
    s = scaled(draw.scenario, frames=args.frames, size=args.size, spp=args.spp)
    m = s.motion
    return s, {
        "seed": seed,
        "ring": f"{s.target.ring.outer_radius_m:.2f}/{s.target.ring.height_m:.2f}",
        "rim": draw.rim,
        "light": draw.light,
        "motion": draw.motion,
        "tilt": m.facing_tilt_deg,
        "range": float(np.linalg.norm(m.start_position_m)),
    }


def one(seed: int, args: argparse.Namespace) -> dict[str, Any]:
    s, row = member(seed, args)
    tag = f"{seed}-{s.rig.width}x{s.rig.height}-{s.render.spp}spp-{s.frames}f"
    seq = args.root / tag
    run = args.root / "-".join([f"{tag}-run", *variant_words(args)])
    try:
        if not (seq / "frames.csv").is_file():
            render_sequence(s, seq, overwrite=True)
        start = time.process_time()
        run_pipeline(seq, "online", run, pipeline_config(args, s), overwrite=True)
        row["cpu_s"] = time.process_time() - start
        res = evaluate_run(seq, run)
        for name, key in (("per-frame (frontend)", "fe"), ("offline", "off")):
            r = res.get(name)
            if r is None:
                continue
            row[f"{key}_frames"] = r.frames
            row[f"{key}_pos"] = r.pos_cm
            row[f"{key}_rot"] = r.rot_deg
            row[f"{key}_bias"] = r.bias
        for name, key in (("offline", "nees_off"), ("online filtered", "nees_on")):
            if name in res and res[name].nees_in_95 is not None:
                row[key] = res[name].nees_in_95
        row.update(ring_checks(seq, run, s))
        row["status"] = "ok"
    except SatposeError as exc:  # a clear refusal (e.g. no frame gave a pose)
        row["status"] = f"refused: {str(exc).splitlines()[0][:120]}"
    except Exception as exc:  # a bug: recorded, and the benchmark goes on
        row["status"] = f"exception: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
        traceback.print_exc()
    print({k: v for k, v in row.items() if not k.endswith("_bias")}, flush=True)
    return row


def score(seeds: list[int], args: argparse.Namespace) -> list[dict[str, Any]]:
    """`one` per seed, in seed order: in this process, or with ``args.jobs`` > 1 in that
    many worker processes (fresh interpreters: no state inherited between members). A worker
    that dies (a crash below Python) is that member's exception row, and the others go on."""
    if args.jobs == 1:
        return [one(seed, args) for seed in seeds]
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=ctx) as pool:
        futures = [pool.submit(one, seed, args) for seed in seeds]
        rows = []
        for seed, fut in zip(seeds, futures, strict=True):
            try:
                rows.append(fut.result())
            except Exception as exc:  # the worker itself failed, not the pipeline
                why = str(exc).splitlines()[0][:120] if str(exc) else ""
                row = member(seed, args)[1]
                row["status"] = f"exception: {type(exc).__name__}: {why}"
                rows.append(row)
    return rows


def _f(x: Any, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def markdown(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    ok = [r for r in rows if r["status"] == "ok" and "fe_pos" in r]
    lines = [
        f"# Stereo pipeline on the random family: {args.set} seeds",
        "",
        f"Generated by `python benchmarks/random_family.py --set {args.set} --count "
        f"{args.count}"
        + (f" --first {args.first}" if args.first else "")
        + f" --frames {args.frames} --size {args.size[0]}x{args.size[1]} --spp "
        f"{args.spp}"
        + ("" if args.disparity_bias is None else f" --disparity-bias {args.disparity_bias:g}")
        + ("" if args.landmark_bias is None else f" --landmark-bias {args.landmark_bias:g}")
        + (" --largest-ring" if args.largest_ring else "")
        + (f" --lit-rim {args.lit_rim}" if args.lit_rim else "")
        + (f" --interpolation {args.interpolation}" if args.interpolation else "")
        + ("" if args.consider is None else f" --consider {args.consider:g}")
        + ("" if args.config is None else f" --config {args.config}")
        + ("" if args.out is None else f" --out {args.out}")
        + ("" if args.jobs == 1 else f" --jobs {args.jobs}")
        + f"` ({machine_summary()}; {time.strftime('%Y-%m-%d')}). Do not edit by hand.",
        "",
        "Per sequence: per-frame (frontend) and offline-smoother mean errors (position of the "
        "ring centre; rotation after the constant body offset of a non-cooperative frame), the "
        "bias (mean) / random part (sd) of the frontend's signed depth [cm], lateral [cm] and "
        "tilt [deg] errors (**defect**: a bias above a third of its random part), the NEES "
        "in-band fractions (offline, online), and the ring over the frames with >= 80 % of "
        "the rim in view: frames with a ring on the outer front rim (radius within 2 %), the "
        "mean radius error and the median ellipse-centre error against the projected true rim.",
        "",
    ]
    if ok:
        fe_pos = np.array([r["fe_pos"] for r in ok])
        fe_rot = np.array([r["fe_rot"] for r in ok])
        # the smoother's figures over every sequence with a trajectory, per-frame pose or not
        smoothed = [r for r in rows if r["status"] == "ok"]
        off_pos = np.array([r.get("off_pos", np.nan) for r in smoothed])
        off_rot = np.array([r.get("off_rot", np.nan) for r in smoothed])
        centre = np.array([r.get("centre_px", np.nan) for r in smoothed])
        outer = np.array([r.get("outer_frac", np.nan) for r in smoothed])
        # a sequence without a per-frame pose (or refused, or ended in an exception) is not
        # within the paper: the fraction is over every sequence scored
        paper = np.sum((fe_pos <= PAPER[0]) & (fe_rot <= PAPER[1])) / len(rows)
        offline_only = sum(r["status"] == "ok" and "fe_pos" not in r for r in rows)
        nees_off = np.array([r.get("nees_off", np.nan) for r in smoothed])
        nees_on = np.array([r.get("nees_on", np.nan) for r in smoothed])
        defects = sum(bool(r["fe_bias"].defects()) for r in ok)
        refused = sum(r["status"].startswith("refused") for r in rows)
        crashed = sum(r["status"].startswith("exception") for r in rows)
        summary = [
            (
                "sequences with a per-frame pose / a smoothed trajectory only / refused (no "
                "pose) / ended in an exception",
                f"{len(ok)} / {offline_only} / {refused} / {crashed}",
                "- / - / - / 0",
            ),
            (
                "per-frame pos, median [cm] (sequences with a per-frame pose)",
                _f(np.median(fe_pos), ".2f"),
                "<= 1.0",
            ),
            ("per-frame rot, median [deg]", _f(np.median(fe_rot), ".2f"), "<= 0.5"),
            (
                "sequences within the paper (1.74 cm and 0.94 deg; of all sequences)",
                f"{100 * paper:.0f} %",
                ">= 95 %",
            ),
            (
                "offline pos, median [cm] (sequences with a trajectory)",
                _f(np.nanmedian(off_pos), ".2f"),
                "<= 0.4",
            ),
            ("offline rot, median [deg]", _f(np.nanmedian(off_rot), ".2f"), "<= 0.2"),
            (
                "ring on the outer front rim (frames, pooled)",
                f"{100 * np.nanmean(outer):.0f} %",
                ">= 98 %",
            ),
            ("ellipse centre error, median [px]", _f(np.nanmedian(centre), ".2f"), "<= 0.3"),
            (
                "offline NEES in its 95 % band in >= 80 % of frames",
                f"{100 * np.nanmean(nees_off >= 0.8):.0f} % of seqs",
                ">= 80 %",
            ),
            (
                "online NEES in its 95 % band in >= 80 % of frames",
                f"{100 * np.nanmean(nees_on >= 0.8):.0f} % of seqs",
                ">= 80 %",
            ),
            ("sequences with a bias defect (frontend)", f"{defects} of {len(ok)}", "0"),
        ]
        lines += ["## Summary", "", "| measure | value | target |", "|---|---|---|"]
        lines += [f"| {a} | {b} | {c} |" for a, b, c in summary]
        lines.append("")
    lines += [
        "## Sequences",
        "",
        "| seed | ring r/h [m] | rim | light | motion | tilt [deg] | range [m] | frames (fe) | "
        "fe pos [cm] | fe rot [deg] | off pos [cm] | off rot [deg] | depth bias/sd [cm] | "
        "lateral bias/sd [cm] | tilt bias/sd [deg] | defect | NEES in band off/on | "
        "outer rim | radius bias [mm] | centre [px] | status |",
        "|" + "---|" * 21,
    ]
    for r in rows:
        b = r.get("fe_bias")
        bias = (
            [
                f"{b.depth_cm:+.2f}/{b.depth_sd_cm:.2f}",
                f"{b.lateral_cm:.2f}/{b.lateral_sd_cm:.2f}",
                f"{b.tilt_deg:+.2f}/{b.tilt_sd_deg:.2f}",
                ", ".join(b.defects()) or "-",
            ]
            if b is not None
            else ["-"] * 4
        )
        lines.append(
            "| "
            + " | ".join(
                [
                    str(r["seed"]),
                    r["ring"],
                    r["rim"],
                    r["light"],
                    r["motion"],
                    f"{r['tilt']:.0f}",
                    f"{r['range']:.1f}",
                    f"{r.get('fe_frames', 0)}/{args.frames}",
                    _f(r.get("fe_pos"), ".2f"),
                    _f(r.get("fe_rot"), ".2f"),
                    _f(r.get("off_pos"), ".2f"),
                    _f(r.get("off_rot"), ".2f"),
                    *bias,
                    f"{_f(r.get('nees_off'), '.2f')}/{_f(r.get('nees_on'), '.2f')}",
                    _f(r.get("outer_frac"), ".2f"),
                    _f(r.get("radius_bias_mm"), "+.1f"),
                    _f(r.get("centre_px"), ".2f"),
                    r["status"],
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=["tuning", "validation"], default="validation")
    parser.add_argument("--count", type=int, default=40, help="N seeds of the set")
    parser.add_argument(
        "--first", type=int, default=0, help="skip the set's first seeds (index, not seed)"
    )
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument(
        "--size", type=lambda s: tuple(int(v) for v in s.split("x")), default=DEFAULT_SIZE
    )
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--root", type=Path, default=Path("runs/random"))
    parser.add_argument(
        "--disparity-bias",
        type=float,
        metavar="PX",
        help="the backend's ring_disparity_bias_px (default: the backend's default, off)",
    )
    parser.add_argument(
        "--landmark-bias",
        type=float,
        metavar="PX",
        help="the backend's landmark_disparity_bias_px (default: the backend's default, off)",
    )
    parser.add_argument(
        "--consider",
        type=float,
        metavar="PX",
        help="the backend's ring_disparity_consider_px (default: the backend's default)",
    )
    parser.add_argument(
        "--largest-ring",
        action="store_true",
        help="the old ring choice: the largest consistent pair wins (stereo_ring.behind_sigma: "
        "null)",
    )
    parser.add_argument(
        "--lit-rim",
        choices=["lamp", "all"],
        help="the ring refitted where no shadow of it shows beside the rim (rim.labels: light, "
        "the scene's light stated as the user would; docs/frontend.md): in the lamp-lit "
        "scenes only, or in all (the sun's direction too)",
    )
    parser.add_argument(
        "--known-ring",
        choices=["radius", "full"],
        help="state each member's ring as a user of a standard interface would "
        "(stereo_ring.known_ring): its outer radius, or its full dimensions (outer and inner "
        "radius, wall height, lip)",
    )
    parser.add_argument(
        "--interpolation",
        choices=["linear", "cubic", "lanczos4"],
        help="the stereo frontend's preprocess.interpolation (the undistortion's resampling; "
        "default: the config's)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        help="a `satpose run` configuration (YAML) to score instead of the default; the "
        "options above apply on top; runs and page are named after its file",
    )
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="sequences scored at once, each in its own process (results do not depend on "
        "it; the CPU times of a loaded machine do)",
    )
    args = parser.parse_args()
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: must be >= 1")
    seeds = list(TUNING_SEEDS if args.set == "tuning" else VALIDATION_SEEDS)[
        args.first : args.first + args.count
    ]
    if not seeds:
        parser.error(f"--first {args.first} --count {args.count}: no seed of the {args.set} set")
    rows = score(seeds, args)
    suffix = "".join(f"_{w}" for w in variant_words(args))
    suffix += f"_from_{seeds[0]}" if args.first else ""
    # the family's own image size (the rig's, 1024x768) has the plain page names; a scaled
    # run says its size (640x480: the faster proxy used before, docs/frontend.md)
    suffix += "" if tuple(args.size) == DEFAULT_SIZE else f"_{args.size[0]}x{args.size[1]}"
    out = args.out or Path(f"docs/results/random_family_{args.set}{suffix}.md")
    write_page(out, markdown(rows, args))


if __name__ == "__main__":
    main()
