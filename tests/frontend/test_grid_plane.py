"""The normal of a plane from its rectangular line grid (`satpose.frontend.grid_plane`), on
drawn images of a solar-array-like grid with known pose: drawn with OpenCV's integer
anti-aliased lines (the same pixels on every machine), so the tolerances are about the
method, not the renderer."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.frontend.grid_plane import GridPlaneConfig, measure_grid_plane
from satpose.frontend.measurements import MeasurementError, PlaneNormalMeasurement

W, H = 960, 768
K = np.array([[1100.0, 0.0, (W - 1) / 2], [0.0, 1100.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _pose(tilt_deg: float, turn_deg: float, range_m: float) -> Rigid3:
    """``cam_from_plane``: the grid plane (z = 0) tilted about x then turned about y, its
    origin ``range_m`` ahead and a little below the optical axis (the array fills the lower
    part of the image, as in the paper's view)."""
    R = (
        rotvec_to_matrix(np.array([0.0, math.radians(turn_deg), 0.0]))
        @ rotvec_to_matrix(np.array([math.radians(tilt_deg), 0.0, 0.0]))
        @ np.diag([1.0, -1.0, -1.0])
    )
    return Rigid3(R=R, t=np.array([0.0, 0.15, range_m]))


def _draw(
    T: Rigid3, dist: np.ndarray, angle_deg: float = 90.0, pitch: float = 0.02, n: int = 30
) -> np.ndarray:
    """A dark image with a grid of bright lines ``pitch`` apart on the plane (the second
    family at ``angle_deg`` to the first), each drawn as a polyline through 200 projected
    (and distorted) points, plus a bright bar off the grid (a strut)."""
    img = np.full((H, W), 25, np.uint8)
    rvec, _ = cv2.Rodrigues(T.R)
    a = math.radians(angle_deg)
    u1, u2 = np.array([1.0, 0.0, 0.0]), np.array([math.cos(a), math.sin(a), 0.0])
    span = pitch * n
    s = np.linspace(-span / 2, span / 2, 200)
    for u, v in ((u1, u2), (u2, u1)):
        for k in range(n + 1):
            off = (k - n / 2) * pitch
            # a line of the family ``u`` through the point ``off`` along the other normal
            perp = v - (v @ u) * u
            perp /= np.linalg.norm(perp)
            pts = off * perp[None] + s[:, None] * u[None]
            px, _ = cv2.projectPoints(pts, rvec, T.t.astype(float), K, dist)
            poly = np.round(px.reshape(-1, 2) * 16).astype(np.int32)
            cv2.polylines(img, [poly], False, 210, 2, cv2.LINE_AA, 4)
    cv2.line(img, (150 * 16, 80 * 16), (420 * 16, 200 * 16), 230, 5, cv2.LINE_AA, 4)
    return img


def _err_deg(m: PlaneNormalMeasurement, T: Rigid3) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(m.normal @ T.R[:, 2])))))


@pytest.mark.parametrize(
    ("tilt", "turn", "k1"), [(35.0, 10.0, 0.0), (20.0, -25.0, 0.0), (40.0, 15.0, -0.08)]
)
def test_normal_of_a_drawn_grid(tilt: float, turn: float, k1: float) -> None:
    """A 0.6 m grid of 31 x 31 lines at 1 m, tilted 20-40 deg (mild barrel distortion in
    the third case, removed from the segments' ends): the normal within 0.3 deg (0.03-0.2
    measured: the drawing's anti-aliasing) and within 3 of its stated sigmas."""
    T = _pose(tilt, turn, 1.0)
    dist = np.array([k1, 0.0, 0.0, 0.0, 0.0])
    cam = PinholeCamera(width=W, height=H, K=K, dist=dist)
    m, why = measure_grid_plane(_draw(T, dist), cam)
    assert m is not None, why
    err = _err_deg(m, T)
    assert err < 0.3, err
    assert err < 3.0 * math.degrees(m.sigma_rad), (err, math.degrees(m.sigma_rad))
    assert m.normal[2] < 0 and min(m.lines) >= 20 and m.skew_deg < 0.5


def test_same_image_same_measurement() -> None:
    """Seeded RANSAC and bootstrap: the same image gives the same normal and sigma."""
    T = _pose(30.0, 5.0, 1.2)
    cam = PinholeCamera(width=W, height=H, K=K)
    img = _draw(T, np.zeros(5))
    a, _ = measure_grid_plane(img, cam)
    b, _ = measure_grid_plane(img, cam)
    assert a is not None and b is not None
    assert np.array_equal(a.normal, b.normal) and a.sigma_rad == b.sigma_rad


def test_what_is_not_a_rectangular_grid_is_refused() -> None:
    """A blank image, a few lines (a bracket's struts) and a grid whose families meet at 70
    deg give no normal, each with its reason; uint16 and BGR images are read like grey."""
    cam = PinholeCamera(width=W, height=H, K=K)
    m, why = measure_grid_plane(np.zeros((H, W), np.uint8), cam)
    assert m is None and "segments" in why
    few = np.full((H, W), 25, np.uint8)
    for k in range(4):
        cv2.line(few, (100, 100 + 60 * k), (800, 160 + 60 * k), 220, 3, cv2.LINE_AA)
        cv2.line(few, (100 + 60 * k, 500), (300 + 60 * k, 740), 220, 3, cv2.LINE_AA)
    m, why = measure_grid_plane(few, cam)
    assert m is None and ("segments" in why or "lines" in why), why
    T = _pose(35.0, 10.0, 1.0)
    m, why = measure_grid_plane(_draw(T, np.zeros(5), angle_deg=70.0), cam)
    assert m is None and "perpendicular" in why, why
    grid = _draw(T, np.zeros(5))
    g16, _ = measure_grid_plane(grid.astype(np.uint16) * 257, cam)
    bgr, _ = measure_grid_plane(cv2.cvtColor(grid, cv2.COLOR_GRAY2BGR), cam)
    assert g16 is not None and bgr is not None
    assert _err_deg(g16, T) < 0.3 and _err_deg(bgr, T) < 0.3


def test_bad_settings_and_measurements() -> None:
    with pytest.raises(MeasurementError, match="inlier_px"):
        GridPlaneConfig(inlier_px=0.0)
    with pytest.raises(MeasurementError, match="min_segments"):
        GridPlaneConfig(min_segments=1)
    with pytest.raises(MeasurementError, match="sigma"):
        PlaneNormalMeasurement(
            normal=np.array([0, 0, 1.0]), sigma_rad=0.0, lines=(1, 1), skew_deg=0
        )
    with pytest.raises(MeasurementError, match="normal"):
        PlaneNormalMeasurement(
            normal=np.array([np.nan, 0, 1.0]), sigma_rad=0.01, lines=(1, 1), skew_deg=0
        )
    m = PlaneNormalMeasurement(
        normal=np.array([0, 0, 2.0]), sigma_rad=0.01, lines=(1, 1), skew_deg=0
    )
    assert np.allclose(m.normal, [0, 0, -1])  # unit, toward the camera
