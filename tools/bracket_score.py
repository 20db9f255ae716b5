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

from satpose.backend.labelling import LabellingConfig, SequenceLabeller
from satpose.datasets.bracket_family import measured_points_b
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import load_sequence
from satpose.frontend.bracket import BracketGeometry, project
from satpose.frontend.bracket_lines import StrutDetectorConfig, noise_free_hypotheses
from satpose.tools.bracket import hypothesis_candidates, partial_view, run_bracket
from satpose.tools.files import read_tum

MISLABEL_DEG = 20.0
"""A reported pose with a larger attitude error counts as mislabelled."""


def _angle_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Signed angle from direction ``b`` to ``a`` [rad]."""
    return math.atan2(float(a[0] * b[1] - a[1] * b[0]) * -1.0, float(a @ b))


def _rivals(T: Rigid3, poses: list[Rigid3], V: np.ndarray) -> list[Rigid3]:
    """The poses more than the detector's rival distance (8 deg or 5 % of the range at the
    bracket's centroid) from ``T``."""
    cfg = StrutDetectorConfig()
    ctr = V.mean(axis=0)
    range_m = float(np.linalg.norm(T.apply(ctr[None])[0]))
    out = []
    for p in poses:
        dR = math.degrees(float(np.linalg.norm(matrix_to_rotvec(p.R @ T.R.T))))
        dc = float(np.linalg.norm(p.apply(ctr[None])[0] - T.apply(ctr[None])[0]))
        if dR > cfg.rival_deg or dc > cfg.rival_rel * range_m:
            out.append(p)
    return out


def ambiguous_noise_free(T: Rigid3, V: np.ndarray, K: np.ndarray, fraction: float) -> bool:
    """Whether the exact image of the bracket (``p1, p2``, the apex from the exact strut
    lines) already fits a second pose: a P3P solution other than the truth (more than the
    detector's rival distance away: 8 deg or 5 % of the range) with the camera on the front
    face and its visible stub ends within the detector's 3 sigma (``3 px + 5 %`` of the stub)
    of the exact ones (`noise_free_hypotheses` without the strut widths). Such a frame is
    ambiguous whatever a single-frame detector does."""
    return math.isfinite(nearest_rival_offsets(T, V, K, fraction)[0])


def nearest_rival_offsets(
    T: Rigid3, V: np.ndarray, K: np.ndarray, fraction: float
) -> tuple[float, float, float]:
    """How far the exact image's second poses (the rivals of `ambiguous_noise_free`, each at
    its own maximum of the likelihood, ``refined``) put what the detector measures from
    where the truth puts it: for the rival whose visible stub ends lie nearest the true ones,
    (the larger of its two stub ends' reprojection distances [px], the larger of ``p1``'s and
    ``p2``'s [px], its attitude difference from the truth [deg]); NaNs without a rival. With
    a whole triangle (fraction 1) the "stub ends" are the apex."""
    hyps = noise_free_hypotheses(
        T, BracketGeometry(vertices_m=V), K, fraction, StrutDetectorConfig(strut_radius_m=None)
    )
    pts = measured_points_b(V, fraction)  # P1, P2, end on P1P5, end on P2P5
    true_px = project(T, pts, K)
    best = (math.nan, math.nan, math.nan)
    for h in hyps:
        if not _rivals(T, [h.pose], V):
            continue
        d = np.linalg.norm(project(h.refined, pts, K) - true_px, axis=1)
        end_px, vertex_px = float(d[2:].max()), float(d[:2].max())
        if not end_px >= best[0]:  # also replaces the NaN start
            rot = math.degrees(float(np.linalg.norm(matrix_to_rotvec(h.refined.R @ T.R.T))))
            best = (end_px, vertex_px, rot)
    return best


def decidable_noise_free(
    seq_path: Path, labelling: LabellingConfig | None = None
) -> tuple[list[bool], list[bool], int, list[float]]:
    """What the decision over frames (`SequenceLabeller`) reports on the member's *exact*
    images (every consistent pose of each frame from noise-free projections, weighed as the
    detector's, strut widths included): per frame, reported offline, reported online, how
    many reported poses are another answer than the truth (rival distance), and each frame's
    offline log-likelihood ratio. The most a detector with this decision rule can report:
    the exact data's ratio is the evidence noisy data give on average (the noise adds the
    same chi-square to every track), so where it is below the threshold, noisy data do not
    decide either."""
    seq = load_sequence(seq_path)
    assert seq.target is not None and seq.target.bracket is not None and seq.truth is not None
    b = seq.target.bracket
    V = np.array([b.P1, b.P2, b.P5])
    K = seq.calibration.left.K
    width = seq.target.extras.get("bracket_strut_width_m")
    cfg = StrutDetectorConfig(strut_radius_m=None if width is None else float(width) / 2)
    geo = BracketGeometry(vertices_m=V)
    lab = SequenceLabeller(V.mean(axis=0), labelling)
    truths, online = [], []
    poses_on: list[Rigid3 | None] = []
    for fr in seq.frames:
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        truths.append(T)
        hyps = noise_free_hypotheses(T, geo, K, b.visible_fraction, cfg)
        lab.step(fr.t_s, hypothesis_candidates(hyps))
        d = lab.online_decision()
        online.append(d.candidate)
        poses_on.append(d.pose)
    decisions = lab.decide()
    offline = [d.candidate for d in decisions]
    wrong = 0
    for k, T in enumerate(truths):
        wrong += sum(bool(_rivals(T, [p], V)) for p in (poses_on[k], decisions[k].pose) if p)
    return (
        [j is not None for j in offline],
        [j is not None for j in online],
        wrong,
        [d.log_lr for d in decisions],
    )


def _mislabelled_pose(est: Rigid3, T: Rigid3, V: np.ndarray, K: np.ndarray) -> bool:
    """A pose whose projected ``P1`` lies nearer the true image of ``P2`` than of ``P1`` (or
    the reverse), or whose attitude error exceeds 20 deg."""
    e = project(est, V[:2], K)
    t = project(T, V[:2], K)
    swapped = np.linalg.norm(e[0] - t[1]) < np.linalg.norm(e[0] - t[0]) or np.linalg.norm(
        e[1] - t[0]
    ) < np.linalg.norm(e[1] - t[1])
    rot = math.degrees(float(np.linalg.norm(matrix_to_rotvec(est.R @ T.R.T))))
    return bool(swapped or rot > MISLABEL_DEG)


def score_sequence(
    seq_path: Path,
    run_dir: Path,
    *,
    estimator: str = "none",
    detector: StrutDetectorConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
    labelling: LabellingConfig | None = None,
) -> dict[str, Any]:
    """Run `run_bracket` on a member (``estimator`` none: the per-frame poses; ``labelling``
    the decision over frames' settings, None: its defaults) into ``run_dir`` and score each
    frame: range, pose or reason, errors, point residuals.

    Returns:
        ``rows`` (per frame: ``seed`` (the folder's name), ``frame``, ``range_m``, ``T``
        (truth), ``ambiguous_exact``, ``rival_end_px``, ``rival_vertex_px``,
        ``rival_deg`` (`nearest_rival_offsets`), then ``reason`` or ``e_rot_deg``, ``e_pos_m``,
        ``mislabelled``, ``resid``, ``dtheta``, ``dend``), ``fraction``, ``V`` (P1, P2, P5),
        ``K``, ``cpu_s``, ``summary`` (`run_bracket`'s) and ``exact_wrong``; the rows of
        the paper's view also hold ``decidable_exact``, ``decidable_exact_online``,
        ``exact_lr`` (`decidable_noise_free`), ``online`` and ``online_mislabelled`` (the
        online decision's ``per_frame_online.tum``; a view without one: none online).
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
        labelling=labelling,
    )
    cpu = time.process_time() - start
    t_est, est_poses = read_tum(run_dir / "per_frame.tum")
    poses = {round(float(t), 6): p for t, p in zip(t_est, est_poses, strict=True)}
    online: dict[float, Rigid3] = {}
    n = len(seq.frames)
    exact_off, exact_on, exact_wrong, exact_lr = [False] * n, [False] * n, 0, [math.nan] * n
    if partial_view(seq) is not None:  # the paper's view: a decision over frames
        t_on, on_poses = read_tum(run_dir / "per_frame_online.tum")
        online = {round(float(t), 6): p for t, p in zip(t_on, on_poses, strict=True)}
        exact_off, exact_on, exact_wrong, exact_lr = decidable_noise_free(seq_path)
    with open(run_dir / "points.csv") as fh:
        points = {int(r["frame"]): r for r in csv.DictReader(fh)}
    rows = []
    model = measured_points_b(V, frac)  # P1, P2 and the visible ends (target frame)
    for k, fr in enumerate(seq.frames):
        T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
        rng_m = float(np.linalg.norm(T.apply(model).mean(axis=0)))
        r = points[fr.index]
        est = poses.get(round(fr.t_s, 6))
        est_on = online.get(round(fr.t_s, 6))
        rival = nearest_rival_offsets(T, V, K, frac)
        row: dict[str, Any] = {
            "seed": Path(seq_path).name,
            "frame": fr.index,
            "range_m": rng_m,
            "T": T,
            "ambiguous_exact": math.isfinite(rival[0]),
            "rival_end_px": rival[0],
            "rival_vertex_px": rival[1],
            "rival_deg": rival[2],
            "decidable_exact": exact_off[k],
            "decidable_exact_online": exact_on[k],
            "exact_lr": exact_lr[k],
            "online": est_on is not None,
            "online_mislabelled": est_on is not None and _mislabelled_pose(est_on, T, V, K),
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
    return {
        "rows": rows,
        "fraction": frac,
        "V": V,
        "K": K,
        "cpu_s": cpu,
        "summary": summary,
        "exact_wrong": exact_wrong,
    }


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
