"""Star-tracker frontend (seed 004): spots from events or frames, identification, attitude.

- Spots from events: the events of a time window are counted per pixel, 3x3-summed and
  thresholded; each connected blob is a star. Its position is the mean of the ON-event mean
  and the OFF-event mean (a moving star fires ON events on its leading edge and OFF events on
  its trailing edge, so the two means straddle the star) at the mean of their times.
- Spots from frames: background (median) and noise (MAD) per image, threshold, connected
  blobs, intensity-weighted centroid.
- Identification (lost in space): tetra3rs' geometric-hashing plate solver on a multi-scale
  database (patterns from the short image side to the diagonal). Only its star matches are
  used; the attitude is our own Wahba solution with a covariance.
- Attitude: Wahba's problem by SVD (Markley 1988), covariance ``(sum_i (I - b_i b_i^T) /
  sigma_i^2)^-1`` (Shuster's QUEST measurement model) for the right perturbation
  ``R_true = R Exp(delta)``, delta in the camera frame.
- Relative rotation between windows: rotation-only alignment of matched bearings (Wahba again),
  and for comparison the five-point essential matrix (OpenCV), which is degenerate for stars at
  infinity (no translation: E = [t]x R = 0).
- Tracking: catalogue stars projected with the attitude predicted from the last attitude and
  rate; events within a gate of each prediction are that star's (no image, no blobs, no plate
  solve), then Wahba. Falls back to lost-in-space when fewer than ``min_stars`` remain.

Camera frame OpenCV; attitude ``inertial_from_camera`` (ICRS). Never imports gtsam.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError
from satpose.datasets.events import Events
from satpose.datasets.geometry import matrix_to_rotvec, rotvec_to_matrix
from satpose.datasets.sky import radec_to_unit

ARCSEC = math.pi / (180 * 3600)


class StarTrackerError(SatposeError):
    """Bad input to the star tracker (empty catalogue, inconsistent shapes)."""


# --------------------------------------------------------------------------------------------
# Attitude from vectors
# --------------------------------------------------------------------------------------------


def wahba(
    b_cam: np.ndarray, r_inertial: np.ndarray, sigma_rad: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation ``R`` with ``r_i ~ R b_i`` (Wahba's problem, SVD solution).

    Args:
        b_cam: unit bearings in the camera frame, shape (N, 3), N >= 2.
        r_inertial: matching unit vectors in the inertial frame, shape (N, 3).
        sigma_rad: angular noise of each pair (scalar or (N,)) [rad].

    Returns:
        ``(R, cov)``: ``inertial_from_camera`` (3, 3) and the 3x3 covariance [rad^2] of
        ``delta`` in ``R_true = R Exp(delta)`` (camera frame).
    """
    b = np.asarray(b_cam, float)
    r = np.asarray(r_inertial, float)
    if b.shape != r.shape or b.ndim != 2 or b.shape[1] != 3 or b.shape[0] < 2:
        raise StarTrackerError(f"wahba needs two (N>=2, 3) arrays, got {b.shape}, {r.shape}")
    w = np.broadcast_to(1.0 / np.asarray(sigma_rad, float) ** 2, (b.shape[0],))
    B = (w[:, None] * r).T @ b
    U, _, Vt = np.linalg.svd(B)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    info = np.sum(w) * np.eye(3) - (w[:, None] * b).T @ b
    return R, np.linalg.inv(info)


def relative_rotation_bearings(
    b1: np.ndarray, b2: np.ndarray, sigma_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-only alignment: ``cam1_from_cam2`` with ``b1 ~ R b2`` and its covariance."""
    return wahba(b2, b1, sigma_rad * math.sqrt(2.0))


def relative_rotation_five_point(
    b1: np.ndarray, b2: np.ndarray, threshold: float
) -> np.ndarray | None:
    """``cam1_from_cam2`` from the five-point essential matrix (OpenCV RANSAC + recoverPose).

    ``threshold`` is the RANSAC epipolar threshold in normalised image units. Returns None if
    OpenCV finds no essential matrix. For a pure rotation every E = [t]x R with any t fits the
    data as well as the true one, so the returned rotation is arbitrary: the failure this
    function exists to show.
    """
    p1 = np.ascontiguousarray(b1[:, :2] / b1[:, 2:3])
    p2 = np.ascontiguousarray(b2[:, :2] / b2[:, 2:3])
    if p1.shape[0] < 5:
        return None
    E, mask = cv2.findEssentialMat(
        p2, p1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=threshold
    )
    if E is None or E.shape != (3, 3):
        return None
    _, R21, _, _ = cv2.recoverPose(E, p2, p1, np.eye(3), mask=mask)
    # recoverPose gives x1 = R x2 + t for points x2 in camera 2: that is cam1_from_cam2.
    return np.asarray(R21)


# --------------------------------------------------------------------------------------------
# Spots
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spots:
    """Star spots of one window or frame.

    Attributes:
        px: sub-pixel positions, shape (N, 2).
        t_s: time each position refers to, shape (N,).
        weight: brightness proxy (event count or summed DN), shape (N,).
    """

    px: np.ndarray
    t_s: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return int(self.px.shape[0])


def peak_on_events(x: np.ndarray, y: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Mask of ON events followed (at the same pixel, in these time-sorted events) by an OFF
    event: the crossing of a pixel's highest level while a star passes.

    A passing star makes a pixel cross levels ``L0 + C, ..., L0 + nC`` going up (ON) and
    ``L0 + (n-1)C, ..., L0 + C`` coming down (OFF; the last level ``L0`` is reached, not
    passed). Without the top ON event the ON and OFF sets mirror each other in time, so their
    centroids straddle the star symmetrically; with it the ON centroid is pulled toward the
    star and the balanced centroid lags behind the motion. The next event of a pixel comes
    tens of milliseconds later, so this runs on the whole stream (`run_event_tracker`), not
    per window: an online system would know a peak only once that OFF event has arrived.
    """
    pix = y.astype(np.int64) * 65536 + x.astype(np.int64)
    order = np.argsort(pix, kind="stable")  # time order kept within a pixel
    ps, pp = pix[order], p[order]
    peak_sorted = np.zeros(order.size, dtype=bool)
    peak_sorted[:-1] = (ps[:-1] == ps[1:]) & (pp[:-1] == 1) & (pp[1:] == 0)
    peak = np.zeros(order.size, dtype=bool)
    peak[order] = peak_sorted
    return peak


def _balanced_centroids(
    lab: np.ndarray, n: int, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-label ON/OFF-balanced centroid, time and event count for labels 1..n."""
    out_px = np.zeros((n + 1, 2))
    out_t = np.zeros(n + 1)
    parts = []
    for pol in (1, 0):
        m = p == pol
        c = np.bincount(lab[m], minlength=n + 1).astype(float)
        sx = np.bincount(lab[m], weights=x[m], minlength=n + 1)
        sy = np.bincount(lab[m], weights=y[m], minlength=n + 1)
        st = np.bincount(lab[m], weights=t[m], minlength=n + 1)
        parts.append((c, sx, sy, st))
    (c1, x1, y1, t1), (c0, x0, y0, t0) = parts
    both = (c1 > 0) & (c0 > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.where(both, 0.5 * (x1 / c1 + x0 / c0), (x1 + x0) / (c1 + c0))
        my = np.where(both, 0.5 * (y1 / c1 + y0 / c0), (y1 + y0) / (c1 + c0))
        mt = np.where(both, 0.5 * (t1 / c1 + t0 / c0), (t1 + t0) / (c1 + c0))
    out_px[:, 0], out_px[:, 1], out_t[:] = mx, my, mt
    return out_px[1:], out_t[1:], (c1 + c0)[1:]


def event_spots(events: Events, width: int, height: int, min_events: int = 6) -> Spots:
    """Star spots from one window of events (blobs of the 3x3-summed event count)."""
    if len(events) == 0:
        return Spots(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    x = events.x.astype(np.int64)
    y = events.y.astype(np.int64)
    cnt = np.bincount(y * width + x, minlength=width * height).reshape(height, width)
    box = cv2.boxFilter(cnt.astype(np.float32), -1, (3, 3), normalize=False)
    mask = (box >= min_events).astype(np.uint8)
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    lab = labels[y, x]
    px, t, c = _balanced_centroids(
        lab, n - 1, x.astype(float), y.astype(float), events.t_s, events.p
    )
    keep = c >= min_events
    return Spots(px[keep], t[keep], c[keep])


def frame_spots(image: np.ndarray, t_s: float, k_sigma: float = 5.0, min_pixels: int = 2) -> Spots:
    """Star spots of a frame: pixels above median + k MAD-sigma, intensity-weighted centroids."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or not np.isfinite(img).all():
        raise StarTrackerError("frame_spots needs a finite 2-D image")
    bg = float(np.median(img))
    sigma = 1.4826 * float(np.median(np.abs(img - bg))) or 1.0
    sig = img - bg
    mask = (cv2.GaussianBlur(sig, (3, 3), 0.8) > k_sigma * sigma * 0.5).astype(np.uint8)
    mask &= (sig > k_sigma * sigma * 0.3).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return Spots(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    ys, xs = np.nonzero(labels)
    lab = labels[ys, xs]
    w = np.clip(sig[ys, xs], 0, None)
    s = np.bincount(lab, weights=w, minlength=n)
    cx = np.bincount(lab, weights=w * xs, minlength=n)
    cy = np.bincount(lab, weights=w * ys, minlength=n)
    peak = np.zeros(n)
    np.maximum.at(peak, lab, sig[ys, xs])
    ok = (stats[:, cv2.CC_STAT_AREA] >= min_pixels) & (s > 0) & (peak > k_sigma * sigma)
    ok[0] = False
    idx = np.flatnonzero(ok)
    return Spots(
        np.column_stack([cx[idx] / s[idx], cy[idx] / s[idx]]), np.full(idx.size, t_s), s[idx]
    )


# --------------------------------------------------------------------------------------------
# Catalogue and identification (tetra3rs)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SolverCatalogue:
    """The plate solver's stars as numpy: ids, ICRS unit vectors at its epoch, magnitudes."""

    ids: np.ndarray
    unit: np.ndarray
    mag: np.ndarray
    row_of: dict[int, int]


@functools.lru_cache(maxsize=4)
def solver_database(min_fov_deg: float, max_fov_deg: float, epoch_yr: float) -> object:
    """A tetra3rs database from its bundled Gaia catalogue (cached per process)."""
    import tetra3rs

    return tetra3rs.SolverDatabase.generate_from_gaia(
        max_fov_deg=max_fov_deg, min_fov_deg=min_fov_deg, epoch_proper_motion_year=epoch_yr
    )


@functools.lru_cache(maxsize=4)
def solver_catalogue(min_fov_deg: float, max_fov_deg: float, epoch_yr: float) -> SolverCatalogue:
    db = solver_database(min_fov_deg, max_fov_deg, epoch_yr)
    n = int(db.num_stars)  # type: ignore[attr-defined]
    stars = [db.get_star(i) for i in range(n)]  # type: ignore[attr-defined]
    ids = np.array([s.id for s in stars], dtype=np.int64)
    ra = np.radians([s.ra_deg for s in stars])
    dec = np.radians([s.dec_deg for s in stars])
    mag = np.array([s.magnitude for s in stars], dtype=float)
    return SolverCatalogue(ids, radec_to_unit(ra, dec), mag, {int(i): k for k, i in enumerate(ids)})


def bearings(cam: PinholeCamera, px: np.ndarray) -> np.ndarray:
    """Unit bearings (N, 3), camera frame, of distortion-free pixels (N, 2)."""
    xy = (np.asarray(px, float) - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    v = np.column_stack([xy, np.ones(xy.shape[0])])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------------
# The tracker
# --------------------------------------------------------------------------------------------

Status = Literal["lost_in_space", "tracking", "lost"]


@dataclass(frozen=True, kw_only=True)
class StarTrackerConfig:
    """Settings of both trackers (event and frame).

    Attributes:
        window_s: event window length (the attitude output period in tracking).
        lis_window_s: event window for a lost-in-space solve (longer: more events per star).
        min_events: events per blob (lost in space) or per tracked star.
        gate_px: association radius around predicted star positions.
        min_stars: fewest matched stars for an attitude.
        centroid_sigma_px: assumed per-star centroid noise (weights, covariance).
        outlier_sigma: residual gate (in centroid sigmas) after the first Wahba solve.
        rate_history: windows over which the rate for the prediction is differenced.
        min_motion_px: star motion the events of one tracking output must span (slow slews
            integrate longer than ``window_s``; outputs stay ``window_s`` apart).
        drop_peak_on: leave each pixel's top-level ON event out (`peak_on_events`; needs the
            pixel's next event, so it is decided on the whole stream).
        mag_limit: faintest catalogue star predicted in tracking.
        epoch_yr: epoch of the solver catalogue.
    """

    window_s: float = 0.005
    lis_window_s: float = 0.05
    min_events: int = 4
    gate_px: float = 3.0
    min_stars: int = 5
    centroid_sigma_px: float = 0.35
    outlier_sigma: float = 5.0
    rate_history: int = 20
    min_motion_px: float = 0.3
    drop_peak_on: bool = True
    mag_limit: float = 7.5
    epoch_yr: float = 2026.9

    def __post_init__(self) -> None:
        if not (0 < self.window_s <= self.lis_window_s):
            raise StarTrackerError("need 0 < window_s <= lis_window_s")
        if self.min_stars < 3 or self.gate_px <= 0 or self.centroid_sigma_px <= 0:
            raise StarTrackerError("min_stars >= 3, gate_px > 0, centroid_sigma_px > 0")


@dataclass(frozen=True)
class AttitudeSolution:
    """One attitude output.

    Attributes:
        t_s: time of the attitude.
        R: ``inertial_from_camera`` (3, 3) or None if lost.
        cov: 3x3 covariance of ``delta`` (``R_true = R Exp(delta)``) [rad^2], or None.
        status: how it was obtained.
        star_ids: catalogue ids of the stars used, (M,).
        b_cam: their bearings (M, 3).
        cpu_ms: processing CPU time of this output [ms].
    """

    t_s: float
    R: np.ndarray | None
    cov: np.ndarray | None
    status: Status
    star_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    b_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cpu_ms: float = 0.0


class StarTracker:
    """Lost-in-space plus tracking over a stream of spots (from events or frames).

    ``identify`` runs the plate solver on spots; ``track`` associates spots with predicted
    catalogue stars. The event tracker `track_events` adds the gated fast path on raw events.
    """

    def __init__(self, cam: PinholeCamera, config: StarTrackerConfig | None = None) -> None:
        self.cam = cam
        self.config = config or StarTrackerConfig()
        c = self.config
        hfov = math.degrees(2 * math.atan(cam.width / (2 * cam.fx)))
        vfov = math.degrees(2 * math.atan(cam.height / (2 * cam.fy)))
        dfov = math.degrees(2 * math.atan(math.hypot(cam.width, cam.height) / (2 * cam.fx)))
        self.hfov_deg = hfov
        # Non-square sensor: a 4-star pattern spans anything from the short side to the
        # diagonal, so the database covers that range of scales.
        self.db = solver_database(round(min(hfov, vfov), 3), round(dfov, 3), c.epoch_yr)
        self.cat = solver_catalogue(round(min(hfov, vfov), 3), round(dfov, 3), c.epoch_yr)
        self._bright = self.cat.mag <= c.mag_limit
        self.sigma_rad = c.centroid_sigma_px / cam.fx
        self.history: list[tuple[float, np.ndarray]] = []

    # ---- building blocks ------------------------------------------------------------------

    def _solve(
        self, t_s: float, b: np.ndarray, ids: np.ndarray, status: Status
    ) -> AttitudeSolution:
        c = self.config
        if ids.size < c.min_stars:
            return AttitudeSolution(t_s, None, None, "lost")
        r = self.cat.unit[[self.cat.row_of[int(i)] for i in ids]]
        R, cov = wahba(b, r, self.sigma_rad)
        res = np.linalg.norm(np.cross(r, b @ R.T), axis=1)
        ok = res < c.outlier_sigma * self.sigma_rad * math.sqrt(2)
        if ok.sum() < c.min_stars:
            return AttitudeSolution(t_s, None, None, "lost")
        if not ok.all():
            b, r, ids = b[ok], r[ok], ids[ok]
            R, cov = wahba(b, r, self.sigma_rad)
        return AttitudeSolution(t_s, R, cov, status, ids, b)

    def identify(self, spots: Spots, t_s: float) -> AttitudeSolution:
        """Lost in space: plate-solve the spots (brightest first), Wahba on the matches."""
        if len(spots) < self.config.min_stars:
            return AttitudeSolution(t_s, None, None, "lost")
        order = np.argsort(-spots.weight)
        px = spots.px[order]
        cent = np.column_stack([px - [self.cam.cx, self.cam.cy], spots.weight[order]])
        res = self.db.solve_from_centroids(  # type: ignore[attr-defined]
            cent,
            fov_estimate_deg=self.hfov_deg,
            image_width=self.cam.width,
            image_height=self.cam.height,
            solve_timeout_ms=2000,
        )
        if not res:
            return AttitudeSolution(t_s, None, None, "lost")
        idx = np.asarray(res.matched_centroids, dtype=np.int64)
        ids = np.asarray(res.matched_catalog_ids, dtype=np.int64)
        known = np.array([int(i) in self.cat.row_of for i in ids], dtype=bool)
        return self._solve(t_s, bearings(self.cam, px[idx[known]]), ids[known], "lost_in_space")

    def predict(self, t_s: float) -> np.ndarray | None:
        """Attitude at ``t_s`` from the last attitude and the rate over recent outputs."""
        if not self.history:
            return None
        t1, R1 = self.history[-1]
        k = max(0, len(self.history) - 1 - self.config.rate_history)
        t0, R0 = self.history[k]
        rate = matrix_to_rotvec(R0.T @ R1) / (t1 - t0) if t1 > t0 else np.zeros(3)
        return R1 @ rotvec_to_matrix(rate * (t_s - t1))

    def body_rate_rad_s(self) -> np.ndarray:
        """Body rate [rad/s] from the recent outputs (zero with fewer than two)."""
        if len(self.history) < 2:
            return np.zeros(3)
        k = max(0, len(self.history) - 1 - self.config.rate_history)
        (t0, R0), (t1, R1) = self.history[k], self.history[-1]
        return matrix_to_rotvec(R0.T @ R1) / (t1 - t0)

    def integration_s(self) -> float:
        """Event span for a tracking output: long enough for the stars to move
        ``min_motion_px`` at the current rate, between ``window_s`` and ``lis_window_s``."""
        c = self.config
        speed = float(np.linalg.norm(self.body_rate_rad_s())) * self.cam.fx  # px/s near the centre
        if speed <= 0:
            return c.lis_window_s
        return float(np.clip(c.min_motion_px / speed, c.window_s, c.lis_window_s))

    def predicted_stars(self, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Catalogue rows (bright enough) in view of attitude ``R`` and their pixels."""
        cam = self.cam
        rows = np.flatnonzero(self._bright)
        v = self.cat.unit[rows] @ R
        front = v[:, 2] > 0.5
        rows, v = rows[front], v[front]
        px = v[:, :2] / v[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        m = 2.0
        inside = (px[:, 0] > m) & (px[:, 0] < cam.width - 1 - m) & (px[:, 1] > m)
        inside &= px[:, 1] < cam.height - 1 - m
        return rows[inside], px[inside]

    def _accept(self, sol: AttitudeSolution) -> AttitudeSolution:
        if sol.R is None:
            self.history.clear()
        else:
            self.history.append((sol.t_s, sol.R))
            del self.history[: -self.config.rate_history - 1]
        return sol

    # ---- frames ---------------------------------------------------------------------------

    def track_spots(self, spots: Spots, t_s: float) -> AttitudeSolution:
        """Frame tracker step: associate spots with predicted stars, else lost in space."""
        start = time.process_time()
        R_pred = self.predict(t_s)
        sol = AttitudeSolution(t_s, None, None, "lost")
        if R_pred is not None and len(spots):
            rows, px = self.predicted_stars(R_pred)
            if rows.size:
                d = np.linalg.norm(spots.px[:, None, :] - px[None], axis=2)
                j = np.argmin(d, axis=1)
                ok = d[np.arange(len(spots)), j] < self.config.gate_px
                # one spot per star
                jj, first = np.unique(j[ok], return_index=True)
                si = np.flatnonzero(ok)[first]
                sol = self._solve(
                    t_s, bearings(self.cam, spots.px[si]), self.cat.ids[rows[jj]], "tracking"
                )
        if sol.R is None:
            sol = self.identify(spots, t_s)
        return self._accept(_with_cpu(sol, start))

    # ---- events ---------------------------------------------------------------------------

    def track_events(
        self, events: Events, t0_s: float, t1_s: float, span_s: float | None = None
    ) -> AttitudeSolution:
        """Event tracker step: an attitude at the centre of ``[t0_s, t1_s)`` from ``events``
        (already sliced; they may start earlier, ``span_s`` before ``t1_s``).

        Tracking: stamp each predicted star's gate into a label image, look every event up in
        it, balanced ON/OFF centroid per star, moved to the window centre with the predicted
        image motion, Wahba. Lost (or too few stars): lost-in-space on the window's blobs.
        """
        start = time.process_time()
        c = self.config
        t_mid = 0.5 * (t0_s + t1_s)
        R_pred = self.predict(t_mid)
        sol = AttitudeSolution(t_mid, None, None, "lost")
        if R_pred is not None and len(events):
            sol = self._track_gated(events, t_mid, R_pred, span_s or (t1_s - t0_s))
        if sol.R is None:
            sol = self.identify(
                event_spots(events, self.cam.width, self.cam.height, 2 * c.min_events), t_mid
            )
        return self._accept(_with_cpu(sol, start))

    def _track_gated(
        self, events: Events, t_mid: float, R_pred: np.ndarray, span_s: float
    ) -> AttitudeSolution:
        c = self.config
        cam = self.cam
        rows, px = self.predicted_stars(R_pred)
        if rows.size < c.min_stars:
            return AttitudeSolution(t_mid, None, None, "lost")
        # Until a rate is known (one past attitude) the prediction ignores the motion.
        # The events of a star spread along its path over the span.
        streak = float(np.linalg.norm(self.body_rate_rad_s())) * cam.fx * span_s
        gate = c.gate_px * (3.0 if len(self.history) < 3 else 1.0) + 0.5 * streak
        g = math.ceil(gate)
        off = np.arange(-g, g + 1)
        cx = np.rint(px[:, 0]).astype(np.int64)
        cy = np.rint(px[:, 1]).astype(np.int64)
        X = cx[:, None, None] + off[None, None, :]
        Y = cy[:, None, None] + off[None, :, None]
        X, Y = np.broadcast_arrays(X, Y)
        dist2 = (X - px[:, 0, None, None]) ** 2 + (Y - px[:, 1, None, None]) ** 2
        inside = (dist2 <= gate**2) & (X >= 0) & (X < cam.width) & (Y >= 0) & (Y < cam.height)
        label = np.zeros(cam.height * cam.width, dtype=np.int64)
        star = np.broadcast_to(np.arange(1, rows.size + 1)[:, None, None], X.shape)
        label[(Y * cam.width + X)[inside]] = star[inside]
        lab = label[events.y.astype(np.int64) * cam.width + events.x.astype(np.int64)]
        hit = lab > 0
        if not hit.any():
            return AttitudeSolution(t_mid, None, None, "lost")
        cen, t_star, cnt = _balanced_centroids(
            lab[hit],
            rows.size,
            events.x[hit].astype(float),
            events.y[hit].astype(float),
            events.t_s[hit],
            events.p[hit],
        )
        ok = cnt >= c.min_events
        if ok.sum() < c.min_stars:
            return AttitudeSolution(t_mid, None, None, "lost")
        # Move each centroid to the window centre along the predicted image motion.
        b = bearings(cam, cen[ok])
        w = self.body_rate_rad_s()
        b_mid = b + np.cross(b, w) * (t_mid - t_star[ok])[:, None]  # d b/dt = -w x b = b x w
        b_mid /= np.linalg.norm(b_mid, axis=1, keepdims=True)
        return self._solve(t_mid, b_mid, self.cat.ids[rows[ok]], "tracking")


def _with_cpu(sol: AttitudeSolution, start: float) -> AttitudeSolution:
    return AttitudeSolution(
        sol.t_s,
        sol.R,
        sol.cov,
        sol.status,
        sol.star_ids,
        sol.b_cam,
        1e3 * (time.process_time() - start),
    )


def run_event_tracker(
    tracker: StarTracker, events: Events, t0_s: float, t1_s: float
) -> list[AttitudeSolution]:
    """Attitude every ``window_s`` over ``[t0_s, t1_s)`` while tracking (each from the events of
    the last `StarTracker.integration_s`, at the centre of the newest ``window_s``); while
    lost, consecutive windows of ``lis_window_s`` (doubled after each failure, up to 8x) go to
    the lost-in-space solver. With
    ``drop_peak_on`` the peak ON events of the whole stream are removed first."""
    c = tracker.config
    if c.drop_peak_on and len(events):
        keep = ~peak_on_events(events.x, events.y, events.p)
        events = Events(
            t_us=events.t_us[keep], x=events.x[keep], y=events.y[keep], p=events.p[keep]
        )
    out: list[AttitudeSolution] = []
    t = t0_s
    fails = 0
    while True:
        if tracker.history:
            b = t + c.window_s
            if b > t1_s + 1e-9:
                break
            span = tracker.integration_s()
            ev = events.slice_time(max(t0_s, b - span), b)
            if len(tracker.history) < 2:
                # No rate yet to move centroids in time: the attitude is that of the span's
                # centre (still later than the lost-in-space output before it).
                sol = tracker.track_events(ev, b - span, b)
            else:
                sol = tracker.track_events(ev, t, b, span_s=span)
        else:
            # Lost: non-overlapping lost-in-space windows, so output times keep increasing;
            # after each failure the next window is twice as long (up to 8x): few stars fire
            # when the rotation axis is near the boresight.
            b = t + c.lis_window_s * 2 ** min(fails, 3)
            if b > t1_s + 1e-9:
                break
            sol = tracker.track_events(events.slice_time(t, b), t, b)
        out.append(sol)
        fails = fails + 1 if sol.R is None else 0
        t = b
    return out
