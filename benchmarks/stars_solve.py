"""Lost in space on real star images (issue 18) against an independent solver.

Writes docs/results/stars_solve.md: per image, ``satpose stars solve``'s solution
(`satpose.frontend.star_images.solve_image`) against the cedar-solve reference
(tests/data/tetra3/reference.csv, made by benchmarks/stars_solve_reference.py): boresight
difference, roll difference, field-of-view difference, matches, CPU time. Run from the
repository root::

    python benchmarks/stars_solve.py                      # the three committed frames
    python benchmarks/stars_solve.py --images TETRA3/test_data   # all eight

CPU time: `time.process_time` (all threads of the process) around extraction,
identification, refinement and verification, the median of ``--repeats`` solves after one
warm-up solve; the tetra3rs database is built once per process and reported separately.
"""

from __future__ import annotations

import argparse
import datetime
import math
import statistics
import time
from importlib.metadata import version
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from _common import machine_summary, write_page

from satpose.frontend.star_images import (
    StarSolution,
    StarSolveConfig,
    database_fov_range,
    extract_stars,
    radec_roll_deg,
    solve_image,
)
from satpose.frontend.stars import ARCSEC, solver_catalogue, solver_database

KNOWN = StarSolveConfig(fov_ranges_deg=((10.4, 12.4),), epoch_yr=2019.58)
UNKNOWN = StarSolveConfig(epoch_yr=2019.58)


def sep_arcsec(ra1: float, dec1: float, ra2: float, dec2: float) -> float:
    a = np.radians([ra1, dec1, ra2, dec2])
    u = np.array([math.cos(a[1]) * math.cos(a[0]), math.cos(a[1]) * math.sin(a[0]), math.sin(a[1])])
    v = np.array([math.cos(a[3]) * math.cos(a[2]), math.cos(a[3]) * math.sin(a[2]), math.sin(a[3])])
    return math.degrees(math.atan2(np.linalg.norm(np.cross(u, v)), float(u @ v))) * 3600


def db_build_s(config: StarSolveConfig, width: int, height: int) -> float:
    t = time.process_time()
    lo, hi = database_fov_range(config.fov_ranges_deg[0], width, height)
    solver_database(lo, hi, config.epoch_yr)
    solver_catalogue(lo, hi, config.epoch_yr)
    return time.process_time() - t


def timed(img: np.ndarray, config: StarSolveConfig, repeats: int) -> tuple[StarSolution, float]:
    sols = [solve_image(img, config) for _ in range(repeats)]
    return sols[-1], statistics.median(s.cpu_ms for s in sols)


def compare(sol: StarSolution, ref: pd.Series) -> dict[str, float]:
    if sol.R is None or sol.camera is None or sol.cov is None:
        return {}
    ra, dec, roll = radec_roll_deg(sol.R)
    d_roll = ((roll - ref.roll_deg + 180) % 360 - 180) * 3600
    sig = np.sqrt(np.diag(sol.cov)) / ARCSEC
    return {
        "boresight": sep_arcsec(ra, dec, ref.ra_deg, ref.dec_deg),
        "roll": d_roll,
        "fov_pct": (sol.camera.fov_deg / ref.fov_deg - 1) * 100,
        "fov": sol.camera.fov_deg,
        "k": sol.camera.k,
        "sig_cross": math.sqrt(0.5 * (sig[0] ** 2 + sig[1] ** 2)),
        "sig_roll": sig[2],
        "rmse": sol.rmse_arcsec,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, default=Path("tests/data/tetra3"))
    ap.add_argument("--reference", type=Path, default=Path("tests/data/tetra3/reference.csv"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/stars_solve.md"))
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    ref = pd.read_csv(args.reference, comment="#").set_index("image")
    ref_header = [
        line[2:].strip()
        for line in args.reference.read_text(encoding="utf-8").splitlines()
        if line.startswith("#")
    ]
    paths = sorted(
        p for p in args.images.iterdir() if p.suffix.lower() in (".tif", ".tiff", ".png")
    )
    paths = [p for p in paths if p.stem in ref.index]
    images = {p.stem: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths}
    h, w = next(iter(images.values())).shape[:2]
    db_known = db_build_s(KNOWN, w, h)
    db_unknown = db_build_s(UNKNOWN, w, h)
    first = next(iter(images.values()))
    solve_image(first, KNOWN)  # warm-up (first calls into numpy/scipy/OpenCV)
    solve_image(first, UNKNOWN)

    rows, rows_u = [], []
    for stem, img in images.items():
        ext = []
        for _ in range(args.repeats):
            t = time.process_time()
            extract_stars(img, KNOWN.extraction)
            ext.append((time.process_time() - t) * 1e3)
        sol, cpu = timed(img, KNOWN, args.repeats)
        r = ref.loc[stem]
        rows.append(
            {"image": stem, "status": sol.status, "reason": sol.reason, "cpu": cpu}
            | {"ext": statistics.median(ext), "m": sol.star_ids.size, "cedar_m": r.matches}
            | {"cedar_k": r.distortion, "cedar_rmse": r.rmse_arcsec}
            | compare(sol, r)
        )
        sol_u, cpu_u = timed(img, UNKNOWN, args.repeats)
        rows_u.append(
            {"image": stem, "status": sol_u.status, "cpu": cpu_u, "m": sol_u.star_ids.size}
            | compare(sol_u, r)
        )

    solved = [x for x in rows if x["status"] == "solved"]
    worst = {
        k: max((abs(x[k]) for x in solved), default=math.nan)
        for k in ("boresight", "roll", "fov_pct", "cpu")
    }

    def met(ok: bool) -> str:
        return "met" if ok else "**not met**"

    n = len(rows)
    default_images = ap.get_default("images")
    images_arg = "" if args.images == default_images else " --images TETRA3/test_data"
    lines = [
        "# Lost in space on real star images (issue 18): satpose vs cedar-solve",
        "",
        f"Generated by `python benchmarks/stars_solve.py{images_arg}` on {n} frames "
        f"({machine_summary(libraries=False)}, tetra3rs {version('tetra3rs')}, "
        f"{datetime.date.today().isoformat()}). Do not edit by hand.",
        "",
        "Images: esa/tetra3 `test_data/` (FLIR Blackfly S, 1024x768, 16-bit TIFF, 11.4 deg; "
        "credit: tests/data/tetra3/README.md). Reference: `tests/data/tetra3/reference.csv`:",
        "",
        *[f"> {line}" for line in ref_header],
        "",
        "satpose: `satpose stars solve --fov-deg 11.4 --fov-tolerance-deg 1 --epoch-yr 2019.58` "
        "(field of view 10.4-12.4 deg; radial distortion fitted). Boresight: angle between the "
        "two solvers' image-centre directions; roll: ours minus the reference's `roll_deg` "
        "(`180 - cedar Roll`, docs/stars.md); field of view: horizontal, edge to edge, "
        f"through the distortion. CPU: median of {args.repeats} solves after a warm-up, "
        "extraction included, `time.process_time` (all threads); the tetra3rs database is "
        f"built once per process: {db_known:.1f} s CPU for 10.4-12.4 deg, "
        f"{db_unknown:.1f} s for 8-25 deg (the default search's first band, where these "
        "frames solve).",
        "",
        "## Targets",
        "",
        "| target | measured | |",
        "|---|---|---|",
        f"| all frames solved | {len(solved)}/{n} | {met(len(solved) == n)} |",
        f"| boresight within 10 arcsec of the independent solver | worst "
        f"{worst['boresight']:.1f} arcsec | {met(worst['boresight'] <= 10)} |",
        f"| roll within 60 arcsec | worst {worst['roll']:.1f} arcsec | "
        f"{met(worst['roll'] <= 60)} |",
        f"| field of view within 0.05 % | worst {worst['fov_pct']:.4f} % | "
        f"{met(worst['fov_pct'] <= 0.05)} |",
        f"| <= 50 ms CPU per image including extraction | worst {worst['cpu']:.1f} ms | "
        f"{met(worst['cpu'] <= 50)} |",
        "",
        "## Per image, field of view known within 1 deg",
        "",
        "| image | status | boresight diff [arcsec] | roll diff [arcsec] | fov [deg] | "
        "fov diff [%] | matches (cedar) | RMS [arcsec] (cedar) | 1-sigma cross / roll "
        "[arcsec] | k (cedar distortion) | extraction [ms] | CPU [ms] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in rows:
        if x["status"] != "solved":
            lines.append(f"| {x['image']} | {x['reason']} |" + " |" * 10)
            continue
        lines.append(
            f"| {x['image']} | solved | {x['boresight']:.1f} | {x['roll']:+.1f} | "
            f"{x['fov']:.4f} | {x['fov_pct']:+.4f} | {x['m']} ({int(x['cedar_m'])}) | "
            f"{x['rmse']:.1f} ({x['cedar_rmse']:.1f}) | {x['sig_cross']:.2f} / "
            f"{x['sig_roll']:.1f} | {x['k']:+.5f} ({x['cedar_k']:+.5f}) | {x['ext']:.1f} | "
            f"{x['cpu']:.1f} |"
        )
    lines += [
        "",
        "## Per image, field of view unknown (default search: 8-25, 25-70, 3-8 deg)",
        "",
        "| image | status | boresight diff [arcsec] | roll diff [arcsec] | fov diff [%] | "
        "matches | CPU [ms] |",
        "|---|---|---|---|---|---|---|",
    ]
    for x in rows_u:
        if x["status"] != "solved":
            lines.append(f"| {x['image']} | {x['status']} | | | | | {x['cpu']:.1f} |")
            continue
        lines.append(
            f"| {x['image']} | solved | {x['boresight']:.1f} | {x['roll']:+.1f} | "
            f"{x['fov_pct']:+.4f} | {x['m']} | {x['cpu']:.1f} |"
        )
    lines += [
        "",
        "Notes: both solvers use catalogue (astrometric) places without annual aberration "
        "(up to about 20 arcsec, common to both); cedar-solve's database is Hipparcos at "
        "epoch 2024.0, ours tetra3rs' Gaia at 2019.58. Cedar reports fewer matches (its own "
        "centroider and matching; not investigated). Part of the roll differences is the "
        "reference's own roll error (17-51 stars). The 1-sigma columns are our covariance "
        "(scaled by the reduced chi-square).",
        "",
    ]
    write_page(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
