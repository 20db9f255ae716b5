"""Reference solutions of real star images by an independent solver (cedar-solve).

Runs cedar-solve (a fork of ESA's tetra3: its own Hipparcos database, centroider, pattern
search and distortion fit; nothing shared with satpose's tetra3rs + own refinement) on every
image of a folder and writes one CSV row per image, with the solver, its version and this
command in the file's ``#`` header. satpose does not depend on cedar-solve: run this under a
separate interpreter (cedar-solve's wheel carries its database and needs numpy < 2)::

    python3 -m venv /tmp/venv-cedar
    /tmp/venv-cedar/bin/pip install 'numpy<2' cedar-solve==0.5.1
    /tmp/venv-cedar/bin/python benchmarks/stars_solve_reference.py TEST_DATA_DIR \\
        --out tests/data/tetra3/reference.csv

``TEST_DATA_DIR``: esa/tetra3's ``test_data/`` (eight 16-bit TIFF frames). Columns:
``image`` (file stem), ``ra_deg``, ``dec_deg`` (boresight: the image centre), ``roll_deg``
(satpose's convention, docs/stars.md: ``180 - cedar_roll_deg`` wrapped to (-180, 180]),
``cedar_roll_deg`` (cedar's own ``Roll``), ``fov_deg`` (horizontal, cedar's ``FOV``),
``distortion`` (cedar's, at half the width), ``rmse_arcsec``, ``matches``, ``t_solve_ms``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import sys
from importlib.metadata import version
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path, help="folder of .tif/.tiff/.png images")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--fov-deg", type=float, default=11.4)
    ap.add_argument("--fov-max-error-deg", type=float, default=1.0)
    ap.add_argument("--source", default="", help="where the images come from (for the header)")
    args = ap.parse_args()

    import numpy as np
    import tetra3  # cedar-solve's module name
    from PIL import Image

    t3 = tetra3.Tetra3()
    props = t3.database_properties
    files = sorted(
        p for p in args.images.iterdir() if p.suffix.lower() in (".tif", ".tiff", ".png")
    )
    rows = []
    for p in files:
        with Image.open(p) as img:
            r = t3.solve_from_image(
                img, fov_estimate=args.fov_deg, fov_max_error=args.fov_max_error_deg
            )
        if r["RA"] is None:
            print(f"{p.name}: no solution", file=sys.stderr)
            continue
        roll = (180.0 - r["Roll"] + 180.0) % 360.0 - 180.0
        rows.append(
            {
                "image": p.stem,
                "ra_deg": f"{r['RA']:.7f}",
                "dec_deg": f"{r['Dec']:.7f}",
                "roll_deg": f"{roll:.6f}",
                "cedar_roll_deg": f"{r['Roll']:.6f}",
                "fov_deg": f"{r['FOV']:.6f}",
                "distortion": f"{r['distortion']:.6f}",
                "rmse_arcsec": f"{r['RMSE']:.3f}",
                "matches": r["Matches"],
                "t_solve_ms": f"{r['T_solve']:.2f}",
            }
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="", encoding="utf-8") as fh:
        fh.write(
            f"# solver: cedar-solve {version('cedar-solve')} (fork of esa/tetra3), numpy "
            f"{np.__version__}, Python {sys.version.split()[0]}; its bundled database "
            f"(catalogue {props['star_catalog']}, fov {props['min_fov']}-{props['max_fov']} deg, "
            f"proper motion epoch {props['epoch_proper_motion']})\n"
            f"# call: solve_from_image(image, fov_estimate={args.fov_deg}, "
            f"fov_max_error={args.fov_max_error_deg}) with its default centroider and "
            "distortion fit (distortion=0 start)\n"
            "# command: python benchmarks/stars_solve_reference.py TEST_DATA_DIR --out "
            f"{args.out} (under a venv with numpy<2 and cedar-solve)\n"
            f"# images: {args.source or args.images}\n"
            f"# written {datetime.date.today().isoformat()}; roll_deg = 180 - cedar_roll_deg "
            "(satpose/tetra3rs convention)\n"
        )
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["image"])
        w.writeheader()
        w.writerows(rows)
    print(f"{len(rows)}/{len(files)} solved; wrote {args.out}")


if __name__ == "__main__":
    main()
