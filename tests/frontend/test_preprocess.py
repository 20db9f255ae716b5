"""Undistortion: the same pixels whatever the OpenCV version."""

from __future__ import annotations

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.frontend.preprocess import Undistorter


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
