"""Ellipse detectors on rendered sequences, scored against the projected ring truth.

    python benchmarks/ellipse_detectors.py                 # writes docs/results/ellipses.md
    python benchmarks/ellipse_detectors.py SEQ [SEQ ...]   # other sequence folders

For every frame and camera the image is converted to grey and undistorted with
``cv2.initUndistortRectifyMap(K, dist, None, K, ...)`` + ``cv2.remap`` (K kept), then every
detector runs on the whole image:

1. ``arc-support``: `satpose.frontend.ellipses.detect_ellipses` with its default config;
2. ``contours``: what a user would otherwise write: Gaussian blur, Canny, ``cv2.findContours``,
   ``cv2.fitEllipse`` per contour, with size, fit-residual and length filters and
   duplicate removal (`contour_ellipses`);
3. ``edgedrawing``: OpenCV-contrib's ``cv2.ximgproc.createEdgeDrawing()`` + ``detectEllipses``
   with default parameters, run by ``benchmarks/_edgedrawing_worker.py`` in a separate
   environment (``--contrib-python``, default ``/work/venv-contrib/bin/python``) because
   opencv-contrib conflicts with the project's opencv-python-headless. Skipped with a note
   when that interpreter is missing.

Truth: with ``pose = seq.truth.pose(i)`` (left_cam_from_target; right camera:
``right_from_left @ pose``) and target.yaml's ring, the image conics of the outer and inner
front edge (z = 0) and of the outer and inner base (z = -height) are
``circle_to_conic(K, cam_from_target @ Rigid3(t=[0, 0, z]), r)``; the dark components are
circles of ``component_radius_m`` centred at ``target.components`` (their top faces). A
detection matches a truth ellipse when its centre is within 2 px and both semi-axes within
2 px. False positives are detections matching none of the four ring ellipses and no
component.

4. ``arc-support ROI``: the same detector in a search window, the truth outer front edge's
   bounding box grown by 25 % on every side (what a tracker would pass on from the previous
   frame); it shows the cost in a ROI.

Timing: the process (and the EdgeDrawing worker) is pinned to one core with
``os.sched_setaffinity`` and OpenCV runs single-threaded; each detector call is timed as CPU
time of the process (``time.process_time``; EdgeDrawing inside its worker, excluding image
I/O), so time the core spends on other work does not count, though cache and memory
contention from it still does. The medians are comparable within one run only.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from satpose.datasets import load_sequence
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Sequence as SatSequence
from satpose.frontend.conics import (
    ConicError,
    Ellipse,
    circle_to_conic,
    conic_to_ellipse,
    sampson_distance,
)
from satpose.frontend.ellipses import EllipseDetectorConfig, detect_ellipses

DEFAULT_SEQUENCES = [
    "/work/runs/paper-docking",
    "/work/runs/close-approach",
    "/work/runs/tumble",
]
DEFAULT_CONTRIB_PYTHON = "/work/venv-contrib/bin/python"
MATCH_CENTER_PX = 2.0
MATCH_AXIS_PX = 2.0
RING_NAMES = ("outer front", "inner front", "outer base", "inner base")
DETECTORS = ("arc-support", "arc-support ROI", "contours", "edgedrawing")
ROI_GROWTH = 0.25


# ---------------------------------------------------------------------------------------------
# Truth and images
# ---------------------------------------------------------------------------------------------


@dataclass
class Truth:
    ring: dict[str, Ellipse]
    components: list[Ellipse]


def truth_ellipses(seq: SatSequence, i: int, cam: str) -> Truth:
    """The four ring ellipses and the component circles in undistorted pixels of ``cam``."""
    if seq.truth is None or seq.target is None or seq.target.ring is None:
        raise SystemExit(f"{seq.root}: needs groundtruth.csv and target.yaml with a ring")
    calib = seq.calibration
    pose = seq.truth.pose(i)
    if cam == "right":
        if calib.right_from_left is None:
            raise SystemExit(f"{seq.root}: mono sequence has no right camera")
        pose = calib.right_from_left @ pose
    K = calib.camera(cam).K  # type: ignore[arg-type]
    ring = seq.target.ring
    height = float(ring.extras["height_m"])
    inner = float(ring.extras["inner_radius_m"])
    circles = {
        "outer front": (0.0, ring.radius_m),
        "inner front": (0.0, inner),
        "outer base": (-height, ring.radius_m),
        "inner base": (-height, inner),
    }
    out = {}
    for name, (z, r) in circles.items():
        T = pose @ Rigid3(t=np.array([0.0, 0.0, z]))
        out[name] = conic_to_ellipse(circle_to_conic(K, T, r))
    comps = []
    positions = seq.target.components if seq.target.components is not None else np.zeros((0, 3))
    r_comp = float(seq.target.extras.get("component_radius_m", 0.0))
    for p in positions:
        T = pose @ Rigid3(t=np.asarray(p, dtype=float))
        if r_comp <= 0 or T.t[2] <= 0:
            continue
        try:
            comps.append(conic_to_ellipse(circle_to_conic(K, T, r_comp)))
        except ConicError:
            continue
    return Truth(ring=out, components=comps)


def undistorted_gray(seq: SatSequence, i: int, cam: str) -> np.ndarray:
    """Grey, undistorted image (same K) of frame ``i``, camera ``cam``."""
    c = seq.calibration.camera(cam)  # type: ignore[arg-type]
    img = seq.frames[i].image(cam)  # type: ignore[arg-type]
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    m1, m2 = cv2.initUndistortRectifyMap(c.K, c.dist, None, c.K, (c.width, c.height), cv2.CV_32FC1)
    return cv2.remap(img, m1, m2, cv2.INTER_LINEAR)


# ---------------------------------------------------------------------------------------------
# Detectors
# ---------------------------------------------------------------------------------------------


def arc_support(gray: np.ndarray) -> np.ndarray:
    """This project's detector, default config: (N, 5) ``[cx, cy, a, b, theta]``."""
    found = detect_ellipses(gray, EllipseDetectorConfig())
    return np.array([d.ellipse.params for d in found]).reshape(-1, 5)


def arc_support_roi(gray: np.ndarray, truth: Truth) -> np.ndarray:
    """This project's detector in a ROI around the truth outer front edge."""
    e = truth.ring["outer front"]
    # Bounding box of the ellipse, grown by ROI_GROWTH of its size on every side.
    c, s = math.cos(e.theta), math.sin(e.theta)
    hw = math.hypot(e.a * c, e.b * s)
    hh = math.hypot(e.a * s, e.b * c)
    mx, my = hw * (1 + 2 * ROI_GROWTH), hh * (1 + 2 * ROI_GROWTH)
    roi = (
        math.floor(e.cx - mx),
        math.floor(e.cy - my),
        math.ceil(e.cx + mx) + 1,
        math.ceil(e.cy + my) + 1,
    )
    found = detect_ellipses(gray, EllipseDetectorConfig(), roi=roi)
    return np.array([d.ellipse.params for d in found]).reshape(-1, 5)


def contour_ellipses(gray: np.ndarray) -> np.ndarray:
    """Canny + findContours + fitEllipse with the filters a careful user would add.

    Canny thresholds are those of the arc-support detector (4 / 10 grey levels per pixel on
    the same 1-px Gaussian blur; OpenCV's Sobel gain is 8); a contour of a thin edge runs there
    and back, so it needs >= 40 points (>= 20 edge pixels). An ellipse is kept when >= 80 % of
    the contour points lie within 1 px of it, the contour covers >= 40 % of the perimeter, the
    semi-minor axis is >= 6 px and the axis ratio >= 0.2; near-duplicates (centre and axes
    within 1.5 px) keep the longest contour.
    """
    H, W = gray.shape
    blur = cv2.GaussianBlur(gray, (0, 0), 1.0)
    edges = cv2.Canny(blur, 32, 80, L2gradient=True)
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cands: list[tuple[int, np.ndarray]] = []
    for c in contours:
        if len(c) < 40:
            continue
        (cx, cy), (w, h), ang = cv2.fitEllipse(c)
        if not (np.isfinite([cx, cy, w, h]).all() and min(w, h) > 0):
            continue
        e = Ellipse.from_params(np.array([cx, cy, w / 2, h / 2, math.radians(ang)]))
        if e.b < 6 or e.a > max(W, H) or e.b < 0.2 * e.a:
            continue
        pts = c.reshape(-1, 2).astype(float)
        if np.mean(np.abs(sampson_distance(pts, e.conic())) <= 1.0) < 0.8:
            continue
        if len(c) / 2 < 0.4 * e.perimeter:
            continue
        cands.append((len(c), e.params))
    cands.sort(key=lambda t: -t[0])
    kept: list[np.ndarray] = []
    for _, p in cands:
        if any(
            math.hypot(p[0] - q[0], p[1] - q[1]) <= 1.5
            and abs(p[2] - q[2]) <= 1.5
            and abs(p[3] - q[3]) <= 1.5
            for q in kept
        ):
            continue
        kept.append(p)
    return np.array(kept).reshape(-1, 5)


def run_edgedrawing(
    python: str, paths: list[str], cpu: int | None
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """EdgeDrawing on saved images via the worker: ellipses and time per image path."""
    worker = Path(__file__).with_name("_edgedrawing_worker.py")
    request = json.dumps({"images": paths, "cpu": cpu, "params": {}})
    res = subprocess.run(
        [python, str(worker)], input=request, capture_output=True, text=True, check=False
    )
    if res.returncode != 0:
        raise SystemExit(f"EdgeDrawing worker failed:\n{res.stderr}")
    ells: dict[str, np.ndarray] = {}
    times: dict[str, float] = {}
    for line in res.stdout.splitlines():
        d = json.loads(line)
        if "error" in d:
            raise SystemExit(f"EdgeDrawing worker: {d['image']}: {d['error']}")
        ells[d["image"]] = np.array(d["ellipses"], dtype=float).reshape(-1, 5)
        times[d["image"]] = float(d["time_ms"])
    return ells, times


# ---------------------------------------------------------------------------------------------
# Scoring
# ---------------------------------------------------------------------------------------------


def match(dets: np.ndarray, e: Ellipse) -> int | None:
    """Index of the detection that matches ``e`` best (centre and both semi-axes within the
    tolerances), or None."""
    if len(dets) == 0:
        return None
    dc = np.hypot(dets[:, 0] - e.cx, dets[:, 1] - e.cy)
    da = np.abs(dets[:, 2] - e.a)
    db = np.abs(dets[:, 3] - e.b)
    ok = (dc <= MATCH_CENTER_PX) & (da <= MATCH_AXIS_PX) & (db <= MATCH_AXIS_PX)
    if not ok.any():
        return None
    cost = np.where(ok, dc + np.maximum(da, db), np.inf)
    return int(np.argmin(cost))


@dataclass
class Score:
    images: int = 0
    found: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RING_NAMES, 0))
    center_err: list[float] = field(default_factory=list)
    axis_err: list[float] = field(default_factory=list)
    false_pos: list[int] = field(default_factory=list)
    components: int = 0
    times_ms: list[float] = field(default_factory=list)

    def add(self, dets: np.ndarray, truth: Truth, time_ms: float) -> None:
        self.images += 1
        self.times_ms.append(time_ms)
        true_pos = np.zeros(len(dets), dtype=bool)
        for name, e in truth.ring.items():
            k = match(dets, e)
            if k is None:
                continue
            self.found[name] += 1
            true_pos[k] = True
            if name == "outer front":
                self.center_err.append(math.hypot(dets[k, 0] - e.cx, dets[k, 1] - e.cy))
                self.axis_err.append(max(abs(dets[k, 2] - e.a), abs(dets[k, 3] - e.b)))
        # A detection near any ring ellipse (even one matched by another) is not false.
        for e in truth.ring.values():
            for k in range(len(dets)):
                if match(dets[k : k + 1], e) is not None:
                    true_pos[k] = True
        for e in truth.components:
            for k in range(len(dets)):
                if match(dets[k : k + 1], e) is not None:
                    if not true_pos[k]:
                        self.components += 1
                    true_pos[k] = True
        self.false_pos.append(int((~true_pos).sum()))

    def merge(self, other: Score) -> None:
        self.images += other.images
        for k in RING_NAMES:
            self.found[k] += other.found[k]
        self.center_err += other.center_err
        self.axis_err += other.axis_err
        self.false_pos += other.false_pos
        self.components += other.components
        self.times_ms += other.times_ms


# ---------------------------------------------------------------------------------------------
# Overlays
# ---------------------------------------------------------------------------------------------

COLORS = {
    "arc-support": (0, 0, 255),
    "arc-support ROI": (0, 128, 255),
    "contours": (255, 160, 0),
    "edgedrawing": (255, 0, 255),
}


def overlay(gray: np.ndarray, truth: Truth, dets: dict[str, np.ndarray]) -> np.ndarray:
    """Truth ring (green) and each detector's ellipses side by side."""
    tiles = []
    for name in ("arc-support", "contours", "edgedrawing"):
        vis = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        for e in truth.ring.values():
            _draw(vis, e.params, (0, 200, 0))
        for p in dets.get(name, np.zeros((0, 5))):
            _draw(vis, p, COLORS[name])
        cv2.putText(vis, name, (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 1.0, COLORS[name], 2)
        tiles.append(vis)
    return np.hstack(tiles)


def _draw(vis: np.ndarray, p: np.ndarray, color: tuple[int, int, int]) -> None:
    s = 16  # sub-pixel drawing: cv2.ellipse's `shift`
    cv2.ellipse(
        vis,
        (round(p[0] * s), round(p[1] * s)),
        (round(p[2] * s), round(p[3] * s)),
        math.degrees(p[4]),
        0,
        360,
        color,
        1,
        cv2.LINE_AA,
        4,
    )


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------


def evaluate(
    path: str,
    step: int,
    contrib: str | None,
    cpu: int | None,
    overlays: Path | None,
) -> dict[str, Score]:
    seq = load_sequence(path)
    cams = ["left", "right"] if seq.calibration.is_stereo else ["left"]
    scores = {d: Score() for d in DETECTORS}
    frames = list(range(0, len(seq), step))
    records = []
    detectors: dict[str, Callable[[np.ndarray], np.ndarray]] = {
        "arc-support": arc_support,
        "contours": contour_ellipses,
    }
    show = {frames[0], frames[len(frames) // 2], frames[-1]}
    with tempfile.TemporaryDirectory() as tmp:
        for i in frames:
            for cam in cams:
                gray = undistorted_gray(seq, i, cam)
                truth = truth_ellipses(seq, i, cam)
                png = str(Path(tmp) / f"{i:06d}_{cam}.png")
                cv2.imwrite(png, gray)
                dets: dict[str, np.ndarray] = {}
                times: dict[str, float] = {}
                for name, fn in detectors.items():
                    start = time.process_time()
                    dets[name] = fn(gray)
                    times[name] = 1e3 * (time.process_time() - start)
                start = time.process_time()
                dets["arc-support ROI"] = arc_support_roi(gray, truth)
                times["arc-support ROI"] = 1e3 * (time.process_time() - start)
                records.append((i, cam, png, truth, dets, times))
            print(f"{seq.name}: frame {i}", flush=True)
        ed: tuple[dict[str, np.ndarray], dict[str, float]] | None = None
        if contrib is not None:
            ed = run_edgedrawing(contrib, [r[2] for r in records], cpu)
        for i, cam, png, truth, dets, times in records:
            if ed is not None:
                dets["edgedrawing"] = ed[0][png]
                times["edgedrawing"] = ed[1][png]
            for name in dets:
                scores[name].add(dets[name], truth, times[name])
            if overlays is not None and cam == "left" and i in show:
                gray = cv2.imread(png, cv2.IMREAD_GRAYSCALE)
                out = overlays / f"{seq.name}_{i:03d}_{cam}.png"
                cv2.imwrite(str(out), overlay(gray, truth, dets))
    return scores


def _pct(v: Sequence[float], q: float) -> str:
    return f"{np.percentile(v, q):.2f}" if len(v) else "-"


def markdown(
    command: str,
    results: dict[str, dict[str, Score]],
    contrib_note: str,
    cpu: int | None,
    step: int,
) -> str:
    now = datetime.date.today().isoformat()
    lines = [
        "# Ellipse detectors on the rendered sequences",
        "",
        f"Generated by `{command}` (machine: {platform.machine()}, {os.cpu_count()} cores, "
        f"timed on core {cpu}, {now}). Do not edit by hand.",
        "",
        ("Every frame" if step == 1 else f"Every {step}th frame")
        + " and both cameras, undistorted, whole image. A detection matches a truth "
        f"ellipse when its centre is within {MATCH_CENTER_PX:g} px and both semi-axes within "
        f"{MATCH_AXIS_PX:g} px. *outer front* is the ring's outer front edge (the target "
        "frame's circle); its centre and axis errors (largest semi-axis error) are over the "
        "images where it was found. *FP/img*: detections matching none of the four ring "
        "ellipses and no dark component (matches to components are counted in *comp.*). "
        "Time: median CPU time per image on one core (see the script's docstring). "
        f"*arc-support ROI*: the same detector in the truth outer front edge's bounding box "
        f"grown by {100 * ROI_GROWTH:.0f} % on every side, as a tracker would supply it.",
        "",
        contrib_note,
        "",
        "| sequence | detector | images | outer front found | centre err median / p95 [px] "
        "| axis err median / p95 [px] | inner front | outer base | inner base | comp. "
        "| FP/img | time median [ms] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for seq_name, scores in results.items():
        for det, s in scores.items():
            if s.images == 0:
                continue
            n = s.images

            def rate(k: str, s: Score = s, n: int = n) -> str:
                return f"{100 * s.found[k] / n:.1f} %"

            lines.append(
                f"| {seq_name} | {det} | {n} | {rate('outer front')} "
                f"| {_pct(s.center_err, 50)} / {_pct(s.center_err, 95)} "
                f"| {_pct(s.axis_err, 50)} / {_pct(s.axis_err, 95)} "
                f"| {rate('inner front')} | {rate('outer base')} | {rate('inner base')} "
                f"| {s.components} | {np.mean(s.false_pos):.2f} | {_pct(s.times_ms, 50)} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="*", default=DEFAULT_SEQUENCES)
    parser.add_argument("--out", default="docs/results/ellipses.md")
    parser.add_argument("--contrib-python", default=DEFAULT_CONTRIB_PYTHON)
    parser.add_argument("--overlays", default=None, help="folder for overlay PNGs")
    parser.add_argument("--step", type=int, default=1, help="use every STEP-th frame")
    args = parser.parse_args(argv)

    cpu: int | None = None
    if hasattr(os, "sched_setaffinity"):
        cpu = max(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
    cv2.setNumThreads(1)
    contrib: str | None = args.contrib_python
    if contrib is None or not Path(contrib).exists():
        contrib_note = (
            f"EdgeDrawing was skipped: no interpreter at `{args.contrib_python}` (create it "
            "with `python3 -m venv /work/venv-contrib && /work/venv-contrib/bin/pip install "
            "opencv-contrib-python-headless numpy`)."
        )
        contrib = None
    else:
        version = subprocess.run(
            [contrib, "-c", "import cv2; print(cv2.__version__)"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
        contrib_note = (
            f"EdgeDrawing: opencv-contrib-python-headless {version} in `{contrib}`, default "
            "parameters."
        )
    overlays = Path(args.overlays) if args.overlays else None
    if overlays is not None:
        overlays.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Score]] = {}
    total = {d: Score() for d in DETECTORS}
    for path in args.sequences:
        scores = evaluate(path, args.step, contrib, cpu, overlays)
        results[Path(path).name] = scores
        for d in DETECTORS:
            total[d].merge(scores[d])
    if len(results) > 1:
        results["all"] = total
    command = "python benchmarks/ellipse_detectors.py " + " ".join(
        a for a in (argv if argv is not None else sys.argv[1:])
    )
    text = markdown(command.strip(), results, contrib_note, cpu, args.step)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
