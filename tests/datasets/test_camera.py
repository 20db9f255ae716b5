"""Pinhole-radtan camera: agrees with OpenCV, undistortion inverts distortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import CameraError, PinholeCamera
from satpose.datasets.scenarios import RigConfig


def _camera() -> PinholeCamera:
    return RigConfig().calibration().left


def test_project_matches_opencv() -> None:
    cam = _camera()
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1.5, 1.5, (200, 2)), rng.uniform(3, 8, 200)]
    ours = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-9)


def test_undistort_inverts_distort_over_the_image() -> None:
    cam = _camera()
    vv, uu = np.mgrid[0 : cam.height : 7, 0 : cam.width : 7]
    px = np.c_[uu.ravel(), vv.ravel()].astype(float)
    np.testing.assert_allclose(cam.normalized_to_pixels(cam.undistort_points(px)), px, atol=1e-8)


def test_distortion_jacobian_matches_finite_differences() -> None:
    cam = _camera()
    xy = np.random.default_rng(2).uniform(-0.35, 0.35, (20, 2))
    J = cam.distortion_jacobian(xy)
    h = 1e-6
    for k in range(2):
        d = np.zeros(2)
        d[k] = h
        num = (cam.distort_normalized(xy + d) - cam.distort_normalized(xy - d)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, atol=1e-8)


def test_points_behind_the_camera_are_nan() -> None:
    assert np.all(np.isnan(_camera().project(np.array([[0.0, 0.0, -1.0]]))))


def test_scaled_keeps_pixel_centre_convention() -> None:
    cam = PinholeCamera(
        width=1024, height=768, K=np.array([[1500.0, 0, 511.5], [0, 1500, 383.5], [0, 0, 1]])
    )
    small = cam.scaled(256, 192)
    assert (small.cx, small.cy, small.fx) == (127.5, 95.5, 375.0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"K": np.eye(3) * [1, 1, 2]},
        {"K": np.array([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]])},
        {"dist": [0.1, 0.2, 0.3]},
        {"model": "fisheye"},
        {"width": 0},
    ],
)
def test_invalid_camera_is_rejected(kwargs) -> None:  # type: ignore[no-untyped-def]
    base = dict(width=10, height=10, K=np.array([[10.0, 0, 5], [0, 10, 5], [0, 0, 1]]))
    with pytest.raises(CameraError):
        PinholeCamera(**{**base, **kwargs})
