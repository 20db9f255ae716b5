"""The ring acquired on colour contrast when grey shows none
(`StereoRingConfig.colour_contrast`, `Undistorter.colour_contrast`).

Drawn BGR images (OpenCV, 4x supersampled, averaged, blurred; seeded noise): the same on
every CPU. A blue anodised rim face on a grey panel of the same luminance is the case of
tuning seed 32 of the random family (docs/frontend.md, "A rim of the panel's brightness").
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
from satpose.frontend.preprocess import Undistorter, dominant_colour
from satpose.frontend.rim import rim_samples
from satpose.frontend.stereo import Circle3D

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIGHT_FROM_LEFT = Rigid3(R=np.eye(3), t=np.array([-0.3, 0.0, 0.0]))
S = 4  # supersampling
PANEL_BGR = (110.0, 110.0, 110.0)
RIM_BGR = (200.0, 118.0, 60.0)  # luminance 0.114 B + 0.587 G + 0.299 R = 110.0: the panel's


def _rim() -> Circle3D:
    """The outer front rim: 0.30 m, 4 m away, tilted 25 deg about the vertical."""
    t = math.radians(25.0)
    normal = -np.array([math.sin(t), 0.0, math.cos(t)])
    return Circle3D(
        center=np.array([0.1, 0.05, 4.0]), normal=normal, radius=0.30, covariance=np.eye(7)
    )


def _poly(T: Rigid3, c: Circle3D) -> np.ndarray:
    P, _ = rim_samples(c, 1440)
    x = (P @ T.R.T + T.t) @ K.T
    x = x[:, :2] / x[:, 2:3]
    return np.round((x + 0.5) * S * 16 - 0.5 * 16).astype(np.int32)


def _blue_rim(T: Rigid3, seed: int) -> np.ndarray:
    """BGR uint8: a grey panel filling the view, a blue rim face 0.30 -> 0.27 m of the
    panel's luminance, the panel again inside; noise 1 grey level per channel."""
    rim = _rim()
    img = np.empty((H * S, W * S, 3), np.float32)
    img[:] = PANEL_BGR
    cv2.fillPoly(img, [_poly(T, rim)], RIM_BGR, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [_poly(T, replace(rim, radius=0.27))], PANEL_BGR, cv2.LINE_8, shift=4)
    small = img.reshape(H, S, W, S, 3).mean(axis=(1, 3))
    small = cv2.GaussianBlur(small, (0, 0), 0.6)
    small += np.random.default_rng(seed).normal(0.0, 1.0, small.shape)
    return np.clip(small + 0.5, 0, 255).astype(np.uint8)


def _calibration() -> Calibration:
    cam = PinholeCamera(width=W, height=H, K=K)
    return Calibration(left=cam, right=cam, right_from_left=RIGHT_FROM_LEFT)


def test_colour_contrast_is_the_component_off_the_dominant_colour() -> None:
    """Exact: the length of each pixel's BGR component orthogonal to the dominant colour,
    /255; a panel of the dominant colour is 0 at every brightness; None for a grey image; a
    colourless image is 'too dark' there."""
    und = Undistorter(PinholeCamera(width=W, height=H, K=K))
    img = np.full((H, W, 3), 90, np.uint8)
    img[10:20, 30:50] = (200, 118, 60)
    c = und.colour_contrast(img)
    assert c is not None
    u = dominant_colour([img])
    assert u is not None
    np.testing.assert_allclose(u, np.full(3, 1 / math.sqrt(3)), atol=1e-7)
    off = np.array([200.0, 118.0, 60.0]) - np.mean([200.0, 118.0, 60.0])
    assert c.gray[15, 40] == pytest.approx(np.linalg.norm(off) / 255, abs=1e-6)
    assert c.gray[100, 100] == pytest.approx(0.0, abs=1e-6)
    assert und.colour_contrast(np.full((H, W), 90, np.uint8)) is None
    neutral = und.colour_contrast(np.full((H, W, 3), 90, np.uint8))
    assert neutral is not None and neutral.problem == "too dark"
    # amber foil whose facets vary in brightness only, and a neutral patch on it
    gold = np.array([40.0, 140.0, 200.0])
    rng = np.random.default_rng(3)
    foil = gold * rng.uniform(0.2, 1.0, (H, W, 1))
    foil[10:20, 30:50] = 120.0
    c = und.colour_contrast(np.clip(foil + 0.5, 0, 255).astype(np.uint8))
    assert c is not None
    inside = np.ones((H, W), bool)
    inside[8:22, 28:52] = False
    assert float(np.max(c.gray[inside])) < 3 / 255  # the foil's texture: rounding only
    assert float(np.min(c.gray[12:18, 32:48])) > 60 / 255


def _follows_the_rim_on_colour(calib: Calibration, left: np.ndarray, right: np.ndarray) -> None:
    """Two frames of the pair: the rim in each (radius within 3 mm, centre within 1 cm),
    tracked on the colour contrast."""
    fe = StereoFrontend(calib)
    rim = _rim()
    for k in range(2):
        m = fe.process(k, float(k), left, right)
        assert m.ring is not None, m.failures
        assert abs(m.ring.radius_m - rim.radius) < 0.003, m.ring.radius_m
        assert float(np.linalg.norm(m.ring.center_m - rim.center)) < 0.01, m.ring.center_m
        assert fe._ring_channel == "colour"


def test_rim_of_the_panels_luminance_is_acquired_on_colour() -> None:
    """Drawn stereo pair: in grey (the images converted, or the colour pass off) no ring; on
    colour contrast the ring's radius within 3 mm and its centre within 1 cm (noise 1 grey
    level, 0.6 px blur: the band's outer edge), and the next frame follows it there."""
    left, right = _blue_rim(Rigid3.identity(), 5), _blue_rim(RIGHT_FROM_LEFT, 6)
    calib = _calibration()
    grey = [cv2.cvtColor(x, cv2.COLOR_BGR2GRAY) for x in (left, right)]
    assert StereoFrontend(calib).process(0, 0.0, *grey).ring is None
    cfg = FrontendConfig()
    off = replace(cfg, stereo_ring=replace(cfg.stereo_ring, colour_contrast=False))
    assert StereoFrontend(calib, off).process(0, 0.0, left, right).ring is None
    _follows_the_rim_on_colour(calib, left, right)


def _with_disc(img: np.ndarray, T: Rigid3, grey: float) -> np.ndarray:
    """``img`` with a neutral disc of radius 0.12 m drawn beside the rim in its plane
    (supersampled like `_blue_rim`): a closed curve that grey shows and colour does not."""
    rim = _rim()
    side = np.cross(rim.normal, [0.0, 1.0, 0.0])
    disc = replace(rim, center=rim.center + 0.55 * side / np.linalg.norm(side), radius=0.12)
    mask = np.zeros((H * S, W * S), np.float32)
    cv2.fillPoly(mask, [_poly(T, disc)], 1.0, lineType=cv2.LINE_8, shift=4)
    m = cv2.GaussianBlur(mask.reshape(H, S, W, S).mean(axis=(1, 3)), (0, 0), 0.6)[..., None]
    return np.clip(img * (1 - m) + grey * m + 0.5, 0, 255).astype(np.uint8)


def test_acquisition_takes_the_larger_ring_of_grey_and_colour() -> None:
    """A bright neutral disc (0.12 m) beside a rim of the panel's luminance: grey alone
    takes the disc for the ring; acquiring on both kinds of image takes the larger, the
    rim (radius within 3 mm, centre within 1 cm), and follows it on colour."""
    calib = _calibration()
    left = _with_disc(_blue_rim(Rigid3.identity(), 5).astype(np.float32), Rigid3.identity(), 220)
    right = _with_disc(_blue_rim(RIGHT_FROM_LEFT, 6).astype(np.float32), RIGHT_FROM_LEFT, 220)
    cfg = FrontendConfig()
    off = replace(cfg, stereo_ring=replace(cfg.stereo_ring, colour_contrast=False))
    grey = StereoFrontend(calib, off).process(0, 0.0, left, right)
    assert grey.ring is not None and abs(grey.ring.radius_m - 0.12) < 0.005, grey.ring
    _follows_the_rim_on_colour(calib, left, right)


@pytest.mark.parametrize("reset_after", [3, 4])
def test_a_stale_radius_memory_restarts(reset_after: int) -> None:
    """A remembered radius 12 % larger than the rim (a wrong first sighting): the rim is
    refused as an inner edge, with a failure that says so, until it has been seen in
    ``memory_reset_frames`` frames in a row; then it is taken (radius within 3 mm)."""
    left, right = _blue_rim(Rigid3.identity(), 5), _blue_rim(RIGHT_FROM_LEFT, 6)
    cfg = FrontendConfig()
    cfg = replace(cfg, stereo_ring=replace(cfg.stereo_ring, memory_reset_frames=reset_after))
    fe = StereoFrontend(_calibration(), cfg)
    fe._radii = [0.34]
    for k in range(reset_after):
        m = fe.process(k, float(k), left, right)
        if k < reset_after - 1:
            assert m.ring is None
            assert any("smaller than the ring seen so far (0.340 m)" in f for f in m.failures)
        else:
            assert m.ring is not None, m.failures
            assert abs(m.ring.radius_m - 0.30) < 0.003, m.ring.radius_m
    with pytest.raises(ValueError, match="memory_reset_frames"):
        replace(cfg.stereo_ring, memory_reset_frames=1)


def test_better_channel_takes_another_larger_curve_else_the_more_precise() -> None:
    """`_better_channel`: radii more than `max_radius_change` apart: the larger ring; within
    it: the smaller centre covariance, whichever is larger; one channel: that one."""
    fe = StereoFrontend(_calibration())
    rim = _rim()

    def ring(radius: float, sigma_m: float) -> Circle3D:
        return replace(rim, radius=radius, covariance=np.eye(7) * sigma_m**2)

    assert fe._better_channel({"grey": ring(0.12, 1e-4), "colour": ring(0.30, 1e-2)}) == "colour"
    assert fe._better_channel({"grey": ring(0.30, 1e-2), "colour": ring(0.12, 1e-4)}) == "grey"
    assert fe._better_channel({"grey": ring(0.300, 2e-3), "colour": ring(0.305, 3e-3)}) == "grey"
    assert fe._better_channel({"grey": ring(0.305, 3e-3), "colour": ring(0.300, 2e-3)}) == "colour"
    assert fe._better_channel({"colour": ring(0.1, 1.0)}) == "colour"
