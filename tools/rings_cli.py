"""``satpose rings SEQUENCE --out DIR``: the on-orbit calibration check of seed 002's boom
camera against the servicer's concentric-ring target.

Per frame: undistort the left image, find the ring target (`satpose.frontend.rings`) in a
window around its nominal projection (or the whole image without a nominal pose), estimate its
centre and normal in the camera frame with their covariance. The radii and the nominal pose
come from target.yaml ``servicer_rings`` (`satpose.datasets.servicer_rings`; the known
geometry this method needs), or the radii from ``--radii-mm``. The rendered ring pose
(``left_cam_from_rings``, truth) is used only for the report.

The check: over the frames, the mean measured centre and normal are compared with the nominal
ones. The mounting is reported as changed (``verdict=departs``) when the centre or the normal
departs from the nominal by more than ``k`` times the larger of its frame-to-frame scatter and
its propagated per-frame sigma, and by more than the floor (``--tol-mm``, ``--tol-deg``).
``mount_rotation_deg`` is the camera rotation that best maps the nominal centre direction and
normal onto the measured ones (a rotation of the camera about its centre moves both;
``range_departure_mm`` is what a rotation cannot explain: a focal-length error or a mounting
translation along the line of sight, which one view cannot tell apart). The rotation of the
target about its own axis is not observable.

DIR (written to a temporary folder, then renamed):

- ``rings.csv``: per frame the status and reason, the centre [m] and unit normal (camera
  frame), the rings' spreads, the mirror-tilt ambiguity (`satpose.frontend.rings.rings_pose`;
  the nominal normal, when known, settles it), the propagated sigmas, the number of ring
  edges used, and (with a nominal pose) the centre error [mm] and normal error [deg] against
  it, (with truth) against the rendered pose;
- ``summary.json``: the check's numbers and verdict (also printed on one line);
- ``overlay/NNNNNN.png``: every ``--overlay-every``-th frame with the detected edges (green)
  and the nominal ones (red).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import load_sequence
from satpose.datasets.servicer_rings import RingsTargetInfo, from_yaml
from satpose.frontend.conics import ConicError, Ellipse, circle_to_conic, conic_to_ellipse
from satpose.frontend.measurements import exception_failure
from satpose.frontend.preprocess import Undistorter
from satpose.frontend.rings import RingsDetection, RingsDetectorConfig, detect_rings, rings_roi
from satpose.tools.badframes import BadFrames
from satpose.tools.files import check_out, staged_output

log = logging.getLogger(__name__)

COLUMNS = (
    "frame t_s status reason n_edges cx_m cy_m cz_m nx ny nz center_spread_mm "
    "normal_spread_deg ambiguity sigma_center_mm sigma_normal_deg center_err_mm normal_err_deg "
    "truth_center_err_mm truth_normal_err_deg"
).split()


class RingsRunError(SatposeError):
    """`satpose rings` cannot run on this input."""


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(
        math.acos(float(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
    )


def _errors(det: RingsDetection, ref: Rigid3 | None) -> tuple[float, float]:
    """Centre error [mm] and normal error [deg] of a detection against a rings pose."""
    if ref is None or det.pose.center_m is None or det.pose.normal is None:
        return math.nan, math.nan
    return (
        float(np.linalg.norm(det.pose.center_m - ref.t)) * 1e3,
        _angle_deg(det.pose.normal, ref.R[:, 2]),
    )


def mount_rotation(
    center_nominal: np.ndarray,
    normal_nominal: np.ndarray,
    center: np.ndarray,
    normal: np.ndarray,
) -> np.ndarray:
    """Rotation vector [rad] of the rotation R that best maps the nominal centre direction
    and normal onto the measured ones (Kabsch on the two unit vectors, equal weights):
    the camera mounting rotation the measurement implies, ``measured = R nominal``."""
    A = np.array([center_nominal / np.linalg.norm(center_nominal), normal_nominal])
    B = np.array([center / np.linalg.norm(center), normal])
    U, _, Vt = np.linalg.svd(B.T @ A)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return matrix_to_rotvec(U @ D @ Vt)


def check_summary(
    centres: np.ndarray,
    normals: np.ndarray,
    sigma_c: np.ndarray,
    sigma_n_deg: np.ndarray,
    nominal: Rigid3 | None,
    *,
    k: float = 3.0,
    tol_mm: float = 1.0,
    tol_deg: float = 0.1,
) -> dict[str, Any]:
    """The calibration check over the frames with a pose.

    Args:
        centres: (N, 3) measured centres [m]; normals: (N, 3) unit normals.
        sigma_c: (N,) propagated centre sigmas [m]; sigma_n_deg: (N,) normal sigmas [deg].
        nominal: nominal ``left_cam_from_rings`` (None: only the scatter is reported).
        k, tol_mm, tol_deg: departure thresholds (see the module docstring).
    """
    out: dict[str, Any] = {"frames_with_pose": len(centres)}
    if len(centres) == 0:
        out["verdict"] = "no_pose"
        return out
    c = centres.mean(axis=0)
    n = normals.mean(axis=0)
    n /= np.linalg.norm(n)
    scatter_c = float(np.sqrt(np.mean(np.sum((centres - c) ** 2, axis=1))))
    scatter_n = float(np.sqrt(np.mean([_angle_deg(v, n) ** 2 for v in normals])))
    out.update(
        center_m=c.tolist(),
        normal=n.tolist(),
        scatter_center_mm=scatter_c * 1e3,
        scatter_normal_deg=scatter_n,
        median_sigma_center_mm=float(np.nanmedian(sigma_c)) * 1e3,
        median_sigma_normal_deg=float(np.nanmedian(sigma_n_deg)),
    )
    if nominal is None:
        out["verdict"] = "no_nominal"
        return out
    n_nom = nominal.R[:, 2]
    dep_c = float(np.linalg.norm(c - nominal.t)) * 1e3
    dep_n = _angle_deg(n, n_nom)
    lim_c = max(k * max(out["scatter_center_mm"], out["median_sigma_center_mm"]), tol_mm)
    lim_n = max(k * max(scatter_n, out["median_sigma_normal_deg"]), tol_deg)
    rot = np.degrees(mount_rotation(nominal.t, n_nom, c, n))
    out.update(
        center_departure_mm=dep_c,
        normal_departure_deg=dep_n,
        center_limit_mm=lim_c,
        normal_limit_deg=lim_n,
        range_departure_mm=float(np.linalg.norm(c) - np.linalg.norm(nominal.t)) * 1e3,
        mount_rotation_deg=rot.tolist(),
        verdict="departs" if (dep_c > lim_c or dep_n > lim_n) else "consistent",
    )
    return out


def _ellipse(K: np.ndarray, pose: Rigid3, r: float) -> Ellipse | None:
    try:
        return conic_to_ellipse(circle_to_conic(K, pose, r))
    except ConicError:
        return None


def draw_overlay(
    gray8: np.ndarray, det: RingsDetection, K: np.ndarray, info: RingsTargetInfo
) -> np.ndarray:
    """BGR overlay: nominal edges (red), detected edges (green)."""
    out = cv2.cvtColor(gray8, cv2.COLOR_GRAY2BGR)

    def draw(e: Ellipse, colour: tuple[int, int, int]) -> None:
        cv2.ellipse(
            out,
            (round(e.cx * 16), round(e.cy * 16)),
            (round(e.a * 16), round(e.b * 16)),
            math.degrees(e.theta),
            0,
            360,
            colour,
            1,
            cv2.LINE_AA,
            4,
        )

    if info.nominal is not None:
        for r in info.edge_radii_m:
            e = _ellipse(K, info.nominal, float(r))
            if e is not None:
                draw(e, (0, 0, 255))
    for e in det.ellipses:
        draw(e, (0, 255, 0))
    return out


def run_rings(
    sequence_path: Path,
    out: Path,
    *,
    radii_m: list[float] | None = None,
    overlay_every: int = 10,
    overwrite: bool = False,
    config: RingsDetectorConfig | None = None,
    k_sigma: float = 3.0,
    tol_mm: float = 1.0,
    tol_deg: float = 0.1,
) -> dict[str, Any]:
    """Run the rings check on a sequence (left camera); see the module docstring for the
    files. Returns the summary (also written to DIR/summary.json)."""
    seq = load_sequence(sequence_path)
    check_out(out, overwrite, error=RingsRunError)
    target_path = seq.root / "target.yaml"
    raw = seq.target.extras.get("servicer_rings") if seq.target is not None else None
    if raw is not None:
        info = from_yaml(raw, target_path)
    elif radii_m is None:
        raise RingsRunError(
            f"{target_path}: field 'servicer_rings' is missing (give the ring radii with "
            "--radii-mm)"
        )
    else:
        info = RingsTargetInfo(edge_radii_m=np.zeros(0), nominal=None, truth=None)
    if radii_m is not None:
        r = np.asarray(radii_m, float)
        if r.size < 2 or not np.all(np.isfinite(r)) or r[0] <= 0 or np.any(np.diff(r) <= 0):
            raise RingsRunError(f"--radii-mm: need >= 2 increasing positive radii, got {radii_m}")
        info = RingsTargetInfo(edge_radii_m=r, nominal=info.nominal, truth=info.truth)
    cfg = config or RingsDetectorConfig()
    cam = seq.calibration.left
    und = Undistorter(cam)
    K = cam.K
    roi = None
    if info.nominal is not None:
        roi = rings_roi(K, info.nominal, float(info.edge_radii_m[-1]), (cam.height, cam.width), cfg)
    prior = info.nominal.R[:, 2] if info.nominal is not None else None
    bad = BadFrames(seq.root)
    with staged_output(out, overwrite, error=RingsRunError) as stage:
        (stage / "overlay").mkdir()
        rows: list[list[Any]] = []
        centres: list[np.ndarray] = []
        normals: list[np.ndarray] = []
        sig_c: list[float] = []
        sig_n: list[float] = []
        for k, fr in enumerate(seq.frames):
            n0 = (len(rows), len(centres))
            why: str | None = None
            try:
                image = fr.left()
            except SatposeError as exc:
                why = f"image: {exc}"
            else:
                try:
                    prep = und(image)
                    det = detect_rings(prep, K, info.edge_radii_m, cfg, roi, prior)
                    p = det.pose
                    if p.center_m is not None and p.normal is not None:
                        centres.append(p.center_m)
                        normals.append(p.normal)
                        sig_c.append(det.sigma_center_m)
                        sig_n.append(det.sigma_normal_deg)
                        pose_cols = [*p.center_m.tolist(), *p.normal.tolist()]
                    else:
                        pose_cols = [math.nan] * 6
                    rows.append(
                        [
                            fr.index,
                            fr.t_s,
                            "ok" if p.center_m is not None else "no_pose",
                            p.reason,
                            len(det.ellipses),
                            *pose_cols,
                            p.center_spread_m * 1e3,
                            p.normal_spread_deg,
                            p.ambiguity,
                            det.sigma_center_m * 1e3,
                            det.sigma_normal_deg,
                            *_errors(det, info.nominal),
                            *_errors(det, info.truth),
                        ]
                    )
                    if overlay_every > 0 and k % overlay_every == 0:
                        img = draw_overlay(prep.gray8, det, K, info)
                        cv2.imwrite(str(stage / "overlay" / f"{fr.index:06d}.png"), img)
                except Exception as exc:
                    log.debug("frame %d: rings raised", fr.index, exc_info=True)
                    why = exception_failure("rings", exc)
            if why is not None:
                # a frame without a pose: drop what a failed step had added
                del rows[n0[0] :]
                for lst in (centres, normals, sig_c, sig_n):
                    del lst[n0[1] :]
                rows.append([fr.index, fr.t_s, "error", why, 0, *[math.nan] * 15])
            bad.note(fr.index, (rows[-1][3],) if rows[-1][3] else (), (fr.left_path,))
        with open(stage / "rings.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(COLUMNS)
            w.writerows(rows)
        summary: dict[str, Any] = {"frames": len(seq.frames)}
        summary.update(
            check_summary(
                np.array(centres).reshape(-1, 3),
                np.array(normals).reshape(-1, 3),
                np.array(sig_c),
                np.array(sig_n),
                info.nominal,
                k=k_sigma,
                tol_mm=tol_mm,
                tol_deg=tol_deg,
            )
        )
        if info.truth is not None and centres:
            e = np.array([r[-2:] for r in rows if r[2] == "ok"], dtype=float)
            summary["truth_center_err_median_mm"] = float(np.median(e[:, 0]))
            summary["truth_normal_err_median_deg"] = float(np.median(e[:, 1]))
        if bad.count:
            summary["bad_frames"] = bad.summary(len(seq.frames))
        (stage / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def summary_line(summary: dict[str, Any]) -> str:
    """The summary on one line (floats rounded, vectors as comma lists)."""
    parts = []
    for key, v in summary.items():
        if key in ("center_m", "normal"):
            continue
        if isinstance(v, float):
            parts.append(f"{key}={v:.3f}")
        elif isinstance(v, list):
            parts.append(f"{key}=" + ",".join(f"{x:.3f}" for x in v))
        else:
            parts.append(f"{key}={v}")
    return " ".join(parts)


def _radii(text: str) -> list[float]:
    try:
        return [float(x) * 1e-3 for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _handler(args: argparse.Namespace) -> None:
    summary = run_rings(
        args.sequence,
        args.out,
        radii_m=args.radii_mm,
        overlay_every=args.overlay_every,
        overwrite=args.overwrite,
        k_sigma=args.k_sigma,
        tol_mm=args.tol_mm,
        tol_deg=args.tol_deg,
    )
    print(summary_line(summary))


def register(subparsers: Any) -> None:
    """Add ``satpose rings``."""
    p = subparsers.add_parser(
        "rings",
        help="seed 002: check the camera's mounting against the servicer's ring target",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("sequence", type=Path, help="sequence folder (the left camera is used)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--radii-mm",
        type=_radii,
        default=None,
        help="band edge radii in mm, increasing, comma-separated (default: target.yaml)",
    )
    p.add_argument("--overlay-every", type=int, default=10, help="overlay PNG every N frames")
    p.add_argument("--k-sigma", type=float, default=3.0, help="departure threshold in sigmas")
    p.add_argument("--tol-mm", type=float, default=1.0, help="centre departure floor [mm]")
    p.add_argument("--tol-deg", type=float, default=0.1, help="normal departure floor [deg]")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.set_defaults(handler=_handler)
