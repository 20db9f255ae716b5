"""Seed 002's Monte Carlo run (final approach 2 m -> 0 m on the solar-panel bracket): one run
of simulated image points, solved per frame by our P3P solver and the paper's ant colony,
checked against PnP with known strut ends, and smoothed by the backend.

Used by ``benchmarks/bracket_montecarlo.py`` (docs/results/bracket.md) and by the campaign's
``pipeline: bracket-mc`` cells (`satpose.tools.campaign`): one cell is one run
(`run_once` with a seed), its `RunResult` stored as JSON text (`result_to_json`) in the
results table and given back (`result_from_json`) so that the benchmark builds its page from a
campaign. The set-up is the paper's (`satpose.datasets.bracket_paper`, docs/bracket.md).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

from satpose.backend import BackendConfig, MeasurementConfig, MotionConfig, make_estimator
from satpose.datasets.bracket_paper import (
    PAPER_VERTICES_M,
    PAPER_VISIBLE_FRACTION,
    paper_camera,
    paper_times,
    paper_truth,
)
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec
from satpose.datasets.sequence import Calibration
from satpose.frontend.bracket import (
    AntColonyConfig,
    BracketConfig,
    BracketGeometry,
    simulate_observation,
    solve_bracket,
    to_frame_measurements,
)

VERTEX_ERROR_M = 0.010
"""The paper's "vertex coordinate error 10 mm", read as 10 mm RMS 3-D error per vertex."""


def backend_config() -> BackendConfig:
    """Constant-twist smoother tuned to the scenario's known dynamics (docs/bracket.md)."""
    return BackendConfig(
        motion=MotionConfig(
            # wobble: 1 deg at 8 s period -> ~0.011 rad/s^2 peak angular acceleration
            angular_accel_noise_rad_s2_rthz=0.01,
            # straight-line approach seen from the spinning body: |omega x v| ~ 0.02 m/s^2
            linear_accel_noise_m_s2_rthz=0.02,
        ),
        measurements=MeasurementConfig(coupling="loose", robust="none"),
    )


@dataclass
class RunResult:
    t_s: np.ndarray
    err: dict[str, np.ndarray]  # method -> (frames, 6) [rot rad (cam frame), pos m]
    nees: np.ndarray
    cpu: dict[str, list[float]]
    fails: dict[str, int]
    candidates: list[int]


def error_vec(est: Rigid3, true: Rigid3) -> np.ndarray:
    """``[rotation error (rad, rotvec of R_true R_est^T), position error (m)]``."""
    return np.concatenate([matrix_to_rotvec(true.R @ est.R.T), est.t - true.t])


def run_once(
    sigma_px: float,
    vertex_error_m: float,
    seed: int,
    ant: AntColonyConfig | None,
    smooth: bool,
    dt_s: float = 0.2,
) -> RunResult:
    rng = np.random.default_rng(seed)
    cam = paper_camera()
    K = cam.K
    t_s = paper_times(dt_s)
    truth = paper_truth(t_s)
    sigma_v = vertex_error_m / math.sqrt(3.0)
    true_vertices = PAPER_VERTICES_M + sigma_v * rng.standard_normal((3, 3))
    geo = BracketGeometry(
        vertices_m=PAPER_VERTICES_M,
        vertex_sigma_m=sigma_v,
        visible_fraction=PAPER_VISIBLE_FRACTION,
    )
    observations = [
        simulate_observation(T, true_vertices, K, PAPER_VISIBLE_FRACTION, sigma_px, rng)
        for T in truth
    ]
    n = len(t_s)
    err = {}
    cpu: dict[str, list[float]] = {"ours depth": [], "ours frame": [], "ant depth": []}
    fails = {"ours": 0, "ant": 0}
    nees = np.full(n, np.nan)
    cands = []
    e = np.full((n, 6), np.nan)
    frames = []
    prior = None
    for i, (obs, T) in enumerate(zip(observations, truth, strict=True)):
        c0 = time.process_time()
        r = solve_bracket(obs, geo, K, prior_depths=prior)
        cpu["ours frame"].append(time.process_time() - c0)
        frames.append(to_frame_measurements(r, i, float(t_s[i])))
        if r.pose is None or r.covariance is None:
            fails["ours"] += 1
            continue
        prior = r.depths_m
        cands.append(r.candidates)
        e[i] = error_vec(r.pose, T)
        # NEES in the right-perturbation tangent: xi = [Log(R^T R_true), R^T (t_true - t)]
        xi = np.concatenate([matrix_to_rotvec(r.pose.R.T @ T.R), r.pose.R.T @ (T.t - r.pose.t)])
        nees[i] = xi @ np.linalg.solve(r.covariance, xi)
    err["ours per frame"] = e
    # Reference with more information than the paper uses: the strut ends P3, P4 as known
    # model points (exactly 1/5 along the struts) -> 4-point PnP (OpenCV, Levenberg-Marquardt),
    # started from our per-frame pose.
    v = PAPER_VERTICES_M
    f = PAPER_VISIBLE_FRACTION
    model4 = np.array([v[0], v[1], v[1] + f * (v[2] - v[1]), v[0] + f * (v[2] - v[0])])
    e = np.full((n, 6), np.nan)
    for i, (obs, T) in enumerate(zip(observations, truth, strict=True)):
        m = frames[i].pose
        if m is None:
            continue
        start = m.left_cam_from_target
        ok, rv, tv = cv2.solvePnP(
            model4,
            obs.points(),
            K,
            None,
            rvec=cv2.Rodrigues(start.R)[0],
            tvec=start.t.copy().reshape(3, 1),
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if ok:
            e[i] = error_vec(Rigid3(R=cv2.Rodrigues(rv)[0], t=tv.ravel()), T)
    err["reference: PnP with known strut ends"] = e
    # CPU of the depth solve timed the way the colony's is below: its own pass over the frames,
    # without the covariance (which would otherwise run between two solves).
    prior = None
    for obs in observations:
        r = solve_bracket(obs, geo, K, BracketConfig(covariance=False), prior_depths=prior)
        cpu["ours depth"].append(r.solve_cpu_s)
        prior = r.depths_m if r.depths_m is not None else prior
    if ant is not None:
        e = np.full((n, 6), np.nan)
        prior = None
        acfg = BracketConfig(solver="ant-colony", covariance=False, ant=ant)
        for i, (obs, T) in enumerate(zip(observations, truth, strict=True)):
            r = solve_bracket(obs, geo, K, acfg, prior_depths=prior, rng=rng)
            cpu["ant depth"].append(r.solve_cpu_s)
            if r.pose is None:
                fails["ant"] += 1  # keep the last prior: the paper tracks from the last solution
                continue
            prior = r.depths_m
            e[i] = error_vec(r.pose, T)
        err["ant colony per frame"] = e
    if smooth:
        calib = Calibration(left=cam)
        for name in ("offline", "online"):
            est = make_estimator(name, calib, backend_config())
            for fm in frames:
                est.add(fm)
            out = est.estimate()
            e = np.full((n, 6), np.nan)
            for k, fr in enumerate(out.frame):
                e[int(fr)] = error_vec(out.left_cam_from_target[k], truth[int(fr)])
            err[f"ours + {name} smoother"] = e
            if name == "online":
                filt = est.filtered()
                e = np.full((n, 6), np.nan)
                for k, fr in enumerate(filt.frame):
                    e[int(fr)] = error_vec(filt.left_cam_from_target[k], truth[int(fr)])
                err["ours + online filter (causal)"] = e
    return RunResult(t_s=t_s, err=err, nees=nees, cpu=cpu, fails=fails, candidates=cands)


@dataclass(frozen=True, kw_only=True)
class MonteCarloConfig:
    """One Monte Carlo run's settings (the campaign's ``config`` of ``pipeline: bracket-mc``).

    Attributes:
        sigma_px: image noise per point coordinate [px].
        vertex_error_m: RMS 3-D error of each bracket vertex [m] (the model is deformed).
        ant_iterations: iterations of the paper's ant colony (0: not run).
        smooth: also run the backend's offline and online smoothers.
        dt_s: frame interval [s].
    """

    sigma_px: float = 1.0
    vertex_error_m: float = VERTEX_ERROR_M
    ant_iterations: int = AntColonyConfig().iterations
    smooth: bool = True
    dt_s: float = 0.2

    def __post_init__(self) -> None:
        if not (self.sigma_px >= 0 and self.vertex_error_m >= 0 and self.dt_s > 0):
            raise ValueError("sigma_px and vertex_error_m must be >= 0 and dt_s > 0")
        if self.ant_iterations < 0:
            raise ValueError(f"ant_iterations must be >= 0, got {self.ant_iterations}")


def run_config(config: MonteCarloConfig, seed: int) -> RunResult:
    """`run_once` with a `MonteCarloConfig` (the paper's ant colony with its iterations)."""
    ant = None
    if config.ant_iterations > 0:
        ant = replace(AntColonyConfig(), iterations=config.ant_iterations)
    return run_once(
        config.sigma_px, config.vertex_error_m, seed, ant, config.smooth, dt_s=config.dt_s
    )


def result_to_json(r: RunResult) -> str:
    """A `RunResult` as JSON text (NaN as ``NaN``; floats round-trip exactly)."""
    return json.dumps(
        {
            "t_s": r.t_s.tolist(),
            "err": {k: v.tolist() for k, v in r.err.items()},
            "nees": r.nees.tolist(),
            "cpu": {k: [float(x) for x in v] for k, v in r.cpu.items()},
            "fails": r.fails,
            "candidates": [int(c) for c in r.candidates],
        }
    )


def result_from_json(text: str) -> RunResult:
    """The inverse of `result_to_json`."""
    d = json.loads(text)
    return RunResult(
        t_s=np.array(d["t_s"], dtype=float),
        err={k: np.array(v, dtype=float).reshape(-1, 6) for k, v in d["err"].items()},
        nees=np.array(d["nees"], dtype=float),
        cpu={k: list(v) for k, v in d["cpu"].items()},
        fails=dict(d["fails"]),
        candidates=list(d["candidates"]),
    )
