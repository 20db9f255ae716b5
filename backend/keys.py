"""GTSAM keys of every variable the backend creates (the only place they are defined).

- ``X(k)``: ``left_cam_from_target`` at frame ``k`` (Pose3).
- ``V(k)``: body twist ``[omega, v]`` of the target at frame ``k`` (6-vector, target frame).
- ``L(j)``: landmark with track id ``j`` in the target frame (3-vector) [m].
- ``R(0)``: the docking ring's radius (1-vector) [m], shared by all frames.
"""

from __future__ import annotations

from gtsam.symbol_shorthand import L, R, V, X

__all__ = ["RADIUS", "L", "V", "X"]

RADIUS = R(0)
