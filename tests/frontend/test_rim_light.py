"""The ring refitted where no shadow of it shows beside the rim (satpose.frontend.rim, labels
``light``): the labels against a ray-traced oracle, and drawn stereo images of a dark rim whose
cast shadow on the panel behind it shows beside the rim on a different side in each camera.

Images are drawn with OpenCV polygons (4x supersampled, then averaged and blurred), not
rendered: they are the same on every CPU.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3
from satpose.frontend.edges import EdgeSearchConfig, edges_of_polarity, smoothed
from satpose.frontend.rim import (
    RimFitConfig,
    RimImage,
    camera_centers,
    edge_slopes,
    fit_outer_rim,
    lit_labels,
    rim_samples,
    shadow_band,
)
from satpose.frontend.stereo import Circle3D, StereoRig, circle_conic, refine_circle

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIG = StereoRig(
    K_left=K, K_right=K, right_from_left=Rigid3(R=np.eye(3), t=np.array([-0.3, 0.0, 0.0]))
)
EDGES = EdgeSearchConfig(
    smooth_sigma_px=0.6, step_px=0.25, locate="model", model_window_px=(-2.0, 0.5)
)
LAMP = np.array([0.15, 0.12, 0.0])  # between the cameras, above them


def _circle(center: np.ndarray, tilt_deg: float, radius: float) -> Circle3D:
    los = center / np.linalg.norm(center)
    side = np.cross(los, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    t = math.radians(tilt_deg)
    normal = -(math.cos(t) * los + math.sin(t) * side)  # toward the cameras
    return Circle3D(center=center, normal=normal, radius=radius, covariance=np.eye(7))


def _project(T: Rigid3, X: np.ndarray) -> np.ndarray:
    x = (X @ T.R.T + T.t) @ K.T
    return x[:, :2] / x[:, 2:3]


def _in_shadow(Q: np.ndarray, light: np.ndarray, rim: Circle3D, depth_m: float) -> bool:
    """Ray-traced: the segment from panel point ``Q`` to the lamp passes through the solid
    cylinder of the ring (radius ``rim.radius``, from the panel up to the rim's plane)."""
    s = np.linspace(0.0, 1.0, 4001)[:, None]
    X = Q + s * (light - Q)
    z = (X - rim.center) @ rim.normal  # height above the rim's plane (< 0: behind it)
    radial = X - rim.center - z[:, None] * rim.normal
    inside = (z <= 0) & (z >= -depth_m) & (np.linalg.norm(radial, axis=1) < rim.radius)
    return bool(inside.any())


def test_lit_labels_match_a_ray_traced_shadow() -> None:
    """Where the wall is hidden from a camera, the camera sees just beyond the rim's edge the
    panel point on its ray over the edge; the sample is kept iff that point is lit (no ray
    from it to the lamp crosses the ring). The labels need no wall height: the oracle's
    height (5 and 15 cm) must not matter."""
    rim = _circle(np.array([0.2, -0.1, 4.0]), 30.0, 0.3)
    P, rho = rim_samples(rim, 360)
    centers = camera_centers(RIG)
    _, keep_l, keep_r = lit_labels(rim, RIG, 360, LAMP, sun=False)
    s_lamp = edge_slopes(P, rho, rim.normal, LAMP)
    for depth in (0.05, 0.15):
        for C, keep in zip(centers, (keep_l, keep_r), strict=True):
            s_cam = edge_slopes(P, rho, rim.normal, C)
            hidden = np.flatnonzero(s_cam < 0)
            dark = np.zeros(len(P), bool)
            for k in hidden:
                ray = P[k] - C
                # the panel point on the camera's ray just over the edge (a hair outward)
                Q = C + ray * (1.0 + depth / float(-(ray @ rim.normal))) + 1e-6 * rho[k]
                dark[k] = _in_shadow(Q, LAMP, rim, depth)
            wrong = hidden[keep[hidden] == dark[hidden]]
            # they may disagree only where the shadow band is narrower than a hundredth of
            # the wall height (measured: 5 samples, all within 0.005 of the boundary; the
            # radial-slope rule ignores the shadow's tangential shift there)
            assert np.all(np.abs(s_lamp[wrong] - s_cam[wrong]) < 0.01), (depth, wrong)
            assert dark[hidden].any() and (~dark[hidden]).any()  # both kinds occur


def test_lit_labels_lamp_at_a_camera_and_sun() -> None:
    """A lamp in a camera's centre shows that camera no shadow (all kept); the other camera,
    0.3 m to the right, keeps the half of the rim turned toward the lamp (its shadow falls
    on the far side). Sunlight along the line of sight to the ring casts the ring's shadow
    straight behind its wall, hidden from cameras near that line (all kept); sunlight
    travelling toward +x casts it on the +x side, in both cameras."""
    rim = _circle(np.array([0.1, 0.05, 5.0]), 20.0, 0.4)
    _, rho = rim_samples(rim, 720)
    _, keep_l, keep_r = lit_labels(rim, RIG, 720, np.zeros(3), sun=False)
    assert keep_l.all()
    assert 0.4 < keep_r.mean() < 0.6  # measured: 0.49
    assert rho[keep_r, 0].mean() < -0.5  # measured: -0.61 (the side toward the lamp, -x)
    along = rim.center / np.linalg.norm(rim.center)
    _, sun_l, sun_r = lit_labels(rim, RIG, 720, along, sun=True)
    assert sun_l.all() and sun_r.all()
    side = along + np.array([0.6, 0.0, 0.0])  # ~30 deg off the line of sight, toward +x
    for kept in lit_labels(rim, RIG, 720, side, sun=True)[1:]:
        assert 0.2 < kept.mean() < 0.8
        assert rho[~kept, 0].mean() > 0.5


def test_light_config_is_checked() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        RimFitConfig(labels="light")
    with pytest.raises(ValueError, match="exactly one"):
        RimFitConfig(labels="light", light_position_m=(0, 0, 0), sun_direction=(0, 0, 1))
    with pytest.raises(ValueError, match="finite"):
        RimFitConfig(labels="light", light_position_m=(0.0, math.nan, 0.0))
    with pytest.raises(ValueError, match="labels"):
        RimFitConfig(labels="shadow")  # type: ignore[arg-type]


def _draw_shadowed(T: Rigid3, rim: Circle3D, depth_m: float, inner_m: float) -> np.ndarray:
    """A dark rim (0.1) on a bright panel (0.8) ``depth_m`` behind it, with the ring's shadow
    from ``LAMP`` on the panel (0.1): the outer circle cast from the lamp onto the panel's
    plane. The wall's outer face (from the rim down to the panel) is drawn over it, as bright
    as the panel where the lamp lights it and dark where it is turned away from the lamp."""
    s = 4
    img = np.full((H * s, W * s), 0.8, np.float32)
    P, rho = rim_samples(rim, 1440)
    n = rim.normal
    v = LAMP - P
    shadow = P - depth_m * v / (v @ n)[:, None]  # the lamp's rays over the edge, on the panel
    base = P - depth_m * n
    inner = rim.center + (P - rim.center) * (inner_m / rim.radius)
    lit = np.einsum("ij,ij->i", rho, v) > 0

    def poly(X: np.ndarray) -> np.ndarray:
        return np.round((_project(T, X) + 0.5) * s * 16 - 0.5 * 16).astype(np.int32)

    cv2.fillPoly(img, [poly(shadow)], 0.1, lineType=cv2.LINE_8, shift=4)
    for i in range(len(P)):
        j = (i + 1) % len(P)
        quad = poly(np.array([P[i], P[j], base[j], base[i]]))
        cv2.fillPoly(img, [quad], 0.8 if lit[i] else 0.1, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [poly(P)], 0.1, lineType=cv2.LINE_8, shift=4)
    cv2.fillPoly(img, [poly(inner)], 0.8, lineType=cv2.LINE_8, shift=4)
    small = img.reshape(H, s, W, s).mean(axis=(1, 3))
    return cv2.GaussianBlur(small, (0, 0), 0.5)


@pytest.mark.parametrize("shadow", ["model", "drop"])
def test_lit_refit_removes_the_shadow_bias(shadow: str) -> None:
    """A dark rim whose shadow on the panel (10 cm behind) merges with it on the side away
    from the lamp, a different side in each camera: the edges all round the ellipse put the
    ring centimetres too far (the shadow's disparity is the panel's). Modelled (the band's
    predicted width times one fitted height) the shadow costs nothing; dropping the band's
    samples halves what each camera sees and leaves most of the bias's size, of the other
    sign."""
    rim = _circle(np.array([0.15, 0.1, 4.0]), 25.0, 0.3)
    depth = 0.10
    cams = (Rigid3.identity(), RIG.right_from_left)
    imgs = [_draw_shadowed(T, rim, depth, 0.26) for T in cams]
    images = tuple(RimImage(image_s=smoothed(g, EDGES), raw=g, polarity=-1) for g in imgs)
    # the all-edges fit: edges all round each projected true circle, refitted
    P, _ = rim_samples(rim, 240)
    pts = []
    for T, img in zip(cams, images, strict=True):
        p = _project(T, P)
        c = circle_conic(K, T, rim.center, rim.normal, rim.radius)
        g = np.c_[p, np.ones(len(p))] @ c
        nrm = g[:, :2] / np.linalg.norm(g[:, :2], axis=1, keepdims=True)
        nrm *= np.sign(np.einsum("ij,ij->i", nrm, p - _project(T, rim.center[None])))[:, None]
        e = edges_of_polarity(img.image_s, p, nrm, -1, 3.0, EDGES, raw=img.raw)
        pts.append(e[np.isfinite(e[:, 0])])
    everything = refine_circle(RIG, rim.center, rim.normal, rim.radius, pts[0], pts[1])
    config = RimFitConfig(
        enabled=True,
        labels="light",
        light_position_m=(float(LAMP[0]), float(LAMP[1]), float(LAMP[2])),
        shadow=shadow,  # type: ignore[arg-type]
    )
    # the refit starts from the biased all-edges circle, as in the pipeline
    fit = fit_outer_rim(RIG, everything, (images[0], images[1]), EDGES, config)
    los = rim.center / np.linalg.norm(rim.center)
    depth_all = float((everything.center - rim.center) @ los)
    depth_lit = float((fit.circle.center - rim.center) @ los)
    # measured: all edges +2.5 cm; shadow modelled +0.02 cm (radius +0.2 mm); the band's
    # samples dropped (each camera keeps half, the all-edges normal kept) -0.9 cm
    assert depth_all > 0.015, depth_all
    limit = 0.4 * depth_all if shadow == "drop" else 0.002
    assert abs(depth_lit) < limit, (depth_lit, depth_all)
    assert abs(fit.circle.radius - rim.radius) < 0.002
    assert 0.3 < min(fit.rim_fraction) and max(fit.rim_fraction) < 0.7


def test_refine_circle_fits_a_shared_band_height() -> None:
    """Edge points displaced outward by ``k * band`` (one k for both images, per-point
    widths): the fit with ``band`` recovers the circle exactly (noise-free) and is less
    certain than without the nuisance; without it the circle is biased."""
    rim = _circle(np.array([0.1, 0.05, 4.0]), 30.0, 0.3)
    rng = np.random.default_rng(5)
    P, rho = rim_samples(rim, 240)
    k = 0.02  # metres of "height"
    pts, bands = [], []
    for T in (Rigid3.identity(), RIG.right_from_left):
        band = np.where(rng.random(len(P)) < 0.5, rng.uniform(5.0, 15.0, len(P)), 0.0)  # px/m
        p = _project(T, P)
        out = _project(T, P + 1e-4 * rho) - p
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        pts.append(p + (k * band)[:, None] * out)
        bands.append(band)
    start = (rim.center + 0.01, rim.normal, 0.31)
    fit = refine_circle(RIG, *start, pts[0], pts[1], sigma_px=0.1, band=(bands[0], bands[1]))
    plain = refine_circle(RIG, *start, pts[0], pts[1], sigma_px=0.1)
    # first-order displacement along the image normal: exact to ~1e-6 m here
    assert np.linalg.norm(fit.center - rim.center) < 2e-5
    assert abs(fit.radius - rim.radius) < 2e-5
    assert np.linalg.norm(plain.center - rim.center) > 50 * np.linalg.norm(fit.center - rim.center)
    assert fit.covariance[2, 2] > plain.covariance[2, 2]  # the nuisance costs information


def test_light_config_from_yaml_form() -> None:
    """The light as a user states it in a run's config (YAML form), and one-line errors."""
    from satpose.datasets.config import from_plain
    from satpose.datasets.errors import ConfigError
    from satpose.tools.pipeline import PipelineConfig

    rim = {"enabled": True, "labels": "light", "light_position_m": [0.15, -0.12, 0.0]}
    c = from_plain(PipelineConfig, {"frontend": {"rim": rim}})
    assert c.frontend.rim.light_position_m == (0.15, -0.12, 0.0)
    assert c.frontend.rim.shadow == "model"
    with pytest.raises(ConfigError, match="exactly one of light_position_m"):
        from_plain(PipelineConfig, {"frontend": {"rim": {"labels": "light"}}})
    with pytest.raises(ConfigError, match="light_position_m: expected 3 values"):
        from_plain(PipelineConfig, {"frontend": {"rim": {**rim, "light_position_m": [0.1]}}})


def test_no_band_anywhere_is_the_plain_fit() -> None:
    """A light that casts no visible band (sunlight along the ring's axis: the shadow falls
    straight behind the wall) gives zero band widths, and the fit with them is the plain one
    (no unconstrained nuisance)."""
    rim = _circle(np.array([0.1, 0.05, 4.0]), 30.0, 0.3)
    widths = shadow_band(rim, RIG, 240, -rim.normal, sun=True)
    assert not np.any(widths[0]) and not np.any(widths[1])
    P, _ = rim_samples(rim, 240)
    pts = [_project(T, P) for T in (Rigid3.identity(), RIG.right_from_left)]
    start = (rim.center + 0.01, rim.normal, 0.31)
    fit = refine_circle(RIG, *start, pts[0], pts[1], sigma_px=0.1, band=widths)
    plain = refine_circle(RIG, *start, pts[0], pts[1], sigma_px=0.1)
    assert np.allclose(fit.center, plain.center, atol=1e-12)
    assert np.allclose(fit.covariance, plain.covariance, atol=1e-15)
    # a lamp behind the rim's plane lights no front face: no band either
    behind = rim.center - 2.0 * rim.normal
    assert not any(np.any(w) for w in shadow_band(rim, RIG, 240, behind, sun=False))
