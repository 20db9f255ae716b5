"""``satpose check-calib`` and ``satpose check-sfm``: independent checks with pycolmap.

Both parse their arguments, build the config, call one library function
(`satpose.tools.calibcheck.check_calibration`, `satpose.tools.sfmcheck.check_sfm`) and write
their results atomically into ``--out``:

check-calib SEQUENCE --out DIR
    ``calib.yaml`` (OpenCV's calibration, sequence format), ``calib_pycolmap.yaml``,
    ``calib_report.yaml`` (errors against the sequence's calib.yaml and between the two
    methods, the targets, the resolved config) and ``calib_views.csv`` (per-view RMS).
check-sfm SEQUENCE --trajectory TUM --out DIR
    ``sfm_report.yaml`` (COLMAP's health, the verdict ``ground truth`` or ``refused: ...``,
    the alignment, disagreement statistics, timings, the resolved config),
    ``sfm_frames.csv`` (per frame), ``colmap_pose.tum`` (COLMAP's ``left_cam_from_target``
    in the trajectory's target frame) and ``colmap/`` (the COLMAP model, binary).

docs/checks.md explains what they measure and when the SfM check refuses.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import yaml

from satpose.datasets.config import load_config, to_plain

if TYPE_CHECKING:
    from satpose.tools.calibcheck import CalibCheckConfig, CalibCheckResult, CalibrationErrors
    from satpose.tools.sfmcheck import SfmCheckConfig, SfmCheckResult

STATS_PERCENTILES = (50, 90)


def register(subparsers: Any) -> None:
    """Add ``check-calib`` and ``check-sfm`` to the ``satpose`` command line."""
    p = subparsers.add_parser(
        "check-calib",
        help="calibrate a stereo rig from ChArUco board images (OpenCV and pycolmap)",
        description="Detect the ChArUco board described in the sequence's target.yaml, "
        "calibrate both cameras and the rig with OpenCV and, independently, with a pycolmap "
        "bundle adjustment, and compare both with the sequence's calib.yaml (exact for "
        "rendered sequences). Writes DIR/calib.yaml (OpenCV) in the sequence format.",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="board sequence folder")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--config", type=Path, metavar="FILE", help="YAML/TOML CalibCheckConfig (see docs)"
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing output folder of this command"
    )
    p.set_defaults(handler=cmd_check_calib)

    p = subparsers.add_parser(
        "check-sfm",
        help="check a trajectory against a pycolmap reconstruction",
        description="Reconstruct the sequence with pycolmap (the stereo pair as a rig of "
        "fixed, calibrated extrinsics, so the scale is metric), judge COLMAP's own health "
        "and align the reconstruction to TUM. The verdict is 'ground truth' only if COLMAP "
        "is consistent with itself; the per-frame disagreement goes to sfm_frames.csv.",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="stereo sequence folder")
    p.add_argument(
        "--trajectory",
        type=Path,
        required=True,
        metavar="TUM",
        help="left_cam_from_target per frame (t tx ty tz qx qy qz qw), e.g. frontend_pose.tum",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--config", type=Path, metavar="FILE", help="YAML/TOML SfmCheckConfig")
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing output folder of this command"
    )
    p.set_defaults(handler=cmd_check_sfm)


# --------------------------------------------------------------------------------------------
# Writing helpers
# --------------------------------------------------------------------------------------------


def _yaml_text(data: Any) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def _write_text(path: Path, text: str) -> None:
    from satpose.tools.files import atomic_write

    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def _write_csv(path: Path, frame: pd.DataFrame) -> None:
    from satpose.tools.files import atomic_write

    atomic_write(path, lambda tmp: frame.to_csv(tmp, index=False, float_format="%.9g"))


def _num(x: float, digits: int = 6) -> float | None:
    """A float for YAML (None for NaN)."""
    return None if not math.isfinite(x) else round(float(x), digits)


# --------------------------------------------------------------------------------------------
# check-calib
# --------------------------------------------------------------------------------------------


def _errors_plain(e: CalibrationErrors) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for cam, ce in e.cameras.items():
        out[cam] = {
            "focal_rel_pct": [_num(100 * x, 5) for x in ce.focal_rel],
            "principal_point_px": [_num(x, 4) for x in ce.principal_point_px],
            "dist_diff": [_num(x, 6) for x in ce.dist_diff],
            "max_image_px": _num(ce.max_image_px, 4),
        }
    if e.rig is not None:
        out["right_from_left"] = {
            "baseline_rel_pct": _num(100 * e.rig.baseline_rel, 5),
            "rotation_deg": _num(e.rig.rotation_deg, 5),
            "direction_deg": _num(e.rig.direction_deg, 5),
        }
    return out


def calib_report(result: CalibCheckResult, cfg: CalibCheckConfig) -> dict[str, Any]:
    """The plain-data content of calib_report.yaml."""
    from satpose.tools.calibcheck import TARGETS

    ref = "truth (rendered sequence)" if result.reference_is_truth else "the sequence's calib.yaml"
    report: dict[str, Any] = {
        "reference": ref,
        "board": to_plain(result.board),
        "views_with_board": result.detections,
        "targets": {
            "focal_rel_pct": 100 * TARGETS["focal_rel"],
            "principal_point_px": TARGETS["principal_point_px"],
            "baseline_rel_pct": 100 * TARGETS["baseline_rel"],
        },
        "methods": {},
        "config": to_plain(cfg),
    }
    for method, fit in result.fits.items():
        errors = result.versus_reference[method]
        report["methods"][method] = {
            "rms_px": {k: _num(v, 4) for k, v in fit.rms_px.items()},
            "views": fit.views,
            "versus_reference": _errors_plain(errors),
            "meets_targets": errors.meets_targets(),
        }
    if result.opencv_vs_pycolmap is not None:
        report["pycolmap_minus_opencv"] = _errors_plain(result.opencv_vs_pycolmap)
    return report


def write_calib_outputs(result: CalibCheckResult, cfg: CalibCheckConfig, out: Path) -> None:
    """calib.yaml, calib_pycolmap.yaml, calib_report.yaml and calib_views.csv in ``out``."""
    from satpose.datasets.sequence import calibration_to_yaml

    for method, name in (("opencv", "calib.yaml"), ("pycolmap", "calib_pycolmap.yaml")):
        if method in result.fits:
            text = _yaml_text(calibration_to_yaml(result.fits[method].calibration))
            _write_text(out / name, text)
    _write_text(out / "calib_report.yaml", _yaml_text(calib_report(result, cfg)))
    rows = [
        {"method": m, "camera": cam, "frame": frame, "rms_px": rms}
        for m, fit in result.fits.items()
        for cam, per_view in fit.view_rms_px.items()
        for frame, rms in sorted(per_view.items())
    ]
    columns = ["method", "camera", "frame", "rms_px"]
    _write_csv(out / "calib_views.csv", pd.DataFrame(rows, columns=columns))


def _print_calib(result: CalibCheckResult) -> None:
    ref = "truth" if result.reference_is_truth else "calib.yaml"
    print(f"board found in {result.detections} images")
    for method, errors in result.versus_reference.items():
        fit = result.fits[method]
        for cam, e in errors.cameras.items():
            fx, fy = (100 * x for x in e.focal_rel)
            cx, cy = e.principal_point_px
            print(
                f"{method:8s} {cam:5s}: focal {fx:+.3f}/{fy:+.3f} %, principal point "
                f"{cx:+.2f}/{cy:+.2f} px, max image {e.max_image_px:.2f} px vs {ref}; "
                f"RMS {fit.rms_px[cam]:.3f} px"
            )
        if errors.rig is not None:
            r = errors.rig
            print(
                f"{method:8s} rig  : baseline {100 * r.baseline_rel:+.3f} %, rotation "
                f"{r.rotation_deg:.3f} deg, direction {r.direction_deg:.3f} deg vs {ref}"
            )
        met = ", ".join(
            f"{k} {'met' if v else 'MISSED'}" for k, v in errors.meets_targets().items()
        )
        print(f"{method:8s} targets: {met}")


def cmd_check_calib(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from satpose.datasets.sequence import load_sequence
    from satpose.tools.calibcheck import CalibCheckConfig, check_calibration
    from satpose.tools.files import check_out, staged_output

    cfg = load_config(CalibCheckConfig, args.config) if args.config else CalibCheckConfig()
    seq = load_sequence(args.sequence)
    check_out(args.out, args.overwrite, marker="calib_report.yaml", what="a check-calib")
    with tqdm(total=len(seq), desc="detect board", unit="frame", file=sys.stderr, delay=0.5) as bar:
        result = check_calibration(seq, cfg, progress=lambda _k: bar.update(1))
    with staged_output(
        args.out, args.overwrite, marker="calib_report.yaml", what="a check-calib"
    ) as stage:
        write_calib_outputs(result, cfg, stage)
    _print_calib(result)
    print(f"wrote {args.out}/calib.yaml (OpenCV), calib_pycolmap.yaml, calib_report.yaml")


# --------------------------------------------------------------------------------------------
# check-sfm
# --------------------------------------------------------------------------------------------


def _stats(x: np.ndarray, scale: float = 1.0, digits: int = 4) -> dict[str, float | None]:
    if x.size == 0:
        return {}
    x = x * scale
    out: dict[str, float | None] = {
        "mean": _num(float(np.mean(x)), digits),
        "rms": _num(float(np.sqrt(np.mean(x**2))), digits),
        "max": _num(float(np.max(x)), digits),
    }
    for p in STATS_PERCENTILES:
        out[f"p{p}"] = _num(float(np.percentile(x, p)), digits)
    return out


def sfm_report(result: SfmCheckResult, cfg: SfmCheckConfig, trajectory: str) -> dict[str, Any]:
    """The plain-data content of sfm_report.yaml."""
    h = result.health
    d = result.disagreement
    report: dict[str, Any] = {
        "verdict": h.verdict,
        "reasons": list(h.reasons),
        "trajectory": trajectory,
        "health": {
            "frames": len(h.frames),
            "registered_frames": sum(f.registered for f in h.frames),
            "registered_fraction": _num(h.registered_fraction, 4),
            "models": h.models,
            "points3D": h.points,
            "mean_track_length": _num(h.mean_track_length, 3),
            "mean_reprojection_px": _num(h.reprojection_px, 4),
            "rig_consistency": {
                "median_rotation_deg": _num(h.rig_rotation_deg, 4),
                "p90_rotation_deg": _num(h.rig_rotation_p90_deg, 4),
                "median_translation_cm": _num(100 * h.rig_translation_m, 3),
            },
            "worst_neighbour_agreement": _num(h.worst_neighbour_agreement, 4),
            "neighbour_pairs_judged": h.neighbour_pairs_judged,
            "masked": h.masked,
        },
        "disagreement": {
            "frames": len(d),
            "frames_in_fit": int(sum(x.used_in_fit for x in d)),
            "position_cm": _stats(np.array([x.position_m for x in d]), 100.0, 3),
            "rotation_deg": _stats(np.array([x.rotation_deg for x in d]), 1.0, 4),
        },
        "alignment": None,
        "sim3_scale": _num(result.sim3_scale, 6),
        "timings_s": {k: _num(v, 2) for k, v in result.timings_s.items()},
        "config": to_plain(cfg),
    }
    if result.alignment is not None:
        a = result.alignment
        report["alignment"] = {
            "kind": "SE(3): left_cam_from_target = left_cam_from_world @ world_from_target",
            "world_from_target_R": np.round(a.rotation, 9).tolist(),
            "world_from_target_t": np.round(a.translation, 9).tolist(),
        }
    return report


def sfm_frames_table(result: SfmCheckResult, sequence: Any) -> pd.DataFrame:
    """sfm_frames.csv: one row per selected frame (health; disagreement where available)."""
    by_pos = {x.position: x for x in result.disagreement}
    rows = []
    for f in result.health.frames:
        fr = sequence[f.position]
        row: dict[str, Any] = {
            "frame": fr.index,
            "t_s": fr.t_s,
            "registered": f.registered,
            "reproj_left_px": f.reprojection_px[0],
            "reproj_right_px": f.reprojection_px[1],
            "points_left": f.points[0],
            "points_right": f.points[1],
            "rig_rotation_deg": f.rig_rotation_deg,
            "rig_translation_m": f.rig_translation_m,
            "neighbour_agreement": f.neighbour_agreement,
        }
        d = by_pos.get(f.position)
        cols = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
        values = [*d.colmap.t, *d.colmap.quat_xyzw] if d is not None else [math.nan] * 7
        row.update({f"colmap_{c}": v for c, v in zip(cols, values, strict=True)})
        row["position_m"] = d.position_m if d is not None else math.nan
        row["rotation_deg"] = d.rotation_deg if d is not None else math.nan
        row["used_in_fit"] = d.used_in_fit if d is not None else False
        rows.append(row)
    return pd.DataFrame(rows)


def _write_model(rec: Any, out: Path) -> None:
    """The COLMAP model (binary) as ``out/colmap/``, replaced atomically."""
    final = out / "colmap"
    tmp = out / f".colmap.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        rec.write(tmp)
        if final.exists():
            old = out / f".colmap.old-{uuid.uuid4().hex[:8]}"
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_sfm_outputs(
    result: SfmCheckResult, cfg: SfmCheckConfig, sequence: Any, trajectory: str, out: Path
) -> None:
    """sfm_report.yaml, sfm_frames.csv, colmap_pose.tum and colmap/ in ``out``."""
    from satpose.tools.files import write_tum

    _write_csv(out / "sfm_frames.csv", sfm_frames_table(result, sequence))
    d = result.disagreement
    write_tum([x.t_s for x in d], [x.colmap for x in d], out / "colmap_pose.tum")
    _write_model(result.run.reconstruction, out)
    _write_text(out / "sfm_report.yaml", _yaml_text(sfm_report(result, cfg, trajectory)))


def cmd_check_sfm(args: argparse.Namespace) -> None:
    import pycolmap

    from satpose.datasets.sequence import load_sequence
    from satpose.tools.files import check_out, read_tum, staged_output
    from satpose.tools.sfmcheck import SfmCheckConfig, check_sfm, match_trajectory

    cfg = load_config(SfmCheckConfig, args.config) if args.config else SfmCheckConfig()
    seq = load_sequence(args.sequence)
    t_s, poses = read_tum(args.trajectory)
    trajectory = match_trajectory(seq, t_s, poses, str(args.trajectory))
    check_out(args.out, args.overwrite, marker="sfm_report.yaml", what="a check-sfm")
    # COLMAP logs every step at INFO and warns about thread counts; keep its errors only
    # unless asked (-v).
    if not getattr(args, "verbose", 0):
        pycolmap.logging.minloglevel = int(pycolmap.logging.Level.ERROR)
    result = check_sfm(seq, trajectory, cfg, progress=lambda m: print(m, file=sys.stderr))
    with staged_output(
        args.out, args.overwrite, marker="sfm_report.yaml", what="a check-sfm"
    ) as stage:
        write_sfm_outputs(result, cfg, seq, str(args.trajectory), stage)
    h = result.health
    pos = np.array([x.position_m for x in result.disagreement])
    rot = np.array([x.rotation_deg for x in result.disagreement])
    print(
        f"COLMAP: {sum(f.registered for f in h.frames)}/{len(h.frames)} frames registered, "
        f"{h.points} points, track length {h.mean_track_length:.1f}, reprojection "
        f"{h.reprojection_px:.2f} px, rig consistency {h.rig_rotation_deg:.3f} deg / "
        f"{100 * h.rig_translation_m:.2f} cm (median), worst neighbour agreement "
        f"{h.worst_neighbour_agreement:.0%}"
    )
    if pos.size:
        print(
            f"{args.trajectory.name} vs COLMAP over {pos.size} frames: position median "
            f"{100 * np.median(pos):.2f} cm (max {100 * pos.max():.2f}), rotation median "
            f"{np.median(rot):.3f} deg (max {rot.max():.3f})"
        )
    print(f"verdict: {h.verdict}")
    print(f"wrote {args.out}/sfm_report.yaml, sfm_frames.csv, colmap_pose.tum, colmap/")
