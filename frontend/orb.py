"""Close range (seed 000, section 4.2): ORB features on the target as landmarks.

When the panel corners and components leave the view, ORB features of the target are matched
between the stereo images (brute-force Hamming, then the epipolar and depth gates of
`satpose.frontend.landmarks`) and triangulated; matched frame to frame by descriptor near
their predicted positions, they keep track ids, and a feature that blinked or came back after
ORB paused takes back the id of the mapped track predicted where it is (search by
projection, `OrbConfig.reidentify`). With a map of their target-frame positions
(`TargetFrameTracker`), EPnP + RANSAC on the left image gives a pose ``R', t'`` that rejects
mismatches and, fused with the ring (eq. 10), the paper's close-range pose.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.frontend.conics import Ellipse
from satpose.frontend.landmarks import LandmarkConfig
from satpose.frontend.measurements import LandmarkKind, LandmarkMeasurement
from satpose.frontend.stereo import StereoRig, triangulate

ORB_FIRST_ID = 1_000_000
"""ORB track ids start here, apart from corner and component ids."""


@dataclass(frozen=True, kw_only=True)
class OrbConfig:
    """ORB landmarks.

    Attributes:
        use_below_range_m: ORB runs when the ring is closer than this (the paper's s1) ...
        min_other_landmarks: ... or when fewer corner/component landmarks than this are seen.
        features: ORB features per image.
        max_extent: features are taken within this many ring semi-major axes of the ring
            centre, on the lit target, and outside the ring's rim (whose symmetric edges
            match anywhere along it).
        max_hamming: largest descriptor distance of a match.
        ratio: Lowe's ratio test between the best and second-best temporal match.
        gate_px: a temporal match must land within this distance of its predicted position
            (the pose's prediction, or the image motion that most matches agree on,
            whichever carries more tracks: `_associate`).
        consensus_px, consensus_iterations: the image motion's RANSAC (a similarity
            transform from two matches): inlier distance [px] and hypotheses drawn.
        ransac_px, min_inliers: EPnP + RANSAC reprojection threshold and minimum inliers.
        reidentify: a feature that no track of the previous frame claims is matched against
            every earlier track the caller predicts a position for (the mapped ones: search
            by projection, `OrbTracker._reidentify`), so a feature that blinked, or came back
            after ORB paused, keeps its id and its map position instead of being mapped again
            with the current pose's error.
        reidentify_px: the gate of that search [px] around the predicted position. Tighter
            than ``gate_px``, which also covers the image motion of a target whose twist is
            not known yet: re-identification needs a pose prediction, and a look-alike's
            chance of falling inside the gate grows with its area.
        library_size: earlier tracks kept for that (the most recently seen).
        landmarks: stereo pairing settings.
    """

    use_below_range_m: float = 3.5
    min_other_landmarks: int = 3
    features: int = 500
    max_extent: float = 4.0
    max_hamming: int = 48
    ratio: float = 0.8
    gate_px: float = 20.0
    consensus_px: float = 3.0
    consensus_iterations: int = 200
    ransac_px: float = 2.0
    min_inliers: int = 8
    reidentify: bool = True
    reidentify_px: float = 8.0
    library_size: int = 5000
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.consensus_px) and self.consensus_px > 0):
            raise ValueError(f"orb.consensus_px must be > 0, got {self.consensus_px}")
        if not (math.isfinite(self.reidentify_px) and self.reidentify_px > 0):
            raise ValueError(f"orb.reidentify_px must be > 0, got {self.reidentify_px}")
        if self.library_size < 0:
            raise ValueError(f"orb.library_size must be >= 0, got {self.library_size}")
        if self.consensus_iterations < 1:
            raise ValueError(
                f"orb.consensus_iterations must be >= 1, got {self.consensus_iterations}"
            )


@dataclass
class _OrbTrack:
    track_id: int
    descriptor: np.ndarray
    left: np.ndarray


class OrbTracker:
    """ORB features of the target, stereo-triangulated, with track ids across frames."""

    def __init__(self, rig: StereoRig, config: OrbConfig | None = None) -> None:
        self.rig = rig
        self.config = config or OrbConfig()
        self.orb = cv2.ORB_create(
            nfeatures=self.config.features,
            scaleFactor=1.2,
            nlevels=4,
            edgeThreshold=15,
            patchSize=21,
            fastThreshold=12,
        )
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)  # frame to frame: ratio test on 2-NN
        self.stereo_matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)  # mutual best
        self.tracks: list[_OrbTrack] = []
        self.library: dict[int, _OrbTrack] = {}  # every track seen, last sighting, oldest first
        self._next_id = ORB_FIRST_ID

    def reset(self) -> None:
        """Forget the previous frame's tracks (the library stays: `OrbConfig.reidentify`)."""
        self.tracks = []

    def _mask(self, gray8: np.ndarray, ring: Ellipse | None) -> np.ndarray:
        mask = (gray8 > 8).astype(np.uint8) * 255
        if ring is not None:
            roi = np.zeros_like(mask)
            R = self.config.max_extent * ring.a
            cv2.circle(roi, (int(ring.cx), int(ring.cy)), int(R), 255, -1)
            cv2.ellipse(
                roi,
                (int(ring.cx), int(ring.cy)),
                (int(ring.a * 1.15), int(ring.b * 1.15)),
                float(np.degrees(ring.theta)),
                0,
                360,
                0,
                -1,
            )
            mask &= roi
        return mask

    def update(
        self,
        left8: np.ndarray,
        right8: np.ndarray,
        ring_left: Ellipse | None,
        ring_right: Ellipse | None,
        ring_depth_m: float | None,
        predicted: dict[int, np.ndarray] | None = None,
    ) -> list[LandmarkMeasurement]:
        """ORB landmarks of this frame.

        Args:
            ring_left, ring_right: the ring ellipses (feature masks), if found.
            ring_depth_m: the ring's depth (stereo depth gate).
            predicted: optional ``{track_id: left px}`` expected positions of tracks: of the
                previous frame's, and of earlier ones to re-identify (`OrbConfig.reidentify`).
        """
        cfg = self.config
        kl, dl = self.orb.detectAndCompute(left8, self._mask(left8, ring_left))
        kr, dr = self.orb.detectAndCompute(right8, self._mask(right8, ring_right))
        if dl is None or dr is None or len(kl) < 4 or len(kr) < 4:
            self.tracks = []
            return []
        pl = np.array([k.pt for k in kl])
        pr = np.array([k.pt for k in kr])
        # Stereo: mutual best Hamming matches, then the epipolar/depth gates.
        matches = self.stereo_matcher.match(dl, dr)
        good = [m for m in matches if m.distance <= cfg.max_hamming]
        if not good:
            self.tracks = []
            return []
        li = np.array([m.queryIdx for m in good])
        ri = np.array([m.trainIdx for m in good])
        epi = _epipolar_distance(self.rig, pl[li], pr[ri])
        X0, _ = triangulate(self.rig, pl[li], pr[ri], refine=False)
        z = X0[:, 2]
        lm = cfg.landmarks
        ok = (
            (epi < lm.max_epipolar_px)
            & np.isfinite(z)
            & (z > lm.min_depth_m)
            & (z < lm.max_depth_m)
        )
        if ring_depth_m is not None:
            ok &= np.abs(z - ring_depth_m) < lm.max_depth_offset_m
        idx_l, idx_r = li[ok], ri[ok]
        if idx_l.size == 0:
            self.tracks = []
            return []
        ids = self._associate(dl[idx_l], pl[idx_l], predicted)
        sigma = cfg.landmarks.sigma_px["orb"]
        X, cov = triangulate(self.rig, pl[idx_l], pr[idx_r], sigma_px=sigma)
        out = []
        new_tracks = []
        for k in range(idx_l.size):
            if not np.all(np.isfinite(X[k])):
                continue
            out.append(
                LandmarkMeasurement(
                    track_id=ids[k],
                    kind=LandmarkKind.ORB,
                    left_px=pl[idx_l[k]],
                    right_px=pr[idx_r[k]],
                    sigma_px=sigma,
                    point_m=X[k],
                    covariance=cov[k],
                )
            )
            new_tracks.append(
                _OrbTrack(track_id=ids[k], descriptor=dl[idx_l[k]], left=pl[idx_l[k]])
            )
        self.tracks = new_tracks
        for t in new_tracks:  # most recently seen last
            self.library.pop(t.track_id, None)
            self.library[t.track_id] = t
        while len(self.library) > cfg.library_size:
            del self.library[next(iter(self.library))]
        return out

    def _associate(
        self, desc: np.ndarray, pts: np.ndarray, predicted: dict[int, np.ndarray] | None
    ) -> list[int]:
        """Track id per current feature: the previous frame's feature with the closest
        descriptor (ratio test) near its predicted position, else a new id.

        The predicted position is the pose's prediction where there is one, else the
        feature's last position. Where the target moved more than that says (frames far
        apart in time, the twist not known yet: a spinning target's features move tens of
        pixels), the image motion of the descriptor matches themselves predicts instead: a
        similarity transform that most ratio-test matches agree on (`_image_motion`), taken
        when it carries more tracks than the prediction."""
        cfg = self.config
        ids = [-1] * len(desc)
        if self.tracks:
            prev_desc = np.array([t.descriptor for t in self.tracks])
            last = np.array([t.left for t in self.tracks])
            prev_pos = np.array(
                [
                    predicted[t.track_id] if predicted and t.track_id in predicted else t.left
                    for t in self.tracks
                ]
            )
            knn = self.matcher.knnMatch(desc, prev_desc, k=2)
            cands = []
            for q, ms in enumerate(knn):
                if not ms:
                    continue
                best = ms[0]
                if len(ms) > 1 and best.distance > cfg.ratio * ms[1].distance:
                    continue
                if best.distance > cfg.max_hamming:
                    continue
                cands.append((q, best.trainIdx))
            pairs = _gated(cands, prev_pos, pts, cfg.gate_px)
            # the image motion can only carry more where the prediction left candidates out
            motion = (
                None
                if len(pairs) == len(cands)
                else _image_motion(
                    np.array([last[t] for _, t in cands]).reshape(-1, 2),
                    np.array([pts[q] for q, _ in cands]).reshape(-1, 2),
                    cfg.consensus_px,
                    cfg.consensus_iterations,
                )
            )
            if motion is not None:
                moved = _gated(cands, motion(last), pts, cfg.gate_px)
                if len(moved) > len(pairs):
                    pairs = moved
            for q, t in pairs:
                ids[q] = self.tracks[t].track_id
        if cfg.reidentify and predicted:
            for q, tid in self._reidentify(desc, pts, predicted, ids).items():
                ids[q] = tid
        for q in range(len(ids)):
            if ids[q] < 0:
                ids[q] = self._next_id
                self._next_id += 1
        return ids

    def _reidentify(
        self, desc: np.ndarray, pts: np.ndarray, predicted: dict[int, np.ndarray], ids: list[int]
    ) -> dict[int, int]:
        """Search by projection: ``{feature index: earlier track id}`` for the features
        without an id yet, among the library's tracks that are not in this frame already
        and have a predicted position. A feature takes the track with the closest
        descriptor among those predicted within ``reidentify_px`` of it, if within
        ``max_hamming``, clearly closer than the next one there (``ratio``) and mutual (no
        other feature within the gate is closer to that track)."""
        cfg = self.config
        taken = set(ids)
        cand = [tid for tid in predicted if tid in self.library and tid not in taken]
        free = [q for q, i in enumerate(ids) if i < 0]
        if not cand or not free:
            return {}
        pos = np.array([predicted[tid] for tid in cand], float).reshape(-1, 2)
        lib = np.array([self.library[tid].descriptor for tid in cand])
        k_idx, c_idx = np.nonzero(
            np.linalg.norm(pts[free][:, None, :] - pos[None, :, :], axis=2) <= cfg.reidentify_px
        )
        if k_idx.size == 0:
            return {}
        # Hamming distance of each (feature, candidate) pair within the gate: bits of the XOR
        ham = np.unpackbits(desc[free][k_idx] ^ lib[c_idx], axis=1).sum(axis=1)
        # each candidate's closest feature within the gate: a match must be mutual
        cand_best = np.full(len(cand), np.iinfo(np.int64).max)
        np.minimum.at(cand_best, c_idx, ham.astype(np.int64))
        best: dict[int, tuple[int, int]] = {}  # candidate -> (distance, feature)
        for k in np.unique(k_idx):
            sel = np.flatnonzero(k_idx == k)
            order = sel[np.argsort(ham[sel], kind="stable")]
            d0 = int(ham[order[0]])
            if d0 > cfg.max_hamming:
                continue
            if order.size > 1 and d0 > cfg.ratio * int(ham[order[1]]):
                continue
            c = int(c_idx[order[0]])
            if d0 > cand_best[c]:
                continue
            if c not in best or d0 < best[c][0]:
                best[c] = (d0, free[int(k)])
        return {q: cand[c] for c, (_, q) in best.items()}


def _gated(
    cands: list[tuple[int, int]], prev_pos: np.ndarray, pts: np.ndarray, gate_px: float
) -> list[tuple[int, int]]:
    """The candidate matches (current feature, previous track) whose feature lies within
    ``gate_px`` of the track's predicted position ``prev_pos``, each track used once (in the
    order of the current features)."""
    taken: set[int] = set()
    out = []
    for q, t in cands:
        if t in taken or np.linalg.norm(prev_pos[t] - pts[q]) > gate_px:
            continue
        taken.add(t)
        out.append((q, t))
    return out


def _image_motion(
    src: np.ndarray, dst: np.ndarray, inlier_px: float, iterations: int
) -> Callable[[np.ndarray], np.ndarray] | None:
    """The similarity transform (rotation, scale, translation) of the image that most of the
    point pairs ``src -> dst`` (N, 2) agree on within ``inlier_px``, refitted on its inliers
    by least squares; None with fewer than 6 inliers (or pairs). RANSAC from pairs of matches
    with a fixed seed, so the same matches give the same motion."""
    n = len(src)
    if n < 6:
        return None
    zs = src[:, 0] + 1j * src[:, 1]
    zd = dst[:, 0] + 1j * dst[:, 1]
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, n, size=(2, iterations))
    d = zs[i] - zs[j]
    ok = np.abs(d) > 1e-6  # two distinct points
    if not ok.any():
        return None
    a_all = (zd[i[ok]] - zd[j[ok]]) / d[ok]  # z' = a z + b, one hypothesis per pair
    b_all = zd[i[ok]] - a_all * zs[i[ok]]
    residuals = np.abs(a_all[:, None] * zs[None, :] + b_all[:, None] - zd[None, :])
    k = int(np.argmax((residuals < inlier_px).sum(axis=1)))  # the first of the best
    best = residuals[k] < inlier_px
    if best.sum() < 6:
        return None
    A = np.c_[zs[best], np.ones(int(best.sum()))]
    a, b = np.linalg.lstsq(A, zd[best], rcond=None)[0]

    def apply(p: np.ndarray) -> np.ndarray:
        z = a * (p[:, 0] + 1j * p[:, 1]) + b
        return np.c_[z.real, z.imag]

    return apply


def epnp_ransac(
    K: np.ndarray, points_target: np.ndarray, pixels: np.ndarray, config: OrbConfig
) -> tuple[Rigid3, np.ndarray] | None:
    """EPnP + RANSAC (seed 000: ``R', t'``) of target-frame points (N, 3) seen at undistorted
    left pixels (N, 2). Returns ``(left_cam_from_target, inlier mask)`` or None."""
    if len(points_target) < max(6, config.min_inliers):
        return None
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        points_target.astype(np.float64),
        pixels.astype(np.float64),
        K,
        None,
        flags=cv2.SOLVEPNP_EPNP,
        reprojectionError=config.ransac_px,
        iterationsCount=200,
        confidence=0.999,
    )
    if not ok or inliers is None or len(inliers) < config.min_inliers:
        return None
    mask = np.zeros(len(points_target), bool)
    mask[inliers.reshape(-1)] = True
    return Rigid3(R=rotvec_to_matrix(rvec.reshape(3)), t=tvec.reshape(3)), mask


def pose_eq10(center: np.ndarray, normal: np.ndarray, pnp: Rigid3) -> Rigid3:
    """Seed 000 eq. 10: x = x', z = normalised(n_c + z'), y = z x x, t = (X_c + t') / 2
    (x re-orthogonalised against the fused z)."""
    x = pnp.R[:, 0]
    z = normal + pnp.R[:, 2]
    z /= np.linalg.norm(z)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return Rigid3(R=np.c_[x, np.cross(z, x), z], t=0.5 * (center + pnp.t))


def _epipolar_distance(rig: StereoRig, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Distance [px] of each right point from the epipolar line of its own left point."""
    F = rig.fundamental()
    lines = np.c_[left, np.ones(len(left))] @ F.T
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    return np.abs(np.einsum("ij,ij->i", lines, np.c_[right, np.ones(len(right))]))
