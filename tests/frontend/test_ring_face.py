"""The rim-face check (`RingConfig.face_rise`, `satpose.frontend.ring.face_rise`).

A ring lit from the side shows its wall's outer face beside the rim on one side; sunlit, that
face is brighter than the rim's front face. The edge of the tracked polarity (rim brighter than
the panel) is then the lit wall's edge against the panel, a few px outside the rim, and the
fit is pulled toward it there (tuning seed 5 of the random family: ellipse centre 0.2 -> 1.8 px
off over ten frames). The images are drawn with OpenCV (4x supersampled, averaged, blurred):
the same on every CPU.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.frontend.conics import Ellipse
from satpose.frontend.edges import smoothed
from satpose.frontend.ellipses import EllipseDetectorConfig, detect_ellipses
from satpose.frontend.measurements import Camera
from satpose.frontend.preprocess import PreparedImage, Undistorter
from satpose.frontend.ring import RingConfig, RingTracker, face_rise

W, H, S = 320, 240, 4
CENTRE, A, B, THETA_DEG = (160.3, 121.7), 70.0, 56.0, 20.0


def _poly(a: float, b: float, dx: float = 0.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    x, y = a * np.cos(t), b * np.sin(t)
    c, s = math.cos(math.radians(THETA_DEG)), math.sin(math.radians(THETA_DEG))
    p = np.c_[CENTRE[0] + dx + c * x - s * y, CENTRE[1] + s * x + c * y]
    return np.round((p + 0.5) * S * 16 - 8).astype(np.int32)


def _draw(rim_px: float, wall_shift_px: float) -> PreparedImage:
    """A grey rim (0.45) ``rim_px`` wide whose outer edge is the ellipse (CENTRE, A, B,
    THETA_DEG) on a dark panel (0.1), a darker hole inside (0.15), and a sunlit wall face
    (0.95) showing on the left: the rim's ellipse shifted by ``wall_shift_px`` to the left
    (the base), drawn behind the rim."""
    img = np.full((H * S, W * S), 0.1, np.float32)
    if wall_shift_px:
        cv2.fillPoly(img, [_poly(A, B, -wall_shift_px)], 0.95, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [_poly(A, B)], 0.45, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [_poly(A - rim_px, B - rim_px)], 0.15, lineType=cv2.LINE_8, shift=4)
    small = cv2.GaussianBlur(img.reshape(H, S, W, S).mean(axis=(1, 3)), (0, 0), 0.7)
    gray8 = np.clip(np.rint(small * 255), 0, 255).astype(np.uint8)
    camera = PinholeCamera(
        width=W, height=H, K=np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    )
    return Undistorter(camera)(gray8)


def _detector(gray8: np.ndarray, roi: tuple[int, int, int, int] | None = None) -> list:  # type: ignore[type-arg]
    return detect_ellipses(gray8, EllipseDetectorConfig(), roi)


def _centre_error(image: PreparedImage, config: RingConfig) -> float:
    """Centre error [px] of the rim refined from the true ellipse with the rim's polarity
    (+1: brighter than the panel), as the tracker refines its prediction every frame."""
    truth = Ellipse(cx=CENTRE[0], cy=CENTRE[1], a=A, b=B, theta=math.radians(THETA_DEG))
    found = RingTracker(Camera.LEFT, _detector, config).refine_at(image, truth, +1)
    assert found is not None
    obs, _ = found
    return float(np.hypot(*(obs.center_px - np.array(CENTRE))))


ON = replace(RingConfig(), face_rise=0.3)
OFF = RingConfig()  # the default: no check


def test_lit_wall_pulls_the_fit_without_the_check() -> None:
    """The premise: where the sunlit wall shows (4 px at most, on the left), its edge against
    the panel is taken for the rim: the centre moves by about 2 px."""
    assert _centre_error(_draw(8.0, 4.0), OFF) > 1.5


def test_the_check_leaves_out_the_band() -> None:
    """With the check the points bounding the lit wall are left out and the centre error
    drops below a quarter (noise-free drawing; what is left, ~0.5 px, comes from the band's
    tapered ends, narrower than the blur, where the edge is pulled without a visible rise:
    see docs/frontend.md, "A sunlit wall beside the rim")."""
    off = _centre_error(_draw(8.0, 4.0), OFF)
    assert _centre_error(_draw(8.0, 4.0), ON) < 0.25 * off


def test_face_rise_separates_rim_face_and_band() -> None:
    """`face_rise` itself: ~0 (|.| < 0.2) on the rim's edge where no wall shows (right side),
    and above 0.4 on the lit wall's edge
    sampled past the band against the panel (left side, 4 px outside the rim;
    the wall is 0.5 brighter than the rim for a contrast of 0.85: 0.59 ideally)."""
    image = _draw(8.0, 4.0)
    cfg = ON
    image_s = smoothed(image.gray, cfg.edges)
    c, s = math.cos(math.radians(THETA_DEG)), math.sin(math.radians(THETA_DEG))
    # the ends of the major axis: +a (right, no wall) and -a (left, wall 4 px wide)
    right = np.array([[CENTRE[0] + A * c, CENTRE[1] + A * s]])
    left = np.array([[CENTRE[0] - A * c - 4.0, CENTRE[1] - A * s]])
    n_right = np.array([[c, s]])
    # sampled 2-6 px inside: past the 4 px band
    rise = face_rise(image_s, np.vstack([right, left]), np.vstack([n_right, -n_right]), 6.0)
    assert abs(rise[0]) < 0.2
    assert rise[1] > 0.4


@pytest.mark.parametrize("rim_px", [2.0, 8.0])
def test_the_check_changes_nothing_without_a_wall(rim_px: float) -> None:
    """Without a wall in view, a wide rim face and a thin rim band (narrower than the face
    depth, so every point rises alike and the median absorbs it) are refined as before: the
    same centre within 0.05 px, on the truth within 0.1 px."""
    image = _draw(rim_px, 0.0)
    on, off = _centre_error(image, ON), _centre_error(image, OFF)
    assert on < 0.1
    assert abs(on - off) < 0.05


def test_bad_face_config_is_refused() -> None:
    with pytest.raises(ValueError, match="face_rise"):
        RingConfig(face_rise=0.0)
    with pytest.raises(ValueError, match="face_depth_px"):
        RingConfig(face_depth_px=1.0)
