"""Signed error terms (`satpose.tools.metrics.signed_errors`) and their bias summary
(`satpose.tools.evaluate.Bias`), against constructed errors (exact oracles)."""

from __future__ import annotations

import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.tools.evaluate import Bias
from satpose.tools.metrics import signed_errors


def _truth(rng: np.random.Generator, n: int) -> list[Rigid3]:
    """Rings 3-8 m ahead, normals tilted up to ~30 deg toward the camera, any spin."""
    out = []
    for _ in range(n):
        t = np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(3.0, 8.0)])
        R = rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))  # z toward the camera
        R = rotvec_to_matrix(np.r_[rng.uniform(-0.5, 0.5, 2), 0.0]) @ R
        R = R @ rotvec_to_matrix(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))
        out.append(Rigid3(R=R, t=t))
    return out


def test_a_depth_and_lateral_offset_is_measured_exactly() -> None:
    rng = np.random.default_rng(0)
    truth = _truth(rng, 20)
    est = []
    for T in truth:
        los = T.t / np.linalg.norm(T.t)
        side = np.cross(los, [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        # 5 cm farther, 2 cm sideways; the body frame turned about its normal (a
        # non-cooperative x axis) must not matter
        spin = rotvec_to_matrix(np.array([0.0, 0.0, 1.0]))
        est.append(Rigid3(R=T.R @ spin, t=T.t + 0.05 * los + 0.02 * side))
    e = signed_errors(est, truth)
    np.testing.assert_allclose(e.depth_m, 0.05, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(e.lateral_m, axis=1), 0.02, atol=2e-3)
    np.testing.assert_allclose(e.tilt_deg, 0.0, atol=1e-9)
    np.testing.assert_allclose(e.normal_deg, 0.0, atol=1e-6)
    b = Bias.of(e)
    assert b.depth_cm == pytest.approx(5.0) and b.depth_sd_cm == pytest.approx(0.0, abs=1e-9)
    assert "depth" in b.defects()


def test_a_normal_tilted_away_from_the_camera_is_a_positive_tilt_error() -> None:
    rng = np.random.default_rng(1)
    truth = _truth(rng, 10)
    est = []
    for T in truth:
        to_cam = -T.t / np.linalg.norm(T.t)
        n = T.R[:, 2]
        axis = np.cross(to_cam, n)  # turning n about this axis moves it away from to_cam
        axis /= np.linalg.norm(axis)
        est.append(Rigid3(R=rotvec_to_matrix(np.radians(2.0) * axis) @ T.R, t=T.t))
    e = signed_errors(est, truth)
    np.testing.assert_allclose(e.tilt_deg, 2.0, atol=1e-9)
    np.testing.assert_allclose(e.normal_deg, 2.0, atol=1e-6)
    np.testing.assert_allclose(e.depth_m, 0.0, atol=1e-12)


def test_zero_mean_noise_is_random_not_a_defect() -> None:
    """Statistical tier: 400 frames of 1 cm depth noise; the mean of 400 samples has sd
    0.05 cm, so |bias| < sd / 3 = 0.33 cm holds with overwhelming probability (6.6 sigma)."""
    rng = np.random.default_rng(2)
    truth = _truth(rng, 400)
    est = [Rigid3(R=T.R, t=T.t * (1 + rng.normal(0.0, 0.01) / np.linalg.norm(T.t))) for T in truth]
    b = Bias.of(signed_errors(est, truth))
    assert b.depth_sd_cm == pytest.approx(1.0, rel=0.15)
    assert b.defects() == []


def test_spec_score_against_constructed_errors() -> None:
    """ESA SPEC: e_t = |dt| / |t| and e_q = rotation angle [rad], each zeroed below its
    threshold (2.173 mm/m, 0.169 deg), score = mean(e_t + e_q); the body-frame offset is
    removed first when given."""
    from satpose.tools.metrics import spec_score

    rng = np.random.default_rng(3)
    truth = _truth(rng, 4)
    big = []
    for T in truth:  # 1 % of the range along x, 1 deg about z
        d = np.array([0.01 * np.linalg.norm(T.t), 0.0, 0.0])
        big.append(Rigid3(R=T.R @ rotvec_to_matrix(np.radians([0.0, 0.0, 1.0])), t=T.t + d))
    s = spec_score(big, truth)
    assert s.translation == pytest.approx(0.01, rel=1e-12)
    assert s.rotation == pytest.approx(np.radians(1.0), rel=1e-9)
    assert s.score == pytest.approx(0.01 + np.radians(1.0), rel=1e-9)
    # below both thresholds: zero
    small = [
        Rigid3(
            R=T.R @ rotvec_to_matrix(np.radians([0.1, 0.0, 0.0])),
            t=T.t + np.array([0.002 * np.linalg.norm(T.t), 0.0, 0.0]),
        )
        for T in truth
    ]
    assert spec_score(small, truth).score == 0.0
    # a constant body-frame rotation of the estimate is removed by the offset
    off = rotvec_to_matrix(np.array([0.0, 0.3, 0.0]))
    turned = [Rigid3(R=T.R @ off.T, t=T.t) for T in truth]
    assert spec_score(turned, truth).rotation > 0.29
    assert spec_score(turned, truth, off).score == pytest.approx(0.0, abs=1e-12)
