"""Which stereo-consistent circle is the ring's outer front rim (stereo generalisation).

At acquisition every left/right pair of ring candidates that makes one consistent 3-D circle
is a candidate for the outer front rim. The largest used to win: the outer front rim is the
largest of the rim's own concentric edges (inner rim, rim face edges). But a ring with a wall
also shows edges larger than its rim that lie *behind* it: the wall's base, the outline of
rim + wall, and a cast shadow of the ring on the panel it stands on (measured on the tuning
seeds: benchmarks/ring_diagnosis.py, docs/results/ring_diagnosis_before.md). Their best
circles are larger than the rim, nearly concentric with it, and their centres lie back along
the normal (toward the panel), by up to the wall height. The rim is the front of the ring:
nothing of the ring stands in front of the plane of its front rim but bolt heads.

So a larger consistent circle is refused when a smaller one nests inside it (its centre
within the smaller one's radius, across the normal) and its centre lies behind the smaller
one's plane by more than ``k`` standard deviations of that offset (`behind_rim`). Concentric
edges in the rim's own plane (inner -> outer rim) are not behind, and the larger still wins.

A camera's detector can miss the rim that the other camera found (an arc lost to a shadow's
edge next to it): `transferred_ellipse` carries a candidate of one camera into the other
through the depth of a consistent circle found already (the rim is near it), and the tracker
refines the edge there (`RingTracker.refine_at`); the pair then has to pass the same
consistency test as any other. A transferred circle larger than the one it was carried
through counts only when it lies in that circle's plane around it (`coplanar_outer`): the
other camera's detector found only the rim's inner edge, this camera found the outer one
(tuning seed 9: a noisy sun-lit rim whose outer edge the right camera's fit kept on 65 % of
the perimeter, short of the 70 % asked).
"""

from __future__ import annotations

import math

import numpy as np

from satpose.frontend.conics import ConicError, Ellipse, conic_to_ellipse
from satpose.frontend.measurements import Camera
from satpose.frontend.stereo import (
    Circle3D,
    GeometryFailure,
    StereoRig,
    circle_conic,
    circle_scale,
    cone_circle_candidates,
)


def behind_offset(front: Circle3D, back: Circle3D) -> tuple[float, float]:
    """How far ``back``'s centre lies behind ``front``'s plane [m] (> 0: farther from the
    cameras along ``front``'s normal) and the standard deviation of that offset from both
    circles' centre covariances."""
    n = np.asarray(front.normal, float)
    if n @ front.center > 0:
        n = -n  # toward the cameras
    d = float((front.center - back.center) @ n)
    var = float(n @ (front.covariance[:3, :3] + back.covariance[:3, :3]) @ n)
    return d, math.sqrt(max(var, 0.0))


def nested(inner: Circle3D, outer: Circle3D) -> bool:
    """``outer`` is larger than ``inner`` and its centre lies within ``inner``'s radius of
    ``inner``'s axis."""
    n = np.asarray(inner.normal, float)
    dc = outer.center - inner.center
    across = dc - (dc @ n) * n
    return outer.radius > inner.radius and float(np.linalg.norm(across)) < inner.radius


def behind_rim(front: Circle3D, back: Circle3D, k_sigma: float) -> bool:
    """``back`` is an edge behind the rim ``front`` (its base, the outline of rim and wall, a
    cast shadow), not the rim: nested around it and behind its plane by > ``k_sigma``
    standard deviations."""
    if not nested(front, back):
        return False
    d, s = behind_offset(front, back)
    return d > k_sigma * s


def coplanar_outer(
    inner: Circle3D, outer: Circle3D, k_sigma: float, min_growth: float = 1.03
) -> bool:
    """``outer`` is a larger edge of ``inner``'s own planar face (the rim's outer front edge
    around an inner edge of it): nested around it, at least ``min_growth`` larger, and its
    centre neither behind nor in front of ``inner``'s plane by more than ``k_sigma``
    standard deviations of the offset. An edge found beside the true one at another depth
    fails the last test by far: a circle that one camera's ellipse fixes up to scale moves
    along the line of sight with its radius (3 % larger: 3 % of the range farther)."""
    if not nested(inner, outer) or outer.radius < min_growth * inner.radius:
        return False
    d, s = behind_offset(inner, outer)
    return abs(d) <= k_sigma * s


def front_choice(circles: list[Circle3D], k_sigma: float) -> int:
    """Index of the outer front rim among consistent circles ordered largest first: the
    largest that no smaller candidate shows to lie behind the ring's front (`behind_rim`)."""
    for i, c in enumerate(circles):
        if not any(behind_rim(f, c, k_sigma) for f in circles[i + 1 :]):
            return i
    return len(circles) - 1


def section_image(
    rig: StereoRig,
    source: Camera,
    normal: np.ndarray,
    direction: np.ndarray,
    per_radius: float,
    distance: float,
) -> Ellipse:
    """The image in the other camera of the circle that a circular section of ``source``'s
    cone makes at ``distance``: centre ``distance * direction`` and normal ``normal`` in
    ``source``'s frame, radius ``distance / per_radius`` (`circle_scale`).

    Raises:
        GeometryFailure: the image is not an ellipse (the circle is edge-on or behind).
    """
    dst = Camera.RIGHT if source is Camera.LEFT else Camera.LEFT
    left_from_src = rig.cam_from_left(source).inverse()
    centre = left_from_src.apply((distance * np.asarray(direction, float))[None])[0]
    try:
        return conic_to_ellipse(
            circle_conic(
                rig.intrinsics(dst),
                rig.cam_from_left(dst),
                centre,
                left_from_src.R @ np.asarray(normal, float),
                distance / per_radius,
            )
        )
    except (ConicError, ValueError, np.linalg.LinAlgError) as exc:
        raise GeometryFailure(f"transferred ring candidate is not an ellipse ({exc})") from None


def transferred_ellipse(
    rig: StereoRig, conic: np.ndarray, source: Camera, reference: Circle3D
) -> Ellipse:
    """The image in the other camera of the circle that ``source``'s ellipse ``conic`` shows
    when it lies at ``reference``'s distance with the circular section nearest
    ``reference``'s normal (the cone fixes the circle up to scale; the distance fixes it).

    Raises:
        GeometryFailure: the cone has no circular section, or the image is not an ellipse.
    """
    src_from_left = rig.cam_from_left(source)
    c_ref = src_from_left.apply(reference.center[None])[0]
    n_ref = src_from_left.R @ reference.normal
    K_src = rig.intrinsics(source)
    sections = cone_circle_candidates(K_src, conic)
    n, d = min(sections, key=lambda s: -abs(float(s[0] @ n_ref)))
    return section_image(
        rig, source, n, d, circle_scale(K_src, conic, n, d), float(np.linalg.norm(c_ref))
    )
