"""Calibration readers: Kalibr camchain, OpenCV FileStorage (YAML/XML), ROS CameraInfo
(messages and camera_calibration's YAML files) and satpose's own calib.yaml.

Each returns a `SourceCalibration` in the source's own terms (lens model, coefficients, image
size if stated); `read_calibration_file` tells the formats apart by their content. Keys read
(docs/import.md, "Calibration files"):

- Kalibr camchain: ``cam0``/``cam1`` with ``camera_model: pinhole``, ``intrinsics: [fu, fv,
  pu, pv]``, ``distortion_model: radtan | equidistant``, ``distortion_coeffs``,
  ``resolution: [w, h]``, optional ``rostopic``; cam1's ``T_cn_cnm1`` (4x4, maps cam0
  coordinates into cam1) is ``right_from_left``.
- OpenCV FileStorage: one camera as ``camera_matrix`` + ``distortion_coefficients`` (the
  calibration sample's names; ``K``/``D`` and ``cameraMatrix``/``distCoeffs`` also), or a
  stereo pair as ``K1 D1 K2 D2 R T`` (``M1``/``M2`` for K, stereo_calib's names) where R, T
  are stereoCalibrate's (``x_right = R x_left + T``); image size from ``image_width`` +
  ``image_height`` or ``image_size``/``imageSize`` ``[w, h]`` if present. 4/5 coefficients are
  radtan, 8/12/14 rational; ``distortion_model: equidistant`` (or ``fisheye``) marks
  cv2.fisheye coefficients.
- ROS CameraInfo: ``distortion_model`` ``plumb_bob`` (radtan), ``rational_polynomial``,
  ``equidistant``; K, D, and for a stereo pair the rectification R and projection P of both
  cameras (see `stereo_from_camera_infos`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from satpose.datasets.config import yaml_problem
from satpose.datasets.errors import shown
from satpose.datasets.geometry import GeometryError, Rigid3, is_rotation
from satpose.datasets.importers.common import (
    LensModel,
    RecordingError,
    SourceCalibration,
    SourceCamera,
)

ROS_MODELS: dict[str, LensModel] = {
    "plumb_bob": "radtan",
    "rational_polynomial": "rational",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
}
"""ROS ``CameraInfo.distortion_model`` names to lens models (image_geometry's names;
``fisheye`` is what some drivers write for equidistant)."""

KALIBR_MODELS: dict[str, LensModel] = {
    "radtan": "radtan",
    "radial-tangential": "radtan",
    "equidistant": "equidistant",
}
"""Kalibr / EuRoC ``distortion_model`` names (EuRoC's sensor.yaml says ``radial-tangential``)."""


def rigid_from_matrix(T: np.ndarray, path: Path, field: str) -> Rigid3:
    """A 4x4 ``[[R, t], [0, 1]]`` as `Rigid3` (R re-orthonormalised), or `RecordingError`."""
    m = np.asarray(T, dtype=float)
    if m.shape != (4, 4) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise RecordingError(path, field, "must be a 4x4 homogeneous transform [[R, t], [0, 1]]")
    return _rt(m[:3, :3], m[:3, 3], path, field)


def _rt(R: np.ndarray, t: np.ndarray, path: Path, field: str) -> Rigid3:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not is_rotation(R, tol=1e-6):
        raise RecordingError(path, field, "rotation is not orthonormal with det +1")
    # Files carry 6-9 digits: re-orthonormalise (SVD) so that Rigid3 and the loader's unit
    # quaternion check see an exact rotation; the change is below the file's precision.
    u, _, vt = np.linalg.svd(R)
    try:
        return Rigid3(R=u @ vt, t=np.asarray(t, dtype=float).reshape(3))
    except (GeometryError, ValueError) as exc:
        raise RecordingError(path, field, str(exc)) from None


def _numbers(value: Any, path: Path, field: str, count: int | None = None) -> np.ndarray:
    if isinstance(value, dict) and "data" in value:  # ROS / EuRoC {rows, cols, data}
        value = value["data"]
    if isinstance(value, np.ndarray):
        value = value.reshape(-1).tolist()
    if not isinstance(value, (list, tuple)) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise RecordingError(path, field, f"must be a list of numbers, got {shown(value)}")
    if count is not None and len(value) != count:
        raise RecordingError(path, field, f"expected {count} numbers, got {len(value)}")
    out = np.array(value, dtype=float)
    if not np.all(np.isfinite(out)):
        raise RecordingError(path, field, "holds a NaN or infinite value")
    return out


def _size(value: Any, path: Path, field: str) -> tuple[int, int]:
    v = _numbers(value, path, field, 2)
    if np.any(v != np.round(v)) or np.any(v <= 0):
        raise RecordingError(
            path, field, f"must be two positive integers [w, h], got {shown(value)}"
        )
    return int(v[0]), int(v[1])


# --------------------------------------------------------------------------------------------
# Kalibr camchain and EuRoC sensor.yaml
# --------------------------------------------------------------------------------------------


def kalibr_camera(raw: Any, path: Path, name: str, coeff_key: str) -> SourceCamera:
    """One Kalibr-style camera block (Kalibr's camchain ``camN``, EuRoC's sensor.yaml):
    ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model``,
    ``distortion_coeffs`` (Kalibr) / ``distortion_coefficients`` (EuRoC), ``resolution``."""
    prefix = f"{name}." if name else ""
    if not isinstance(raw, dict):
        raise RecordingError(path, name or None, "missing or not a mapping")
    model = raw.get("camera_model", "pinhole")
    if model != "pinhole":
        raise RecordingError(
            path,
            f"{prefix}camera_model",
            f"{model!r} is not supported; satpose imports pinhole cameras "
            "(with radtan or equidistant distortion)",
        )
    fu, fv, pu, pv = _numbers(raw.get("intrinsics"), path, f"{prefix}intrinsics", 4)
    dist_name = str(raw.get("distortion_model", "radtan"))
    lens = KALIBR_MODELS.get(dist_name)
    if lens is None:
        raise RecordingError(
            path,
            f"{prefix}distortion_model",
            f"{dist_name!r} is not supported; use one of {sorted(KALIBR_MODELS)}",
        )
    coeffs = _numbers(raw.get(coeff_key, [0.0] * 4), path, f"{prefix}{coeff_key}")
    if "resolution" not in raw:
        raise RecordingError(path, f"{prefix}resolution", "required key is missing")
    size = _size(raw["resolution"], path, f"{prefix}resolution")
    return SourceCamera(
        K=np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]]),
        model=lens,
        coeffs=coeffs,
        size=size,
        path=path,
        field=name or "camera",
        size_field=f"{prefix}resolution",
    )


def read_kalibr(data: dict[str, Any], path: Path) -> SourceCalibration:
    """A Kalibr camchain (``cam0`` = left, ``cam1`` = right; more cameras are refused)."""
    cams = sorted(k for k in data if k.startswith("cam") and k[3:].isdigit())
    if cams not in (["cam0"], ["cam0", "cam1"]):
        raise RecordingError(
            path, ",".join(cams) or "cam0", "a camchain for satpose holds cam0 (and cam1)"
        )
    left = kalibr_camera(data["cam0"], path, "cam0", "distortion_coeffs")
    topics = [str(data["cam0"].get("rostopic", ""))]
    right = rfl = None
    if "cam1" in data:
        right = kalibr_camera(data["cam1"], path, "cam1", "distortion_coeffs")
        if "T_cn_cnm1" not in data["cam1"]:
            raise RecordingError(path, "cam1.T_cn_cnm1", "required key is missing")
        T = matrix4(data["cam1"]["T_cn_cnm1"], path, "cam1.T_cn_cnm1")
        rfl = rigid_from_matrix(T, path, "cam1.T_cn_cnm1")
        topics.append(str(data["cam1"].get("rostopic", "")))
    return SourceCalibration(
        left=left,
        right=right,
        right_from_left=rfl,
        path=path,
        topics=tuple(topics) if all(topics) else (),
    )


def matrix4(value: Any, path: Path, field: str) -> np.ndarray:
    """A 4x4 matrix written as 4 rows of 4 (Kalibr) or ``{rows, cols, data}`` (EuRoC)."""
    if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
        rows = [_numbers(r, path, field, 4) for r in value]
        if len(rows) != 4:
            raise RecordingError(path, field, f"expected 4 rows, got {len(rows)}")
        return np.stack(rows)
    return _numbers(value, path, field, 16).reshape(4, 4)


# --------------------------------------------------------------------------------------------
# ROS CameraInfo
# --------------------------------------------------------------------------------------------


def camera_info(
    *,
    width: int,
    height: int,
    distortion_model: str,
    D: Any,
    K: Any,
    path: Path,
    field: str,
    binning: tuple[int, int] = (0, 0),
    roi_size: tuple[int, int] = (0, 0),
) -> SourceCamera:
    """A ROS CameraInfo's camera (message or YAML file), ``field`` naming it in messages."""
    lens = ROS_MODELS.get(distortion_model)
    if lens is None:
        raise RecordingError(
            path,
            f"{field}.distortion_model",
            f"{distortion_model!r} is not supported; use one of {sorted(ROS_MODELS)}",
        )
    if any(b > 1 for b in binning) or any(r > 0 for r in roi_size):
        raise RecordingError(
            path,
            f"{field}.binning/roi",
            "binned or region-of-interest camera infos are not supported",
        )
    Km = _numbers(K, path, f"{field}.K", 9).reshape(3, 3)
    if width <= 0 or height <= 0:
        raise RecordingError(path, f"{field}.width/height", f"{width}x{height} is not a size")
    return SourceCamera(
        K=Km,
        model=lens,
        coeffs=_numbers(D, path, f"{field}.D"),
        size=(int(width), int(height)),
        path=path,
        field=field,
        size_field=f"{field}.width/height",
    )


def stereo_from_camera_infos(
    R_left: Any, P_left: Any, R_right: Any, P_right: Any, path: Path, field: str
) -> Rigid3 | None:
    """``right_from_left`` from the rectification rotations R and projections P of a ROS
    stereo pair, or None when they carry no baseline (two unrelated monocular infos).

    ROS: ``R`` rotates camera coordinates into the rectified frame; ``P = K' [I | t]`` projects
    rectified coordinates, ``t = K'^-1 P[:, 3]`` (for the right camera ``(-baseline, 0, 0)``
    with ``P[0, 3] = -fx' baseline``). With ``x_rect_r = x_rect_l + (t_r - t_l)``:
    ``right_from_left = (R_r^T, 0) @ (I, t_r - t_l) @ (R_l, 0)``.
    """
    Rl = _numbers(R_left, path, f"{field}.R (left)", 9).reshape(3, 3)
    Rr = _numbers(R_right, path, f"{field}.R (right)", 9).reshape(3, 3)
    Pl = _numbers(P_left, path, f"{field}.P (left)", 12).reshape(3, 4)
    Pr = _numbers(P_right, path, f"{field}.P (right)", 12).reshape(3, 4)
    if not (np.any(Rl) and np.any(Rr) and np.any(Pl) and np.any(Pr)):
        return None
    tl = np.linalg.solve(Pl[:, :3], Pl[:, 3])
    tr = np.linalg.solve(Pr[:, :3], Pr[:, 3])
    if np.linalg.norm(tr - tl) == 0.0:
        return None
    for R, name in ((Rl, "left"), (Rr, "right")):
        if not is_rotation(R, tol=1e-6):
            raise RecordingError(path, f"{field}.R ({name})", "is not a rotation matrix")
    return _rt(Rr.T @ Rl, Rr.T @ (tr - tl), path, f"{field}.R/P")


def read_ros_camera_info_yaml(data: dict[str, Any], path: Path) -> SourceCamera:
    """camera_calibration's YAML (``image_width``, ``image_height``, ``camera_matrix``,
    ``distortion_model``, ``distortion_coefficients``; ``{rows, cols, data}`` matrices)."""
    for key in ("image_width", "image_height", "camera_matrix"):
        if key not in data:
            raise RecordingError(path, key, "required key is missing")
    w, h = _size([data["image_width"], data["image_height"]], path, "image_width/image_height")
    cam = camera_info(
        width=w,
        height=h,
        distortion_model=str(data.get("distortion_model", "plumb_bob")),
        D=data.get("distortion_coefficients", [0.0] * 5),
        K=data["camera_matrix"],
        path=path,
        field="camera",
    )
    return SourceCamera(
        K=cam.K,
        model=cam.model,
        coeffs=cam.coeffs,
        size=cam.size,
        path=path,
        field="camera_matrix",
        size_field="image_width/image_height",
    )


def ros_pair_from_yaml(
    left: dict[str, Any], right: dict[str, Any], lpath: Path, rpath: Path
) -> SourceCalibration:
    """Two camera_calibration YAML files (left, right) with their R and P for the baseline."""
    lcam = read_ros_camera_info_yaml(left, lpath)
    rcam = read_ros_camera_info_yaml(right, rpath)
    for data, p in ((left, lpath), (right, rpath)):
        for key in ("rectification_matrix", "projection_matrix"):
            if key not in data:
                raise RecordingError(p, key, "required for a stereo pair (the baseline)")
    rfl = stereo_from_camera_infos(
        left["rectification_matrix"],
        left["projection_matrix"],
        right["rectification_matrix"],
        right["projection_matrix"],
        rpath,
        "projection_matrix",
    )
    if rfl is None:
        raise RecordingError(
            rpath, "projection_matrix", "carries no baseline (P[:, 3] equal to the left one's)"
        )
    return SourceCalibration(left=lcam, right=rcam, right_from_left=rfl, path=lpath)


# --------------------------------------------------------------------------------------------
# OpenCV FileStorage
# --------------------------------------------------------------------------------------------

_K_KEYS = ("camera_matrix", "cameraMatrix", "K")
_D_KEYS = ("distortion_coefficients", "distCoeffs", "D")


def _fs_node(fs: cv2.FileStorage, keys: tuple[str, ...]) -> tuple[str, np.ndarray] | None:
    for key in keys:
        node = fs.getNode(key)
        if not node.empty():
            m = node.mat()
            if m is None and node.isSeq():
                m = np.array([node.at(i).real() for i in range(node.size())])
            if m is None:
                continue
            return key, np.asarray(m, dtype=float)
    return None


def read_opencv(path: Path) -> SourceCalibration:
    """An OpenCV FileStorage file (YAML ``%YAML:1.0`` or XML) written by ``cv2.FileStorage``
    (keys: the module docstring)."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise RecordingError(
            path, None, f"not a readable OpenCV FileStorage file ({exc.err})"
        ) from None
    if not fs.isOpened():
        raise RecordingError(path, None, "not a readable OpenCV FileStorage file")
    try:
        size: tuple[int, int] | None = None
        size_field = "image_width/image_height"
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        if not w.empty() and not h.empty():
            size = _size([w.real(), h.real()], path, size_field)
        else:
            for key in ("image_size", "imageSize"):
                got = _fs_node(fs, (key,))
                if got is not None:
                    size, size_field = _size(got[1].reshape(-1).tolist(), path, key), key
                    break
        model_node = fs.getNode("distortion_model")
        fisheye = not model_node.empty() and model_node.string() in ("equidistant", "fisheye")

        def camera(k_keys: tuple[str, ...], d_keys: tuple[str, ...]) -> SourceCamera | None:
            k = _fs_node(fs, k_keys)
            if k is None:
                return None
            d = _fs_node(fs, d_keys)
            coeffs = np.zeros(5) if d is None else d[1].reshape(-1)
            if fisheye:
                lens: LensModel = "equidistant"
            else:
                lens = "radtan" if coeffs.size <= 5 else "rational"
            if k[1].size != 9:
                raise RecordingError(path, k[0], f"expected a 3x3 matrix, got {k[1].shape}")
            return SourceCamera(
                K=k[1].reshape(3, 3),
                model=lens,
                coeffs=coeffs,
                size=size,
                path=path,
                field=k[0],
                size_field=size_field,
            )

        left = camera(("K1", "M1"), ("D1",))
        if left is not None:
            right = camera(("K2", "M2"), ("D2",))
            if right is None:
                raise RecordingError(path, "K2", "a stereo file (K1) needs K2 too")
            R, T = _fs_node(fs, ("R",)), _fs_node(fs, ("T",))
            if R is None or T is None:
                raise RecordingError(path, "R,T", "a stereo file needs stereoCalibrate's R and T")
            if R[1].size == 3:  # a rotation vector (cv2.Rodrigues form)
                R = ("R", cv2.Rodrigues(R[1].reshape(3))[0])
            rfl = _rt(R[1].reshape(3, 3), T[1].reshape(-1), path, "R,T")
            return SourceCalibration(left=left, right=right, right_from_left=rfl, path=path)
        mono = camera(_K_KEYS, _D_KEYS)
        if mono is None:
            raise RecordingError(
                path,
                "camera_matrix",
                "no camera: expected camera_matrix + distortion_coefficients, or K1 D1 K2 D2 R T",
            )
        return SourceCalibration(left=mono, path=path)
    finally:
        fs.release()


# --------------------------------------------------------------------------------------------
# Any file
# --------------------------------------------------------------------------------------------


def _satpose_calib(path: Path) -> SourceCalibration:
    from satpose.datasets.sequence import load_calibration

    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    kind = "stereo" if isinstance(data["cameras"], dict) and "right" in data["cameras"] else "mono"
    calib = load_calibration(path, kind)

    def cam(c: Any, name: str) -> SourceCamera:
        return SourceCamera(
            K=c.K,
            model="radtan",
            coeffs=c.dist,
            size=c.size,
            path=path,
            field=f"cameras.{name}",
            size_field=f"cameras.{name}.width/height",
        )

    return SourceCalibration(
        left=cam(calib.left, "left"),
        right=cam(calib.right, "right") if calib.right is not None else None,
        right_from_left=calib.right_from_left,
        path=path,
    )


def _load_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise RecordingError(path, None, f"not valid YAML: {yaml_problem(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(path, None, f"cannot read ({exc})") from None


def _is_filestorage(path: Path) -> bool:
    if path.suffix.lower() in (".xml", ".gz"):
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError as exc:
        raise RecordingError(path, None, f"cannot read ({exc.strerror or exc})") from None
    # OpenCV 4 heads its YAML with "%YAML:1.0", OpenCV 5 with "%YAML 1.2"; both tag matrices.
    return head.startswith(b"%YAML:") or b"!!opencv-" in head


def read_calibration_file(path: Path, right: Path | None = None) -> SourceCalibration:
    """Read a calibration file of any supported kind, told apart by content: OpenCV
    FileStorage (``%YAML:1.0`` header, ``!!opencv-matrix`` tags, or .xml), Kalibr camchain
    (``cam0``), satpose calib.yaml (``cameras``), ROS camera_calibration YAML
    (``image_width`` + ``camera_matrix``). ``right``: a second ROS camera-info file for the
    right camera of a stereo pair."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(path, None, "calibration file does not exist")
    if right is not None:
        left_data, right_data = _load_yaml(path), _load_yaml(Path(right))
        if not (isinstance(left_data, dict) and isinstance(right_data, dict)):
            raise RecordingError(path, None, "two calibration files must be ROS camera-info YAML")
        return ros_pair_from_yaml(left_data, right_data, path, Path(right))
    if _is_filestorage(path):
        return read_opencv(path)
    data = _load_yaml(path)
    if not isinstance(data, dict):
        raise RecordingError(path, None, "must hold a YAML mapping at the top level")
    if "cam0" in data:
        return read_kalibr(data, path)
    if "cameras" in data:
        return _satpose_calib(path)
    if "image_width" in data and "camera_matrix" in data:
        return SourceCalibration(left=read_ros_camera_info_yaml(data, path), path=path)
    raise RecordingError(
        path,
        None,
        "unknown calibration format: expected a Kalibr camchain (cam0), an OpenCV "
        "FileStorage file (%YAML:1.0 or .xml), a ROS camera-info YAML (image_width, "
        "camera_matrix) or a satpose calib.yaml (cameras)",
    )
