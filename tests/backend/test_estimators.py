"""The three estimators end to end on simulated measurements: consistency (NEES), batch vs
iSAM2, missing frames, the first frames, outliers, spin axis and rate.

Estimators start from the measurements (never from the truth). Two kinds of simulated data
(tests/backend/conftest.py):

- ``exact``: a truth drawn from the motion prior and measurements with exactly the Gaussian
  noise each factor assumes — the estimator's model is then exactly right, so its NEES must
  follow the chi-square distribution;
- ``frontend``: the preset's own (deterministic) truth through the frontend's simulator.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from satpose.backend import (
    BackendConfig,
    BackendError,
    Estimate,
    Isam2Config,
    MeasurementConfig,
    OfflineEstimator,
    StepReport,
    make_estimator,
)
from satpose.backend.pose3 import exp, local_error, tangent
from satpose.datasets.config import from_plain
from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.frontend.measurements import FrameMeasurements, LandmarkKind, LandmarkMeasurement

FRAMES = 30


def _config(coupling: str, robust: str = "cauchy") -> BackendConfig:
    return BackendConfig(
        measurements=MeasurementConfig(coupling=coupling, robust=robust)  # type: ignore[arg-type]
    )


def _run(name: str, case, config: BackendConfig, measurements=None):  # type: ignore[no-untyped-def]
    est = make_estimator(name, case.calib, config)  # type: ignore[arg-type]
    for m in case.measurements if measurements is None else measurements:
        est.add(m)
    return est


def _errors(est: Estimate, case) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Right-perturbation pose errors ``Log(T_est^-1 T_true)`` and twist errors
    ``twist_true - twist_est`` (the sign that matches the covariance's perturbation)."""
    e = np.array(
        [local_error(p, T) for p, T in zip(est.left_cam_from_target, case.poses, strict=True)]
    )
    return e, case.twists - est.twist


def _nees(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0])


# --------------------------------------------------------------------------------------------
# Consistency
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("coupling", ["loose", "tight"])
@pytest.mark.parametrize("preset_name", ["paper-docking", "tumble"])
def test_smoother_nees_is_chi_square(preset_name: str, coupling: str, cases) -> None:  # type: ignore[no-untyped-def]
    """Joint NEES of the whole smoothed trajectory. Frames are correlated through the motion
    prior, so the per-frame NEES values are not independent; the joint error over all frames,
    ``e^T P^-1 e`` with ``P`` the joint marginal covariance (6N x 6N poses, 12N x 12N poses
    and twists), is chi-square with 6N (12N) degrees of freedom if the estimator is
    consistent. Pooled over three independent runs (sum of the three, 3x the degrees of
    freedom); 95% interval ``chi2.ppf([0.025, 0.975], dof)``."""
    totals = {"pose": [0.0, 0], "state": [0.0, 0]}
    for seed in (21, 22, 23):
        case = cases("exact", preset_name, FRAMES, seed)
        est = _run("offline", case, _config(coupling, robust="none"))
        assert isinstance(est, OfflineEstimator)
        e, te = _errors(est.estimate(), case)
        for which, err in (("pose", e), ("state", np.hstack([e, te]))):
            v = err.reshape(-1)
            P = est.joint_covariance(which)  # type: ignore[arg-type]
            totals[which][0] += float(v @ np.linalg.solve(P, v))
            totals[which][1] += v.size
    for which, (nees, dof) in totals.items():
        lo, hi = chi2.ppf([0.025, 0.975], dof)
        assert lo < nees < hi, (which, nees / dof, lo / dof, hi / dof)


def _average_nees_upper_bound(P: np.ndarray, dim: int) -> float:
    """97.5% quantile of the frame-averaged NEES ``(1/N) sum_k e_k^T P_kk^-1 e_k`` when
    ``e ~ N(0, P)`` with ``P`` the joint (correlated) covariance, by Satterthwaite's scaled
    chi-square with the exact mean (``dim``) and variance ``2 tr((M P)^2) / N^2``,
    ``M = blockdiag(P_kk^-1)``."""
    n = P.shape[0] // dim
    M = np.zeros_like(P)
    for k in range(n):
        b = slice(dim * k, dim * (k + 1))
        M[b, b] = np.linalg.inv(P[b, b])
    A = M @ P
    var = 2.0 * np.trace(A @ A) / n**2
    scale, dof = var / (2.0 * dim), 2.0 * dim**2 / var
    return float(scale * chi2.ppf(0.975, dof))


@pytest.mark.parametrize("preset_name", ["paper-docking", "tumble"])
def test_average_nees_on_the_presets_is_not_optimistic(preset_name: str, cases) -> None:  # type: ignore[no-untyped-def]
    """On the presets' own truth (deterministic: constant body spin, straight-line centroid)
    the default process noise over-covers what the truth does, so the estimators must be
    consistent or conservative: the average pose and twist NEES stay below the upper end of
    their 95% interval. The interval accounts for the correlation between frames (in tight
    coupling the gauge — the anchor's azimuth — is one error shared by every frame):
    `_average_nees_upper_bound` from the smoother's joint covariance; for the filters (loose,
    weakly correlated) the independent-frame bound ``chi2.ppf(0.975, 6N) / N``."""
    case = cases("frontend", preset_name, FRAMES, 7)
    independent = chi2.ppf(0.975, 6 * FRAMES) / FRAMES
    for coupling in ("loose", "tight"):
        smoother = _run("offline", case, _config(coupling))
        assert isinstance(smoother, OfflineEstimator)
        bounds = {
            "pose": _average_nees_upper_bound(smoother.joint_covariance("pose"), 6),
            "twist": _average_nees_upper_bound(smoother.joint_covariance("twist"), 6),
        }
        online = _run("online", case, _config(coupling))
        outputs = {"offline": (smoother.estimate(), bounds), "online": (online.estimate(), bounds)}
        if coupling == "loose":
            filtered = {"pose": independent, "twist": independent}
            outputs["online filtered"] = (online.filtered(), filtered)  # type: ignore[union-attr]
            outputs["kalman"] = (_run("kalman", case, _config(coupling)).estimate(), filtered)
        for label, (out, hi) in outputs.items():
            e, te = _errors(out, case)
            pose_nees = _nees(e, out.pose_covariance).mean()
            twist_nees = _nees(te, out.twist_covariance).mean()
            assert pose_nees < hi["pose"], (label, coupling, pose_nees, hi)
            assert twist_nees < hi["twist"], (label, coupling, twist_nees, hi)


def test_batch_and_final_isam2_agree(cases) -> None:  # type: ignore[no-untyped-def]
    """Same graph, same optimum. Two tolerance tiers, per component in units of the batch
    estimate's own sigma: without a robust kernel iSAM2 converges to the batch solution up to
    its relinearisation thresholds (0.02 sigma; measured 0.003). With the default Cauchy kernel
    the weights depend continuously on the residuals and iSAM2 recomputes them only for
    variables it relinearises (0.2 sigma; measured 0.12). Sigmas: 1% without kernel
    (measured 0.1%), 5% with Cauchy, whose weights (and so the information) move with those
    residuals (measured up to 3%)."""
    case = cases("frontend", "tumble", FRAMES, 3)
    for robust, tol, sigma_rtol in (("none", 0.02, 0.01), ("cauchy", 0.2, 0.05)):
        for coupling in ("loose", "tight"):
            batch = _run("offline", case, _config(coupling, robust)).estimate()
            final = _run("online", case, _config(coupling, robust)).estimate()
            for i in range(FRAMES):
                d = local_error(batch.left_cam_from_target[i], final.left_cam_from_target[i])
                assert np.all(np.abs(d) < tol * batch.pose_sigmas()[i]), (robust, coupling, i)
                dt = final.twist[i] - batch.twist[i]
                assert np.all(np.abs(dt) < tol * batch.twist_sigmas()[i]), (robust, coupling, i)
            np.testing.assert_allclose(final.pose_sigmas(), batch.pose_sigmas(), rtol=sigma_rtol)
            np.testing.assert_allclose(final.twist_sigmas(), batch.twist_sigmas(), rtol=sigma_rtol)


def test_relinearisation_window_holds_old_variables_and_keeps_the_estimates(cases) -> None:  # type: ignore[no-untyped-def]
    """``relinearize_window``: old states, landmarks and radii keep their linearisation point
    during the online loop, so iSAM2 relinearises fewer variables (measured 624 against 769
    over 30 frames); the filtered estimates move by a fraction of their sigma (measured at
    most 0.45 pose / 0.64 twist sigma; the one-Gauss-Newton-step filter is itself 0.5-0.9
    sigma from the batch optimum of the same frames, window or not); `estimate` relinearises
    everything, so even a window of 0 without the escape bound ends at the batch solution
    (same 0.2-sigma tier as above)."""
    case = cases("frontend", "tumble", FRAMES, 3)
    runs = {}
    for label, online in (
        ("all", Isam2Config(relinearize_window=None)),
        ("window", Isam2Config()),
        ("frozen", Isam2Config(relinearize_window=0, held_relinearize_factor=1e6)),
    ):
        reports: list[StepReport] = []
        est = make_estimator("online", case.calib, BackendConfig(online=online), reports.append)
        for m in case.measurements:
            est.add(m)
        relinearized = sum(r.relinearized or 0 for r in reports if r.step == "add")
        runs[label] = (est.filtered(), est.estimate(), relinearized)  # type: ignore[union-attr]
    assert runs["window"][2] < 0.9 * runs["all"][2]
    assert runs["frozen"][2] < runs["window"][2]
    a, b = runs["all"][0], runs["window"][0]
    d = np.array(
        [
            local_error(p, q)
            for p, q in zip(a.left_cam_from_target, b.left_cam_from_target, strict=True)
        ]
    )
    assert np.max(np.abs(d) / a.pose_sigmas()) < 1.0
    assert np.median(np.max(np.abs(d) / a.pose_sigmas(), axis=1)) < 0.25
    assert np.max(np.abs(a.twist - b.twist) / a.twist_sigmas()) < 1.0
    batch = _run("offline", case, BackendConfig()).estimate()
    for label in ("window", "frozen"):
        final = runs[label][1]
        for i in range(FRAMES):
            d_i = local_error(batch.left_cam_from_target[i], final.left_cam_from_target[i])
            assert np.all(np.abs(d_i) < 0.2 * batch.pose_sigmas()[i]), (label, i)
            dv = final.twist[i] - batch.twist[i]
            assert np.all(np.abs(dv) < 0.2 * batch.twist_sigmas()[i]), (label, i)
        np.testing.assert_allclose(final.pose_sigmas(), batch.pose_sigmas(), rtol=0.05)


# --------------------------------------------------------------------------------------------
# Missing data and the first frames
# --------------------------------------------------------------------------------------------


def _drop(ms: list[FrameMeasurements], frames: set[int]) -> list[FrameMeasurements]:
    return [
        FrameMeasurements(frame=m.frame, t_s=m.t_s, failures=("dropped",))
        if m.frame in frames
        else m
        for m in ms
    ]


def test_kalman_retrodicts_the_frames_before_its_first_pose_with_the_measured_twist(cases) -> None:  # type: ignore[no-untyped-def]
    """Frames before the filter's first pose (the frontend fixes its target frame at the ring's
    second sighting) are predicted backwards from the second pose's state, which knows the
    twist: on `tumble` (several deg per frame) the first two frames, without a pose, stay
    inside their chi2(6) 99.9 % bound; from the first pose alone (zero-mean twist prior)
    they would be that pose, a frame or two of tumble away (checked: far outside)."""
    case = cases("frontend", "tumble", FRAMES, 5)
    ms = _drop(case.measurements, {0, 1})
    est = _run("kalman", case, _config("loose"), ms).estimate()
    e, _ = _errors(est, case)
    nees = _nees(e, est.pose_covariance)
    assert np.all(nees[:2] < chi2.ppf(0.999, 6)), nees[:3]
    # what the first pose alone gives: frame 2's pose for frames 0 and 1
    stale = np.array([local_error(est.left_cam_from_target[2], case.poses[k]) for k in (0, 1)])
    assert np.all(_nees(stale, est.pose_covariance[:2]) > 10 * chi2.ppf(0.999, 6))
    assert np.all(np.linalg.norm(e[:2, :3], axis=1) < 0.2 * np.linalg.norm(stale[:, :3], axis=1))


@pytest.mark.parametrize("coupling", ["loose", "tight"])
def test_frames_without_measurements_are_predicted(coupling: str, cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", "paper-docking", FRAMES, 5)
    gap = {10, 11, 12, 13}
    ms = _drop(case.measurements, {0, 1} | gap | {FRAMES - 1})  # leading, middle, last
    # without the ring's common disparity bias: it adds the same depth variance to every
    # frame (it is constant over the sequence), and this test is about what the gap adds
    config = _config(coupling)
    config = replace(config, measurements=replace(config.measurements, ring_disparity_bias_px=None))
    for name in ("offline", "online", "kalman"):
        est = _run(name, case, config, ms)
        outputs = {"estimate": est.estimate()}
        if name == "online":
            outputs["filtered"] = est.filtered()  # type: ignore[union-attr]
        for label, out in outputs.items():
            assert len(out) == FRAMES and list(out.frame) == list(range(FRAMES))
            s = out.pose_sigmas()
            # uncertainty grows into the gap: the filter's only grows, the smoother's peaks
            # in the middle; and the last frame (no measurement) is less certain than the one
            # before it
            assert s[12, 5] > 1.2 * s[9, 5], (name, label)
            assert s[FRAMES - 1, 5] > s[FRAMES - 2, 5], (name, label)
            e, _ = _errors(out, case)
            nees = _nees(e, out.pose_covariance)
            # predicted frames stay consistent: each within the chi2(6) 99.9% bound
            assert np.all(nees[sorted(gap)] < chi2.ppf(0.999, 6)), (name, label, nees)


@pytest.mark.parametrize("coupling", ["loose", "tight"])
def test_first_frames_are_determined(coupling: str, cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", "tumble", FRAMES, 5)
    cfg = _config(coupling)
    for name in ("offline", "online", "kalman"):
        est = make_estimator(name, case.calib, cfg)  # type: ignore[arg-type]
        with pytest.raises(BackendError, match="no frame with usable measurements"):
            est.estimate()
        est.add(case.measurements[0])
        one = est.estimate()  # one frame: the twist is only its prior
        prior = cfg.motion.first_angular_rate_sigma_rad_s
        assert one.twist_sigmas()[0, 0] == pytest.approx(prior, rel=1e-3)
        est.add(case.measurements[1])
        two = est.estimate()  # two frames determine the twist, to within the pose noise
        assert two.twist_sigmas()[1, 0] < 0.02 * prior
        assert len(two) == 2


def test_frame_times_must_increase(cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", "tumble", FRAMES, 5)
    for name in ("offline", "online", "kalman"):
        est = make_estimator(name, case.calib)  # type: ignore[arg-type]
        est.add(case.measurements[1])
        with pytest.raises(BackendError, match="does not follow"):
            est.add(case.measurements[0])


# --------------------------------------------------------------------------------------------
# Outliers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["offline", "online"])
def test_robust_kernel_down_weights_an_outlier_pose(name: str, cases) -> None:
    case = cases("frontend", "paper-docking", FRAMES, 5)
    k = 15
    m = case.measurements[k]
    assert m.pose is not None
    bad = exp(m.pose.left_cam_from_target, tangent(np.radians([3.0, -2.0, 5.0]), [0.1, -0.05, 0.2]))
    ms = list(case.measurements)
    ms[k] = replace(m, pose=replace(m.pose, left_cam_from_target=bad))
    errors = {}
    for robust in ("none", "huber", "cauchy"):
        out = _run(name, case, _config("loose", robust), ms).estimate()
        e, _ = _errors(out, case)
        errors[robust] = _nees(e, out.pose_covariance)[k]
    # Without a kernel the outlier (5 deg, 23 cm off) drags the estimate far outside its
    # covariance. Huber bounds its pull but, linear in the residual, still moves a frame whose
    # only measurement it is by ~k sigma_motion^2 / sigma_meas; the redescending Cauchy kernel
    # ignores it: the frame stays consistent (chi2(6) 99.9% bound).
    assert errors["none"] > 100
    assert errors["huber"] < 0.7 * errors["none"]
    assert errors["cauchy"] < chi2.ppf(0.999, 6)


# --------------------------------------------------------------------------------------------
# Motion outputs
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset_name", ["paper-docking", "tumble"])
def test_spin_axis_and_rate_are_recovered(preset_name: str, cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", preset_name, FRAMES, 9)
    true_axis = case.twists[0, :3] / np.linalg.norm(case.twists[0, :3])
    dt = float(np.median(np.diff(case.t_s)))
    true_rate = np.degrees(np.linalg.norm(case.twists[0, :3])) * dt  # deg per frame
    for coupling in ("loose", "tight"):
        for name in ("offline", "online"):
            out = _run(name, case, _config(coupling)).estimate()
            # the target: spin rate within 0.1 deg/frame at every frame
            assert np.abs(out.spin_rate_deg_per_frame() - true_rate).max() < 0.1
            axis_err = np.degrees(np.arccos(np.clip(out.spin_axis() @ true_axis, -1, 1)))
            assert axis_err.max() < 2.0, axis_err.max()  # 2 deg: several sigma on tumble
            z = (out.spin_rate_rad_s() - np.linalg.norm(case.twists[:, :3], axis=1)) / (
                out.spin_rate_sigma_rad_s()
            )
            assert np.abs(z).max() < 4.0  # within its own 1-sigma bound x 4


def test_estimate_helpers() -> None:
    w = np.array([0.0, 0.0, np.radians(2.0)])
    T = Rigid3.from_rotvec([0.0, np.pi / 2, 0.0], [0.0, 0.0, 5.0])
    C = np.diag([4e-6, 1e-6, 9e-6, 1e-4, 1e-4, 1e-4])
    est = Estimate(
        frame=[0, 1],
        t_s=[0.0, 5.0],
        left_cam_from_target=(T, T),
        twist=np.tile(np.r_[w, 0.01, 0.0, 0.0], (2, 1)),
        pose_covariance=np.stack([C, C]),
        twist_covariance=np.stack([C, C]),
    )
    np.testing.assert_allclose(est.spin_rate_deg_per_frame(), [10.0, 10.0])
    np.testing.assert_allclose(est.spin_axis()[0], [0, 0, 1])
    np.testing.assert_allclose(est.spin_axis_cam()[0], T.R[:, 2], atol=1e-12)
    np.testing.assert_allclose(est.spin_rate_sigma_rad_s(), [3e-3, 3e-3])  # sigma along z
    np.testing.assert_allclose(est.pose_sigmas()[0], np.sqrt(np.diag(C)))
    np.testing.assert_allclose(est.origin_velocity_cam()[0], T.R @ [0.01, 0, 0], atol=1e-15)
    assert rotation_angle(est.left_cam_from_target[1].R) == pytest.approx(np.pi / 2)
    with pytest.raises(BackendError, match="twist"):
        replace(est, twist=np.zeros((2, 5)))
    with pytest.raises(BackendError, match="NaN"):
        replace(est, pose_covariance=np.full((2, 6, 6), np.nan))


def test_config_loads_by_key_and_rejects_unknown_keys() -> None:
    cfg = from_plain(
        BackendConfig,
        {
            "motion": {"angular_accel_noise_rad_s2_rthz": 2e-4},
            "measurements": {"coupling": "loose", "robust": "cauchy"},
            "online": {"relinearize_rotation": 0.01},
        },
    )
    assert cfg.motion.angular_accel_noise_rad_s2_rthz == 2e-4
    assert cfg.measurements.coupling == "loose" and cfg.measurements.robust == "cauchy"
    with pytest.raises(ConfigError, match="unknown key"):
        from_plain(BackendConfig, {"motion": {"spin": 1.0}})
    with pytest.raises(ConfigError, match="positive"):
        from_plain(BackendConfig, {"motion": {"linear_accel_noise_m_s2_rthz": -1.0}})
    with pytest.raises(ConfigError, match="held_relinearize_factor"):
        from_plain(BackendConfig, {"online": {"held_relinearize_factor": 0.5}})
    with pytest.raises(ConfigError, match="relinearize_window"):
        from_plain(BackendConfig, {"online": {"relinearize_window": -1}})
    with pytest.raises(BackendError, match="unknown estimator"):
        make_estimator("ekf", None)  # type: ignore[arg-type]


def test_hook_reports_every_step(cases) -> None:  # type: ignore[no-untyped-def]
    case = cases("frontend", "tumble", FRAMES, 5)
    ms = _drop(case.measurements[:6], {3})
    for name in ("offline", "online", "kalman"):
        reports: list[StepReport] = []
        est = make_estimator(name, case.calib, _config("tight"), hook=reports.append)  # type: ignore[arg-type]
        for m in ms:
            est.add(m)
        est.estimate()
        adds = [r for r in reports if r.step == "add"]
        assert [r.frame for r in adds] == [m.frame for m in ms]
        assert any("prediction only" in r.notes for r in adds if r.frame == 3)
        assert all(r.timings_ms and min(r.timings_ms.values()) >= 0 for r in reports)
        if name == "online":  # the first frame is solved in batch (warm-up), then iSAM2
            assert any("warm-up" in note for note in adds[0].notes)
            assert all(r.factors > 0 and r.relinearized is not None for r in adds[1:])
        if name == "offline":
            assert [r.step for r in reports][-1] == "optimize" and reports[-1].iterations


# --------------------------------------------------------------------------------------------
# The ring's circles
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["offline", "online"])
def test_inner_and_outer_edge_get_their_own_radius(name: str, cases) -> None:  # type: ignore[no-untyped-def]
    """The frontend may track the rim's inner front edge first (as on the rendered `tumble`)
    and the outer one later: concentric, coplanar, 13% smaller. Each circle gets its own
    radius variable, so the estimate stays consistent even without a robust kernel; one radius
    shared by both circles drags the depth by decimetres."""
    case = cases("frontend", "tumble", FRAMES, 11)
    inner = 0.26 / 0.30
    ms = [
        replace(m, ring=replace(m.ring, radius_m=m.ring.radius_m * inner))
        if m.frame < 6 and m.ring is not None
        else m
        for m in case.measurements
    ]
    errors = {}
    for gap in (0.04, 0.99):  # 0.99: every ring is taken as the same circle
        cfg = BackendConfig(measurements=MeasurementConfig(robust="none", ring_circle_gap=gap))
        reports: list[StepReport] = []
        est = make_estimator(name, case.calib, cfg, hook=reports.append)  # type: ignore[arg-type]
        for m in ms:
            est.add(m)
        out = est.estimate()
        e, _ = _errors(out, case)
        errors[gap] = e
        if gap == 0.04:
            new_circle = [r.frame for r in reports if any("another circle" in n for n in r.notes)]
            assert new_circle == [6]
            # each frame's position within its own covariance (chi2(3), 99.9%)
            pos = _nees(e[:, 3:], out.pose_covariance[:, 3:, 3:])
            assert np.all(pos < chi2.ppf(0.999, 3)), pos.max()
    shared = np.linalg.norm(errors[0.99][:, 3:], axis=1).mean()
    assert shared > 10 * np.linalg.norm(errors[0.04][:, 3:], axis=1).mean()


# --------------------------------------------------------------------------------------------
# Landmarks in the tight graph
# --------------------------------------------------------------------------------------------


def _with_orb(case, tracks: dict[int, np.ndarray], seed: int) -> list[FrameMeasurements]:  # type: ignore[no-untyped-def]
    """The case's measurements plus ORB tracks: track id -> (N, 3) target-frame point per frame
    (NaN where the track is not seen), observed with 0.8 px noise in both images."""
    rng = np.random.default_rng(seed)
    calib = case.calib
    assert calib.right is not None and calib.right_from_left is not None
    out = []
    for k, (m, T) in enumerate(zip(case.measurements, case.poses, strict=True)):
        extra = []
        for tid, pts in tracks.items():
            if not np.all(np.isfinite(pts[k])):
                continue
            P = T.apply(pts[k])
            pl = calib.left.K @ P
            pr = calib.right.K @ calib.right_from_left.apply(P)
            extra.append(
                LandmarkMeasurement(
                    track_id=tid,
                    kind=LandmarkKind.ORB,
                    left_px=pl[:2] / pl[2] + rng.normal(0, 0.8, 2),
                    right_px=pr[:2] / pr[2] + rng.normal(0, 0.8, 2),
                    sigma_px=0.8,
                    point_m=P + rng.normal(0, 0.01, 3),
                    covariance=np.eye(3) * 1e-4,
                )
            )
        out.append(replace(m, landmarks=m.landmarks + tuple(extra)))
    return out


def _panel_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.c_[rng.uniform(-0.5, 0.5, (n, 2)), np.full(n, -0.1)]


def test_landmarks_seen_once_stay_out_of_the_graph(cases) -> None:  # type: ignore[no-untyped-def]
    """A landmark seen in one frame only carries no information on the pose (its three
    coordinates absorb the stereo pixels): it waits for its second sighting and, if none
    comes, never becomes a variable; the smoothed trajectory is the one without it."""
    case = cases("frontend", "paper-docking", FRAMES, 13)
    rng = np.random.default_rng(13)
    tracks = {}
    for tid in range(5000, 5040):  # 40 single sightings, spread over the sequence
        pts = np.full((FRAMES, 3), np.nan)
        pts[(tid * 7) % FRAMES] = _panel_points(rng, 1)[0]
        tracks[tid] = pts
    sizes, estimates = {}, {}
    for label, ms in (("plain", case.measurements), ("with singles", _with_orb(case, tracks, 13))):
        reports: list[StepReport] = []
        est = make_estimator("offline", case.calib, _config("tight"), hook=reports.append)
        for m in ms:
            est.add(m)
        estimates[label] = est.estimate()
        sizes[label] = reports[-1].variables
    assert sizes["with singles"] == sizes["plain"]
    a, b = estimates["plain"], estimates["with singles"]
    for i in range(FRAMES):
        d = local_error(a.left_cam_from_target[i], b.left_cam_from_target[i])
        assert np.all(np.abs(d) < 1e-6 * a.pose_sigmas()[i])


def test_orb_tracks_are_capped_per_frame_longest_first(cases) -> None:  # type: ignore[no-untyped-def]
    """With ``max_orb_per_frame = K`` a frame contributes at most K ORB tracks, the anchor
    and the longest-tracked first, so the same K long tracks carry through the sequence; the
    estimate stays consistent."""
    case = cases("frontend", "tumble", FRAMES, 17)
    rng = np.random.default_rng(17)
    tracks = {}
    for tid in range(6000, 6012):  # 12 tracks through the whole sequence
        tracks[tid] = np.tile(_panel_points(rng, 1)[0], (FRAMES, 1))
    for tid in range(7000, 7030):  # 30 tracks of 3 frames each
        pts = np.full((FRAMES, 3), np.nan)
        start = (tid * 5) % (FRAMES - 3)
        pts[start : start + 3] = _panel_points(rng, 1)[0]
        tracks[tid] = pts
    ms = _with_orb(case, tracks, 17)
    K = 4
    cfg = BackendConfig(measurements=MeasurementConfig(max_orb_per_frame=K))
    est = make_estimator("offline", case.calib, cfg)
    assert isinstance(est, OfflineEstimator)
    for m in ms:
        est.add(m)
    out = est.estimate()
    in_graph = est.builder.landmarks
    orb = {t for t in in_graph if t >= 6000}
    # the first frame's K lowest long tracks win and keep winning (most sightings)
    assert orb == set(range(6000, 6000 + K))
    e, _ = _errors(out, case)
    pose_nees = _nees(e, out.pose_covariance)
    assert np.all(pose_nees < chi2.ppf(0.999, 6)), pose_nees.max()


def _mean_depth_errors(case, measurements, field: str, sigma: float) -> dict:  # type: ignore[no-untyped-def]
    """Mean depth error (along each frame's line of sight) [m] of the offline and online
    smoothers without and with the bias variable ``field`` (standard deviation ``sigma``),
    keyed ``(None | sigma, name)``; with it, each frame's translation NEES must lie below the
    3-dof chi-square 99.9 % bound."""
    out = {}
    for s in (None, sigma):
        config = _config("tight")
        config = replace(config, measurements=replace(config.measurements, **{field: s}))
        for name in ("offline", "online"):
            est = _run(name, case, config, measurements).estimate()
            err = np.array(
                [p.t - T.t for p, T in zip(est.left_cam_from_target, case.poses, strict=True)]
            )
            los = np.array([T.t / np.linalg.norm(T.t) for T in case.poses])
            out[(s, name)] = float(np.mean(np.einsum("ij,ij->i", err, los)))
            if s is not None:
                e, _ = _errors(est, case)
                C = est.pose_covariance[:, 3:, 3:]
                assert np.all(_nees(e[:, 3:], C) < chi2.ppf(0.999, 3)), (field, name)
    return out


def test_common_disparity_bias_is_carried_and_estimated(cases) -> None:  # type: ignore[no-untyped-def]
    """Ring centres measured with a disparity error common to every frame (0.3 px: the ring
    1.3-2 cm too far at 4.5-5.5 m) on a turning target with unbiased landmarks: without the
    bias variable the smoother keeps the ring's depth error; with it the landmarks (rigid in
    the target frame while the bias points along the camera's line of sight) recover the
    depth (measured: mean depth error 1.69 cm without, 0.35 cm with, offline and online), and
    the bias stays inside the estimate's covariance (each frame's translation NEES within the
    3-dof chi-square 99.9 % bound)."""
    case = cases("frontend", "tumble", FRAMES, 4)
    f = float(case.calib.left.K[0, 0])
    b = float(np.linalg.norm(case.calib.right_from_left.t))
    beta = 0.3
    biased = []
    for m in case.measurements:
        if m.ring is not None:
            c = m.ring.center_m
            ring = replace(m.ring, center_m=c + c * float(np.linalg.norm(c)) * beta / (f * b))
            m = replace(m, ring=ring)
        biased.append(m)
    depth_err = _mean_depth_errors(case, biased, "ring_disparity_bias_px", 0.2)
    for name in ("offline", "online"):
        assert depth_err[(None, name)] > 0.008, depth_err  # the bias passes through
        assert abs(depth_err[(0.2, name)]) < 0.4 * depth_err[(None, name)], depth_err


def test_landmark_disparity_bias_is_carried_and_estimated(cases) -> None:  # type: ignore[no-untyped-def]
    """Landmarks whose right-image points are all shifted by one disparity error (0.5 px, as
    a rig whose right camera turned by 0.5 / f since calibration) on a turning target with an
    unbiased ring: without the rig variable the landmarks pull the smoother's depth; with
    ``landmark_disparity_bias_px`` the right camera's yaw absorbs the shift (it moves every
    right-image point alike, while the ring's radius and the turning target fix the depth),
    and each frame's translation NEES stays within the 3-dof chi-square 99.9 % bound."""
    case = cases("frontend", "tumble", FRAMES, 4)
    beta = 0.5
    biased = []
    for m in case.measurements:
        lms = tuple(
            lm
            if lm.right_px is None
            else replace(lm, right_px=np.asarray(lm.right_px, float) + np.array([beta, 0.0]))
            for lm in m.landmarks
        )
        biased.append(replace(m, landmarks=lms))
    depth_err = _mean_depth_errors(case, biased, "landmark_disparity_bias_px", 0.3)
    # measured: mean depth error 2.96 mm without, -0.35 mm with (offline and online)
    for name in ("offline", "online"):
        assert abs(depth_err[(0.3, name)]) < 0.5 * abs(depth_err[(None, name)]), depth_err


class _FailingISAM2:
    """Fault injection: iSAM2 whose ``update`` raises GTSAM's indeterminate-system error for
    the frames in ``fail_at`` (counted by calls) and is the real iSAM2 otherwise."""

    def __init__(self, real, fail_at: set[int]) -> None:  # type: ignore[no-untyped-def]
        self._real, self._fail_at, self.calls = real, fail_at, 0

    def update(self, *args):  # type: ignore[no-untyped-def]
        self.calls += 1
        if self.calls in self._fail_at:
            raise RuntimeError(
                "\\nIndeterminate linear system detected while working near variable\\n7 (x7)."
            )
        return self._real.update(*args)

    def __getattr__(self, name: str):  # type: ignore[no-untyped-def]
        return getattr(self._real, name)


def _online_without_final_updates(case):  # type: ignore[no-untyped-def]
    config = _config("tight")
    return make_estimator(
        "online", case.calib, replace(config, online=replace(config.online, final_updates=0))
    )


def test_an_update_that_raises_restarts_isam2_from_a_batch_solve(cases) -> None:  # type: ignore[no-untyped-def]
    """iSAM2 throwing in one frame's update (nothing dead to drop): the whole graph is solved
    again by Levenberg-Marquardt and iSAM2 restarts there; the frame is estimated, its note
    says so, and the smoothed trajectory is as consistent as without the fault (each frame's
    pose NEES below the 6-dof chi-square 99.9 % bound)."""
    case = cases("frontend", "tumble", FRAMES, 4)
    est = _online_without_final_updates(case)
    notes: list[str] = []
    est.hook = lambda r: notes.extend(r.notes)
    for k, m in enumerate(case.measurements):
        if k == 10:
            assert est._released
            est.isam = _FailingISAM2(est.isam, {1})
        est.add(m)
    assert any("restarted from a batch solve" in n for n in notes), notes
    out = est.estimate()
    e, _ = _errors(out, case)
    assert np.all(_nees(e, out.pose_covariance) < chi2.ppf(0.999, 6))
    f, _ = _errors(est.filtered(), case)
    assert np.all(np.abs(f[:, 3:]) < 0.05), np.abs(f[:, 3:]).max()  # [m]: a frame estimated


def test_a_frame_whose_update_cannot_be_rescued_reports_its_prediction(cases, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The restart failing too: ``add`` raises (the pipeline makes it the frame's failure
    note) but the frame has a filtered row, its constant-twist prediction with the stated
    "unknown" standard deviations (1 rad, 10 m), and the run goes on to an estimate."""
    import satpose.backend.online as online

    case = cases("frontend", "tumble", FRAMES, 4)
    est = _online_without_final_updates(case)
    real_lm = online.levenberg_marquardt
    failed = []
    for k, m in enumerate(case.measurements):
        if k == 10:
            est.isam = _FailingISAM2(est.isam, {1})

            def no_lm(*args, **kwargs):  # type: ignore[no-untyped-def]
                raise RuntimeError("Levenberg-Marquardt failed (injected)")

            monkeypatch.setattr(online, "levenberg_marquardt", no_lm)
        try:
            est.add(m)
        except RuntimeError:
            failed.append(k)
        monkeypatch.setattr(online, "levenberg_marquardt", real_lm)
    assert failed == [10]
    f = est.filtered()
    assert len(f.frame) == len(case.measurements)
    np.testing.assert_allclose(np.sqrt(np.diag(f.pose_covariance[10])), [1, 1, 1, 10, 10, 10])
    e, _ = _errors(f, case)
    assert np.all(np.abs(e[11:, 3:]) < 0.05), np.abs(e[11:, 3:]).max()  # the frames after it
    assert len(est.estimate().frame) == len(case.measurements)


def test_considered_disparity_error_widens_the_covariance_only(cases) -> None:  # type: ignore[no-untyped-def]
    """``ring_disparity_consider_px``: the offline estimate is the one without it (to 1e-9 m
    and rad), every frame's pose covariance grows (the difference is positive semi-definite
    to rounding), and with ring centres that carry a common disparity error of 0.3 px (the
    ring 1.3-2 cm too far at 4.5-5.5 m, `test_common_disparity_bias_is_carried_and_estimated`)
    the considered covariances (sigma 0.3 px) hold every frame's translation error within the
    3-dof chi-square 99.9 % bound, where the plain ones do not."""
    case = cases("frontend", "tumble", FRAMES, 4)
    f = float(case.calib.left.K[0, 0])
    b = float(np.linalg.norm(case.calib.right_from_left.t))
    biased = []
    for m in case.measurements:
        if m.ring is not None:
            c = m.ring.center_m
            ring = replace(m.ring, center_m=c + c * float(np.linalg.norm(c)) * 0.3 / (f * b))
            m = replace(m, ring=ring)
        biased.append(m)
    config = _config("tight")
    plain = _run("offline", case, config, biased).estimate()
    considered_config = replace(
        config, measurements=replace(config.measurements, ring_disparity_consider_px=0.3)
    )
    est = _run("offline", case, considered_config, biased)
    considered = est.estimate()
    assert est.final_note is None
    for p, q in zip(plain.left_cam_from_target, considered.left_cam_from_target, strict=True):
        np.testing.assert_allclose(local_error(p, q), 0.0, atol=1e-9)
    for Cp, Cc in zip(plain.pose_covariance, considered.pose_covariance, strict=True):
        assert np.linalg.eigvalsh(Cc - Cp).min() > -1e-9 * np.abs(Cp).max()
    e, _ = _errors(considered, case)
    bound = chi2.ppf(0.999, 3)
    assert np.any(_nees(e[:, 3:], plain.pose_covariance[:, 3:, 3:]) > bound)
    assert np.all(_nees(e[:, 3:], considered.pose_covariance[:, 3:, 3:]) < bound)


def test_a_failing_considered_covariance_falls_back_to_the_plain_one(cases, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Fault injection: when the considered covariances cannot be had (their marginal raises)
    the offline estimate is still returned, with the plain covariances, and ``final_note``
    (which the run prints) says so."""
    import satpose.backend.offline as offline

    class Failing:
        def __init__(self, *args) -> None:  # type: ignore[no-untyped-def]
            pass

        def marginal(self, key: int) -> np.ndarray:
            raise BackendError("the considered disparity error has no positive variance")

    case = cases("frontend", "tumble", FRAMES, 4)
    config = _config("tight")
    plain = _run("offline", case, config).estimate()
    monkeypatch.setattr(offline, "ConsideredCovariances", Failing)
    considered_config = replace(
        config, measurements=replace(config.measurements, ring_disparity_consider_px=0.3)
    )
    est = _run("offline", case, considered_config)
    out = est.estimate()
    assert est.final_note is not None and "without the considered" in est.final_note
    np.testing.assert_allclose(out.pose_covariance, plain.pose_covariance, rtol=1e-9, atol=0)
