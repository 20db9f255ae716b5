"""Stereo calibration from a ChArUco board sequence, two ways, and its comparison with a
reference calibration.

1. **OpenCV**: ChArUco corners (``cv2.aruco.CharucoDetector``), ``cv2.calibrateCamera`` per
   camera, then ``cv2.stereoCalibrate`` with the intrinsics fixed for ``right_from_left``.
2. **pycolmap**, independently of OpenCV's estimates (it shares only the corner detections):
   a focal length from the board homographies (Zhang's orthogonality constraints, principal
   point at the image centre), per-view poses from pycolmap's absolute-pose solver, then one
   pycolmap bundle adjustment over a two-camera rig with the board corners held fixed as 3-D
   points: focal lengths, principal points, distortion (COLMAP ``OPENCV``: k1, k2, p1, p2),
   ``sensor_from_rig`` and every board pose are refined.

Conventions: COLMAP's pixel origin is the top-left corner of the top-left pixel, OpenCV's is
its centre, so COLMAP coordinates are OpenCV's + 0.5 px; everything returned here is OpenCV.
The board frame is the sequence's target frame (docs/checks.md).

The comparison (`compare_calibration`) is against the sequence's calib.yaml: for rendered
sequences that is the renderer's exact calibration; for a real recording it is whatever
calibration the user has, and the agreement between OpenCV and pycolmap is the check.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from satpose.datasets.board import BoardConfig, charuco_board
from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError, SatposeError
from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.datasets.sequence import Calibration, CameraName, Sequence

log = logging.getLogger(__name__)

CameraNames: tuple[CameraName, CameraName] = ("left", "right")
COLMAP_PIXEL_OFFSET = 0.5
"""COLMAP pixel coordinates minus OpenCV pixel coordinates [px]."""

TARGETS = {"focal_rel": 0.002, "principal_point_px": 1.0, "baseline_rel": 0.005}
"""The issue's accuracy targets for the OpenCV calibration: focal length within 0.2 %,
principal point within 1 px, baseline within 0.5 %."""


class CalibrationCheckError(SatposeError):
    """The board could not be found often enough, or a calibration failed."""


@dataclass(frozen=True, kw_only=True)
class CalibCheckConfig:
    """How `check_calibration` runs.

    Attributes:
        min_corners: a view is used if at least this many ChArUco corners are found (and they
            are not all on one line).
        min_views: fewer usable views per camera is an error.
        fix_k3: keep k3 = 0 (OpenCV ``CALIB_FIX_K3``; COLMAP's ``OPENCV`` model has no k3).
        pycolmap: also calibrate with pycolmap.
        pycolmap_loss: robust loss of the pycolmap bundle adjustment (``trivial`` is plain
            least squares, like OpenCV).
    """

    min_corners: int = 12
    min_views: int = 5
    fix_k3: bool = True
    pycolmap: bool = True
    pycolmap_loss: Literal["trivial", "cauchy"] = "trivial"

    def __post_init__(self) -> None:
        if self.min_corners < 6:
            raise ConfigError("calib check: min_corners must be >= 6 (a homography needs 4)")
        if self.min_views < 3:
            raise ConfigError("calib check: min_views must be >= 3")


# --------------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class BoardView:
    """ChArUco corners found in one image.

    Attributes:
        frame: frame index.
        ids: (M,) corner ids, increasing (rows of `board_corners`).
        pixels: (M, 2) corner positions, OpenCV pixels.
    """

    frame: int
    ids: np.ndarray
    pixels: np.ndarray


def _grey8(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    return img


def board_from_target(extras: Mapping[str, Any], where: str) -> BoardConfig:
    """The board described under ``board`` in target.yaml (see docs/checks.md)."""
    raw = extras.get("board")
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{where}: no `board` mapping; describe the ChArUco board there "
            "(dictionary, squares_x, squares_y, square_size_m, marker_size_m)"
        )
    if raw.get("kind", "charuco") != "charuco":
        raise ConfigError(f"{where}: board.kind {raw.get('kind')!r} is not supported (charuco)")
    if raw.get("legacy_pattern", False):
        raise ConfigError(f"{where}: board.legacy_pattern boards are not supported")
    keys = ("dictionary", "squares_x", "squares_y", "square_size_m", "marker_size_m")
    missing = [k for k in keys if k not in raw]
    if missing:
        raise ConfigError(f"{where}: board: missing {missing}")
    try:
        return BoardConfig(
            dictionary=str(raw["dictionary"]),
            squares_x=int(raw["squares_x"]),
            squares_y=int(raw["squares_y"]),
            square_size_m=float(raw["square_size_m"]),
            marker_size_m=float(raw["marker_size_m"]),
        )
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: board: {exc}") from None


def detect_board(
    sequence: Sequence,
    board: BoardConfig,
    min_corners: int,
    progress: Callable[[int], None] | None = None,
) -> dict[CameraName, list[BoardView]]:
    """ChArUco corners in every image of a sequence, per camera.

    Views with fewer than ``min_corners`` corners, or with all corners on one line, are
    dropped.
    """
    cv_board = charuco_board(board)
    detector = cv2.aruco.CharucoDetector(cv_board)
    cams: tuple[CameraName, ...] = CameraNames if sequence.kind == "stereo" else ("left",)
    out: dict[CameraName, list[BoardView]] = {c: [] for c in cams}
    for k, frame in enumerate(sequence):
        for cam in cams:
            corners, ids, _, _ = detector.detectBoard(_grey8(frame.image(cam)))
            if ids is None or len(ids) < min_corners:
                continue
            if cv_board.checkCharucoCornersCollinear(ids):
                continue
            ids = ids.ravel().astype(int)
            order = np.argsort(ids)
            out[cam].append(
                BoardView(
                    frame=frame.index,
                    ids=ids[order],
                    pixels=corners.reshape(-1, 2).astype(float)[order],
                )
            )
        if progress is not None:
            progress(k)
    return out


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class CalibrationFit:
    """One method's calibration and its residuals.

    Attributes:
        method: ``opencv`` or ``pycolmap``.
        calibration: the estimated calibration (OpenCV conventions).
        rms_px: RMS reprojection error per camera and, for stereo, of the stereo step [px]
            (keys ``left``, ``right``, ``stereo``).
        views: views used per camera (and ``stereo``: views seen by both cameras).
        view_rms_px: per-camera ``{frame: RMS reprojection error [px]}``.
    """

    method: str
    calibration: Calibration
    rms_px: dict[str, float]
    views: dict[str, int]
    view_rms_px: dict[str, dict[int, float]] = field(default_factory=dict)


def _object_points(board: BoardConfig, ids: np.ndarray) -> np.ndarray:
    n = board.squares_x - 1
    s = board.square_size_m
    return np.stack([(ids % n + 1) * s, (ids // n + 1) * s, np.zeros(ids.size)], axis=1)


def _stereo_pairs(
    views: Mapping[CameraName, list[BoardView]], min_corners: int
) -> list[tuple[np.ndarray, BoardView, BoardView]]:
    """Views seen by both cameras: (common ids, left view, right view)."""
    right = {v.frame: v for v in views.get("right", [])}
    pairs = []
    for lv in views["left"]:
        rv = right.get(lv.frame)
        if rv is None:
            continue
        ids = np.intersect1d(lv.ids, rv.ids)
        if ids.size >= min_corners:
            pairs.append((ids, lv, rv))
    return pairs


def _rows(view: BoardView, ids: np.ndarray) -> np.ndarray:
    return view.pixels[np.searchsorted(view.ids, ids)]


# --------------------------------------------------------------------------------------------
# OpenCV
# --------------------------------------------------------------------------------------------


def calibrate_opencv(
    views: Mapping[CameraName, list[BoardView]],
    sizes: Mapping[CameraName, tuple[int, int]],
    board: BoardConfig,
    cfg: CalibCheckConfig,
) -> CalibrationFit:
    """``cv2.calibrateCamera`` per camera, then ``cv2.stereoCalibrate`` (intrinsics fixed).

    Args:
        views: board views per camera (`detect_board`).
        sizes: ``(width, height)`` per camera [px].
    """
    flags = cv2.CALIB_FIX_K3 if cfg.fix_k3 else 0
    cameras: dict[str, PinholeCamera] = {}
    rms: dict[str, float] = {}
    view_rms: dict[str, dict[int, float]] = {}
    for cam, vs in views.items():
        _enough(cam, vs, cfg)
        obj = [_object_points(board, v.ids).astype(np.float32) for v in vs]
        img = [v.pixels.astype(np.float32).reshape(-1, 1, 2) for v in vs]
        err, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj, img, sizes[cam], None, None, flags=flags
        )
        w, h = sizes[cam]
        cameras[cam] = PinholeCamera(width=w, height=h, K=K, dist=dist.ravel()[:5])
        rms[cam] = float(err)
        per_view = {}
        for v, o, rv, tv in zip(vs, obj, rvecs, tvecs, strict=True):
            proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
            per_view[v.frame] = float(np.sqrt(np.mean(np.sum((proj[:, 0] - v.pixels) ** 2, 1))))
        view_rms[cam] = per_view
    counts = {cam: len(vs) for cam, vs in views.items()}
    if "right" not in cameras:
        return CalibrationFit(
            method="opencv",
            calibration=Calibration(left=cameras["left"]),
            rms_px=rms,
            views=counts,
            view_rms_px=view_rms,
        )
    pairs = _stereo_pairs(views, cfg.min_corners)
    if len(pairs) < cfg.min_views:
        raise CalibrationCheckError(
            f"only {len(pairs)} views show the board to both cameras with >= "
            f"{cfg.min_corners} common corners; at least {cfg.min_views} are needed"
        )
    obj = [_object_points(board, ids).astype(np.float32) for ids, _, _ in pairs]
    left = [_rows(lv, ids).astype(np.float32).reshape(-1, 1, 2) for ids, lv, _ in pairs]
    right = [_rows(rv, ids).astype(np.float32).reshape(-1, 1, 2) for ids, _, rv in pairs]
    L, R_ = cameras["left"], cameras["right"]
    err, *_, R, T, _, _ = cv2.stereoCalibrate(
        obj,
        left,
        right,
        L.K.copy(),
        L.dist.copy(),
        R_.K.copy(),
        R_.dist.copy(),
        sizes["left"],
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    rms["stereo"] = float(err)
    counts["stereo"] = len(pairs)
    calib = Calibration(left=L, right=R_, right_from_left=Rigid3(R=R, t=np.ravel(T)))
    return CalibrationFit(
        method="opencv", calibration=calib, rms_px=rms, views=counts, view_rms_px=view_rms
    )


def _enough(cam: str, vs: list[BoardView], cfg: CalibCheckConfig) -> None:
    if len(vs) < cfg.min_views:
        raise CalibrationCheckError(
            f"the board was found in {len(vs)} {cam} images (with >= {cfg.min_corners} corners); "
            f"at least {cfg.min_views} are needed"
        )


# --------------------------------------------------------------------------------------------
# pycolmap
# --------------------------------------------------------------------------------------------


def homography_focal(views: list[BoardView], board: BoardConfig, size: tuple[int, int]) -> float:
    """Focal length [px] from board homographies, principal point at the image centre and
    square pixels assumed (Zhang's two orthogonality constraints per view, least squares in
    ``1 / f^2``). Homographies from ``pycolmap.estimate_homography_matrix``."""
    import pycolmap

    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    rows, rhs = [], []
    for v in views:
        plane = _object_points(board, v.ids)[:, :2]
        found = pycolmap.estimate_homography_matrix(plane, v.pixels - c)
        if found is None:
            continue
        H = np.asarray(found["H"], float)
        h1, h2 = H[:, 0], H[:, 1]
        # h1' W h2 = 0 and h1' W h1 = h2' W h2 with W = diag(a, a, 1), a = 1 / f^2.
        rows.append(h1[0] * h2[0] + h1[1] * h2[1])
        rhs.append(-h1[2] * h2[2])
        rows.append(h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2)
        rhs.append(h2[2] ** 2 - h1[2] ** 2)
    a_arr, b_arr = np.array(rows), np.array(rhs)
    if a_arr.size == 0 or not np.any(a_arr):
        raise CalibrationCheckError("no board homography constrains the focal length")
    a = float(a_arr @ b_arr / (a_arr @ a_arr))
    if not a > 0:
        raise CalibrationCheckError(
            "board homographies give no real focal length (views too fronto-parallel?)"
        )
    return 1.0 / math.sqrt(a)


def _rigid(T: Rigid3) -> Any:
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(T.R), T.t.reshape(3, 1))


def _from_rigid(T: Any) -> Rigid3:
    return Rigid3(R=np.asarray(T.rotation.matrix()), t=np.asarray(T.translation, float).ravel())


def _mean_pose(poses: list[Rigid3]) -> Rigid3:
    """Chordal mean rotation and median translation of a few nearly equal poses."""
    U, _, Vt = np.linalg.svd(sum((p.R for p in poses), np.zeros((3, 3))))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return Rigid3(R=R, t=np.median([p.t for p in poses], axis=0))


def calibrate_pycolmap(
    views: Mapping[CameraName, list[BoardView]],
    sizes: Mapping[CameraName, tuple[int, int]],
    board: BoardConfig,
    cfg: CalibCheckConfig,
) -> CalibrationFit:
    """Calibrate with pycolmap only (see the module docstring): homography focal length,
    absolute poses, then one bundle adjustment with the board corners fixed."""
    import pycolmap

    cams = [c for c in CameraNames if c in views]
    camera_id = {c: i + 1 for i, c in enumerate(cams)}
    colmap_cams = {}
    poses: dict[str, dict[int, Rigid3]] = {}
    for cam in cams:
        _enough(cam, views[cam], cfg)
        w, h = sizes[cam]
        f = homography_focal(views[cam], board, (w, h))
        camera = pycolmap.Camera(
            camera_id=camera_id[cam],
            model="OPENCV",
            width=w,
            height=h,
            params=[f, f, w / 2, h / 2, 0.0, 0.0, 0.0, 0.0],
        )
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = 0.02 * max(w, h)  # the initial camera has no distortion
        poses[cam] = {}
        for v in views[cam]:
            r = pycolmap.estimate_and_refine_absolute_pose(
                v.pixels + COLMAP_PIXEL_OFFSET, _object_points(board, v.ids), camera, est
            )
            if r is not None:
                poses[cam][v.frame] = _from_rigid(r["cam_from_world"])
        colmap_cams[cam] = camera
    rec = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(colmap_cams["left"].sensor_id)
    right_from_left = None
    if "right" in cams:
        common = sorted(set(poses["left"]) & set(poses["right"]))
        if len(common) < cfg.min_views:
            raise CalibrationCheckError(
                f"pycolmap: only {len(common)} views have poses in both cameras"
            )
        right_from_left = _mean_pose(
            [poses["right"][k] @ poses["left"][k].inverse() for k in common]
        )
        rig.add_sensor(colmap_cams["right"].sensor_id, _rigid(right_from_left))
    for cam in cams:
        rec.add_camera(colmap_cams[cam])
    rec.add_rig(rig)
    # One frame per view; its pose is the left camera's (the rig's reference sensor).
    frame_ids: dict[int, int] = {}
    frames = sorted(set().union(*(poses[c] for c in cams)))
    obs: dict[int, list[tuple[int, int]]] = {}
    image_id = 0
    for k in frames:
        if k in poses["left"]:
            rig_from_world = poses["left"][k]
        else:
            assert right_from_left is not None
            rig_from_world = right_from_left.inverse() @ poses["right"][k]
        fid = len(frame_ids) + 1
        frame_ids[k] = fid
        frame = pycolmap.Frame(frame_id=fid, rig_id=1)
        frame.rig_from_world = _rigid(rig_from_world)
        images = []
        for cam in cams:
            view = next((v for v in views[cam] if v.frame == k), None)
            if view is None or k not in poses[cam]:
                continue
            image_id += 1
            image = pycolmap.Image(
                name=f"{cam}/{k:06d}",
                keypoints=view.pixels + COLMAP_PIXEL_OFFSET,
                camera_id=camera_id[cam],
                image_id=image_id,
            )
            image.frame_id = fid
            frame.add_data_id(image.data_id)
            images.append(image)
            for idx, corner in enumerate(view.ids):
                obs.setdefault(int(corner), []).append((image_id, idx))
        rec.add_frame(frame)
        for image in images:
            rec.add_image(image)
    config = pycolmap.BundleAdjustmentConfig()
    for iid in rec.images:
        config.add_image(iid)
    corners = _object_points(board, np.array(sorted(obs)))
    for corner, xyz in zip(sorted(obs), corners, strict=True):
        track = pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in obs[corner]])
        config.add_constant_point(rec.add_point3D(xyz, track))
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=True,
        refine_principal_point=True,
        refine_extra_params=True,
        refine_sensor_from_rig=True,
        refine_rig_from_world=True,
        print_summary=False,
    )
    if cfg.pycolmap_loss == "cauchy":
        options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.solver_options.max_num_iterations = 200
    options.ceres.solver_options.function_tolerance = 1e-12
    options.ceres.solver_options.gradient_tolerance = 1e-12
    options.ceres.solver_options.parameter_tolerance = 1e-12
    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    if not summary.is_solution_usable():
        raise CalibrationCheckError(f"pycolmap bundle adjustment failed: {summary.brief_report()}")
    out: dict[str, PinholeCamera] = {}
    for cam in cams:
        p = np.asarray(rec.cameras[camera_id[cam]].params, float)
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        K = np.array(
            [[fx, 0, cx - COLMAP_PIXEL_OFFSET], [0, fy, cy - COLMAP_PIXEL_OFFSET], [0, 0, 1.0]]
        )
        w, h = sizes[cam]
        out[cam] = PinholeCamera(width=w, height=h, K=K, dist=[k1, k2, p1, p2, 0.0])
    rms, view_rms = _colmap_residuals(rec, cams, camera_id)
    counts = {
        c: sum(1 for img in rec.images.values() if img.camera_id == camera_id[c]) for c in cams
    }
    if "right" in cams:
        sensor = rec.rig(1).sensor_from_rig(colmap_cams["right"].sensor_id)
        calib = Calibration(
            left=out["left"], right=out["right"], right_from_left=_from_rigid(sensor)
        )
        counts["stereo"] = sum(1 for fr in rec.frames.values() if fr.num_data_ids() == 2)
    else:
        calib = Calibration(left=out["left"])
    return CalibrationFit(
        method="pycolmap", calibration=calib, rms_px=rms, views=counts, view_rms_px=view_rms
    )


def _colmap_residuals(
    rec: Any, cams: list[CameraName], camera_id: Mapping[str, int]
) -> tuple[dict[str, float], dict[str, dict[int, float]]]:
    """RMS reprojection error per camera and per view of a pycolmap reconstruction [px]."""
    sq: dict[str, list[float]] = {c: [] for c in cams}
    view_rms: dict[str, dict[int, float]] = {c: {} for c in cams}
    name_of = {v: k for k, v in camera_id.items()}
    for image in rec.images.values():
        cam = name_of[image.camera_id]
        camera = rec.cameras[image.camera_id]
        cam_from_world = image.cam_from_world()
        errs = []
        for p2 in image.points2D:
            if not p2.has_point3D():
                continue
            xyz = rec.points3D[p2.point3D_id].xyz
            uv = camera.img_from_cam(cam_from_world * xyz)
            errs.append(float(np.sum((np.asarray(uv).ravel() - np.asarray(p2.xy)) ** 2)))
        sq[cam].extend(errs)
        view_rms[cam][int(image.name.split("/")[1])] = float(np.sqrt(np.mean(errs)))
    return {c: float(np.sqrt(np.mean(v))) for c, v in sq.items()}, view_rms


# --------------------------------------------------------------------------------------------
# Comparison
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class CameraErrors:
    """One camera's intrinsics against a reference.

    Attributes:
        focal_rel: (fx, fy) estimated / reference - 1.
        principal_point_px: (cx, cy) estimated - reference [px].
        dist_diff: (5,) estimated - reference distortion coefficients.
        max_image_px: largest distance over a grid of the image between where the estimated
            and the reference camera put the same ray [px] (all intrinsics together).
    """

    focal_rel: tuple[float, float]
    principal_point_px: tuple[float, float]
    dist_diff: tuple[float, ...]
    max_image_px: float


@dataclass(frozen=True, kw_only=True)
class RigErrors:
    """``right_from_left`` against a reference.

    Attributes:
        baseline_rel: estimated / reference baseline - 1.
        rotation_deg: angle of ``R_est R_ref^T`` [deg].
        direction_deg: angle between the translation vectors [deg].
    """

    baseline_rel: float
    rotation_deg: float
    direction_deg: float


def camera_errors(est: PinholeCamera, ref: PinholeCamera, grid: int = 16) -> CameraErrors:
    """Compare intrinsics; ``max_image_px`` maps a ``grid`` x ``grid`` lattice of reference
    pixels to rays with the reference camera and back to pixels with the estimated one."""
    u = np.linspace(0, ref.width - 1, grid)
    v = np.linspace(0, ref.height - 1, grid)
    px = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    rays = ref.undistort_points(px)
    back = est.normalized_to_pixels(rays)
    return CameraErrors(
        focal_rel=(est.fx / ref.fx - 1, est.fy / ref.fy - 1),
        principal_point_px=(est.cx - ref.cx, est.cy - ref.cy),
        dist_diff=tuple(float(x) for x in est.dist - ref.dist),
        max_image_px=float(np.max(np.linalg.norm(back - px, axis=1))),
    )


def rig_errors(est: Rigid3, ref: Rigid3) -> RigErrors:
    """Compare two ``right_from_left`` transforms."""
    te, tr = est.t, ref.t
    cos = float(te @ tr / (np.linalg.norm(te) * np.linalg.norm(tr)))
    return RigErrors(
        baseline_rel=float(np.linalg.norm(te) / np.linalg.norm(tr) - 1),
        rotation_deg=math.degrees(rotation_angle(est.R @ ref.R.T)),
        direction_deg=math.degrees(math.acos(min(1.0, max(-1.0, cos)))),
    )


@dataclass(frozen=True, kw_only=True)
class CalibrationErrors:
    """A calibration against a reference: per camera and the rig (stereo only)."""

    cameras: dict[str, CameraErrors]
    rig: RigErrors | None

    def meets_targets(self) -> dict[str, bool]:
        """The issue's targets (`TARGETS`), each True/False."""
        f = max(abs(x) for e in self.cameras.values() for x in e.focal_rel)
        pp = max(abs(x) for e in self.cameras.values() for x in e.principal_point_px)
        out = {
            "focal_rel": f <= TARGETS["focal_rel"],
            "principal_point_px": pp <= TARGETS["principal_point_px"],
        }
        if self.rig is not None:
            out["baseline_rel"] = abs(self.rig.baseline_rel) <= TARGETS["baseline_rel"]
        return out


def compare_calibration(est: Calibration, ref: Calibration) -> CalibrationErrors:
    """Errors of ``est`` against ``ref`` (cameras present in both; rig if both are stereo)."""
    cams: dict[str, CameraErrors] = {"left": camera_errors(est.left, ref.left)}
    if est.right is not None and ref.right is not None:
        cams["right"] = camera_errors(est.right, ref.right)
    rig = None
    if est.right_from_left is not None and ref.right_from_left is not None:
        rig = rig_errors(est.right_from_left, ref.right_from_left)
    return CalibrationErrors(cameras=cams, rig=rig)


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class CalibCheckResult:
    """Everything `check_calibration` found.

    Attributes:
        board: the board used.
        detections: views per camera with enough corners.
        fits: ``{"opencv": ..., "pycolmap": ...}``.
        versus_reference: each fit against the sequence's calib.yaml.
        opencv_vs_pycolmap: the pycolmap fit against the OpenCV fit (the check for real data).
        reference_is_truth: the sequence was rendered, so calib.yaml is exact.
    """

    board: BoardConfig
    detections: dict[str, int]
    fits: dict[str, CalibrationFit]
    versus_reference: dict[str, CalibrationErrors]
    opencv_vs_pycolmap: CalibrationErrors | None
    reference_is_truth: bool


def check_calibration(
    sequence: Sequence,
    cfg: CalibCheckConfig | None = None,
    board: BoardConfig | None = None,
    progress: Callable[[int], None] | None = None,
) -> CalibCheckResult:
    """Detect the board, calibrate with OpenCV (and pycolmap), compare with calib.yaml.

    Args:
        sequence: a board sequence (the ``calibration`` preset, or real images of a ChArUco
            board described in target.yaml).
        board: overrides target.yaml's board description.
        progress: called with the frame position after each frame's detection.
    """
    cfg = cfg or CalibCheckConfig()
    if board is None:
        extras = sequence.target.extras if sequence.target is not None else {}
        board = board_from_target(extras, str(sequence.root / "target.yaml"))
    views = detect_board(sequence, board, cfg.min_corners, progress)
    calib = sequence.calibration
    sizes = {c: calib.camera(c).size for c in views}
    fits = {"opencv": calibrate_opencv(views, sizes, board, cfg)}
    if cfg.pycolmap:
        fits["pycolmap"] = calibrate_pycolmap(views, sizes, board, cfg)
    versus = {m: compare_calibration(f.calibration, calib) for m, f in fits.items()}
    cross = None
    if "pycolmap" in fits:
        cross = compare_calibration(fits["pycolmap"].calibration, fits["opencv"].calibration)
    return CalibCheckResult(
        board=board,
        detections={c: len(v) for c, v in views.items()},
        fits=fits,
        versus_reference=versus,
        opencv_vs_pycolmap=cross,
        reference_is_truth=sequence.generator.get("tool") == "satpose-render",
    )
