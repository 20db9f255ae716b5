"""The outer front rim among stereo-consistent circles (`satpose.frontend.ring_choice`)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration
from satpose.frontend.conics import conic_to_ellipse
from satpose.frontend.measurements import Camera, RingMeasurement
from satpose.frontend.pipeline import FrontendConfig, StereoFrontend, StereoRingConfig
from satpose.frontend.rim import rim_samples
from satpose.frontend.ring_choice import (
    behind_offset,
    behind_rim,
    coplanar_outer,
    front_choice,
    transferred_ellipse,
)
from satpose.frontend.stereo import Circle3D, StereoRig, circle_conic

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIGHT_FROM_LEFT = Rigid3(R=np.eye(3), t=np.array([-0.3, 0.0, 0.0]))
RIG = StereoRig(K_left=K, K_right=K, right_from_left=RIGHT_FROM_LEFT)


def _circle(center: np.ndarray, tilt_deg: float, radius: float, sigma_m: float) -> Circle3D:
    los = center / np.linalg.norm(center)
    side = np.cross(los, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    t = math.radians(tilt_deg)
    normal = -(math.cos(t) * los + math.sin(t) * side)  # toward the cameras
    cov = np.eye(7) * 1e-6
    cov[:3, :3] = np.eye(3) * sigma_m**2
    return Circle3D(center=center, normal=normal, radius=radius, covariance=cov)


def _moved(c: Circle3D, along_normal_m: float, radius: float) -> Circle3D:
    return replace(c, center=c.center + along_normal_m * c.normal, radius=radius)


def test_an_edge_behind_the_rim_loses_and_a_coplanar_larger_one_wins() -> None:
    """Noise-free geometry, centres known to 5 mm: a base or shadow circle 6 cm behind the
    rim and 4 cm larger is behind it (12 sigma); the rim's inner edge is coplanar, so the
    outer rim is not behind it and wins as the largest."""
    rim = _circle(np.array([0.2, -0.1, 5.0]), 30.0, 0.40, 0.005)
    base = _moved(rim, -0.06, 0.44)
    inner = replace(rim, radius=0.37)
    d, s = behind_offset(rim, base)
    assert abs(d - 0.06) < 1e-12 and abs(s - 0.005 * math.sqrt(2)) < 1e-12
    assert behind_rim(rim, base, 3.0)
    assert not behind_rim(inner, rim, 3.0)  # coplanar: the larger, outer rim stays
    assert not behind_rim(rim, inner, 3.0)  # smaller: never "around" the rim
    assert front_choice([base, rim, inner], 3.0) == 1
    assert front_choice([rim, inner], 3.0) == 0
    # within the centres' uncertainty (1 cm behind, sigma 7 mm) the larger still wins
    assert front_choice([_moved(rim, -0.01, 0.44), rim], 3.0) == 0
    # a larger circle in front of a smaller one (nothing of the ring is) is not refused
    assert front_choice([_moved(rim, +0.06, 0.44), rim], 3.0) == 0


def test_a_larger_edge_counts_as_the_outer_rim_only_in_the_inner_edges_plane() -> None:
    """Noise-free geometry, centres known to 5 mm (offset sigma 7.1 mm, 3 sigma 2.1 cm): the
    outer rim 10 % larger in the inner edge's plane is its outer edge; 1 cm off that plane
    (1.4 sigma) still is; a base 6 cm behind, a circle 6 cm in front (an edge carried at the
    wrong depth), one only 2 % larger, a smaller one and one off the axis are not."""
    inner = _circle(np.array([0.2, -0.1, 5.0]), 30.0, 0.40, 0.005)
    assert coplanar_outer(inner, replace(inner, radius=0.44), 3.0, 1.06)
    assert coplanar_outer(inner, _moved(inner, -0.01, 0.44), 3.0, 1.06)
    assert not coplanar_outer(inner, _moved(inner, -0.06, 0.44), 3.0, 1.06)
    assert not coplanar_outer(inner, _moved(inner, +0.06, 0.44), 3.0, 1.06)
    assert not coplanar_outer(inner, replace(inner, radius=0.408), 3.0, 1.06)
    assert coplanar_outer(inner, replace(inner, radius=0.408), 3.0, 1.01)
    assert not coplanar_outer(inner, replace(inner, radius=0.36), 3.0, 1.0)
    u = np.cross(inner.normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    assert not coplanar_outer(inner, replace(inner, center=inner.center + 0.5 * u, radius=0.5), 3.0)


def test_a_circle_off_the_axis_is_not_nested() -> None:
    """A larger circle whose centre lies beyond the smaller one's radius across its normal
    (another object) is not taken for that ring's base, however far behind."""
    rim = _circle(np.array([0.0, 0.0, 5.0]), 20.0, 0.30, 0.002)
    u = np.cross(rim.normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    other = replace(rim, center=rim.center + 0.5 * u - 0.1 * rim.normal, radius=0.35)
    assert not behind_rim(rim, other, 3.0)


def test_transferred_ellipse_is_the_other_cameras_image_at_the_reference_depth() -> None:
    """Noise-free: a left ellipse carried to the right camera at the true circle's distance
    is the right image of that circle (1e-6 px), and back; at a reference 5 cm farther the
    right ellipse moves by the disparity change (0.74 px at 4 m, f = 800, b = 0.3; 0.05 px)."""
    true = _circle(np.array([0.3, 0.1, 4.0]), 35.0, 0.3, 0.002)
    cl = circle_conic(K, Rigid3.identity(), true.center, true.normal, true.radius)
    cr = circle_conic(K, RIGHT_FROM_LEFT, true.center, true.normal, true.radius)
    right = conic_to_ellipse(cr)
    got = transferred_ellipse(RIG, cl, Camera.LEFT, true)
    assert np.abs(got.params - right.params).max() < 1e-6
    back = transferred_ellipse(RIG, cr, Camera.RIGHT, true)
    assert np.abs(back.params - conic_to_ellipse(cl).params).max() < 1e-6
    farther = replace(true, center=true.center * (1 + 0.05 / np.linalg.norm(true.center)))
    moved = transferred_ellipse(RIG, cl, Camera.LEFT, farther)
    shift = float(np.linalg.norm(moved.center - right.center))
    z = float(true.center[2])
    expected = F * 0.3 * (1 / z - 1 / float(farther.center[2]))  # the disparity change, 0.74 px
    assert abs(shift - expected) < 0.05, (shift, expected)


def _draw(T: Rigid3, rim: Circle3D, skirt: Circle3D, inner_m: float) -> np.ndarray:
    """A panel (0.5) with a dark planar disc behind the ring (``skirt``: a base or a shadow,
    0.08), the rim's bright face (0.85) and its hole (0.3); 4x supersampled, blur 0.6 px."""
    s = 4
    img = np.full((H * s, W * s), 0.5, np.float32)

    def poly(c: Circle3D) -> np.ndarray:
        P, _ = rim_samples(c, 1440)
        x = (P @ T.R.T + T.t) @ K.T
        x = x[:, :2] / x[:, 2:3]
        return np.round((x + 0.5) * s * 16 - 0.5 * 16).astype(np.int32)

    cv2.fillPoly(img, [poly(skirt)], 0.08, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [poly(rim)], 0.85, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [poly(replace(rim, radius=inner_m))], 0.3, lineType=cv2.LINE_8, shift=4)
    small = img.reshape(H, s, W, s).mean(axis=(1, 3))
    return np.clip(cv2.GaussianBlur(small, (0, 0), 0.6) * 255 + 0.5, 0, 255).astype(np.uint8)


def _stereo_ring(
    left: np.ndarray, right: np.ndarray, config: FrontendConfig | None = None
) -> RingMeasurement:
    """The ring the frontend measures in one drawn stereo pair of this file's rig."""
    cam = PinholeCamera(width=W, height=H, K=K)
    calib = Calibration(left=cam, right=cam, right_from_left=RIGHT_FROM_LEFT)
    m = StereoFrontend(calib, config).process(0, 0.0, left, right)
    assert m.ring is not None, m.failures
    return m.ring


def test_drawn_ring_with_a_dark_disc_behind_it_is_measured_on_its_rim() -> None:
    """Drawn stereo images: a ring (rim 0.30 m, face to 0.25 m) 4 m away, tilted 25 deg, in
    front of a dark disc 6 cm behind it and 12 % larger (a base skirt or a cast shadow: a
    planar circle, so it reconstructs as consistently as the rim). The largest consistent
    circle is the disc; the frontend reports the rim (radius within 2 mm, centre within
    1 cm), and with the behind test off (``behind_sigma: None``) the disc."""
    rim = _circle(np.array([0.15, 0.05, 4.0]), 25.0, 0.30, 0.0)
    skirt = _moved(rim, -0.06, 0.336)
    left = _draw(Rigid3.identity(), rim, skirt, 0.25)
    right = _draw(RIGHT_FROM_LEFT, rim, skirt, 0.25)
    ring = _stereo_ring(left, right)
    assert abs(ring.radius_m - 0.30) < 0.002, ring.radius_m
    assert float(np.linalg.norm(ring.center_m - rim.center)) < 0.01
    cfg = FrontendConfig()
    largest = replace(cfg, stereo_ring=replace(cfg.stereo_ring, behind_sigma=None))
    assert abs(_stereo_ring(left, right, largest).radius_m - 0.336) < 0.005


@pytest.mark.parametrize("bad", [0.99, math.nan])
def test_transfer_min_growth_must_be_at_least_one(bad: float) -> None:
    with pytest.raises(ValueError, match="transfer_min_growth"):
        StereoRingConfig(transfer_min_growth=bad)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_behind_sigma_must_be_positive_or_none(bad: float) -> None:
    assert StereoRingConfig(behind_sigma=None).behind_sigma is None
    with pytest.raises(ValueError, match="behind_sigma"):
        StereoRingConfig(behind_sigma=bad)


def _draw_patch(T: Rigid3, rim: Circle3D, inner_m: float, hidden: float) -> np.ndarray:
    """A panel (0.5), the rim's bright face (0.85) and its hole (0.3), and a patch of the
    panel as bright as the rim beside the first ``hidden`` fraction of the rim's perimeter
    (no outer edge there); 4x supersampled, blur 0.6 px."""
    s = 4
    img = np.full((H * s, W * s), 0.5, np.float32)

    def image(c: Circle3D) -> np.ndarray:
        P, _ = rim_samples(c, 1440)
        x = (P @ T.R.T + T.t) @ K.T
        return x[:, :2] / x[:, 2:3]

    def fixed(x: np.ndarray) -> np.ndarray:
        return np.round((x + 0.5) * s * 16 - 0.5 * 16).astype(np.int32)

    outer = image(rim)
    cv2.fillPoly(img, [fixed(outer)], 0.85, lineType=cv2.LINE_8, shift=4)
    arc = outer[: int(hidden * len(outer))]
    if len(arc):
        c = outer.mean(axis=0)
        patch = np.vstack([arc, (c + 4.0 * (arc - c))[::-1]])
        cv2.fillPoly(img, [fixed(patch)], 0.85, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [fixed(image(replace(rim, radius=inner_m)))], 0.3, cv2.LINE_8, shift=4)
    small = img.reshape(H, s, W, s).mean(axis=(1, 3))
    return np.clip(cv2.GaussianBlur(small, (0, 0), 0.6) * 255 + 0.5, 0, 255).astype(np.uint8)


def test_outer_rim_that_one_camera_misses_is_carried_from_the_other() -> None:
    """Drawn stereo images: a ring (rim 0.30 m, face to 0.25 m) 4 m away, tilted 25 deg; in
    the right image the panel beside 46 % of the rim is as bright as the rim's face, so the
    right camera's detector finds only the face's inner edge (its outer edge shows on 54 %
    of the perimeter). The left camera's outer edge, carried into the right image at the
    depth of the inner circle, is refined there and lies in that circle's plane: the frontend
    reports the outer rim (radius within 2 mm, centre within 1 cm). Without the rule
    (``transfer_min_growth`` beyond any growth) it reports the inner edge, 0.25 m."""
    rim = _circle(np.array([0.15, 0.05, 4.0]), 25.0, 0.30, 0.0)
    left = _draw_patch(Rigid3.identity(), rim, 0.25, 0.0)
    right = _draw_patch(RIGHT_FROM_LEFT, rim, 0.25, 0.46)
    ring = _stereo_ring(left, right)
    assert abs(ring.radius_m - 0.30) < 0.002, ring.radius_m
    assert float(np.linalg.norm(ring.center_m - rim.center)) < 0.01
    cfg = FrontendConfig()
    off = replace(cfg, stereo_ring=replace(cfg.stereo_ring, transfer_min_growth=1e9))
    assert abs(_stereo_ring(left, right, off).radius_m - 0.25) < 0.002


def _swept_from(
    rim: Circle3D, found_in: str
) -> tuple[StereoFrontend, dict[str, Any], tuple[list[Circle3D], dict[str, Any]]]:
    """Drawn stereo images of ``rim`` (face to 0.25 m); the frontend, its prepared images,
    and what `StereoFrontend._swept` finds from camera ``found_in``'s candidates alone (the
    other camera's discarded)."""
    images = {
        "left": _draw_patch(Rigid3.identity(), rim, 0.25, 0.0),
        "right": _draw_patch(RIGHT_FROM_LEFT, rim, 0.25, 0.0),
    }
    cam = PinholeCamera(width=W, height=H, K=K)
    fe = StereoFrontend(Calibration(left=cam, right=cam, right_from_left=RIGHT_FROM_LEFT))
    imgs = {c: fe.undistort[c](images[c]) for c in images}
    options = {c: fe.rings[c].acquire(imgs[c]) if c == found_in else [] for c in images}
    assert options[found_in]
    return fe, imgs, fe._swept(options, imgs)


def test_sweep_finds_the_ring_in_the_camera_whose_detector_found_nothing() -> None:
    """Drawn stereo images of the ring of the test above (4 m): with the left camera's
    candidates discarded, the sweep along the epipolar lines of the right camera's
    candidates finds the left ring and the pair makes the rim's circle (radius within 2 mm,
    centre within 1 cm); with no candidate in either camera there is nothing to sweep."""
    rim = _circle(np.array([0.15, 0.05, 4.0]), 25.0, 0.30, 0.0)
    fe, imgs, (circles, pair) = _swept_from(rim, "right")
    assert circles, "the sweep found no consistent pair"
    outer = [c for c in circles if abs(c.radius - 0.30) < 0.002]
    assert outer, [c.radius for c in circles]
    assert float(np.linalg.norm(outer[0].center - rim.center)) < 0.01
    assert set(pair) == {"left", "right"}
    assert fe._swept({"left": [], "right": []}, imgs) == ([], {})


def test_sweep_carries_the_circle_not_the_shape_of_a_close_tilted_ring() -> None:
    """Drawn stereo images of a ring (rim 0.30 m, face to 0.25 m) 1.6 m away, tilted 65 deg
    across the baseline: the two cameras see it 11 deg apart, so its image is an ellipse of
    semi-minor axis 65 px in the left image and 91 px in the right (noise-free projections).
    With the right camera's candidates discarded, the sweep carries the circle each section
    of the left ellipse's cone makes at each distance into the right image and finds the rim
    there (radius within 2 mm, centre within 1 cm); the left ellipse's shape shifted along
    the epipolar line is 25 px off at the minor axis' ends, beyond the refinement's reach."""
    rim = _circle(np.array([0.12, 0.03, 1.6]), 65.0, 0.30, 0.0)
    minor = {
        name: conic_to_ellipse(RIG.circle_conic(cam, rim)).b
        for name, cam in (("left", Camera.LEFT), ("right", Camera.RIGHT))
    }
    assert abs(minor["left"] - minor["right"]) > 20.0, minor
    _, _, (circles, _) = _swept_from(rim, "left")
    outer = [c for c in circles if abs(c.radius - 0.30) < 0.002]
    assert outer, [c.radius for c in circles]
    assert float(np.linalg.norm(outer[0].center - rim.center)) < 0.01


def test_a_circle_smaller_than_any_ring_is_not_taken_for_one() -> None:
    """Drawn stereo images of a ring scaled down to 8 cm (face to 6.7 cm) 2 m away, the size
    of a closed curve of foil cells: stereo reconstructs it as consistently as a ring, but
    it is under `min_radius_m` (0.1 m), so the frame has no ring and says why; with the
    bound off (0) the same images give the 8 cm circle (within 2 mm)."""
    rim = _circle(np.array([0.05, 0.02, 2.0]), 25.0, 0.08, 0.0)
    left = _draw_patch(Rigid3.identity(), rim, 0.067, 0.0)
    right = _draw_patch(RIGHT_FROM_LEFT, rim, 0.067, 0.0)
    cam = PinholeCamera(width=W, height=H, K=K)
    calib = Calibration(left=cam, right=cam, right_from_left=RIGHT_FROM_LEFT)
    m = StereoFrontend(calib).process(0, 0.0, left, right)
    assert m.ring is None
    assert any("min_radius_m" in f for f in m.failures), m.failures
    cfg = FrontendConfig()
    off = replace(cfg, stereo_ring=replace(cfg.stereo_ring, min_radius_m=0.0))
    assert abs(_stereo_ring(left, right, off).radius_m - 0.08) < 0.002


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf])
def test_min_radius_must_be_finite_and_not_negative(bad: float) -> None:
    assert StereoRingConfig(min_radius_m=0.0).min_radius_m == 0.0
    with pytest.raises(ValueError, match="min_radius_m"):
        StereoRingConfig(min_radius_m=bad)
