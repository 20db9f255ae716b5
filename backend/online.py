"""``online``: iSAM2, updated once per frame.

`OnlineEstimator.filtered` is the estimate each frame had right after its own update (what a
real-time tracker would have reported); `estimate` is the current smoothed trajectory.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.estimate import Estimate, Hook, StepReport
from satpose.backend.factors import FactorClock, MeasurementConfig
from satpose.backend.graph import GraphBuilder
from satpose.backend.keys import V, X
from satpose.backend.motion import MotionConfig
from satpose.backend.pose3 import from_pose3
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration
from satpose.frontend.measurements import FrameMeasurements


@dataclass(frozen=True, kw_only=True)
class Isam2Config:
    """iSAM2 settings.

    Attributes:
        relinearize_threshold: a variable is relinearised when its update exceeds this (max
            norm of its tangent delta: rad, m, rad/s, m/s or m — the states' deltas are all
            well below 0.01 once converged).
        relinearize_skip: check for relinearisation every this many updates.
        extra_updates: additional ``update()`` calls (Gauss-Newton steps) per frame.
        factorization: ``cholesky`` (fast) or ``qr`` (more robust to ill-conditioning).
    """

    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    extra_updates: int = 0
    factorization: Literal["cholesky", "qr"] = "cholesky"

    def __post_init__(self) -> None:
        if not self.relinearize_threshold > 0:
            raise BackendError("online.relinearize_threshold must be positive")
        if self.relinearize_skip < 1 or self.extra_updates < 0:
            raise BackendError("online.relinearize_skip >= 1 and extra_updates >= 0 required")
        if self.factorization not in ("cholesky", "qr"):
            raise BackendError(f"online.factorization: cholesky or qr, got {self.factorization}")


@dataclass
class _Filtered:
    pose: Rigid3
    twist: np.ndarray
    pose_cov: np.ndarray
    twist_cov: np.ndarray


class OnlineEstimator:
    """iSAM2 tracker: one incremental update per frame."""

    name = "online"

    def __init__(
        self,
        calibration: Calibration,
        *,
        motion: MotionConfig,
        measurements: MeasurementConfig,
        config: Isam2Config,
        hook: Hook | None = None,
    ) -> None:
        self.config = config
        self.hook = hook
        self.clock = FactorClock()
        self.builder = GraphBuilder(calibration, motion, measurements, self.clock)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(config.relinearize_threshold)
        params.relinearizeSkip = config.relinearize_skip
        params.setFactorization("CHOLESKY" if config.factorization == "cholesky" else "QR")
        self.isam = gtsam.ISAM2(params)
        self._filtered: dict[int, _Filtered] = {}
        self._estimate: Estimate | None = None

    def add(self, measurements: FrameMeasurements) -> None:
        """Add one frame and update iSAM2; records the frame's filtered estimate."""
        t0 = time.perf_counter()
        update = self.builder.add(measurements, prefer="prediction")
        t1 = time.perf_counter()
        c0 = self.clock.seconds
        relinearized = 0
        timings = {"build": 1e3 * (t1 - t0)}
        if update.created:
            result = self.isam.update(update.factors, update.values)
            relinearized = result.getVariablesRelinearized()
            for _ in range(self.config.extra_updates):
                relinearized += self.isam.update().getVariablesRelinearized()
            t2 = time.perf_counter()
            timings["update"] = 1e3 * (t2 - t1)
            timings["python_factors"] = 1e3 * (self.clock.seconds - c0)
            for i in update.created:
                pose = from_pose3(self.isam.calculateEstimatePose3(X(i)))
                twist = np.asarray(self.isam.calculateEstimateVector(V(i)), float)
                self.builder.set_hint(i, pose, twist)
            t3 = time.perf_counter()
            timings["estimate"] = 1e3 * (t3 - t2)
            for i in update.created:
                pose, twist = self.builder.hint(i)
                self._filtered[i] = _Filtered(
                    pose,
                    twist,
                    self.isam.marginalCovariance(X(i)),
                    self.isam.marginalCovariance(V(i)),
                )
            timings["marginals"] = 1e3 * (time.perf_counter() - t3)
        self._estimate = None
        if self.hook is not None:
            self.hook(
                StepReport(
                    estimator=self.name,
                    step="add",
                    frame=int(measurements.frame),
                    timings_ms=timings,
                    factors=self.isam.getFactorsUnsafe().size(),
                    variables=self.isam.size(),
                    new_factors=update.factors.size(),
                    relinearized=relinearized,
                    notes=tuple(update.notes),
                )
            )

    def _require_start(self) -> None:
        if not self.builder.started:
            raise BackendError(
                "no frame with usable measurements yet: "
                + (
                    "loose coupling needs a pose"
                    if self.builder.config.coupling == "loose"
                    else "tight coupling needs the ring and an anchor landmark"
                )
            )

    def filtered(self) -> Estimate:
        """Each frame's estimate right after its own update (frames added before the graph
        started get theirs from the starting update)."""
        self._require_start()
        n = len(self.builder)
        rows = [self._filtered[i] for i in range(n)]
        return Estimate(
            frame=np.array(self.builder.frames),
            t_s=np.array(self.builder.t_s),
            left_cam_from_target=tuple(r.pose for r in rows),
            twist=np.array([r.twist for r in rows]),
            pose_covariance=np.array([r.pose_cov for r in rows]),
            twist_covariance=np.array([r.twist_cov for r in rows]),
        )

    def estimate(self) -> Estimate:
        """The current smoothed estimate of every frame (iSAM2's full solution)."""
        self._require_start()
        if self._estimate is None:
            values = self.isam.calculateEstimate()
            n = len(self.builder)
            self._estimate = Estimate(
                frame=np.array(self.builder.frames),
                t_s=np.array(self.builder.t_s),
                left_cam_from_target=tuple(from_pose3(values.atPose3(X(i))) for i in range(n)),
                twist=np.array([values.atVector(V(i)) for i in range(n)]),
                pose_covariance=np.array([self.isam.marginalCovariance(X(i)) for i in range(n)]),
                twist_covariance=np.array([self.isam.marginalCovariance(V(i)) for i in range(n)]),
            )
        return self._estimate
