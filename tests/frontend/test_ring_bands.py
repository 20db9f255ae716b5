"""Ring seeds from thin bands (satpose.frontend.ring_bands): a dark rim on a busy panel.

The image is drawn with OpenCV (4x supersampled, averaged, blurred): the same on every CPU.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.frontend.ellipses import EllipseDetectorConfig, detect_ellipses
from satpose.frontend.measurements import Camera
from satpose.frontend.preprocess import Undistorter
from satpose.frontend.ring import RingConfig, RingTracker
from satpose.frontend.ring_bands import BandSeedConfig, band_seeds

W, H, S = 320, 240, 4
CENTRE, A, B, THETA_DEG, BAND_PX = (160.3, 121.7), 62.0, 48.0, 20.0, 4.0


def _ellipse_poly(a: float, b: float) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    x, y = a * np.cos(t), b * np.sin(t)
    c, s = math.cos(math.radians(THETA_DEG)), math.sin(math.radians(THETA_DEG))
    p = np.c_[CENTRE[0] + c * x - s * y, CENTRE[1] + s * x + c * y]
    return np.round((p + 0.5) * S * 16 - 8).astype(np.int32)


def _busy_panel_with_dark_ring() -> np.ndarray:
    """A panel of random bright blocks (foil facets, 3-9 px) carrying a 4 px dark band whose
    outer edge is the ellipse (CENTRE, A, B, THETA_DEG); black space around."""
    rng = np.random.default_rng(5)
    panel = np.zeros((H * S, W * S), np.float32)
    for _ in range(2500):
        x, y = rng.integers(40 * S, 280 * S), rng.integers(20 * S, 220 * S)
        w, h = rng.integers(3 * S, 9 * S), rng.integers(2 * S, 6 * S)
        panel[y : y + h, x : x + w] = rng.uniform(0.3, 1.0)
    inside = np.zeros_like(panel)
    inside[20 * S : 220 * S, 40 * S : 280 * S] = 1.0
    img = np.where(inside > 0, np.maximum(panel, 0.25), 0.05).astype(np.float32)
    band = np.zeros_like(img)
    cv2.fillPoly(band, [_ellipse_poly(A, B)], 1.0, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(band, [_ellipse_poly(A - BAND_PX, B - BAND_PX)], 0.0, lineType=cv2.LINE_8, shift=4)
    img = np.where(band > 0, 0.08, img)
    small = cv2.GaussianBlur(img.reshape(H, S, W, S).mean(axis=(1, 3)), (0, 0), 0.7)
    return np.clip(np.rint(small * 255), 0, 255).astype(np.uint8)


def _detector(gray8: np.ndarray, roi: tuple[int, int, int, int] | None = None) -> list:  # type: ignore[type-arg]
    return detect_ellipses(gray8, EllipseDetectorConfig(), roi)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return _busy_panel_with_dark_ring()


def test_arc_detector_alone_misses_the_band(image: np.ndarray) -> None:
    """The premise: the texture's edges cut the band's arcs, no ring-sized ellipse is found."""
    assert not [c for c in _detector(image) if c.ellipse.a > 30]


def test_band_seeds_find_the_band(image: np.ndarray) -> None:
    seeds = band_seeds(image, _detector, 8.0, 4.0, BandSeedConfig())
    # the band's outer or inner edge (4 px apart): within a band's width of the truth
    assert any(
        math.hypot(e.cx - CENTRE[0], e.cy - CENTRE[1]) < 1.5
        and A - BAND_PX - 1 < e.a < A + 1
        and B - BAND_PX - 1 < e.b < B + 1
        for e in seeds
    ), seeds


def test_acquisition_falls_back_to_band_seeds(image: np.ndarray) -> None:
    """With bands on, the tracker's candidates include the band's outer edge, refined on
    sub-pixel edges (texture beside it: 1 px on the centre, 2 % on the axes); with bands
    off there is no candidate at all."""
    camera = PinholeCamera(
        width=W, height=H, K=np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    )
    prepared = Undistorter(camera)(image)
    found = RingTracker(Camera.LEFT, _detector).acquire(prepared)
    assert any(
        np.hypot(*(o.center_px - np.array(CENTRE))) < 1.0
        and abs(o.axes_px[0] - A) < 0.02 * A
        and abs(o.axes_px[1] - B) < 0.02 * B
        for o, _ in found
    ), [(o.center_px, o.axes_px) for o, _ in found]
    off = replace(RingConfig(), bands=replace(RingConfig().bands, enabled=False))
    assert RingTracker(Camera.LEFT, _detector, off).acquire(prepared) == []


def test_bad_band_config_is_refused() -> None:
    with pytest.raises(ValueError, match="disc_radii_px"):
        BandSeedConfig(disc_radii_px=())
