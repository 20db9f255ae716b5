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
from satpose.datasets.sequence import Sequence, load_sequence, png_params

RATE_HZ = 20.0
LEVELS: tuple[int | None, ...] = (None, 0, 1, 3, 6, 9)


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


def time_reading(bag: Path) -> tuple[float, float, int]:
    """Wall and CPU time [s] of streaming every pair, and the number of pairs."""
    start, cpu = time.perf_counter(), time.process_time()
    n = sum(1 for _ in BagSource(bag).frames())
    return time.perf_counter() - start, time.process_time() - cpu, n


def time_encoding(images: list[np.ndarray]) -> list[tuple[int | None, float, float]]:
    """Per zlib level (as `SequenceWriter` sets it): (level, CPU ms per image, kB per
    image), over the distinct images, one thread."""
    rows = []
    for level in LEVELS:
        reps = 5
        start = time.process_time()
        size = 0
        for _ in range(reps):
            for img in images:
                ok, buf = cv2.imencode(".png", img, png_params(level))
                assert ok
                size += buf.size
        n = reps * len(images)
        rows.append((level, (time.process_time() - start) / n * 1e3, size / n / 1e3))
    return rows


def time_import(
    bag: Path, out: Path, level: int | None, workers: int
) -> tuple[float, float, int, int]:
    """Wall time [s], CPU time of this process (all threads) [s], frames and folder bytes."""
    shutil.rmtree(out, ignore_errors=True)
    opts = ImportOptions(png_compression=level, workers=workers)
    start, cpu = time.perf_counter(), time.process_time()
    report = import_recording([bag], out, opts)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    size = folder_bytes(out)
    shutil.rmtree(out)
    return elapsed, cpu, report.frames, size


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
        read_s, read_cpu, n = time_reading(bag)
        rows = []
        for level, workers in ((None, 1), (None, 2), (0, 1), (0, 2)):
            elapsed, cpu, frames, size = time_import(bag, args.work / "imported", level, workers)
            assert frames == n == args.frames
            rows.append((level, workers, elapsed, cpu, frames, size))
        summary.append((label, folder_bytes(bag), n / read_s, n / read_cpu, rows))
        lines = [
            f"### {label}",
            "",
            f"Bag: {folder_bytes(bag) / 1e9:.2f} GB. Reading and decoding alone "
            f"(`BagSource.frames`): {n / read_s:.0f} stereo frames/s wall, "
            f"{n / read_cpu:.0f} per CPU-second.",
            "",
            "PNG encoding of one image as `SequenceWriter` writes it (`cv2.imencode`, one "
            "thread, CPU time):",
            "",
            "| zlib level | CPU ms per image | kB per image | size / raw |",
            "|---|---|---|---|",
        ]
        raw_kb = w * h / 1e3
        for level, ms, kb in time_encoding(images):
            name = "OpenCV default (1, RLE)" if level is None else str(level)
            lines.append(f"| {name} | {ms:.2f} | {kb:.0f} | {kb / raw_kb:.2f} |")
        lines += [
            "",
            "Whole import (`import_recording`: read, decode, 2 PNGs per frame, rename):",
            "",
            "| zlib level | PNG threads | wall [s] | stereo frames/s (wall) | CPU [s] | "
            "stereo frames per CPU-second | sequence [GB] |",
            "|---|---|---|---|---|---|---|",
        ]
        for level, workers, elapsed, cpu, frames, size in rows:
            name = "default" if level is None else str(level)
            lines.append(
                f"| {name} | {workers} | {elapsed:.1f} | {frames / elapsed:.0f} | {cpu:.1f} | "
                f"{frames / cpu:.0f} | {size / 1e9:.2f} |"
            )
        sections.append("\n".join(lines))

    minutes = (time.perf_counter() - t0) / 60
    load_end = os.getloadavg()[0]
    best_wall = max(
        (fr / el, label) for label, _, _, _, rows in summary for _, _, el, _, fr, _ in rows
    )
    best_cpu = max(
        (fr / cp, label) for label, _, _, _, rows in summary for _, _, _, cp, fr, _ in rows
    )
    verdict = (
        f"Fastest import measured: {best_wall[0]:.0f} stereo frames/s wall clock "
        f"({best_wall[1]}), {best_cpu[0]:.0f} per CPU-second; the 200 frames/s target is "
        f"{'met' if best_wall[0] >= 200 else 'not met'} on this machine while it was shared "
        f"(load average {load:.1f} at the start, {load_end:.1f} at the end, on {os.cpu_count()} "
        "cores: the wall-clock rates are what this process got, the per-CPU-second rates what "
        "one core does)."
    )
    head = [
        "# Import speed",
        "",
        f"Generated by `python benchmarks/import_speed.py --frames {args.frames} --size "
        f"{args.size}` ({machine_summary()}; {date.today().isoformat()}; {minutes:.1f} min). "
        "Do not edit by hand.",
        "",
        f"A {args.frames}-frame {w}x{h} mono8 stereo ROS 2 bag (sqlite3, Image + CameraInfo "
        f"per camera and frame, {RATE_HZ:g} Hz) imported into a sequence folder; three "
        "rendered paper-docking pairs repeated with distinct stamps. The bags are read once "
        "before timing (in the page cache: no disk reads); the sequence is written to the "
        "same disk. Target: >= 200 stereo frames/s.",
        "",
        verdict,
        "",
        "| images | bag [GB] | reading alone [frames/s wall; per CPU-s] | import, defaults "
        "[frames/s wall; per CPU-s] | import, level 0 [frames/s wall; per CPU-s] |",
        "|---|---|---|---|---|",
    ]
    for label, bag_bytes, read_fps, read_cpu_fps, rows in summary:
        by = {(lv, wk): (fr / el, fr / cp) for lv, wk, el, cp, fr, _ in rows}
        d, z = by[(None, 1)], by[(0, 1)]
        head.append(
            f"| {label} | {bag_bytes / 1e9:.2f} | {read_fps:.0f}; {read_cpu_fps:.0f} | "
            f"{d[0]:.0f}; {d[1]:.0f} | {z[0]:.0f}; {z[1]:.0f} |"
        )
    write_page(args.out, "\n".join(head) + "\n\n" + "\n\n".join(sections) + "\n")


if __name__ == "__main__":
    main()
