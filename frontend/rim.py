"""The ring's outer front rim, and only it, from both images (the stereo generalisation issue).

A docking or launch-adapter ring is a cylindrical wall with height. Its image shows the outer
front rim, the wall's outer face between the rim and the base, the wall's two silhouette lines
and the base; the outer contour of the whole ring is the convex hull of the rim's and the
base's images, not the rim's image. Where the wall's outer face is visible, an edge found near
the rim's ellipse may be the rim (the crease between the rim's front face and the wall), the
base or a silhouette, and which one depends on materials and light. Fitting all of them as one
ellipse biases the ellipse toward the base on the wall side, by a different amount in the two
cameras (each sees the wall from its own centre: the silhouette is viewpoint-dependent), which
is a depth and lateral bias of centimetres.

Which points can be the rim follows from geometry alone. At a rim point ``P`` with outward
radial direction ``rho``, the wall's outer face is turned toward a camera at ``C`` when
``rho . (C - P) > 0``. Where it is turned away, the rim is the occluding edge of the ring there
(the wall and base are hidden behind it), and the edge found is the rim; where it is turned
toward the camera, the edge is ambiguous. `rim_labels` labels each sample of the current 3-D
circle per camera (``rim`` or ``wall side``, with a margin of a few degrees around the
silhouette's tangent point); `fit_outer_rim` searches sub-pixel edges along the normals of the
circle's projection at the ``rim`` samples only, in each camera, and refits the 3-D circle
(`satpose.frontend.stereo.refine_circle`) to them, twice. The labels depend on the camera
centre, so the two cameras keep different arcs; for a camera inside the cylinder's extension
(``|lateral offset| < radius``) no wall is visible and the whole rim is kept. The wall height is
not needed, so the method works without the ring's dimensions (non-cooperative); a known
outer radius (``known ring``) is used as a prior on the radius.

With a lamp beside the cameras (or the sun) the ring's shadow on the panel behind it, and the
wall's unlit face, can show beside the rim as a dark band, on the side away from the light
and so on a different side in each camera; a dark rim merges with it, and every edge locator
finds the band's far edge, whose disparity is the panel's: the ring is measured centimetres
too far (benchmarks/ring_ablation.py). Given the light (``labels = light``: the rig's lamp
position, a calibration of the chaser's own illuminator, or the sun's direction), where the
band shows follows from geometry (`lit_labels`, no ring dimensions needed), and its width
is proportional to the wall's height (`shadow_band`): the refit either drops those samples
or fits the height as one nuisance shared by both cameras (``shadow = model``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from satpose.frontend.conics import ConicError, Ellipse, conic_to_ellipse, sampson_distance
from satpose.frontend.edges import EdgeSearchConfig, edges_of_polarity
from satpose.frontend.measurements import Camera, EllipseObservation
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_conic,
    refine_circle,
    tangent_basis,
)


@dataclass(frozen=True, kw_only=True)
class RimFitConfig:
    """The rim-only refit of the ring's 3-D circle (`fit_outer_rim`).

    Attributes:
        enabled: refit on rim points only (False: the ring is the circle of all edge points
            near the ring's ellipse, as before the stereo generalisation issue).
        samples: samples of the circle's projection per camera.
        wall_margin_deg: a sample is ``rim`` when the wall's outer face there is turned away
            from the camera by at least this angle (``rho . (C - P) / |C - P| < -sin``);
            covers the circle's own error near the silhouette's tangent point.
        search_px: half-width of the first edge search along the projected circle's normals
            (later passes search ``search_px / 2``).
        passes: label-search-refit passes.
        min_rim_fraction: fewer ``rim`` samples with an edge than this fraction of
            ``samples`` in either camera and the refit is refused (the caller keeps the
            all-points circle and says so).
        outlier_sigma: edge points farther than this many robust standard deviations from
            the refitted circle's image are dropped (bolt heads, a shadow's edge).
        labels: which samples are kept in each camera. ``wall``: where the wall's outer face
            is turned away from the camera (`rim_labels`). ``light``: by where a shadow of the
            ring (cast on the panel, or the wall's own unlit face) can show beside the rim in
            that camera (`lit_labels`), those samples dropped or modelled (``shadow``); needs
            the light: ``light_position_m`` or ``sun_direction``. (Keeping only samples that
            are both wall-hidden and lit leaves a quarter of the rim or less, too little:
            tried on tuning seeds 0, 6, 7, depth errors of -15 to -36 cm.)
        light_position_m: a lamp on the rig, in the left camera frame [m] (calibration of the
            chaser's own illuminator).
        sun_direction: the direction sunlight travels, left camera frame (normalised on use).
        light_margin_deg: ``light`` labels: a sample is also kept where the light's slope
            over the edge falls short of the camera's by less than the tangent of this angle
            (`lit_labels`); 0 keeps exactly the samples where the light sees beyond the edge
            at least as far as the camera does.
        keep_normal: ``light`` labels, ``shadow = drop``: refit the centre and radius only
            and keep the normal of the circle fitted to all edges. Each camera keeps about
            half the rim (the side toward the light), which constrains the normal of a
            near-frontal ring poorly.
        shadow: ``light`` labels: ``drop`` the samples where a shadow band may show beside
            the rim, or ``model`` it: keep every sample and expect the edge outside the rim
            by the band's predicted width (`shadow_band`) times one unknown height fitted
            with the circle (the two cameras' bands come from one 3-D shadow).
    """

    enabled: bool = False
    samples: int = 240
    wall_margin_deg: float = 5.0
    search_px: float = 3.0
    passes: int = 2
    min_rim_fraction: float = 0.2
    outlier_sigma: float = 3.0
    labels: Literal["wall", "light"] = "wall"
    light_position_m: tuple[float, float, float] | None = None
    sun_direction: tuple[float, float, float] | None = None
    light_margin_deg: float = 0.0
    keep_normal: bool = True
    shadow: Literal["drop", "model"] = "model"

    def __post_init__(self) -> None:
        if self.shadow not in ("drop", "model"):
            raise ValueError(f"rim fit: shadow must be drop or model, got {self.shadow!r}")
        if self.labels not in ("wall", "light"):
            raise ValueError(f"rim fit: labels must be wall or light, got {self.labels!r}")
        if self.labels != "wall" and (self.light_position_m is None) == (
            self.sun_direction is None
        ):
            raise ValueError(
                f"rim fit: labels = {self.labels} needs exactly one of light_position_m, "
                "sun_direction"
            )
        for name in ("light_position_m", "sun_direction"):
            v = getattr(self, name)
            if v is not None and (len(v) != 3 or not np.all(np.isfinite(v))):
                raise ValueError(f"rim fit: {name} must be 3 finite numbers, got {v}")
        if self.sun_direction is not None and not np.linalg.norm(self.sun_direction) > 0:
            raise ValueError("rim fit: sun_direction must not be zero")
        if not 0.0 <= self.light_margin_deg < 45.0:
            raise ValueError(
                f"rim fit: light_margin_deg must be in [0, 45), got {self.light_margin_deg}"
            )
        if self.samples < 24:
            raise ValueError(f"rim fit: samples must be >= 24, got {self.samples}")
        if not 0.0 <= self.wall_margin_deg < 45.0:
            raise ValueError(
                f"rim fit: wall_margin_deg must be in [0, 45), got {self.wall_margin_deg}"
            )
        if not (self.search_px > 0 and self.passes >= 1 and 0 < self.min_rim_fraction <= 1):
            raise ValueError("rim fit: search_px > 0, passes >= 1, 0 < min_rim_fraction <= 1")

    def light(self) -> tuple[np.ndarray, bool]:
        """The light as `lit_labels` and `shadow_band` take it: ``(sun_direction, True)``
        or ``(light_position_m, False)``."""
        sun = self.sun_direction is not None
        return np.asarray(self.sun_direction if sun else self.light_position_m, float), sun


@dataclass(frozen=True)
class RimFit:
    """The ring's 3-D circle refitted on rim points, with what the labels kept.

    Attributes:
        circle: the refitted circle (left camera frame).
        points: per camera (left, right) the rim edge points used [undistorted px].
        rim_fraction: per camera, the fraction of the circle's samples labelled ``rim``
            (the rest are on the side where the wall's outer face is visible).
        rms_px: RMS first-order distance of the kept points to the circle's images.
    """

    circle: Circle3D
    points: tuple[np.ndarray, np.ndarray]
    rim_fraction: tuple[float, float]
    rms_px: float


def camera_centers(rig: StereoRig) -> tuple[np.ndarray, np.ndarray]:
    """Left and right camera centres in the left camera frame [m]."""
    return rig.center(Camera.LEFT), rig.center(Camera.RIGHT)


def rim_samples(circle: Circle3D, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on the circle and their outward radial directions, (n, 3) each."""
    u, v = tangent_basis(circle.normal)
    phi = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    rho = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v
    return circle.center + circle.radius * rho, rho


def wall_facing(points: np.ndarray, rho: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
    """Per rim point, the sine of the angle by which the wall's outer face there is turned
    toward the camera (> 0: visible beside the rim; < 0: hidden behind it)."""
    view = camera_center - points
    return np.einsum("ij,ij->i", rho, view) / np.linalg.norm(view, axis=1)


def rim_labels(
    circle: Circle3D, rig: StereoRig, n: int, margin_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the circle and per camera whether each is a clean ``rim`` sample.

    Returns:
        points (n, 3), and boolean masks (n,) for the left and the right camera.
    """
    P, rho = rim_samples(circle, n)
    c_left, c_right = camera_centers(rig)
    s = -math.sin(math.radians(margin_deg))
    return P, wall_facing(P, rho, c_left) < s, wall_facing(P, rho, c_right) < s


def _outward_normals(conic: np.ndarray, pts: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Unit normals of the conic at points on it, pointing away from ``center``."""
    g = np.c_[pts, np.ones(len(pts))] @ conic
    nrm = g[:, :2] / np.linalg.norm(g[:, :2], axis=1, keepdims=True)
    flip = np.einsum("ij,ij->i", nrm, pts - center) < 0
    nrm[flip] *= -1.0
    return nrm


def edge_slopes(
    points: np.ndarray, rho: np.ndarray, normal: np.ndarray, toward: np.ndarray
) -> np.ndarray:
    """Per rim point, the tangent of the angle between the front normal and the direction
    ``toward`` a point (``toward`` (3,) a position) or along a direction (``toward`` (N, 3)),
    measured outward: ``rho . v / (normal . v)``. A ray from that point (or along that
    direction) passing over the rim's edge lands ``-h * slope`` outward of the edge on a
    plane ``h`` behind the rim (the panel); -inf where it is behind the rim's plane (the
    rim's front face is then not seen, or not lit)."""
    v = toward - points if toward.ndim == 1 else toward  # (N, 3)
    front = v @ normal
    out = np.einsum("ij,ij->i", rho, v)
    safe = np.where(front > 1e-12, front, 1.0)
    return np.where(front > 1e-12, out / safe, -np.inf)


def lit_labels(
    circle: Circle3D,
    rig: StereoRig,
    n: int,
    light: np.ndarray,
    sun: bool,
    margin_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the circle and per camera whether what that camera sees just beyond the
    rim's outer edge is lit (no shadow of the ring shows beside the rim there).

    A camera at ``C`` sees, just beyond the edge at ``P``, the panel ``-h s_C`` outward of the
    edge (``s_C`` from `edge_slopes`; ``h`` the wall height) when the wall is hidden, or the
    wall's outer face when ``s_C > 0``. The light (a lamp at ``light``, or the sun: ``light``
    the direction sunlight travels) leaves the panel up to ``-h s_L`` outward in the ring's
    shadow, and the wall's face unlit when ``s_L < 0``. So a dark band lies beside the rim in
    that camera exactly where ``s_L < s_C``: a lamp beside the cameras puts it on the side
    away from the lamp, a different side in each camera, and every edge locator then finds
    the band's far edge, whose disparity is the panel's (the ring measured too far). The
    height cancels: no ring dimensions are needed. Samples with ``s_L >= s_C - tan(margin)``
    are kept.

    Returns:
        points (n, 3), and boolean masks (n,) for the left and the right camera.
    """
    P, _, _, s_light, s_cams = _light_slopes(circle, rig, n, light, sun)
    tol = math.tan(math.radians(margin_deg)) + 1e-9
    return P, s_light >= s_cams[0] - tol, s_light >= s_cams[1] - tol


def _light_slopes(
    circle: Circle3D, rig: StereoRig, n: int, light: np.ndarray, sun: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """`edge_slopes` at the circle's samples (`rim_samples`, normal toward the cameras)
    toward the light (a lamp at ``light``, or the sun: ``light`` the direction sunlight
    travels) and toward each camera: ``(points, outward directions, normal, s_light,
    (s_left, s_right))``."""
    P, rho = rim_samples(circle, n)
    c_left, c_right = camera_centers(rig)
    normal = circle.normal if circle.normal @ (c_left - circle.center) > 0 else -circle.normal
    toward = np.broadcast_to(-light / np.linalg.norm(light), P.shape) if sun else light
    s_cams = (edge_slopes(P, rho, normal, c_left), edge_slopes(P, rho, normal, c_right))
    return P, rho, normal, edge_slopes(P, rho, normal, toward), s_cams


def shadow_band(
    circle: Circle3D, rig: StereoRig, n: int, light: np.ndarray, sun: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Per camera and sample of the circle (`rim_samples`), the predicted width [px per metre
    of wall height] of the dark band beside the rim: the ring's shadow on the panel (and the
    wall's unlit face) where `lit_labels` finds one (``s_L < s_C`` and ``s_L < 0``), else 0.
    The band's far edge is the lamp's ray over the rim's edge where it meets a plane ``h``
    behind the rim, ``Q = P - h v / (n . v)`` (``v`` toward the light); its width is the
    distance of ``Q``'s image outside the rim's image, linear in ``h`` to first order.

    Returns:
        (n,) per camera (left, right), >= 0.
    """
    P, rho, normal, s_light, s_cams = _light_slopes(circle, rig, n, light, sun)
    v = np.broadcast_to(-light / np.linalg.norm(light), P.shape) if sun else light - P
    h0 = 1e-3 * circle.radius  # a small height: the band's width is linear in it
    Q = P - h0 * v / (v @ normal)[:, None]
    out = []
    for cam, s_cam in zip((Camera.LEFT, Camera.RIGHT), s_cams, strict=True):
        K, T = rig.intrinsics(cam), rig.cam_from_left(cam)
        conic = circle_conic(K, T, circle.center, circle.normal, circle.radius)
        x = (Q @ T.R.T + T.t) @ K.T
        q = x[:, :2] / x[:, 2:3]
        xo = ((P + h0 * rho) @ T.R.T + T.t) @ K.T  # a point outside, for the sign
        outside = np.sign(sampson_distance(xo[:, :2] / xo[:, 2:3], conic))
        width = np.maximum(outside * sampson_distance(q, conic), 0.0) / h0
        # where the light is behind the rim's plane the front face itself is unlit: no band
        # model there (s_light is -inf)
        dark = np.isfinite(s_light) & (s_light < s_cam) & (s_light < -1e-9)
        out.append(np.where(dark & np.isfinite(width), width, 0.0))
    return out[0], out[1]


def sample_labels(
    circle: Circle3D, rig: StereoRig, config: RimFitConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of ``circle`` that `fit_outer_rim` keeps per camera (``config.labels``)."""
    if config.labels == "wall":
        return rim_labels(circle, rig, config.samples, config.wall_margin_deg)
    light, sun = config.light()
    return lit_labels(circle, rig, config.samples, light, sun, config.light_margin_deg)


@dataclass(frozen=True)
class RimImage:
    """What `fit_outer_rim` needs of one camera's image."""

    image_s: np.ndarray  # smoothed, `satpose.frontend.edges.smoothed`
    raw: np.ndarray  # the undistorted grey image in [0, 1]
    polarity: int  # the rim's edge polarity in this camera (+1, -1, 0)


def fit_outer_rim(
    rig: StereoRig,
    circle: Circle3D,
    images: tuple[RimImage, RimImage],
    edges: EdgeSearchConfig,
    config: RimFitConfig,
    radius_prior: tuple[float, float] | None = None,
) -> RimFit:
    """Refit ``circle`` (fitted to all edges near the ring) on rim points only.

    Per pass and camera: the circle's samples labelled ``rim`` (`rim_labels`), projected, edges
    searched along the projection's normals with the rim's polarity, then `refine_circle` on
    both cameras' points with a robust cut.

    Raises:
        GeometryFailure: too few rim edge points in a camera, or the refit failed.
    """
    cams = tuple((rig.intrinsics(c), rig.cam_from_left(c)) for c in (Camera.LEFT, Camera.RIGHT))
    half = config.search_px
    keep = config.labels == "light" and config.keep_normal and config.shadow == "drop"
    kept: list[np.ndarray] = [np.zeros((0, 2)), np.zeros((0, 2))]
    fractions = (0.0, 0.0)
    model = config.labels == "light" and config.shadow == "model"
    for _ in range(config.passes):
        P, m_left, m_right = sample_labels(circle, rig, config)
        fractions = (float(m_left.mean()), float(m_right.mean()))
        bands = (np.zeros(len(P)), np.zeros(len(P)))
        if model:
            bands = shadow_band(circle, rig, config.samples, *config.light())
            m_left = m_right = np.ones(len(P), bool)
        found, found_band = [], []
        projected = zip(rig.project(P), rig.project(circle.center[None]), strict=True)
        for (K, T), img, mask, band, (px, center) in zip(
            cams, images, (m_left, m_right), bands, projected, strict=True
        ):
            pts = px[mask]
            conic = circle_conic(K, T, circle.center, circle.normal, circle.radius)
            nrm = _outward_normals(conic, pts, center[0])
            e = edges_of_polarity(img.image_s, pts, nrm, img.polarity, half, edges, raw=img.raw)
            ok = np.isfinite(e[:, 0])
            e = e[ok]
            if e.shape[0] < config.min_rim_fraction * config.samples:
                raise GeometryFailure(
                    f"rim fit: {e.shape[0]} rim edge points in the "
                    f"{'left' if T is cams[0][1] else 'right'} image "
                    f"(of {int(mask.sum())} rim samples)"
                )
            found.append(e)
            found_band.append(band[mask][ok])
        circle = _refit(rig, circle, found, radius_prior, keep, found_band if model else None)
        # robust cut: bolt heads or a shadow's edge next to the rim
        res = [
            sampson_distance(p, circle_conic(K, T, circle.center, circle.normal, circle.radius))
            for p, (K, T) in zip(found, cams, strict=True)
        ]
        if model:  # the band's height at this circle (least squares), out of the residuals
            d, b = np.concatenate(res), np.concatenate(found_band)
            k = float(d @ b / max(float(b @ b), 1e-12))
            res = [r - k * fb for r, fb in zip(res, found_band, strict=True)]
        sigma = max(1.4826 * float(np.median(np.abs(np.concatenate(res)))), 0.05)
        inl = [np.abs(r) < config.outlier_sigma * sigma for r in res]
        kept = [p[m] for p, m in zip(found, inl, strict=True)]
        kept_band = [b[m] for b, m in zip(found_band, inl, strict=True)]
        if min(len(k) for k in kept) < config.min_rim_fraction * config.samples:
            raise GeometryFailure("rim fit: too few rim edge points after the robust cut")
        circle = _refit(rig, circle, kept, radius_prior, keep, kept_band if model else None)
        half = config.search_px / 2
    res_all = np.concatenate(
        [
            sampson_distance(p, circle_conic(K, T, circle.center, circle.normal, circle.radius))
            for p, (K, T) in zip(kept, cams, strict=True)
        ]
    )
    return RimFit(
        circle=circle,
        points=(kept[0], kept[1]),
        rim_fraction=fractions,
        rms_px=float(np.sqrt(np.mean(res_all**2))),
    )


def _refit(
    rig: StereoRig,
    circle: Circle3D,
    points: list[np.ndarray],
    radius_prior: tuple[float, float] | None,
    fixed_normal: bool = False,
    band: list[np.ndarray] | None = None,
) -> Circle3D:
    return refine_circle(
        rig,
        circle.center,
        circle.normal,
        circle.radius,
        points[0],
        points[1],
        iterations=6,
        radius_prior=radius_prior,
        fixed_normal=fixed_normal,
        band=None if band is None else (band[0], band[1]),
    )


def projected_observation(
    rig: StereoRig,
    circle: Circle3D,
    camera: Camera,
    points: np.ndarray,
    sigma_px: float,
    source: str,
) -> EllipseObservation:
    """The circle's image in one camera as an `EllipseObservation` (covariance propagated
    from the circle's to first order), with the edge points it was fitted to.

    Raises:
        GeometryFailure: the projection is not an ellipse.
    """
    K, T = rig.intrinsics(camera), rig.cam_from_left(camera)

    def params(x: np.ndarray) -> np.ndarray:
        n = x[3:6] / np.linalg.norm(x[3:6])
        return conic_to_ellipse(circle_conic(K, T, x[:3], n, float(x[6]))).params

    x0 = np.r_[circle.center, circle.normal, circle.radius]
    try:
        e = Ellipse.from_params(params(x0))
        J = np.zeros((5, 7))
        for k in range(7):
            h = 1e-6 * max(1.0, abs(float(x0[k])))
            d = np.zeros(7)
            d[k] = h
            dp = params(x0 + d) - params(x0 - d)
            dp[4] = (dp[4] + math.pi / 2) % math.pi - math.pi / 2  # angle wraps at pi
            J[:, k] = dp / (2 * h)
    except (ConicError, np.linalg.LinAlgError, ValueError) as exc:
        raise GeometryFailure(f"the ring circle's image is not an ellipse ({exc})") from None
    cov = J @ circle.covariance @ J.T
    return EllipseObservation(
        camera=camera,
        center_px=e.center,
        axes_px=[e.a, e.b],
        angle_rad=e.theta,
        conic=e.conic(),
        covariance=0.5 * (cov + cov.T) + 1e-12 * np.eye(5),
        edge_points_px=points,
        sigma_px=max(sigma_px, 0.02),
        source=source,
    )
