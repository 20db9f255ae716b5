"""``satpose stars solve IMAGE... --out DIR``: lost in space on real star images (issue 18).

Reads each image (16-bit TIFF/PNG, 8-bit JPEG/PNG; FITS is not read: astropy is not a
dependency), solves it with `satpose.frontend.star_images.solve_image` and writes, into a
folder staged under a temporary name and renamed when complete:

- ``solutions.csv``: one row per image, columns `CSV_COLUMNS` (docs/stars.md).
- ``overlays/<stem>.png``: the image (stretched to 8 bit) with the verified stars circled
  and labelled with their catalogue ids, or the spots and the reason for no solution.
- ``config.yaml``: the resolved solve config.

A missing input file is a one-line error before anything is done; an image that exists but
cannot be decoded is a ``no_solution`` row with the reason.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import yaml

from satpose.datasets.config import to_plain
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import matrix_to_quat_xyzw
from satpose.datasets.sequence import replace_dir
from satpose.frontend.star_images import (
    StarSolution,
    StarSolveConfig,
    no_solution,
    radec_roll_deg,
    solve_image,
    to_gray,
)
from satpose.frontend.stars import ARCSEC, StarTrackerError

CSV_COLUMNS = [
    "image",
    "status",
    "ra_deg",
    "dec_deg",
    "roll_deg",
    "fov_deg",
    "qx",
    "qy",
    "qz",
    "qw",
    "matches",
    "rmse_arcsec",
    "sigma_cross_arcsec",
    "sigma_roll_arcsec",
    "cpu_ms",
    "reason",
    "distortion_k",
    "focal_px",
    "spots",
    "predicted",
    "false_alarm",
    "fov_band_deg",
]
"""Leading columns fixed by issue 18, then diagnostics (`solution_row`)."""

FITS_SUFFIXES = (".fits", ".fit", ".fts")


class StarImageError(SatposeError):
    """An image file that cannot be read as a star image."""


def read_sky_image(path: Path) -> np.ndarray:
    """The pixels of one image file as stored (uint8/uint16/float, gray or colour).

    OpenCV reads 8- and 16-bit TIFF, PNG and JPEG unchanged (no tifffile needed). Raises
    `StarImageError` naming the file for FITS, unreadable or undecodable files.
    """
    if path.suffix.lower() in FITS_SUFFIXES:
        raise StarImageError(f"{path}: FITS is not supported (astropy is not a dependency)")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise StarImageError(f"{path}: cannot read ({exc.strerror or exc})") from None
    # OpenCV logs libtiff/libpng complaints about a broken file to stderr; the reason is
    # reported once, by the caller.
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None or img.size == 0:
        raise StarImageError(f"{path}: cannot decode the image (corrupt or not an image)")
    return img


def solution_row(image: str, sol: StarSolution) -> dict[str, Any]:
    """One ``solutions.csv`` row. ``sigma_cross_arcsec``: the root mean of the two
    cross-boresight variances; ``sigma_roll_arcsec``: about the boresight (1 sigma)."""
    row: dict[str, Any] = dict.fromkeys(CSV_COLUMNS, math.nan)
    row.update(image=image, status=sol.status, reason=sol.reason, cpu_ms=sol.cpu_ms)
    row["matches"] = int(sol.star_ids.size)
    row["spots"] = len(sol.stars) if sol.stars is not None else 0
    row["predicted"] = sol.predicted
    if sol.R is not None and sol.cov is not None and sol.camera is not None:
        ra, dec, roll = radec_roll_deg(sol.R)
        q = matrix_to_quat_xyzw(sol.R)
        row.update(ra_deg=ra, dec_deg=dec, roll_deg=roll, fov_deg=sol.camera.fov_deg)
        row.update(qx=q[0], qy=q[1], qz=q[2], qw=q[3])
        var = np.diag(sol.cov)
        row["sigma_cross_arcsec"] = math.sqrt(0.5 * (var[0] + var[1])) / ARCSEC
        row["sigma_roll_arcsec"] = math.sqrt(var[2]) / ARCSEC
        row["rmse_arcsec"] = sol.rmse_arcsec
        row["distortion_k"] = sol.camera.k
        row["focal_px"] = sol.camera.f_px
        row["false_alarm"] = sol.false_alarm
    if sol.band_deg is not None:  # the band whose database identified the stars
        row["fov_band_deg"] = f"{sol.band_deg[0]:g}-{sol.band_deg[1]:g}"
    return row


def stretch_8bit(image: np.ndarray) -> np.ndarray:
    """A gray 8-bit view of a sky image: 1st to 99.8th percentile, square-root stretch."""
    img = to_gray(image).astype(np.float32)  # the gray the extraction sees
    lo, hi = np.percentile(img[::4, ::4], [1.0, 99.8])
    v = np.clip((img - lo) / max(float(hi - lo), 1e-6), 0, 1)
    return (np.sqrt(v) * 255).astype(np.uint8)


def draw_overlay(
    image: np.ndarray | None, sol: StarSolution, title: str, path: Path, labels: int = 40
) -> None:
    """Overlay PNG: verified stars circled in green (the ``labels`` brightest with their
    catalogue ids), other spots in red, and two status lines (solution or reason)."""
    if image is None:
        canvas = np.zeros((240, 640, 3), np.uint8)
    else:
        canvas = cv2.cvtColor(stretch_8bit(image), cv2.COLOR_GRAY2BGR)
    w = canvas.shape[1]
    font, green = cv2.FONT_HERSHEY_SIMPLEX, (80, 230, 80)
    if sol.stars is not None:
        for x, y in sol.stars.px:
            cv2.circle(canvas, (round(x), round(y)), 6, (60, 60, 230), 1, cv2.LINE_AA)
    labelled = set(np.argsort(sol.star_mag)[:labels].tolist())
    for k, ((x, y), sid) in enumerate(zip(sol.px, sol.star_ids, strict=True)):
        p = (round(x), round(y))
        cv2.circle(canvas, p, 9, green, 1, cv2.LINE_AA)
        if k in labelled:
            cv2.putText(canvas, str(int(sid)), (p[0] + 10, p[1] - 6), font, 0.35, green, 1)
    if sol.R is not None and sol.camera is not None:
        ra, dec, roll = radec_roll_deg(sol.R)
        lines = [
            f"{title}: solved, {sol.star_ids.size} stars, {sol.rmse_arcsec:.1f} arcsec RMS",
            f"RA {ra:.4f}  Dec {dec:.4f}  roll {roll:.3f}  FOV {sol.camera.fov_deg:.4f} deg",
        ]
    else:
        lines = [f"{title}: no solution", sol.reason]
    cv2.rectangle(canvas, (0, 0), (w, 40), (0, 0, 0), -1)
    for i, line in enumerate(lines):
        cv2.putText(canvas, line, (6, 16 + 18 * i), font, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), canvas):
        raise StarImageError(f"{path}: cannot write the overlay")


@dataclass(frozen=True)
class SolveRun:
    """What `solve_images` did: one row per image and the solutions."""

    rows: list[dict[str, Any]]
    solutions: list[StarSolution]


def solve_images(
    images: list[Path], out: Path, config: StarSolveConfig, overwrite: bool = False
) -> SolveRun:
    """Solve every image and write ``out`` (module docstring), atomically.

    Raises `SatposeError` (one line) for a missing input or an existing ``out`` without
    ``overwrite``; an image that cannot be decoded or solved is a recorded failure.
    """
    from tqdm import tqdm

    for p in images:
        if not p.is_file():
            raise StarImageError(f"{p}: no such file")
    if out.exists() and not overwrite:
        raise StarImageError(f"{out}: output folder already exists (use --overwrite)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
        (tmp / "overlays").mkdir(parents=True)
    except OSError as exc:
        raise StarImageError(f"{out}: cannot create the output folder ({exc})") from None
    rows, sols = [], []
    try:
        used: set[str] = set()
        for k, p in enumerate(tqdm(images, desc="stars solve", unit="image", delay=0.5)):
            img: np.ndarray | None = None
            try:
                img = read_sky_image(p)
                sol = solve_image(img, config)
            except (StarImageError, StarTrackerError) as exc:
                msg = str(exc)
                sol = no_solution(msg[len(str(p)) + 2 :] if msg.startswith(str(p)) else msg)
            rows.append(solution_row(str(p), sol))
            sols.append(sol)
            stem = p.stem if p.stem not in used else f"{p.stem}_{k}"
            used.add(stem)
            draw_overlay(img, sol, p.name, tmp / "overlays" / f"{stem}.png")
        df = pd.DataFrame(rows, columns=CSV_COLUMNS)
        df.to_csv(tmp / "solutions.csv", index=False, float_format="%.9g")
        meta = {"images": [str(p) for p in images], "solve": to_plain(config)}
        (tmp / "config.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
        replace_dir(tmp, out, overwrite)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return SolveRun(rows, sols)


def summary(run: SolveRun, out: Path) -> str:
    """The one-line summary ``satpose stars solve`` prints."""
    n = len(run.rows)
    solved = [r for r in run.rows if r["status"] == "solved"]
    cpu = np.median([r["cpu_ms"] for r in run.rows]) if run.rows else 0.0
    text = f"{len(solved)}/{n} solved"
    if solved:
        m = [r["matches"] for r in solved]
        text += f" ({min(m)}-{max(m)} stars matched)"
    text += f", median {cpu:.0f} ms CPU per image; wrote {out}/solutions.csv and overlays/"
    return text


def config_from_args(args: argparse.Namespace) -> StarSolveConfig:
    """`StarSolveConfig` from the command line (field-of-view range, epoch, distortion)."""
    c = StarSolveConfig()
    if args.fov_range is not None and args.fov_deg is not None:
        raise StarImageError("give --fov-deg (with --fov-tolerance-deg) or --fov-range, not both")
    if args.fov_tolerance_deg is not None and args.fov_deg is None:
        raise StarImageError("--fov-tolerance-deg needs --fov-deg")
    kw: dict[str, Any] = {"fit_distortion": not args.no_distortion}
    if args.fov_deg is not None:
        tol = args.fov_tolerance_deg if args.fov_tolerance_deg is not None else 0.1 * args.fov_deg
        kw["fov_ranges_deg"] = ((args.fov_deg - tol, args.fov_deg + tol),)
    elif args.fov_range is not None:
        kw["fov_ranges_deg"] = (tuple(args.fov_range),)
    if args.epoch_yr is not None:
        kw["epoch_yr"] = args.epoch_yr
    return replace(c, **kw)


def _cmd_solve(args: argparse.Namespace) -> None:
    config = config_from_args(args)
    run = solve_images(args.images, args.out, config, overwrite=args.overwrite)
    print(summary(run, args.out))
    sys.stdout.flush()


def register_solve(sub: Any) -> None:
    """Add ``solve`` to ``satpose stars`` (tools/stars.py ``register``)."""
    s = sub.add_parser(
        "solve",
        help="lost in space on real star images: attitude, field of view, distortion",
        description="Identify the stars in each image and write OUT/solutions.csv "
        "(inertial_from_camera, RA/Dec/roll, field of view, 1-sigma), one overlay PNG per "
        "image and config.yaml (docs/stars.md).",
    )
    s.add_argument("images", type=Path, nargs="+", metavar="IMAGE", help="TIFF, PNG or JPEG")
    s.add_argument("--out", type=Path, required=True, metavar="DIR")
    s.add_argument("--fov-deg", type=float, help="approximate horizontal field of view [deg]")
    s.add_argument(
        "--fov-tolerance-deg", type=float, help="+- around --fov-deg (default 10 %% of it)"
    )
    s.add_argument(
        "--fov-range",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        help="horizontal field of view range [deg] (default: 8-25, then 25-70, then 3-8)",
    )
    s.add_argument("--epoch-yr", type=float, help="observation epoch for proper motions")
    s.add_argument("--no-distortion", action="store_true", help="do not fit radial distortion")
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(handler=_cmd_solve)


__all__ = [
    "CSV_COLUMNS",
    "StarImageError",
    "read_sky_image",
    "register_solve",
    "solution_row",
    "solve_images",
]
