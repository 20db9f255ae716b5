"""Star-tracker frontend (seed 004): spots from events or frames, identification, attitude.

- Spots from events: the events of a time window are counted per pixel, 3x3-summed and
  thresholded; each connected blob is a star. Its position is the mean of the ON-event mean
  and the OFF-event mean (a moving star fires ON events on its leading edge and OFF events on
  its trailing edge, so the two means straddle the star) at the mean of their times. In
  tracking this balanced centroid starts a moving-spot fit (`fit_moving_spots`) of every
  event as a threshold-level crossing (`pixel_passes`, `ladder_levels`), which removes the
  centroid's along-track lag under threshold mismatch and its blindness to sub-pixel
  cross-track motion at slow slews (docs/stars.md).
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
  solve), balanced centroid, spot fit, then Wahba with per-star weights. Falls back to
  lost-in-space when fewer than ``min_stars`` remain.

Camera frame OpenCV; attitude ``inertial_from_camera`` (ICRS). Never imports gtsam.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from scipy.special import ndtr

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError
from satpose.datasets.events import Events
from satpose.datasets.geometry import matrix_to_rotvec, rotvec_to_matrix
from satpose.datasets.sequence import atomic_write
from satpose.datasets.sky import radec_to_unit
from satpose.frontend.star_events import StreamStats, stream_noise
from satpose.frontend.star_sensor import (
    Refractory,
    Thresholds,
    estimate_thresholds,
    pixel_intervals,
    refractory_from_stream,
    star_passes,
)

ARCSEC = math.pi / (180 * 3600)
_log = logging.getLogger(__name__)


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
    order = np.lexsort((np.asarray(x), np.asarray(y)))  # time order kept within a pixel
    ps = np.asarray(y)[order].astype(np.int32) * 65536 + np.asarray(x)[order]
    peak = np.zeros(order.size, dtype=bool)
    peak[order] = _peaks_sorted(ps, np.asarray(p)[order])
    return peak


def _peaks_sorted(pix: np.ndarray, pol: np.ndarray) -> np.ndarray:
    """`peak_on_events` on events sorted by pixel (time order kept within a pixel)."""
    peak = np.zeros(pix.size, dtype=bool)
    peak[:-1] = (pix[:-1] == pix[1:]) & (pol[:-1] == 1) & (pol[1:] == 0)
    return peak


@dataclass(frozen=True)
class PixelPasses:
    """Each event's place in its pixel's passes (arrays in the events' order).

    A star passing a pixel makes it fire a run of ON events and then a run of OFF events; a
    run is a maximal sequence of one polarity at one pixel.

    Attributes:
        pos: index of the event within its run (0 = first).
        run_len: length of its run.
        partner_len: length of the partner run (the OFF run after an ON run, the ON run
            before an OFF run), 0 if there is none.
        cut_start: the run is its pixel's first and starts within ``edge_s`` of the stream's
            first event, or it is the OFF run of such an ON run (the pass may have begun
            before the recording, above the resting level).
        cut_end: the run is its pixel's last, is ON and ends within ``edge_s`` of the
            stream's last event (the pass may not be over).
        open_end: the run's pass may not have returned to rest before the stream ended (its
            last run is its pixel's last and ends within ``edge_s`` of the last event).
        net: the pixel's polarity sum (+1 ON, -1 OFF) up to and including the event.
        net_last: the pixel's polarity sum over all its events.
        pixel_cut_start: the pixel's first run is ``cut_start``.
        pixel_open_end: the pixel's last run is ``open_end``.
        edge_s: the edge length used.
    """

    pos: np.ndarray
    run_len: np.ndarray
    partner_len: np.ndarray
    cut_start: np.ndarray
    cut_end: np.ndarray
    open_end: np.ndarray
    net: np.ndarray
    net_last: np.ndarray
    pixel_cut_start: np.ndarray
    pixel_open_end: np.ndarray
    edge_s: float


@dataclass(frozen=True)
class _SortedPasses:
    """Run and pixel structure of an event stream in pixel-major (stable) order."""

    order: np.ndarray  # event index of each sorted position
    pix: np.ndarray  # sorted pixel keys
    pol: np.ndarray  # sorted polarities
    new_run: np.ndarray  # sorted position starts a run
    starts: np.ndarray  # first sorted position of each run
    length: np.ndarray  # events per run
    on_then_off: np.ndarray  # run k is ON and run k + 1 its OFF run (same pixel)
    cut_start: np.ndarray  # per run, see PixelPasses
    cut_end: np.ndarray
    open_end: np.ndarray
    pix_id: np.ndarray  # sorted position -> pixel index
    first_ev: np.ndarray  # first sorted position of each pixel
    last_ev: np.ndarray
    net: np.ndarray  # polarity sum so far, sorted order
    pixel_cut: np.ndarray  # per pixel: its first run is cut_start
    pixel_open: np.ndarray  # per pixel: its last run is open_end
    edge_s: float
    t_s: np.ndarray  # times in the events' order (``t_s[order]``: sorted order)
    t_scale: float  # t_s * t_scale: [s]


def _sorted_passes(
    t_s: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    edge_s: float | None,
    t_scale: float = 1.0,
) -> _SortedPasses:
    # ``t_s * t_scale`` are the times [s]: the tracker passes integer microseconds, so that
    # only the gathered times are converted (the same values as converting all first).
    # Stable sort by pixel (radix sorts of the 16-bit coordinates): time order kept within it.
    # The stream-long arrays are the tracker's whole-stream step (2.8 M events at 6 deg/s):
    # only what the levels need is gathered into the sorted order, in 32-bit integers and
    # in place where possible (each fresh stream-long array costs page faults as well).
    order = np.lexsort((np.asarray(x), np.asarray(y)))
    n_ev = order.size
    key = np.asarray(y).astype(np.int32)
    key <<= 16
    np.bitwise_or(key, np.asarray(x), out=key, casting="unsafe")  # coordinates < 65536
    ps = key[order]
    del key
    pp = np.asarray(p)[order]
    t_s = np.asarray(t_s)
    pix_start = np.ones(n_ev, dtype=bool)
    np.not_equal(ps[1:], ps[:-1], out=pix_start[1:])
    new_run = np.ones(n_ev, dtype=bool)
    np.not_equal(pp[1:], pp[:-1], out=new_run[1:])
    new_run |= pix_start
    starts = np.flatnonzero(new_run).astype(np.int32)
    ends = np.append(starts[1:], n_ev) - 1
    length = ends - starts + 1
    run_pix, run_pol = ps[starts], pp[starts].astype(np.int8)
    t_start, t_end = t_s[order[starts]] * t_scale, t_s[order[ends]] * t_scale
    n_runs = starts.size
    on_then_off = np.zeros(n_runs, dtype=bool)
    on_then_off[:-1] = (run_pix[1:] == run_pix[:-1]) & (run_pol[:-1] == 1) & (run_pol[1:] == 0)
    if edge_s is None:
        # About one rise or fall: the 95th percentile of the runs' durations (cut runs
        # included: at slow slews most passes outlast a short recording).
        edge_s = float(np.percentile(t_end - t_start, 95))
    first_of_pix = np.ones(n_runs, dtype=bool)
    first_of_pix[1:] = run_pix[1:] != run_pix[:-1]
    last_of_pix = np.ones(n_runs, dtype=bool)
    last_of_pix[:-1] = run_pix[:-1] != run_pix[1:]
    t0, t1 = float(t_s.min() * t_scale), float(t_s.max() * t_scale)
    early = first_of_pix & (t_start < t0 + edge_s)
    cut_start = early.copy()
    cut_start[1:] |= on_then_off[:-1] & early[:-1]
    late = last_of_pix & (t_end > t1 - edge_s)
    cut_end = (run_pol == 1) & late
    open_end = late.copy()
    open_end[:-1] |= on_then_off[:-1] & late[1:]
    pix_id = np.cumsum(pix_start, dtype=np.int32)
    pix_id -= 1
    sgn = np.where(pp == 1, np.int32(1), np.int32(-1))
    net = np.cumsum(sgn, dtype=np.int32)
    first_ev = np.flatnonzero(pix_start)
    net -= (net[first_ev] - sgn[first_ev])[pix_id]  # the polarity sum within the pixel
    del sgn
    last_ev = np.append(first_ev[1:], n_ev) - 1
    # The runs of the pixels' first and last events (a first event starts a run).
    first_run = np.searchsorted(starts, first_ev)
    last_run = np.searchsorted(starts, last_ev, side="right") - 1
    return _SortedPasses(
        order,
        ps,
        pp,
        new_run,
        starts,
        length,
        on_then_off,
        cut_start,
        cut_end,
        open_end,
        pix_id,
        first_ev,
        last_ev,
        net,
        cut_start[first_run],
        open_end[last_run],
        float(edge_s),
        t_s,
        float(t_scale),
    )


def pixel_passes(
    t_s: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, edge_s: float | None = None
) -> PixelPasses:
    """The pass structure of a time-sorted event stream (`PixelPasses`).

    ``edge_s`` defaults to the 95th percentile of the runs' durations (first to last event):
    about one rise or fall; 0 treats no run as cut.
    """
    n_ev = np.asarray(t_s).size
    if n_ev == 0:
        z = np.zeros(0, dtype=np.int32)
        b = z.astype(bool)
        return PixelPasses(z, z, z, b, b, b, z, z, b, b, 0.0)
    s = _sorted_passes(t_s, x, y, p, edge_s)
    partner = np.zeros(s.starts.size, dtype=np.int32)
    partner[:-1] = np.where(s.on_then_off[:-1], s.length[1:], 0)
    partner[1:] += np.where(s.on_then_off[:-1], s.length[:-1], 0)
    # Back to the events' order: each event's run and its index in the sorted order.
    rank = np.empty(n_ev, dtype=np.int32)
    rank[s.order] = np.arange(n_ev, dtype=np.int32)
    run = (np.cumsum(s.new_run, dtype=np.int32) - 1)[rank]
    pid = s.pix_id[rank]
    return PixelPasses(
        pos=rank - s.starts[run],
        run_len=s.length[run],
        partner_len=partner[run],
        cut_start=s.cut_start[run],
        cut_end=s.cut_end[run],
        open_end=s.open_end[run],
        net=s.net[rank],
        net_last=s.net[s.last_ev][pid],
        pixel_cut_start=s.pixel_cut[pid],
        pixel_open_end=s.pixel_open[pid],
        edge_s=s.edge_s,
    )


def stream_levels(
    t_s: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, edge_s: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Each event's `ladder_levels` value and its `peak_on_events` flag, in the events' order.

    The same results as ``ladder_levels(p, pixel_passes(...))`` and ``peak_on_events``, from
    one pixel sort and two scatters back to the events' order (the tracker's whole-stream
    step: at 16 deg/s, 2.9 M events, it is several times cheaper than the two calls)."""
    lv = stream_levels_dead_time(t_s, x, y, p, 0.0, edge_s=edge_s)
    return lv.levels, lv.peak


@dataclass(frozen=True)
class StreamLevels:
    """What `stream_levels_dead_time` found (arrays in the events' order).

    Attributes:
        levels: `ladder_levels` as float32 (whole thresholds from the polarity sum; half-integer for
            pixels anchored at their last event).
        peak: `peak_on_events`.
        dead_time: thresholds each event's level stands for beyond ``levels`` because of
            the dead time (the log intensity's rise while the pixel was blind, `DEAD_TIME`
            below), None without one.
        refractory: the dead time measured from the stream (`star_sensor.estimate_refractory`),
            None when it was given.
        refractory_used_s: the dead time the levels account for [s].
    """

    levels: np.ndarray
    peak: np.ndarray
    dead_time: np.ndarray | None
    refractory: Refractory | None
    refractory_used_s: float


REFRACTORY_INTERVALS = 200_000
"""Most same-polarity intervals the dead time is measured from (`stream_levels_dead_time`)."""

DEAD_TIME_MAX_GAIN = 1.0
"""Most thresholds one interval's dead time adds to a level (`stream_levels_dead_time`):
``tau / (dt - tau)`` is capped here, since an interval within the timestamp jitter of the
dead time says only that the pixel was driven at least that fast."""


def stream_levels_dead_time(
    t_s: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    refractory_s: float | None,
    use: np.ndarray | None = None,
    edge_s: float | None = None,
    hot_intervals_us: np.ndarray | None = None,
    ladder: bool = True,
    t_scale: float = 1.0,
) -> StreamLevels:
    """`stream_levels` with the pixel's dead time in its levels.

    A DVS pixel is blind for ``tau`` after an event and its reference is then reset to the
    log intensity at that moment, so a pixel driven at log-intensity rate ``s`` fires one
    event per ``C + s tau``, not per ``C``: the interval is ``dt = tau + C / s``, and the
    step between two events of a run (same pixel and polarity) is ``C dt / (dt - tau)``.
    Each event's level is its polarity sum plus the sum over its pixel's earlier in-run
    intervals of ``tau / (dt - tau)`` (capped at `DEAD_TIME_MAX_GAIN`), signed like the
    run; pixels anchored at their last event keep their anchor. ``refractory_s`` None: the
    dead time is measured first (`star_sensor.refractory_from_stream`: the intervals of the
    hot pixels, ``hot_intervals_us``, else the same-polarity intervals of the events in
    ``use``, only if the hot pixels do not show it) and used if identified, else 0.
    ``ladder`` False: the dead time is measured (``refractory``) but not put into the
    levels (``dead_time`` None, ``refractory_used_s`` 0): the tracker's default, which
    skips the ladder's dozen stream-long arrays (about 0.5 ms per output at 6 deg/s).
    ``t_scale``: ``t_s * t_scale`` is in seconds (the tracker passes the integer
    microseconds with 1e-6: a stream-long float copy less)."""
    n_ev = np.asarray(t_s).size
    if n_ev == 0:
        return StreamLevels(np.zeros(0), np.zeros(0, dtype=bool), None, None, 0.0)
    s = _sorted_passes(t_s, x, y, p, edge_s, t_scale)
    offset = _level_offset(s.pixel_cut, s.pixel_open, s.net[s.last_ev])
    # float32: integers and halves (and NaN), exact; half the page faults of float64.
    sorted_levels = offset.astype(np.float32)[s.pix_id]
    sorted_levels += s.net
    levels = np.empty(n_ev, dtype=np.float32)
    levels[s.order] = sorted_levels
    del sorted_levels
    peak = np.empty(n_ev, dtype=bool)
    peak[s.order] = _peaks_sorted(s.pix, s.pol)
    found: Refractory | None = None
    tau = refractory_s
    if tau is None:

        def star_intervals_us() -> np.ndarray:
            # Same-polarity intervals (the event's predecessor in its run, both in
            # ``use``): an even subset of at most REFRACTORY_INTERVALS, enough for a
            # 200-bin histogram, picked before the stream-long arrays are formed.
            inner = np.flatnonzero(~s.new_run)
            if use is not None:
                u = np.asarray(use, bool)
                inner = inner[u[s.order[inner]] & u[s.order[inner - 1]]]
            inner = inner[:: max(1, -(-inner.size // REFRACTORY_INTERVALS))]
            t_a, t_b = s.t_s[s.order[inner]] * s.t_scale, s.t_s[s.order[inner - 1]] * s.t_scale
            return np.rint((t_a - t_b) * 1e6)

        found = refractory_from_stream(star_intervals_us, hot_intervals_us)
        tau = found.refractory_s if found.identified else 0.0
    if tau <= 0 or not ladder:
        return StreamLevels(levels, peak, None, found, 0.0)
    inner = ~s.new_run  # the event's predecessor is in its run
    dt = np.zeros(n_ev)
    dt[1:] = np.diff(s.t_s[s.order] * s.t_scale)
    gain = np.zeros(n_ev)
    gain[inner] = np.minimum(tau / np.maximum(dt[inner] - tau, 1e-12), DEAD_TIME_MAX_GAIN)
    gain[inner & (dt <= tau)] = DEAD_TIME_MAX_GAIN
    cs = np.cumsum(np.where(s.pol == 1, gain, -gain))
    extra = cs - (cs[s.first_ev] - 0.0)[s.pix_id]  # from the pixel's first event
    # Anchored pixels count from their last event.
    anchored = np.isfinite(offset) & s.pixel_cut
    extra = np.where(anchored[s.pix_id], extra - extra[s.last_ev][s.pix_id], extra)
    dead = np.empty(n_ev)
    dead[s.order] = extra
    return StreamLevels(levels, peak, dead, found, float(tau))


def matched_ladder_events(
    t_s: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    edge_s: float | None = None,
    passes: PixelPasses | None = None,
) -> np.ndarray:
    """Mask of the events that form level-matched ON/OFF pairs within each pixel's passes.

    A star passing a pixel makes it fire a run of ON events (levels ``L0 + k C_on``,
    ``k = 1..n``) and then a run of OFF events (``L0 + n C_on - k C_off``, ``k = 1..m``, the
    last one anywhere in ``(L0, L0 + C_off]``). The ``k``-th OFF event and the ``(n - k)``-th
    ON event cross levels that differ by ``k (C_on - C_off)``: zero without threshold
    mismatch and of zero mean with it (``C_on``, ``C_off`` are independent per pixel). Keeping
    for every pass only the ``K = min(n - 1, m)`` pairs ``(ON_{n-k}, OFF_k)``, ``k = 1..K``,
    leaves ON and OFF sets that mirror each other in level, so their centroids straddle the
    star symmetrically in expectation. What this drops: the top ON event (no OFF mirror),
    the lowest OFF events when the OFF ladder is longer (it ends up to ``C_off`` lower than
    the ON ladder starts: the along-track lag of `peak_on_events` alone) or the lowest ON
    events when it is shorter, and isolated noise events (a pass with one polarity only).

    The events must be time sorted. The decision needs the pixel's whole pass (about 0.2 s
    at 1 deg/s): this runs on the whole stream (`run_event_tracker`); an online system would
    have that latency. Runs cut by the ends of the stream (`pixel_passes`) have no partner
    to match: the OFF runs of passes cut by the start are kept whole, the ON runs of passes
    cut by either end without their top event if it is followed by an OFF event, else whole
    (`peak_on_events`' behaviour there, for about one rise or fall).
    """
    ps = passes if passes is not None else pixel_passes(t_s, x, y, p, edge_s)
    on = np.asarray(p) == 1
    pos, L = ps.pos, ps.run_len
    K = np.where(on, np.minimum(L - 1, ps.partner_len), np.minimum(ps.partner_len - 1, L))
    K = np.maximum(K, 0)
    keep = np.where(on, (pos <= L - 2) & (pos >= L - 1 - K), pos < K)
    has_off = ps.partner_len > 0
    keep |= ps.cut_start & ~on
    keep |= ps.cut_start & on & ((pos <= L - 2) | ~has_off)
    keep |= ps.cut_end
    return keep


def ladder_levels(p: np.ndarray, passes: PixelPasses) -> np.ndarray:
    """Each event's threshold level above its pixel's resting level, in thresholds ``C``.

    Every event moves the pixel's reference level by ``C`` (up for ON, down for OFF) and
    fires when the log intensity crosses the new reference, so the crossing's level is the
    pixel's polarity sum up to that event (`PixelPasses.net`) times ``C``, counted from the
    pixel's level at the start of the stream. A star passing a resting pixel gives ON
    events at ``L0 + k C`` (``k = 1..n``) and OFF events at ``L0 + (n - k) C``; a slow slew
    whose jitter makes the intensity go up and down gives the right levels too (no pass
    structure assumed). Nominal ``C`` for ``C_on`` and ``C_off``: the mismatch makes a level
    wrong by ``k dC``, zero on average. Pixels whose first run was cut by the start of the
    stream (not at rest then) are anchored at their last event instead: after a passing
    star the reference rests in ``(L0, L0 + C_off]``, taken as ``L0 + C / 2``; if their last
    run is also open-ended there is no anchor: NaN (the fit leaves them out).
    """
    del p  # the polarity is in the sums
    offset = _level_offset(passes.pixel_cut_start, passes.pixel_open_end, passes.net_last)
    return passes.net + offset


def _level_offset(cut_start: np.ndarray, open_end: np.ndarray, net_last: np.ndarray) -> np.ndarray:
    """What `ladder_levels` adds to a pixel's polarity sum: 0 for a pixel at rest at the
    start, ``1/2 - net_last`` for one anchored at its last event, NaN without an anchor."""
    offset = np.where(cut_start, 0.5 - net_last, 0.0)
    return np.where(cut_start & open_end, np.nan, offset)


def _pixel_psf(u: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of a unit Gaussian (sigma) centred at 0 falling on the pixel ``[u - 1/2,
    u + 1/2]`` and its derivative with respect to the Gaussian's centre."""
    a, b = (u + 0.5) / sigma, (u - 0.5) / sigma
    g = ndtr(a) - ndtr(b)
    dg = -(np.exp(-0.5 * a * a) - np.exp(-0.5 * b * b)) / (sigma * math.sqrt(2 * math.pi))
    return g, dg


def level_sigma(level: np.ndarray, contrast: float, threshold_sigma: float) -> np.ndarray:
    """Standard deviation [log units] of the log intensity an event's `ladder_levels` value
    ``level`` stands for: 0.03 (the crossing itself), ``level x threshold_sigma`` (the
    pixel's threshold mismatch accumulated over the ladder) and, for pixels anchored at
    their last event (half-integer levels: the reference rests anywhere in ``(L0, L0 + C]``
    after a pass), the anchor's uniform spread ``C / sqrt(12)``."""
    lvl = np.asarray(level, float)
    anchored = (lvl % 1.0) != 0.0
    return np.sqrt(0.03**2 + (lvl * threshold_sigma) ** 2 + anchored * (contrast**2 / 12.0))


@dataclass(frozen=True)
class SpotFit:
    """Moving-spot fit of each star (index ``0..S-1``).

    Attributes:
        px: position at the reference time, (S, 2).
        log_flux: ``log(F / background)`` of the whole star, (S,).
        cov: 2x2 covariance of ``px`` [px^2], (S, 2, 2): the inverse normal matrix scaled
            by the reduced chi-square of all the stars' residuals together.
        n: events used, (S,).
        ok: converged with enough events, (S,).
        d_omega: the shared body-rate correction [rad/s] (zero unless fitted).
        cost: Huber cost (at 2 sigma, in sigma^2) of all events of the stars with at least
            4 events, at the solution.
    """

    px: np.ndarray
    log_flux: np.ndarray
    cov: np.ndarray
    n: np.ndarray
    ok: np.ndarray
    d_omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    d_omega_data: np.ndarray = field(default_factory=lambda: np.zeros(3))
    d_omega_info: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    cost: float = 0.0


def fit_moving_spots(
    lab: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    dt: np.ndarray,
    level: np.ndarray,
    px0: np.ndarray,
    vel: np.ndarray,
    log_flux0: np.ndarray,
    psf_sigma_px: float,
    level_sigma: np.ndarray,
    iterations: int = 3,
    vel_sigma_px_s: float = 0.0,
    rate_jac: np.ndarray | None = None,
    rate_sigma: float = 0.0,
) -> SpotFit:
    """Fit moving Gaussian spots to events as level crossings (Gauss-Newton, all stars at once).

    Each event of star ``s`` at pixel ``(x, y)`` and time ``dt`` (relative to the reference
    time) says that the pixel's log intensity above its resting level,
    ``log(1 + F_s G(x - X_s(dt), y - Y_s(dt)))`` with the pixel-integrated PSF ``G`` and
    ``X_s(dt) = px_s + vel_s dt``, equals its threshold level ``level`` (in log units). The
    unknowns per star are the position and ``log F_s`` (relative to the background); the
    velocity comes from the predicted rate, or with ``vel_sigma_px_s > 0`` it is fitted too
    with that prior around ``vel`` (for slow slews, where the jitter's velocity exceeds the
    slew's). Residuals are weighted by ``1 / level_sigma`` with a Huber loss (noise events).
    Unlike a centroid of counts, this uses where every level was crossed, so a sub-pixel
    cross-track shift moves the crossing times even when it changes no pixel's event count.

    With ``rate_jac`` (S, 2, 3), ``d vel_s / d omega`` [px/s per rad/s], and ``rate_sigma``
    > 0 [rad/s] the stars share one correction ``d_omega`` of the body rate (prior sigma
    ``rate_sigma`` around zero): ``vel_s + rate_jac_s d_omega``, solved with the stars'
    unknowns eliminated (Schur complement); each star's ``cov`` is then its marginal.
    A jitter whose rate differs from the rate predicted over many outputs moves the stars
    within the span; one shared rate is 3 unknowns, per-star velocities 2 per star.
    """
    if iterations < 1:
        raise StarTrackerError("fit_moving_spots needs at least one iteration")
    S = px0.shape[0]
    P = 5 if vel_sigma_px_s > 0 else 3
    state = np.column_stack([px0, log_flux0, vel][:P] if P == 5 else [px0, log_flux0])
    state = state.astype(float)
    v0 = np.asarray(vel, float)
    w0 = 1.0 / np.asarray(level_sigma, float) ** 2
    cnt = np.bincount(lab, minlength=S)
    H = np.zeros((S, P, P))
    prior = np.zeros((P, P))
    if P == 5:
        prior[3, 3] = prior[4, 4] = 1.0 / vel_sigma_px_s**2

    shared = rate_jac is not None and rate_sigma > 0 and P == 3
    d_omega = np.zeros(3)
    A = np.zeros((S, 2, 3)) if rate_jac is None else np.asarray(rate_jac, float)

    def velocity() -> np.ndarray:
        if P == 5:
            return state[:, 3:5]
        return v0 + A @ d_omega if shared else v0

    fitted = cnt >= 4
    for _ in range(iterations):
        v = velocity()
        cx = state[lab, 0] + v[lab, 0] * dt
        cy = state[lab, 1] + v[lab, 1] * dt
        gx, dgx = _pixel_psf(x - cx, psf_sigma_px)
        gy, dgy = _pixel_psf(y - cy, psf_sigma_px)
        F = np.exp(state[lab, 2])
        G = gx * gy
        den = 1.0 + F * G
        r = np.log(den) - level
        # d r / d centre: d/dcx gx(x - cx) = -gx'(x - cx) = dgx as defined (centre derivative).
        jx, jy = F * dgx * gy / den, F * gx * dgy / den
        cols = [jx, jy, F * G / den] + ([jx * dt, jy * dt] if P == 5 else [])
        J = np.column_stack(cols)
        rs = np.abs(r) * np.sqrt(w0)
        w = w0 * np.where(rs > 2.0, 2.0 / np.maximum(rs, 1e-12), 1.0)  # Huber at 2 sigma
        g = np.zeros((S, P))
        for i in range(P):
            g[:, i] = np.bincount(lab, weights=w * J[:, i] * r, minlength=S)
            for j in range(i, P):
                H[:, i, j] = H[:, j, i] = np.bincount(
                    lab, weights=w * J[:, i] * J[:, j], minlength=S
                )
        H += prior
        if P == 5:
            g[:, 3:5] += (state[:, 3:5] - v0) / vel_sigma_px_s**2
        Hinv = np.linalg.inv(H + 1e-9 * np.eye(P))
        if shared:
            # Event Jacobian on d_omega: (d r / d centre) . rate_jac_s * dt; eliminate the stars.
            Jw = (jx[:, None] * A[lab, 0] + jy[:, None] * A[lab, 1]) * dt[:, None]
            Jw[~fitted[lab]] = 0.0
            Hso = np.zeros((S, 3, 3))
            g_o = np.zeros(3)
            H_oo = np.eye(3) / rate_sigma**2
            for a in range(3):
                g_o[a] = np.sum(w * Jw[:, a] * r) + d_omega[a] / rate_sigma**2
                for i in range(3):
                    Hso[:, i, a] = np.bincount(lab, weights=w * J[:, i] * Jw[:, a], minlength=S)
                for b in range(a, 3):
                    H_oo[a, b] = H_oo[b, a] = H_oo[a, b] + np.sum(w * Jw[:, a] * Jw[:, b])
            Hso[~fitted] = 0.0
            HiHso = Hinv @ Hso
            red = H_oo - np.einsum("sia,sib->ab", Hso, HiHso)
            g_red = g_o - np.einsum("sia,si->a", HiHso, g)
            red_inv = np.linalg.inv(red)
            dw = -red_inv @ g_red
            step = -(Hinv @ (g[:, :, None] + Hso @ dw[:, None]))[:, :, 0]
            d_omega += np.clip(dw, -3 * rate_sigma, 3 * rate_sigma)
        else:
            step = -(Hinv @ g[:, :, None])[:, :, 0]
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        step[:, 2] = np.clip(step[:, 2], -1.0, 1.0)
        state += np.where(fitted[:, None], step, 0.0)
    ok = fitted & np.all(np.isfinite(state), axis=1)
    ok &= np.all(np.abs(state[:, :2] - px0) < 1.5, axis=1)
    # Residuals at the solution: one chi-square scale for the window (per star it would rest
    # on a handful of events).
    v = velocity()
    gx, _ = _pixel_psf(x - state[lab, 0] - v[lab, 0] * dt, psf_sigma_px)
    gy, _ = _pixel_psf(y - state[lab, 1] - v[lab, 1] * dt, psf_sigma_px)
    r = np.log1p(np.exp(state[lab, 2]) * gx * gy) - level
    used = ok[lab]
    dof = int(used.sum()) - P * int(ok.sum())
    chi2 = float(np.sum((w * r * r)[used])) / dof if dof > 0 else 1.0
    # Huber cost (2 sigma) of every event of the stars with enough events: the same events
    # whatever the PSF, so fits with different PSF sigmas can be compared (`StarTracker`
    # measures the sigma this way).
    rs = np.abs(r[fitted[lab]]) * np.sqrt(w0[fitted[lab]])
    cost = float(np.sum(np.where(rs <= 2.0, rs * rs, 4.0 * rs - 4.0)))
    cov_full = Hinv  # the last iteration's (H is not changed after it)
    if shared:
        # Marginal of each star's unknowns with d_omega unknown too (last linearisation).
        cov_full = cov_full + HiHso @ red_inv @ np.swapaxes(HiHso, 1, 2)
    cov_full = cov_full * chi2
    rate_info = np.zeros((3, 3))
    d_data = np.zeros(3)
    if shared:
        # What the events alone say about the rate, prior taken out: at convergence
        # (info + prior) d_omega = info d_data. Information chi-square scaled.
        info = red - np.eye(3) / rate_sigma**2
        d_data = np.linalg.lstsq(info, red @ d_omega, rcond=None)[0]
        rate_info = info / chi2
    return SpotFit(
        state[:, :2],
        state[:, 2],
        cov_full[:, :2, :2],
        cnt,
        ok,
        d_omega,
        d_data,
        rate_info,
        cost if np.isfinite(cost) else math.inf,
    )


def _balanced_centroids(
    lab: np.ndarray, n: int, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-label ON/OFF-balanced centroid, time and event count for labels 1..n."""
    out_px = np.zeros((n + 1, 2))
    out_t = np.zeros(n + 1)
    # One bincount per quantity over (label, ON) keys: the same sums, in the same order, as
    # one per polarity (ON: p == 1; anything else counts as OFF, as before).
    key = 2 * np.asarray(lab, np.int64) + (p == 1)
    m2 = 2 * (n + 1)
    c0, c1 = np.bincount(key, minlength=m2).astype(float).reshape(-1, 2).T  # OFF, ON
    x0, x1 = np.bincount(key, weights=x, minlength=m2).reshape(-1, 2).T
    y0, y1 = np.bincount(key, weights=y, minlength=m2).reshape(-1, 2).T
    t0, t1 = np.bincount(key, weights=t, minlength=m2).reshape(-1, 2).T
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


CACHE_ENV = "SATPOSE_CACHE_DIR"
"""Environment variable naming the folder of saved tetra3rs databases (`database_cache_dir`);
set to an empty string, nothing is saved or read."""


def database_cache_dir() -> Path | None:
    """Where solver databases are saved: ``$SATPOSE_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/satpose``, else ``~/.cache/satpose``, then ``tetra3rs-<version>``
    (a database belongs to the tetra3rs release and its bundled catalogue); None when
    ``$SATPOSE_CACHE_DIR`` is set empty."""
    from importlib.metadata import version

    root = os.environ.get(CACHE_ENV)
    if root == "":
        return None
    if root is None:
        xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        root = str(Path(xdg) / "satpose")
    return Path(root) / f"tetra3rs-{version('tetra3rs')}"


@functools.lru_cache(maxsize=4)
def solver_database(min_fov_deg: float, max_fov_deg: float, epoch_yr: float) -> object:
    """A tetra3rs database from its bundled Gaia catalogue: kept per process, and saved in
    `database_cache_dir` so that later runs load it (0.05 s) instead of building it (12 s
    for a 6-31 deg pattern range, about 2 min for 2-11 deg). A saved file that does not
    load is rebuilt with a warning naming it; a folder that cannot be written only costs
    the saving (warned)."""
    import tetra3rs

    folder = database_cache_dir()
    path = None
    if folder is not None:
        path = folder / f"gaia-{min_fov_deg:g}-{max_fov_deg:g}deg-epoch{epoch_yr:g}.t3db"
        if path.is_file():
            try:
                return tetra3rs.SolverDatabase.load_from_file(str(path))
            except Exception as exc:  # any unreadable file: rebuild it
                _log.warning("%s: saved star database unreadable (%s); rebuilding it", path, exc)
    db = tetra3rs.SolverDatabase.generate_from_gaia(
        max_fov_deg=max_fov_deg, min_fov_deg=min_fov_deg, epoch_proper_motion_year=epoch_yr
    )
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: db.save_to_file(str(tmp)))
        except Exception as exc:  # a read-only or full disk: carry on without saving
            _log.warning("%s: star database not saved (%s)", path, exc)
    return db


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

_CONE_MARGIN_DEG = 2.0
"""Boresight motion before the tracker's catalogue cone is recomputed (`StarTracker._cone`)."""


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
        rate_history: outputs over which the rate for the prediction is differenced (80:
            0.4 s of 5 ms event outputs; fewer made the rate noisy at 0.1 deg/s).
        min_motion_px: star motion the events of one tracking output must span (slow slews
            integrate longer than ``window_s``; outputs stay ``window_s`` apart).
        event_selection: which events the balanced centroid (the spot fit's start, the
            lost-in-space blobs) uses, decided on the whole stream: ``drop_peak``
            (`peak_on_events` left out), ``matched`` (`matched_ladder_events`: level-matched
            ON/OFF pairs per pixel pass; the best choice for ``centroid="balanced"`` at
            slews, but it starves the tracker at 0.1 deg/s where most passes outlast the
            recording) or ``all``.
        acquisition_selection: the events of the lost-in-space blobs and of the first
            output after an acquisition (no rate yet, no fit): ``drop_peak`` (default: at
            16 deg/s, where that output centroids 50 ms long streaks, all events made the
            smoothed error 3.6 arcsec instead of 2.6) or the same as ``event_selection``
            (``all``). With ``event_selection="matched"`` the tracking selection is used.
        centroid: star position in tracking: ``spot_fit`` (`fit_moving_spots` on every
            event's threshold level, started from the balanced centroid) or ``balanced``.
        contrast_threshold, threshold_sigma, psf_sigma_px: the event sensor's nominal
            calibration (mean threshold C, its pixel-to-pixel spread, Gaussian PSF sigma) the
            spot fit assumes.
        fit_sigma_floor_px: added in quadrature to each spot fit's own position sigma
            (model errors the fit's residuals do not show).
        fit_max_events: most events per star the spot fit uses (evenly thinned beyond).
        fit_max_stars: most stars the spot fit (and then Wahba) uses: those with the most
            events.
        fit_velocity_sigma_px_s: > 0: the spot fit also fits each star's image velocity,
            with this prior sigma around the predicted one [px/s].
        fit_rate_sigma_rad_s: > 0: where a tracking output's span is longer than 1.5
            ``window_s``, the spot fit also fits one body rate shared by all stars, with
            this prior sigma around the predicted rate [rad/s] (0.003: about the rate of
            the 17 Hz, 10 arcsec jitter of the ``slew`` preset; 0.002-0.005 measured equal
            at 0.1 deg/s, docs/stars.md); the output then carries the rate measurement.
        scale_by_residuals: multiply each Wahba covariance by the reduced chi-square of its
            residuals when that exceeds 1.
        mag_limit: faintest catalogue star predicted in tracking.
        epoch_yr: epoch of the solver catalogue.
        psf_outputs: the PSF sigma of the spot fit is measured over the first this many
            fitted outputs (`StarTracker._measure_psf`; ``psf_sigma_px`` is then only the
            starting point); 0: ``psf_sigma_px`` is used as it is (calib.yaml states it).
        noise_window_s: background-activity filter: an event is used by the centroids,
            blobs and spot fit only if a neighbouring pixel fired within this time of it
            (`star_events.correlated_events`; 0: off).
        noise_min_share: the filter runs only if it drops at least this share of the
            stream's first 0.2 s (`star_events.stream_noise`: at fast slews nearly every
            event is a star's and the filter only costs CPU).
        gate_spot_rms: the tracking gate's radius is at least this many times the star
            image's measured size (`StarTracker.spot_rms_px`: RMS distance of a star's
            events from their centroid, measured right after an acquisition).
        hot_pixel_ratio: pixels with more than this many times the events of every
            neighbour are dropped from the stream (`star_events.hot_pixels`; 0: off).
        shrink_rate: shrink the predicted rate towards zero by its own noise
            (`StarTracker.body_rate_rad_s`; for stares right after an acquisition).
        static_span_s, static_motion_px: a failed tracking output is retried with spans up
            to ``static_span_s`` (instead of ``lis_window_s``) while the stars move less
            than ``static_motion_px`` in it (`StarTracker.max_span_s`).
        refractory_s: the pixels' dead time [s]; None: measured from the stream's
            same-polarity intervals (`star_sensor.estimate_refractory`; 0 where not
            identified).
        dead_time_levels: (off by default: on the second model the fits preferred the plain
            ladder, docs/stars.md) the spot fit's levels may count the log intensity's rise
            during each dead time (`stream_levels_dead_time`: a DVS pixel resets its reference when
            the dead time ends); whether they do is decided on the first
            ``dead_time_outputs`` fits by their costs (`StarTracker._choose_dead_time`).
    """

    window_s: float = 0.005
    lis_window_s: float = 0.05
    min_events: int = 4
    gate_px: float = 3.0
    min_stars: int = 5
    centroid_sigma_px: float = 0.35
    outlier_sigma: float = 5.0
    rate_history: int = 80
    min_motion_px: float = 0.15
    event_selection: Literal["matched", "drop_peak", "all"] = "all"
    acquisition_selection: Literal["drop_peak", "all"] = "drop_peak"
    centroid: Literal["spot_fit", "balanced"] = "spot_fit"
    contrast_threshold: float = 0.25
    threshold_sigma: float = 0.03
    psf_sigma_px: float = 0.8
    fit_sigma_floor_px: float = 0.05
    fit_max_events: int = 24
    fit_max_stars: int = 40
    fit_velocity_sigma_px_s: float = 0.0
    fit_rate_sigma_rad_s: float = 0.003
    scale_by_residuals: bool = True
    mag_limit: float = 7.5
    epoch_yr: float = 2026.9
    shrink_rate: bool = True
    noise_window_s: float = 0.01
    noise_min_share: float = 0.05
    gate_spot_rms: float = 2.2
    hot_pixel_ratio: float = 4.0
    static_span_s: float = 0.2
    static_motion_px: float = 1.0
    psf_outputs: int = 20
    refractory_s: float | None = None
    dead_time_levels: bool = False
    dead_time_outputs: int = 20

    def __post_init__(self) -> None:
        if not (0 < self.window_s <= self.lis_window_s):
            raise StarTrackerError("need 0 < window_s <= lis_window_s")
        if self.min_stars < 3 or self.gate_px <= 0 or self.centroid_sigma_px <= 0:
            raise StarTrackerError("min_stars >= 3, gate_px > 0, centroid_sigma_px > 0")
        if self.event_selection not in ("matched", "drop_peak", "all"):
            raise StarTrackerError(f"unknown event_selection {self.event_selection!r}")
        if self.acquisition_selection not in ("drop_peak", "all"):
            raise StarTrackerError(f"unknown acquisition_selection {self.acquisition_selection!r}")
        if self.centroid not in ("spot_fit", "balanced"):
            raise StarTrackerError(f"unknown centroid {self.centroid!r}")
        if not (self.contrast_threshold > 0 and self.threshold_sigma >= 0):
            raise StarTrackerError("contrast_threshold > 0 and threshold_sigma >= 0 needed")
        if not self.psf_sigma_px > 0:
            raise StarTrackerError("psf_sigma_px must be positive")
        if self.refractory_s is not None and not (
            math.isfinite(self.refractory_s) and self.refractory_s >= 0
        ):
            raise StarTrackerError("refractory_s must be >= 0 (or None: measured)")


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
        span_s: time span of the data behind it (event tracking: the integration span,
            which can be longer than the output period; frames: 0).
        stream_cpu_ms: this output's even share of the CPU time of the whole-stream event
            analysis (`run_event_tracker`: pass structure, levels, selection) [ms].
        data_t_s: event tracking: the time the data behind ``R`` centre on (the weighted
            mean time of the stars' events, weights as in Wahba), earlier than ``t_s`` by
            up to the span; ``R`` is the attitude there moved to ``t_s`` by the predicted
            rate (or the fitted one, ``fit_rate_sigma_rad_s``). A smoother should take
            ``data_R`` at ``data_t_s``: a rate predicted from 0.4 s of outputs cannot follow
            jitter faster than that. None: the data are at ``t_s``.
        data_R: the attitude at ``data_t_s`` (None with it).
        rate_meas_rad_s, rate_info: with ``fit_rate_sigma_rad_s``: the body rate the span's
            events measure (`fit_moving_spots`' shared rate, prior removed) and its 3x3
            information [(rad/s)^-2]; None otherwise.
    """

    t_s: float
    R: np.ndarray | None
    cov: np.ndarray | None
    status: Status
    star_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    b_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cpu_ms: float = 0.0
    span_s: float = 0.0
    stream_cpu_ms: float = 0.0
    data_t_s: float | None = None
    data_R: np.ndarray | None = None
    rate_meas_rad_s: np.ndarray | None = None
    rate_info: np.ndarray | None = None


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
        half_diag = math.radians(dfov / 2)
        margin = math.radians(_CONE_MARGIN_DEG)
        self._cone_cos_radius = math.cos(min(half_diag + 2 * margin, math.pi / 2))
        self._cone_cos_margin = math.cos(margin)
        self._cone_axis: np.ndarray | None = None
        self._cone_rows = np.zeros(0, dtype=np.int64)
        self._cone_unit = np.zeros((0, 3))
        self.sigma_rad = c.centroid_sigma_px / cam.fx
        self.history: list[tuple[float, np.ndarray, np.ndarray]] = []  # (t, R, cov)
        self._rate_src: tuple[np.ndarray, np.ndarray, float, float] | None = None
        self._rate = np.zeros(3)
        self.spot_rms_px: float | None = None  # measured (`_track_gated`), None until then
        self._label = np.zeros(0, dtype=np.int32)  # gate label image (`_track_gated`)
        self.stream_stats: StreamStats | None = None  # `run_event_tracker`'s noise findings
        self.refractory: Refractory | None = None  # the dead time measured from the stream
        self.refractory_used_s = 0.0  # the dead time the spot fit's levels account for
        # Whether the pixels reset after their dead time (None: not decided yet;
        # `_choose_dead_time`), and the two ladders' summed fit costs.
        self.dead_time_reset: bool | None = None
        self.dead_time_costs = np.zeros(2)
        self._dead_seen = 0
        # `run_event_tracker`'s stream without hot pixels and its noise-filter mask.
        self.stream: tuple[Events, np.ndarray] | None = None
        # PSF sigma of the spot fit: the configured one until measured (`_measure_psf`).
        self.psf_sigma_px = c.psf_sigma_px
        self._psf_costs: np.ndarray | None = (
            np.zeros(len(_PSF_FACTORS)) if c.psf_outputs > 0 else None
        )
        self._psf_seen = 0

    # ---- building blocks ------------------------------------------------------------------

    def _solve(
        self,
        t_s: float,
        b: np.ndarray,
        ids: np.ndarray,
        status: Status,
        sigma_rad: np.ndarray | None = None,
    ) -> AttitudeSolution:
        """Wahba on bearings ``b`` of catalogue stars ``ids`` (per-star noise ``sigma_rad``,
        default ``centroid_sigma_px``), one pass of outlier removal."""
        c = self.config
        if ids.size < c.min_stars:
            return AttitudeSolution(t_s, None, None, "lost")
        sig = np.broadcast_to(self.sigma_rad if sigma_rad is None else sigma_rad, ids.shape)
        r = self.cat.unit[[self.cat.row_of[int(i)] for i in ids]]
        R, cov = wahba(b, r, sig)
        res = np.linalg.norm(np.cross(r, b @ R.T), axis=1)
        ok = res < c.outlier_sigma * sig * math.sqrt(2)
        if ok.sum() < c.min_stars:
            return AttitudeSolution(t_s, None, None, "lost")
        if not ok.all():
            b, r, ids, sig = b[ok], r[ok], ids[ok], sig[ok]
            R, cov = wahba(b, r, sig)
        if c.scale_by_residuals:
            # Residuals larger than the assumed noise (2 DOF per star, 3 fitted) widen the
            # covariance; smaller ones never shrink it.
            res = np.linalg.norm(np.cross(r, b @ R.T), axis=1)
            chi2 = float(np.sum((res / sig) ** 2)) / max(2 * ids.size - 3, 1)
            cov = cov * max(1.0, chi2)
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
        t1, R1, _ = self.history[-1]
        return R1 @ rotvec_to_matrix(self.body_rate_rad_s() * (t_s - t1))

    def body_rate_rad_s(self) -> np.ndarray:
        """Body rate [rad/s] from the recent outputs (zero with fewer than two)."""
        if len(self.history) < 2:
            return np.zeros(3)
        k = max(0, len(self.history) - 1 - self.config.rate_history)
        (t0, R0, P0), (t1, R1, P1) = self.history[k], self.history[-1]
        src = self._rate_src  # once per output (predict, span, gate, motion all ask)
        if src is None or src[0] is not R0 or src[1] is not R1 or (src[2], src[3]) != (t0, t1):
            w = matrix_to_rotvec(R0.T @ R1) / (t1 - t0) if t1 > t0 else np.zeros(3)
            if self.config.shrink_rate and t1 > t0:
                # The difference of two noisy attitudes: per axis noise variance s^2 =
                # (var0 + var1) / dt^2. Shrunk towards zero by w^2 / (w^2 + s^2) (the MMSE
                # factor for a rate of that size): a slew is left as it is, but right after
                # an acquisition at a stare (outputs 10 ms apart, 20-80 arcsec noise: 2000
                # arcsec/s of rate noise against 0.05 deg/s) the noise no longer moves the
                # gates and the centroids (the second event model lost lock every 0.3 s).
                s2 = (np.diagonal(P0) + np.diagonal(P1)) / (t1 - t0) ** 2
                w = w * w**2 / np.maximum(w**2 + s2, 1e-30)
            self._rate = w
            self._rate_src = (R0, R1, t0, t1)  # holds the arrays: their ids stay theirs
        return self._rate

    def integration_s(self) -> float:
        """Event span for a tracking output: long enough for the stars to move
        ``min_motion_px`` at the current rate, between ``window_s`` and ``lis_window_s``.
        Until the rate is settled (`rate_settled`: right after acquisition, when a failed
        output is not retried) the motion asked for is doubled."""
        c = self.config
        speed = float(np.linalg.norm(self.body_rate_rad_s())) * self.cam.fx  # px/s near the centre
        if speed <= 0:
            return c.lis_window_s
        motion = c.min_motion_px * (1.0 if self.rate_settled() else 2.0)
        return float(np.clip(motion / speed, c.window_s, c.lis_window_s))

    def max_span_s(self) -> float:
        """Longest event span a tracking output may integrate when retried: ``lis_window_s``,
        or up to ``static_span_s`` while the stars move less than ``static_motion_px`` in it
        (a stare: jitter around a nearly still sky fires few events, and a longer span
        blurs nothing)."""
        c = self.config
        speed = float(np.linalg.norm(self.body_rate_rad_s())) * self.cam.fx
        if c.static_span_s <= c.lis_window_s:
            return c.lis_window_s
        if speed <= 0:
            return c.static_span_s
        return float(np.clip(c.static_motion_px / speed, c.lis_window_s, c.static_span_s))

    def rate_settled(self) -> bool:
        """Whether the rate rests on two tracked outputs after the last acquisition (the
        first one after a lost-in-space solve has no rate to compensate motion with)."""
        return len(self.history) >= 3

    def predicted_stars(self, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Catalogue rows (bright enough) in view of attitude ``R`` and their pixels."""
        cam = self.cam
        rows, unit = self._cone(R[:, 2])
        v = unit @ R
        front = v[:, 2] > 0.5
        rows, v = rows[front], v[front]
        px = v[:, :2] / v[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        m = 2.0
        inside = (px[:, 0] > m) & (px[:, 0] < cam.width - 1 - m) & (px[:, 1] > m)
        inside &= px[:, 1] < cam.height - 1 - m
        return rows[inside], px[inside]

    def _cone(self, boresight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bright catalogue rows (and unit vectors) within the field's half-diagonal plus
        ``_CONE_MARGIN_DEG`` of ``boresight``; recomputed only when the boresight has moved
        more than the margin (tracking projects a few hundred stars, not the catalogue)."""
        if self._cone_axis is None or float(boresight @ self._cone_axis) < self._cone_cos_margin:
            rows = np.flatnonzero(self._bright)
            keep = self.cat.unit[rows] @ boresight > self._cone_cos_radius
            self._cone_rows = rows[keep]
            self._cone_unit = self.cat.unit[self._cone_rows]
            self._cone_axis = boresight.copy()
        return self._cone_rows, self._cone_unit

    @property
    def psf_measured(self) -> bool:
        """Whether `psf_sigma_px` has been measured (`_measure_psf` finished)."""
        return self._psf_costs is None and self.config.psf_outputs > 0

    def _measure_psf(self, run_fit: Callable[[float], SpotFit]) -> None:
        """The star image's blur from the stream: over the first ``psf_outputs`` spot fits
        of a run, the fit is repeated with the PSF sigma at each of `_PSF_FACTORS` times the
        configured one and the Huber costs (`SpotFit.cost`: the same events each time) are
        summed; then the sigma at the parabola's minimum in log sigma through the best
        sigma and its two neighbours is used from there on. The model is a Gaussian:
        for a defocused star it finds the Gaussian that best explains the events' levels."""
        c = self.config
        if self._psf_costs is None:  # measured already (or stated)
            return
        self._psf_costs += [run_fit(c.psf_sigma_px * f).cost for f in _PSF_FACTORS]
        self._psf_seen += 1
        if self._psf_seen < c.psf_outputs:
            return
        cost, self._psf_costs = self._psf_costs, None
        k = int(np.clip(np.argmin(cost), 1, cost.size - 2))
        y0, y1, y2 = cost[k - 1 : k + 2]
        den = y0 - 2 * y1 + y2
        step = 0.5 * (y0 - y2) / den if den > 0 else 0.0
        log_f = math.log(_PSF_FACTORS[k]) + float(np.clip(step, -1, 1)) * math.log(2) / 4
        self.psf_sigma_px = c.psf_sigma_px * math.exp(log_f)

    def _choose_dead_time(self, cost_reset: float, cost_plain: float) -> None:
        """Whether the pixels reset their reference when the dead time ends (a DVS pixel:
        each step is ``C`` plus the rise while blind, `stream_levels_dead_time`) or count
        every crossing (a crossing while blind is lost but still moves the reference, as in
        ESIM): over the first ``dead_time_outputs`` spot fits with a dead time the fit's
        Huber costs (the same events) of both ladders are summed, and the lower one is used
        from then on (`dead_time_reset`)."""
        self.dead_time_costs += [cost_reset, cost_plain]
        self._dead_seen += 1
        if self._dead_seen >= self.config.dead_time_outputs:
            self.dead_time_reset = bool(self.dead_time_costs[0] <= self.dead_time_costs[1])

    def _accept(self, sol: AttitudeSolution) -> AttitudeSolution:
        if sol.R is None:
            self.history.clear()
        else:
            cov = np.zeros((3, 3)) if sol.cov is None else sol.cov
            self.history.append((sol.t_s, sol.R, cov))
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
        self,
        events: Events,
        t0_s: float,
        t1_s: float,
        span_s: float | None = None,
        levels: np.ndarray | None = None,
        selected: np.ndarray | None = None,
        blob_selected: np.ndarray | None = None,
        dead_time: np.ndarray | None = None,
    ) -> AttitudeSolution:
        """Event tracker step: an attitude at the centre of ``[t0_s, t1_s)`` from ``events``
        (already sliced; they may start earlier, ``span_s`` before ``t1_s``).

        Tracking: stamp each predicted star's gate into a label image, look every event up in
        it, balanced ON/OFF centroid per star, moved to the window centre with the predicted
        image motion; with ``levels`` (each event's `ladder_levels`, aligned with
        ``events``) and ``centroid="spot_fit"`` refined by `fit_moving_spots`; Wahba. Lost
        (or too few stars): lost-in-space on the window's blobs. ``selected`` (aligned with
        ``events``) marks the events the balanced centroids use (all if None),
        ``blob_selected`` those the blobs use (``selected`` if None). ``dead_time``
        (aligned with ``events``): thresholds the dead time adds to each level
        (`stream_levels_dead_time`), None: none.
        """
        start = time.process_time()
        c = self.config
        t_mid = 0.5 * (t0_s + t1_s)
        R_pred = self.predict(t_mid)
        sol = AttitudeSolution(t_mid, None, None, "lost")
        if R_pred is not None and len(events):
            sol = self._track_gated(
                events, t_mid, R_pred, span_s or (t1_s - t0_s), levels, selected, dead_time
            )
        if sol.R is None:
            use = selected if blob_selected is None else blob_selected
            blobs = events if use is None else _subset(events, use)
            sol = self.identify(
                event_spots(blobs, self.cam.width, self.cam.height, 2 * c.min_events), t_mid
            )
        return self._accept(_with_cpu(sol, start, span_s or (t1_s - t0_s)))

    def _track_gated(
        self,
        events: Events,
        t_mid: float,
        R_pred: np.ndarray,
        span_s: float,
        levels: np.ndarray | None = None,
        selected: np.ndarray | None = None,
        dead_time: np.ndarray | None = None,
    ) -> AttitudeSolution:
        c = self.config
        cam = self.cam
        rows, px = self.predicted_stars(R_pred)
        if rows.size < c.min_stars:
            return AttitudeSolution(t_mid, None, None, "lost")
        # Until a rate is known (one past attitude) the prediction ignores the motion.
        # The events of a star spread along its path over the span.
        streak = float(np.linalg.norm(self.body_rate_rad_s())) * cam.fx * span_s
        wide = len(self.history) < 3
        base = c.gate_px
        if self.spot_rms_px is not None:
            # A wide (defocused) star's events reach beyond gate_px: a gate that cuts one
            # side of them pulls the centroid towards the prediction, and the error feeds
            # back (the second event model's stare: 100 arcsec).
            base = max(base, c.gate_spot_rms * self.spot_rms_px)
        gate = base * (3.0 if wide else 1.0) + 0.5 * streak
        # The pixel offsets (raster order) from a star's rounded pixel that can be within
        # the gate (the star is within half a pixel of it per axis): about 2/3 of the square.
        g = math.ceil(gate)
        oy, ox = np.mgrid[-g : g + 1, -g : g + 1].reshape(2, -1)
        near = np.maximum(np.abs(ox) - 0.5, 0) ** 2 + np.maximum(np.abs(oy) - 0.5, 0) ** 2
        ox, oy = ox[near <= gate**2], oy[near <= gate**2]
        cx = np.rint(px[:, 0]).astype(np.int64)
        cy = np.rint(px[:, 1]).astype(np.int64)
        X = cx[:, None] + ox[None, :]
        Y = cy[:, None] + oy[None, :]
        dist2 = (X - px[:, 0, None]) ** 2 + (Y - px[:, 1, None]) ** 2
        inside = (dist2 <= gate**2) & (X >= 0) & (X < cam.width) & (Y >= 0) & (Y < cam.height)
        # One label image per tracker, cleared after use (zeroing 0.3 M pixels per output
        # was a tenth of the CPU per output at 6 deg/s).
        if self._label.size != cam.height * cam.width:
            self._label = np.zeros(cam.height * cam.width, dtype=np.int32)
        label = self._label
        stamped = (Y * cam.width + X)[inside]
        star = np.broadcast_to(np.arange(1, rows.size + 1)[:, None], X.shape)
        label[stamped] = star[inside]
        lab_all = label[events.y.astype(np.int32) * cam.width + events.x].astype(np.int64)
        label[stamped] = 0
        # The gated events only, from here on (a star's events are a small share of a
        # window's at fast slews).
        gi = np.flatnonzero(lab_all)
        lab = lab_all[gi]
        ex_f, ey_f = events.x[gi].astype(float), events.y[gi].astype(float)
        et = events.t_us[gi] * 1e-6
        ep = events.p[gi]
        hit = np.ones(gi.size, dtype=bool) if selected is None else selected[gi]
        if not hit.any():
            return AttitudeSolution(t_mid, None, None, "lost")
        cen, t_star, cnt = _balanced_centroids(
            lab[hit], rows.size, ex_f[hit], ey_f[hit], et[hit], ep[hit]
        )
        ok = cnt >= c.min_events
        if ok.sum() < c.min_stars:
            return AttitudeSolution(t_mid, None, None, "lost")
        if len(self.history) == 2 and streak < 1.0:
            # The star image's size from the wide gate of the second output after an
            # acquisition (the first with a rate; nothing cut): the median over stars of the
            # events' RMS distance from their centroid, if the stars hardly move in the span.
            li = lab[hit] - 1
            d2 = (ex_f[hit] - cen[li, 0]) ** 2 + (ey_f[hit] - cen[li, 1]) ** 2
            near = d2 < (c.gate_px * 2.0) ** 2  # not a neighbouring star's events
            r2 = np.bincount(li[near], weights=d2[near], minlength=rows.size)
            n2 = np.bincount(li[near], minlength=rows.size)
            good = ok & (n2 >= 2 * c.min_events)
            if good.sum() >= c.min_stars:
                rms = float(np.median(np.sqrt(r2[good] / n2[good])))
                self.spot_rms_px = rms if self.spot_rms_px is None else max(self.spot_rms_px, rms)
        # Move each centroid to the window centre along the predicted image motion.
        b = bearings(cam, cen[ok])
        w = self.body_rate_rad_s()
        b_mid = b + np.cross(b, w) * (t_mid - t_star[ok])[:, None]  # d b/dt = -w x b = b x w
        b_mid /= np.linalg.norm(b_mid, axis=1, keepdims=True)
        if levels is None or c.centroid != "spot_fit" or len(self.history) < 2:
            # (Without a rate the fit would take moving stars for still ones.)
            sol = self._solve(t_mid, b_mid, self.cat.ids[rows[ok]], "tracking")
            ones = np.ones(int(ok.sum()))
            return _at_data_time(sol, _compact_labels(ok)[lab[hit]], et[hit], ones, w)
        # Moving-spot fit, started from the moved centroids, velocity from the predicted rate,
        # on the fit_max_stars stars with the most events (CPU per output bounded).
        if ok.sum() > c.fit_max_stars:
            keep_rows = np.flatnonzero(ok)[np.argsort(-cnt[ok], kind="stable")]
            sub = np.isin(np.flatnonzero(ok), keep_rows[: c.fit_max_stars])
            ok[np.flatnonzero(ok)[~sub]] = False
            b_mid = b_mid[sub]
        px_mid = b_mid[:, :2] / b_mid[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        vel_jac = _velocity_rate_jacobian(b_mid, cam.fx, cam.fy)
        vel = vel_jac @ w
        star_of = _compact_labels(ok)
        li = star_of[lab]
        lvl_g = levels[gi].astype(float)  # (`stream_levels_dead_time` stores float32)
        use = (li >= 0) & (lvl_g > 0)
        # At most about fit_max_events per star (a deterministic, evenly spread subset: the
        # golden-ratio sequence of the event index): CPU per output stays bounded at fast
        # slews, where a star fires hundreds of events per window.
        n_star = np.bincount(li[use], minlength=int(ok.sum()))
        frac = (np.arange(li.size) * 0.6180339887498949) % 1.0
        use &= frac < c.fit_max_events / np.maximum(n_star, 1)[np.maximum(li, 0)]
        lvl = lvl_g[use]
        # The log intensity each event stands for, in thresholds: the ladder level plus
        # what the dead times before it added (a DVS pixel's reset), unless the stream's
        # first fits preferred the plain ladder (`_choose_dead_time`).
        with_dead = None if dead_time is None else lvl + dead_time[gi][use]
        lvl_c = lvl if with_dead is None or self.dead_time_reset is False else with_dead
        li = li[use]
        top = np.zeros(int(ok.sum()))
        np.maximum.at(top, li, lvl_c)
        sigma_psf = self.psf_sigma_px
        g0 = float((2 * ndtr(0.5 / sigma_psf) - 1) ** 2)
        C = c.contrast_threshold
        log_flux0 = np.log(np.maximum(np.expm1((top + 0.5) * C), 1e-3) / g0)
        # One body rate for the span's stars, fitted, where the span reaches back over more
        # than one output (slow slews): within it jitter moves the stars at a rate the
        # prediction (0.4 s of outputs) averages away.
        shared_rate = c.fit_rate_sigma_rad_s > 0 and span_s > 1.5 * c.window_s

        def run_fit(sigma: float, levels_c: np.ndarray = lvl_c) -> SpotFit:
            return fit_moving_spots(
                li,
                ex_f[use],
                ey_f[use],
                et[use] - t_mid,
                levels_c * C,
                px_mid,
                vel,
                log_flux0,
                sigma,
                level_sigma(lvl, c.contrast_threshold, c.threshold_sigma),
                vel_sigma_px_s=c.fit_velocity_sigma_px_s,
                rate_jac=vel_jac,
                rate_sigma=c.fit_rate_sigma_rad_s if shared_rate else 0.0,
            )

        fit = run_fit(sigma_psf)
        if self._psf_costs is not None and int(fit.ok.sum()) >= c.min_stars:
            self._measure_psf(run_fit)
        if with_dead is not None and self.dead_time_reset is None and fit.ok.sum() >= c.min_stars:
            self._choose_dead_time(fit.cost, run_fit(sigma_psf, lvl).cost)
        # Fitted stars with the fit's own noise (mean of the two axes' variances, floored);
        # stars the fit could not take (fewer than 4 levelled events: most of them at
        # 0.1 deg/s) keep their moved balanced centroid with centroid_sigma_px.
        good = fit.ok
        b_use = b_mid.copy()
        sig = np.full(b_use.shape[0], self.sigma_rad)
        b_use[good] = bearings(cam, fit.px[good])
        var = 0.5 * np.trace(fit.cov[good], axis1=1, axis2=2)
        sig[good] = np.sqrt(var + c.fit_sigma_floor_px**2) / cam.fx
        sol = self._solve(t_mid, b_use, self.cat.ids[rows[ok]], "tracking", sig)
        if shared_rate and sol.R is not None:
            # The fitted positions are at t_mid along the fitted rate: data_R goes back along
            # it, and the output carries the span's own rate measurement.
            sol = replace(sol, rate_meas_rad_s=w + fit.d_omega_data, rate_info=fit.d_omega_info)
            w = w + fit.d_omega
        return _at_data_time(sol, star_of[lab[hit]], et[hit], sig**-2.0, w)


_PSF_FACTORS = 2.0 ** (np.arange(-2, 5) / 4.0)
"""PSF sigmas tried by `StarTracker._measure_psf`, relative to the configured one
(0.71x-2x)."""


def _compact_labels(ok: np.ndarray) -> np.ndarray:
    """Map from 1-based gate labels (0: no star) to ``0..ok.sum()-1`` for the stars ``ok``,
    -1 for the others."""
    star_of = np.full(ok.size + 1, -1, dtype=np.int64)
    star_of[1:][ok] = np.arange(int(ok.sum()))
    return star_of


def _at_data_time(
    sol: AttitudeSolution, star: np.ndarray, t: np.ndarray, weight: np.ndarray, rate: np.ndarray
) -> AttitudeSolution:
    """``sol`` with the time its data centre on (`AttitudeSolution.data_t_s`): each star used
    (events at ``t`` of star ``star``, -1: none used) spreads its Wahba ``weight`` evenly
    over its events. ``data_R``: ``sol.R`` moved back there by the body ``rate`` it was moved
    forward with."""
    if sol.R is None:
        return sol
    keep = star >= 0
    s, t = star[keep], t[keep]
    w_ev = weight[s] / np.bincount(s, minlength=weight.size)[s]
    t_data = float(np.sum(w_ev * t) / np.sum(w_ev))
    R_data = sol.R @ rotvec_to_matrix(rate * (t_data - sol.t_s))
    return replace(sol, data_t_s=t_data, data_R=R_data)


def _velocity_rate_jacobian(b: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """``d (pixel velocity) / d (body rate)`` of stars at bearings ``b`` (N, 2, 3): the
    bearing moves as ``db/dt = b x w = [b]_x w``, the pixel as the projection's Jacobian."""
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    P = np.zeros((b.shape[0], 2, 3))
    P[:, 0, 0] = fx / bz
    P[:, 0, 2] = -fx * bx / bz**2
    P[:, 1, 1] = fy / bz
    P[:, 1, 2] = -fy * by / bz**2
    skew = np.zeros((b.shape[0], 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -bz, by, -bx
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = bz, -by, bx
    return P @ skew


def _subset(events: Events, keep: np.ndarray) -> Events:
    return Events(t_us=events.t_us[keep], x=events.x[keep], y=events.y[keep], p=events.p[keep])


def _with_cpu(sol: AttitudeSolution, start: float, span_s: float = 0.0) -> AttitudeSolution:
    return replace(sol, cpu_ms=1e3 * (time.process_time() - start), span_s=span_s)


def run_event_tracker(
    tracker: StarTracker, events: Events, t0_s: float, t1_s: float
) -> list[AttitudeSolution]:
    """Attitude every ``window_s`` over ``[t0_s, t1_s)`` while tracking (each from the events of
    the last `StarTracker.integration_s`, at the centre of the newest ``window_s``); while
    lost, consecutive windows of ``lis_window_s`` (doubled after each failure, up to 8x) go to
    the lost-in-space solver. With
    ``event_selection`` the stream's events are selected first (`matched_ladder_events`,
    `peak_on_events`); with ``centroid="spot_fit"`` every event's threshold level is
    computed first (`ladder_levels`). Each output's ``stream_cpu_ms`` is an even share of
    that whole-stream step."""
    c = tracker.config
    cpu0 = time.process_time()
    # Hot pixels out of the stream; uncorrelated events (background activity) out of the
    # centroids, blobs and fit (their levels NaN), but kept for the pixels' level ladders.
    W, H = tracker.cam.width, tracker.cam.height
    clean, not_hot, noise = stream_noise(
        events, W, H, c.noise_window_s, c.hot_pixel_ratio, c.noise_min_share
    )
    tracker.stream_stats = noise
    hot_dt: np.ndarray | None = None
    if noise.hot_pixels.size:
        hot_ev = _subset(events, ~not_hot)
        hot_dt = pixel_intervals(hot_ev.t_us, hot_ev.x, hot_ev.y)
        events, clean = _subset(events, not_hot), clean[not_hot]
    tracker.stream = (events, clean)
    selected = np.ones(len(events), dtype=bool)
    acquire: np.ndarray | None = None  # acquisition's selection, if different
    levels: np.ndarray | None = None
    dead: np.ndarray | None = None  # thresholds the dead time adds to each level
    fits = c.centroid == "spot_fit"
    if len(events) and c.event_selection == "matched":
        passes = pixel_passes(events.t_s, events.x, events.y, events.p)
        selected = matched_ladder_events(events.t_s, events.x, events.y, events.p, passes=passes)
        if fits:
            levels = ladder_levels(events.p, passes)
    elif len(events) and (fits or "drop_peak" in (c.event_selection, c.acquisition_selection)):
        sl = stream_levels_dead_time(
            events.t_us,
            events.x,
            events.y,
            events.p,
            c.refractory_s,
            clean,
            hot_intervals_us=hot_dt,
            ladder=fits and c.dead_time_levels,
            t_scale=1e-6,
        )
        tracker.refractory = sl.refractory
        if fits and c.dead_time_levels:
            tracker.refractory_used_s, dead = sl.refractory_used_s, sl.dead_time
        all_levels, peak = sl.levels, sl.peak
        levels = all_levels if fits else None
        if c.event_selection == "drop_peak":
            selected = ~peak
        elif c.acquisition_selection == "drop_peak":
            acquire = ~peak & clean
    selected &= clean
    if acquire is None:
        acquire = selected
    if levels is not None:
        levels[~clean] = np.nan  # in place: the stream-long array is this function's own
    if levels is None:
        events, acquire = _subset(events, selected), acquire[selected]
        selected = np.ones(len(events), dtype=bool)
        dead = None
    prep_cpu_ms = 1e3 * (time.process_time() - cpu0)

    def window(
        a: float, b: float
    ) -> tuple[Events, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        i0, i1 = np.searchsorted(events.t_us, [round(a * 1e6), round(b * 1e6)])
        ev = Events(
            t_us=events.t_us[i0:i1], x=events.x[i0:i1], y=events.y[i0:i1], p=events.p[i0:i1]
        )
        lv = None if levels is None else levels[i0:i1]
        dt = None if dead is None else dead[i0:i1]
        return ev, selected[i0:i1], acquire[i0:i1], lv, dt

    out: list[AttitudeSolution] = []
    t = t0_s
    fails = 0
    while True:
        if tracker.history:
            b = t + c.window_s
            if b > t1_s + 1e-9:
                break
            span = tracker.integration_s()
            ev, sel, acq, lv, dt = window(max(t0_s, b - span), b)
            if len(tracker.history) < 2:
                # No rate yet to move centroids in time: the attitude is that of the span's
                # centre (still later than the lost-in-space output before it); the
                # acquisition's events.
                sol = tracker.track_events(ev, b - span, b, levels=lv, selected=acq)
            else:
                saved = list(tracker.history)
                settled = tracker.rate_settled()
                sol = tracker.track_events(
                    ev, t, b, span_s=span, levels=lv, selected=sel, blob_selected=acq, dead_time=dt
                )
                cpu = sol.cpu_ms
                # Too few events (the stars nearly stop along track when the jitter cancels
                # a slow slew): retry the same output with twice the span, up to
                # lis_window_s, before giving up tracking. Only once the rate is settled
                # (right after acquisition a failure more likely means a bad rate).
                max_span = tracker.max_span_s()
                while settled and sol.status != "tracking" and span < max_span:
                    span = min(2 * span, max_span)
                    tracker.history[:] = saved
                    ev, sel, acq, lv, dt = window(max(t0_s, b - span), b)
                    sol = tracker.track_events(
                        ev,
                        t,
                        b,
                        span_s=span,
                        levels=lv,
                        selected=sel,
                        blob_selected=acq,
                        dead_time=dt,
                    )
                    cpu += sol.cpu_ms
                sol = replace(sol, cpu_ms=cpu)
        else:
            # Lost: non-overlapping lost-in-space windows, so output times keep increasing;
            # after each failure the next window is twice as long (up to 8x): few stars fire
            # when the rotation axis is near the boresight.
            b = t + c.lis_window_s * 2 ** min(fails, 3)
            if b > t1_s + 1e-9:
                break
            ev, _, acq, _, _ = window(t, b)
            sol = tracker.track_events(_subset(ev, acq), t, b)
        out.append(sol)
        fails = fails + 1 if sol.R is None else 0
        t = b
    # The whole-stream pass analysis (incremental per event in an online system) is charged
    # to the outputs evenly.
    share = prep_cpu_ms / max(len(out), 1)
    return [replace(s, stream_cpu_ms=share) for s in out]


def measure_thresholds(
    tracker: StarTracker, sols: list[AttitudeSolution], max_events: int = 2_000_000
) -> Thresholds | None:
    """The sensor's mean ON and OFF contrast thresholds from the stream `run_event_tracker`
    tracked (its first ``max_events`` events) and the attitudes it output
    (`star_sensor.estimate_thresholds`: event counts of identified stars' passes against
    their catalogue magnitudes, each interval counted with the dead time where the spot
    fit's levels count it: pixels that reset, `StarTracker.dead_time_reset`).
    None: no stream, fewer than two attitudes, or too few stars."""
    from scipy.spatial.transform import Rotation, Slerp

    if tracker.stream is None:
        return None
    ok = [s for s in sols if s.R is not None]
    if len(ok) < 2:
        return None
    events, clean = tracker.stream
    n = min(len(events), max_events)
    t_ok = np.array([s.t_s for s in ok])
    R_ok = np.array([s.R for s in ok])
    slerp = Slerp(t_ok, Rotation.from_matrix(R_ok))

    def attitude_at(t: np.ndarray) -> np.ndarray:
        return np.asarray(slerp(np.clip(t, t_ok[0], t_ok[-1])).as_matrix())

    tau = tracker.refractory_used_s if tracker.dead_time_reset else 0.0
    passes = star_passes(events.t_us[:n], events.x[:n], events.y[:n], events.p[:n], clean[:n], tau)
    inside = (passes.t_peak_s >= t_ok[0]) & (passes.t_peak_s <= t_ok[-1])
    cam = tracker.cam
    return estimate_thresholds(
        passes.subset(inside),
        attitude_at,
        cam.fx,
        cam.fy,
        cam.cx,
        cam.cy,
        tracker.cat.unit,
        tracker.cat.mag,
    )
