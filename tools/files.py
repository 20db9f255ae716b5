"""Result files: measurements as Parquet, trajectories as TUM, all written atomically.

measurements.parquet holds one row per item (long format), so that any tool reading Parquet
can filter it without knowing satpose; `read_measurements` rebuilds the frontend's
`FrameMeasurements` exactly. Columns:

- ``frame`` (int64), ``t_s`` (float64): the frame.
- ``item`` (string): ``frame``, ``ellipse``, ``ring``, ``landmark``, ``pose``, ``spin``,
  ``failure``, ``timing``.
- ``camera`` (string): ``left``/``right`` for ellipses.
- ``track_id`` (int64): landmark track id, -1 otherwise.
- ``label`` (string): landmark kind, pose method, ellipse source, spin status or timing stage.
- ``values`` (list<float64>): ellipse ``[cx, cy, a, b, angle]``; ring
  ``[cx, cy, cz, nx, ny, nz, r]``; landmark ``[ul, vl, ur, vr, X, Y, Z]`` (NaN where
  absent); pose ``[tx, ty, tz, qx, qy, qz, qw]``; spin ``[rate_rad_s, sigma_rad_s,
  window_start_s, window_end_s, samples, *candidates_rad_s]`` (rate and sigma NaN when refused
  without a candidate; the candidates of an ``ambiguous`` rate follow, none otherwise);
  timing ``[ms]``.
- ``covariance`` (list<float64>): row-major, matching ``values`` (5x5; 7x7; 3x3 of X; 6x6
  over [rotation, translation]).
- ``points`` (list<float64>): ellipse edge points ``[x0, y0, x1, y1, ...]``.
- ``sigma_px`` (float64): pixel noise of ellipses and landmarks.
- ``text`` (string): failure reasons; the reason a spin rate was refused.

TUM: ``t tx ty tz qx qy qz qw`` per line, space separated (readable by evo).
"""

from __future__ import annotations

import shutil
import uuid
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import atomic_write, replace_dir
from satpose.frontend.measurements import (
    EllipseObservation,
    FrameMeasurements,
    LandmarkMeasurement,
    PoseMeasurement,
    RingMeasurement,
    SpinRateMeasurement,
)


class ResultFileError(SatposeError):
    """A result file is missing, unreadable or malformed."""


def check_out(
    out: Path,
    overwrite: bool,
    *,
    marker: str | None = None,
    what: str = "an output",
    error: type[SatposeError] = ResultFileError,
) -> None:
    """Refuse an output folder we must not replace, before any work is done.

    A missing or empty folder is fine. A non-empty one is replaced only with ``overwrite``
    and, when ``marker`` is given, only if it holds that file (it is then one of ours: a
    ``what`` folder, e.g. ``"a run"``); any other non-empty folder is never touched.
    """
    if not out.exists():
        return
    if not out.is_dir():
        raise error(f"{out}: exists and is not a folder")
    if not any(out.iterdir()):
        return
    if marker is not None and not (out / marker).is_file():
        raise error(f"{out}: folder is not empty and not {what} folder (no {marker})")
    if not overwrite:
        raise error(f"{out}: {what} folder already exists (choose another folder or --overwrite)")


def make_stage(out: Path, error: type[SatposeError] = ResultFileError) -> Path:
    """An empty hidden folder next to ``out`` (``.<name>.tmp-xxxxxxxx``) to build it in."""
    stage = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage.mkdir()
    except OSError as exc:
        raise error(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    return stage


@contextmanager
def staged_output(
    out: Path,
    overwrite: bool,
    *,
    marker: str | None = None,
    what: str = "an output",
    error: type[SatposeError] = ResultFileError,
) -> Iterator[Path]:
    """Build the output folder ``out`` in a staging folder and rename it into place at the
    end, so that a failure or Ctrl-C leaves nothing (and an existing folder, replaced only
    with ``overwrite``, stays as it was until the new one is complete)::

        with staged_output(out, overwrite, marker="run.yaml", what="a run") as stage:
            write_files(stage)

    `check_out` (``marker``, ``what``, ``error``) runs first, before any work.
    """
    check_out(out, overwrite, marker=marker, what=what, error=error)
    stage = make_stage(out, error)
    try:
        yield stage
        replace_dir(stage, out, overwrite=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------------------------
# Measurements
# ----------------------------------------------------------------------------------------------


def _row(m: FrameMeasurements, item: str, **kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "frame": m.frame,
        "t_s": m.t_s,
        "item": item,
        "camera": None,
        "track_id": -1,
        "label": None,
        "values": [],
        "covariance": [],
        "points": [],
        "sigma_px": np.nan,
        "text": None,
    }
    base.update(kw)
    return base


def measurements_to_frame(items: Iterable[FrameMeasurements], timings: bool = True) -> pd.DataFrame:
    """The long-format table of a sequence of frame measurements (``timings``: include the
    per-stage wall times, the only values that differ between identical runs)."""
    rows: list[dict[str, Any]] = []
    for m in items:
        rows.append(_row(m, "frame"))
        if m.ring is not None:
            for e in m.ring.ellipses:
                rows.append(
                    _row(
                        m,
                        "ellipse",
                        camera=e.camera.value,
                        label=e.source,
                        values=[*e.center_px, *e.axes_px, e.angle_rad],
                        covariance=e.covariance.ravel().tolist(),
                        points=e.edge_points_px.ravel().tolist(),
                        sigma_px=e.sigma_px,
                    )
                )
            rows.append(
                _row(
                    m,
                    "ring",
                    values=[*m.ring.center_m, *m.ring.normal, m.ring.radius_m],
                    covariance=m.ring.covariance.ravel().tolist(),
                )
            )
        for lm in m.landmarks:
            right = lm.right_px if lm.right_px is not None else [np.nan, np.nan]
            point = lm.point_m if lm.point_m is not None else [np.nan] * 3
            cov = lm.covariance.ravel().tolist() if lm.covariance is not None else []
            rows.append(
                _row(
                    m,
                    "landmark",
                    track_id=lm.track_id,
                    label=lm.kind.value,
                    values=[*lm.left_px, *right, *point],
                    covariance=cov,
                    sigma_px=lm.sigma_px,
                )
            )
        if m.pose is not None:
            T = m.pose.left_cam_from_target
            rows.append(
                _row(
                    m,
                    "pose",
                    label=m.pose.method.value,
                    values=[*T.t, *T.quat_xyzw],
                    covariance=m.pose.covariance.ravel().tolist(),
                )
            )
        if m.spin is not None:
            sp = m.spin
            rows.append(
                _row(
                    m,
                    "spin",
                    label=sp.status.value,
                    values=[
                        sp.rate_rad_s,
                        sp.sigma_rad_s,
                        sp.window_start_s,
                        sp.window_end_s,
                        float(sp.samples),
                        *sp.candidates_rad_s,
                    ],
                    text=sp.reason,
                )
            )
        for f in m.failures:
            rows.append(_row(m, "failure", text=f))
        for stage, ms in m.timings_ms.items() if timings else ():
            rows.append(_row(m, "timing", label=stage, values=[float(ms)]))
    columns = [
        "frame",
        "t_s",
        "item",
        "camera",
        "track_id",
        "label",
        "values",
        "covariance",
        "points",
        "sigma_px",
        "text",
    ]
    df = pd.DataFrame(rows, columns=columns)
    return df.astype(
        {"frame": "int64", "t_s": "float64", "track_id": "int64", "sigma_px": "float64"}
    )


def write_measurements(
    items: Sequence[FrameMeasurements], path: str | Path, timings: bool = True
) -> Path:
    """Write measurements.parquet atomically (see `measurements_to_frame` for ``timings``)."""
    df = measurements_to_frame(items, timings)
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False))


def read_measurements(path: str | Path) -> list[FrameMeasurements]:
    """Rebuild the frontend's per-frame measurements from measurements.parquet."""
    p = Path(path)
    if not p.is_file():
        raise ResultFileError(f"{p}: measurements file is missing")
    try:
        df = pd.read_parquet(p)
    except Exception as exc:  # pyarrow raises many types for corrupt files
        raise ResultFileError(f"{p}: not a readable Parquet file ({exc})") from None
    needed = {"frame", "t_s", "item", "values", "covariance"}
    if not needed <= set(df.columns):
        raise ResultFileError(f"{p}: missing columns {sorted(needed - set(df.columns))}")
    by_frame: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for rec in df.to_dict("records"):
        by_frame[int(rec["frame"])].append(rec)
    out = []
    for frame in sorted(by_frame):
        recs = by_frame[frame]
        out.append(_frame_from_rows(frame, recs))
    return out


def _arr(values: Any, shape: tuple[int, ...]) -> np.ndarray:
    return np.asarray(list(values), dtype=float).reshape(shape)


def _frame_from_rows(frame: int, recs: list[dict[str, Any]]) -> FrameMeasurements:
    t_s = float(recs[0]["t_s"])
    ellipses = []
    ring = None
    landmarks = []
    pose = None
    spin = None
    failures = []
    timings = {}
    for r in recs:
        item = r["item"]
        v = np.asarray(list(r["values"]), dtype=float)
        if item == "ellipse":
            ellipses.append(
                EllipseObservation(
                    camera=r["camera"],
                    center_px=v[:2],
                    axes_px=v[2:4],
                    angle_rad=float(v[4]),
                    conic=_conic(v),
                    covariance=_arr(r["covariance"], (5, 5)),
                    edge_points_px=_arr(r["points"], (-1, 2)),
                    sigma_px=float(r["sigma_px"]),
                    source=r["label"],
                )
            )
        elif item == "ring":
            ring = (v, _arr(r["covariance"], (7, 7)))
        elif item == "landmark":
            has_right = bool(np.all(np.isfinite(v[2:4])))
            has_point = bool(np.all(np.isfinite(v[4:7])))
            landmarks.append(
                LandmarkMeasurement(
                    track_id=int(r["track_id"]),
                    kind=r["label"],
                    left_px=v[:2],
                    right_px=v[2:4] if has_right else None,
                    sigma_px=float(r["sigma_px"]),
                    point_m=v[4:7] if has_point else None,
                    covariance=_arr(r["covariance"], (3, 3)) if has_point else None,
                )
            )
        elif item == "pose":
            pose = PoseMeasurement(
                left_cam_from_target=Rigid3.from_quat_xyzw(v[3:7], v[:3]),
                covariance=_arr(r["covariance"], (6, 6)),
                method=r["label"],
            )
        elif item == "spin":
            spin = SpinRateMeasurement(
                rate_rad_s=float(v[0]),
                sigma_rad_s=float(v[1]),
                status=r["label"],
                window_start_s=float(v[2]),
                window_end_s=float(v[3]),
                samples=int(v[4]),
                reason=str(r["text"] or ""),
                candidates_rad_s=tuple(float(c) for c in v[5:]),
            )
        elif item == "failure":
            failures.append(str(r["text"]))
        elif item == "timing":
            timings[str(r["label"])] = float(v[0])
    ring_m = None
    if ring is not None:
        v, cov = ring
        ring_m = RingMeasurement(
            ellipses=tuple(ellipses),
            center_m=v[:3],
            normal=v[3:6],
            radius_m=float(v[6]),
            covariance=cov,
        )
    return FrameMeasurements(
        frame=frame,
        t_s=t_s,
        ring=ring_m,
        landmarks=tuple(landmarks),
        pose=pose,
        failures=tuple(failures),
        timings_ms=timings,
        spin=spin,
    )


def _conic(v: np.ndarray) -> np.ndarray:
    from satpose.frontend.conics import Ellipse

    return Ellipse.from_params(v).conic()


# ----------------------------------------------------------------------------------------------
# TUM trajectories
# ----------------------------------------------------------------------------------------------


def write_tum(t_s: Sequence[float], poses: Sequence[Rigid3], path: str | Path) -> Path:
    """Write ``t tx ty tz qx qy qz qw`` lines atomically (the pose is ``left_cam_from_target``
    or whatever the caller documents)."""
    lines = [
        " ".join(f"{x:.9f}" for x in (t, *T.t, *T.quat_xyzw))
        for t, T in zip(t_s, poses, strict=True)
    ]
    text = "\n".join(lines) + ("\n" if lines else "")
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def read_tum(path: str | Path) -> tuple[np.ndarray, list[Rigid3]]:
    """Read a TUM trajectory: times (N,) and poses."""
    p = Path(path)
    if not p.is_file():
        raise ResultFileError(f"{p}: trajectory file is missing")
    t, poses = [], []
    for k, line in enumerate(p.read_text().splitlines()):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError:
            raise ResultFileError(f"{p}: line {k + 1}: not 8 numbers") from None
        if v.size != 8 or not np.all(np.isfinite(v)):
            raise ResultFileError(
                f"{p}: line {k + 1}: expected 8 finite numbers (t tx ty tz qx qy qz qw)"
            )
        q = v[4:8]
        if abs(np.linalg.norm(q) - 1) > 1e-6:
            raise ResultFileError(f"{p}: line {k + 1}: quaternion is not unit norm")
        t.append(v[0])
        poses.append(Rigid3.from_quat_xyzw(q / np.linalg.norm(q), v[1:4]))
    return np.array(t), poses
