"""``satpose bracket SEQUENCE --out DIR``: seed 002's final approach on a mono sequence.

Per frame: undistort, find the three struts (`satpose.frontend.bracket_lines`), solve the
bracket pose with its covariance (`satpose.frontend.bracket`), then smooth the per-frame poses
with the backend's constant-twist smoother (loosely coupled). The bracket geometry comes from
target.yaml: ``bracket`` if present, else ``solar_brackets[--side]`` (a known-geometry method
reads only the geometry it needs). Ground truth, if present, is used only for the report.
A ``bracket`` entry (the paper's view: ``visible_fraction`` and the struts' diameter
``bracket_strut_width_m``) is measured with `satpose.frontend.bracket_lines.detect_partial`
(base strut and stubs; every consistent pose of a frame) and the labelling is decided over
frames by `satpose.backend.labelling.SequenceLabeller` (``--decision offline|online``;
frames the motion cannot decide are refused);
``solar_brackets`` (whole triangle with its yoke) with ``detect_struts``.

DIR (written to a temporary folder, then renamed):

- ``trajectory.tum``: ``left_cam_from_target`` of the smoother (or the per-frame poses with
  ``--estimator none``), TUM ``t tx ty tz qx qy qz qw``;
- ``per_frame.tum``: the per-frame bracket poses;
- ``per_frame_online.tum`` (paper's view): the per-frame poses an ``--decision online`` run
  reports (each frame decided from the frames up to it), whatever ``--decision`` says;
- ``points.csv``: per frame the four image points, their sigma, the pose method or the reason
  a frame has no pose;
- ``overlay/NNNNNN.png``: every ``--overlay-every``-th frame with the LSD segments, strut
  candidates, the chosen struts, the points and (if known) the projected truth;
- ``errors.csv`` (with ground truth): per-frame and smoothed position / rotation errors.

A frame that cannot be measured (unreadable image, an exception inside the detection or the
solver) has no pose and its reason in points.csv; bad frames are named as warnings and
counted in the summary (``bad_frames``).
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import shutil
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import Sequence, load_sequence
from satpose.frontend.bracket import (
    BracketConfig,
    BracketGeometry,
    BracketResult,
    project,
    solve_bracket,
    to_frame_measurements,
)
from satpose.frontend.bracket_lines import (
    PartialHypothesis,
    Strut,
    StrutDetection,
    StrutDetectorConfig,
    decided_frame_pose,
    detect_partial,
    detect_struts,
    partial_candidates,
    partial_hypotheses,
    silhouette_candidates,
)
from satpose.frontend.grid_plane import GridPlaneConfig, measure_grid_plane
from satpose.frontend.measurements import FrameMeasurements, exception_failure
from satpose.frontend.preprocess import Undistorter
from satpose.tools.badframes import BadFrames
from satpose.tools.files import check_out, staged_output, write_tum

log = logging.getLogger(__name__)

POINT_COLUMNS = "frame t_s p1_x p1_y p2_x p2_y p3_x p3_y p4_x p4_y sigma_px reason".split()
ERROR_COLUMNS = (
    "frame t_s range_m pos_err_m rot_err_deg smoothed_pos_err_m smoothed_rot_err_deg".split()
)


class BracketRunError(SatposeError):
    """`satpose bracket` cannot run on this input."""


def bracket_from_target(seq: Sequence, side: int) -> tuple[BracketGeometry, float | None]:
    """The bracket (target frame) and its visible fraction from the sequence's target.yaml."""
    path = seq.root / "target.yaml"
    if seq.target is None:
        raise BracketRunError(f"{path}: missing (the bracket method needs the bracket geometry)")
    if seq.target.bracket is not None:
        b = seq.target.bracket
        frac = b.visible_fraction if b.visible_fraction < 1.0 else None
        return BracketGeometry(vertices_m=np.array([b.P1, b.P2, b.P5])), frac
    raw = seq.target.extras.get("solar_brackets")
    if not isinstance(raw, list) or not raw:
        raise BracketRunError(f"{path}: field 'bracket' (or 'solar_brackets') is missing")
    if not 0 <= side < len(raw):
        raise BracketRunError(f"{path}: solar_brackets has {len(raw)} entries, --side {side}")
    try:
        v = np.array([raw[side][k] for k in ("P1", "P2", "P5")], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise BracketRunError(
            f"{path}: solar_brackets[{side}] is not {{P1, P2, P5}} ({exc})"
        ) from None
    return BracketGeometry(vertices_m=v), None


def partial_view(seq: Sequence) -> tuple[float, float | None] | None:
    """``(visible fraction, strut radius [m] or None)`` when target.yaml describes the bracket
    for the paper's view (a ``bracket`` entry: its ``visible_fraction``, and the struts'
    diameter ``bracket_strut_width_m``), else None (``solar_brackets``: the whole triangle
    with its yoke, `detect_struts`)."""
    if seq.target is None or seq.target.bracket is None:
        return None
    path = seq.root / "target.yaml"
    width = seq.target.extras.get("bracket_strut_width_m")
    if width is None:
        return seq.target.bracket.visible_fraction, None
    try:
        w = float(width)
    except (TypeError, ValueError):
        raise BracketRunError(
            f"{path}: bracket_strut_width_m must be a number, got {width!r}"
        ) from None
    if not (math.isfinite(w) and w > 0):
        raise BracketRunError(f"{path}: bracket_strut_width_m must be positive, got {w}")
    return seq.target.bracket.visible_fraction, w / 2


def draw_overlay(
    gray8: np.ndarray,
    det: StrutDetection,
    result: BracketResult | None,
    geometry: BracketGeometry,
    K: np.ndarray,
    truth: Rigid3 | None,
) -> np.ndarray:
    """BGR overlay: LSD segments (dark green), strut candidates (blue), chosen struts (base
    red, from P1 yellow, from P2 magenta), the points (white), truth vertices (green circles),
    the estimated vertices (red crosses)."""
    out = cv2.cvtColor(gray8, cv2.COLOR_GRAY2BGR)

    def pt(p: np.ndarray) -> tuple[int, int]:
        return round(float(p[0])), round(float(p[1]))

    for s in det.segments:
        cv2.line(out, pt(s[:2]), pt(s[2:]), (0, 110, 0), 1, cv2.LINE_AA)
    for c in det.candidates:
        cv2.line(out, pt(c.end(0)), pt(c.end(1)), (255, 80, 0), 1, cv2.LINE_AA)
    if det.struts is not None:
        for c, col in zip(det.struts, ((0, 0, 255), (0, 255, 255), (255, 0, 255)), strict=True):
            cv2.line(out, pt(c.end(0)), pt(c.end(1)), col, 2, cv2.LINE_AA)
    if det.observation is not None:
        for p in det.observation.points():
            cv2.circle(out, pt(p), 4, (255, 255, 255), 1, cv2.LINE_AA)
    if truth is not None:
        for p in project(truth, geometry.vertices_m, K):
            cv2.circle(out, pt(p), 9, (0, 255, 0), 1, cv2.LINE_AA)
    if result is not None and result.pose is not None:
        for p in project(result.pose, geometry.vertices_m, K):
            cv2.drawMarker(out, pt(p), (0, 0, 255), cv2.MARKER_CROSS, 14, 1)
    return out


def _truth_pose(seq: Sequence, frame: int) -> Rigid3 | None:
    """groundtruth.csv's pose of a frame, for the overlay (None: no truth for it)."""
    if seq.truth is None:
        return None
    try:
        return seq.truth.pose(seq.truth.row_of_frame(frame))
    except KeyError:
        return None


def _error(est: Rigid3, true: Rigid3) -> tuple[float, float]:
    return (
        float(np.linalg.norm(est.t - true.t)),
        math.degrees(float(np.linalg.norm(matrix_to_rotvec(est.R.T @ true.R)))),
    )


def _as_found_or_refit(
    gray8: np.ndarray,
    K: np.ndarray,
    geo: BracketGeometry,
    fraction: float,
    config: StrutDetectorConfig,
    short_edges: bool,
) -> tuple[StrutDetection, tuple[np.ndarray, list[Strut]] | StrutDetection]:
    """`detect_partial` on the strut candidates as found (`partial_candidates` with
    ``short_edges``) and, only when they give no consistent triple, on each candidate moved
    to its strut's silhouette where its bar is only the lit part of a side-lit strut (tuning
    seed 24). Only then: where the bars as found fit, the refit moves some struts and not
    others and costs accuracy (tuning seeds 1, 26, 31: up to 1.6x their bound), and it can
    lose a triple (seed 18, frames 9-11). The detection and the candidates it used."""
    cands = partial_candidates(gray8, config, silhouette=False, short_edges=short_edges)
    det = detect_partial(gray8, K, geo, fraction, config, prepared=cands)
    if det.result is None and not det.alternatives and not isinstance(cands, StrutDetection):
        refit = silhouette_candidates(gray8, cands, config)
        det_refit = detect_partial(gray8, K, geo, fraction, config, prepared=refit)
        if det_refit.result is not None or det_refit.alternatives:
            return det_refit, refit
    return det, cands


def run_bracket(
    sequence_path: Path,
    out: Path,
    *,
    estimator: str = "offline",
    side: int = 0,
    overlay_every: int = 10,
    overwrite: bool = False,
    detector: StrutDetectorConfig | None = None,
    angular_noise: float = 1e-5,
    linear_noise: float = 2e-4,
    require_pose: bool = True,
    decision: str = "offline",
    labelling: Any = None,
    predicted_searches: int = 1,
    progress: Callable[[int, int], None] | None = None,
    grid: GridPlaneConfig | None = None,
) -> dict[str, Any]:
    """Run the bracket method on a mono (or stereo: left image only) sequence; see the module
    docstring for the files. Returns a summary (frames with a pose, RMS errors if truth).

    ``angular_noise`` [rad/s^2/sqrt(Hz)] and ``linear_noise`` [m/s^2/sqrt(Hz)] set the
    smoother's constant-twist prior (`satpose.backend.MotionConfig`). The angular default is
    10x the backend's: with 1 s between frames the backend's 1e-5 makes iSAM2's system
    indeterminate at the first twist (seen on `bracket-final`).

    A sequence without any pose is an error unless ``require_pose`` is False (benchmarks:
    then the trajectories are empty and points.csv holds every frame's reason).

    ``progress(done, total)`` is called after each frame (it may stop the run by raising:
    the output folder is then not written).

    The paper's view (a ``bracket`` entry): every frame's consistent poses go to
    `satpose.backend.labelling.SequenceLabeller` (settings ``labelling``, a
    `LabellingConfig`; None: its defaults); ``decision`` ``offline`` reports each frame as
    decided by the whole sequence (back to a track's start), ``online`` from the frames up to
    it (from the decision on). Each frame is also searched near the predictions of the
    ``predicted_searches`` best tracks. With ``labelling.plane_normals`` each frame's solar
    array normal is measured (`satpose.frontend.grid_plane.measure_grid_plane`, settings
    ``grid``) and weighed by the decision over frames."""
    if decision not in ("offline", "online"):
        raise BracketRunError(f"decision must be offline or online, got {decision!r}")
    seq = load_sequence(sequence_path)
    check_out(out, overwrite, error=BracketRunError)
    geo, fraction = bracket_from_target(seq, side)
    if fraction is not None:
        geo = BracketGeometry(vertices_m=geo.vertices_m, visible_fraction=fraction)
    cam = seq.calibration.left
    und = Undistorter(cam)
    K = cam.K
    det_cfg = StrutDetectorConfig() if detector is None else detector
    partial = partial_view(seq)
    labeller = None
    if partial is not None:
        from satpose.backend.labelling import SequenceLabeller

        det_cfg = replace(det_cfg, strut_radius_m=partial[1])
        labeller = SequenceLabeller(geo.vertices_m.mean(axis=0), labelling)
    # paper's view: frame position -> (detection, hypotheses, labeller step, online decision)
    pending: dict[int, tuple[StrutDetection, list[PartialHypothesis], int, Any]] = {}
    grey_of: dict[int, np.ndarray] = {}  # overlay frames of the paper's view, drawn at the end
    solver = BracketConfig()
    bad = BadFrames(seq.root)
    with staged_output(out, overwrite, error=BracketRunError) as stage:
        (stage / "overlay").mkdir()
        frames: list[FrameMeasurements] = []
        per_frame: list[tuple[float, Rigid3]] = []
        rows: list[list[Any]] = []
        prev: BracketResult | None = None
        for k, fr in enumerate(seq.frames):
            n0 = (len(frames), len(per_frame), len(rows))
            prev_before = prev
            why: str | None = None
            try:
                image = fr.left()
            except SatposeError as exc:
                why = f"image: {exc}"
            else:
                try:
                    prep = und(image)
                    truth = _truth_pose(seq, fr.index)
                    result: BracketResult | None = None
                    if prep.problem is not None:
                        det = StrutDetection(
                            None, None, np.zeros((0, 4)), reason=f"image {prep.problem}"
                        )
                    elif labeller is not None and partial is not None:
                        det, cands = _as_found_or_refit(
                            prep.gray8, K, geo, partial[0], det_cfg, short_edges=False
                        )
                        if det.result is None and not det.alternatives:
                            # still none: a thick short stub's two edges differ in direction
                            # by more than a long strut's (its interior edge bent by the
                            # junction or a terminator; tuning seed 20: 4-5 deg at 40 px), so
                            # its bar did not form. Pair short edges at their larger angle,
                            # the bars as found and then at their silhouettes. Only here:
                            # more bars elsewhere (the cell grid) only add hypotheses
                            det_short, short = _as_found_or_refit(
                                prep.gray8, K, geo, partial[0], det_cfg, short_edges=True
                            )
                            if det_short.result is not None or det_short.alternatives:
                                det, cands = det_short, short
                        # also near the best tracks' predictions (a least-squares start
                        # there finds a pose whose P3P pair noise turned complex)
                        near = [
                            detect_partial(
                                prep.gray8, K, geo, partial[0], det_cfg, predicted=p, prepared=cands
                            )
                            for p in labeller.predictions(fr.t_s, predicted_searches)
                        ]
                        hyps = partial_hypotheses(
                            det,
                            geo,
                            K,
                            partial[0],
                            det_cfg,
                            extra=[d for d in near if d.result is not None],
                        )
                        step_cands = hypothesis_candidates(hyps)
                        if labeller.config.plane_normals and step_cands:
                            # the solar array's plane, rigid with the bracket: one normal per
                            # frame, shared by its candidates (none: the frame goes without)
                            plane, plane_why = measure_grid_plane(image, cam, grid)
                            if plane is None:
                                log.debug("frame %d: %s", fr.index, plane_why)
                            step_cands = [replace(c, plane=plane) for c in step_cands]
                        labeller.step(fr.t_s, step_cands)
                        step = len(labeller.t_s) - 1
                        pending[k] = (det, hyps, step, labeller.online_decision())
                        if overlay_every > 0 and k % overlay_every == 0:
                            grey_of[k] = prep.gray8
                        # reported (or not) once decided, below
                        det = replace(det, reason=det.reason or "not decided")
                    else:
                        predicted = prev.pose if prev is not None else None
                        det = detect_struts(prep.gray8, K, geo, det_cfg, predicted=predicted)
                        if det.observation is None and predicted is not None:
                            # lost: search again, keeping the labelling closest to the last attitude
                            det = detect_struts(prep.gray8, K, geo, det_cfg, reference=predicted)
                        if det.observation is not None:
                            prior = (
                                prev.depths_m
                                if prev is not None and det.hypotheses == 1
                                else (det.result.depths_m if det.result is not None else None)
                            )
                            result = solve_bracket(
                                det.observation, geo, K, solver, prior_depths=prior
                            )
                    reason = det.reason if result is None else result.reason
                    if result is not None and result.pose is not None:
                        prev = result
                        per_frame.append((fr.t_s, result.pose))
                        frames.append(to_frame_measurements(result, fr.index, fr.t_s))
                    else:
                        frames.append(
                            FrameMeasurements(
                                frame=fr.index,
                                t_s=fr.t_s,
                                failures=(f"bracket: {reason or 'no pose'}",),
                            )
                        )
                    obs = det.observation
                    pts = obs.points().ravel().tolist() if obs is not None else [math.nan] * 8
                    rows.append(
                        [
                            fr.index,
                            fr.t_s,
                            *pts,
                            obs.sigma_px if obs is not None else math.nan,
                            reason,
                        ]
                    )
                    if overlay_every > 0 and k % overlay_every == 0 and k not in grey_of:
                        img = draw_overlay(prep.gray8, det, result, geo, K, truth)
                        cv2.imwrite(str(stage / "overlay" / f"{fr.index:06d}.png"), img)
                except Exception as exc:
                    log.debug("frame %d: bracket raised", fr.index, exc_info=True)
                    why = exception_failure("bracket", exc)
                    prev = prev_before
                    pending.pop(k, None)
                    grey_of.pop(k, None)
            if why is not None:
                # a frame without a pose: drop what a failed step had added
                del frames[n0[0] :], per_frame[n0[1] :], rows[n0[2] :]
                frames.append(FrameMeasurements(frame=fr.index, t_s=fr.t_s, failures=(why,)))
                rows.append([fr.index, fr.t_s, *[math.nan] * 8, math.nan, why])
            bad.note(fr.index, frames[-1].failures, (fr.left_path,))
            if progress is not None:
                progress(k + 1, len(seq.frames))
        online_poses: list[tuple[float, Rigid3]] = []
        if labeller is not None:
            decisions = labeller.decide()

            def reported(
                det: StrutDetection, hyps: list[PartialHypothesis], d: Any
            ) -> tuple[StrutDetection, BracketResult | None, str]:
                """The decided frame's detection and pose (with its covariance), or the
                refusal."""
                if d.candidate is None:
                    why = det.reason if not hyps else d.reason
                    return replace(det, observation=None, struts=None, result=None), None, why
                chosen = hyps[d.candidate]
                assert chosen.detection is not None
                # the frame's own maximum of the likelihood in the decided basin
                start = d.pose if d.pose is not None else chosen.refined
                fitted = decided_frame_pose(start, chosen.model, d.pose, labeller.agree)
                if fitted is None:
                    why = (
                        "the frame's own best pose departs from the decided track "
                        f"(decided with log-likelihood ratio {d.log_lr:.1f})"
                    )
                    return replace(det, observation=None, struts=None, result=None), None, why
                pose, cov = fitted
                res = BracketResult(pose=pose, covariance=cov, selected_by="sequence")
                return chosen.detection, res, ""

            for k, (det, hyps, step, online) in pending.items():
                fr = seq.frames[k]
                det_on, result_on, _ = reported(det, hyps, online)
                if result_on is not None and result_on.pose is not None:
                    online_poses.append((fr.t_s, result_on.pose))
                if decision == "online":
                    det, result, reason = det_on, result_on, _
                else:
                    det, result, reason = reported(det, hyps, decisions[step])
                if result is not None and result.pose is not None:
                    frames[k] = to_frame_measurements(result, fr.index, fr.t_s)
                else:
                    frames[k] = FrameMeasurements(
                        frame=fr.index, t_s=fr.t_s, failures=(f"bracket: {reason or 'no pose'}",)
                    )
                obs = det.observation
                pts = obs.points().ravel().tolist() if obs is not None else [math.nan] * 8
                rows[k] = [
                    fr.index,
                    fr.t_s,
                    *pts,
                    obs.sigma_px if obs is not None else math.nan,
                    reason,
                ]
                if k in grey_of:
                    truth = _truth_pose(seq, fr.index)
                    img = draw_overlay(grey_of[k], det, result, geo, K, truth)
                    cv2.imwrite(str(stage / "overlay" / f"{fr.index:06d}.png"), img)
            per_frame = [(m.t_s, m.pose.left_cam_from_target) for m in frames if m.pose is not None]
            write_tum(
                [t for t, _ in online_poses],
                [p for _, p in online_poses],
                stage / "per_frame_online.tum",
            )
        with open(stage / "points.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(POINT_COLUMNS)
            w.writerows(rows)
        if not per_frame and require_pose:
            raise BracketRunError(
                f"{sequence_path}: no frame gave a bracket pose ({refusal_summary(frames)})"
            )
        if not per_frame:
            estimator = "none"  # nothing to smooth: empty trajectories, the reasons written
        write_tum([t for t, _ in per_frame], [p for _, p in per_frame], stage / "per_frame.tum")
        smoothed: dict[int, Rigid3] = {}
        if estimator != "none":
            from satpose.backend import (
                BackendConfig,
                MeasurementConfig,
                MotionConfig,
                make_estimator,
            )
            from satpose.backend.online import Isam2Config

            # Loose coupling: the per-frame bracket poses are the measurements; the Cauchy
            # kernel (default) keeps a wrongly labelled frame from pulling the trajectory.
            # iSAM2 with QR: with frames 1 s apart and a small angular noise the Cholesky
            # factorisation declares the system indeterminate at the first twist (measured on
            # bracket-final with 1e-5); QR does not, and costs little at one frame per second.
            config = BackendConfig(
                motion=MotionConfig(
                    angular_accel_noise_rad_s2_rthz=angular_noise,
                    linear_accel_noise_m_s2_rthz=linear_noise,
                ),
                measurements=MeasurementConfig(coupling="loose"),
                online=Isam2Config(factorization="qr"),
            )
            est = make_estimator(estimator, seq.calibration, config)
            try:
                for m in frames:
                    est.add(m)
                e = est.estimate()
            except RuntimeError as exc:  # gtsam: an indeterminate system
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc)
                raise BracketRunError(
                    f"{sequence_path}: the {estimator} smoother failed ({first}); the per-frame "
                    "poses are available with --estimator none"
                ) from None
            smoothed = {int(f): p for f, p in zip(e.frame, e.left_cam_from_target, strict=True)}
            t_of = {fr.index: fr.t_s for fr in seq.frames}
            order = sorted(smoothed)
            write_tum(
                [t_of[f] for f in order], [smoothed[f] for f in order], stage / "trajectory.tum"
            )
        else:
            shutil.copy(stage / "per_frame.tum", stage / "trajectory.tum")
        summary: dict[str, Any] = {
            "frames": len(seq.frames),
            "frames_with_pose": len(per_frame),
        }
        if seq.truth is not None:
            err_rows = []
            pf = {m.frame: m.pose.left_cam_from_target for m in frames if m.pose is not None}
            for fr in seq.frames:
                try:
                    T = seq.truth.pose(seq.truth.row_of_frame(fr.index))
                except KeyError:
                    continue
                a = _error(pf[fr.index], T) if fr.index in pf else (math.nan, math.nan)
                b = _error(smoothed[fr.index], T) if fr.index in smoothed else (math.nan, math.nan)
                err_rows.append([fr.index, fr.t_s, float(np.linalg.norm(T.t)), *a, *b])
            with open(stage / "errors.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(ERROR_COLUMNS)
                w.writerows(err_rows)
            E = np.array([r[3:] for r in err_rows], dtype=float)
            for name, col, unit in (
                ("per_frame_pos_rms_mm", 0, 1e3),
                ("per_frame_rot_rms_deg", 1, 1.0),
                ("smoothed_pos_rms_mm", 2, 1e3),
                ("smoothed_rot_rms_deg", 3, 1.0),
            ):
                v = E[:, col][np.isfinite(E[:, col])]
                if v.size:
                    summary[name] = float(np.sqrt(np.mean(v**2)) * unit)
        if bad.count:
            summary["bad_frames"] = bad.summary(len(seq.frames))
        refused = refusal_summary(frames)
        if refused:
            summary["refused"] = refused
    return summary


def hypothesis_candidate(h: PartialHypothesis, ref: object = None, group: int = -1) -> Any:
    """A frame's consistent pose as `satpose.backend.labelling` weighs it: the frame's
    measured quantities as a function of the pose (the fit's measurement), the refined pose
    with its covariance (start, gates), the strut widths' misfit (2 dof with a known
    radius)."""
    from satpose.backend.labelling import Candidate
    from satpose.frontend.measurements import PoseMeasurement, PoseMethod

    return Candidate(
        pose=PoseMeasurement(
            left_cam_from_target=h.refined, covariance=h.covariance, method=PoseMethod.BRACKET
        ),
        image=h.model,
        image_chi2=h.width_chi2,
        image_dim=h.image_dim - (h.model.dim - 6),
        group=group,
        ref=ref,
    )


def hypothesis_candidates(hyps: list[PartialHypothesis]) -> list[Any]:
    """`hypothesis_candidate` of each, those with the same measured quantities in one group
    (`satpose.backend.labelling.Candidate.group`); ``ref`` is the hypothesis."""
    groups: list[np.ndarray] = []
    out = []
    for h in hyps:
        g = next((i for i, z in enumerate(groups) if np.array_equal(z, h.model.z)), None)
        if g is None:
            groups.append(h.model.z)
            g = len(groups) - 1
        out.append(hypothesis_candidate(h, ref=h, group=g))
    return out


def refusal_summary(frames: list[FrameMeasurements], first: int = 3) -> str:
    """``"N of M frames without a pose: <reason> (count), ..."`` for the frames whose bracket
    pose was refused, the ``first`` most frequent reasons named (the text before the
    reason's details), or "" when every frame has a pose. Each frame's full reason is in
    points.csv."""
    kinds = Counter(
        m.failures[0].removeprefix("bracket: ").split(":")[0].strip() if m.failures else "no pose"
        for m in frames
        if m.pose is None
    )
    if not kinds:
        return ""
    named = ", ".join(f"{k} ({n})" for k, n in kinds.most_common(first))
    more = f", {len(kinds) - first} other reasons" if len(kinds) > first else ""
    return f"{sum(kinds.values())} of {len(frames)} frames without a pose: {named}{more}"


def _handler(args: argparse.Namespace) -> None:
    summary = run_bracket(
        args.sequence,
        args.out,
        estimator=args.estimator,
        side=args.side,
        overlay_every=args.overlay_every,
        overwrite=args.overwrite,
        angular_noise=args.angular_noise,
        linear_noise=args.linear_noise,
        decision=args.decision,
    )
    refused = summary.pop("refused", "")
    print(
        " ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in summary.items())
    )
    if refused:
        print(f"refused: {refused} (each frame's reason: {args.out}/points.csv)")


def register(subparsers: Any) -> None:
    """Add ``satpose bracket``."""
    p = subparsers.add_parser(
        "bracket",
        help="seed 002: pose from the solar-panel bracket's struts (mono), smoothed",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("sequence", type=Path, help="sequence folder (mono, or the left camera)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--estimator",
        choices=("offline", "online", "kalman", "none"),
        default="offline",
        help="smoother for trajectory.tum (default offline; none = per-frame poses)",
    )
    p.add_argument("--side", type=int, default=0, help="which of target.yaml's solar_brackets")
    p.add_argument("--overlay-every", type=int, default=10, help="overlay PNG every N frames")
    p.add_argument(
        "--angular-noise",
        type=float,
        default=1e-5,
        help="smoother: angular acceleration noise [rad/s^2/sqrt(Hz)] (default 1e-5)",
    )
    p.add_argument(
        "--linear-noise",
        type=float,
        default=2e-4,
        help="smoother: linear acceleration noise [m/s^2/sqrt(Hz)] (default 2e-4)",
    )
    p.add_argument(
        "--decision",
        choices=("offline", "online"),
        default="offline",
        help="paper's view: report a frame's labelling as decided by the whole sequence "
        "(offline, the default) or by the frames up to it (online)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.set_defaults(handler=_handler)


def render_family_member(args: argparse.Namespace) -> None:
    """``satpose render bracket-random --seed N --out DIR [--frames N] [--size WxH]``: one
    member of the bracket family (`satpose.datasets.bracket_family`)."""
    import sys
    import time

    from tqdm import tqdm

    from satpose.datasets.bracket_family import (
        BRACKET_RANDOM_NAME,
        DEFAULT_FRAMES,
        DEFAULT_SIZE,
        BracketFamilyError,
        render_bracket_sequence,
    )
    from satpose.datasets.seed_split import seed_sets, split_of

    if args.seed is None:
        raise BracketFamilyError(f"render {BRACKET_RANDOM_NAME} needs --seed N ({seed_sets()})")
    for flag in ("spp", "config"):
        if getattr(args, flag, None) is not None:
            raise BracketFamilyError(
                f"render {BRACKET_RANDOM_NAME}: --{flag} does not apply (a numpy ray caster "
                "with 2x2 samples per pixel; the scene is the seed's)"
            )
    frames = args.frames or DEFAULT_FRAMES
    size = args.size or DEFAULT_SIZE
    start = time.perf_counter()
    with tqdm(
        total=frames,
        desc=f"render {BRACKET_RANDOM_NAME} {args.seed}",
        unit="frame",
        file=sys.stderr,
        dynamic_ncols=True,
        delay=0.5,
    ) as bar:
        render_bracket_sequence(
            args.seed,
            args.out,
            frames=frames,
            size=size,
            overwrite=args.overwrite,
            progress=lambda _k: bar.update(1),
        )
    elapsed = time.perf_counter() - start
    print(
        f"wrote {frames} mono frames ({size[0]}x{size[1]}) of {BRACKET_RANDOM_NAME} seed "
        f"{args.seed} ({split_of(args.seed)} set) to {args.out} in {elapsed:.1f} s"
    )
