"""Point sampling for the sub-pixel edge search."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from satpose.frontend.edges import EdgeSearchConfig, edges_along_normals, sample_image, smoothed


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


@pytest.mark.parametrize("blur", [0.5, 0.8])
def test_dark_band_moments_undo_the_pull_of_a_thin_band(blur: float) -> None:
    """A step (0.6 inside, 0.5 outside) followed by a black band 0.5-1.0 px wide, blurred:
    the step fit lands up to the blur inside the edge (measured -0.24 to -0.74 px); the
    moment locator (``dark_band``) removes most of that pull (measured: within 0.04-0.08 px
    at blur 0.5, 0.10-0.20 at 0.8; at larger blur the -3.0..3.5 px window cuts the blurred
    band's tails). Without a band it changes nothing."""
    from scipy.special import erf

    rng = np.random.default_rng(7)
    xx = np.mgrid[0:120, 0:120][1].astype(float)
    u = 60.3

    def step(x0: float) -> np.ndarray:
        return 0.5 * (1 + erf((xx - x0) / (blur * np.sqrt(2))))

    pts = np.c_[np.full(60, 59.5), np.linspace(30, 90, 60)]
    nrm = np.tile([1.0, 0.0], (60, 1))
    for width in (0.0, 0.5, 1.0):
        img = 0.6 - 0.6 * step(u) + 0.5 * step(u + width) + rng.normal(0, 0.003, xx.shape)
        out = {}
        for band in (False, True):
            cfg = EdgeSearchConfig(
                smooth_sigma_px=0.6,
                step_px=0.25,
                locate="model",
                model_window_px=(-2.0, 0.5),
                dark_band=band,
            )
            e, _ = edges_along_normals(smoothed(img, cfg), pts, nrm, +1, 3.0, cfg, raw=img)
            out[band] = float(np.nanmean(e[:, 0])) - u
        if width == 0.0:
            assert out[True] == out[False]  # no dip: untouched
        else:
            assert out[False] < -0.2  # the pull is real
            assert abs(out[True]) < 0.35 * abs(out[False]) and abs(out[True]) < 0.25, (width, out)
