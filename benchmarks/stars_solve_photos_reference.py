"""Independent reference solutions for the sky photos of benchmarks/stars_solve_photos.py.

Two solvers that share nothing with satpose (neither its catalogue, nor its extraction, nor
its pattern search):

- **astrometry.net** (Debian's ``astrometry.net`` 0.93 with the Tycho-2 index files
  ``astrometry-data-tycho2-07`` to ``-10-19``, 22'-2000' quads; the rows of earlier runs
  say which were installed then: the header's command lines): ``solve-field`` on every image (its
  own source extraction, quad hashing and TAN-SIP fit); the boresight, roll and field of
  view are read back through its ``wcs-xy2rd`` at the image centre, 10 px below it and at
  the left and right edges of the middle row, so the numbers include its SIP distortion.
  It runs once per distortion order (``--tweak-order``; `ASTROMETRY_ORDERS`), each a solver
  row of its own: ``astrometry.net`` (order 2, solve-field's default), ``astrometry.net
  TAN`` (order 1: no distortion) and ``astrometry.net SIP-3`` (order 3). No order suits
  every picture: order 2 has no cubic term, so a lens's radial distortion leaks into its
  scale (virgo.jpg: 20.28 deg at order 2, 20.43 at 3, 20.46 at 4), and with a handful of
  matched stars orders 2-3 overfit (openstartracker's img9.png, 5 matches: roll -143.99
  deg at order 2, -144.28 at order 1). The spread between the rows is the reference's own
  uncertainty.
- **cedar-solve** 0.5.1 (ESA tetra3's fork, its bundled Hipparcos database for 10-30 deg
  fields): ``solve_from_image`` as in benchmarks/stars_solve_reference.py.

Every image of the list (tests/data/sky_photos/images.csv) is tried by both, including the
no-star pictures (a solution there would mean the picture does show stars). One CSV row per
image and solver; the versions and commands go into the file's ``#`` header. satpose does not
depend on either: run this under the cedar-solve venv, with astrometry.net installed::

    apt-get install astrometry.net astrometry-data-tycho2-07 astrometry-data-tycho2-08 \\
        astrometry-data-tycho2-09 astrometry-data-tycho2-10-19
    python3 -m venv /work/cedar-venv && /work/cedar-venv/bin/pip install 'numpy<2' \\
        cedar-solve==0.5.1
    /work/cedar-venv/bin/python benchmarks/stars_solve_photos_reference.py --data DATA \\
        --out tests/data/sky_photos/reference.csv [--sources S... --keep]

(``--sources`` with ``--keep``: run those sources' images and keep the file's other rows.)

``DATA`` holds one folder per source (docs/stars.md, "Other cameras"). Columns: ``source``,
``file``, ``solver`` (``astrometry.net`` or ``cedar-solve``), ``status`` (``solved``,
``no_solution``, or ``not_run`` when the solver could not read the file), ``ra_deg``,
``dec_deg`` (image centre), ``roll_deg`` (satpose's convention: position angle of
image-down at the centre, north through east; cedar's ``180 - Roll``),
``fov_deg`` (horizontal, edge to edge of the middle row), ``matches``, ``detail``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import math
import re
import shutil
import subprocess
import sys
import tempfile
from importlib.metadata import version
from pathlib import Path

FITS_BLOCK = 2880


def read_images(path: Path) -> list[dict[str, str]]:
    """Rows of the image list (``#`` lines are comments)."""
    with path.open(encoding="utf-8") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


def fits_table_rows(path: Path) -> int:
    """Rows of the first binary-table extension of a FITS file (``NAXIS2`` of HDU 1)."""
    data = path.read_bytes()
    hdu, pos = 0, 0
    while pos < len(data):
        cards: dict[str, str] = {}
        while True:
            block = data[pos : pos + FITS_BLOCK]
            pos += FITS_BLOCK
            done = False
            for k in range(0, FITS_BLOCK, 80):
                card = block[k : k + 80].decode("ascii", "replace")
                key = card[:8].strip()
                if key == "END":
                    done = True
                    break
                if card[8:10] == "= ":
                    cards[key] = card[10:].split("/")[0].strip()
            if done:
                break
        if hdu == 1:
            return int(cards.get("NAXIS2", "0"))
        size = 1
        for i in range(1, int(cards.get("NAXIS", "0")) + 1):
            size *= int(cards[f"NAXIS{i}"])
        if int(cards.get("NAXIS", "0")) == 0:
            size = 0
        nbytes = abs(int(cards.get("BITPIX", "8"))) // 8 * size
        pos += -(-nbytes // FITS_BLOCK) * FITS_BLOCK
        hdu += 1
    return 0


def xy2rd(wcs: Path, x: float, y: float) -> tuple[float, float]:
    """Sky place [deg] of a FITS pixel (1-based) through astrometry.net's ``wcs-xy2rd``."""
    out = subprocess.run(
        ["wcs-xy2rd", "-w", str(wcs), "-x", repr(x), "-y", repr(y)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    m = re.search(r"RA,Dec \(([-+0-9.eE]+), ([-+0-9.eE]+)\)", out)
    if not m:
        raise RuntimeError(f"wcs-xy2rd: unexpected output {out!r}")
    return float(m.group(1)), float(m.group(2))


def unit(ra: float, dec: float) -> tuple[float, float, float]:
    a, d = math.radians(ra), math.radians(dec)
    return (math.cos(d) * math.cos(a), math.cos(d) * math.sin(a), math.sin(d))


def position_angle_deg(ra1: float, dec1: float, ra2: float, dec2: float) -> float:
    """Position angle of place 2 seen from place 1, north through east [deg]."""
    d1, d2, da = math.radians(dec1), math.radians(dec2), math.radians(ra2 - ra1)
    y = math.sin(da) * math.cos(d2)
    x = math.cos(d1) * math.sin(d2) - math.sin(d1) * math.cos(d2) * math.cos(da)
    return math.degrees(math.atan2(y, x))


ASTROMETRY_ORDERS = {"astrometry.net": 2, "astrometry.net TAN": 1, "astrometry.net SIP-3": 3}
"""Solver name of each ``solve-field --tweak-order`` run."""
SOLVERS = (*ASTROMETRY_ORDERS, "cedar-solve")


def solve_astrometry_net(
    image: Path, width: int, height: int, fov_deg: float | None, cpulimit: int, order: int
) -> dict[str, object]:
    """``solve-field`` on one image with SIP distortion of polynomial ``order`` (1: plain
    TAN); the boresight, roll and field of view of its WCS."""
    work = Path(tempfile.mkdtemp(prefix="anet-"))
    try:
        cmd = ["solve-field", "--no-plots", "--overwrite", "--dir", str(work)]
        cmd += ["--cpulimit", str(cpulimit), "--new-fits", "none", "--rdls", "none"]
        cmd += ["--index-xyls", "none", "--match", "none", "--solved", "none", "--crpix-center"]
        cmd += ["--tweak-order", str(order)]
        if fov_deg:
            cmd += ["--scale-units", "degwidth"]
            cmd += ["--scale-low", f"{0.7 * fov_deg:g}", "--scale-high", f"{1.3 * fov_deg:g}"]
        cmd += ["--temp-dir", str(work), str(image)]
        run = subprocess.run(cmd, capture_output=True, text=True)
        wcs = work / f"{image.stem}.wcs"
        if not wcs.is_file():
            tail = (run.stdout.strip().splitlines() or [""])[-1]
            return {"status": "no_solution", "detail": tail[:120]}
        cx, cy = (width + 1) / 2.0, (height + 1) / 2.0
        ra, dec = xy2rd(wcs, cx, cy)
        ra_d, dec_d = xy2rd(wcs, cx, cy + 10.0)  # FITS y = image row + 1: image down
        left, right = xy2rd(wcs, 0.5, cy), xy2rd(wcs, width + 0.5, cy)
        dot = sum(a * b for a, b in zip(unit(*left), unit(*right), strict=True))
        fov = math.degrees(math.acos(max(-1.0, min(1.0, dot))))
        corr = work / f"{image.stem}.corr"
        return {
            "status": "solved",
            "ra_deg": f"{ra % 360.0:.7f}",
            "dec_deg": f"{dec:.7f}",
            "roll_deg": f"{position_angle_deg(ra, dec, ra_d, dec_d):.6f}",
            "fov_deg": f"{fov:.6f}",
            "matches": fits_table_rows(corr) if corr.is_file() else "",
            "detail": "TAN (solve-field)" if order == 1 else f"TAN-SIP {order} (solve-field)",
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)


def solve_cedar(t3: object, image: Path, fov_deg: float | None) -> dict[str, object]:
    """cedar-solve's ``solve_from_image`` (its own centroider and distortion fit)."""
    from PIL import Image

    with Image.open(image) as img:
        kw = {"fov_estimate": fov_deg, "fov_max_error": 0.15 * fov_deg} if fov_deg else {}
        try:
            gray = img.convert("L")
        except OSError as exc:  # e.g. a compressed TIFF without Pillow's libtiff
            return {"status": "not_run", "detail": f"Pillow cannot decode it: {exc}"}
        r = t3.solve_from_image(gray, **kw)  # type: ignore[attr-defined]
    if r.get("RA") is None:
        return {"status": "no_solution", "detail": str(r.get("status", "no match"))}
    return {
        "status": "solved",
        "ra_deg": f"{r['RA']:.7f}",
        "dec_deg": f"{r['Dec']:.7f}",
        "roll_deg": f"{(180.0 - r['Roll'] + 180.0) % 360.0 - 180.0:.6f}",
        "fov_deg": f"{r['FOV']:.6f}",
        "matches": r["Matches"],
        "detail": f"distortion {r['distortion']:.5f}, RMSE {r['RMSE']:.1f} arcsec",
    }


def installed_indexes() -> str:
    """The Debian astrometry.net index packages installed (``dpkg-query``), e.g.
    ``astrometry-data-tycho2-07-littleendian, ...``."""
    out = subprocess.run(
        ["dpkg-query", "-W", "-f", "${Package} ${Status}\\n", "astrometry-data-*"],
        capture_output=True,
        text=True,
    ).stdout
    names = [ln.split()[0] for ln in out.splitlines() if ln.endswith("install ok installed")]
    return ", ".join(sorted(names)) or "none found by dpkg-query"


def write(args: argparse.Namespace, rows: list[dict[str, str]], anet: str) -> None:
    """Write the rows so far (a temporary file, then a rename)."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cols = ["source", "file", "solver", "status", "ra_deg", "dec_deg", "roll_deg", "fov_deg"]
    cols += ["matches", "detail"]
    tmp = args.out.with_suffix(".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        fh.write(
            f"# astrometry.net: {anet or 'solve-field'} with the index files of the run (each "
            "command line below); solve-field --tweak-order 2 (astrometry.net), "
            "1 (astrometry.net TAN), 3 (astrometry.net SIP-3) --cpulimit "
            f"{args.cpulimit} (no-star pictures {args.no_star_cpulimit}) --crpix-center, "
            "--scale-units degwidth 0.7-1.3 x fov_deg when "
            "images.csv states a pinhole field, else no scale hint\n"
            f"# {args.cedar_header}\n"
            "# command: python benchmarks/stars_solve_photos_reference.py --data DATA --out "
            f"{args.out}"
            + (f" --sources {' '.join(args.sources)}" if args.sources else "")
            + (f" --solvers {' '.join(repr(v) for v in args.solvers)}" if args.solvers else "")
            + (" --keep" if args.keep else "")
            + f"; index files {args.indexes}; written {datetime.date.today().isoformat()}\n"
            + "".join(f"# earlier: {line}\n" for line in args.earlier)
            + "# roll_deg: position angle of image-down at the centre, north through east "
            "(satpose; cedar: 180 - Roll)\n"
        )
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    tmp.replace(args.out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="one folder per source")
    ap.add_argument("--images", type=Path, default=Path("tests/data/sky_photos/images.csv"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cpulimit", type=int, default=30, help="solve-field CPU seconds")
    ap.add_argument(
        "--no-star-cpulimit", type=int, default=10, help="solve-field CPU seconds, no-star"
    )
    ap.add_argument("--sources", nargs="*", help="only these sources (default: all)")
    ap.add_argument(
        "--keep",
        action="store_true",
        help="keep --out's rows of the images and solvers not run now (a run of some "
        "--sources or --solvers only)",
    )
    ap.add_argument("--solvers", nargs="*", choices=SOLVERS, help="only these (default: all)")
    args = ap.parse_args()
    solvers = args.solvers or list(SOLVERS)

    from PIL import Image

    t3 = None
    args.cedar_header = "cedar-solve: not run"
    if "cedar-solve" in solvers:
        import tetra3  # cedar-solve's module name

        t3 = tetra3.Tetra3()
        p = t3.database_properties
        args.cedar_header = (
            f"cedar-solve {version('cedar-solve')} (numpy {__import__('numpy').__version__}), "
            f"bundled database (catalogue {p['star_catalog']}, fov {p['min_fov']}-"
            f"{p['max_fov']} deg, epoch {p['epoch_proper_motion']}): solve_from_image(gray, "
            "fov_estimate=fov_deg, fov_max_error=0.15 fov_deg) or no estimate"
        )
    anet = subprocess.run(["solve-field", "--version"], capture_output=True, text=True)
    args.indexes = installed_indexes()
    items = [i for i in read_images(args.images) if not args.sources or i["source"] in args.sources]
    run_now = {(i["source"], i["file"]) for i in items}
    rows = []
    args.earlier = []  # the kept rows' own command lines
    if args.keep and args.out.is_file():
        for line in args.out.read_text(encoding="utf-8").splitlines():
            for tag in ("# command: ", "# earlier: "):
                if line.startswith(tag):
                    args.earlier.append(line[len(tag) :])
            if line.startswith("# cedar-solve ") and t3 is None:
                args.cedar_header = line[2:]
        with args.out.open(encoding="utf-8") as fh:
            old = csv.DictReader(line for line in fh if not line.startswith("#"))
            rows = [
                r
                for r in old
                if (r["source"], r["file"]) not in run_now or r["solver"] not in solvers
            ]
    for item in items:
        path = args.data / item["source"] / item["file"]
        if not path.is_file():
            print(f"{path}: missing, not run", file=sys.stderr)
            continue
        with Image.open(path) as img:
            width, height = img.size
        fov = float(item["fov_deg"]) if item["fov_deg"] else None
        # A fisheye's "field of view" is no pinhole scale: search every scale then.
        hint = fov if fov and fov < 90 else None
        first_order: dict[str, object] | None = None
        # The default order first: the others change only the final fit of the stars it
        # identified, so they are run only where it solved.
        for solver in sorted(solvers, key=lambda v: v != "astrometry.net"):
            if solver in ASTROMETRY_ORDERS and first_order and first_order["status"] != "solved":
                res = {"status": "no_solution", "detail": "not run: order 2 found no solution"}
            elif solver in ASTROMETRY_ORDERS:
                limit = args.no_star_cpulimit if item["kind"] == "no_star" else args.cpulimit
                res = solve_astrometry_net(
                    path, width, height, hint, limit, ASTROMETRY_ORDERS[solver]
                )
                first_order = first_order or (res if solver == "astrometry.net" else None)
            else:
                assert t3 is not None
                res = solve_cedar(t3, path, hint)
            row = {"source": item["source"], "file": item["file"], "solver": solver}
            row.update({k: "" for k in ("ra_deg", "dec_deg", "roll_deg", "fov_deg", "matches")})
            row.update({k: str(v) for k, v in res.items()})
            rows.append(row)
            print(f"{item['source']}/{item['file']} {solver}: {row['status']}", file=sys.stderr)
        write(args, rows, anet.stdout.strip())
    order = {(i["source"], i["file"]): k for k, i in enumerate(read_images(args.images))}
    rows.sort(key=lambda r: (order.get((r["source"], r["file"]), len(order)), r["solver"]))
    write(args, rows, anet.stdout.strip())
    solved = sum(r["status"] == "solved" for r in rows)
    print(f"{solved}/{len(rows)} solver runs solved; wrote {args.out}")


if __name__ == "__main__":
    main()
