"""Seed 004: sky, event simulator, Wahba, five-point degeneracy, rotation graph."""

from __future__ import annotations

import math

import numpy as np
import pytest

from satpose.datasets.event_io import (
    read_events,
    write_events_aedat4,
    write_events_h5,
    write_events_txt,
)
from satpose.datasets.events import Events, EventSensor, Photometry, simulate_events
from satpose.datasets.geometry import matrix_to_rotvec, rotvec_to_matrix
from satpose.datasets.sequence import SequenceError
from satpose.datasets.sky import (
    HIPPARCOS_EPOCH_YR,
    MAS_TO_RAD,
    StarCatalogue,
    load_hipparcos,
    propagate,
    random_rotation,
    star_camera,
)
from satpose.frontend.stars import (
    relative_rotation_bearings,
    relative_rotation_five_point,
    wahba,
)

ARCSEC = math.pi / (180 * 3600)


def test_hipparcos_loads_and_propagates() -> None:
    cat = load_hipparcos(HIPPARCOS_EPOCH_YR, mag_limit=20.0)
    assert len(cat) == 117955  # the whole Hipparcos-2 catalogue
    np.testing.assert_allclose(np.linalg.norm(cat.unit, axis=1), 1.0, atol=1e-12)
    # Barnard's star (HIP 87937): proper motion (-798.58, 10328.12) mas/yr in hip2.dat.
    k0 = cat.index_of(87937)
    later = load_hipparcos(HIPPARCOS_EPOCH_YR + 35.0, mag_limit=20.0)
    moved = math.acos(float(np.clip(cat.unit[k0] @ later.unit[later.index_of(87937)], -1, 1)))
    expected = math.atan(35.0 * math.hypot(-798.58, 10328.12) * MAS_TO_RAD)
    assert moved == pytest.approx(expected, rel=1e-6)  # linear tangent-plane motion
    # A star with zero proper motion stays put.
    u = propagate(np.array([1.0]), np.array([0.3]), np.array([0.0]), np.array([0.0]), 50.0)
    u0 = propagate(np.array([1.0]), np.array([0.3]), np.array([0.0]), np.array([0.0]), 0.0)
    np.testing.assert_allclose(u, u0, atol=1e-15)


SPOT_CAM = star_camera(64, 48, 2.0)
SPOT_PHOT = Photometry()


def _moving_spot_events(threshold: float, seed: int = 0) -> Events:
    """One mag-5 star crossing a 64x48 sensor along its middle row (y = 23.5) in 0.1 s,
    entering and leaving beyond the PSF; no mismatch, refractory period or noise events."""
    cat = StarCatalogue(
        hip=np.array([1]), unit=np.array([[0.0, 0.0, 1.0]]), mag=np.array([5.0]), epoch_yr=2026.0
    )
    half = math.atan(40.0 / SPOT_CAM.fx)  # star from x = cx - 40 px to cx + 40 px

    def attitude(t: np.ndarray) -> np.ndarray:
        ang = half - 2 * half * np.atleast_1d(t) / 0.1
        return rotvec_to_matrix(np.column_stack([0 * ang, ang, 0 * ang]))

    sensor = EventSensor(
        contrast_threshold=threshold, threshold_sigma=0.0, refractory_s=0.0, noise_rate_hz=0.0
    )
    return simulate_events(
        cat, attitude, SPOT_CAM, SPOT_PHOT, sensor, 0.0, 0.1, np.random.default_rng(seed)
    )


def _expected_on_events(threshold: float) -> tuple[int, int]:
    """Exact ON count and the number of pixels that fire: every pixel of row y sees its log
    intensity rise by dL_y and fall back, so it fires floor(dL_y / C) ON events (ESIM, no
    noise). The falling side crosses the same levels except the last one, the starting level
    itself, which is reached but not passed: one OFF event fewer per firing pixel."""
    from scipy.special import ndtr

    s = SPOT_PHOT.psf_sigma_px
    flux = float(SPOT_PHOT.flux_e_s(np.array([5.0]))[0])
    y = np.arange(48)
    wy = ndtr((y + 0.5 - 23.5) / s) - ndtr((y - 0.5 - 23.5) / s)
    wx = ndtr(0.5 / s) - ndtr(-0.5 / s)  # the star centre passes every pixel centre
    n = np.floor(np.log1p(flux * wy * wx / SPOT_PHOT.background_e_s) / threshold)
    return int(64 * n.sum()), int(64 * np.count_nonzero(n))


@pytest.mark.parametrize("threshold", [0.1, 0.2, 0.4])
def test_event_counts_match_contrast_threshold(threshold: float) -> None:
    ev = _moving_spot_events(threshold)
    on_expected, pixels = _expected_on_events(threshold)
    on = int(ev.p.sum())
    off = len(ev) - on
    # Tolerance: the log intensity is sampled every <= 0.1 px, so a pixel's peak can be
    # missed by ~2e-3 in log; no row here has a level that close to its peak: exact.
    assert on == on_expected
    assert off == on_expected - pixels
    assert np.all(np.diff(ev.t_us) >= 0)


def test_event_files_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    ev = _moving_spot_events(0.3)
    write_events_h5(ev, tmp_path / "e.h5")
    write_events_txt(ev, tmp_path / "e.txt")
    write_events_aedat4(ev, tmp_path / "e.aedat4", 64, 48)
    for path in (tmp_path / "e.h5", tmp_path / "e.txt", tmp_path / "e.aedat4"):
        back = read_events(path)
        np.testing.assert_array_equal(back.t_us, ev.t_us)
        np.testing.assert_array_equal(back.x, ev.x)
        np.testing.assert_array_equal(back.p, ev.p)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(SequenceError, match=r"bad\.h5"):
        read_events(tmp_path / "bad.h5")
    (tmp_path / "bad.aedat4").write_bytes(b"not aedat")
    with pytest.raises(SequenceError, match=r"bad\.aedat4"):
        read_events(tmp_path / "bad.aedat4")


def test_wahba_recovers_rotation() -> None:
    rng = np.random.default_rng(3)
    R = random_rotation(rng)
    b = rng.normal(size=(12, 3)) + np.array([0.0, 0.0, 5.0])
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    r = b @ R.T
    R_est, cov = wahba(b, r, 1e-5)
    assert np.abs(matrix_to_rotvec(R.T @ R_est)).max() < 1e-12  # noise-free: exact
    # Noisy: errors over many trials match the covariance (NEES mean ~ 3).
    sigma = 5 * ARCSEC
    nees = []
    for _ in range(300):
        noisy = b + sigma * rng.normal(size=b.shape)  # sigma per tangential axis (QUEST model)
        noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
        R_est, cov = wahba(noisy, r, sigma)
        e = matrix_to_rotvec(R.T @ R_est)
        nees.append(e @ np.linalg.solve(cov, e))
    # chi2(3 * 300) mean bounds at 99 %: 3 +- 2.576 sqrt(6 / 300)
    assert abs(np.mean(nees) - 3.0) < 2.576 * math.sqrt(6 / 300) * 1.2


def test_five_point_is_degenerate_for_stars_at_infinity() -> None:
    rng = np.random.default_rng(5)
    wrong_5pt = 0
    wrong_rot = 0
    trials = 20
    for _ in range(trials):
        b2 = rng.normal(size=(30, 3)) * [0.15, 0.12, 0] + [0, 0, 1]
        b2 /= np.linalg.norm(b2, axis=1, keepdims=True)
        R12 = rotvec_to_matrix(rng.normal(size=3) * math.radians(0.5))
        b1 = b2 @ R12.T + rng.normal(size=b2.shape) * 2 * ARCSEC
        b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
        R_rot, _ = relative_rotation_bearings(b1, b2, 2 * ARCSEC)
        wrong_rot += np.linalg.norm(matrix_to_rotvec(R12.T @ R_rot)) > math.radians(0.01)
        R5 = relative_rotation_five_point(b1, b2, threshold=1e-5)
        err = math.pi if R5 is None else np.linalg.norm(matrix_to_rotvec(R12.T @ R5))
        wrong_5pt += err > math.radians(0.05)
    assert wrong_rot == 0
    assert wrong_5pt >= trials // 4  # the pure-rotation degeneracy shows in many trials


def test_rotation_graph_against_truth() -> None:
    from satpose.backend.rotation import (
        AttitudeWindow,
        OnlineAttitudeSmoother,
        RotationGraphConfig,
        nees,
        smooth_attitudes,
    )

    rng = np.random.default_rng(7)
    R0 = random_rotation(rng)
    w = np.radians([0.2, 1.0, 0.1])
    t = np.arange(200) * 0.005
    truth = np.array([R0 @ rotvec_to_matrix(w * tk) for tk in t])
    cov = np.diag([8.0, 8.0, 40.0]) ** 2 * ARCSEC**2
    L = np.linalg.cholesky(cov)
    windows = []
    for k in range(t.size):
        meas = truth[k] @ rotvec_to_matrix(L @ rng.normal(size=3))  # perturbed, never truth
        windows.append(AttitudeWindow(t_s=float(t[k]), R=meas, cov=cov))
    cfg = RotationGraphConfig(angular_accel_noise_rad_s2_rthz=1e-3, relative_factors=False)
    est = smooth_attitudes(windows, cfg)
    err = matrix_to_rotvec(np.einsum("nji,njk->nik", truth, est.R))
    rms = np.sqrt(np.mean(err**2, axis=0)) / ARCSEC
    # A constant rate over 200 windows: smoothing must beat a single window by far.
    assert rms[0] < 8.0 / 3 and rms[2] < 40.0 / 3
    np.testing.assert_allclose(est.rate_rad_s.mean(0), w, atol=math.radians(0.01))
    assert 1.0 < np.mean(nees(err, est.cov)) < 6.0  # covariance consistent (3 DOF)
    online = OnlineAttitudeSmoother(cfg)
    for win in windows:
        online.add(win)
    est2 = online.estimate()
    err2 = matrix_to_rotvec(np.einsum("nji,njk->nik", truth, est2.R))
    assert np.sqrt(np.mean(err2**2, axis=0))[0] / ARCSEC < 8.0 / 3


def test_tracker_catalogue_cone_matches_the_whole_catalogue() -> None:
    # Tracking projects only the catalogue cone around the last boresight (recomputed after
    # it moves by more than a margin); the stars in view must be those of the whole catalogue.
    from satpose.frontend.stars import StarTracker

    cam = star_camera(640, 480, 20.0)
    tracker = StarTracker(cam)
    full = StarTracker(cam)
    full._cone_cos_radius = -1.0  # the whole sky, recomputed every time
    full._cone_cos_margin = 2.0
    rng = np.random.default_rng(4)
    R = random_rotation(rng)
    recomputed = []
    for step_deg in (0.0, 0.5, 1.0, 1.5, 3.0, 10.0, 90.0):
        R = R @ rotvec_to_matrix(math.radians(step_deg) * np.array([0.6, 0.8, 0.0]))
        axis = tracker._cone_axis
        rows, px = tracker.predicted_stars(R)
        recomputed.append(tracker._cone_axis is not axis)
        rows_all, px_all = full.predicted_stars(R)
        assert rows.size > 5
        np.testing.assert_array_equal(rows, rows_all)
        np.testing.assert_allclose(px, px_all, atol=1e-9)
    # Kept while the boresight stays within the 2 deg margin (0.5, 1.0, 1.5 deg steps: 3 deg
    # in all, recomputed once on the way), recomputed after the large steps.
    assert recomputed[0] and recomputed[-1] and recomputed[-2] and not all(recomputed)


def test_rotation_graph_takes_attitudes_and_rates_at_their_data_times() -> None:
    # An event output at t_k whose data centre on t_k - 20 ms (its attitude moved forward
    # by a rate that misses the jitter): the graph takes that attitude at its own time (on
    # the nearest window, moved by that window's rate) and the span's rate measurement.
    # Noise-free measurements of a wobbling trajectory, graph started from perturbed values:
    # the smoothed windows equal the truth; placing the same attitudes at t_k does not.
    import gtsam

    from satpose.backend.rotation import (
        AttitudeWindow,
        Q,
        RotationGraphConfig,
        W,
        attitude_at_factor,
        smooth_attitudes,
    )

    rng = np.random.default_rng(3)
    R0 = random_rotation(rng)
    w0 = np.radians([0.1, 0.05, 0.0])
    wob = 20 * ARCSEC * 2 * np.pi * 5.0  # 20 arcsec at 5 Hz about x: rate amplitude

    def rate(t: np.ndarray) -> np.ndarray:
        return w0 + np.outer(np.cos(2 * np.pi * 5.0 * t), [wob, 0.0, 0.0])

    fine = np.arange(0, 0.6 + 1e-9, 1e-4)
    truth = [R0]
    for k in range(1, fine.size):
        truth.append(truth[-1] @ rotvec_to_matrix(rate(fine[k - 1 : k] + 5e-5)[0] * 1e-4))
    truth = np.array(truth)

    def at(ts: float) -> np.ndarray:
        return truth[round(ts / 1e-4)]

    t = np.arange(0.05, 0.6, 0.005)
    cov = np.eye(3) * (2 * ARCSEC) ** 2
    windows, shifted = [], []
    for k, tk in enumerate(t):
        tm = tk - 0.02 if k > 8 else tk
        Rm = at(tm)
        windows.append(
            AttitudeWindow(
                t_s=float(tk),
                R=Rm,
                cov=cov,
                t_meas_s=float(tm),
                rate_rad_s=rate(np.array([tm]))[0],
                rate_info=np.eye(3) / (1e-4) ** 2,
            )
        )
        shifted.append(AttitudeWindow(t_s=float(tk), R=Rm, cov=cov))
    cfg = RotationGraphConfig(angular_accel_noise_rad_s2_rthz=0.05, relative_factors=False)
    truth_t = np.array([at(tk) for tk in t])
    errs = []
    for wins in (windows, shifted):
        est = smooth_attitudes(wins, cfg)
        err = matrix_to_rotvec(np.einsum("nji,njk->nik", truth_t, est.R)) / ARCSEC
        errs.append(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1))))
    assert errs[0] < 0.5  # arcsec: the wobble (20 arcsec) followed
    assert errs[1] > 10 * errs[0]  # a 20 ms lag at 5 Hz: several arcsec
    # The factor's Jacobians (whitened by the isotropic 2 arcsec) against central
    # differences on the manifold.
    tau = -0.0021
    f = attitude_at_factor(0, tau, at(0.3), cov)
    Rj = gtsam.Rot3(at(0.3 - tau) @ rotvec_to_matrix(np.array([3e-5, -2e-5, 1e-5])))
    wj = rate(np.array([0.3]))[0] + 1e-3

    def error(R: gtsam.Rot3, w: np.ndarray) -> np.ndarray:
        vals = gtsam.Values()
        vals.insert(Q(0), R)
        vals.insert(W(0), w)
        return np.asarray(f.unwhitenedError(vals))

    vals = gtsam.Values()
    vals.insert(Q(0), Rj)
    vals.insert(W(0), wj)
    A = f.linearize(vals).jacobian()[0] * (2 * ARCSEC)  # un-whitened
    h = 1e-6
    for i, e in enumerate(np.eye(3)):
        dR = (error(Rj.retract(h * e), wj) - error(Rj.retract(-h * e), wj)) / (2 * h)
        dw = (error(Rj, wj + h * e) - error(Rj, wj - h * e)) / (2 * h)
        np.testing.assert_allclose(A[:, i], dR, atol=1e-6)
        np.testing.assert_allclose(A[:, 3 + i], dw, atol=1e-6)
