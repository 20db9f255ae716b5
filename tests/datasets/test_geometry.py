"""Rigid transforms and rotations: round trips and group properties (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from satpose.datasets.geometry import (
    GeometryError,
    Rigid3,
    matrix_to_quat_xyzw,
    matrix_to_rotvec,
    quat_xyzw_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
    skew,
)

finite = st.floats(-10, 10, allow_nan=False)
vec3 = arrays(np.float64, 3, elements=finite)
# Rotation vectors with angle < pi - 1e-3, where the logarithm is unique.
rotvecs = vec3.map(lambda v: v / max(1.0, np.linalg.norm(v) / (np.pi - 1e-3)))


@given(rotvecs)
def test_exp_log_round_trip(rv: np.ndarray) -> None:
    R = rotvec_to_matrix(rv)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(matrix_to_rotvec(R), rv, atol=1e-9)
    assert rotation_angle(R) == pytest.approx(np.linalg.norm(rv), abs=1e-9)


@given(rotvecs)
def test_quaternion_round_trip_scalar_last(rv: np.ndarray) -> None:
    R = rotvec_to_matrix(rv)
    q = matrix_to_quat_xyzw(R)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12) and q[3] >= 0
    np.testing.assert_allclose(quat_xyzw_to_matrix(q), R, atol=1e-12)


def test_quaternion_order_is_xyzw() -> None:
    # 90 deg about z: q = [0, 0, sin 45, cos 45] in x, y, z, w order.
    q = matrix_to_quat_xyzw(rotvec_to_matrix([0, 0, np.pi / 2]))
    np.testing.assert_allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


@given(rotvecs, vec3, rotvecs, vec3, arrays(np.float64, (5, 3), elements=finite))
@settings(max_examples=50)
def test_composition_and_inverse(r1, t1, r2, t2, pts) -> None:  # type: ignore[no-untyped-def]
    a_from_b = Rigid3.from_rotvec(r1, t1)
    b_from_c = Rigid3.from_rotvec(r2, t2)
    a_from_c = a_from_b @ b_from_c
    np.testing.assert_allclose(a_from_c.apply(pts), a_from_b.apply(b_from_c.apply(pts)), atol=1e-9)
    np.testing.assert_allclose((a_from_b @ a_from_b.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(a_from_c.matrix(), a_from_b.matrix() @ b_from_c.matrix(), atol=1e-9)


def test_skew_is_cross_product() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 3))
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b), atol=1e-15)


@pytest.mark.parametrize("R", [np.diag([1.0, 1.0, -1.0]), np.eye(3) * 2, np.full((3, 3), np.nan)])
def test_invalid_rotation_is_rejected(R: np.ndarray) -> None:
    with pytest.raises(GeometryError):
        Rigid3(R=R, t=np.zeros(3))


def test_rigid_is_immutable() -> None:
    T = Rigid3.identity()
    with pytest.raises(ValueError):
        T.t[0] = 1.0
