"""Helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import multiprocessing
import os
import platform
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import TypeVar

import numpy as np

from satpose.datasets.bracket_family import measured_points_b, render_bracket_sequence
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset
from satpose.datasets.seed_split import TUNING_SEEDS
from satpose.datasets.sequence import Sequence, load_sequence
from satpose.frontend.preprocess import Undistorter

T = TypeVar("T")


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


@dataclass(frozen=True)
class BracketMember:
    """One bracket-family member as the strut benchmarks read it: the sequence (with its
    truth), the bracket's vertices ``P1, P2, P5`` and its measured points (``P1, P2`` and
    the visible stub ends, `measured_points_b`), the struts' radius and the left camera's
    undistorter."""

    seq: Sequence
    vertices: np.ndarray
    points: np.ndarray
    radius_m: float
    undistort: Undistorter


def bracket_members(seeds: list[int], root: Path) -> Iterator[tuple[int, BracketMember]]:
    """The bracket-family members ``seeds`` under ``root`` (``seed-N``; rendered at the
    benchmarks' 12 frames, 960x768 where missing), in order."""
    for seed in seeds:
        path = root / f"seed-{seed}"
        if not (path / "frames.csv").is_file():
            print(f"rendering seed {seed}", flush=True)
            render_bracket_sequence(seed, path, frames=12, size=(960, 768), overwrite=True)
        seq = load_sequence(path)
        assert seq.target is not None and seq.target.bracket is not None
        assert seq.truth is not None
        b = seq.target.bracket
        V = np.array([b.P1, b.P2, b.P5])
        yield (
            seed,
            BracketMember(
                seq=seq,
                vertices=V,
                points=measured_points_b(V, b.visible_fraction),
                radius_m=float(seq.target.extras["bracket_strut_width_m"]) / 2,
                undistort=Undistorter(seq.calibration.left),
            ),
        )


def rows_by_member(job: Callable[[int], list[T]], seeds: list[int], jobs: int) -> list[T]:
    """``job(seed)``'s rows for every seed, in order, printing progress: in this process
    (``jobs`` 1) or ``jobs`` fresh interpreters (spawned: no state inherited between
    members); ``job`` must then be picklable (a module-level function or a partial)."""
    rows: list[T] = []
    if jobs == 1:
        for seed in seeds:
            rows += job(seed)
            print(seed, len(rows), flush=True)
        return rows
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        for seed, got in zip(seeds, pool.map(job, seeds), strict=True):
            rows += got
            print(seed, len(rows), flush=True)
    return rows
