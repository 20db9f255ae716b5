"""Stereo geometry (seed 000 eqs. 2-9): conics, circle reconstruction, triangulation, poses."""

from __future__ import annotations

import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.datasets.scenarios import preset, trajectory
from satpose.datasets.target import geometry
from satpose.frontend.conics import (
    Ellipse,
    circle_to_conic,
    conic_to_ellipse,
    fit_ellipse_direct,
    refine_ellipse,
    sampson_distance,
)
from satpose.frontend.stereo import (
    GeometryFailure,
    StereoRig,
    circle_from_stereo_conics,
    cone_circle_candidates,
    pose_from_ring_landmark,
    refine_circle,
    triangulate,
)


@pytest.fixture(scope="module")
def setup():  # type: ignore[no-untyped-def]
    s = preset("tumble")  # oblique ring views: 15-50 deg from the line of sight
    calib = s.rig.calibration()
    return StereoRig.from_calibration(calib), trajectory(s).left_cam_from_target, geometry(s.target)


def test_ellipse_conic_round_trip() -> None:
    e = Ellipse(cx=321.4, cy=200.2, a=80.0, b=35.5, theta=2.9)
    f = conic_to_ellipse(e.conic())
    np.testing.assert_allclose(f.params, e.params, atol=1e-9)
    assert np.abs(sampson_distance(e.points(64), e.conic())).max() < 1e-9


def test_ellipse_fit_noise_free_and_noisy() -> None:
    e = Ellipse(cx=100.3, cy=80.7, a=50.0, b=30.0, theta=0.4)
    np.testing.assert_allclose(fit_ellipse_direct(e.points(40)).params, e.params, atol=1e-8)
    # Noisy: 200 points, sigma 0.3 px -> the refined centre error is within 3 sigma of its own
    # predicted standard deviation, over 50 seeds (NEES of the 5 parameters ~ chi2(5)).
    nees = []
    for seed in range(50):
        rng = np.random.default_rng(seed)
        pts = e.points(200, phase=rng.uniform(0, 6)) + rng.normal(0, 0.3, (200, 2))
        f, cov, rms = refine_ellipse(pts, fit_ellipse_direct(pts), sigma_px=0.3)
        d = f.params - e.params
        nees.append(d @ np.linalg.solve(cov, d))
        assert rms == pytest.approx(0.3, rel=0.2)
    # mean of 50 chi2(5) draws: 5 +- 3 * sqrt(10 / 50)
    assert abs(np.mean(nees) - 5.0) < 3 * np.sqrt(10 / 50)


@pytest.mark.parametrize("frame", [0, 20, 59])
def test_cone_has_two_circular_sections_one_true(setup, frame: int) -> None:  # type: ignore[no-untyped-def]
    rig, poses, g = setup
    P = poses[frame]
    C = circle_to_conic(rig.K_left, P, g.ring.radius_m)
    cands = cone_circle_candidates(rig.K_left, C)
    angles = sorted(np.degrees(np.arccos(np.clip([n @ P.R[:, 2] for n, _ in cands], -1, 1))))
    assert angles[0] < 1e-5  # one candidate is the true normal (noise-free: exact)
    assert angles[1] > 5.0  # the other is a genuinely different plane (the ambiguity)
    for n, d in cands:
        assert n @ d < 0  # both face the camera


@pytest.mark.parametrize("frame", [0, 30, 59])
def test_circle_from_stereo_conics_is_exact(setup, frame: int) -> None:  # type: ignore[no-untyped-def]
    rig, poses, g = setup
    P = poses[frame]
    Cl = circle_to_conic(rig.K_left, P, g.ring.radius_m)
    Cr = circle_to_conic(rig.K_right, rig.right_from_left @ P, g.ring.radius_m)
    c, n, r = circle_from_stereo_conics(rig, Cl, Cr)
    np.testing.assert_allclose(c, P.t, atol=1e-9)
    np.testing.assert_allclose(n, P.R[:, 2], atol=1e-9)
    assert r == pytest.approx(g.ring.radius_m, abs=1e-9)


def test_refined_circle_is_consistent_with_its_covariance(setup) -> None:  # type: ignore[no-untyped-def]
    rig, poses, _ = setup
    P = poses[10]
    el = conic_to_ellipse(circle_to_conic(rig.K_left, P, 0.3))
    er = conic_to_ellipse(circle_to_conic(rig.K_right, rig.right_from_left @ P, 0.3))
    nees = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        pl = el.points(150, phase=rng.uniform(0, 6)) + rng.normal(0, 0.4, (150, 2))
        pr = er.points(150, phase=rng.uniform(0, 6)) + rng.normal(0, 0.4, (150, 2))
        circ = refine_circle(rig, P.t + 0.02, P.R[:, 2], 0.31, pl, pr, sigma_px=0.4)
        d = np.concatenate([circ.center - P.t, [circ.radius - 0.3]])
        C = circ.covariance[np.ix_([0, 1, 2, 6], [0, 1, 2, 6])]
        nees.append(d @ np.linalg.solve(C, d))
    # chi2(4): mean 4, std of the mean of 40 draws sqrt(8 / 40)
    assert abs(np.mean(nees) - 4.0) < 3 * np.sqrt(8 / 40)


def test_triangulation_exact_and_consistent(setup) -> None:  # type: ignore[no-untyped-def]
    rig, _, _ = setup
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-1, 1, (300, 2)), rng.uniform(3, 8, 300)]
    pl, pr = rig.project(X)
    Xt, _ = triangulate(rig, pl, pr, refine=False)  # plain DLT, eqs. 4-5
    np.testing.assert_allclose(Xt, X, atol=1e-9)
    noisy_l = pl + rng.normal(0, 0.5, pl.shape)
    noisy_r = pr + rng.normal(0, 0.5, pr.shape)
    Xn, cov = triangulate(rig, noisy_l, noisy_r, sigma_px=0.5)
    d = Xn - X
    nees = np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov), d)
    assert abs(nees.mean() - 3.0) < 3 * np.sqrt(6 / 300)  # chi2(3)


def test_epipolar_distance_matches_true_correspondences(setup) -> None:  # type: ignore[no-untyped-def]
    rig, _, _ = setup
    rng = np.random.default_rng(4)
    X = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(3, 8, 20)]
    pl, pr = rig.project(X)
    D = rig.epipolar_distance(pl, pr)
    assert np.abs(np.diag(D)).max() < 1e-8
    assert np.all(np.argmin(D, axis=1) == np.arange(20))


def test_pose_eq9_recovers_truth(setup) -> None:  # type: ignore[no-untyped-def]
    _, poses, g = setup
    P = poses[25]
    corner = P.apply(g.panel_corners[0])
    T = pose_from_ring_landmark(P.t, P.R[:, 2], corner)
    # Target x points toward corner 0 projected on the ring plane: exactly the truth frame.
    assert rotation_angle(T.R.T @ P.R) < 1e-9
    np.testing.assert_allclose(T.t, P.t)
    assert isinstance(T, Rigid3)


@pytest.mark.parametrize("bad", [1e6, -1e6, np.nan, np.inf])
def test_refine_circle_survives_a_diverging_step(setup, monkeypatch, bad: float) -> None:  # type: ignore[no-untyped-def]
    """A Gauss-Newton step that explodes (the OverflowError of `r0 * exp(x[5])` seen on a
    tumbling render) is bounded or refused: a finite circle or a GeometryFailure, never an
    OverflowError."""
    rig, poses, _ = setup
    P = poses[10]
    el = conic_to_ellipse(circle_to_conic(rig.K_left, P, 0.3))
    er = conic_to_ellipse(circle_to_conic(rig.K_right, rig.right_from_left @ P, 0.3))
    rng = np.random.default_rng(5)
    pl = el.points(80) + rng.normal(0, 0.4, (80, 2))
    pr = er.points(80) + rng.normal(0, 0.4, (80, 2))

    def diverging(J: np.ndarray, b: np.ndarray, rcond: object = None) -> tuple[np.ndarray, ...]:
        return (np.full(J.shape[1], bad), np.zeros(0), J.shape[1], np.ones(J.shape[1]))

    monkeypatch.setattr(np.linalg, "lstsq", diverging)
    if not np.isfinite(bad):
        with pytest.raises(GeometryFailure, match="diverged"):
            refine_circle(rig, P.t, P.R[:, 2], 0.3, pl, pr, iterations=6)
        return
    try:
        circ = refine_circle(rig, P.t, P.R[:, 2], 0.3, pl, pr, iterations=6)
    except GeometryFailure as exc:
        assert "diverged" in str(exc)  # e.g. the centre pushed behind the camera
        return
    assert np.all(np.isfinite(circ.center)) and np.isfinite(circ.radius)
    assert np.all(np.isfinite(circ.covariance))
    # 6 steps of at most 0.3 in log(radius): the radius cannot run off to overflow
    assert np.exp(-6 * 0.3) * 0.3 <= circ.radius <= np.exp(6 * 0.3) * 0.3 + 1e-12


@pytest.mark.parametrize("bad", [1e9, np.nan])
def test_refine_ellipse_survives_a_diverging_step(monkeypatch, bad: float) -> None:  # type: ignore[no-untyped-def]
    """A diverging geometric ellipse fit ends in a ConicError or a finite ellipse whose
    axes moved at most one major axis per step, never an exception from the arithmetic."""
    from satpose.frontend.conics import ConicError

    e = Ellipse(cx=100.3, cy=80.7, a=50.0, b=30.0, theta=0.4)
    pts = e.points(60) + np.random.default_rng(6).normal(0, 0.3, (60, 2))

    def diverging(J: np.ndarray, b: np.ndarray, rcond: object = None) -> tuple[np.ndarray, ...]:
        return (np.full(J.shape[1], bad), np.zeros(0), J.shape[1], np.ones(J.shape[1]))

    monkeypatch.setattr(np.linalg, "lstsq", diverging)
    try:
        f, cov, _ = refine_ellipse(pts, e, iterations=3)
    except ConicError as exc:
        assert "diverged" in str(exc) or "singular" in str(exc)
        return
    assert np.isfinite(bad)
    assert np.all(np.isfinite(f.params)) and np.all(np.isfinite(cov)) and f.a <= 50.0 * 2**3
