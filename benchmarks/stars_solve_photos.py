"""Lost in space on other cameras' sky photos and on no-star pictures (issue 18).

Writes docs/results/stars_solve_photos.md: for every image of tests/data/sky_photos/images.csv
(other cameras, fields of view, JPEGs, partial skies, light pollution, and pictures without
a star field: daytime photos, a lit object, dark frames with hot pixels, a dot chart, a raw
Bayer frame), `satpose.frontend.star_images.solve_image` twice — field of view unknown (the
default search) and known within 10 % (``--fov-deg``) — against the independent solutions
in tests/data/sky_photos/reference.csv (astrometry.net and cedar-solve, made by
benchmarks/stars_solve_photos_reference.py). Run from the repository root::

    python benchmarks/stars_solve_photos.py --data DATA

``DATA`` holds one folder per source (docs/stars.md, "Other cameras", says where each comes
from); the committed images alone: ``--data tests/data`` (the others are reported missing).

An image is *solvable* when an independent solver solved it and its horizontal field lies
in the range satpose searches (`SUPPORTED_FOV_DEG`); a solution of ours is *right* when it
agrees with one of the reference solutions within `AGREE_PX` pixels: at the boresight, and at
the ends of the image's middle row for roll and field of view (the sky then lands within
`AGREE_PX` of the reference's place along that row); *wrong* otherwise; a solution without
any reference is *unverified*. The references are astrometry.net with SIP distortion of order
1, 2 and 3 and cedar-solve (benchmarks/stars_solve_photos_reference.py): they differ among
themselves by several pixels on wide lenses and sparse fields, and no one of them is right
for every picture. Targets: every solvable image solved, every no-star picture refused, no wrong
and no unverified solution. CPU: `time.process_time` of one solve (extraction included);
the tetra3rs databases (one per field-of-view band and image aspect ratio, four kept per
process) are built when first needed and not counted there: their CPU has a column of its
own. Images are run grouped by aspect ratio, so each database is built once; the page is
rewritten after every image (a stopped run leaves a page saying how far it got).

The verification is checked on wrong attitudes too: for every image a reference solved,
`WRONG_TRIALS` attitudes (half uniformly random, half the reference's boresight moved by
0.3-5 deg) go through `check_attitude` with the reference's field of view; none may pass.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import math
import time
from dataclasses import replace
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
from _common import machine_summary, write_page

from satpose.datasets.geometry import rotvec_to_matrix
from satpose.frontend.star_images import (
    SkyCamera,
    StarSolution,
    StarSolveConfig,
    _false_alarm_bright,
    _match,
    _predict,
    check_attitude,
    database_fov_range,
    extract_stars,
    fov_to_focal,
    match_radius,
    radec_roll_deg,
    solve_image,
)
from satpose.frontend.stars import solver_catalogue
from satpose.tools.stars_solve import read_sky_image

IMAGES = Path("tests/data/sky_photos/images.csv")
REFERENCE = Path("tests/data/sky_photos/reference.csv")
SUPPORTED_FOV_DEG = (
    min(lo for lo, _ in StarSolveConfig().fov_ranges_deg),
    max(hi for _, hi in StarSolveConfig().fov_ranges_deg),
)
AGREE_PX = 3.0
"""Largest boresight difference, and roll and field-of-view differences at the image's half
width, in pixels, for a solution to agree with a reference (the solvers centroid to a
fraction of a pixel; their distortion models differ by up to a pixel or two at the edges of
wide JPEGs)."""
HINT_TOLERANCE = 0.1
"""``--fov-deg`` runs: the field is known within 10 % (the command's default tolerance)."""
NO_STAR_HINT_DEG = 11.4
"""``--fov-deg`` for no-star pictures: a star-tracker lens (esa/tetra3's)."""
WRONG_TRIALS = 100
"""Wrong attitudes per reference-solved image for the verification check."""


def reference_R(ref: dict[str, str]) -> np.ndarray:
    """``inertial_from_camera`` of a reference row (boresight RA/Dec, roll as in
    `radec_roll_deg`: image-down's position angle, north through east)."""
    ra, dec, roll = (math.radians(float(ref[k])) for k in ("ra_deg", "dec_deg", "roll_deg"))
    z = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    y = math.cos(roll) * north + math.sin(roll) * east
    return np.column_stack([np.cross(y, z), y, z])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix uniform on SO(3) (a normalised Gaussian quaternion)."""
    x, y, z, s = (float(v) for v in rng.normal(size=4))
    n = math.sqrt(x * x + y * y + z * z + s * s)
    x, y, z, s = x / n, y / n, z / n, s / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * s), 2 * (x * z + y * s)],
            [2 * (x * y + z * s), 1 - 2 * (x * x + z * z), 2 * (y * z - x * s)],
            [2 * (x * z - y * s), 2 * (y * z + x * s), 1 - 2 * (x * x + y * y)],
        ]
    )


def wrong_attitudes(
    img: np.ndarray, ref: dict[str, str], base: StarSolveConfig, rng: np.random.Generator
) -> tuple[int, float, float]:
    """`check_attitude` on `WRONG_TRIALS` wrong attitudes with the reference's field of view:
    (accepted, smallest false-alarm probability among them, the reference attitude's own)."""
    h, w = img.shape[:2]
    fov = float(ref["fov_deg"])
    band = next((b for b in base.fov_ranges_deg if b[0] <= fov <= b[1]), (fov, fov))
    cfg = replace(base, fov_ranges_deg=(band,))
    stars = extract_stars(img, cfg.extraction)
    cam = SkyCamera(w, h, fov_to_focal(fov, w))
    R0 = reference_R(ref)
    scales = database_fov_range(band, w, h)
    cat = solver_catalogue(scales[0], scales[1], cfg.epoch_yr)
    radius = match_radius(cfg, stars)

    def false_alarm(R: np.ndarray) -> float:
        prow, ppx = _predict(cat, R, cam, float(np.max(cat.mag)))
        pi, _ = _match(ppx, stars.px, radius)
        return _false_alarm_bright(stars, ppx, cat.mag[prow], pi, radius)

    accepted, smallest = 0, 1.0
    for k in range(WRONG_TRIALS):
        if k % 2 == 0:
            R = random_rotation(rng)
        else:  # the boresight moved (an axis across it): every star off its place
            a = rng.uniform(0, 2 * math.pi)
            ang = math.radians(rng.uniform(0.3, 5.0))
            R = R0 @ rotvec_to_matrix(np.array([math.cos(a), math.sin(a), 0.0]) * ang)
        verdict, _, _ = check_attitude(stars, R, cam, cfg)
        accepted += verdict == ""
        smallest = min(smallest, false_alarm(R))
    return accepted, smallest, false_alarm(R0)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


def header(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8").splitlines()
    return [line[2:].strip() for line in text if line.startswith("#")]


def sep_deg(ra1: float, dec1: float, ra2: float, dec2: float) -> float:
    """Angle between two sky places [deg]."""
    a = np.radians([ra1, dec1, ra2, dec2])
    u = np.array([math.cos(a[1]) * math.cos(a[0]), math.cos(a[1]) * math.sin(a[0]), math.sin(a[1])])
    v = np.array([math.cos(a[3]) * math.cos(a[2]), math.cos(a[3]) * math.sin(a[2]), math.sin(a[3])])
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(u, v))), float(u @ v)))


def compare(sol: StarSolution, ref: dict[str, str], width: int) -> dict[str, Any]:
    """Differences of a solution from a reference row: boresight [arcsec], roll [arcsec],
    field of view [%], the largest of the three in pixels of the reference's scale
    (``px``: the boresight, roll and field of view at the half width) and the reference's
    ``solver``."""
    assert sol.R is not None and sol.camera is not None
    ra, dec, roll = radec_roll_deg(sol.R)
    fov_ref = float(ref["fov_deg"])
    px_deg = fov_ref / width  # mean scale across the width
    bore = sep_deg(ra, dec, float(ref["ra_deg"]), float(ref["dec_deg"]))
    droll = (roll - float(ref["roll_deg"]) + 180.0) % 360.0 - 180.0
    dfov = sol.camera.fov_deg / fov_ref - 1
    return {
        "bore_arcsec": bore * 3600,
        "roll_arcsec": droll * 3600,
        "fov_pct": dfov * 100,
        "px": max(bore / px_deg, abs(math.radians(droll)) * width / 2, abs(dfov) * width / 2),
        "solver": ref["solver"],
    }


def verdict(sol: StarSolution, refs: list[dict[str, str]], width: int) -> tuple[str, dict]:
    """``right``/``wrong``/``unverified``/``refused`` and the differences from the closest
    solved reference (the largest of the three pixel differences decides)."""
    if sol.status != "solved":
        return "refused", {}
    if not refs:
        return "unverified", {}
    ds = [compare(sol, r, width) for r in refs]
    d = min(ds, key=lambda e: e["px"])
    ok = d["px"] <= AGREE_PX
    return ("right" if ok else "wrong"), d


def hint_deg(item: dict[str, str], refs: list[dict[str, str]]) -> float | None:
    """The ``--fov-deg`` a user would give: the source's stated field, else the reference's
    rounded to 0.5 deg; no-star pictures: a star tracker's; none where the range it means
    leaves the 0.5-90 deg that ``--fov-deg`` accepts (a fisheye, the Hubble deep field)."""
    if item["kind"] == "no_star":
        return NO_STAR_HINT_DEG
    fov = float(item["fov_deg"]) if item["fov_deg"] else None
    if fov is None and refs:
        fov = round(float(refs[0]["fov_deg"]) * 2) / 2
    if fov is None or not (0.5 <= (1 - HINT_TOLERANCE) * fov and (1 + HINT_TOLERANCE) * fov <= 90):
        return None  # outside what `--fov-deg` accepts (0.5-90 deg): a deep field, a fisheye
    return fov


def cell(sol: StarSolution, v: str, d: dict) -> list[str]:
    """Table cells of one run: outcome, our RA/Dec/roll/FOV, differences, matches, CPU."""
    if sol.status != "solved":
        return [f"refused: {sol.reason}", "", "", "", "", f"{sol.cpu_ms:.0f}"]
    assert sol.R is not None and sol.camera is not None
    ra, dec, roll = radec_roll_deg(sol.R)
    ours = f"{ra:.4f} / {dec:+.4f} / {roll:+.3f} / {sol.camera.fov_deg:.4f}"
    diff = (
        f'{d["bore_arcsec"]:.0f}" / {d["roll_arcsec"]:+.0f}" / {d["fov_pct"]:+.3f} % '
        f"({d['px']:.1f} px; {d['solver']})"
        if d
        else ""
    )
    v = v if v == "right" else f"**{v}**"
    if sol.band_deg is not None and not (sol.band_deg[0] <= sol.camera.fov_deg <= sol.band_deg[1]):
        v += f" (found by the {sol.band_deg[0]:g}-{sol.band_deg[1]:g} deg band)"
    m = f"{sol.star_ids.size}/{sol.predicted}"
    return [v, ours, diff, m, f"{sol.rmse_arcsec:.0f}", f"{sol.cpu_ms:.0f}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="one folder per source")
    ap.add_argument("--images", type=Path, default=IMAGES)
    ap.add_argument("--reference", type=Path, default=REFERENCE)
    ap.add_argument("--out", type=Path, default=Path("docs/results/stars_solve_photos.md"))
    ap.add_argument("--sources", nargs="*", help="only these sources (default: all)")
    args = ap.parse_args()

    items = [i for i in read_csv(args.images) if not args.sources or i["source"] in args.sources]
    ref_rows = read_csv(args.reference)
    base = StarSolveConfig()
    table, missing = [], []
    count = dict.fromkeys(
        ("solvable", "solved_u", "solved_h", "no_star", "refused_u", "refused_h"), 0
    )
    count |= dict.fromkeys(("wrong", "unverified", "outside", "outside_solved"), 0)
    count |= dict.fromkeys(("wrong_accepted", "wrong_trials"), 0)
    unsolved: list[str] = []
    wrong_rows: list[str] = []
    rng = np.random.default_rng(18)
    lo, hi = SUPPORTED_FOV_DEG
    # Grouped by the images' shape (each field-of-view band's database depends on the
    # aspect ratio; four are kept per process), so that each is built once.
    present = []
    for item in items:
        path = args.data / item["source"] / item["file"]
        if not path.is_file():
            missing.append(f"{item['source']}/{item['file']}")
            continue
        h, w = read_sky_image(path).shape[:2]
        refs = [r for r in ref_rows if (r["source"], r["file"]) == (item["source"], item["file"])]
        fovs = [float(r["fov_deg"]) for r in refs if r["status"] == "solved"]
        # The solvable sky images first (a stopped run has measured them), then the rest.
        later = not (item["kind"] == "sky" and fovs and lo <= fovs[0] <= hi)
        present.append(((later, database_fov_range(base.fov_ranges_deg[0], w, h)), item))
    present.sort(key=lambda e: e[0])
    for run, (_, item) in enumerate(present):
        path = args.data / item["source"] / item["file"]
        img = read_sky_image(path)
        h, w = img.shape[:2]
        tried = [r for r in ref_rows if (r["source"], r["file"]) == (item["source"], item["file"])]
        refs = [r for r in tried if r["status"] == "solved"]
        ref_fov = float(refs[0]["fov_deg"]) if refs else math.nan
        solvable = item["kind"] == "sky" and bool(refs) and lo <= ref_fov <= hi
        c0 = time.process_time()
        sol_u = solve_image(img, base)
        hint = hint_deg(item, refs)
        sol_h = None
        if hint is not None:
            tol = HINT_TOLERANCE * hint
            sol_h = solve_image(img, replace(base, fov_ranges_deg=((hint - tol, hint + tol),)))
        # CPU beyond the solves' own: the databases built for this image's bands.
        db_s = time.process_time() - c0 - (sol_u.cpu_ms + (sol_h.cpu_ms if sol_h else 0)) / 1e3
        runs = [(sol_u, "u")] + ([(sol_h, "h")] if sol_h is not None else [])
        outcomes = {}
        for sol, tag in runs:
            v, d = verdict(sol, refs, w)
            outcomes[tag] = (v, d)
            count["wrong"] += v == "wrong"
            count["unverified"] += v == "unverified"
        if item["kind"] == "no_star":
            count["no_star"] += 1
            count["refused_u"] += sol_u.status != "solved"
            count["refused_h"] += sol_h is None or sol_h.status != "solved"
        elif solvable:
            count["solvable"] += 1
            count["solved_u"] += outcomes["u"][0] == "right"
            count["solved_h"] += "h" in outcomes and outcomes["h"][0] == "right"
            if outcomes["u"][0] != "right" or ("h" in outcomes and outcomes["h"][0] != "right"):
                unsolved.append(f"{item['source']}/{item['file']}")
        else:
            count["outside"] += 1
            count["outside_solved"] += any(v == "right" for v, _ in outcomes.values())
        if refs:
            r0 = refs[0]
            ref_txt = (
                f"{r0['solver']}: {float(r0['ra_deg']):.4f} / {float(r0['dec_deg']):+.4f} / "
                f"{float(r0['roll_deg']):+.3f} / {float(r0['fov_deg']):.4f}"
            )
            if len(refs) > 1:
                ref_txt += f" (also {', '.join(r['solver'] for r in refs[1:])})"
        else:
            ref_txt = "none solved" if tried else "not run"
        kind = item["kind"] if item["kind"] == "no_star" else ("sky" if solvable else "sky*")
        first = [
            f"{item['source']}/{item['file']}",
            kind,
            item["licence"],
            f"{w}x{h}{'' if img.ndim == 2 else 'x' + str(img.shape[2])} {img.dtype}",
            ref_txt,
        ]
        table.append([*first, "unknown", *cell(sol_u, *outcomes["u"]), f"{db_s:.1f}"])
        if sol_h is not None and hint is not None:
            given = f"{hint:g} ± {HINT_TOLERANCE * hint:.2g}"
            table.append(["", "", "", "", "", given, *cell(sol_h, *outcomes["h"]), ""])
        if item["kind"] == "sky" and refs and lo <= ref_fov <= hi:
            acc, smallest, own = wrong_attitudes(img, refs[0], base, rng)
            count["wrong_accepted"] += acc
            count["wrong_trials"] += WRONG_TRIALS
            wrong_rows.append(
                f"| {item['source']}/{item['file']} | {acc}/{WRONG_TRIALS} | {smallest:.1e} | "
                f"{own:.1e} |"
            )
        page(args, items, run + 1, len(present), count, table, missing, unsolved, wrong_rows)


def page(
    args: argparse.Namespace,
    items: list[dict[str, str]],
    run: int,
    n_run: int,
    count: dict[str, int],
    table: list[list[str]],
    missing: list[str],
    unsolved: list[str],
    wrong_rows: list[str],
) -> None:
    """Write the results page for the images run so far."""
    lo, hi = SUPPORTED_FOV_DEG

    def met(ok: bool) -> str:
        return "met" if ok else "**not met**"

    n_s, n_n = count["solvable"], count["no_star"]
    lines = [
        "# Lost in space on other cameras' sky photos and no-star pictures (issue 18)",
        "",
        "Generated by `python benchmarks/stars_solve_photos.py --data DATA"
        + (f" --sources {' '.join(args.sources)}" if args.sources else "")
        + "` on "
        f"{len(items) - len(missing)} images ({machine_summary(libraries=False)}, tetra3rs "
        f"{version('tetra3rs')}, {datetime.date.today().isoformat()}, load average "
        f"{' '.join(Path('/proc/loadavg').read_text().split()[:3])}). Do not edit by hand. "
        + (
            ""
            if run == n_run
            else f"**Partial: the run stopped after {run} of {n_run} images** (the "
            "others are not in the tables). "
        )
        + "Images, their sources and licences: `tests/data/sky_photos/images.csv` (where to "
        'get them: docs/stars.md, "Other cameras"). Reference: '
        "`tests/data/sky_photos/reference.csv`:",
        "",
        *[f"> {line}" for line in header(args.reference)],
        "",
        f"satpose: field of view unknown (the default search, {lo:g}-{hi:g} deg) and known "
        f"within {HINT_TOLERANCE:.0%} (`--fov-deg F`: the source's stated field, else the "
        f"reference's rounded to 0.5 deg; no-star pictures: {NO_STAR_HINT_DEG} deg). An "
        f"image is *solvable* (kind `sky`) when a reference solver solved it and its field "
        f"lies within {lo:g}-{hi:g} deg; `sky*`: a sky image outside that (too narrow for "
        f"the catalogue's stars, or a fisheye), which must be refused or right. *Right*: "
        f"boresight, roll and field of view (both at the half width) within {AGREE_PX:g} px "
        "of one of the reference solutions (astrometry.net with SIP order 1, 2 or 3, "
        "cedar-solve: they differ among themselves by several pixels on wide lenses and "
        "sparse fields).",
        "",
        "## Targets",
        "",
        "| target | measured | |",
        "|---|---|---|",
        f"| every solvable image solved, field of view unknown | {count['solved_u']}/{n_s} | "
        f"{met(count['solved_u'] == n_s)} |",
        f"| every solvable image solved, field of view known (`--fov-deg`) | "
        f"{count['solved_h']}/{n_s} | {met(count['solved_h'] == n_s)} |",
        f"| every no-star picture refused (both runs) | {count['refused_u']}/{n_n} and "
        f"{count['refused_h']}/{n_n} | {met(count['refused_u'] == count['refused_h'] == n_n)} |",
        f"| wrong solutions (any image, any run) | {count['wrong']} | {met(count['wrong'] == 0)} |",
        f"| unverified solutions (no reference) | {count['unverified']} | "
        f"{met(count['unverified'] == 0)} |",
        f"| wrong attitudes passing the verification | {count['wrong_accepted']}/"
        f"{count['wrong_trials']} | {met(count['wrong_accepted'] == 0)} |",
        "",
        f"Sky images outside the supported fields: {count['outside']} "
        f"({count['outside_solved']} solved anyway, right). "
        + (f"Solvable images not solved in both runs: {', '.join(unsolved)}. " if unsolved else "")
        + (f"Missing from `--data` (not run): {', '.join(missing)}." if missing else ""),
        "",
        "## Per image",
        "",
        "Ours: RA / Dec / roll / horizontal field of view [deg] (roll: docs/stars.md). "
        "Difference: boresight / roll / field of view against the closest reference solution "
        "(in brackets: the largest of the three in pixels at the half width, and that "
        "reference); the reference column shows the first. Matches: "
        "verified stars / catalogue stars predicted in the image.",
        "",
        "| image | kind | licence | size | reference RA / Dec / roll / FOV | FOV given | outcome "
        "| ours | difference | matches | RMS [arcsec] | CPU [ms] | databases [s CPU] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in table]
    lines += [
        "",
        "Databases: CPU of the tetra3rs databases built for the image's runs (0 when "
        "those of the images before it were reused; the first image of an aspect ratio "
        "pays for its bands).",
        "",
        "## Verification on wrong attitudes",
        "",
        f"`check_attitude` with the first reference's field of view on {WRONG_TRIALS} wrong "
        "attitudes per image (half uniformly random, half the reference's boresight moved "
        "0.3-5 deg): how many pass, the smallest false-alarm probability among them "
        "(threshold `max_false_alarm` 1e-9), and the reference attitude's own.",
        "",
        "| image | wrong attitudes passed | smallest false-alarm p | reference's p |",
        "|---|---|---|---|",
        *wrong_rows,
        "",
    ]
    write_page(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
