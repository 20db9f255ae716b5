"""``offline``: batch Levenberg-Marquardt over the whole sequence, with marginal covariances."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Literal

import gtsam
import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.estimate import Estimate, Hook, StepReport
from satpose.backend.factors import FactorClock, MeasurementConfig
from satpose.backend.graph import GraphBuilder
from satpose.backend.keys import DISPARITY_BIAS, V, X
from satpose.backend.motion import MotionConfig
from satpose.backend.pose3 import from_state, state_covariance_to_pose, state_to_pose_jacobian
from satpose.backend.solve import ConsideredCovariances, Covariances, levenberg_marquardt
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


_PLAIN_COVARIANCES = "covariances without the considered ring disparity error"


class OfflineEstimator:
    """Collects every frame's factors; `estimate` solves the whole graph (warm-started from the
    previous solution when frames were added since) and computes marginal covariances.

    With ``MeasurementConfig.ring_disparity_consider_px`` (and the bias not estimated) a
    second graph is built alongside, the same factors with the ring's common disparity error
    as a variable; it is only linearised at the solution, for the covariances that consider
    that error (`ConsideredCovariances`). ``final_note`` says when they could not be had and
    the plain ones were reported."""

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
        self._covariances: Covariances | ConsideredCovariances | None = None
        self._estimate: Estimate | None = None
        self.final_note: str | None = None
        self._consider: tuple[GraphBuilder, gtsam.NonlinearFactorGraph, float] | None = None
        sigma = measurements.ring_disparity_consider_px
        if (
            sigma is not None
            and measurements.ring_disparity_bias_px is None
            and measurements.coupling == "tight"
        ):
            with_bias = replace(measurements, ring_disparity_bias_px=sigma)
            builder = GraphBuilder(calibration, motion, with_bias, FactorClock())
            self._consider = (builder, gtsam.NonlinearFactorGraph(), sigma)

    def add(self, measurements: FrameMeasurements) -> None:
        """Add one frame (see `GraphBuilder.add`); no optimisation happens here."""
        t0 = time.perf_counter()
        update = self.builder.add(measurements, prefer="measurement")
        self.graph.push_back(update.factors)
        self.initial.insert(update.values)
        if self._consider is not None:
            self._consider[1].push_back(self._consider[0].add(measurements, "measurement").factors)
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
            raise BackendError(not_started_message(self.builder))
        t0 = time.perf_counter()
        c0 = self.clock.seconds
        self.final_note = None
        initial = gtsam.Values(self.initial)
        if self._result is not None:
            initial.update(self._result)  # warm start: previous solution where it exists
        solution = levenberg_marquardt(
            self.graph,
            initial,
            self.config.max_iterations,
            self.config.relative_error_tol,
            self.config.absolute_error_tol,
        )
        result = solution.values
        t1 = time.perf_counter()
        covariances: Covariances | ConsideredCovariances | None = self._considered(result)
        estimate = None
        if covariances is not None:
            try:
                estimate = estimate_from_values(self.builder, result, covariances)
            except (BackendError, RuntimeError) as exc:
                self.final_note = f"{_PLAIN_COVARIANCES}: {exc}"
        if estimate is None:
            covariances = Covariances(self.graph, result)
            estimate = estimate_from_values(self.builder, result, covariances)
        assert covariances is not None
        self._result, self._covariances, self._estimate = result, covariances, estimate
        for i in range(len(self.builder)):
            self.builder.set_hint(
                i, self._estimate.left_cam_from_target[i], self._estimate.twist[i]
            )
        t2 = time.perf_counter()
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
                    iterations=solution.iterations,
                    error=solution.error,
                )
            )

    def _considered(self, result: gtsam.Values) -> ConsideredCovariances | None:
        """The covariances considering the ring's common disparity error, or None (not
        asked for, no ring in the graph, or not computable: ``final_note`` says why)."""
        if self._consider is None:
            return None
        _, graph, sigma = self._consider
        keys = set(graph.keyVector())
        if DISPARITY_BIAS not in keys:
            return None  # no ring factor: nothing to consider
        values = gtsam.Values(result)
        values.insert(DISPARITY_BIAS, np.zeros(1))
        if not keys <= set(values.keys()):
            self.final_note = f"{_PLAIN_COVARIANCES} (its graph has variables the solution lacks)"
            return None
        try:  # the marginals themselves are computed when the estimate asks for them
            return ConsideredCovariances(graph, values, DISPARITY_BIAS, sigma)
        except (BackendError, RuntimeError) as exc:
            self.final_note = f"{_PLAIN_COVARIANCES}: {exc}"
            return None

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
        n = len(self.builder)
        keys: list[int] = []
        for i in range(n):
            if which in ("pose", "state"):
                keys.append(X(i))
            if which in ("twist", "state"):
                keys.append(V(i))
        poses = {X(i) for i in range(n)}
        n_keys = len(keys)
        assert self._result is not None and self._covariances is not None
        blocks = self._covariances.joint(keys)
        # pose blocks: the graph's X = T^-1 perturbation -> T's (`pose3.state_to_pose_jacobian`)
        J = [
            state_to_pose_jacobian(self._result.atPose3(k)) if k in poses else np.eye(6)
            for k in keys
        ]
        C = np.block([[J[a] @ blocks[a][b] @ J[b].T for b in range(n_keys)] for a in range(n_keys)])
        return 0.5 * (C + C.T)


def not_started_message(builder: GraphBuilder) -> str:
    """Why there is no estimate yet."""
    need = (
        "a pose (loose coupling)"
        if builder.config.coupling == "loose"
        else "the ring and an anchor landmark (tight coupling)"
    )
    return f"no frame with usable measurements yet: the graph starts at a frame with {need}"


def estimate_from_values(
    builder: GraphBuilder, values: gtsam.Values, covariances: Covariances
) -> Estimate:
    """The `Estimate` of every frame from solved graph values and their covariances."""
    n = len(builder)
    states = [values.atPose3(X(i)) for i in range(n)]
    return Estimate(
        frame=np.array(builder.frames),
        t_s=np.array(builder.t_s),
        left_cam_from_target=tuple(from_state(Xi) for Xi in states),
        twist=np.array([values.atVector(V(i)) for i in range(n)]),
        pose_covariance=np.array(
            [state_covariance_to_pose(states[i], covariances.marginal(X(i))) for i in range(n)]
        ),
        twist_covariance=np.array([covariances.marginal(V(i)) for i in range(n)]),
    )
