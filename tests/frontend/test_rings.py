"""The `rings` check: pose of a concentric-ring target from its conics."""

from __future__ import annotations

import math

import numpy as np

from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.frontend.conics import circle_to_conic, fit_ellipse_direct
from satpose.frontend.rings import rings_pose

K = np.array([[1500.0, 0.0, 511.5], [0.0, 1500.0, 383.5], [0.0, 0.0, 1.0]])
RADII = (0.04, 0.07, 0.10)


def target_pose(rng: np.random.Generator) -> Rigid3:
    """Ring plane tilted 15-45 deg, 0.8-1.2 m away, somewhere in the view."""
    tilt = math.radians(rng.uniform(15, 45))
    az = rng.uniform(0, 2 * math.pi)
    R = rotvec_to_matrix(np.array([math.cos(az), math.sin(az), 0.0]) * tilt) @ np.diag(
        [1.0, -1.0, -1.0]
    )  # target z toward the camera
    t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.8, 1.2)])
    return Rigid3(R=R, t=t)


def truth_normal(T: Rigid3) -> np.ndarray:
    return T.R[:, 2]


def test_noise_free_recovery() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = target_pose(rng)
        conics = [circle_to_conic(K, T, r) for r in RADII]
        out = rings_pose(K, conics, RADII)
        assert out.center_m is not None, out.reason
        assert np.linalg.norm(out.center_m - T.t) < 1e-9
        assert np.degrees(np.arccos(min(1.0, float(out.normal @ truth_normal(T))))) < 1e-6
        assert out.center_spread_m < 1e-9


def _noisy_conic(T: Rigid3, r: float, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    phi = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    pts = T.apply(np.c_[r * np.cos(phi), r * np.sin(phi), np.zeros_like(phi)])
    uv = pts @ K.T
    uv = uv[:, :2] / uv[:, 2:3] + sigma_px * rng.standard_normal((phi.size, 2))
    e = fit_ellipse_direct(uv)
    c, s = math.cos(e.theta), math.sin(e.theta)
    Rm = np.array([[c, -s], [s, c]])
    A = Rm @ np.diag([1 / e.a**2, 1 / e.b**2]) @ Rm.T
    ctr = e.center
    C = np.zeros((3, 3))
    C[:2, :2] = A
    C[:2, 2] = C[2, :2] = -A @ ctr
    C[2, 2] = ctr @ A @ ctr - 1
    return C


def test_noisy_rings() -> None:
    """0.3 px edge noise, 200 edge points per ring, 40 poses at 0.8-1.2 m: centre error RMS
    below 3 mm and normal error RMS below 0.5 deg (measured 0.2 mm, 0.06 deg); the rings
    agree to better than 3 mm in 95 % of the poses. A 5 % focal-length error changes that
    agreement by only ~5 % (median ratio of spreads): concentric rings do not reveal a
    focal-length error in one view, so the check is the pose against the nominal mounting."""
    rng = np.random.default_rng(1)
    spread, spread_bad, c_err, n_err = [], [], [], []
    K_bad = K.copy()
    K_bad[0, 0] *= 1.05
    K_bad[1, 1] *= 1.05
    for _ in range(40):
        T = target_pose(rng)
        conics = [_noisy_conic(T, r, 0.3, rng) for r in RADII]
        a = rings_pose(K, conics, RADII)
        b = rings_pose(K_bad, conics, RADII)
        assert a.center_m is not None and a.normal is not None and b.center_m is not None
        spread.append(a.center_spread_m)
        spread_bad.append(b.center_spread_m)
        c_err.append(np.linalg.norm(a.center_m - T.t))
        n_err.append(np.degrees(np.arccos(min(1.0, float(a.normal @ truth_normal(T))))))
    assert np.sqrt(np.mean(np.square(c_err))) < 3e-3
    assert np.sqrt(np.mean(np.square(n_err))) < 0.5
    assert np.percentile(spread, 95) < 3e-3
    assert abs(np.median(np.array(spread_bad) / np.array(spread)) - 1.0) < 0.2


def test_bad_input_gives_a_reason() -> None:
    T = target_pose(np.random.default_rng(2))
    C = circle_to_conic(K, T, 0.05)
    assert "two rings" in rings_pose(K, [C], [0.05]).reason
    assert "radii" in rings_pose(K, [C, C], [0.05]).reason
    assert "invalid" in rings_pose(K, [C, np.full((3, 3), np.nan)], [0.05, 0.07]).reason
