"""Frontend defaults on satellites, rigs and light they were not tuned on.

    python benchmarks/frontend_variations.py            # renders the variants if needed
    python benchmarks/frontend_variations.py --from-campaign runs/campaigns/variants

The second builds the same page from the campaign benchmarks/campaigns/frontend_variations.yaml
(`satpose campaign ... --out runs/campaigns/variants`): the same variants, rendered and scored
as its cells (``estimator: frontend``), read back from its results.parquet.

The issue asks the frontend's defaults to hold on held-out sequences (other ring radii,
component layouts, baselines, distortion, light). Each variant below changes one thing of
`paper-docking` (and runs the 7 m to 3 m approach in 30 frames instead of 81); the variants
are rendered into runs/bench/variants/ and scored by benchmarks/frontend.py, which writes
docs/results/frontend_variations.md. No frontend parameter is changed per variant.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

from satpose.datasets.config import replace_nested
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset

APPROACH = {"frames": 30, "motion": {"velocity_m_s": [0.0, 0.0, -4.0 / 150.0]}}
"""7 m to 3 m in 30 frames at 0.2 Hz (the spin stays 10 deg per frame)."""

VARIANTS: dict[str, dict[str, Any]] = {
    "ring-small": {"target": {"ring": {"outer_radius_m": 0.22, "inner_radius_m": 0.19}}},
    "ring-large-offset": {
        "target": {
            "ring": {
                "outer_radius_m": 0.36,
                "inner_radius_m": 0.31,
                "height_m": 0.14,
                "center_offset_m": [0.06, -0.03],
            }
        }
    },
    "components-4": {
        "target": {
            "components": {
                "positions_m": [[0.38, 0.36], [-0.45, 0.2], [0.1, -0.39], [-0.35, -0.33]],
                "radius_m": 0.045,
            }
        }
    },
    "baseline-0.2": {"rig": {"baseline_m": 0.2}},
    "baseline-0.5": {"rig": {"baseline_m": 0.5}},
    "distortion-strong": {
        "rig": {
            "dist_left": [-0.18, 0.09, 5e-4, -3e-4, 0.0],
            "dist_right": [-0.16, 0.07, -4e-4, 5e-4, 0.0],
        }
    },
    "sun-side": {"light": {"kind": "sun", "direction": [0.55, 0.25, 0.8]}},
}


def render_variant(name: str, overrides: dict[str, Any], root: Path) -> Path:
    out = root / name
    if (out / "frames.csv").is_file():
        return out
    scenario = replace_nested(preset("paper-docking"), {**APPROACH, **overrides, "name": name})
    print(f"rendering {name} into {out}", flush=True)
    render_sequence(scenario, out, overwrite=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-campaign", type=Path, metavar="DIR", help="a campaign folder")
    ap.add_argument("--out", default="docs/results/frontend_variations.md")
    args = ap.parse_args()
    cmd = [sys.executable, str(Path(__file__).with_name("frontend.py")), "--out", args.out]
    cmd += ["--title", "Stereo frontend (seed 000) on held-out variants"]
    if args.from_campaign is not None:
        cmd += [
            "--generated-by",
            f"python benchmarks/frontend_variations.py --from-campaign {args.from_campaign}",
            "--from-campaign",
            str(args.from_campaign),
        ]
        subprocess.run(cmd, check=True)
        return
    root = Path("runs/bench/variants")
    paths = [render_variant(n, o, root) for n, o in VARIANTS.items()]
    cmd += ["--generated-by", "python benchmarks/frontend_variations.py"]
    subprocess.run([*cmd, *map(str, paths)], check=True)


if __name__ == "__main__":
    main()
