"""Point sampling for the sub-pixel edge search."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from satpose.frontend.edges import sample_image


@pytest.mark.parametrize("method", ["linear", "cubic"])
def test_sample_image_reproduces_a_plane_and_opencv_on_its_grid(method: str) -> None:
    """Bilinear reproduces a linear image, both kernels a constant one (1e-6 relative; Keys
    with a = -0.75 reproduces constants, not slopes); at positions on
    OpenCV's 1/32 px grid (where 4.x and 5.x remap agree) they equal remap with the same
    kernel and replicated border to float32 rounding (1e-6)."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    plane = 0.2 + 0.01 * xx - 0.007 * yy
    x = rng.uniform(2, 46, 300)
    y = rng.uniform(2, 36, 300)
    if method == "linear":
        got = sample_image(plane, x, y, method).astype(np.float64)
        np.testing.assert_allclose(got, 0.2 + 0.01 * x - 0.007 * y, rtol=1e-6)
    flat = sample_image(np.full((40, 50), 0.3), x, y, method)
    np.testing.assert_allclose(flat, 0.3, rtol=1e-6)
    img = rng.random((40, 50)).astype(np.float32)
    gx = (np.round(rng.uniform(-3, 53, (200, 3)) * 32) / 32).astype(np.float32)
    gy = (np.round(rng.uniform(-3, 43, (200, 3)) * 32) / 32).astype(np.float32)
    flag = cv2.INTER_LINEAR if method == "linear" else cv2.INTER_CUBIC
    ref = cv2.remap(img, gx, gy, flag, borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(sample_image(img, gx, gy, method), ref, atol=1e-6)
