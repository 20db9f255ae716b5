"""Rotation-only factor graph for the star tracker (seed 004, patent step 5).

State per window ``i``: the attitude ``Q(i) = inertial_from_camera`` (gtsam ``Rot3``) and the
body rate ``W(i)`` (camera frame, rad/s, ``Vector3``). Factors:

- absolute attitude (Wahba on identified stars): ``PriorFactorRot3`` with the frontend's 3x3
  covariance. GTSAM's ``Rot3`` local coordinates are the right perturbation
  ``R_true = R Exp(delta)``, the frontend's convention.
- relative rotation between windows (rotation-only alignment of matched bearings):
  ``BetweenFactorRot3`` on ``R_i^T R_j = cam_i_from_cam_j``.
- constant angular rate, white noise on the angular acceleration (the SO(3) form of
  backend/motion.py's WNOA prior): ``e = [Log(R_i^T R_j) - dt w_i ; w_j - w_i]``,
  ``Q(dt) = [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) q I3``. Jacobians with ``D = R_i^T R_j``,
  ``phi = Log(D)``: ``dphi/dR_i = -J_r^-1(phi) D^T``, ``dphi/dR_j = J_r^-1(phi)``.

`smooth_attitudes` solves the whole graph (Levenberg-Marquardt, marginal covariances);
`OnlineAttitudeSmoother` adds one window at a time to iSAM2. Nothing gtsam leaves the module.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from satpose.backend.errors import BackendError

_Q = "q"
_W = "w"


def Q(i: int) -> int:
    return int(gtsam.symbol(_Q, i))


def W(i: int) -> int:
    return int(gtsam.symbol(_W, i))


@dataclass(frozen=True, kw_only=True)
class RotationGraphConfig:
    """Settings of the rotation graph.

    Attributes:
        angular_accel_noise_rad_s2_rthz: sqrt PSD of the angular acceleration (jitter and
            slew changes must fit inside it).
        first_rate_sigma_rad_s: zero-mean prior on the first window's rate (per axis).
        relative_factors: add the relative-rotation factors.
        relinearize_threshold: iSAM2 relinearisation threshold [rad].
    """

    angular_accel_noise_rad_s2_rthz: float = 0.05
    first_rate_sigma_rad_s: float = 0.5
    relative_factors: bool = True
    relinearize_threshold: float = 1e-6

    def __post_init__(self) -> None:
        if not (self.angular_accel_noise_rad_s2_rthz > 0 and self.first_rate_sigma_rad_s > 0):
            raise BackendError("rotation graph noise settings must be positive")


@dataclass(frozen=True, kw_only=True)
class AttitudeWindow:
    """What the frontend measured in one window.

    Attributes:
        t_s: window time.
        R: absolute ``inertial_from_camera`` (3, 3) or None if none was solved.
        cov: its 3x3 covariance [rad^2] (right perturbation).
        rel_R: ``cam_prev_from_cam_this`` relative to the previous window, or None.
        rel_cov: its 3x3 covariance.
        t_meas_s: the time ``R`` refers to when that is not ``t_s`` (an event output's data
            centre on an earlier time than the output, `AttitudeSolution.data_t_s`): the
            prior goes on the window nearest that time, moved by its rate.
        rate_rad_s, rate_info: a body-rate measurement at ``t_meas_s`` (else ``t_s``) and
            its 3x3 information [(rad/s)^-2] (an event output's shared-rate fit, prior
            removed): a prior on that window's rate.
    """

    t_s: float
    R: np.ndarray | None = None
    cov: np.ndarray | None = None
    rel_R: np.ndarray | None = None
    rel_cov: np.ndarray | None = None
    t_meas_s: float | None = None
    rate_rad_s: np.ndarray | None = None
    rate_info: np.ndarray | None = None


@dataclass(frozen=True)
class AttitudeEstimate:
    """Smoothed attitudes (numpy). ``R`` (N, 3, 3) inertial_from_camera, ``cov`` (N, 3, 3),
    ``rate_rad_s`` (N, 3) body rate, ``t_s`` (N,)."""

    t_s: np.ndarray
    R: np.ndarray
    cov: np.ndarray
    rate_rad_s: np.ndarray


def _process_cov(dt: float, q: float) -> np.ndarray:
    Qc = q * q * np.eye(3)
    return np.block([[dt**3 / 3 * Qc, dt**2 / 2 * Qc], [dt**2 / 2 * Qc, dt * Qc]])


def constant_rate_factor(i: int, j: int, dt: float, q: float) -> gtsam.CustomFactor:
    """WNOA prior on ``(Q(i), W(i), Q(j), W(j))`` ``dt`` seconds apart (Python factor)."""
    if not dt > 0:
        raise BackendError(f"window times must increase, got a step of {dt} s")
    eye, zero = np.eye(3), np.zeros((3, 3))
    H_wi = np.asfortranarray(np.vstack([-dt * eye, -eye]))
    H_wj = np.asfortranarray(np.vstack([zero, eye]))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        k = this.keys()
        Ri, Rj = values.atRot3(k[0]), values.atRot3(k[2])
        wi, wj = values.atVector(k[1]), values.atVector(k[3])
        D = Ri.between(Rj)
        phi = gtsam.Rot3.Logmap(D)
        if H is not None:
            Jinv = gtsam.Rot3.LogmapDerivative(phi)
            H[0] = np.asfortranarray(np.vstack([-Jinv @ D.matrix().T, zero]))
            H[1] = H_wi
            H[2] = np.asfortranarray(np.vstack([Jinv, zero]))
            H[3] = H_wj
        return np.concatenate([phi - dt * wi, wj - wi])

    return gtsam.CustomFactor(
        gtsam.noiseModel.Gaussian.Covariance(_process_cov(dt, q)), [Q(i), W(i), Q(j), W(j)], error
    )


def attitude_at_factor(j: int, tau: float, R_meas: np.ndarray, cov: np.ndarray) -> Any:
    """Absolute attitude ``R_meas`` measured ``tau`` seconds after window ``j``, on
    ``(Q(j), W(j))``: ``e = Log(R_meas^T R_j Exp(w_j tau))`` (a `PriorFactorRot3` on ``Q(j)``
    when ``tau`` is 0). Jacobians with ``E = Exp(w_j tau)``: ``de/dR_j = J_r^-1(e) E^T``,
    ``de/dw_j = J_r^-1(e) J_r(w_j tau) tau``."""
    noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float))
    if tau == 0.0:
        return gtsam.PriorFactorRot3(Q(j), gtsam.Rot3(R_meas), noise)
    Rm_inv = gtsam.Rot3(R_meas).inverse()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        k = this.keys()
        Rj, wj = values.atRot3(k[0]), values.atVector(k[1])
        E = gtsam.Rot3.Expmap(wj * tau)
        e = gtsam.Rot3.Logmap(Rm_inv.compose(Rj).compose(E))
        if H is not None:
            Jinv = gtsam.Rot3.LogmapDerivative(e)
            H[0] = np.asfortranarray(Jinv @ E.matrix().T)
            H[1] = np.asfortranarray(Jinv @ gtsam.Rot3.ExpmapDerivative(wj * tau) * tau)
        return e

    return gtsam.CustomFactor(noise, [Q(j), W(j)], error)


def _nearest(times: Sequence[float], t: float, k: int) -> int:
    """Index ``<= k`` of the window time nearest ``t`` (``times`` increasing)."""
    i = bisect.bisect_left(times, t, 0, k + 1)
    return min((c for c in (i - 1, i) if 0 <= c <= k), key=lambda c: abs(times[c] - t))


def _window_factors(
    graph: gtsam.NonlinearFactorGraph,
    k: int,
    win: AttitudeWindow,
    times: Sequence[float],
    config: RotationGraphConfig,
) -> None:
    """Factors of window ``k`` (``times``: windows ``0..k``'s times, this one's included)."""
    prev_t = float(times[k - 1]) if k else None
    if win.R is not None:
        if win.cov is None:
            raise BackendError(f"window {k}: an absolute attitude needs its covariance")
        j, tau = k, 0.0
        if win.t_meas_s is not None and win.t_meas_s != win.t_s:
            j = _nearest(times, win.t_meas_s, k)
            tau = float(win.t_meas_s - times[j])
        graph.add(attitude_at_factor(j, tau, win.R, win.cov))
        if win.rate_rad_s is not None and win.rate_info is not None:
            # (A tiny floor keeps the information positive definite when the span's events
            # say nothing about one axis; the rate is the window's, tau from the data.)
            info = np.asarray(win.rate_info, float) + 1e-6 * np.eye(3)
            graph.add(
                gtsam.PriorFactorVector(
                    W(j),
                    np.asarray(win.rate_rad_s, float),
                    gtsam.noiseModel.Gaussian.Information(info),
                )
            )
    if prev_t is None:
        graph.add(
            gtsam.PriorFactorVector(
                W(k),
                np.zeros(3),
                gtsam.noiseModel.Isotropic.Sigma(3, config.first_rate_sigma_rad_s),
            )
        )
        return
    graph.add(
        constant_rate_factor(k - 1, k, win.t_s - prev_t, config.angular_accel_noise_rad_s2_rthz)
    )
    if config.relative_factors and win.rel_R is not None and win.rel_cov is not None:
        graph.add(
            gtsam.BetweenFactorRot3(
                Q(k - 1),
                Q(k),
                gtsam.Rot3(win.rel_R),
                gtsam.noiseModel.Gaussian.Covariance(win.rel_cov),
            )
        )


def _initial(windows: list[AttitudeWindow]) -> list[np.ndarray]:
    """Initial attitudes: each window's own solution, else chained relative rotations, else the
    previous one."""
    out: list[np.ndarray] = []
    for k, w in enumerate(windows):
        if w.R is not None:
            out.append(np.asarray(w.R))
        elif out and w.rel_R is not None:
            out.append(out[-1] @ w.rel_R)
        elif out:
            out.append(out[-1])
        else:
            later = next((x.R for x in windows[k:] if x.R is not None), None)
            if later is None:
                raise BackendError("no window has an absolute attitude: the graph has no anchor")
            out.append(np.asarray(later))
    return out


def _rates(t: np.ndarray, Rs: list[np.ndarray]) -> np.ndarray:
    w = np.zeros((len(Rs), 3))
    for k in range(1, len(Rs)):
        w[k] = gtsam.Rot3.Logmap(gtsam.Rot3(Rs[k - 1]).between(gtsam.Rot3(Rs[k]))) / (
            t[k] - t[k - 1]
        )
    if len(Rs) > 1:
        w[0] = w[1]
    return w


def smooth_attitudes(
    windows: list[AttitudeWindow], config: RotationGraphConfig | None = None
) -> AttitudeEstimate:
    """Offline: the whole rotation graph by Levenberg-Marquardt, with marginal covariances."""
    config = config or RotationGraphConfig()
    if not windows:
        raise BackendError("no windows to smooth")
    t = np.array([w.t_s for w in windows], float)
    if np.any(np.diff(t) <= 0):
        raise BackendError("window times must increase")
    times = t.tolist()
    init_R = _initial(windows)
    init_w = _rates(t, init_R)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, w in enumerate(windows):
        _window_factors(graph, k, w, times, config)
        values.insert(Q(k), gtsam.Rot3(init_R[k]))
        values.insert(W(k), init_w[k])
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marg = gtsam.Marginals(graph, result)
    n = len(windows)
    return AttitudeEstimate(
        t_s=t,
        R=np.array([result.atRot3(Q(k)).matrix() for k in range(n)]),
        cov=np.array([marg.marginalCovariance(Q(k)) for k in range(n)]),
        rate_rad_s=np.array([result.atVector(W(k)) for k in range(n)]),
    )


class OnlineAttitudeSmoother:
    """iSAM2 over the rotation graph, updated once per window.

    ``add(window)`` returns the filtered attitude of that window (its estimate right after its
    own update); ``estimate()`` the smoothed trajectory so far.
    """

    def __init__(self, config: RotationGraphConfig | None = None) -> None:
        self.config = config or RotationGraphConfig()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        self.t: list[float] = []
        self.filtered: list[np.ndarray] = []
        self._pending: list[AttitudeWindow] = []
        self._last_R: np.ndarray | None = None
        self._last_w = np.zeros(3)

    def add(self, win: AttitudeWindow) -> np.ndarray | None:
        """Add one window; None until a window with an absolute attitude has anchored the
        graph (windows before it are kept and added with it)."""
        if self.t and win.t_s <= self.t[-1]:
            raise BackendError(f"window time {win.t_s} does not increase")
        if self._last_R is None and win.R is None:
            self._pending.append(win)
            return None
        batch = [*self._pending, win]
        self._pending = []
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        inits = _initial(batch) if self._last_R is None else None
        for j, w in enumerate(batch):
            k = len(self.t)
            prev_t = self.t[-1] if self.t else None
            self.t.append(w.t_s)
            _window_factors(graph, k, w, self.t, self.config)
            if inits is not None:
                R0 = inits[j]
            else:
                assert self._last_R is not None
                dt = w.t_s - (prev_t if prev_t is not None else w.t_s)
                R0 = (
                    w.R
                    if w.R is not None
                    else self._last_R @ gtsam.Rot3.Expmap(self._last_w * dt).matrix()
                )
            values.insert(Q(k), gtsam.Rot3(R0))
            values.insert(W(k), self._last_w)
            self._last_R = np.asarray(R0)
        self.isam.update(graph, values)
        est = self.isam.calculateEstimate()
        k = len(self.t) - 1
        self._last_R = est.atRot3(Q(k)).matrix()
        self._last_w = est.atVector(W(k))
        self.filtered.extend([self._last_R] * len(batch))
        return self._last_R

    def estimate(self) -> AttitudeEstimate:
        """Smoothed attitudes of every window added so far (iSAM2's current solution)."""
        if not self.t:
            raise BackendError("no anchored window yet")
        est = self.isam.calculateEstimate()
        n = len(self.t)
        return AttitudeEstimate(
            t_s=np.array(self.t),
            R=np.array([est.atRot3(Q(k)).matrix() for k in range(n)]),
            cov=np.array([self.isam.marginalCovariance(Q(k)) for k in range(n)]),
            rate_rad_s=np.array([est.atVector(W(k)) for k in range(n)]),
        )


def nees(err_rotvec: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared per window (3 DOF): ``e^T P^-1 e``."""
    return np.einsum("ni,nij,nj->n", err_rotvec, np.linalg.inv(cov), err_rotvec)


__all__ = [
    "AttitudeEstimate",
    "AttitudeWindow",
    "OnlineAttitudeSmoother",
    "RotationGraphConfig",
    "attitude_at_factor",
    "constant_rate_factor",
    "nees",
    "smooth_attitudes",
]
