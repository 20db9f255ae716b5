"""``offline``: batch Levenberg-Marquardt over the whole sequence, with marginal covariances."""

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
from satpose.datasets.sequence import Calibration
from satpose.frontend.measurements import FrameMeasurements


@dataclass(frozen=True, kw_only=True)
class OfflineConfig:
    """Batch smoother settings.

    Attributes:
        max_iterations: Levenberg-Marquardt iterations at most.
        relative_error_tol: stop when the error decreases by less than this fraction.
        absolute_error_tol: stop when the error decreases by less than this.
    """

    max_iterations: int = 100
    relative_error_tol: float = 1e-10
    absolute_error_tol: float = 1e-12

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise BackendError(f"offline.max_iterations must be >= 1, got {self.max_iterations}")
        if not (self.relative_error_tol >= 0 and self.absolute_error_tol >= 0):
            raise BackendError("offline error tolerances must be non-negative")


class OfflineEstimator:
    """Collects every frame's factors; `estimate` solves the whole graph (warm-started from the
    previous solution when frames were added since) and computes marginal covariances."""

    name = "offline"

    def __init__(
        self,
        calibration: Calibration,
        *,
        motion: MotionConfig,
        measurements: MeasurementConfig,
        config: OfflineConfig,
        hook: Hook | None = None,
    ) -> None:
        self.config = config
        self.hook = hook
        self.clock = FactorClock()
        self.builder = GraphBuilder(calibration, motion, measurements, self.clock)
        self.graph = gtsam.NonlinearFactorGraph()
        self.initial = gtsam.Values()
        self._result: gtsam.Values | None = None
        self._marginals: gtsam.Marginals | None = None
        self._estimate: Estimate | None = None

    def add(self, measurements: FrameMeasurements) -> None:
        """Add one frame (see `GraphBuilder.add`); no optimisation happens here."""
        t0 = time.perf_counter()
        update = self.builder.add(measurements, prefer="measurement")
        self.graph.push_back(update.factors)
        self.initial.insert(update.values)
        self._estimate = None
        if self.hook is not None:
            self.hook(
                StepReport(
                    estimator=self.name,
                    step="add",
                    frame=int(measurements.frame),
                    timings_ms={"build": 1e3 * (time.perf_counter() - t0)},
                    factors=self.graph.size(),
                    variables=self.initial.size(),
                    new_factors=update.factors.size(),
                    notes=tuple(update.notes),
                )
            )

    def _solve(self) -> None:
        if not self.builder.started:
            raise BackendError(
                "no frame with usable measurements yet: "
                + (
                    "loose coupling needs a pose"
                    if self.builder.config.coupling == "loose"
                    else "tight coupling needs the ring and an anchor landmark"
                )
            )
        t0 = time.perf_counter()
        c0 = self.clock.seconds
        initial = gtsam.Values(self.initial)
        if self._result is not None:
            initial.update(self._result)  # warm start: previous solution where it exists
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.config.max_iterations)
        params.setRelativeErrorTol(self.config.relative_error_tol)
        params.setAbsoluteErrorTol(self.config.absolute_error_tol)
        optimizer = gtsam.LevenbergMarquardtOptimizer(self.graph, initial, params)
        result = optimizer.optimize()
        t1 = time.perf_counter()
        marginals = gtsam.Marginals(self.graph, result)
        t2 = time.perf_counter()
        self._result, self._marginals = result, marginals
        n = len(self.builder)
        for i in range(n):
            self.builder.set_hint(i, from_pose3(result.atPose3(X(i))), result.atVector(V(i)))
        self._estimate = Estimate(
            frame=np.array(self.builder.frames),
            t_s=np.array(self.builder.t_s),
            left_cam_from_target=tuple(from_pose3(result.atPose3(X(i))) for i in range(n)),
            twist=np.array([result.atVector(V(i)) for i in range(n)]),
            pose_covariance=np.array([marginals.marginalCovariance(X(i)) for i in range(n)]),
            twist_covariance=np.array([marginals.marginalCovariance(V(i)) for i in range(n)]),
        )
        if self.hook is not None:
            self.hook(
                StepReport(
                    estimator=self.name,
                    step="optimize",
                    frame=self.builder.frames[-1],
                    timings_ms={
                        "optimize": 1e3 * (t1 - t0),
                        "marginals": 1e3 * (t2 - t1),
                        "python_factors": 1e3 * (self.clock.seconds - c0),
                    },
                    factors=self.graph.size(),
                    variables=result.size(),
                    iterations=optimizer.iterations(),
                    error=self.graph.error(result),
                )
            )

    def estimate(self) -> Estimate:
        """The smoothed trajectory of every frame added so far (solves if frames were added)."""
        if self._estimate is None:
            self._solve()
        assert self._estimate is not None
        return self._estimate

    def joint_covariance(self, which: Literal["pose", "twist", "state"] = "pose") -> np.ndarray:
        """Joint marginal covariance of every frame's pose (6N x 6N), twist (6N x 6N) or state
        (12N x 12N, ``[pose_0, twist_0, pose_1, ...]``), frame-major — for consistency checks
        of the whole trajectory (frames are correlated through the motion prior)."""
        self.estimate()
        assert self._marginals is not None
        n = len(self.builder)
        keys: list[int] = []
        for i in range(n):
            if which in ("pose", "state"):
                keys.append(X(i))
            if which in ("twist", "state"):
                keys.append(V(i))
        joint = self._marginals.jointMarginalCovariance(gtsam.KeyVector(keys))
        blocks = [[joint.at(a, b) for b in keys] for a in keys]
        return np.block(blocks)
