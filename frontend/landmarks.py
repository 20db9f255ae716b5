"""Point landmarks across the stereo pair and across frames, with stable track ids.

Per frame: detections in each image (panel corners, dark components, ORB features) are
paired across the stereo rig along epipolar lines (seed 000 eq. 3: the closest candidate to
``l_r = F p_l``, here also required to be unique and at a plausible depth), triangulated
(eqs. 4-5) and associated with existing tracks: each track's points are carried into the new
images by pyramidal Lucas-Kanade (started from a prediction when the caller has one), and the
nearest stereo pair of the same kind within ``gate_px`` continues the track. Unmatched pairs
start new tracks; track ids are never reused.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from satpose.frontend.measurements import LandmarkKind, LandmarkMeasurement
from satpose.frontend.stereo import StereoRig, triangulate


@dataclass(frozen=True, kw_only=True)
class LandmarkConfig:
    """Stereo pairing and tracking of point landmarks (pixels of the undistorted images).

    Attributes:
        sigma_px: reported pixel noise per kind (corner, component, orb); it sets the
            landmark covariances the backend weighs them by.
        max_epipolar_px: a right candidate must lie this close to the left point's epipolar line.
        max_depth_offset_m: and triangulate within this distance of the ring's depth (the
            landmarks are on the target), when the ring depth is known.
        min_depth_m, max_depth_m: otherwise, this depth range.
        gate_px: a detection continues a track if within this distance of its LK position.
        max_missed: a track not seen for more than this many frames is dropped.
        lk_window_px, lk_levels: Lucas-Kanade window and pyramid levels.
    """

    sigma_px: dict[str, float] = field(
        default_factory=lambda: {"corner": 0.3, "component": 0.8, "orb": 0.8}
    )
    max_epipolar_px: float = 2.0
    max_depth_offset_m: float = 1.5
    min_depth_m: float = 0.3
    max_depth_m: float = 100.0
    gate_px: float = 6.0
    max_missed: int = 2
    lk_window_px: int = 21
    lk_levels: int = 3


@dataclass
class _Track:
    track_id: int
    kind: LandmarkKind
    left: np.ndarray
    right: np.ndarray
    missed: int = 0


def stereo_pairs(
    rig: StereoRig,
    left: np.ndarray,
    right: np.ndarray,
    config: LandmarkConfig,
    ring_depth_m: float | None,
) -> list[tuple[int, int]]:
    """Unique left-right pairs ``(i, j)`` of points (N, 2), (M, 2): closest to the epipolar
    line first, within ``max_epipolar_px`` and at a plausible depth."""
    if len(left) == 0 or len(right) == 0:
        return []
    D = rig.epipolar_distance(left, right)
    cand = np.argwhere(D < config.max_epipolar_px)
    if cand.size == 0:
        return []
    X, _ = triangulate(rig, left[cand[:, 0]], right[cand[:, 1]], refine=False)
    z = X[:, 2]
    ok = np.isfinite(z) & (z > config.min_depth_m) & (z < config.max_depth_m)
    if ring_depth_m is not None:
        ok &= np.abs(z - ring_depth_m) < config.max_depth_offset_m
    cand = cand[ok]
    order = np.argsort(D[cand[:, 0], cand[:, 1]])
    used_l: set[int] = set()
    used_r: set[int] = set()
    pairs = []
    for i, j in cand[order]:
        if i in used_l or j in used_r:
            continue
        used_l.add(int(i))
        used_r.add(int(j))
        pairs.append((int(i), int(j)))
    return pairs


class LandmarkTracker:
    """Stereo pairing, triangulation and temporal tracking of point landmarks."""

    def __init__(
        self, rig: StereoRig, config: LandmarkConfig | None = None, first_id: int = 0
    ) -> None:
        self.rig = rig
        self.config = config or LandmarkConfig()
        self.tracks: dict[int, _Track] = {}
        self._kinds: dict[int, LandmarkKind] = {}  # every id ever issued
        self._next_id = first_id
        self._prev: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self.tracks.clear()
        self._prev = None

    def rename(self, mapping: dict[int, int]) -> None:
        """Give tracks the ids of the landmarks they were re-identified as."""
        for new, old in mapping.items():
            if new in self.tracks and old not in self.tracks:
                track = self.tracks.pop(new)
                track.track_id = old
                self.tracks[old] = track
                self._kinds[old] = track.kind

    def _lk(
        self, prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, guess: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        p0 = pts.astype(np.float32).reshape(-1, 1, 2)
        flags = 0
        p1 = None
        if guess is not None:
            p1 = guess.astype(np.float32).reshape(-1, 1, 2).copy()
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        out, st, _ = cv2.calcOpticalFlowPyrLK(
            prev,
            cur,
            p0,
            p1,
            winSize=(cfg.lk_window_px, cfg.lk_window_px),
            maxLevel=cfg.lk_levels,
            flags=flags,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        if out is None:
            return pts.copy(), np.zeros(len(pts), bool)
        return out.reshape(-1, 2), st.reshape(-1).astype(bool)

    def update(
        self,
        left8: np.ndarray,
        right8: np.ndarray,
        detections: Sequence[tuple[LandmarkKind, np.ndarray, np.ndarray]],
        ring_depth_m: float | None = None,
        predicted: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> list[LandmarkMeasurement]:
        """Track this frame's detections.

        Args:
            left8, right8: the undistorted 8-bit images (for Lucas-Kanade).
            detections: ``(kind, left points (N, 2), right points (M, 2))`` per kind.
            ring_depth_m: the ring centre's depth, if known (depth gate of stereo pairs).
            predicted: optional ``{track_id: (left px, right px)}`` where the caller expects
                landmarks (e.g. from the previous pose and twist and a map): LK starts there
                for current tracks, and landmarks no longer tracked are re-identified there.

        Returns:
            One measurement per stereo pair, with its track id.
        """
        cfg = self.config
        # 1. Carry tracks into the new images.
        carried: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if self._prev is not None and self.tracks:
            ids = list(self.tracks)
            L = np.array([self.tracks[i].left for i in ids])
            R = np.array([self.tracks[i].right for i in ids])
            gl = gr = None
            if predicted:
                gl = np.array([predicted.get(i, (self.tracks[i].left, None))[0] for i in ids])
                gr = np.array(
                    [predicted[i][1] if i in predicted else self.tracks[i].right for i in ids]
                )
            l1, okl = self._lk(self._prev[0], left8, L, gl)
            r1, okr = self._lk(self._prev[1], right8, R, gr)
            for k, tid in enumerate(ids):
                if okl[k] and okr[k]:
                    carried[tid] = (l1[k], r1[k])
                elif predicted and tid in predicted:
                    carried[tid] = predicted[tid]
        # 2. Stereo pairs of this frame's detections, per kind.
        out: list[LandmarkMeasurement] = []
        seen: set[int] = set()
        for kind, left, right in detections:
            left = np.asarray(left, float).reshape(-1, 2)
            right = np.asarray(right, float).reshape(-1, 2)
            pairs = stereo_pairs(self.rig, left, right, cfg, ring_depth_m)
            if not pairs:
                continue
            pl = np.array([left[i] for i, _ in pairs])
            pr = np.array([right[j] for _, j in pairs])
            # 3. Associate with carried tracks of the same kind (greedy, nearest first).
            cand = [
                (
                    float(
                        np.linalg.norm(pl[p] - carried[t][0])
                        + np.linalg.norm(pr[p] - carried[t][1])
                    ),
                    p,
                    t,
                )
                for p, t in itertools.product(range(len(pairs)), carried)
                if self.tracks[t].kind == kind
            ]
            cand = [c for c in cand if c[0] < 2 * cfg.gate_px]
            cand.sort()
            assigned: dict[int, int] = {}
            taken: set[int] = set()
            for _, p, t in cand:
                if p in assigned or t in taken:
                    continue
                assigned[p] = t
                taken.add(t)
            X, cov = triangulate(self.rig, pl, pr, sigma_px=cfg.sigma_px[kind.value])
            # Pairs no track claimed may be a known landmark seen again after a gap: the
            # nearest predicted position of a landmark that is not being tracked.
            if predicted:
                dormant = [
                    (
                        float(
                            np.linalg.norm(pl[p] - predicted[t][0])
                            + np.linalg.norm(pr[p] - predicted[t][1])
                        ),
                        p,
                        t,
                    )
                    for p in range(len(pairs))
                    if p not in assigned
                    for t in predicted
                    if t not in self.tracks and self._kinds.get(t) == kind
                ]
                for d, p, t in sorted(dormant):
                    if d < 2 * cfg.gate_px and p not in assigned and t not in taken:
                        assigned[p] = t
                        taken.add(t)
            for p in range(len(pairs)):
                if not np.all(np.isfinite(X[p])):
                    continue
                if p in assigned:
                    tid = assigned[p]
                    if tid not in self.tracks:
                        self.tracks[tid] = _Track(track_id=tid, kind=kind, left=pl[p], right=pr[p])
                else:
                    tid = self._next_id
                    self._next_id += 1
                    self.tracks[tid] = _Track(track_id=tid, kind=kind, left=pl[p], right=pr[p])
                    self._kinds[tid] = kind
                track = self.tracks[tid]
                track.left, track.right, track.missed = pl[p], pr[p], 0
                seen.add(tid)
                out.append(
                    LandmarkMeasurement(
                        track_id=tid,
                        kind=kind,
                        left_px=pl[p],
                        right_px=pr[p],
                        sigma_px=cfg.sigma_px[kind.value],
                        point_m=X[p],
                        covariance=cov[p],
                    )
                )
        # 4. Tracks not seen this frame: keep their LK position a little while, then drop.
        for tid in list(self.tracks):
            if tid in seen:
                continue
            track = self.tracks[tid]
            track.missed += 1
            if track.missed > cfg.max_missed or tid not in carried:
                del self.tracks[tid]
            else:
                track.left, track.right = carried[tid]
        self._prev = (left8, right8)
        return out
