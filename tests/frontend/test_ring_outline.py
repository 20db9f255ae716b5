"""The ring's outline fitted as a cylinder (satpose.frontend.ring_outline).

Points are placed on the exact outline (the convex hull of the projected rim and base), or
found as edges in images drawn with OpenCV polygons (4x supersampled, averaged, blurred): the
same on every CPU.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3
from satpose.frontend.conics import sampson_distance
from satpose.frontend.edges import EdgeSearchConfig, edges_of_polarity, smoothed
from satpose.frontend.measurements import Camera
from satpose.frontend.rim import rim_samples
from satpose.frontend.ring_outline import (
    OutlineConfig,
    fit_ring_outline,
    inner_edge_points,
    outline_distances,
    outline_hull,
)
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_conic,
    refine_circle,
)

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIG = StereoRig(
    K_left=K, K_right=K, right_from_left=Rigid3(R=np.eye(3), t=np.array([-0.3, 0.0, 0.0]))
)
CAMS = (Rigid3.identity(), RIG.right_from_left)
CONFIG = OutlineConfig(enabled=True)


def _circle(center: np.ndarray, tilt_deg: float, radius: float) -> Circle3D:
    los = center / np.linalg.norm(center)
    side = np.cross(los, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    t = math.radians(tilt_deg)
    normal = -(math.cos(t) * los + math.sin(t) * side)  # toward the cameras
    return Circle3D(center=center, normal=normal, radius=radius, covariance=np.eye(7))


def _on_outline(
    rim: Circle3D, height: float, n: int, rng: np.random.Generator, samples: int = 1440
) -> list[np.ndarray]:
    """``n`` points per camera spread along the outline (the hull of ``samples`` points per
    circle, its segments densified)."""
    out = []
    for T in CAMS:
        hull, _ = outline_hull(K, T, rim.center, rim.normal, rim.radius, height, samples)
        nxt = np.roll(hull, -1, axis=0)
        length = np.linalg.norm(nxt - hull, axis=1)
        s = np.sort(rng.uniform(0, length.sum(), n))
        k = np.searchsorted(np.cumsum(length), s)
        f = (s - (np.cumsum(length) - length)[k]) / length[k]
        out.append(hull[k] + f[:, None] * (nxt[k] - hull[k]))
    return out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def test_outline_distances_of_points_on_and_off_the_hull() -> None:
    rim = _circle(np.array([0.2, -0.1, 5.0]), 35.0, 0.4)
    hull, base = outline_hull(K, CAMS[0], rim.center, rim.normal, rim.radius, 0.1, 720)
    assert base.any() and (~base).any()  # both circles contribute at 35 deg tilt
    pts = _on_outline(rim, 0.1, 400, np.random.default_rng(0), samples=720)[0]
    d, kind = outline_distances(pts, hull, base)
    assert np.abs(d).max() < 1e-9  # on the boundary, exactly
    assert set(np.unique(kind)) == {0, 1, 2}  # rim arc, base arc and both silhouettes
    centre = hull.mean(axis=0)
    out = centre + (pts - centre) * 1.01
    assert (outline_distances(out, hull, base)[0] > 0).all()  # outside is positive


@pytest.mark.parametrize(("tilt_deg", "height"), [(25.0, 0.1), (50.0, 0.07), (60.0, 0.12)])
def test_noise_free_outline_gives_the_rim(tilt_deg: float, height: float) -> None:
    """Points on the outline of a cylinder: the circle of all of them is biased by
    centimetres; the outline fit, started there, returns the rim and the wall height."""
    rim = _circle(np.array([0.2, -0.1, 5.0]), tilt_deg, 0.45)
    pts = _on_outline(rim, height, 300, np.random.default_rng(1))
    everything = refine_circle(RIG, rim.center + 0.01, rim.normal, rim.radius, pts[0], pts[1])
    fit = fit_ring_outline(RIG, everything, pts[0], pts[1], CONFIG)
    assert np.linalg.norm(everything.center - rim.center) > 0.01  # the bias it removes
    # tolerances: the hull's chords (sagitta < 0.02 px) and the search's convergence
    assert np.linalg.norm(fit.circle.center - rim.center) < 1e-3
    assert _angle_deg(fit.circle.normal, rim.normal) < 0.1
    assert abs(fit.circle.radius - rim.radius) < 5e-4
    assert abs(fit.height_m - height) < 3e-3
    assert fit.circle.normal @ fit.circle.center < 0  # toward the cameras
    # the points it reports as rim lie on the rim's ellipses
    for k, T in enumerate(CAMS):
        C = circle_conic(K, T, rim.center, rim.normal, rim.radius)
        assert len(fit.rim_points[k]) > 60
        # px; a point at a silhouette's end may sit a chord's sagitta off the rim
        assert np.abs(sampson_distance(fit.rim_points[k], C)).max() < 0.05


def test_a_ring_without_a_visible_wall_is_the_plain_circle_fit() -> None:
    """Edges on the rim's ellipses only (the wall not seen, or the crease taken for the
    edge): the fitted height is ~0 and the rim is the plain circle fit's."""
    rim = _circle(np.array([0.1, 0.05, 4.0]), 30.0, 0.35)
    pts = [_on_outline(rim, 0.0, 300, np.random.default_rng(2))[k] for k in (0, 1)]
    plain = refine_circle(RIG, rim.center + 0.01, rim.normal, 0.36, pts[0], pts[1])
    fit = fit_ring_outline(RIG, plain, pts[0], pts[1], CONFIG)
    assert fit.height_m < 2e-3
    assert np.linalg.norm(fit.circle.center - plain.center) < 5e-4


def test_noisy_outline_errors_are_unbiased_and_match_the_covariance() -> None:
    """0.2 px Gaussian noise on the outline's points, 24 seeded trials: the rim centre's
    3-dof NEES summed over the trials lies inside the chi-square(72) 99.8 % interval
    [41.6, 113.6] (a wrong covariance by a factor 1.6 in variance leaves it), and the depth
    error's mean lies within 3.5 standard errors of zero."""
    rim = _circle(np.array([0.15, -0.05, 5.0]), 40.0, 0.45)
    rng = np.random.default_rng(7)
    nees, depth = [], []
    los = rim.center / np.linalg.norm(rim.center)
    for _ in range(24):
        pts = [p + rng.normal(0.0, 0.2, p.shape) for p in _on_outline(rim, 0.08, 250, rng)]
        start = refine_circle(RIG, rim.center + 0.01, rim.normal, rim.radius, pts[0], pts[1])
        fit = fit_ring_outline(RIG, start, pts[0], pts[1], CONFIG)
        e = fit.circle.center - rim.center
        nees.append(float(e @ np.linalg.solve(fit.circle.covariance[:3, :3], e)))
        depth.append(float(e @ los))
    assert 41.6 < sum(nees) < 113.6, sum(nees)
    assert abs(np.mean(depth)) < 3.5 * np.std(depth) / math.sqrt(len(depth)), depth


def _draw(T: Rigid3, rim: Circle3D, height: float, inner_m: float) -> np.ndarray:
    """A ring whose wall is as bright as its rim face (0.8) against a 0.15 background, a 0.3
    hole: the only edge outside is the outline."""
    s = 4
    img = np.full((H * s, W * s), 0.15, np.float32)
    P, _ = rim_samples(rim, 1440)
    base = P - height * rim.normal
    inner = rim.center + (P - rim.center) * (inner_m / rim.radius)

    def poly(X: np.ndarray) -> np.ndarray:
        x = (X @ T.R.T + T.t) @ K.T
        x = x[:, :2] / x[:, 2:3]
        return np.round((x + 0.5) * s * 16 - 0.5 * 16).astype(np.int32)

    hull = cv2.convexHull(np.r_[poly(P), poly(base)])
    cv2.fillPoly(img, [hull], 0.8, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [poly(inner)], 0.3, lineType=cv2.LINE_8, shift=4)
    small = img.reshape(H, s, W, s).mean(axis=(1, 3))
    return cv2.GaussianBlur(small, (0, 0), 0.6)


def test_drawn_ring_edges_follow_the_outline_and_the_fit_finds_the_rim() -> None:
    """Images of a ring with a wall as bright as its rim: sub-pixel edges searched along the
    normals of a start circle find the outline (base on the side where the wall shows). The
    circle of those edges is off by centimetres; the outline fit by about a millimetre."""
    rim = _circle(np.array([0.25, 0.1, 4.0]), 35.0, 0.3)
    height = 0.06
    edges = EdgeSearchConfig(smooth_sigma_px=0.6, step_px=0.25)
    start = Circle3D(
        center=rim.center + np.array([0.004, -0.003, 0.01]),
        normal=rim.normal,
        radius=rim.radius * 1.03,
        covariance=np.eye(7),
    )
    P, _ = rim_samples(start, 240)
    pts = []
    for T in CAMS:
        g = _draw(T, rim, height, 0.27)
        x = (P @ T.R.T + T.t) @ K.T
        p = x[:, :2] / x[:, 2:3]
        c = circle_conic(K, T, start.center, start.normal, start.radius)
        grad = np.c_[p, np.ones(len(p))] @ c
        nrm = grad[:, :2] / np.linalg.norm(grad[:, :2], axis=1, keepdims=True)
        centre = (start.center @ T.R.T + T.t) @ K.T
        nrm *= np.sign(np.einsum("ij,ij->i", nrm, p - centre[:2] / centre[2]))[:, None]
        e = edges_of_polarity(smoothed(g, edges), p, nrm, +1, 8.0, edges, raw=g)
        pts.append(e[np.isfinite(e[:, 0])])
    everything = refine_circle(RIG, start.center, start.normal, start.radius, pts[0], pts[1])
    fit = fit_ring_outline(RIG, everything, pts[0], pts[1], CONFIG)
    err_all = float(np.linalg.norm(everything.center - rim.center))
    err_outline = float(np.linalg.norm(fit.circle.center - rim.center))
    assert err_all > 0.01, err_all
    assert err_outline < 0.003, (err_outline, err_all)
    assert abs(fit.height_m - height) < 0.015
    assert _angle_deg(fit.circle.normal, rim.normal) < 0.5


def test_bad_points_raise_a_geometry_failure() -> None:
    rim = _circle(np.array([0.1, 0.0, 4.0]), 30.0, 0.3)
    with pytest.raises(GeometryFailure, match="too few"):
        fit_ring_outline(RIG, rim, np.zeros((5, 2)), np.zeros((5, 2)), CONFIG)
    nan = np.full((50, 2), np.nan)
    with pytest.raises(GeometryFailure):
        fit_ring_outline(RIG, rim, nan, nan, CONFIG)
    with pytest.raises(ValueError, match="samples"):
        OutlineConfig(samples=3)


def test_a_known_height_is_kept_and_tightens_the_rim() -> None:
    """A known wall height (1 mm) on noisy outline points: the fit keeps it within its
    sigma and the rim centre's covariance is no larger than with the height free (the prior
    adds information); started 1 cm off, the centre lands within 4 of its sigmas."""
    rim = _circle(np.array([0.2, -0.1, 6.0]), 40.0, 0.45)
    rng = np.random.default_rng(11)
    pts = [p + rng.normal(0.0, 0.2, p.shape) for p in _on_outline(rim, 0.09, 300, rng)]
    start = Circle3D(
        center=rim.center + 0.01, normal=rim.normal, radius=rim.radius, covariance=np.eye(7)
    )
    free = fit_ring_outline(RIG, start, pts[0], pts[1], CONFIG)
    known = fit_ring_outline(
        RIG, start, pts[0], pts[1], CONFIG, radius_prior=(0.45, 0.001), height_prior=(0.09, 0.001)
    )
    assert abs(known.height_m - 0.09) < 0.003
    e = known.circle.center - rim.center
    assert float(e @ np.linalg.solve(known.circle.covariance[:3, :3], e)) < 4.0**2
    assert np.trace(known.circle.covariance[:3, :3]) <= np.trace(free.circle.covariance[:3, :3])


def test_a_known_height_labels_edges_on_the_rim_as_the_crease() -> None:
    """Edges on the rim all round (where the wall shows, the crease between rim and wall is
    what the edge search found) with a known 8 cm wall: the base's predicted arc lies pixels
    outside them, and each point nearer the rim's image is labelled rim, so the fit is the rim
    (not pulled inward by the base's arc) and every point is reported on it."""
    rim = _circle(np.array([0.1, 0.05, 4.0]), 35.0, 0.35)
    pts = _on_outline(rim, 0.0, 300, np.random.default_rng(3))
    start = Circle3D(
        center=rim.center + 0.005, normal=rim.normal, radius=rim.radius, covariance=np.eye(7)
    )
    fit = fit_ring_outline(RIG, start, pts[0], pts[1], CONFIG, height_prior=(0.08, 0.001))
    assert np.linalg.norm(fit.circle.center - rim.center) < 1e-3
    assert _angle_deg(fit.circle.normal, rim.normal) < 0.1
    assert len(fit.rim_points[0]) == 300 and len(fit.rim_points[1]) == 300


def test_a_lipped_ring_outline_with_its_lip_known() -> None:
    """The outline of a lipped ring (a 2 cm lip, 8 mm thick, over a narrower wall): with the
    lip stated the fit returns the rim within a millimetre."""
    rim = _circle(np.array([0.2, -0.1, 5.0]), 45.0, 0.45)
    lip = (0.02, 0.008)
    rng = np.random.default_rng(5)
    pts = []
    for T in CAMS:
        hull, _ = outline_hull(K, T, rim.center, rim.normal, rim.radius, 0.1, 1440, lip)
        k = rng.integers(0, len(hull), 300)
        f = rng.uniform(0, 1, 300)[:, None]
        pts.append(hull[k] + f * (np.roll(hull, -1, axis=0)[k] - hull[k]))
    start = Circle3D(
        center=rim.center + 0.01, normal=rim.normal, radius=rim.radius, covariance=np.eye(7)
    )
    fit = fit_ring_outline(RIG, start, pts[0], pts[1], CONFIG, height_prior=(0.1, 0.001), lip=lip)
    assert np.linalg.norm(fit.circle.center - rim.center) < 1e-3
    assert abs(fit.circle.radius - rim.radius) < 1e-3


def test_inner_edge_points_lie_on_the_inner_edge_where_the_wall_shows() -> None:
    """Drawn images (rim face 0.8, wall as bright, hole 0.3): the inner edge is found only
    where the wall's outer face is turned toward the camera, on the inner circle's image (to
    the drawing's accuracy: polygons filled at 1/4 px and averaged, within a few tenths of a
    pixel, which is why the outline test above allows 3 mm), nowhere near the rim's outer
    edge 10 px away; with them the fit stays on the rim."""
    rim = _circle(np.array([0.25, 0.1, 4.0]), 35.0, 0.3)
    height, inner_m = 0.06, 0.25
    edges = EdgeSearchConfig(smooth_sigma_px=0.6, step_px=0.25)
    images = tuple(smoothed(_draw(T, rim, height, inner_m), edges) for T in CAMS)
    edge_points = inner_edge_points(RIG, rim, rim.radius - inner_m, (images[0], images[1]), edges)
    for k, T in enumerate(CAMS):
        C = circle_conic(K, T, rim.center, rim.normal, inner_m)
        assert len(edge_points[k]) > 30
        d = np.abs(sampson_distance(edge_points[k], C))
        assert np.median(d) < 0.3 and d.max() < 1.0, d
        # only where the wall's outer face is turned toward this camera
        centre = RIG.center(Camera.LEFT if k == 0 else Camera.RIGHT)
        rays = RIG.rays(Camera.LEFT if k == 0 else Camera.RIGHT, edge_points[k])[1]
        depth = ((rim.center - centre) @ rim.normal) / (rays @ rim.normal)
        X = centre + depth[:, None] * rays  # the points back on the rim's plane
        rho = (X - rim.center) / np.linalg.norm(X - rim.center, axis=1, keepdims=True)
        assert (np.einsum("ij,ij->i", rho, centre - X) > 0).all()
    outline = _on_outline(rim, height, 300, np.random.default_rng(4))
    start = Circle3D(
        center=rim.center + 0.005, normal=rim.normal, radius=rim.radius, covariance=np.eye(7)
    )
    fit = fit_ring_outline(
        RIG,
        start,
        outline[0],
        outline[1],
        CONFIG,
        height_prior=(height, 0.001),
        inner=(edge_points[0], edge_points[1], rim.radius - inner_m),
    )
    assert np.linalg.norm(fit.circle.center - rim.center) < 2e-3
