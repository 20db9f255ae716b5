"""The `rings` check: pose of a concentric-ring target from its conics, and its detection in
images drawn exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.frontend.conics import circle_to_conic, fit_ellipse_direct
from satpose.frontend.preprocess import PreparedImage, Undistorter
from satpose.frontend.rings import RingsDetectorConfig, detect_rings, rings_pose, rings_roi

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


# --------------------------------------------------------------------------------------------
# Detection in images drawn exactly (supersampled ray-plane intersection)
# --------------------------------------------------------------------------------------------

BANDS = ((0.010, 0.015), (0.025, 0.030), (0.040, 0.045))
EDGES = np.array([r for b in BANDS for r in b])
K_IMG = np.array([[900.0, 0.0, 319.5], [0.0, 900.0, 239.5], [0.0, 0.0, 1.0]])


def _draw(
    cam_from_rings: Rigid3,
    bands: tuple[tuple[float, float], ...] = BANDS,
    noise: float = 2.0 / 255,
    seed: int = 0,
    plate: float = 0.7,
    band: float = 0.25,
    background: float = 0.05,
    size: tuple[int, int] = (640, 480),
) -> PreparedImage:
    """A grey image of dark bands on a light square plate (half side 65 mm) over a dark
    background, each pixel the mean of 4x4 exact samples, plus Gaussian noise."""
    W, H = size
    s = 4
    off = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(W)[None, :, None, None] + off[None, None, None, :]).astype(np.float64)
    v = (np.arange(H)[:, None, None, None] + off[None, None, :, None]).astype(np.float64)
    Hm = K_IMG @ np.c_[cam_from_rings.R[:, 0], cam_from_rings.R[:, 1], cam_from_rings.t]
    Hi = np.linalg.inv(Hm)
    x = Hi[0, 0] * u + Hi[0, 1] * v + Hi[0, 2]
    y = Hi[1, 0] * u + Hi[1, 1] * v + Hi[1, 2]
    w = Hi[2, 0] * u + Hi[2, 1] * v + Hi[2, 2]
    x, y = x / w, y / w
    rho = np.hypot(x, y)
    val = np.where((np.abs(x) < 0.065) & (np.abs(y) < 0.065) & (w > 0), plate, background)
    for r_in, r_out in bands:
        val = np.where((rho > r_in) & (rho < r_out) & (w > 0), band, val)
    img = val.mean(axis=(2, 3))
    img = img + noise * np.random.default_rng(seed).standard_normal(img.shape)
    gray = np.clip(img, 0, 1).astype(np.float32)
    return Undistorter(PinholeCamera(width=W, height=H, K=K_IMG))(
        np.rint(gray * 255).astype(np.uint8)
    )


def _pose_for_image(rng: np.random.Generator) -> Rigid3:
    """Ring plate 0.45-0.6 m away, tilted 30-55 deg, off the image centre."""
    tilt = math.radians(rng.uniform(30, 55))
    az = rng.uniform(0, 2 * math.pi)
    R = rotvec_to_matrix(np.array([math.cos(az), math.sin(az), 0.0]) * tilt) @ np.diag(
        [1.0, -1.0, -1.0]
    )
    t = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.03, 0.03), rng.uniform(0.45, 0.6)])
    return Rigid3(R=R, t=t)


def test_detect_rings_in_drawn_images() -> None:
    """Six poses, whole-image search (no prior), 2 grey levels of noise: all six band edges
    are used (the smallest, 15 px across, is missed by the ellipse detector in two images and
    recovered from the pose); centre error below 0.6 mm and normal error below 0.15 deg at
    0.45-0.6 m (measured: at most 0.24 mm and 0.042 deg); the propagated sigmas are of the
    size of the errors (errors below 5 sigma + 0.1 mm / 0.05 deg; measured within 2.5 sigma)."""
    rng = np.random.default_rng(3)
    for k in range(6):
        T = _pose_for_image(rng)
        det = detect_rings(_draw(T, seed=k), K_IMG, EDGES)
        assert det.pose.center_m is not None and det.pose.normal is not None, det.reason
        assert det.radii_m == tuple(EDGES)
        c_err = float(np.linalg.norm(det.pose.center_m - T.t))
        n_err = math.degrees(math.acos(min(1.0, float(det.pose.normal @ T.R[:, 2]))))
        assert c_err < 0.6e-3, (k, c_err)
        assert n_err < 0.15, (k, n_err)
        assert c_err < 5 * det.sigma_center_m + 1e-4, (c_err, det.sigma_center_m)
        assert n_err < 5 * det.sigma_normal_deg + 0.05, (n_err, det.sigma_normal_deg)


def test_detect_rings_with_a_band_hidden_and_a_window() -> None:
    """Only the two outer bands painted: four edges, associated with the right radii (the
    size ratios and polarities rule out the inner band's); the nominal-pose window works."""
    T = _pose_for_image(np.random.default_rng(5))
    img = _draw(T, bands=BANDS[1:])
    roi = rings_roi(K_IMG, T, float(EDGES[-1]), img.gray.shape, RingsDetectorConfig())
    det = detect_rings(img, K_IMG, EDGES, roi=roi)
    assert det.pose.center_m is not None, det.reason
    assert det.radii_m == tuple(EDGES[2:])
    assert np.linalg.norm(det.pose.center_m - T.t) < 1e-3


def test_detect_rings_bad_input_gives_a_reason() -> None:
    T = _pose_for_image(np.random.default_rng(7))
    # a dark image
    dark = _draw(T, plate=0.004, band=0.002, background=0.0, noise=0.0)
    assert "dark" in detect_rings(dark, K_IMG, EDGES).reason
    # no rings on the plate
    blank = detect_rings(_draw(T, bands=()), K_IMG, EDGES)
    assert blank.pose.center_m is None and blank.reason
    # one ring edge only (a filled disc): not enough
    one = detect_rings(_draw(T, bands=((1e-6, 0.045),)), K_IMG, EDGES)
    assert one.pose.center_m is None and "two" in one.reason
    # radii that are not a list of increasing positive numbers are a programming error
    with pytest.raises(SatposeError):
        detect_rings(_draw(T), K_IMG, [0.03, 0.01])
