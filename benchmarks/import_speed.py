"""Import speed: a 1,000-frame 1024x768 stereo ROS 2 bag into a sequence folder.

    python benchmarks/import_speed.py [--frames 1000] [--size 1024x768] [--work runs/bench-import]

The bag is built from three rendered stereo pairs of ``paper-docking`` (mono8 sensor, 4 spp),
repeated with distinct stamps at 20 Hz, one ``sensor_msgs/Image`` and one ``CameraInfo`` per
camera and frame, written by rosbags' own writer (`satpose.datasets.importers.writers`). A
second bag holds the same images with a camera's dark floor added (a black level of 8 DN and
Gaussian noise of 2 DN, seeded): rendered space is mostly exact zeros, which PNG compresses to
almost nothing, while a lab camera's background is noise.

Measured, each on the bag's pages already in memory (the bags are read once before timing):

1. reading alone: `BagSource.frames` (rosbags read, CDR deserialisation, pairing, decoding);
2. PNG encoding of one image per zlib level (``cv2.imencode``, one thread): time and size;
3. the whole import (`import_recording`: read, decode, PNG write, atomic rename) for zlib
   levels and PNG-writing threads.

Writes docs/results/import.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import cv2
import numpy as np
from _common import machine_summary, write_page  # benchmarks/_common.py (scripts run from the root)

from satpose.datasets.importers import BagSource, ImportOptions, import_recording
from satpose.datasets.importers.writers import BagWriter, rectification
from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset, scaled
from satpose.datasets.sequence import Sequence, load_sequence

RATE_HZ = 20.0
LEVELS = (0, 1, 3, 6, 9)


def rendered(work: Path, size: tuple[int, int]) -> Sequence:
    """Three stereo frames of paper-docking with a mono8 sensor (rendered once, then kept)."""
    out = work / f"source-{size[0]}x{size[1]}"
    if not (out / "frames.csv").is_file():
        s = scaled(preset("paper-docking"), frames=3, size=size, spp=4)
        s = replace(s, sensor=replace(s.sensor, mono=True), render=replace(s.render, masks=False))
        render_sequence(s, out, overwrite=True)
    return load_sequence(out)


def dark_floor(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A lab camera's background: black level 8 DN + Gaussian noise of 2 DN (uint8)."""
    noisy = img.astype(np.float64) + 8.0 + rng.normal(0.0, 2.0, img.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def build_bag(path: Path, seq: Sequence, frames: int, noise: bool) -> list[np.ndarray]:
    """Write the benchmark bag (unless present); return the distinct left/right images."""
    rng = np.random.default_rng(22)
    pairs = [(f.left(), f.right()) for f in seq]
    if noise:
        pairs = [(dark_floor(a, rng), dark_floor(b, rng)) for a, b in pairs]
    if not path.exists():
        calib = seq.calibration
        assert calib.right is not None and calib.right_from_left is not None
        R1, R2, P1, P2 = rectification(calib.left, calib.right, calib.right_from_left)
        with BagWriter(path, 2) as bag:
            for k in range(frames):
                ns = 1_700_000_000_000_000_000 + round(k * 1e9 / RATE_HZ)
                for cam, (img, R, P) in enumerate(
                    ((pairs[k % 3][0], R1, P1), (pairs[k % 3][1], R2, P2))
                ):
                    c = calib.left if cam == 0 else calib.right
                    bag.write(f"/cam{cam}/image_raw", ns, bag.image_msg(ns, img, frame_id="c"))
                    bag.write(f"/cam{cam}/camera_info", ns, bag.camera_info_msg(ns, c, R, P))
    return [img for pair in pairs for img in pair]


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def warm(path: Path) -> None:
    """Read the bag's files once so that every timing sees them in the page cache."""
    for p in path.rglob("*"):
        if p.is_file():
            with open(p, "rb") as fh:
                while fh.read(1 << 24):
                    pass


def time_reading(bag: Path) -> tuple[float, int]:
    start = time.perf_counter()
    n = sum(1 for _ in BagSource(bag).frames())
    return time.perf_counter() - start, n


def time_encoding(images: list[np.ndarray]) -> list[tuple[int, float, float]]:
    """Per zlib level: (level, ms per image, kB per image), over the distinct images."""
    rows = []
    for level in LEVELS:
        reps = 5
        start = time.perf_counter()
        size = 0
        for _ in range(reps):
            for img in images:
                ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])
                assert ok
                size += buf.size
        n = reps * len(images)
        rows.append((level, (time.perf_counter() - start) / n * 1e3, size / n / 1e3))
    return rows


def time_import(bag: Path, out: Path, level: int | None, workers: int) -> tuple[float, int, int]:
    shutil.rmtree(out, ignore_errors=True)
    opts = ImportOptions(png_compression=level, workers=workers)
    start = time.perf_counter()
    report = import_recording([bag], out, opts)
    elapsed = time.perf_counter() - start
    size = folder_bytes(out)
    shutil.rmtree(out)
    return elapsed, report.frames, size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--work", type=Path, default=Path("runs/bench-import"))
    ap.add_argument("--out", type=Path, default=Path("docs/results/import.md"))
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seq = rendered(args.work, (w, h))
    load = os.getloadavg()[0]

    sections = []
    summary = []
    for noise in (False, True):
        label = "rendered + dark floor (8 DN, sigma 2 DN)" if noise else "rendered (mono8)"
        bag = args.work / f"bag-{args.frames}-{w}x{h}-{'noisy' if noise else 'clean'}"
        images = build_bag(bag, seq, args.frames, noise)
        warm(bag)
        read_s, n = time_reading(bag)
        enc = time_encoding(images)
        rows = []
        for level, workers in ((None, 1), (None, 2), (0, 1), (0, 2), (3, 2)):
            elapsed, frames, size = time_import(bag, args.work / "imported", level, workers)
            assert frames == n == args.frames
            rows.append((level, workers, elapsed, frames / elapsed, size))
        best = max(rows, key=lambda r: r[3])
        summary.append((label, folder_bytes(bag), n / read_s, rows[0][3], best))
        lines = [
            f"### {label}",
            "",
            f"Bag: {folder_bytes(bag) / 1e9:.2f} GB; reading and decoding alone "
            f"(`BagSource.frames`): {n / read_s:.0f} stereo frames/s ({read_s:.1f} s).",
            "",
            "PNG encoding, one image, one thread (`cv2.imencode`):",
            "",
            "| zlib level | ms per image | kB per image | x raw |",
            "|---|---|---|---|",
        ]
        raw_kb = w * h / 1e3
        for level, ms, kb in enc:
            lines.append(f"| {level} | {ms:.2f} | {kb:.0f} | {kb / raw_kb:.2f} |")
        lines += [
            "",
            "Whole import (`import_recording`, 2 PNGs per frame):",
            "",
            "| zlib level | PNG threads | time [s] | stereo frames/s | sequence size [GB] |",
            "|---|---|---|---|---|",
        ]
        for level, workers, elapsed, fps, size in rows:
            name = "default (1)" if level is None else str(level)
            lines.append(f"| {name} | {workers} | {elapsed:.1f} | {fps:.0f} | {size / 1e9:.2f} |")
        sections.append("\n".join(lines))

    minutes = (time.perf_counter() - t0) / 60
    head = [
        "# Import speed",
        "",
        f"Generated by `python benchmarks/import_speed.py --frames {args.frames} --size "
        f"{args.size}` ({machine_summary()}; {date.today().isoformat()}; {minutes:.1f} min; "
        f"load average {load:.1f} at the start, the machine shared). Do not edit by hand.",
        "",
        f"A {args.frames}-frame {w}x{h} mono8 stereo ROS 2 bag (sqlite3, Image + CameraInfo "
        f"per camera and frame, {RATE_HZ:g} Hz) imported into a sequence folder; three "
        "rendered paper-docking pairs repeated with distinct stamps. Times on bags already in "
        "the page cache: this measures the CPU (rosbags, decoding, PNG encoding), not the "
        "disk. Target: >= 200 stereo frames/s.",
        "",
        "| images | bag [GB] | reading alone [frames/s] | import, defaults [frames/s] | "
        "fastest import [frames/s] (level, threads) |",
        "|---|---|---|---|---|",
    ]
    for label, bag_bytes, read_fps, default_fps, best in summary:
        level, workers, _, fps, _ = best
        name = "default" if level is None else f"level {level}"
        head.append(
            f"| {label} | {bag_bytes / 1e9:.2f} | {read_fps:.0f} | {default_fps:.0f} | "
            f"{fps:.0f} ({name}, {workers}) |"
        )
    write_page(args.out, "\n".join(head) + "\n\n" + "\n\n".join(sections) + "\n")


if __name__ == "__main__":
    main()
