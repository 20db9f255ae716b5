"""The ring's front rim by the stereo depth of its arcs (`satpose.frontend.ring_depth`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from satpose.datasets.geometry import Rigid3
from satpose.frontend.measurements import Camera
from satpose.frontend.rim import rim_samples
from satpose.frontend.ring_depth import FrontArcsConfig, arc_depths, fit_front_arcs
from satpose.frontend.stereo import Circle3D, StereoRig, refine_circle

W, H, F = 640, 480, 940.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIG = StereoRig(K_left=K, K_right=K, right_from_left=Rigid3(R=np.eye(3), t=np.array([-0.3, 0, 0])))
FB = F * 0.3


def _rim(tilt_deg: float = 25.0) -> Circle3D:
    center = np.array([0.1, -0.05, 7.0])
    t = math.radians(tilt_deg)
    normal = np.array([math.sin(t), 0.0, -math.cos(t)])  # toward the cameras
    return Circle3D(center=center, normal=normal, radius=0.5, covariance=np.eye(7) * 1e-8)


def _edges(
    rim: Circle3D, shadow_from: float, shadow_to: float, behind_m: float = 0.08, n: int = 240
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge points of both images: the rim's, except over the angles [from, to) of the
    rim's own parametrisation, where the edge is that of a shadow on a panel ``behind_m``
    behind the rim and 1 cm wider (one 3-D curve, seen by both cameras). Also the mask of
    the shadow's samples."""
    P, rho = rim_samples(rim, n)
    phi = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    shadow = (phi >= shadow_from) & (phi < shadow_to)
    P = P.copy()
    P[shadow] += -behind_m * rim.normal + 0.01 * rho[shadow]
    left, right = RIG.project(P)
    return left, right, shadow


def _depth_error(c: Circle3D, rim: Circle3D) -> float:
    los = rim.center / np.linalg.norm(rim.center)
    return float((c.center - rim.center) @ los)


def test_a_shadow_arc_behind_the_rim_is_dropped_and_the_rim_refitted() -> None:
    """Noise-free: a shadow edge 8 cm behind the rim over a third of the perimeter pulls the
    all-points circle 1-10 cm back; the front-arc refit finds the rim's centre within 1 mm
    and radius within 0.5 mm, and the shadow's points are the ones dropped (at least 90 % of
    them, at most 5 % of the rim's: the arcs straddle the shadow's ends)."""
    rim = _rim()
    left, right, shadow = _edges(rim, 0.3, 0.3 + 2.1)
    start = refine_circle(RIG, rim.center, rim.normal, rim.radius, left, right, sigma_px=0.1)
    assert _depth_error(start, rim) > 0.01
    fit = fit_front_arcs(RIG, start, left, right, FrontArcsConfig())
    assert fit is not None
    assert float(np.linalg.norm(fit.circle.center - rim.center)) < 1e-3
    assert abs(fit.circle.radius - rim.radius) < 5e-4
    dropped = ~fit.left_keep
    assert dropped[shadow].mean() > 0.9, dropped[shadow].mean()
    assert dropped[~shadow].mean() < 0.05 + 2 / 12, dropped[~shadow].mean()


def test_arc_depths_measures_a_shadow_arc_as_behind() -> None:
    """Noise-free, judged against the true plane: the rim's matched points have z = 0
    (1e-6 px) and the shadow's are behind (z > 0)."""
    rim = _rim()
    left, right, shadow = _edges(rim, 0.3, 2.4)
    a = arc_depths(RIG, rim, left, right, Camera.LEFT, FrontArcsConfig())
    on = a.judged & ~shadow
    far = a.judged & shadow
    assert on.sum() > 80 and far.sum() > 30
    # the rim's own points cross the other image's rim curve on the prediction, up to the
    # polyline's chord (240 samples on a 67 px ellipse: < 0.01 px)
    assert np.abs(a.z[on]).max() < 0.01
    assert np.median(a.z[far]) > 0.3  # 8 cm at 7 m: 0.46 px of disparity, times |cos|


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_clean_rim_stays_unbiased(seed: int) -> None:
    """Edge noise 0.15 px, no shadow, 40 draws: arcs dropped by chance only, and the refit's
    depth errors over their stated sigma (the fit's covariance) inside the chi-square(40)
    99.9 % interval, their mean within 4 standard errors of zero."""
    rng = np.random.default_rng(seed)
    rim = _rim(35.0)
    left0, right0, _ = _edges(rim, 0.0, 0.0)
    z, dropped = [], 0
    for _ in range(40):
        left = left0 + rng.normal(0, 0.15, left0.shape)
        right = right0 + rng.normal(0, 0.15, right0.shape)
        start = refine_circle(RIG, rim.center, rim.normal, rim.radius, left, right)
        fit = fit_front_arcs(RIG, start, left, right, FrontArcsConfig())
        c = start if fit is None else fit.circle
        dropped += fit is not None
        los = rim.center / np.linalg.norm(rim.center)
        sigma = math.sqrt(float(los @ c.covariance[:3, :3] @ los))
        z.append(_depth_error(c, rim) / sigma)
    z_arr = np.array(z)
    lo, hi = chi2.ppf([0.0005, 0.9995], 40)
    assert lo < float(z_arr @ z_arr) < hi, float(z_arr @ z_arr)
    assert abs(float(z_arr.mean())) < 4 / math.sqrt(40)
    assert dropped <= 20  # by chance: per arc 0.6 % one-sided at 2.5 sigma, ~16 arcs judged


def test_noisy_shadow_is_removed_from_the_depth() -> None:
    """Edge noise 0.15 px with the shadow of the first test, 30 draws: the all-points depth
    is biased by centimetres; the refit's mean depth error is within 4 standard errors of
    zero, and below a fifth of the all-points bias."""
    rng = np.random.default_rng(7)
    rim = _rim()
    left0, right0, _ = _edges(rim, 0.3, 2.4)
    before, after = [], []
    for _ in range(30):
        left = left0 + rng.normal(0, 0.15, left0.shape)
        right = right0 + rng.normal(0, 0.15, right0.shape)
        start = refine_circle(RIG, rim.center, rim.normal, rim.radius, left, right)
        fit = fit_front_arcs(RIG, start, left, right, FrontArcsConfig())
        assert fit is not None
        before.append(_depth_error(start, rim))
        after.append(_depth_error(fit.circle, rim))
    b, a = np.array(before), np.array(after)
    assert b.mean() > 0.01
    assert abs(a.mean()) < 4 * a.std(ddof=1) / math.sqrt(len(a)), (a.mean(), a.std())
    assert abs(a.mean()) < 0.2 * b.mean()


def test_two_shadows_apart_are_not_one_span_and_the_circle_stands() -> None:
    """Two arcs behind the rim on opposite sides (not one contiguous span) with at most two
    arcs removable: no hypothesis explains them, and the circle stands (None)."""
    rim = _rim()
    P, rho = rim_samples(rim, 240)
    phi = np.linspace(0.0, 2.0 * math.pi, 240, endpoint=False)
    both = ((phi >= 0.3) & (phi < 1.5)) | ((phi >= 3.5) & (phi < 4.7))
    P[both] += -0.08 * rim.normal + 0.01 * rho[both]
    left, right = RIG.project(P)
    start = refine_circle(RIG, rim.center, rim.normal, rim.radius, left, right, sigma_px=0.1)
    assert fit_front_arcs(RIG, start, left, right, FrontArcsConfig(max_span=2)) is None


@pytest.mark.parametrize(
    "field,bad",
    [
        ("sectors", 2),
        ("max_span", 12),
        ("k_sigma", 0.0),
        ("chi2_level", 1.0),
        ("min_cos", 1.0),
        ("gate_px", -1.0),
    ],
)
def test_config_is_checked(field: str, bad: float) -> None:
    with pytest.raises(ValueError, match=f"front_arcs.{field}"):
        FrontArcsConfig(**{field: bad})
