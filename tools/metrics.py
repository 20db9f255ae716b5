"""Accuracy metrics against ground truth, in the terms of seed 000's tables.

A non-cooperative estimator defines its own target frame: its origin and z axis (the ring
centre and normal) are physical, but its x axis points at whatever landmark it anchored on. The
rotation errors are therefore reported both raw and after one constant body-frame rotation
``R_off`` (``R_est R_off ~ R_true``), the least-squares one over the whole sequence.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from satpose.datasets.geometry import Rigid3, matrix_to_rotvec, rotation_angle

RANGE_BANDS_M: tuple[tuple[float, float], ...] = ((7.0, 5.0), (5.0, 3.0), (3.0, 0.0))
"""Seed 000's range bands (its Table 2), far to near; a frame belongs to ``hi >= r > lo``
(7 m itself counts in the first band)."""


def body_rotation_offset(est: Sequence[Rigid3], truth: Sequence[Rigid3]) -> np.ndarray:
    """The constant rotation ``R_off`` minimising ``sum ||R_est R_off - R_true||_F^2``."""
    M = sum((e.R.T @ t.R for e, t in zip(est, truth, strict=True)), np.zeros((3, 3)))
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


@dataclass(frozen=True, kw_only=True)
class PoseErrors:
    """Per-frame errors of an estimated trajectory.

    Attributes:
        position_m: |t_est - t_true| (the ring centre's position error) [m].
        rotation_deg: rotation error after the constant body-frame offset [deg].
        rotation_raw_deg: rotation error without it [deg].
        range_m: true range |t_true| [m].
        offset_deg: angle of the body-frame offset [deg].
    """

    position_m: np.ndarray
    rotation_deg: np.ndarray
    rotation_raw_deg: np.ndarray
    range_m: np.ndarray
    offset_deg: float


def pose_errors(
    est: Sequence[Rigid3], truth: Sequence[Rigid3], offset: np.ndarray | None = None
) -> PoseErrors:
    """Errors of matched pose lists (same frames, same order)."""
    R_off = body_rotation_offset(est, truth) if offset is None else offset
    pos = np.array([np.linalg.norm(e.t - t.t) for e, t in zip(est, truth, strict=True)])
    rot = np.degrees(
        [rotation_angle((e.R @ R_off).T @ t.R) for e, t in zip(est, truth, strict=True)]
    )
    raw = np.degrees([rotation_angle(e.R.T @ t.R) for e, t in zip(est, truth, strict=True)])
    rng = np.array([np.linalg.norm(t.t) for t in truth])
    return PoseErrors(
        position_m=pos,
        rotation_deg=np.asarray(rot),
        rotation_raw_deg=np.asarray(raw),
        range_m=rng,
        offset_deg=float(np.degrees(rotation_angle(R_off))),
    )


@dataclass(frozen=True, kw_only=True)
class SignedErrors:
    """Per-frame signed errors, the terms a bias shows in (their means over a sequence are
    the bias, their standard deviations the random part).

    Attributes:
        depth_m: position error along the true line of sight ``t_true / |t_true|``
            (+: the estimate is farther than the truth) [m].
        lateral_m: the rest of the position error, (N, 2) in the camera's x and y after the
            line-of-sight component is removed [m].
        tilt_deg: angle between the ring normal (body z) and the true direction to the
            camera, estimate minus truth (+: the estimate sees the ring more obliquely; a
            position error alone leaves it 0) [deg].
        normal_deg: angle between the estimated and the true ring normal [deg].
    """

    depth_m: np.ndarray
    lateral_m: np.ndarray
    tilt_deg: np.ndarray
    normal_deg: np.ndarray


def signed_errors(est: Sequence[Rigid3], truth: Sequence[Rigid3]) -> SignedErrors:
    """Depth, lateral, tilt and normal errors of matched pose lists (``left_cam_from_target``;
    the body z axis is the ring normal in both, whatever the estimate's x axis)."""

    def tilt(n: np.ndarray, los: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip(-(n @ los), -1.0, 1.0))))

    depth, lateral, dtilt, normal = [], [], [], []
    for e, t in zip(est, truth, strict=True):
        los = t.t / np.linalg.norm(t.t)
        d = e.t - t.t
        depth.append(float(d @ los))
        lateral.append((d - (d @ los) * los)[:2])
        dtilt.append(tilt(e.R[:, 2], los) - tilt(t.R[:, 2], los))
        ne, nt = e.R[:, 2], t.R[:, 2]
        normal.append(float(np.degrees(np.arctan2(np.linalg.norm(np.cross(ne, nt)), ne @ nt))))
    return SignedErrors(
        depth_m=np.asarray(depth),
        lateral_m=np.asarray(lateral).reshape(-1, 2),
        tilt_deg=np.asarray(dtilt),
        normal_deg=np.asarray(normal),
    )


def relative_errors(
    est: Sequence[Rigid3], truth: Sequence[Rigid3], offset: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the motion between consecutive poses (seed 000's inter-frame errors):
    translation [m] and rotation [deg] of ``(T_k^-1 T_k+1)_est`` vs the truth, both expressed
    in the (offset-aligned) body frame. Arrays of length N - 1."""
    R_off = body_rotation_offset(est, truth) if offset is None else offset
    off = Rigid3(R=R_off, t=np.zeros(3))
    e_al = [e @ off for e in est]
    dt, dr = [], []
    for k in range(len(est) - 1):
        de = e_al[k].inverse() @ e_al[k + 1]
        dg = truth[k].inverse() @ truth[k + 1]
        dt.append(np.linalg.norm(de.t - dg.t))
        dr.append(np.degrees(np.linalg.norm(matrix_to_rotvec(de.R.T @ dg.R))))
    return np.array(dt), np.array(dr)


def band_mask(range_m: np.ndarray, band: tuple[float, float]) -> np.ndarray:
    """Frames whose true range lies in ``(lo, hi]`` (``band = (hi, lo)``)."""
    hi, lo = band
    return (range_m <= hi + 1e-9) & (range_m > lo)


def band_label(band: tuple[float, float]) -> str:
    hi, lo = band
    return f"{hi:g}-{lo:g} m" if lo > 0 else f"< {hi:g} m"


SPEC_T_THRESHOLD = 2.173e-3
"""ESA SPEC: relative translation errors below this (2.173 mm per metre) count as zero."""
SPEC_Q_THRESHOLD_DEG = 0.169
"""ESA SPEC: rotation errors below this count as zero [deg]."""


@dataclass(frozen=True, kw_only=True)
class SpecScore:
    """The ESA pose-estimation challenge's score (SPEC, Kisantal et al. 2020, with the
    thresholds of its 2021 edition) over matched frames.

    Per frame ``e_t = |t_est - t_true| / |t_true|`` (zero below `SPEC_T_THRESHOLD`) and
    ``e_q = 2 acos |<q_est, q_true>|`` [rad] (the rotation angle between the two; zero below
    `SPEC_Q_THRESHOLD_DEG`); the score is the mean of ``e_t + e_q``. Lower is better.

    Attributes:
        score: mean of ``e_t + e_q``.
        translation: mean ``e_t``.
        rotation: mean ``e_q`` [rad].
    """

    score: float
    translation: float
    rotation: float


def spec_score(
    est: Sequence[Rigid3], truth: Sequence[Rigid3], offset: np.ndarray | None = None
) -> SpecScore:
    """`SpecScore` of matched pose lists. ``offset``: the constant body-frame rotation applied
    to the estimate first (`body_rotation_offset`; a non-cooperative estimate chooses its own
    axes); None: none (a cooperative target's known frame)."""
    R_off = np.eye(3) if offset is None else offset
    e_t = np.array(
        [np.linalg.norm(e.t - t.t) / np.linalg.norm(t.t) for e, t in zip(est, truth, strict=True)]
    )
    e_q = np.array([rotation_angle((e.R @ R_off).T @ t.R) for e, t in zip(est, truth, strict=True)])
    e_t = np.where(e_t < SPEC_T_THRESHOLD, 0.0, e_t)
    e_q = np.where(e_q < np.radians(SPEC_Q_THRESHOLD_DEG), 0.0, e_q)
    return SpecScore(
        score=float(np.mean(e_t + e_q)),
        translation=float(np.mean(e_t)),
        rotation=float(np.mean(e_q)),
    )
