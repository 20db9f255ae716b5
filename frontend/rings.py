"""Camera pose from a concentric-ring target of known radii (seed 002's on-orbit calibration
check: rings on the servicer, always in the boom camera's view).

Each ring's image conic back-projects to an elliptic cone with two circular sections
(`satpose.frontend.stereo.cone_circle_candidates`); with the ring's known radius each section
gives a centre (`circle_scale`). Concentric coplanar rings share the true section (same
normal, same centre); the false ones differ from ring to ring. So the sections that agree
best across rings give the target's plane; their spread (centre, normal) measures how
consistent the detected rings are. It does not reveal a focal-length error in one view (a 5 %
error changes it by ~5 %, tests/frontend/test_rings.py): the calibration check is the
per-frame pose of the servicer's ring target against the boom camera's nominal mounting.

The rotation about the rings' axis is not observable from circles; what is estimated per
frame is the target centre and normal in the camera frame (5 degrees of freedom).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.frontend.stereo import circle_scale, cone_circle_candidates


@dataclass(frozen=True)
class RingsPose:
    """The concentric-ring target seen by one camera.

    Attributes:
        center_m: target centre in the camera frame (3,), or None.
        normal: unit normal toward the camera (3,), or None.
        normal_spread_deg: largest angle between a ring's normal and the mean normal.
        center_spread_m: largest distance between a ring's centre and the mean centre.
        reason: why there is no pose ("" when found).
    """

    center_m: np.ndarray | None
    normal: np.ndarray | None
    normal_spread_deg: float = math.nan
    center_spread_m: float = math.nan
    reason: str = ""


def rings_pose(K: np.ndarray, conics: Sequence[np.ndarray], radii_m: Sequence[float]) -> RingsPose:
    """Centre and normal of a concentric-ring target from its rings' image conics.

    Args:
        K: 3x3 intrinsics of the undistorted image.
        conics: one 3x3 image conic per ring (any scale and sign).
        radii_m: the rings' known radii [m], same order.

    Returns:
        A `RingsPose`; ``center_m`` is None with a ``reason`` when fewer than two rings are
        given or a conic is not an ellipse in front of the camera.
    """
    if len(conics) != len(radii_m):
        return RingsPose(None, None, reason=f"{len(conics)} conics for {len(radii_m)} radii")
    if len(conics) < 2:
        return RingsPose(None, None, reason="need at least two rings (one ring is two-fold)")
    per_ring = []
    for i, (C, r) in enumerate(zip(conics, radii_m, strict=True)):
        Cm = np.asarray(C, dtype=float)
        if Cm.shape != (3, 3) or not np.all(np.isfinite(Cm)) or not r > 0:
            return RingsPose(None, None, reason=f"ring {i}: invalid conic or radius")
        try:
            cands = []
            for n, d in cone_circle_candidates(K, Cm):
                cands.append((n, r * circle_scale(K, Cm, n, d) * d))
        except SatposeError as exc:
            return RingsPose(None, None, reason=f"ring {i}: {exc}")
        per_ring.append(cands)
    best: tuple[float, np.ndarray, np.ndarray, float, float] | None = None
    scale = float(np.mean([np.linalg.norm(c[0][1]) for c in per_ring]))
    for choice in itertools.product(*per_ring):
        normals = np.array([n for n, _ in choice])
        centres = np.array([c for _, c in choice])
        n_mean = normals.mean(axis=0)
        n_mean /= np.linalg.norm(n_mean)
        c_mean = centres.mean(axis=0)
        ang = float(np.degrees(np.max(np.arccos(np.clip(normals @ n_mean, -1.0, 1.0)))))
        spread = float(np.max(np.linalg.norm(centres - c_mean, axis=1)))
        cost = math.radians(ang) + spread / scale
        if best is None or cost < best[0]:
            best = (cost, c_mean, n_mean, ang, spread)
    assert best is not None
    _, c_mean, n_mean, ang, spread = best
    return RingsPose(c_mean, n_mean, normal_spread_deg=ang, center_spread_m=spread)
