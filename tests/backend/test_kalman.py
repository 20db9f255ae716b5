"""The Kalman baseline: oracle against GTSAM's batch smoother on a linear-Gaussian toy, and
spin tracking without angle wrap-around."""

from __future__ import annotations

import gtsam
import numpy as np

from satpose.backend import BackendConfig, MotionConfig, make_estimator
from satpose.backend.kalman import kf_update
from satpose.backend.keys import V, X
from satpose.backend.pose3 import TRANS, block_diagonal
from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.datasets.scenarios import preset
from satpose.frontend.measurements import FrameMeasurements, PoseMeasurement


def test_kf_update_is_the_information_form() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    P = A @ A.T + np.eye(5)
    H = rng.normal(size=(3, 5))
    B = rng.normal(size=(3, 3))
    R = B @ B.T + np.eye(3)
    y = rng.normal(size=3)
    dx, P_new = kf_update(P, y, H, R)
    info = np.linalg.inv(P) + H.T @ np.linalg.solve(R, H)
    np.testing.assert_allclose(P_new, np.linalg.inv(info), atol=1e-12)
    np.testing.assert_allclose(dx, np.linalg.solve(info, H.T @ np.linalg.solve(R, y)), atol=1e-12)


def test_last_filtered_state_equals_the_smoothed_one_on_a_linear_toy() -> None:
    """Identity attitude, no spin: the filter is linear (constant velocity in translation) and
    its last state must equal the last state of GTSAM's batch smoother of the same model
    (WnoaMotionFactorPoint3 + position priors + the first-velocity prior), mean and
    covariance, to rounding."""
    rng = np.random.default_rng(4)
    q, sigma_v0 = 2e-3, 0.05
    # rotation made (numerically) deterministic so that it cannot couple into translation
    motion = MotionConfig(
        angular_accel_noise_rad_s2_rthz=1e-12,
        linear_accel_noise_m_s2_rthz=q,
        first_angular_rate_sigma_rad_s=1e-12,
        first_linear_velocity_sigma_m_s=sigma_v0,
    )
    t_s = np.cumsum(rng.uniform(0.5, 3.0, 25))  # irregular frame times
    pos, vel = np.array([0.2, -0.1, 6.0]), np.array([0.01, 0.0, -0.02])
    frames = []
    for k, t in enumerate(t_s):
        if k:
            dt = t - t_s[k - 1]
            pos, vel = pos + vel * dt, vel + rng.normal(0, q * np.sqrt(dt), 3)
        A = rng.normal(size=(3, 3)) * 0.01
        C_t = A @ A.T + np.eye(3) * 1e-5
        z = pos + rng.multivariate_normal(np.zeros(3), C_t)
        C = block_diagonal(np.eye(3) * 1e-24, C_t)
        pose = None
        if k not in (7, 8):  # two frames without measurements: prediction only
            pose = PoseMeasurement(
                left_cam_from_target=Rigid3(t=z), covariance=C, method="ring+landmarks"
            )
        frames.append((k, t, pose, z, C_t))
    kf = make_estimator("kalman", preset("tumble").rig.calibration(), BackendConfig(motion=motion))
    for k, t, pose, _, _ in frames:
        kf.add(FrameMeasurements(frame=k, t_s=t, pose=pose))
    est = kf.estimate()

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.push_back(
        gtsam.PriorFactorVector(V(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma_v0))
    )
    for k, t, pose, z, C_t in frames:
        values.insert(X(k), z)
        values.insert(V(k), np.zeros(3))
        if pose is not None:
            graph.push_back(
                gtsam.PriorFactorPoint3(X(k), z, gtsam.noiseModel.Gaussian.Covariance(C_t))
            )
        if k:
            graph.push_back(
                gtsam.WnoaMotionFactorPoint3(
                    gtsam.StateData(X(k - 1), V(k - 1), t_s[k - 1]),
                    gtsam.StateData(X(k), V(k), t),
                    np.full(3, q**2),
                )
            )
    result = gtsam.GaussNewtonOptimizer(graph, values).optimize()
    marginals = gtsam.Marginals(graph, result)
    n = len(frames) - 1
    # Linear-Gaussian: the filter's last state is the smoother's last state. Measured
    # agreement ~1e-16 m, ~1e-13 relative on covariances; tolerances leave 1000x margin.
    np.testing.assert_allclose(est.left_cam_from_target[n].t, result.atPoint3(X(n)), atol=1e-12)
    np.testing.assert_allclose(est.twist[n, TRANS], result.atVector(V(n)), atol=1e-13)
    np.testing.assert_allclose(
        est.pose_covariance[n][TRANS, TRANS], marginals.marginalCovariance(X(n)), rtol=1e-10
    )
    np.testing.assert_allclose(
        est.twist_covariance[n][TRANS, TRANS], marginals.marginalCovariance(V(n)), rtol=1e-10
    )


def test_tracks_a_fast_spin_without_wrapping(cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", "paper-docking", 40, 11)  # 10 deg per frame: 400 deg in all
    kf = make_estimator("kalman", case.calib)
    for m in case.measurements:
        kf.add(m)
    est = kf.estimate()
    true_rate = np.degrees(np.linalg.norm(case.twists[-1, :3])) * 5.0  # deg per frame
    # the paper's filter on 0.3 deg poses: within 0.1 deg/frame after 40 frames
    assert abs(est.spin_rate_deg_per_frame()[-1] - true_rate) < 0.1
    err = np.degrees(rotation_angle(est.left_cam_from_target[-1].R.T @ case.poses[-1].R))
    assert err < 1.0  # ~3 sigma of the per-frame pose (0.3 deg)
