"""GTSAM keys of every variable the backend creates (the only place they are defined).

- ``X(k)``: the left camera's pose in the target frame at frame ``k``, ``target_from_left_cam``
  (Pose3; the inverse of the ``left_cam_from_target`` the backend reports, see `pose3`).
- ``V(k)``: body twist ``[omega, v]`` of the target at frame ``k`` (6-vector, target frame).
- ``L(j)``: landmark with track id ``j`` in the target frame (3-vector) [m].
- ``R(k)``: the radius (1-vector) [m] of the ``k``-th circle of the docking ring the frontend
  has measured, shared by every frame that measured that circle (the rim's outer and inner
  front edges are concentric circles of different radii; the frontend may track either).
- ``DISPARITY_BIAS``: a disparity error [px] of the ring's edges common to every frame (1-vector):
  the two cameras see the rim's edge profile differently (a wall, a shadow's sliver, a glint
  seen from two viewpoints), a bias that averaging over frames does not remove
  (`satpose.backend.factors.ring_factor`).
- ``SHARED_BIAS``: the biases (one per group, a vector) that a track's image quantities of one
  group share over all its frames, in their sigmas (e.g. a strut's taper, measured through the
  same shading and blur in every frame; `satpose.backend.labelling.fit_track`).
- ``RIG``: the right camera's pose in the left camera's frame as the landmarks' right-image
  observations see it (Pose3): the calibrated ``left_from_right`` with its yaw free within a
  prior, i.e. a disparity error common to every landmark (a rig whose cameras turned against
  each other since calibration, or corner and feature locators biased differently in the two
  images; `satpose.backend.factors.landmark_factors`).
"""

from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import L, R, V, X

__all__ = [
    "BIAS_CHAR",
    "DISPARITY_BIAS",
    "LANDMARK_CHAR",
    "PLANE_NORMAL",
    "POSE_CHAR",
    "RADIUS",
    "RADIUS_CHAR",
    "RIG",
    "RIG_CHAR",
    "SHARED_BIAS",
    "TWIST_CHAR",
    "L",
    "R",
    "V",
    "X",
]

RADIUS = R(0)
"""The first circle's radius."""
DISPARITY_BIAS = gtsam.symbol("d", 0)
"""The ring edges' common disparity bias [px]."""
SHARED_BIAS = gtsam.symbol("s", 0)
"""A track's per-group image biases (`satpose.backend.labelling.fit_track`)."""
PLANE_NORMAL = gtsam.symbol("n", 0)
"""A track's normal of a plane rigid with the target, as a 2-vector offset in the tangent
plane of a reference direction (`satpose.backend.labelling.fit_track`)."""
RIG = gtsam.symbol("c", 0)
"""The rig's ``left_from_right`` as the landmarks see it."""

# The symbol characters (per-type settings such as iSAM2's relinearisation thresholds).
POSE_CHAR = chr(gtsam.Symbol(X(0)).chr())
TWIST_CHAR = chr(gtsam.Symbol(V(0)).chr())
LANDMARK_CHAR = chr(gtsam.Symbol(L(0)).chr())
RADIUS_CHAR = chr(gtsam.Symbol(RADIUS).chr())
BIAS_CHAR = chr(gtsam.Symbol(DISPARITY_BIAS).chr())
RIG_CHAR = chr(gtsam.Symbol(RIG).chr())
