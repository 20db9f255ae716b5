"""`satpose.backend.solve.Covariances`: GTSAM's marginals, and the dense QR route when they fail."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from satpose.backend.errors import BackendError
from satpose.backend.solve import ConsideredCovariances, Covariances

A, B = gtsam.symbol("v", 0), gtsam.symbol("v", 1)


def _chain(sigma_b: float | None = 2.0) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """``a`` with a prior (sigma 0.5), ``b - a`` measured (sigma ``sigma_b``; None: no factor
    on ``b``): Cov(a) = 0.25, Cov(b) = 0.25 + sigma_b^2, Cov(a, b) = 0.25."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    v.insert(A, np.zeros(1))
    v.insert(B, np.ones(1))
    g.push_back(gtsam.PriorFactorVector(A, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.5)))
    if sigma_b is not None:
        g.push_back(
            gtsam.BetweenFactorVector(
                A, B, np.ones(1), gtsam.noiseModel.Isotropic.Sigma(1, sigma_b)
            )
        )
    return g, v


class _Failing:
    """Stands in for a `gtsam.Marginals` whose per-variable elimination fails (GTSAM raises
    RuntimeError 'Indeterminate linear system' for a nearly indeterminate variable after
    the object was built: seen on a random-family warm-up, docs/backend.md)."""

    def marginalCovariance(self, key: int) -> np.ndarray:
        raise RuntimeError("Indeterminate linear system detected while working near variable")

    def jointMarginalCovariance(self, keys: gtsam.KeyVector) -> None:
        raise RuntimeError("Indeterminate linear system detected while working near variable")


def test_marginals_exact() -> None:
    cov = Covariances(*_chain())
    assert cov.marginal(A)[0, 0] == pytest.approx(0.25, rel=1e-9)
    assert cov.marginal(B)[0, 0] == pytest.approx(4.25, rel=1e-9)
    J = cov.joint([A, B])
    assert J[0][1][0, 0] == pytest.approx(0.25, rel=1e-9)


@pytest.mark.parametrize("call", ["marginal", "joint"])
def test_a_failing_marginal_falls_back_to_the_dense_route(call: str) -> None:
    cov = Covariances(*_chain())
    cov._marginals = _Failing()  # type: ignore[assignment]
    if call == "marginal":
        assert cov.marginal(B)[0, 0] == pytest.approx(4.25, rel=1e-9)
    else:
        J = cov.joint([A, B])
        assert J[1][1][0, 0] == pytest.approx(4.25, rel=1e-9)
        assert J[0][1][0, 0] == pytest.approx(0.25, rel=1e-9)
    assert cov.marginal(A)[0, 0] == pytest.approx(0.25, rel=1e-9)


def test_an_undetermined_variable_is_a_clear_error() -> None:
    cov = Covariances(*_chain(sigma_b=None))
    cov._marginals = _Failing()  # type: ignore[assignment]
    with pytest.raises(BackendError, match="not determined"):
        cov.marginal(B)


def test_considered_covariance_is_schmidts() -> None:
    """``x`` with a prior (sigma 0.5) and four measurements of ``b - x`` (sigma 0.2) that share
    the error ``b`` (zero-mean, sigma 0.3), solved with ``b = 0``. Oracle, in closed form:
    information of ``x`` without ``b``: ``a = 1/0.25 + 4/0.04``; the solution moves by
    ``(4/0.04)/a`` per unit of ``b``; so the considered variance is ``1/a + 0.09 ((4/0.04)/a)^2``
    (to 1e-12), larger than both the plain ``1/a`` and the estimated-``b`` variance."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    v.insert(A, np.zeros(1))
    v.insert(B, np.zeros(1))
    g.push_back(gtsam.PriorFactorVector(A, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.5)))
    for _ in range(4):
        g.push_back(
            gtsam.BetweenFactorVector(A, B, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.2))
        )
    g.push_back(gtsam.PriorFactorVector(B, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.3)))
    a = 1 / 0.25 + 4 / 0.04
    want = 1 / a + 0.09 * (4 / 0.04 / a) ** 2
    got = ConsideredCovariances(g, v, B, 0.3)
    assert got.marginal(A)[0, 0] == pytest.approx(want, rel=1e-12)
    assert got.joint([A])[0][0][0, 0] == pytest.approx(want, rel=1e-12)
    estimated = Covariances(g, v).marginal(A)[0, 0]
    assert want > estimated > 1 / a
