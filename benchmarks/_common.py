"""Helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import os
import platform
from importlib.metadata import version
from pathlib import Path

from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset
from satpose.datasets.seed_split import TUNING_SEEDS


def ensure_rendered(name: str, root: Path) -> Path:
    """The preset ``name`` rendered at full size under ``root`` (rendered now if missing)."""
    out = root / name
    if not (out / "frames.csv").is_file():
        print(f"rendering {name} into {out} (a few minutes)", flush=True)
        render_sequence(preset(name), out, overwrite=True)
    return out


def write_page(path: Path, text: str) -> None:
    """Write a results page whole or not at all (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    print(f"wrote {path}")


def machine_summary(libraries: bool = True) -> str:
    """One line naming what a timing depends on: CPU model and vector units, cores, and (if
    ``libraries``) this interpreter's versions of the compiled libraries (renders differ
    between AVX2 and AVX-512 CPUs)."""
    model, flags = platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "flags":
                flags = set(value.split())
                break
    except OSError:
        pass
    simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    if not libraries:
        return f"{model} ({simd}), {os.cpu_count()} cores"
    libs = ", ".join(
        f"{name} {version(name)}"
        for name in ("opencv-python-headless", "mitsuba", "numpy", "gtsam")
    )
    return f"{model} ({simd}), {os.cpu_count()} cores, {libs}"


def tuning_seeds(text: str) -> list[int]:
    """``--seeds`` of a benchmark that looks at the members (``"0-7,12"``): tuning seeds
    only; exits naming the others (validation seeds are only scored)."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    bad = [s for s in out if s not in TUNING_SEEDS]
    if bad:
        raise SystemExit(f"--seeds: {bad} are not tuning seeds; validation seeds are only scored")
    return out
