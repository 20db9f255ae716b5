"""The spin-rate factor: residual, analytic Jacobian against central differences, and the
spin rate of stereo tracking tightened by one camera's spin-rate measurements.

Tolerances: Jacobians to 1e-7 (central differences with a 1e-6 step on a smooth function).
Fusion: with a constant true rate and a process noise far below the measurements', the
smoother's information on ``|omega|`` adds up, ``1/s_with^2 ~ 1/s_without^2 + k/s_spin^2`` for
``k`` independent spin factors; the estimator's own sigma must match that within 15% (the
motion prior lets the rate vary a little between the factors) and the error stay within 3
sigma.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import gtsam
import numpy as np
import pytest

from satpose.backend import BackendConfig, BackendError, MeasurementConfig, make_estimator
from satpose.backend.factors import spin_rate_factor
from satpose.backend.keys import V
from satpose.datasets.scenarios import preset, trajectory
from satpose.datasets.sequence import Calibration
from satpose.datasets.target import geometry
from satpose.frontend.measurements import FrameMeasurements, SpinRateMeasurement, SpinStatus
from satpose.frontend.simulate import SimulationConfig, simulate_measurements

WINDOW = 5  # frames per simulated spin window


def spin(rate: float, sigma: float, t0: float, t1: float) -> SpinRateMeasurement:
    return SpinRateMeasurement(
        rate_rad_s=rate,
        sigma_rad_s=sigma,
        status=SpinStatus.OK,
        window_start_s=t0,
        window_end_s=t1,
        samples=WINDOW,
    )


def test_residual_and_jacobian(jacobians: tuple[Callable[..., np.ndarray], ...]) -> None:
    analytic, numerical = jacobians
    rng = np.random.default_rng(0)
    cfg = MeasurementConfig(robust="none")
    for _ in range(5):
        twist = rng.normal(size=6) * [0.3, 0.3, 0.3, 0.1, 0.1, 0.1]
        m = spin(0.2, 0.01, 0.0, 4.0)
        f = spin_rate_factor(m, 3, cfg)
        values = gtsam.Values()
        values.insert(V(3), twist)
        np.testing.assert_allclose(
            f.unwhitenedError(values), [np.linalg.norm(twist[:3]) - 0.2], atol=1e-15
        )
        np.testing.assert_allclose(analytic(f, values), numerical(f, values), atol=1e-7)
        assert np.allclose(analytic(f, values)[0, 3:], 0.0)


def test_zero_rate_takes_a_subgradient() -> None:
    f = spin_rate_factor(spin(0.2, 0.01, 0.0, 4.0), 0, MeasurementConfig(robust="none"))
    values = gtsam.Values()
    values.insert(V(0), np.zeros(6))
    A, _ = f.linearize(values).jacobian()
    np.testing.assert_allclose(A / A[0, 0], [[1.0, 0, 0, 0, 0, 0]])
    np.testing.assert_allclose(f.unwhitenedError(values), [-0.2])


def test_refused_measurement_is_not_a_factor() -> None:
    m = SpinRateMeasurement(
        rate_rad_s=math.nan,
        sigma_rad_s=math.nan,
        status=SpinStatus.TOO_SLOW,
        reason="too slow",
        window_start_s=0.0,
        window_end_s=4.0,
        samples=5,
    )
    with pytest.raises(BackendError, match="refused"):
        spin_rate_factor(m, 0, MeasurementConfig())


def _with_spin(
    ms: list[FrameMeasurements], rate: float, sigma: float, rng: np.random.Generator, sliding: bool
) -> list[FrameMeasurements]:
    """Attach a spin measurement (truth + N(0, sigma)) to every WINDOW-th frame, or to every
    frame from the first full window on (``sliding``: overlapping windows)."""
    out = []
    for k, m in enumerate(ms):
        if k >= WINDOW - 1 and (sliding or (k + 1) % WINDOW == 0):
            t0 = ms[k - WINDOW + 1].t_s
            m = replace(m, spin=spin(rate + rng.normal(0.0, sigma), sigma, t0, m.t_s))
        out.append(m)
    return out


@dataclass(frozen=True)
class NoisyTumble:
    calib: Calibration
    rate: float  # true |omega| [rad/s]
    measurements: list[FrameMeasurements]


@pytest.fixture(scope="module")
def noisy_tumble() -> NoisyTumble:
    """tumble (1 deg/s, 0.5 Hz) over 16 frames, stereo measurements with 3 px noise."""
    s = replace(preset("tumble"), frames=16)
    tr = trajectory(s)
    ms = simulate_measurements(
        list(tr.left_cam_from_target),
        tr.t_s,
        s.rig.calibration(),
        geometry(s.target),
        SimulationConfig(sigma_px=3.0),
        seed=3,
    )
    return NoisyTumble(s.rig.calibration(), float(np.linalg.norm(tr.angular_velocity[0])), ms)


def _run(
    name: str, case: NoisyTumble, ms: list[FrameMeasurements], **kw: object
) -> tuple[np.ndarray, np.ndarray]:
    cfg = BackendConfig(measurements=MeasurementConfig(**kw))  # type: ignore[arg-type]
    est = make_estimator(name, case.calib, cfg)  # type: ignore[arg-type]
    for m in ms:
        est.add(m)
    e = est.estimate()
    return e.spin_rate_rad_s(), e.spin_rate_sigma_rad_s()


@pytest.mark.parametrize("estimator", ["offline", "online"])
def test_spin_rate_tightens_stereo_tracking(noisy_tumble: NoisyTumble, estimator: str) -> None:
    """Three spin-rate measurements of 0.01 deg/s each (disjoint 5-frame windows) on top of
    noisy stereo tracking: the estimate's rate sigma drops as the information adds up, and
    the rate stays within 3 sigma of the truth."""
    case = noisy_tumble
    sigma = math.radians(0.01)
    rng = np.random.default_rng(7)
    with_spin = _with_spin(case.measurements, case.rate, sigma, rng, sliding=False)
    k = sum(m.spin is not None for m in with_spin)
    assert k == 3
    r0, s0 = _run(estimator, case, case.measurements)
    r1, s1 = _run(estimator, case, with_spin)
    after = slice(WINDOW - 1, None)
    predicted = 1.0 / np.sqrt(1.0 / s0[after] ** 2 + k / sigma**2)
    assert np.all(s1[after] < 0.5 * s0[after])
    np.testing.assert_allclose(s1[after], predicted, rtol=0.15)
    assert np.all(np.abs(r1[after] - case.rate) < 3.0 * s1[after])
    assert np.all(np.abs(r0 - case.rate) < 3.0 * s0)


def test_overlapping_windows_count_once(noisy_tumble: NoisyTumble) -> None:
    """Sliding windows (one estimate per frame, sharing frames) add nothing beyond the disjoint
    windows among them: the graph uses only windows that do not overlap the last one used.
    Refused measurements and ``spin_rate = False`` leave the estimate as without spin."""
    case = noisy_tumble
    sigma = math.radians(0.01)
    sliding = _with_spin(case.measurements, case.rate, sigma, np.random.default_rng(1), True)
    used = []
    last_end = -math.inf
    for m in sliding:
        if m.spin is not None and m.spin.window_start_s > last_end:
            used.append(m)
            last_end = m.spin.window_end_s
        else:
            used.append(replace(m, spin=None))
    assert sum(m.spin is not None for m in used) == 3
    np.testing.assert_allclose(
        _run("offline", case, sliding)[0], _run("offline", case, used)[0], rtol=0, atol=1e-12
    )
    refused = [
        m
        if m.spin is None
        else replace(m, spin=replace(m.spin, status=SpinStatus.GEOMETRY, reason="x"))
        for m in sliding
    ]
    base = _run("offline", case, case.measurements)[0]
    np.testing.assert_allclose(_run("offline", case, refused)[0], base, atol=1e-12)
    np.testing.assert_allclose(_run("offline", case, sliding, spin_rate=False)[0], base, atol=1e-12)
