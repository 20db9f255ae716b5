"""`satpose bracket` on a bracket-family member against its truth, frame by frame (issue 19).

Used by ``benchmarks/bracket_family.py`` (docs/results/bracket_family_*.md) and by the
campaign's bracket cells (``pipeline: bracket``, `satpose.tools.campaign`), which store the
score of a member as a results-table column (`score_to_json`, JSON text) and give it back
(`score_from_json`) so that the benchmark builds its tables from a campaign.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from satpose.datasets.bracket_family import measured_points_b
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import load_sequence
from satpose.frontend.bracket import (
    BracketGeometry,
    absolute_orientation,
    incentre,
    p3p_depths,
    project,
)
from satpose.frontend.bracket_lines import StrutDetectorConfig
from satpose.tools.bracket import run_bracket
from satpose.tools.files import read_tum

MISLABEL_DEG = 20.0
"""A reported pose with a larger attitude error counts as mislabelled."""


def _angle_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Signed angle from direction ``b`` to ``a`` [rad]."""
    return math.atan2(float(a[0] * b[1] - a[1] * b[0]) * -1.0, float(a @ b))


def ambiguous_noise_free(T: Rigid3, V: np.ndarray, K: np.ndarray, fraction: float) -> bool:
    """Whether the exact image of the bracket (``p1, p2``, the apex from the exact strut
    lines) already fits a second pose: a P3P solution other than the truth (more than the
    detector's rival distance away: 8 deg or 5 % of the range) with the camera on the front
    face and its visible stub ends within the detector's 3 sigma (``3 px + 5 %`` of the stub)
    of the exact ones. Such a frame is ambiguous whatever the detector does."""
    cfg = StrutDetectorConfig()
    geo = BracketGeometry(vertices_m=V, vertex_sigma_m=0.0)
    px = project(T, V, K)
    rays = np.c_[px, np.ones(3)] @ np.linalg.inv(K).T
    rays = rays / rays[:, 2:3]
    ends = np.array([V[0] + fraction * (V[2] - V[0]), V[1] + fraction * (V[2] - V[1])])
    true_ends = project(T, ends, K)
    ctr = V.mean(axis=0)
    range_m = float(np.linalg.norm(T.apply(ctr[None])[0]))
    mod4 = np.vstack([V, incentre(V)])
    for d in p3p_depths(rays, geo.sides_m):
        cam = d[:, None] * rays
        R, t = absolute_orientation(mod4, np.vstack([cam, incentre(cam)]))
        pose = Rigid3(R=R, t=t)
        dR = math.degrees(float(np.linalg.norm(matrix_to_rotvec(pose.R @ T.R.T))))
        dc = float(np.linalg.norm(pose.apply(ctr[None])[0] - T.apply(ctr[None])[0]))
        if dR <= cfg.rival_deg and dc <= cfg.rival_rel * range_m:
            continue  # the truth itself
        normal = pose.rotate(np.cross(V[1] - V[0], V[2] - V[0]))
        if float(-pose.apply(V.mean(axis=0)[None])[0] @ normal) <= 0:
            continue
        if fraction < 1:
            e = project(pose, ends, K)
            ok = True
            for i, start in ((0, px[0]), (1, px[1])):
                length = float(np.linalg.norm(true_ends[i] - start))
                sigma = cfg.end_sigma_px + cfg.end_sigma_rel * length
                if float(np.linalg.norm(e[i] - true_ends[i])) > cfg.max_end_chi * sigma:
                    ok = False
            if not ok:
                continue
        return True
    return False


def score_sequence(
    seq_path: Path,
    run_dir: Path,
    *,
    estimator: str = "none",
    detector: StrutDetectorConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run `run_bracket` on a member (``estimator`` none: the per-frame poses) into
    ``run_dir`` and score each frame: range, pose or reason, errors, point residuals.

    Returns:
        ``rows`` (per frame: ``seed`` (the folder's name), ``frame``, ``range_m``, ``T``
        (truth), ``ambiguous_exact``, then ``reason`` or ``e_rot_deg``, ``e_pos_m``,
        ``mislabelled``, ``resid``, ``dtheta``, ``dend``), ``fraction``, ``V`` (P1, P2, P5),
        ``K``, ``cpu_s`` and ``summary`` (`run_bracket`'s).
    """
    seq = load_sequence(seq_path)
    if seq.target is None or seq.target.bracket is None or seq.truth is None:
        raise ValueError(f"{seq_path}: the bracket score needs target.yaml's bracket and truth")
    b = seq.target.bracket
    V = np.array([b.P1, b.P2, b.P5])
    frac = b.visible_fraction
    K = seq.calibration.left.K
    start = time.process_time()
    summary = run_bracket(
        seq_path,
        run_dir,
        estimator=estimator,
        detector=detector,
        overlay_every=0,
        overwrite=True,
        require_pose=False,
        progress=progress,
    )
    cpu = time.process_time() - start
    t_est, est_poses = read_tum(run_dir / "per_frame.tum")
    poses = {round(float(t), 6): p for t, p in zip(t_est, est_poses, strict=True)}
    with open(run_dir / "points.csv") as fh:
        points = {int(r["frame"]): r for r in csv.DictReader(fh)}
    rows = []
    model = measured_points_b(V, frac)  # P1, P2 and the visible ends (target frame)
    for fr in seq.frames:
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        rng_m = float(np.linalg.norm(T.apply(model).mean(axis=0)))
        r = points[fr.index]
        est = poses.get(round(fr.t_s, 6))
        row: dict[str, Any] = {
            "seed": Path(seq_path).name,
            "frame": fr.index,
            "range_m": rng_m,
            "T": T,
            "ambiguous_exact": ambiguous_noise_free(T, V, K, frac),
        }
        if est is None:
            row["reason"] = r["reason"].split(":")[0].split(" (")[0] or "no pose"
        else:
            p = np.array([float(r[k]) for k in "p1_x p1_y p2_x p2_y p3_x p3_y p4_x p4_y".split()])
            p = p.reshape(4, 2)
            true_px = project(T, model, K)  # P1, P2, end on P1P5, end on P2P5
            apex = project(T, V[2:3], K)[0]
            mislabel_pts = np.linalg.norm(p[0] - true_px[1]) < np.linalg.norm(
                p[0] - true_px[0]
            ) or np.linalg.norm(p[1] - true_px[0]) < np.linalg.norm(p[1] - true_px[1])
            e_rot = matrix_to_rotvec(est.R @ T.R.T)  # camera-frame rotation error
            e_pos = est.t - T.t
            row.update(
                e_rot_deg=np.degrees(e_rot),
                e_pos_m=e_pos,
                mislabelled=bool(mislabel_pts or np.degrees(np.linalg.norm(e_rot)) > MISLABEL_DEG),
                # residuals per coordinate: p1, p2 (2 each), p4 and p3 across their true struts
                resid=[*(p[0] - true_px[0]), *(p[1] - true_px[1])],
                dtheta=[
                    _angle_diff(p[3] - p[0], apex - true_px[0]),
                    _angle_diff(p[2] - p[1], apex - true_px[1]),
                ],
                dend=[
                    float(np.linalg.norm(p[3] - p[0]) - np.linalg.norm(true_px[2] - true_px[0])),
                    float(np.linalg.norm(p[2] - p[1]) - np.linalg.norm(true_px[3] - true_px[1])),
                ]
                if frac < 1
                else [],
            )
        rows.append(row)
    return {"rows": rows, "fraction": frac, "V": V, "K": K, "cpu_s": cpu, "summary": summary}


def _plain(v: Any) -> Any:
    if isinstance(v, Rigid3):
        return {"R": v.R.tolist(), "t": v.t.tolist()}
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_plain(x) for x in v]
    return v


def score_to_json(score: dict[str, Any]) -> str:
    """A `score_sequence` result as JSON text (the campaign's ``bracket.score`` column;
    floats round-trip exactly)."""
    return json.dumps(_plain(score))


def score_from_json(text: str) -> dict[str, Any]:
    """The inverse of `score_to_json`: poses as `Rigid3`, vectors as arrays."""
    score = json.loads(text)
    for row in score["rows"]:
        row["T"] = Rigid3(R=np.array(row["T"]["R"]), t=np.array(row["T"]["t"]))
        for k in ("e_rot_deg", "e_pos_m"):
            if k in row:
                row[k] = np.array(row[k])
    score["V"] = np.array(score["V"])
    score["K"] = np.array(score["K"])
    return score
