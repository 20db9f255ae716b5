"""Batch solves shared by the estimators: Levenberg-Marquardt and marginal covariances.

GTSAM's `Marginals` factorises with Cholesky. While the twist is known only from its weak
first prior (fewer than two frames that fix a pose), the information matrix spans ~12 orders
of magnitude (the prior's 1 rad/s against the motion prior's mrad, times the 5-7 m lever arm
of the camera) and Cholesky can fail on rounding; `marginal_covariances` then falls back to a
dense QR of the whitened Jacobian, which only needs the Jacobian's condition (~1e6).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from satpose.backend.errors import BackendError


@dataclass(frozen=True)
class Solution:
    """A batch solution: the values, the optimizer's iteration count and the final error."""

    values: gtsam.Values
    iterations: int
    error: float


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    max_iterations: int,
    relative_error_tol: float,
    absolute_error_tol: float,
) -> Solution:
    """Levenberg-Marquardt from ``initial`` (GTSAM's defaults otherwise)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(absolute_error_tol)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = optimizer.optimize()
    return Solution(values, optimizer.iterations(), graph.error(values))


class Covariances:
    """Marginal and joint covariances of a solved graph (in each variable's tangent space)."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        self._marginals: gtsam.Marginals | None = None
        self._dense: np.ndarray | None = None
        self._index: dict[int, slice] = {}
        self._graph, self._values = graph, values
        try:
            self._marginals = gtsam.Marginals(graph, values)
        except RuntimeError:
            self._fall_back()

    def _fall_back(self) -> None:
        """The dense QR route (a covariance, or a clear error), when GTSAM's marginals fail:
        at their construction, or per variable after it succeeded (a nearly indeterminate
        variable: seen on tuning seed 14's warm-up at 1024x768)."""
        self._marginals = None
        graph, values = self._graph, self._values
        ordering = gtsam.Ordering()
        start = 0
        for key in values.keys():
            ordering.push_back(key)
            dim = values.atVector(key).size if _is_vector(values, key) else 6
            self._index[key] = slice(start, start + dim)
            start += dim
        try:
            A, _ = graph.linearize(values).jacobian(ordering)
        except ValueError as exc:  # GTSAM: a variable that no factor involves
            raise BackendError(
                "the estimate is not determined (a variable without factors)"
            ) from exc
        if A.shape[0] < A.shape[1]:
            raise BackendError("the estimate is not determined (fewer residuals than unknowns)")
        R: np.ndarray = np.linalg.qr(A, mode="r")  # type: ignore[assignment]
        if np.min(np.abs(np.diag(R))) <= 1e-12 * np.abs(R).max():
            raise BackendError("the estimate is not determined (singular information matrix)")
        Rinv = np.linalg.solve(R, np.eye(R.shape[0]))
        self._dense = Rinv @ Rinv.T

    def marginal(self, key: int) -> np.ndarray:
        """Marginal covariance of one variable."""
        if self._marginals is not None:
            try:
                return np.asarray(self._marginals.marginalCovariance(key), float)
            except RuntimeError:
                self._fall_back()
        assert self._dense is not None
        s = self._index[key]
        return self._dense[s, s].copy()

    def joint(self, keys: list[int]) -> list[list[np.ndarray]]:
        """Joint marginal covariance of ``keys`` as a nested list of blocks."""
        if self._marginals is not None:
            try:
                J = self._marginals.jointMarginalCovariance(gtsam.KeyVector(keys))
                return [[np.asarray(J.at(a, b), float) for b in keys] for a in keys]
            except RuntimeError:
                self._fall_back()
        assert self._dense is not None
        return [[self._dense[self._index[a], self._index[b]] for b in keys] for a in keys]


class ConsideredCovariances:
    """Covariances of a solution that ignores one scalar error common to many factors (a
    *consider* parameter ``b``, zero-mean with standard deviation ``sigma``), with that
    error's effect added (Schmidt's consider covariance).

    ``graph`` is the solved problem with ``b`` as a variable (``bias_key``) and its prior,
    ``values`` the solution of the problem without it plus ``b = 0``. With the information
    matrix of that graph ``[[A, B], [B^T, c]]`` (``x`` the other variables), the solution
    without ``b`` has covariance ``A^-1`` and moves by ``-A^-1 B`` per unit of ``b``, so its
    covariance considering ``b`` is ``A^-1 + sigma^2 A^-1 B B^T A^-1``. Both come from the
    joint covariance ``S`` of the graph with ``b``: ``A^-1 B = -S_xb / S_bb`` and ``A^-1 =
    S_xx - S_xb S_bx / S_bb``."""

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        bias_key: int,
        sigma: float,
    ) -> None:
        self._base = Covariances(graph, values)
        self._bias = bias_key
        self._var = float(sigma) ** 2

    def joint(self, keys: list[int]) -> list[list[np.ndarray]]:
        """Joint covariance of ``keys`` considering the common error (nested blocks)."""
        blocks = self._base.joint([*keys, self._bias])
        dims = [blocks[a][a].shape[0] for a in range(len(keys))]
        S = np.block(blocks)
        n = sum(dims)
        s_xx, s_xb, s_bb = S[:n, :n], S[:n, n], float(S[n, n])
        if not s_bb > 0:
            raise BackendError("the considered disparity error has no positive variance")
        C = s_xx - np.outer(s_xb, s_xb) / s_bb + self._var * np.outer(s_xb, s_xb) / s_bb**2
        C = 0.5 * (C + C.T)
        edges = np.cumsum([0, *dims])
        return [
            [C[edges[a] : edges[a + 1], edges[b] : edges[b + 1]] for b in range(len(keys))]
            for a in range(len(keys))
        ]

    def marginal(self, key: int) -> np.ndarray:
        """Marginal covariance of one variable considering the common error."""
        return self.joint([key])[0][0]


def _is_vector(values: gtsam.Values, key: int) -> bool:
    try:
        values.atPose3(key)
    except RuntimeError:
        return True
    return False
