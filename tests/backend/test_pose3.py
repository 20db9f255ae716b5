"""The one helper that owns the Pose3 tangent order [rotation, translation]."""

from __future__ import annotations

import gtsam
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from satpose.backend.pose3 import (
    ROT,
    TRANS,
    adjoint,
    exp,
    from_pose3,
    local_error,
    tangent,
    to_pose3,
)
from satpose.datasets.geometry import Rigid3

vec3 = st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=40, deadline=None)
@given(vec3, vec3, vec3, vec3)
def test_round_trips(rv: np.ndarray, t: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    T = Rigid3.from_rotvec(rv, t)
    back = from_pose3(to_pose3(T))
    np.testing.assert_allclose(back.R, T.R, atol=1e-12)
    np.testing.assert_allclose(back.t, T.t, atol=1e-12)
    xi = 0.3 * tangent(w, v)  # |xi| < pi: Log(Exp(xi)) = xi
    np.testing.assert_allclose(local_error(T, exp(T, xi)), xi, atol=1e-9)
    # Ad_T maps a right perturbation to a left one: T Exp(xi) = Exp(Ad_T xi) T.
    left = from_pose3(gtsam.Pose3.Expmap(adjoint(T) @ xi)) @ T
    np.testing.assert_allclose(left.matrix(), exp(T, xi).matrix(), atol=1e-9)


def test_tangent_order_is_rotation_then_translation() -> None:
    T = Rigid3.from_rotvec([0.1, -0.2, 0.3], [1.0, 2.0, 3.0])
    rot_only = exp(T, tangent(np.array([0.0, 0.0, 0.5]), np.zeros(3)))
    np.testing.assert_allclose(rot_only.t, T.t, atol=1e-12)  # a rotation leaves t alone
    trans_only = exp(T, tangent(np.zeros(3), np.array([0.0, 0.0, 0.5])))
    np.testing.assert_allclose(trans_only.R, T.R, atol=1e-12)
    # right perturbation: the translation step is along the target's own z axis
    np.testing.assert_allclose(trans_only.t - T.t, 0.5 * T.R[:, 2], atol=1e-12)
    assert (ROT.start, ROT.stop, TRANS.start, TRANS.stop) == (0, 3, 3, 6)
