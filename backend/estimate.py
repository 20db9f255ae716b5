"""What leaves the backend: numpy only.

`Estimate` holds the target's trajectory (pose and body twist with covariances) at every frame
added so far; `StepReport` is the per-step diagnostic handed to an estimator's hook (timings,
graph size, iterations) — never part of the estimate. `Estimator` is the interface the three
estimators share.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.pose3 import ROT, TRANS
from satpose.datasets.geometry import Rigid3
from satpose.frontend.measurements import FrameMeasurements


def _frozen(a: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    out = np.array(a, dtype=float)
    if out.shape != shape:
        raise BackendError(f"Estimate.{name}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise BackendError(f"Estimate.{name}: holds NaN or infinite values")
    out.setflags(write=False)
    return out


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """The target's estimated trajectory, one entry per frame added so far.

    Attributes:
        frame: (N,) frame indices.
        t_s: (N,) frame times [s].
        left_cam_from_target: N poses of the target in the left camera frame.
        twist: (N, 6) body twist ``[omega (rad/s), v (m/s)]`` in the target frame, so that
            ``T(t + dt) ~ T(t) Exp(twist dt)``. ``omega`` compares with groundtruth.csv's
            ``wx, wy, wz``; ``R @ v`` with ``vx, vy, vz`` (velocity of the target-frame origin
            in the left camera frame), see `origin_velocity_cam`.
        pose_covariance: (N, 6, 6) over ``[rotation (rad), translation (m)]`` with right
            perturbation ``T_true = T_est Exp(xi)``.
        twist_covariance: (N, 6, 6) over ``[omega, v]``.
    """

    frame: np.ndarray
    t_s: np.ndarray
    left_cam_from_target: tuple[Rigid3, ...]
    twist: np.ndarray
    pose_covariance: np.ndarray
    twist_covariance: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.left_cam_from_target)
        object.__setattr__(self, "left_cam_from_target", tuple(self.left_cam_from_target))
        frame = np.array(self.frame, dtype=np.int64)
        if frame.shape != (n,):
            raise BackendError(f"Estimate.frame: expected shape ({n},), got {frame.shape}")
        frame.setflags(write=False)
        object.__setattr__(self, "frame", frame)
        object.__setattr__(self, "t_s", _frozen(self.t_s, (n,), "t_s"))
        object.__setattr__(self, "twist", _frozen(self.twist, (n, 6), "twist"))
        for name in ("pose_covariance", "twist_covariance"):
            C = _frozen(getattr(self, name), (n, 6, 6), name)
            if n and not np.allclose(C, np.swapaxes(C, 1, 2), rtol=1e-6, atol=1e-15):
                raise BackendError(f"Estimate.{name}: covariances must be symmetric")
            object.__setattr__(self, name, C)

    def __len__(self) -> int:
        return len(self.left_cam_from_target)

    # -- 1-sigma bounds -----------------------------------------------------------------------

    def pose_sigmas(self) -> np.ndarray:
        """(N, 6) standard deviations ``[rotation (rad) x3, translation (m) x3]``."""
        return np.sqrt(np.clip(np.diagonal(self.pose_covariance, axis1=1, axis2=2), 0, None))

    def twist_sigmas(self) -> np.ndarray:
        """(N, 6) standard deviations ``[omega (rad/s) x3, v (m/s) x3]``."""
        return np.sqrt(np.clip(np.diagonal(self.twist_covariance, axis1=1, axis2=2), 0, None))

    # -- motion ---------------------------------------------------------------------------------

    @property
    def angular_velocity(self) -> np.ndarray:
        """(N, 3) angular velocity in the target frame [rad/s]."""
        return self.twist[:, ROT]

    def origin_velocity_cam(self) -> np.ndarray:
        """(N, 3) velocity of the target-frame origin in the left camera frame [m/s]."""
        R = np.stack([T.R for T in self.left_cam_from_target]) if len(self) else np.zeros((0, 3, 3))
        return np.einsum("nij,nj->ni", R, self.twist[:, TRANS])

    def spin_rate_rad_s(self) -> np.ndarray:
        """(N,) spin rate ``|omega|`` [rad/s]."""
        return np.linalg.norm(self.angular_velocity, axis=1)

    def spin_rate_sigma_rad_s(self) -> np.ndarray:
        """(N,) first-order standard deviation of `spin_rate_rad_s` [rad/s]."""
        w = self.angular_velocity
        n = np.linalg.norm(w, axis=1, keepdims=True)
        u = np.divide(w, n, out=np.zeros_like(w), where=n > 0)
        C = self.twist_covariance[:, ROT, ROT]
        return np.sqrt(np.clip(np.einsum("ni,nij,nj->n", u, C, u), 0, None))

    def spin_axis(self) -> np.ndarray:
        """(N, 3) unit spin axis in the target frame (``omega / |omega|``; zero if not spinning)."""
        w = self.angular_velocity
        n = np.linalg.norm(w, axis=1, keepdims=True)
        return np.divide(w, n, out=np.zeros_like(w), where=n > 0)

    def spin_axis_cam(self) -> np.ndarray:
        """(N, 3) unit spin axis in the left camera frame."""
        if not len(self):
            return np.zeros((0, 3))
        R = np.stack([T.R for T in self.left_cam_from_target])
        return np.einsum("nij,nj->ni", R, self.spin_axis())

    def frame_interval_s(self) -> float:
        """Median interval between consecutive frames [s] (NaN with fewer than two frames)."""
        return float(np.median(np.diff(self.t_s))) if len(self) > 1 else float("nan")

    def spin_rate_deg_per_frame(self, frame_interval_s: float | None = None) -> np.ndarray:
        """(N,) spin rate in degrees per frame interval (default: `frame_interval_s`)."""
        dt = self.frame_interval_s() if frame_interval_s is None else frame_interval_s
        return np.degrees(self.spin_rate_rad_s()) * dt


@dataclass(frozen=True, kw_only=True)
class StepReport:
    """Diagnostics of one estimator step, handed to the optional hook.

    Attributes:
        estimator: ``offline``, ``online`` or ``kalman``.
        step: ``add`` (one frame added) or ``optimize`` (batch solve).
        frame: the frame just added (``add``) or the last frame (``optimize``).
        timings_ms: wall time per stage [ms] (e.g. ``build``, ``update``, ``marginals``,
            ``python_factors`` = time spent inside Python factors during the step); a stage
            ending in ``_cpu`` is the process's CPU time instead (``update_cpu``).
        factors, variables: graph size after the step (0 for the Kalman filter).
        new_factors: factors added by the step.
        iterations: optimizer iterations (``optimize``), or None.
        relinearized: variables iSAM2 relinearised in this step, or None.
        error: graph error after the step, or None.
        notes: what happened (``"prediction only"``, ``"waiting for a first pose"``, ...).
    """

    estimator: str
    step: str
    frame: int
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    factors: int = 0
    variables: int = 0
    new_factors: int = 0
    iterations: int | None = None
    relinearized: int | None = None
    error: float | None = None
    notes: tuple[str, ...] = ()


Hook = Callable[[StepReport], None]


class Estimator(Protocol):
    """One interface for the batch smoother, the iSAM2 tracker and the Kalman baseline."""

    def add(self, measurements: FrameMeasurements) -> None:
        """Add one frame's measurements (frames in time order)."""
        ...

    def estimate(self) -> Estimate:
        """The current best estimate of every frame added so far (smoothed where applicable)."""
        ...
