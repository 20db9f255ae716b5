"""``kalman``: the paper's constant-velocity Kalman filter on per-frame poses (the baseline).

Seed 000 smooths the per-frame ``R`` and ``t`` with a constant-velocity Kalman filter. This
is that filter, written so that a 10 deg/frame spin cannot wrap an angle: an error-state
filter with

- nominal state: ``R`` (``left_cam_from_target`` rotation), ``omega`` (body angular velocity,
  target frame), ``t`` (translation, left camera frame), ``u = dt/dt`` (camera frame);
- error state (12,) ``[dtheta, dt, domega, du]`` with ``R_true = R Exp(dtheta)``;
- prediction over ``dt``: ``R <- R Exp(omega dt)``, ``t <- t + u dt``, error transition
  ``dtheta <- Exp(-omega dt) dtheta + J_r(omega dt) dt domega``, ``dt <- dt + dt du``;
  process noise: the same white-noise-on-acceleration densities as the factor graph
  (`MotionConfig`), the angular one in the target frame, the linear one in the camera frame
  (isotropic, so the frame does not matter);
- update with a `PoseMeasurement` ``(T_m, C)`` (``T_true = T_m Exp(xi)``, ``xi ~ N(0, C)``):
  innovation ``[Log(R^T R_m) ; t_m - t]``, measurement covariance ``C`` with its translation
  rows rotated into the camera frame by ``R_m``; Joseph-form covariance update.

Only per-frame poses are used (loose by nature); a frame without one is prediction only.
The linear Kalman core (`kf_update`) is checked against GTSAM's batch smoother on a
linear-Gaussian toy (tests/backend/test_kalman.py).
"""

from __future__ import annotations

import time

import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.estimate import Estimate, Hook, StepReport
from satpose.backend.motion import MotionConfig, first_twist_covariance
from satpose.backend.pose3 import ROT, TRANS
from satpose.datasets.geometry import Rigid3, matrix_to_rotvec, rotvec_to_matrix, skew
from satpose.frontend.measurements import FrameMeasurements, PoseMeasurement

# Error-state layout: pose part [dtheta, dt] then twist part [domega, du].
TH, TT, W, U = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at ``phi`` (3,): ``Exp(phi + d) ~ Exp(phi) Exp(J_r(phi) d)``."""
    a = float(np.linalg.norm(phi))
    S = skew(phi)
    if a < 1e-8:
        return np.eye(3) - 0.5 * S + S @ S / 6.0
    return np.eye(3) - (1 - np.cos(a)) / a**2 * S + (a - np.sin(a)) / a**3 * S @ S


def kf_update(
    P: np.ndarray, y: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Linear Kalman update: correction ``dx`` (n,) and posterior covariance (n, n) (Joseph
    form) for innovation ``y`` (m,), measurement matrix ``H`` (m, n) and noise ``R`` (m, m)."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T  # P H^T S^-1 (P, S symmetric)
    A = np.eye(P.shape[0]) - K @ H
    P_new = A @ P @ A.T + K @ R @ K.T
    return K @ y, 0.5 * (P_new + P_new.T)


class _State:
    """Nominal state and error covariance of the filter."""

    def __init__(
        self, R: np.ndarray, omega: np.ndarray, t: np.ndarray, u: np.ndarray, P: np.ndarray
    ) -> None:
        self.R, self.omega, self.t, self.u, self.P = R, omega, t, u, P

    def copy(self) -> _State:
        return _State(self.R.copy(), self.omega.copy(), self.t.copy(), self.u.copy(), self.P.copy())


class KalmanEstimator:
    """The constant-velocity Kalman filter baseline (see the module docstring)."""

    name = "kalman"

    def __init__(self, *, motion: MotionConfig, hook: Hook | None = None) -> None:
        self.motion = motion
        self.hook = hook
        self.frames: list[int] = []
        self.t_s: list[float] = []
        self._states: list[_State] = []  # one per frame once started
        self._before = 0  # frames before the first pose (retrodicted)
        self._poses = 0  # poses used so far
        self._state: _State | None = None

    # -- model --------------------------------------------------------------------------------

    def _process_noise(self, dt: float) -> np.ndarray:
        """Q (12x12) for a step of ``dt`` (negative: backward, for frames before the start)."""
        a = abs(dt)
        Q = np.zeros((12, 12))
        for pos, vel, q in (
            (TH, W, self.motion.angular_accel_noise_rad_s2_rthz**2),
            (TT, U, self.motion.linear_accel_noise_m_s2_rthz**2),
        ):
            Q[pos, pos] = np.eye(3) * q * a**3 / 3
            Q[pos, vel] = Q[vel, pos] = np.eye(3) * q * dt * a / 2
            Q[vel, vel] = np.eye(3) * q * a
        return Q

    def _predict(self, s: _State, dt: float) -> _State:
        phi = s.omega * dt
        F = np.eye(12)
        F[TH, TH] = rotvec_to_matrix(-phi)
        F[TH, W] = so3_right_jacobian(phi) * dt
        F[TT, U] = np.eye(3) * dt
        P = F @ s.P @ F.T + self._process_noise(dt)
        return _State(
            s.R @ rotvec_to_matrix(phi), s.omega.copy(), s.t + s.u * dt, s.u.copy(), 0.5 * (P + P.T)
        )

    @staticmethod
    def _measurement_covariance(m: PoseMeasurement) -> np.ndarray:
        """Covariance (6x6) of the innovation noise over ``[dtheta, dt (camera frame)]``."""
        Rm = m.left_cam_from_target.R
        A = np.zeros((6, 6))
        A[0:3, ROT] = np.eye(3)
        A[3:6, TRANS] = Rm
        return A @ m.covariance @ A.T

    def _update(self, s: _State, m: PoseMeasurement) -> _State:
        Tm = m.left_cam_from_target
        y = np.concatenate([matrix_to_rotvec(s.R.T @ Tm.R), Tm.t - s.t])
        H = np.zeros((6, 12))
        H[0:3, TH] = np.eye(3)
        H[3:6, TT] = np.eye(3)
        dx, P = kf_update(s.P, y, H, self._measurement_covariance(m))
        return _State(s.R @ rotvec_to_matrix(dx[TH]), s.omega + dx[W], s.t + dx[TT], s.u + dx[U], P)

    def _first(self, m: PoseMeasurement) -> _State:
        T = m.left_cam_from_target
        P = np.zeros((12, 12))
        P[0:6, 0:6] = self._measurement_covariance(m)
        C = first_twist_covariance(self.motion)
        P[W, W] = C[ROT, ROT]
        P[U, U] = C[TRANS, TRANS]  # isotropic: the same in the camera frame
        return _State(T.R.copy(), np.zeros(3), T.t.copy(), np.zeros(3), P)

    # -- interface ----------------------------------------------------------------------------

    def add(self, measurements: FrameMeasurements) -> None:
        """Predict to this frame and update with its pose (if any)."""
        t0 = time.perf_counter()
        m = measurements
        if self.t_s and not m.t_s > self.t_s[-1]:
            raise BackendError(
                f"frame {m.frame}: time {m.t_s} s does not follow the previous {self.t_s[-1]} s"
            )
        self.frames.append(int(m.frame))
        self.t_s.append(float(m.t_s))
        notes: list[str] = []
        if self._state is None:
            if m.pose is None:
                notes.append("waiting for a first pose")
            else:
                first = self._first(m.pose)
                # Frames before the first pose: retrodicted from it (prediction backwards),
                # again from the second pose's state, which knows the twist (`_retrodicted`).
                self._before = len(self.t_s) - 1
                self._poses = 1
                self._state = first
                self._states = [*self._retrodicted(first), first.copy()]
        else:
            s = self._predict(self._state, self.t_s[-1] - self.t_s[-2])
            if m.pose is not None:
                s = self._update(s, m.pose)
                self._poses += 1
                if self._poses == 2:
                    self._states[: self._before] = self._retrodicted(s)
            else:
                notes.append("prediction only")
            self._state = s
            self._states.append(s.copy())
        if self.hook is not None:
            self.hook(
                StepReport(
                    estimator=self.name,
                    step="add",
                    frame=int(m.frame),
                    timings_ms={"update": 1e3 * (time.perf_counter() - t0)},
                    notes=tuple(notes),
                )
            )

    def _retrodicted(self, s: _State) -> list[_State]:
        """The states of the frames before the first pose, predicted backwards from ``s`` (the
        current frame's state). From the first pose alone the twist is its zero-mean prior,
        so they are that pose; from the second they move with the measured twist (on
        `paper-docking`, whose frontend fixes its target frame at the second frame, the first
        frame's retrodicted pose was 10.1 deg / 6.5 cm off with the prior, 1.6 deg / 1.4 cm
        with the twist; frame 1, the first pose, 0.8 deg / 1.5 cm)."""
        t_now = self.t_s[-1]
        return [self._predict(s, t - t_now) for t in self.t_s[: self._before]]

    def estimate(self) -> Estimate:
        """The filtered estimate of every frame (a filter does not smooth)."""
        if self._state is None:
            raise BackendError("no frame with usable measurements yet: the filter needs a pose")
        poses, twists, pcs, tcs = [], [], [], []
        for s in self._states:
            # Error state -> the Estimate's right perturbations: xi_t = R^T dt;
            # v_body = R^T u  =>  dv = R^T du + [R^T u]x dtheta.
            v = s.R.T @ s.u
            J = np.zeros((12, 12))
            J[ROT, TH] = np.eye(3)
            J[TRANS, TT] = s.R.T
            J[6:9, W] = np.eye(3)
            J[9:12, U] = s.R.T
            J[9:12, TH] = skew(v)
            C = J @ s.P @ J.T
            C = 0.5 * (C + C.T)
            U_, _, Vt = np.linalg.svd(s.R)
            poses.append(Rigid3(R=U_ @ Vt, t=s.t))
            twists.append(np.concatenate([s.omega, v]))
            pcs.append(C[0:6, 0:6])
            tcs.append(C[6:12, 6:12])
        return Estimate(
            frame=np.array(self.frames),
            t_s=np.array(self.t_s),
            left_cam_from_target=tuple(poses),
            twist=np.array(twists),
            pose_covariance=np.array(pcs),
            twist_covariance=np.array(tcs),
        )

    def filtered(self) -> Estimate:
        """Same as `estimate` (the filter's estimates are its filtered ones)."""
        return self.estimate()
