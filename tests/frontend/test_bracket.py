"""Seed 002's bracket pose: exact recovery, noise statistics, degenerate views, bad input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from satpose.datasets.bracket_paper import (
    PAPER_VERTICES_M,
    PAPER_VISIBLE_FRACTION,
    PaperMotion,
    paper_camera,
    paper_times,
    paper_truth,
)
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import (
    Rigid3,
    absolute_orientation,
    matrix_to_rotvec,
    rotvec_to_matrix,
)
from satpose.frontend.bracket import (
    BracketConfig,
    BracketGeometry,
    BracketObservation,
    BracketResult,
    ant_colony_depths,
    bracket_image_points,
    choose_depths,
    depth_candidates_batch,
    p3p_depths,
    pose_information_bound,
    quartic_roots,
    quartic_roots_batch,
    simulate_observation,
    solve_bracket,
    strut_apex,
    to_frame_measurements,
)
from satpose.frontend.measurements import PoseMethod

K = paper_camera().K
GEO = BracketGeometry(
    vertices_m=PAPER_VERTICES_M, vertex_sigma_m=0.0, visible_fraction=PAPER_VISIBLE_FRACTION
)


def tangent_error(est: Rigid3, true: Rigid3) -> np.ndarray:
    """``xi`` with ``T_true = T_est Exp(xi)`` to first order: ``[rotation, translation]``."""
    return np.concatenate([matrix_to_rotvec(est.R.T @ true.R), est.R.T @ (true.t - est.t)])


def true_depths(T: Rigid3) -> np.ndarray:
    return T.apply(PAPER_VERTICES_M)[:, 2]


def test_quartic_roots_match_numpy() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        c = rng.normal(size=5)
        ours = np.array(quartic_roots(*c))
        # every returned value is a root (relative residual; Ferrari loses ~1e-6 at worst)
        scale = np.abs(c).max() * np.maximum(1.0, np.abs(ours)) ** 4
        assert np.all(np.abs(np.polyval(c, ours)) / scale < 1e-5)
        # and every numpy root is among them
        ref = np.roots(c)
        assert np.all(np.min(np.abs(ref[:, None] - ours[None, :]), axis=1) < 1e-3)


def test_noise_free_recovery_along_the_paper_trajectory() -> None:
    """Noise-free: every frame exact to 1e-9 (tight), without a prior (strut-fraction check)."""
    t_s = paper_times()[::10]
    rng = np.random.default_rng(1)
    for T in paper_truth(t_s):
        obs = simulate_observation(T, PAPER_VERTICES_M, K, PAPER_VISIBLE_FRACTION, 0.0, rng)
        r = solve_bracket(obs, GEO, K)
        assert r.pose is not None, r.reason
        xi = tangent_error(r.pose, T)
        assert np.linalg.norm(xi[:3]) < 1e-9
        assert np.linalg.norm(xi[3:]) < 1e-9
        np.testing.assert_allclose(r.depths_m, true_depths(T), atol=1e-9)
        # eq. 9 satisfied and more than one admissible P3P solution found (the mirror one)
        assert r.depth_cost_m < 1e-10
        assert r.candidates >= 1


def test_p3p_returns_the_true_depths_among_its_solutions() -> None:
    rng = np.random.default_rng(2)
    for _ in range(30):
        T = Rigid3(
            R=rotvec_to_matrix(rng.normal(scale=0.4, size=3)),
            t=np.array([-1.0, -0.9, 2.0]) + rng.normal(scale=0.2, size=3),
        )
        pts = bracket_image_points(T, PAPER_VERTICES_M, K, 0.2)
        p5, _ = strut_apex(pts)
        rays = np.c_[np.array([pts[0], pts[1], p5]), np.ones(3)] @ np.linalg.inv(K).T
        sols = p3p_depths(rays, GEO.sides_m)
        assert 1 <= len(sols) <= 4
        assert np.min(np.linalg.norm(sols - true_depths(T), axis=1)) < 1e-9


def test_prior_selects_the_tracked_solution() -> None:
    T = PaperMotion().cam_from_target(12.0)
    obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(3))
    prior = true_depths(T) + np.array([0.01, -0.01, 0.02])  # the previous frame, 1-2 cm off
    no_fraction = BracketGeometry(vertices_m=PAPER_VERTICES_M, vertex_sigma_m=0.0)
    r = solve_bracket(obs, no_fraction, K, prior_depths=prior)
    assert r.pose is not None and r.candidates == 2 and r.selected_by == "prior"
    assert np.linalg.norm(r.pose.t - T.t) < 1e-9
    # Without prior and without the visible fraction the mirror solution cannot be excluded.
    amb = solve_bracket(obs, no_fraction, K)
    assert amb.pose is not None and amb.ambiguous


def test_ant_colony_converges_near_the_solution() -> None:
    """Noise-free, interval centred 3 cm off the truth: the paper's 500 ants x 10 iterations
    land within 6 mm RMS of the true depths (the search's resolution, ~4 mm measured: the
    local step is omega / N = 1 mm at the last iteration and the global jumps rarely help)."""
    T = PaperMotion().cam_from_target(14.0)
    obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(4))
    prior = true_depths(T) + np.array([0.03, -0.02, 0.01])
    errs = []
    for seed in range(5):
        r = solve_bracket(
            obs,
            GEO,
            K,
            BracketConfig(solver="ant-colony", covariance=False),
            prior_depths=prior,
            rng=np.random.default_rng(seed),
        )
        assert r.pose is not None, r.reason
        errs.append(r.depths_m - true_depths(T))
    assert math.sqrt(np.mean(np.square(errs))) < 6e-3


def test_ant_colony_cost_decreases() -> None:
    T = PaperMotion().cam_from_target(8.0)
    pts = bracket_image_points(T, PAPER_VERTICES_M, K, 0.2)
    p5, _ = strut_apex(pts)
    rays = np.c_[np.array([pts[0], pts[1], p5]), np.ones(3)] @ np.linalg.inv(K).T
    d0 = true_depths(T)
    costs = []
    for it in (1, 10):
        cfg = BracketConfig(solver="ant-colony").ant
        _, c = ant_colony_depths(
            rays,
            GEO.sides_m,
            d0 - 0.05,
            d0 + 0.05,
            replace(cfg, iterations=it),
            np.random.default_rng(0),
        )
        costs.append(c)
    assert costs[1] < costs[0]


def test_absolute_orientation_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        R = rotvec_to_matrix(rng.normal(size=3))
        t = rng.normal(size=3)
        model = rng.normal(size=(4, 3))
        Re, te = absolute_orientation(model, model @ R.T + t)
        np.testing.assert_allclose(Re, R, atol=1e-10)
        np.testing.assert_allclose(te, t, atol=1e-10)
        assert np.linalg.det(Re) > 0


@pytest.mark.parametrize(("t_s", "sigma_px", "vertex_m"), [(15.0, 1.0, 0.0), (5.0, 0.5, 0.005)])
def test_noisy_errors_match_the_covariance(t_s: float, sigma_px: float, vertex_m: float) -> None:
    """300 noisy trials at one pose: mean NEES (6 dof) inside the two-sided 99.9 % chi2 bounds
    of the mean of 300 chi2(6) variables, and the per-axis sample std within 15 % of the
    predicted one."""
    T = PaperMotion().cam_from_target(t_s)
    geo = BracketGeometry(
        vertices_m=PAPER_VERTICES_M, vertex_sigma_m=vertex_m, visible_fraction=0.2
    )
    rng = np.random.default_rng(6)
    n = 300
    xis, nees = [], []
    for _ in range(n):
        true_vertices = PAPER_VERTICES_M + vertex_m * rng.standard_normal((3, 3))
        obs = simulate_observation(T, true_vertices, K, 0.2, sigma_px, rng)
        r = solve_bracket(obs, geo, K)
        assert r.pose is not None and r.covariance is not None, r.reason
        xi = tangent_error(r.pose, T)
        xis.append(xi)
        nees.append(xi @ np.linalg.solve(r.covariance, xi))
    lo, hi = chi2.ppf([0.0005, 0.9995], 6 * n) / n
    assert lo < np.mean(nees) < hi, np.mean(nees)
    ratio = np.std(xis, axis=0) / np.sqrt(np.diag(r.covariance))
    assert np.all(np.abs(ratio - 1) < 0.15), ratio


def test_edge_on_bracket_gives_a_reason() -> None:
    """The bracket's plane through the camera centre: all points on one image line."""
    Rx90 = rotvec_to_matrix(np.array([math.pi / 2, 0.0, 0.0]))
    T = Rigid3(R=Rx90, t=np.array([-1.0, 0.5, 2.0]))  # camera y of every vertex = 0
    obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(7))
    r = solve_bracket(obs, GEO, K)
    assert r.pose is None and "edge-on" in r.reason
    # Nearly edge-on (0.5 deg): the strut lines meet at a tiny angle and the frame is refused.
    T2 = Rigid3(R=rotvec_to_matrix(np.array([math.radians(89.5), 0.0, 0.0])), t=T.t)
    obs2 = simulate_observation(T2, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(7))
    _, angle = strut_apex(obs2.points())
    assert math.degrees(float(angle)) < BracketConfig().min_strut_angle_deg
    r2 = solve_bracket(obs2, GEO, K)
    assert r2.pose is None and "edge-on" in r2.reason
    fm = to_frame_measurements(r2, 3, 0.3)
    assert fm.pose is None and fm.failures and "edge-on" in fm.failures[0]


@pytest.mark.parametrize("bad", ["p3_px", "p1_px", "nan"])
def test_missing_points_give_a_reason(bad: str) -> None:
    T = PaperMotion().cam_from_target(10.0)
    pts = bracket_image_points(T, PAPER_VERTICES_M, K, 0.2)
    kw = dict(zip(("p1_px", "p2_px", "p3_px", "p4_px"), pts, strict=True))
    if bad == "nan":
        kw["p4_px"] = np.array([np.nan, 3.0])
        name = "p4_px"
    else:
        kw[bad] = None
        name = bad
    r = solve_bracket(BracketObservation(**kw), GEO, K)
    assert r.pose is None and "missing" in r.reason and name in r.reason


def test_bad_geometry_raises_a_satpose_error() -> None:
    with pytest.raises(SatposeError, match="collinear"):
        BracketGeometry(vertices_m=[[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(SatposeError, match="solver"):
        BracketConfig(solver="newton")  # type: ignore[arg-type]


def test_frame_measurement_carries_pose_and_covariance() -> None:
    T = PaperMotion().cam_from_target(10.0)
    obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.5, np.random.default_rng(8))
    geo = BracketGeometry(vertices_m=PAPER_VERTICES_M, visible_fraction=0.2)
    r = solve_bracket(obs, geo, K)
    fm = to_frame_measurements(r, 5, 0.5)
    assert fm.pose is not None and fm.pose.method == PoseMethod.BRACKET
    assert np.all(np.linalg.eigvalsh(fm.pose.covariance) > 0)


def test_singular_covariance_becomes_a_failure() -> None:
    T = PaperMotion().cam_from_target(10.0)
    obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(9))
    r = solve_bracket(obs, GEO, K)
    assert r.pose is not None
    singular = BracketResult(pose=r.pose, covariance=np.zeros((6, 6)))
    fm = to_frame_measurements(singular, 0, 0.0)
    assert fm.pose is None and "singular" in fm.failures[0]


def test_batched_quartic_roots_match_the_scalar_ones() -> None:
    rng = np.random.default_rng(11)
    coeffs = rng.normal(size=(200, 5))
    batch = quartic_roots_batch(coeffs)
    for c, roots in zip(coeffs, batch, strict=True):
        ref = np.sort_complex(np.roots(c))
        # each numpy root has one of ours within 1e-6 (relative to the root's size)
        gap = np.min(np.abs(ref[:, None] - roots[None, :]), axis=1)
        assert np.all(gap <= 1e-6 * np.maximum(1.0, np.abs(ref)))


def test_batched_depth_solve_equals_the_frame_by_frame_solver() -> None:
    """Offline batch (candidates for all frames at once, then the choice by the previous frame)
    gives the same depths as `solve_bracket` frame by frame, noise 1 px."""
    rng = np.random.default_rng(12)
    truth = paper_truth(paper_times(0.5))
    obs = [simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 1.0, rng) for T in truth]
    cands, fr = depth_candidates_batch(np.array([o.points() for o in obs]), K, GEO.sides_m)
    prior_row = np.full((1, 3), np.nan)
    cfg = BracketConfig(covariance=False)
    prior = None
    for i, o in enumerate(obs):
        d, count = choose_depths(cands[i : i + 1], fr[i : i + 1], prior_row, GEO.visible_fraction)
        r = solve_bracket(o, GEO, K, cfg, prior_depths=prior)
        assert r.depths_m is not None and count[0] == r.candidates
        np.testing.assert_allclose(d[0], r.depths_m, atol=1e-9)
        prior, prior_row = r.depths_m, d


@pytest.mark.parametrize("vertex_sigma_m", [0.0, 0.004])
def test_information_bound_equals_the_solver_covariance(vertex_sigma_m: float) -> None:
    """Six image numbers fix six pose parameters: the Cramer-Rao bound with the strut ends'
    positions unknown equals our solver's propagated covariance (ours is efficient), and
    knowing the strut ends can only lower it."""
    geo = replace(GEO, vertex_sigma_m=vertex_sigma_m)
    for t in (3.0, 12.0, 18.0):
        T = PaperMotion().cam_from_target(t)
        obs = simulate_observation(T, PAPER_VERTICES_M, K, 0.2, 0.0, np.random.default_rng(0))
        r = solve_bracket(replace(obs, sigma_px=1.0), geo, K, prior_depths=true_depths(T))
        assert r.covariance is not None
        A = np.kron(np.eye(2), T.R)  # right perturbation -> camera-frame (left) errors
        cov = A @ r.covariance @ A.T
        bound = pose_information_bound(T, geo, K, 0.2, 1.0)
        np.testing.assert_allclose(np.diag(cov), np.diag(bound), rtol=1e-3)
        known = pose_information_bound(T, geo, K, 0.2, 1.0, known_ends=True)
        assert np.linalg.eigvalsh(bound - known).min() > -1e-12 * np.trace(bound)
