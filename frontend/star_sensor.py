"""The event sensor's refractory period and contrast thresholds, measured from its own stream
(issue 18 part 3; docs/stars.md "What is measured from the stream").

- **Refractory period** (`estimate_refractory`): after an event a pixel is blind for a dead
  time, so no two events of one pixel come closer than that. The intervals between
  consecutive same-polarity events of a pixel (a pixel driven one way by a passing star)
  start at the dead time plus the time the fastest-driven pixels need for one threshold;
  where many pixels are driven faster than one threshold per dead time they pile up right
  above it. The estimate is the lower edge of that distribution, fitted as a step blurred by
  the timestamps' jitter (which the fit measures too). A stream whose intervals start
  smoothly from zero has none (0); a stream whose shortest intervals are long (a slow slew)
  bounds it from above only (``identified`` false).
- **Contrast thresholds** (`estimate_thresholds`): each event is one step ``C`` of log
  intensity, so a pixel the centre of a star's image passes over fires
  ``n ~ log(1 + F g / B) / C_on`` ON events (then about as many OFF events with ``C_off``).
  The flux ``F`` is unknown (zero point, background, optics), but catalogue magnitudes give
  the flux *ratios* of stars: ``log F = a - 0.4 ln(10) m`` with one unknown ``a``. The
  number of events per magnitude therefore measures ``C`` without a photometric zero point
  (relative photometry only). The event *times* alone do not: the spot fit with the
  threshold scaled by ``k`` fits as well with the PSF narrowed and the flux rescaled
  (docs/stars.md gives the numbers). With a dead time each step is larger by the
  log intensity's rise while blind; an interval ``dt`` then stands for ``dt / (dt - tau)``
  thresholds (a pixel reset to the current intensity at the end of the dead time, the DVS
  pixel's behaviour).

numpy and scipy only; every function works on the whole time-sorted stream.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

LN10_04 = 0.4 * math.log(10.0)
"""``d log F / d m`` for magnitudes: -0.921 per magnitude."""


# --------------------------------------------------------------------------------------------
# Intervals and passes
# --------------------------------------------------------------------------------------------


def _pixel_sort(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stable order by pixel (time order kept within it), the sorted pixel keys, and a mask
    of sorted positions whose predecessor is the same pixel."""
    order = np.lexsort((np.asarray(x), np.asarray(y)))
    key = np.asarray(y)[order].astype(np.int64) * 65536 + np.asarray(x)[order]
    same = np.zeros(order.size, dtype=bool)
    same[1:] = key[1:] == key[:-1]
    return order, key, same


def pixel_intervals(t_us: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Intervals [us] between consecutive events of one pixel, whatever their polarity."""
    t_us = np.asarray(t_us)
    if t_us.size < 2:
        return np.zeros(0)
    order, _, same = _pixel_sort(x, y)
    return np.diff(t_us[order]).astype(float)[same[1:]]


def refractory_from_stream(
    star_dt_us: np.ndarray | Callable[[], np.ndarray], hot_dt_us: np.ndarray | None
) -> Refractory:
    """The dead time from a stream's intervals (`estimate_refractory` on each source).

    - **Hot pixels** (`pixel_intervals` of the pixels `star_events.hot_pixels` found): a
      leaky pixel fires at random, so its intervals are flat-topped and a dead time cuts
      them off sharply at ``tau``: where identified there, that is the estimate.
    - **Star passes** (`same_polarity_intervals`): a pixel resetting after its dead time
      fires every ``tau + C / s`` at log-intensity rate ``s``, so their shortest intervals
      are the dead time *plus* the fastest pixels' time per threshold. They measure a dead
      time only when they reach down to zero (none: 0); otherwise their edge bounds it
      from above (``identified`` false; at 900 px/s on a 1.5 px defocused disk the edge
      was 0.42 ms for a 0.3 ms dead time and 0.13 ms for none).

    ``star_dt_us``: the star passes' intervals [us], or a function giving them (called
    only when the hot pixels do not show the dead time: forming them costs stream-long
    arrays).
    """
    if hot_dt_us is not None and np.size(hot_dt_us) >= 200:
        hot = estimate_refractory(hot_dt_us)
        if hot.identified:
            return replace(hot, source="hot pixels")
    star = estimate_refractory(star_dt_us() if callable(star_dt_us) else star_dt_us)
    if star.identified and star.refractory_s == 0:
        return replace(star, source="star passes (intervals reach zero: none)")
    bound = star.refractory_s if not star.identified else star.refractory_s + 2 * star.jitter_s
    return replace(
        star,
        refractory_s=bound,
        sigma_s=bound / 2,
        identified=False,
        source="star passes: an upper bound (the dead time plus the fastest pixels' time "
        "per threshold)",
    )


def same_polarity_intervals(
    t_us: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, use: np.ndarray | None = None
) -> np.ndarray:
    """Intervals [us] between consecutive events of one pixel with the same polarity (both in
    ``use``, if given): the pixel driven one way, where a dead time shows."""
    t_us, x, y, p = (np.asarray(a) for a in (t_us, x, y, p))
    if use is not None:
        t_us, x, y, p = t_us[use], x[use], y[use], p[use]
    if t_us.size < 2:
        return np.zeros(0)
    order, _, same = _pixel_sort(x, y)
    ts, ps = t_us[order], p[order]
    ok = same[1:] & (ps[1:] == ps[:-1])
    return np.diff(ts).astype(float)[ok]


@dataclass(frozen=True)
class Refractory:
    """What `estimate_refractory` found.

    Attributes:
        refractory_s: the dead time [s] (0 when the intervals start from zero; the upper
            bound when not identified).
        sigma_s: its 1-sigma [s] (statistical, from the edge fit's curvature; when not
            identified, half the bound).
        jitter_s: the edge's blur [s]: the timestamps' jitter times sqrt(2) plus the
            spread of the fastest pixels' time per threshold.
        identified: whether the intervals show an edge (a pile-up against a dead time, or
            intervals reaching down to zero).
        intervals: same-polarity intervals used.
        short_share: share of them within 3 edge widths above the edge (how many pixels
            were driven against the dead time).
        source: which intervals it comes from (`refractory_from_stream`).
    """

    refractory_s: float
    sigma_s: float
    jitter_s: float
    identified: bool
    intervals: int
    short_share: float
    source: str = ""


_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(9)
_GH_W = _GH_W / _GH_W.sum()
"""Gauss-Hermite nodes and weights for the expectation over a unit Gaussian."""


def estimate_refractory(dt_us: np.ndarray, min_intervals: int = 200) -> Refractory:
    """The dead time from same-polarity intervals ``dt_us`` (`same_polarity_intervals`).

    The density of the short intervals (on ``[0, H]``, ``H`` the larger of four times
    their 2nd percentile and their 20th, as a 200-bin histogram: the cost does not grow
    with the stream) is fitted by maximum likelihood as an onset at ``tau``,
    ``(d - tau)_+^k exp(-d / theta)``, blurred by a Gaussian of width ``w`` (timestamp
    jitter on both events of an interval), plus an even floor of stray intervals (0-10 %),
    over a grid of ``tau``, ``k`` (0, 1, 2), ``theta``, ``w`` and the floor.

    - A dead time that pixels were driven against is a pile-up: a step or a linear onset
      (``k <= 1``) at ``tau``, significantly away from 0 (log-likelihood gain over the
      best ``tau = 0`` fit above 8).
    - Intervals reaching down to zero (best ``tau`` within two blur widths of 0): no dead
      time, 0.
    - A gradual onset away from zero is a sensor whose fastest pixels never reached a dead
      time (slow slews: the shortest intervals are the time the steepest pixel needs for
      one threshold): not identified; the 0.5th percentile of the intervals plus two blur
      widths (jitter) is returned as an upper bound.

    1-sigma: the profile likelihood's curvature in ``tau`` and, in quadrature, the blur
    ``w`` (the onset's shape is a model; on synthetic intervals its error was within it).
    """
    d = np.asarray(dt_us, float)
    n = d.size
    if n < min_intervals:
        bound = float(d.min()) * 1e-6 if n else math.inf
        return Refractory(bound, bound / 2, 0.0, False, n, 0.0)
    H = max(4.0 * float(np.percentile(d, 2.0)), float(np.percentile(d, 20.0)), 20.0)
    edges = np.linspace(0.0, H, 201)
    cnt = np.histogram(d, bins=edges)[0].astype(float)
    centre = 0.5 * (edges[1:] + edges[:-1])
    if cnt.sum() < min_intervals // 2:
        bound = float(np.percentile(d, 0.5)) * 1e-6
        return Refractory(bound, bound / 2, 0.0, False, n, 0.0)
    upper = float(centre[np.searchsorted(np.cumsum(cnt), 0.25 * cnt.sum())])
    taus = np.linspace(0.0, upper, 41)
    ks = (0.0, 1.0, 2.0)
    ws = [w for w in (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0) if w <= max(H / 8, 2.0)]
    decay = np.array([np.exp(-centre / (f * H)) for f in (0.25, 0.5, 1.0, math.inf)])
    floors = np.array([0.0, 0.03, 0.1])  # share of intervals spread evenly (strays)
    # Log-likelihood table over (tau, k, w, theta, floor), all taus at once.
    ll = np.full((taus.size, len(ks), len(ws), decay.shape[0], floors.size), -math.inf)
    z0 = centre[None, :, None] - taus[:, None, None]  # (tau, bin, node)
    for iw, w in enumerate(ws):
        z = np.maximum(z0 + w * _GH_X[None, None, :], 0.0)
        for ik, k in enumerate(ks):
            g0 = ((z > 0) if k == 0 else z**k) @ _GH_W  # (tau, bin)
            g = g0[:, None, :] * decay[None, :, :] + 1e-12  # (tau, theta, bin)
            g = g / g.sum(2, keepdims=True)
            for ib, b in enumerate(floors):
                f = (1 - b) * g + b / centre.size
                ll[:, ik, iw, :, ib] = np.sum(cnt * np.log(f), axis=2)
    prof = ll.reshape(taus.size, -1).max(axis=1)
    i_best = int(np.argmax(prof))
    tau, ll_best, ll0 = float(taus[i_best]), float(prof[i_best]), float(prof[0])
    ik, iw, _, _ = (int(v) for v in np.unravel_index(int(np.argmax(ll[i_best])), ll.shape[1:]))
    k_best, w_best = ks[ik], ws[iw]
    h = float(taus[1] - taus[0]) if taus.size > 1 else 1.0
    lo = prof[max(i_best - 1, 0)]
    hi = prof[min(i_best + 1, taus.size - 1)]
    curv = float(hi - 2 * ll_best + lo)
    sigma = math.hypot(max(math.sqrt(-h * h / curv) if curv < 0 else h, 0.5), w_best)
    share = float(cnt[(centre > tau) & (centre <= tau + 3 * w_best + 0.05 * H)].sum() / n)
    if tau <= 2 * w_best or tau <= 2.0:
        return Refractory(0.0, max(sigma, w_best) * 1e-6, w_best * 1e-6, True, n, share)
    if k_best > 1.0 or ll_best - ll0 < 8.0:
        bound = (float(np.percentile(d, 0.5)) + 2 * w_best) * 1e-6
        return Refractory(bound, bound / 2, w_best * 1e-6, False, n, share)
    return Refractory(tau * 1e-6, sigma * 1e-6, w_best * 1e-6, True, n, share)


@dataclass(frozen=True)
class StarPasses:
    """Complete passes of a star over a resting pixel: an ON run, then its OFF run, with the
    pixel quiet for at least the pass's duration before and after (arrays, one per pass).

    Attributes:
        x, y: the pixel.
        t_peak_s: midway between the last ON and the first OFF event (the intensity's peak).
        n_on, n_off: events in the ON and the OFF run.
        steps_on, steps_off: thresholds the runs stand for with a dead time ``tau``: 1 for
            the first event of a run, ``dt / (dt - tau)`` for each later one (``n`` when
            ``tau`` is 0).
        min_dt_s: the shortest interval within either run (inf for runs of one event).
    """

    x: np.ndarray
    y: np.ndarray
    t_peak_s: np.ndarray
    n_on: np.ndarray
    n_off: np.ndarray
    steps_on: np.ndarray
    steps_off: np.ndarray
    min_dt_s: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    def subset(self, keep: np.ndarray) -> StarPasses:
        """The passes ``keep`` (mask or indices)."""
        return StarPasses(
            *(
                getattr(self, f)[keep]
                for f in (
                    "x",
                    "y",
                    "t_peak_s",
                    "n_on",
                    "n_off",
                    "steps_on",
                    "steps_off",
                    "min_dt_s",
                )
            )
        )


def star_passes(
    t_us: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    use: np.ndarray | None = None,
    tau_s: float = 0.0,
) -> StarPasses:
    """The complete passes (`StarPasses`) of a time-sorted stream. Only pixels all of whose
    events in the pass and around it are in ``use`` (noise-filtered events) count: a noise
    event inside a pass resets or splits it."""
    t_us, x, y, p = (np.asarray(a) for a in (t_us, x, y, p))
    n = t_us.size
    empty = np.zeros(0)
    if n < 2:
        return StarPasses(empty, empty, empty, empty, empty, empty, empty, empty)
    use_all = np.ones(n, dtype=bool) if use is None else np.asarray(use, bool)
    order, key, same = _pixel_sort(x, y)
    ts = t_us[order].astype(np.int64)
    ps = p[order]
    us = use_all[order]
    new_run = ~same.copy()
    new_run[1:] |= ps[1:] != ps[:-1]
    starts = np.flatnonzero(new_run)
    ends = np.append(starts[1:], n) - 1
    run_pix = key[starts]
    run_pol = ps[starts]
    length = ends - starts + 1
    # Per run: all events used; the thresholds it stands for; its shortest interval.
    run_id = np.cumsum(new_run) - 1
    bad = np.bincount(run_id, weights=(~us).astype(float), minlength=starts.size) > 0
    dt = np.zeros(n)
    dt[1:] = np.diff(ts) * 1e-6
    inner = ~new_run  # an event whose predecessor is in its run
    tau = float(tau_s)
    gain = np.ones(n)
    if tau > 0:
        gain[inner] = dt[inner] / np.maximum(dt[inner] - tau, 1e-12)
        gain[inner & (dt <= tau)] = np.inf
    steps = np.bincount(run_id, weights=gain, minlength=starts.size)
    min_dt = np.full(starts.size, np.inf)
    np.minimum.at(min_dt, run_id[inner], dt[inner])
    k = np.flatnonzero(
        (run_pix[:-1] == run_pix[1:]) & (run_pol[:-1] == 1) & (run_pol[1:] == 0)
    )  # ON run k, its OFF run k + 1
    t_first = ts[starts[k]]
    t_last = ts[ends[k + 1]]
    dur = np.maximum(t_last - t_first, 1)
    # Quiet before (the pixel at rest) and after (back at rest): no event of the pixel
    # within the pass's duration, and not within it of the stream's ends.
    prev_ok = np.ones(k.size, dtype=bool)
    has_prev = (k > 0) & (run_pix[np.maximum(k - 1, 0)] == run_pix[k])
    prev_ok[has_prev] = t_first[has_prev] - ts[ends[k[has_prev] - 1]] > dur[has_prev]
    prev_ok &= ~has_prev | ~bad[np.maximum(k - 1, 0)]
    nxt = k + 2
    has_next = (nxt < starts.size) & (run_pix[np.minimum(nxt, starts.size - 1)] == run_pix[k])
    next_ok = np.ones(k.size, dtype=bool)
    nn = np.minimum(nxt, starts.size - 1)
    next_ok[has_next] = ts[starts[nn[has_next]]] - t_last[has_next] > dur[has_next]
    inside = (t_first - int(t_us.min()) > dur) & (int(t_us.max()) - t_last > dur)
    ok = prev_ok & next_ok & inside & ~bad[k] & ~bad[k + 1]
    k = k[ok]
    t_peak = 0.5 * (ts[ends[k]] + ts[starts[k + 1]]) * 1e-6
    pix = run_pix[k]
    return StarPasses(
        x=(pix % 65536).astype(float),
        y=(pix // 65536).astype(float),
        t_peak_s=t_peak,
        n_on=length[k].astype(float),
        n_off=length[k + 1].astype(float),
        steps_on=steps[k],
        steps_off=steps[k + 1],
        min_dt_s=np.minimum(min_dt[k], min_dt[k + 1]),
    )


@dataclass(frozen=True)
class Thresholds:
    """What `estimate_thresholds` found.

    Attributes:
        c_on, c_off: the mean ON and OFF thresholds [log intensity].
        sigma_on, sigma_off: their 1-sigma (bootstrap over stars).
        c_mean, sigma_mean: their mean and its 1-sigma (what the tracker's single ``C``
            uses).
        stars, passes: identified stars and passes used.
        mag_range: the magnitudes they span.
        refractory_gain: mean thresholds per event the dead-time correction assigned (1: no
            correction).
    """

    c_on: float
    c_off: float
    sigma_on: float
    sigma_off: float
    c_mean: float
    sigma_mean: float
    stars: int
    passes: int
    mag_range: tuple[float, float]
    refractory_gain: float


def _soft_l1(weight: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """scipy's ``soft_l1`` loss ``rho(z) = 2 (sqrt(1 + z) - 1)`` with its two derivatives,
    each residual's times its ``weight``: the cost of ``weight`` identical residuals."""

    def loss(z: np.ndarray) -> np.ndarray:
        t = 1.0 + z
        return np.vstack([2.0 * (t**0.5 - 1.0), t**-0.5, -0.5 * t**-1.5]) * weight

    return loss


def _fit_c(
    mag: np.ndarray,
    y: np.ndarray,
    a0: float | None = None,
    c_on: float = 0.0,
    weight: np.ndarray | None = None,
) -> tuple[float, float]:
    """Least squares (soft L1) of ``y = log1p(exp(a - 0.921 m)) / C`` for ``(a, C)``; with
    ``a0`` and ``c_on`` given, of ``y = (log1p(exp(a0 - 0.921 m)) - c_on / 2) / C`` for ``C``
    (the OFF run starts from the ON run's top, on average half an ON threshold below the
    peak). ``weight``: how many passes each ``(mag, y)`` row stands for (the passes' counts
    are integers, so a few thousand distinct rows stand for tens of thousands of passes;
    the cost is that of the passes one by one). Returns ``(a, C)``."""
    from scipy.optimize import least_squares

    k = np.ones(mag.size) if weight is None else np.asarray(weight, float)
    if a0 is None:
        # Start: bright stars' slope (over the passes, each row as often as it stands for).
        c0 = max(LN10_04 / max(-np.polyfit(mag, y, 1, w=np.sqrt(k))[0], 1e-3), 0.01)
        reps = np.repeat(np.arange(mag.size), k.astype(np.int64))
        a_start = float(np.median(y[reps] * c0 + LN10_04 * mag[reps]))

        def res(q: np.ndarray) -> np.ndarray:
            return np.log1p(np.exp(q[0] - LN10_04 * mag)) / q[1] - y

        sol = least_squares(
            res,
            [a_start, c0],
            loss=_soft_l1(k),
            f_scale=1.0,
            bounds=([-np.inf, 1e-3], [np.inf, 10.0]),
        )
        return float(sol.x[0]), float(sol.x[1])
    top = np.log1p(np.exp(a0 - LN10_04 * mag)) - 0.5 * c_on

    def res1(q: np.ndarray) -> np.ndarray:
        return top / q[0] - y

    sol = least_squares(
        res1, [max(c_on, 0.01)], loss=_soft_l1(k), f_scale=1.0, bounds=([1e-3], [10.0])
    )
    return float(a0), float(sol.x[0])


def _distinct(star: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct ``(star, y)`` rows of the passes and how many passes each stands for."""
    rows, count = np.unique(np.column_stack([star, y]), axis=0, return_counts=True)
    return rows[:, 0].astype(np.int64), rows[:, 1], count


def estimate_thresholds(
    passes: StarPasses,
    attitude_at: Callable[[np.ndarray], np.ndarray],
    cam_fx: float,
    cam_fy: float,
    cam_cx: float,
    cam_cy: float,
    cat_unit: np.ndarray,
    cat_mag: np.ndarray,
    centre_px: float = 0.5,
    isolation_px: float = 6.0,
    max_gain: float = 1.5,
    min_stars: int = 5,
    min_mag_range: float = 1.5,
    bootstrap: int = 100,
    seed: int = 0,
) -> Thresholds | None:
    """The mean ON and OFF thresholds from the passes of identified stars over pixels their
    image centre crosses (module docstring), or None where too few stars or too narrow a
    range of magnitudes make them unidentifiable.

    Each pass is given to the catalogue star nearest to its pixel's line of sight at the
    pass's peak (``attitude_at``: times -> ``inertial_from_camera``, the tracker's
    attitude), if that star is within ``centre_px`` (the pixel is on the star's track) and
    no other catalogue star is within ``isolation_px``. Passes whose intervals carry a
    dead-time correction above ``max_gain`` thresholds per event are left out (the
    correction depends on the pixel's reset behaviour; short intervals also suffer most
    from timestamp jitter). The ON fit gives the magnitude zero point ``a`` and ``C_on``;
    the OFF fit uses that ``a``. 1-sigma: bootstrap over stars (a star's colour, i.e. its
    catalogue band against the sensor's, is shared by its passes)."""
    from scipy.spatial import cKDTree

    if len(passes) == 0:
        return None
    gain_ok = (
        np.maximum(
            passes.steps_on / np.maximum(passes.n_on, 1),
            passes.steps_off / np.maximum(passes.n_off, 1),
        )
        <= max_gain
    )
    R = attitude_at(passes.t_peak_s)
    b = np.column_stack(
        [(passes.x - cam_cx) / cam_fx, (passes.y - cam_cy) / cam_fy, np.ones(len(passes))]
    )
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    b_in = np.einsum("nij,nj->ni", R, b)
    tree = cKDTree(cat_unit)
    dist, idx = tree.query(b_in, k=2)
    d_px = 2 * np.arcsin(np.clip(dist / 2, 0, 1)) * cam_fx  # chord -> angle -> px
    keep = gain_ok & (d_px[:, 0] <= centre_px) & (d_px[:, 1] >= isolation_px)
    if not keep.any():
        return None
    star = idx[keep, 0]
    y_on = passes.steps_on[keep] + 0.5
    y_off = passes.steps_off[keep] + 0.5
    stars = np.unique(star)
    if stars.size < min_stars or float(np.ptp(cat_mag[stars])) < min_mag_range:
        return None
    # The fits run on the distinct (star, count) rows, each weighted by its passes.
    s_on, yd_on, k_on = _distinct(star, y_on)
    s_off, yd_off, k_off = _distinct(star, y_off)
    a, c_on = _fit_c(cat_mag[s_on], yd_on, weight=k_on)
    _, c_off = _fit_c(cat_mag[s_off], yd_off, a0=a, c_on=c_on, weight=k_off)
    i_on, i_off = np.searchsorted(stars, s_on), np.searchsorted(stars, s_off)
    rng = np.random.default_rng(seed)
    boot = []
    for _ in range(bootstrap):
        pick = rng.integers(0, stars.size, stars.size)
        if np.ptp(cat_mag[stars[pick]]) < 0.5:
            continue
        times = np.bincount(pick, minlength=stars.size)  # each star's passes, this often
        w_on, w_off = k_on * times[i_on], k_off * times[i_off]
        on, off = w_on > 0, w_off > 0
        ab, cb_on = _fit_c(cat_mag[s_on[on]], yd_on[on], weight=w_on[on])
        _, cb_off = _fit_c(cat_mag[s_off[off]], yd_off[off], a0=ab, c_on=cb_on, weight=w_off[off])
        boot.append((cb_on, cb_off, 0.5 * (cb_on + cb_off)))
    sd = np.std(np.array(boot), axis=0) if len(boot) > 2 else np.full(3, math.inf)
    n_ev = float(np.sum(passes.n_on[keep] + passes.n_off[keep]))
    gain = float(np.sum(passes.steps_on[keep] + passes.steps_off[keep]) / max(n_ev, 1.0))
    return Thresholds(
        c_on=c_on,
        c_off=c_off,
        sigma_on=float(sd[0]),
        sigma_off=float(sd[1]),
        c_mean=0.5 * (c_on + c_off),
        sigma_mean=float(sd[2]),
        stars=int(stars.size),
        passes=int(keep.sum()),
        mag_range=(float(cat_mag[stars].min()), float(cat_mag[stars].max())),
        refractory_gain=gain,
    )
