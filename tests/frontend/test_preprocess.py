"""Undistortion: the same pixels whatever the OpenCV version."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.frontend.preprocess import PreprocessConfig, Undistorter


def test_undistortion_is_bilinear_at_one_32nd_pixel() -> None:
    """Oracle: numpy bilinear interpolation at the map positions rounded to 1/32 px (the
    fixed-point maps' resolution), float64. OpenCV 4.x remap with float maps computes this
    too, 5.x interpolates at the exact positions (up to 2/255 apart on a rendered frame);
    the fixed-point maps make both agree with the oracle to float32 rounding (1e-6)."""
    w, h = 160, 120
    K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
    cam = PinholeCamera(width=w, height=h, K=K, dist=np.array([-0.3, 0.1, 1e-3, -1e-3, 0.0]))
    image = np.random.default_rng(5).integers(0, 256, (h, w), dtype=np.uint8)
    got = Undistorter(cam)(image).gray
    mx, my = cv2.initUndistortRectifyMap(K, cam.dist, None, K, (w, h), cv2.CV_32FC1)
    qx = np.round(mx.astype(np.float64) * 32) / 32
    qy = np.round(my.astype(np.float64) * 32) / 32
    x0, y0 = np.floor(qx).astype(int), np.floor(qy).astype(int)
    fx, fy = qx - x0, qy - y0
    src = image.astype(np.float64) / 255.0

    def at(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        return np.where(inside, src[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)], 0.0)

    want = (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) + fy * (
        (1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)
    )
    inner = (slice(2, -2), slice(2, -2))  # the constant border's taps are OpenCV's business
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-6)


def _cubic_weights(t: np.ndarray) -> list[np.ndarray]:
    """OpenCV's bicubic (Keys, A = -0.75) weights of the taps at -1, 0, 1, 2 for the
    fraction ``t``."""
    A = -0.75
    w0 = ((A * (t + 1) - 5 * A) * (t + 1) + 8 * A) * (t + 1) - 4 * A
    w1 = ((A + 2) * t - (A + 3)) * t * t + 1
    w2 = ((A + 2) * (1 - t) - (A + 3)) * (1 - t) * (1 - t) + 1
    return [w0, w1, w2, 1 - w0 - w1 - w2]


def test_cubic_undistortion_is_keys_cubic_at_one_32nd_pixel() -> None:
    """``interpolation: cubic``. Oracle: numpy Keys bicubic (A = -0.75, OpenCV's) at the map
    positions rounded to 1/32 px, float64; tolerance float32 rounding (1e-5)."""
    w, h = 160, 120
    K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
    cam = PinholeCamera(width=w, height=h, K=K, dist=np.array([-0.3, 0.1, 1e-3, -1e-3, 0.0]))
    image = np.random.default_rng(6).integers(0, 256, (h, w), dtype=np.uint8)
    got = Undistorter(cam, PreprocessConfig(interpolation="cubic"))(image).gray
    mx, my = cv2.initUndistortRectifyMap(K, cam.dist, None, K, (w, h), cv2.CV_32FC1)
    qx = np.round(mx.astype(np.float64) * 32) / 32
    qy = np.round(my.astype(np.float64) * 32) / 32
    x0, y0 = np.floor(qx).astype(int), np.floor(qy).astype(int)
    wx, wy = _cubic_weights(qx - x0), _cubic_weights(qy - y0)
    src = image.astype(np.float64) / 255.0
    want = np.zeros_like(qx)
    inside = np.ones(qx.shape, bool)
    for j in range(4):
        for i in range(4):
            x, y = x0 + i - 1, y0 + j - 1
            inside &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
            want += wy[j] * wx[i] * src[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)]
    # pixels whose taps all lie in the image (the border is OpenCV's business)
    np.testing.assert_allclose(got[inside], want[inside], atol=1e-5)
    assert inside.mean() > 0.8


@pytest.mark.parametrize("interpolation", ["linear", "cubic", "lanczos4"])
def test_undistorted_crop_equals_the_full_image_for_every_interpolation(
    interpolation: str,
) -> None:
    """`Undistorter.crop` reads enough source pixels for the interpolation's taps: the crop
    is exactly the full undistorted image's pixels in the box."""
    w, h = 160, 120
    K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
    cam = PinholeCamera(width=w, height=h, K=K, dist=np.array([-0.3, 0.1, 1e-3, -1e-3, 0.0]))
    image = np.random.default_rng(7).integers(0, 256, (h, w), dtype=np.uint8)
    und = Undistorter(cam, PreprocessConfig(interpolation=interpolation))
    full = und(image)
    for box in [(50, 40, 110, 90), (0, 0, 30, 20), (130, 100, 160, 120)]:
        crop = und.crop(image, box)
        np.testing.assert_array_equal(crop.gray, full.gray[box[1] : box[3], box[0] : box[2]])


def test_an_unknown_interpolation_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"preprocess\.interpolation"):
        PreprocessConfig(interpolation="nearest-ish")
