"""Worker for benchmarks/ellipse_detectors.py: OpenCV-contrib's EdgeDrawing ellipse detector.

Runs in its own environment (opencv-contrib-python-headless conflicts with the project's
opencv-python-headless), e.g. ``/work/venv-contrib/bin/python``. Reads one JSON request from
stdin::

    {"images": ["/tmp/x/0.png", ...], "cpu": 1, "params": {"PFmode": false}}

and writes one JSON line per image to stdout::

    {"image": "...", "time_ms": 3.2, "ellipses": [[cx, cy, a, b, theta_rad], ...]}

``time_ms`` is the CPU time of ``detectEdges`` + ``detectEllipses`` only (not reading the
PNG), on one core (the process is pinned to ``cpu`` and OpenCV runs single-threaded).
Ellipses are in OpenCV pixel coordinates (centre of the top-left pixel = (0, 0)), semi-axes
``a, b`` and the angle of the first axis from the x axis.

Standalone on purpose: it imports only the standard library, numpy and cv2.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import cv2
import numpy as np


def _ellipses(raw: object) -> list[list[float]]:
    """EdgeDrawing's Vec6d rows ``[cx, cy, r, a, b, angle_deg]``: a circle has r > 0 (and
    a = b = 0), an ellipse r = 0; the semi-axes are r + a and r + b (OpenCV's sample draws
    them with cv.ellipse, which takes semi-axes)."""
    out: list[list[float]] = []
    if raw is None:
        return out
    # (N, 1, 6) in OpenCV 4, (N, 6) in OpenCV 5.
    for row in np.asarray(raw, dtype=float).reshape(-1, 6):
        cx, cy, r, a, b, ang = (float(v) for v in row)
        out.append([cx, cy, r + a, r + b, math.radians(ang)])
    return out


def main() -> int:
    request = json.loads(sys.stdin.read())
    cpu = request.get("cpu")
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {int(cpu)})
    cv2.setNumThreads(1)
    ed = cv2.ximgproc.createEdgeDrawing()
    params = cv2.ximgproc.EdgeDrawing.Params()
    for key, value in request.get("params", {}).items():
        setattr(params, key, value)
    ed.setParams(params)
    for path in request["images"]:
        gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if gray is None:
            print(json.dumps({"image": path, "error": "cannot read image"}), flush=True)
            continue
        start = time.process_time()
        ed.detectEdges(gray)
        raw = ed.detectEllipses()
        elapsed = time.process_time() - start
        line = {"image": path, "time_ms": 1e3 * elapsed, "ellipses": _ellipses(raw)}
        print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
