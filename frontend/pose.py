"""The per-frame pose of a non-cooperative target and the target frame it is expressed in.

The target frame is not known in advance. It is fixed at the first frame with a ring and a
landmark (seed 000 eq. 9) whose ring was seen before (the last frame with a ring saw one
circle with it: radius within ``confirm_radius_gap``, centre within a radius): origin = ring
centre, z = ring normal, x toward the *anchor* landmark (a panel corner if one is visible,
else a component, else an ORB feature). The confirmation costs the first frame's pose;
without it a first frame that took another circle for the ring (a round component, 0.22 m
for a 0.60 m ring on tuning seed 5) fixed the frame on that circle, 56 deg from every later
pose. Every landmark seen with a 3-D point is then *mapped*: its coordinates in the target
frame are kept (a running mean over its first ``map_observations`` sightings), so that the
x axis survives when the anchor leaves the view.

Per frame, `TargetFrameTracker.update` returns a `PoseMeasurement`:

- ``eq9`` (the paper): ring + one mapped landmark — the anchor if visible, else the mapped
  landmark farthest from the ring axis, whose map azimuth gives the x axis.
- ``landmarks`` (default): weighted least squares over SE(3) of the ring centre, ring normal
  and every mapped landmark, each with its covariance (Gauss-Newton); covariance from the
  normal equations. With no ring, the landmarks alone (>= 3) determine the pose.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from satpose.datasets.geometry import Rigid3, absolute_orientation, rotvec_to_matrix, skew
from satpose.frontend.measurements import (
    LandmarkKind,
    LandmarkMeasurement,
    PoseMeasurement,
    PoseMethod,
    RingMeasurement,
)
from satpose.frontend.stereo import (
    GeometryFailure,
    pose_covariance_ring_landmark,
    pose_from_ring_landmark,
    pose_tangent_error,
    tangent_basis,
)

KIND_PRIORITY = {LandmarkKind.CORNER: 0, LandmarkKind.COMPONENT: 1, LandmarkKind.ORB: 2}


@dataclass(frozen=True, kw_only=True)
class PoseConfig:
    """Per-frame pose settings.

    Attributes:
        method: ``landmarks`` (ring + all mapped landmarks, least squares) or ``eq9`` (seed
            000: ring + one landmark).
        map_observations: a landmark's target-frame coordinates are the mean of its first
            this many sightings, then frozen (a frozen map cannot drift).
        min_axis_distance_m: landmarks closer than this to the ring axis carry no usable
            azimuth and are not used as the eq. 9 landmark.
        map_sigma_m: standard deviation added to every mapped landmark's covariance (on top of
            the map's own, propagated from triangulation and the mapping poses) [m].
        max_landmark_residual_sigma: landmarks whose residual exceeds this many standard
            deviations are dropped as mismatches and the fit repeated.
        min_landmarks_without_ring: landmarks needed for a pose when the ring is lost.
        confirm_radius_gap: the target frame is fixed only on a ring that the last frame with
            a ring measured too: radius within this fraction (the frontend's own radius changes by
            < 1 % between frames; ``StereoRingConfig.max_radius_change`` is 4 %) and centre
            within the larger radius. None: on the first ring (seed 000's rule).
        map_error: how the error of the poses a landmark was mapped with enters the pose fit.
            ``independent`` (default): added to each landmark's covariance as if it were
            independent between landmarks and averaged down over the mapping sightings.
            ``shared``: one rigid motion of the whole map, a nuisance of the fit with the
            mapping poses' covariance (`_gauss_newton`); the per-frame covariance is then
            honest with a map the tracker built itself (simulated NEES inside its chi2
            bound, ``independent`` far above it: tests/frontend/test_pose.py), at about the
            same accuracy on rendered sequences (docs/frontend.md, "Map error").
    """

    method: Literal["landmarks", "eq9"] = "landmarks"
    map_observations: int = 5
    min_axis_distance_m: float = 0.08
    map_sigma_m: float = 0.001
    max_landmark_residual_sigma: float = 5.0
    min_landmarks_without_ring: int = 3
    map_error: Literal["independent", "shared"] = "independent"
    confirm_radius_gap: float | None = 0.04

    def __post_init__(self) -> None:
        gap = self.confirm_radius_gap
        if gap is not None and not 0 < gap < 1:
            raise ValueError(f"pose.confirm_radius_gap must be in (0, 1) or null, got {gap}")
        if self.map_error not in ("independent", "shared"):
            raise ValueError(
                f"pose.map_error must be 'independent' or 'shared', got {self.map_error!r}"
            )


@dataclass
class _MapPoint:
    """A mapped landmark.

    Its error has two parts (`_update_map`): the triangulation noise of its sightings, which
    is independent between landmarks and averages down over sightings, and the error of the
    poses it was mapped with, which moves every landmark mapped at about the same time by one
    rigid motion and does not average down over consecutive sightings (``pose_covariance``,
    6x6 over [rotation, translation], the mapping poses' mean covariance). ``covariance``
    (target frame) holds the first part, and with ``map_error: independent`` the second
    folded in as well."""

    kind: LandmarkKind
    position: np.ndarray  # target frame [m]
    count: int = 1
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # target frame
    information: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


@dataclass
class TargetFrameTracker:
    """Defines the target frame and measures the target's pose in it, frame after frame."""

    config: PoseConfig = field(default_factory=PoseConfig)
    anchor_id: int | None = None
    map: dict[int, _MapPoint] = field(default_factory=dict)
    _previous_ring: RingMeasurement | None = field(default=None, repr=False)

    def update(
        self, ring: RingMeasurement | None, landmarks: Sequence[LandmarkMeasurement]
    ) -> tuple[PoseMeasurement | None, str | None]:
        """Pose of this frame and update the map. Returns ``(pose, None)`` or ``(None, reason)``."""
        pts = [lm for lm in landmarks if lm.point_m is not None and lm.covariance is not None]
        previous = self._previous_ring
        if ring is not None:
            self._previous_ring = ring
        try:
            if self.anchor_id is None:
                pose, waiting = self._bootstrap(ring, pts, previous)
                if waiting is not None:
                    return None, waiting
            elif self.config.method == "eq9":
                pose = self._eq9(ring, pts)
            else:
                pose = self._least_squares(ring, pts)
        except GeometryFailure as exc:
            return None, f"pose: {exc}"
        if pose is None:
            if ring is None:
                return None, "pose: no ring and too few mapped landmarks"
            return None, "pose: no landmark with a 3-D point to fix the x axis"
        self._update_map(pose, pts)
        return pose, None

    # -- bootstrap ---------------------------------------------------------------------------

    def _bootstrap(
        self,
        ring: RingMeasurement | None,
        pts: list[LandmarkMeasurement],
        previous: RingMeasurement | None,
    ) -> tuple[PoseMeasurement | None, str | None]:
        """The first pose, which fixes the target frame, and None; ``(None, None)`` without a
        ring or without a landmark off its axis (the x axis); ``(None, reason)`` before the
        ring's second sighting (``confirm_radius_gap``)."""
        if ring is None:
            return None, None
        usable = [lm for lm in pts if _axis_distance(ring, lm) >= self.config.min_axis_distance_m]
        if not usable:
            return None, None
        gap = self.config.confirm_radius_gap
        if gap is not None and (previous is None or not same_circle(previous, ring, gap)):
            return None, (
                f"pose: the target frame waits for a second sighting of the ring "
                f"(radius {ring.radius_m:.3f} m)"
            )
        anchor = min(usable, key=lambda lm: (KIND_PRIORITY[lm.kind], lm.track_id))
        self.anchor_id = anchor.track_id
        return self._pose_eq9(ring, anchor, azimuth=0.0), None

    # -- seed 000 eq. 9 ----------------------------------------------------------------------

    def _pose_eq9(
        self, ring: RingMeasurement, lm: LandmarkMeasurement, azimuth: float
    ) -> PoseMeasurement:
        assert lm.point_m is not None and lm.covariance is not None
        T = pose_from_ring_landmark(ring.center_m, ring.normal, lm.point_m)
        # The landmark sits at `azimuth` about z in the target frame: rotate x back onto it.
        T = Rigid3(R=T.R @ rotvec_to_matrix(np.array([0.0, 0.0, -azimuth])), t=T.t)
        cov = pose_covariance_ring_landmark(
            ring.center_m, ring.normal, ring.covariance, lm.point_m, lm.covariance
        )
        # The covariance was computed in the landmark-aligned frame; rotate it into T's frame.
        Rz = rotvec_to_matrix(np.array([0.0, 0.0, azimuth]))
        A = np.zeros((6, 6))
        A[:3, :3] = Rz
        A[3:, 3:] = Rz
        return PoseMeasurement(
            left_cam_from_target=T, covariance=A @ cov @ A.T, method=PoseMethod.RING_LANDMARK
        )

    def _eq9(
        self, ring: RingMeasurement | None, pts: list[LandmarkMeasurement]
    ) -> PoseMeasurement | None:
        if ring is None:
            return None
        mapped = [
            lm
            for lm in pts
            if lm.track_id in self.map
            and np.hypot(*self.map[lm.track_id].position[:2]) >= self.config.min_axis_distance_m
        ]
        if not mapped:
            return None
        anchor = [lm for lm in mapped if lm.track_id == self.anchor_id]
        lm = (
            anchor[0]
            if anchor
            else max(mapped, key=lambda m: np.hypot(*self.map[m.track_id].position[:2]))
        )
        p = self.map[lm.track_id].position
        return self._pose_eq9(ring, lm, azimuth=math.atan2(p[1], p[0]))

    # -- least squares -----------------------------------------------------------------------

    def _least_squares(
        self, ring: RingMeasurement | None, pts: list[LandmarkMeasurement]
    ) -> PoseMeasurement | None:
        mapped = [lm for lm in pts if lm.track_id in self.map]
        if ring is None and len(mapped) < self.config.min_landmarks_without_ring:
            return None
        if ring is not None and not any(
            np.hypot(*self.map[lm.track_id].position[:2]) >= self.config.min_axis_distance_m
            for lm in mapped
        ):
            return None
        init = self._initial_pose(ring, mapped)
        for _ in range(3):  # drop gross mismatches, refit
            T, info, res = _gauss_newton(
                init,
                ring,
                mapped,
                self.map,
                self.config.map_sigma_m,
                shared_map_error=self.config.map_error == "shared",
            )
            bad = res > self.config.max_landmark_residual_sigma
            if not bad.any() or len(mapped) - int(bad.sum()) < (1 if ring is not None else 3):
                break
            mapped = [lm for lm, b in zip(mapped, bad, strict=True) if not b]
            init = T
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            raise GeometryFailure("the pose is not constrained") from None
        method = PoseMethod.RING_LANDMARKS if ring is not None else PoseMethod.ORB
        if ring is not None and all(lm.kind == LandmarkKind.ORB for lm in mapped):
            method = PoseMethod.RING_ORB
        return PoseMeasurement(
            left_cam_from_target=T, covariance=0.5 * (cov + cov.T), method=method
        )

    def _initial_pose(
        self, ring: RingMeasurement | None, mapped: list[LandmarkMeasurement]
    ) -> Rigid3:
        if ring is not None:
            far = max(mapped, key=lambda m: np.hypot(*self.map[m.track_id].position[:2]))
            p = self.map[far.track_id].position
            return self._pose_eq9(ring, far, math.atan2(p[1], p[0])).left_cam_from_target
        src = np.array([self.map[lm.track_id].position for lm in mapped])
        dst = np.array([lm.point_m for lm in mapped])
        return _umeyama(src, dst)

    # -- relocalisation ---------------------------------------------------------------------------

    def relocalize(
        self,
        ring: RingMeasurement,
        landmarks: Sequence[LandmarkMeasurement],
        predicted: Rigid3 | None = None,
        gate_m: float = 0.03,
        angle_tol_deg: float = 3.0,
        max_prediction_error_deg: float = 45.0,
        min_support_margin: int = 2,
    ) -> dict[int, int]:
        """Re-identify landmarks after tracking was lost: ``{new track id: mapped id}``.

        The ring fixes the origin and z; the unknown rotation about z is the angle on which
        most (detected, mapped) pairs of the same kind agree, each pair matching in distance
        from the axis and height above the ring plane within ``gate_m``. Needs two agreeing
        pairs; returns ``{}`` otherwise.

        A symmetric landmark set (a panel's four corners, at one distance from the axis, are
        symmetric under a half turn) makes several angles about equally likely, and a noisy
        map can even favour the wrong one. So only angles within ``max_prediction_error_deg``
        of the predicted pose's (``predicted``, left_cam_from_target; all angles without
        one) compete, and the best must be supported by ``min_support_margin`` more
        landmarks than the next; otherwise nothing is re-identified (``{}``, the frame gets no
        pose) rather than the target frame being turned.
        """
        pts = [
            lm
            for lm in landmarks
            if lm.point_m is not None
            and lm.kind != LandmarkKind.ORB
            and lm.track_id not in self.map
        ]
        mapped = [(tid, mp) for tid, mp in self.map.items() if mp.kind != LandmarkKind.ORB]
        if len(pts) < 2 or len(mapped) < 2:
            return {}
        n = ring.normal
        x0, y0 = tangent_basis(n)
        votes = []
        for lm in pts:
            assert lm.point_m is not None
            d = lm.point_m - ring.center_m
            a = math.atan2(float(d @ y0), float(d @ x0))
            rho, h = math.hypot(float(d @ x0), float(d @ y0)), float(d @ n)
            for tid, mp in mapped:
                if mp.kind != lm.kind:
                    continue
                p = mp.position
                if abs(math.hypot(p[0], p[1]) - rho) > gate_m or abs(p[2] - h) > gate_m:
                    continue
                votes.append(((a - math.atan2(p[1], p[0])) % (2 * math.pi), lm.track_id, tid))
        if len(votes) < 2:
            return {}
        tol = math.radians(angle_tol_deg)

        def gap(a: float, b: float) -> float:
            return abs((a - b + math.pi) % (2 * math.pi) - math.pi)

        # Each vote's angle with the distinct landmarks that agree with it, best first; then
        # the distinct hypotheses (angles farther apart than the agreement tolerance) that
        # two or more landmarks support.
        groups = sorted(
            (
                (len({v[1] for v in group}), psi, group)
                for psi, _, _ in votes
                for group in [[v for v in votes if gap(v[0], psi) < tol]]
            ),
            key=lambda g: -g[0],
        )
        hypotheses: list[tuple[int, float, list[tuple[float, int, int]]]] = []
        for n, psi, group in groups:
            if n >= 2 and all(gap(psi, other) >= 2 * tol for _, other, _ in hypotheses):
                hypotheses.append((n, psi, group))
        if predicted is not None:
            x = predicted.R[:, 0]
            psi_pred = math.atan2(float(x @ y0), float(x @ x0))
            limit = math.radians(max_prediction_error_deg)
            hypotheses = [h for h in hypotheses if gap(h[1], psi_pred) < limit]
        if not hypotheses:
            return {}
        if len(hypotheses) > 1 and hypotheses[1][0] > hypotheses[0][0] - min_support_margin:
            return {}  # two rotations explain the landmarks about equally well
        best = hypotheses[0][2]
        mapping: dict[int, int] = {}
        used: set[int] = set()
        for _, new, old in sorted(best, key=lambda v: v[1]):
            if new not in mapping and old not in used:
                mapping[new] = old
                used.add(old)
        return mapping

    # -- map -----------------------------------------------------------------------------------

    def _update_map(self, pose: PoseMeasurement, pts: list[LandmarkMeasurement]) -> None:
        """Each landmark's target-frame position over its first ``map_observations`` sightings
        (an information-weighted mean) and its covariance; ``independent`` folds the mapping
        pose's covariance into each sighting's, ``shared`` keeps it apart as the mapping
        poses' mean (see `_MapPoint`, `PoseConfig.map_error`)."""
        T = pose.left_cam_from_target
        target_from_cam = T.inverse()
        shared = self.config.map_error == "shared"
        Ct = pose.covariance[3:, 3:]  # translation, target axes (right perturbation)
        Cr = pose.covariance[:3, :3]
        for lm in pts:
            assert lm.point_m is not None and lm.covariance is not None
            p = target_from_cam.apply(lm.point_m)
            # p = R^T (X - t): X's noise rotated into the target frame, plus (independent)
            # the pose's error moving p by dt and by the rotation error about the origin.
            C = T.R.T @ lm.covariance @ T.R
            if not shared:
                C = C + Ct + skew(p) @ Cr @ skew(p).T
            W = np.linalg.inv(C + np.eye(3) * 1e-12)
            entry = self.map.get(lm.track_id)
            if entry is None:
                self.map[lm.track_id] = _MapPoint(
                    kind=lm.kind,
                    position=p,
                    covariance=C,
                    information=W,
                    pose_covariance=pose.covariance.copy(),
                )
            elif entry.count < self.config.map_observations:
                info = entry.information + W
                cov = np.linalg.inv(info)
                entry.position = cov @ (entry.information @ entry.position + W @ p)
                entry.information, entry.covariance = info, cov
                n = entry.count
                entry.pose_covariance = (entry.pose_covariance * n + pose.covariance) / (n + 1)
                entry.count += 1


def same_circle(a: RingMeasurement, b: RingMeasurement, radius_gap: float) -> bool:
    """Are two rings (of two frames) one circle? Radii within ``radius_gap`` (relative to the
    smaller) and centres within the larger radius of each other."""
    r0, r1 = sorted((a.radius_m, b.radius_m))
    if (r1 - r0) / r0 > radius_gap:
        return False
    return bool(np.linalg.norm(a.center_m - b.center_m) <= r1)


def _axis_distance(ring: RingMeasurement, lm: LandmarkMeasurement) -> float:
    assert lm.point_m is not None
    d = lm.point_m - ring.center_m
    return float(np.linalg.norm(d - (d @ ring.normal) * ring.normal))


def _umeyama(src: np.ndarray, dst: np.ndarray) -> Rigid3:
    """Least-squares rigid transform with ``dst ~ R src + t`` (`absolute_orientation`)."""
    sv = np.linalg.svd(src - src.mean(axis=0), compute_uv=False)
    if len(src) < 3 or sv[1] <= 1e-9 * max(float(sv[0]), 1e-12):
        raise GeometryFailure("degenerate landmark configuration (collinear)")
    R, t = absolute_orientation(src, dst)
    return Rigid3(R=R, t=t)


def _gauss_newton(
    T: Rigid3,
    ring: RingMeasurement | None,
    mapped: list[LandmarkMeasurement],
    world: dict[int, _MapPoint],
    map_sigma: float,
    shared_map_error: bool = True,
    iterations: int = 6,
) -> tuple[Rigid3, np.ndarray, np.ndarray]:
    """Weighted least squares on SE(3) (right perturbation ``T Exp([w, v])``) with the map's
    shared error as a nuisance.

    The ring sees the pose ``T``; the landmarks see ``T_L = T Exp(d)``, the pose in the map's
    frame as it was mapped: ``d`` is the error the mapping poses left in the whole map
    (`_MapPoint`), zero-mean with the mean mapping-pose covariance of the landmarks used.
    Residuals: ring centre ``t - c`` (3, ring centre covariance), ring normal ``B^T R e_z``
    with ``B`` a tangent basis of the measured normal (2, the normal covariance projected on
    ``B``), landmark ``R_L p + t_L - X`` (3 each, triangulation + map covariance), and the
    prior on ``d``. With ``shared_map_error`` False (``map_error: independent``, or a map with
    no mapping-pose covariance, e.g. one seeded from truth) there is no ``d``: ``T_L = T``.

    Returns:
        (pose ``T``, its information matrix 6x6 with ``d`` marginalised, per-landmark
        Mahalanobis residual norms).
    """
    ez = np.array([0.0, 0.0, 1.0])
    ring_blocks = []
    if ring is not None:
        B = np.c_[tangent_basis(ring.normal)]  # 3x2
        ring_blocks = [
            (
                np.linalg.inv(ring.covariance[:3, :3]),
                np.linalg.inv(B.T @ ring.covariance[3:6, 3:6] @ B),
                B,
            )
        ]
    # Landmarks, vectorised: map positions P (M, 3), observations X (M, 3), weights W (M, 3, 3).
    P = np.array([world[lm.track_id].position for lm in mapped]).reshape(-1, 3)
    X = np.array([lm.point_m for lm in mapped]).reshape(-1, 3)
    C = np.array([lm.covariance for lm in mapped]).reshape(-1, 3, 3)
    # The map's own triangulation noise, rotated into the camera frame at the starting pose.
    Cm = np.array([world[lm.track_id].covariance for lm in mapped]).reshape(-1, 3, 3)
    C = C + np.einsum("ij,mjk,lk->mil", T.R, Cm, T.R)
    W = np.linalg.inv(C + np.eye(3) * map_sigma**2) if len(mapped) else np.zeros((0, 3, 3))
    # The shared error's prior information (none for an exact map, e.g. one seeded from truth).
    S = sum((world[lm.track_id].pose_covariance for lm in mapped), np.zeros((6, 6)))
    shared = shared_map_error and len(mapped) > 0 and bool(np.any(S))
    if shared:
        # Only the blocks (tilt of the ring axis, roll about it, translation): a ring whose
        # centre or normal disagrees with the map's by a bias of its own must not turn the map
        # about the ring axis through the correlations of the pose it was bootstrapped from
        # (the ring carries no roll information).
        S = np.where(_SHARED_BLOCKS, S, 0.0)
    Pi = np.linalg.inv(S / len(mapped) + np.eye(6) * 1e-12) if shared else np.zeros((6, 6))
    TL = T
    marginal = np.zeros((6, 6))
    for _ in range(iterations):
        HR = np.zeros((6, 6))
        gR = np.zeros(6)
        for Wc, Wn, B in ring_blocks:
            assert ring is not None
            Jc = np.c_[np.zeros((3, 3)), T.R]
            rc = T.t - ring.center_m
            Jn = B.T @ np.c_[-T.R @ skew(ez), np.zeros((3, 3))]
            rn = B.T @ (T.R @ ez)
            HR += Jc.T @ Wc @ Jc + Jn.T @ Wn @ Jn
            gR += Jc.T @ Wc @ rc + Jn.T @ Wn @ rn
        HL = np.zeros((6, 6))
        gL = np.zeros(6)
        if len(mapped):
            r = P @ TL.R.T + TL.t - X  # (M, 3)
            # J_m = [-R [p_m]x, R] = R [-[p_m]x, I]
            Jl = np.zeros((len(mapped), 3, 6))
            Jl[:, :, :3] = -np.einsum("ij,mjk->mik", TL.R, _skew_many(P))
            Jl[:, :, 3:] = TL.R
            WJ = np.einsum("mij,mjk->mik", W, Jl)
            HL = np.einsum("mji,mjk->ik", Jl, WJ)
            gL = np.einsum("mji,mj->i", WJ, r)
        try:
            if shared:
                # d ~ d0 + dx_L - dx (first order), d0 the current offset of T_L from T
                d0 = pose_tangent_error(T, TL)
                H = np.block([[HR + Pi, -Pi], [-Pi, HL + Pi]])
                g = np.r_[gR - Pi @ d0, gL + Pi @ d0]
                step = -np.linalg.solve(H, g)
                dx, dxl = step[:6], step[6:]
                marginal = HR + Pi - Pi @ np.linalg.solve(HL + Pi, Pi)
            else:
                marginal = HR + HL
                dx = dxl = -np.linalg.solve(marginal, gR + gL)
        except np.linalg.LinAlgError:
            raise GeometryFailure("the pose is not constrained") from None
        if not (np.all(np.isfinite(dx)) and np.all(np.isfinite(dxl))):
            raise GeometryFailure("the pose fit diverged (non-finite step)")
        T = Rigid3(R=T.R @ rotvec_to_matrix(dx[:3]), t=T.t + T.R @ dx[3:])
        # without the shared error the landmarks see T itself
        TL = Rigid3(R=TL.R @ rotvec_to_matrix(dxl[:3]), t=TL.t + TL.R @ dxl[3:]) if shared else T
        if max(np.abs(dx).max(), np.abs(dxl).max()) < 1e-10:
            break
    if not len(mapped):
        return T, marginal, np.zeros(0)
    r = P @ TL.R.T + TL.t - X
    res = np.sqrt(np.einsum("mi,mij,mj->m", r, W, r))
    return T, marginal, res


_SHARED_BLOCKS = np.zeros((6, 6), bool)
for _blk in ([0, 1], [2], [3, 4, 5]):
    _SHARED_BLOCKS[np.ix_(_blk, _blk)] = True


def _skew_many(p: np.ndarray) -> np.ndarray:
    """Cross-product matrices of the rows of ``p`` (M, 3) -> (M, 3, 3)."""
    out = np.zeros((p.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -p[:, 2], p[:, 1]
    out[:, 1, 0], out[:, 1, 2] = p[:, 2], -p[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -p[:, 1], p[:, 0]
    return out
