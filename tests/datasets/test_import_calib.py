"""Calibration readers: Kalibr camchain, OpenCV FileStorage, ROS camera infos; each written
here from a known calibration and read back; lens models format v1 cannot express are
resampled correctly; a size disagreement names the file and field."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.importers import RecordingError, read_calibration_file
from satpose.datasets.importers.calib import stereo_from_camera_infos
from satpose.datasets.importers.common import SourceCamera
from satpose.datasets.importers.writers import rectification
from satpose.datasets.sequence import Calibration, calibration_to_yaml

TIGHT = 1e-12  # noise-free: only float rounding separates what was written from what is read


def stereo_calibration() -> Calibration:
    K0 = np.array([[812.5, 0.0, 511.25], [0.0, 811.0, 383.75], [0.0, 0.0, 1.0]])
    K1 = np.array([[808.0, 0.0, 515.5], [0.0, 809.5, 380.0], [0.0, 0.0, 1.0]])
    left = PinholeCamera(width=1024, height=768, K=K0, dist=[-0.12, 0.05, 1e-4, -2e-4, 0.0])
    right = PinholeCamera(width=1024, height=768, K=K1, dist=[-0.11, 0.04, -3e-4, 1e-4, 0.0])
    rfl = Rigid3.from_rotvec([0.002, -0.013, 0.004], [-0.30, 0.002, -0.001])
    return Calibration(left=left, right=right, right_from_left=rfl)


def resolved(path: Path, right: Path | None = None) -> Calibration:
    """Read a file and turn it into format v1's calibration at the stated size."""
    src = read_calibration_file(path, right)
    cams = [src.left] + ([src.right] if src.right is not None else [])
    pins = [c.with_size(c.size or (1024, 768)).pinhole() for c in cams]
    if len(pins) == 1:
        return Calibration(left=pins[0])
    return Calibration(left=pins[0], right=pins[1], right_from_left=src.right_from_left)


def assert_same(a: Calibration, b: Calibration, tol: float = TIGHT) -> None:
    for name in ("left", "right") if a.is_stereo else ("left",):
        ca, cb = a.camera(name), b.camera(name)  # type: ignore[arg-type]
        assert ca.size == cb.size
        np.testing.assert_allclose(ca.K, cb.K, rtol=0, atol=tol)
        np.testing.assert_allclose(ca.dist, cb.dist, rtol=0, atol=tol)
    if a.is_stereo:
        assert a.right_from_left is not None and b.right_from_left is not None
        np.testing.assert_allclose(
            a.right_from_left.matrix(), b.right_from_left.matrix(), rtol=0, atol=tol
        )


def camchain(calib: Calibration) -> dict:
    """A Kalibr camchain written by hand from calib.yaml's numbers (radtan has 4 coefficients;
    this calibration's k3 is 0)."""
    out = {}
    for k, name in enumerate(("left", "right")):
        c = calib.camera(name)  # type: ignore[arg-type]
        out[f"cam{k}"] = {
            "camera_model": "pinhole",
            "intrinsics": [c.fx, c.fy, c.cx, c.cy],
            "distortion_model": "radtan",
            "distortion_coeffs": [float(v) for v in c.dist[:4]],
            "resolution": [c.width, c.height],
            "rostopic": f"/cam{k}/image_raw",
        }
    assert calib.right_from_left is not None
    out["cam1"]["T_cn_cnm1"] = calib.right_from_left.matrix().tolist()
    return out


def test_kalibr_camchain_reproduces_calib_yaml(tmp_path: Path) -> None:
    calib = stereo_calibration()
    p = tmp_path / "camchain.yaml"
    p.write_text(yaml.safe_dump(camchain(calib)))
    assert_same(resolved(p), calib)
    assert read_calibration_file(p).topics == ("/cam0/image_raw", "/cam1/image_raw")


def test_satpose_calib_yaml_is_read_as_it_is(tmp_path: Path) -> None:
    calib = stereo_calibration()
    p = tmp_path / "calib.yaml"
    p.write_text(yaml.safe_dump(calibration_to_yaml(calib)))
    # calib.yaml stores the quaternion with 17 digits: the rotation comes back within 1e-15.
    assert_same(resolved(p), calib)


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_opencv_stereo_filestorage(tmp_path: Path, suffix: str) -> None:
    calib = stereo_calibration()
    assert calib.right is not None and calib.right_from_left is not None
    p = tmp_path / f"stereo{suffix}"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1024)
    fs.write("image_height", 768)
    fs.write("K1", calib.left.K)
    fs.write("D1", calib.left.dist.reshape(1, 5))
    fs.write("K2", calib.right.K)
    fs.write("D2", calib.right.dist.reshape(1, 5))
    fs.write("R", calib.right_from_left.R)
    fs.write("T", calib.right_from_left.t.reshape(3, 1))
    fs.release()
    assert_same(resolved(p), calib)


def test_opencv_mono_filestorage_without_size_takes_it_from_the_images(tmp_path: Path) -> None:
    calib = stereo_calibration()
    p = tmp_path / "camera.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", calib.left.K)
    fs.write("distortion_coefficients", calib.left.dist.reshape(5, 1))
    fs.release()
    src = read_calibration_file(p)
    assert src.left.size is None and src.right is None
    cam = src.left.with_size((1024, 768)).pinhole()
    np.testing.assert_allclose(cam.K, calib.left.K, rtol=0, atol=TIGHT)
    np.testing.assert_allclose(cam.dist, calib.left.dist, rtol=0, atol=TIGHT)


def test_ros_camera_info_pair_recovers_the_extrinsic_from_R_and_P(tmp_path: Path) -> None:
    calib = stereo_calibration()
    assert calib.right is not None and calib.right_from_left is not None
    R1, R2, P1, P2 = rectification(calib.left, calib.right, calib.right_from_left)
    paths = []
    for name, cam, R, P in (("left", calib.left, R1, P1), ("right", calib.right, R2, P2)):
        data = {
            "image_width": cam.width,
            "image_height": cam.height,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.reshape(-1).tolist()},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": cam.dist.tolist()},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": R.reshape(-1).tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": P.reshape(-1).tolist()},
        }
        paths.append(tmp_path / f"{name}.yaml")
        paths[-1].write_text(yaml.safe_dump(data))
    # stereoRectify's rotations are exact to float rounding; the baseline is |T| = 0.3 m.
    assert_same(resolved(paths[0], paths[1]), calib, tol=1e-12)


def test_camera_infos_without_a_baseline_give_no_extrinsic() -> None:
    P = np.c_[np.eye(3) * 800, np.zeros(3)]
    P[2, 2] = 1
    assert stereo_from_camera_infos(np.eye(3), P, np.eye(3), P, Path("x.bag"), "info") is None


def test_rational_model_with_zero_high_terms_is_radtan() -> None:
    cam = SourceCamera(
        K=np.diag([800.0, 800.0, 1.0]),
        model="rational",
        coeffs=[-0.1, 0.02, 0.001, 0.0, 0.003, 0.0, 0.0, 0.0],
        size=(64, 48),
        path=Path("info"),
        field="x",
    )
    assert not cam.needs_resampling and cam.undistort_maps() is None
    np.testing.assert_array_equal(cam.pinhole().dist, [-0.1, 0.02, 0.001, 0.0, 0.003])


def _dot_image(size: tuple[int, int], center: np.ndarray) -> np.ndarray:
    """A Gaussian blob (sigma 1.5 px) at a sub-pixel position, 16-bit."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    g = np.exp(-((xx - center[0]) ** 2 + (yy - center[1]) ** 2) / (2 * 1.5**2))
    return np.round(g * 60000).astype(np.uint16)


def _centroid(img: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    w = img.astype(float)
    return np.array([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])


@pytest.mark.parametrize("model", ["equidistant", "rational"])
def test_resampled_lens_puts_points_where_the_pinhole_projects_them(model: str) -> None:
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    coeffs = (
        np.array([0.08, -0.02, 0.01, -0.003])
        if model == "equidistant"
        else np.array([-0.2, 0.05, 0.0, 0.0, 0.0, 0.1, 0.01, 0.0])
    )
    cam = SourceCamera(K=K, model=model, coeffs=coeffs, size=(320, 240), path=Path("c"), field="x")
    assert cam.needs_resampling
    X = np.array([[0.21, -0.13, 1.0]])
    if model == "equidistant":
        distorted = cv2.fisheye.projectPoints(
            X.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, coeffs
        )[0].reshape(2)
    else:
        distorted = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, coeffs)[0].reshape(2)
    maps = cam.undistort_maps()
    assert maps is not None
    out = cv2.remap(_dot_image((320, 240), distorted), maps[0], maps[1], cv2.INTER_LINEAR)
    pinhole = cam.pinhole()
    assert not pinhole.has_distortion
    expected = pinhole.project(X)[0]
    # The blob is resampled bilinearly; its centroid moves by far less than 0.05 px.
    np.testing.assert_allclose(_centroid(out), expected, atol=0.05)


def test_size_disagreement_names_the_file_and_field(tmp_path: Path) -> None:
    calib = stereo_calibration()
    p = tmp_path / "camchain.yaml"
    p.write_text(yaml.safe_dump(camchain(calib)))
    src = read_calibration_file(p)
    with pytest.raises(RecordingError) as err:
        src.left.with_size((640, 480))
    assert str(err.value).startswith(f"{p}: cam0.resolution: ")
    assert "1024x768" in str(err.value) and "640x480" in str(err.value)


@pytest.mark.parametrize(
    ("content", "field"),
    [
        ({"cam0": {"camera_model": "omni", "intrinsics": [1, 1, 1, 1]}}, "cam0.camera_model"),
        (
            {
                "cam0": {
                    "intrinsics": [1, 1, 1, 1],
                    "distortion_model": "fov",
                    "resolution": [4, 4],
                }
            },
            "cam0.distortion_model",
        ),
        ({"cam0": {"intrinsics": [1, 1, 1], "resolution": [4, 4]}}, "cam0.intrinsics"),
        ({"cam0": {"intrinsics": [1, 1, 1, 1]}}, "cam0.resolution"),
        ({"something": 1}, None),
    ],
)
def test_bad_calibration_files_name_the_field(tmp_path: Path, content: dict, field: str) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(content))
    with pytest.raises(RecordingError) as err:
        read_calibration_file(p)
    assert str(err.value).startswith(f"{p}: {field}: " if field else f"{p}: ")
    assert "\n" not in str(err.value)
