"""Per-frame bracket poses (seed 002) through the constant-twist smoother, loosely coupled."""

from __future__ import annotations

import numpy as np
import pytest

from satpose.backend import BackendConfig, MeasurementConfig, MotionConfig, make_estimator
from satpose.datasets.bracket_paper import (
    PAPER_VERTICES_M,
    PAPER_VISIBLE_FRACTION,
    paper_camera,
    paper_times,
    paper_truth,
)
from satpose.datasets.geometry import matrix_to_rotvec
from satpose.datasets.sequence import Calibration
from satpose.frontend.bracket import (
    BracketGeometry,
    simulate_observation,
    solve_bracket,
    to_frame_measurements,
)


@pytest.mark.parametrize("name", ["offline", "online"])
def test_smoother_lowers_the_bracket_pose_error(name: str) -> None:
    """Under 1 m (t = 10-14 s, 41 frames), 0.5 px, exact bracket: the smoothed RMS rotation
    and position errors are below 60 % of the per-frame ones (measured ~30 %, 3 seeds)."""
    cam = paper_camera()
    t_s = paper_times()[100:141]
    truth = paper_truth(t_s)
    geo = BracketGeometry(
        vertices_m=PAPER_VERTICES_M, vertex_sigma_m=0.0, visible_fraction=PAPER_VISIBLE_FRACTION
    )
    config = BackendConfig(
        motion=MotionConfig(
            angular_accel_noise_rad_s2_rthz=0.01, linear_accel_noise_m_s2_rthz=0.02
        ),
        measurements=MeasurementConfig(coupling="loose", robust="none"),
    )
    per_frame, smoothed = [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        est = make_estimator(name, Calibration(left=cam), config)  # type: ignore[arg-type]
        prior = None
        for i, (t, T) in enumerate(zip(t_s, truth, strict=True)):
            obs = simulate_observation(T, PAPER_VERTICES_M, cam.K, 0.2, 0.5, rng)
            r = solve_bracket(obs, geo, cam.K, prior_depths=prior)
            assert r.pose is not None, r.reason
            prior = r.depths_m
            per_frame.append(
                [np.linalg.norm(matrix_to_rotvec(r.pose.R.T @ T.R)), np.linalg.norm(r.pose.t - T.t)]
            )
            est.add(to_frame_measurements(r, i, float(t)))
        out = est.estimate()
        for k, fr in enumerate(out.frame):
            P, T = out.left_cam_from_target[k], truth[int(fr)]
            smoothed.append(
                [np.linalg.norm(matrix_to_rotvec(P.R.T @ T.R)), np.linalg.norm(P.t - T.t)]
            )
    rms_frame = np.sqrt(np.mean(np.square(per_frame), axis=0))
    rms_smooth = np.sqrt(np.mean(np.square(smoothed), axis=0))
    assert np.all(rms_smooth < 0.6 * rms_frame), (rms_smooth, rms_frame)
