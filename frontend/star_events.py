"""What the event tracker learns about a sensor from its own stream (issue 18 part 3).

- `hot_pixels`: pixels that fire far more than every neighbour (a star lights several
  neighbouring pixels alike; a hot pixel is alone).
- `correlated_events`: the background-activity filter (Delbruck 2008): an event is kept when
  one of its 8 neighbours fired within ``window_s`` of it. Noise is uncorrelated in space;
  a star's light moves over several pixels together.
- The star image's size is measured by the tracker itself (`StarTracker.spot_rms_px`).

numpy only; all functions take the whole time-sorted stream (the tracker's whole-stream step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from satpose.datasets.events import Events

_NEIGHBOURS = [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dx, dy) != (0, 0)]


def hot_pixels(
    events: Events, width: int, height: int, ratio: float = 4.0, min_events: int = 20
) -> np.ndarray:
    """Flat indices ``y * width + x`` of pixels with at least ``min_events`` events and more
    than ``ratio`` times the events of each of their 8 neighbours."""
    if len(events) == 0:
        return np.zeros(0, dtype=np.int64)
    flat = events.y.astype(np.int64) * width + events.x.astype(np.int64)
    cnt = np.bincount(flat, minlength=width * height).reshape(height, width)
    pad = np.pad(cnt, 1)
    nmax = np.zeros_like(cnt)
    for dx, dy in _NEIGHBOURS:
        nmax = np.maximum(nmax, pad[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width])
    hot = (cnt >= min_events) & (cnt > ratio * nmax)
    return np.flatnonzero(hot.ravel())


def correlated_events(events: Events, width: int, height: int, window_s: float) -> np.ndarray:
    """Mask of the events with an event at one of the 8 neighbouring pixels within
    ``window_s`` (before or after). Costs 8 binary searches over the stream."""
    n = len(events)
    if n == 0:
        return np.zeros(0, dtype=bool)
    x = events.x.astype(np.int64)
    y = events.y.astype(np.int64)
    t = events.t_us - events.t_us[0]
    span = int(t[-1]) + 1
    key = (y * width + x) * span + t
    skey = np.sort(key)
    w_us = max(1, round(window_s * 1e6))
    keep = np.zeros(n, dtype=bool)
    for dx, dy in _NEIGHBOURS:
        nx, ny = x + dx, y + dy
        inside = (nx >= 0) & (nx < width) & (ny >= 0) & (ny < height)
        base = (ny * width + nx) * span
        # First event of the neighbour at or after t - w; it must be before t + w.
        i = np.searchsorted(skey, base + np.maximum(t - w_us, 0))
        i = np.minimum(i, n - 1)
        hit = inside & (skey[i] >= base) & (skey[i] <= base + np.minimum(t + w_us, span - 1))
        keep |= hit
    return keep


@dataclass(frozen=True, kw_only=True)
class StreamStats:
    """What `stream_noise` found: hot pixels, events kept by the correlation filter."""

    hot_pixels: np.ndarray
    hot_events: int
    kept_fraction: float


def stream_noise(
    events: Events, width: int, height: int, window_s: float, hot_ratio: float
) -> tuple[np.ndarray, StreamStats]:
    """Mask of the events that are neither from a `hot_pixels` pixel nor uncorrelated
    (`correlated_events`; ``window_s`` 0: not filtered), and what was found."""
    n = len(events)
    keep = np.ones(n, dtype=bool)
    hot = np.zeros(0, dtype=np.int64)
    n_hot = 0
    if n and hot_ratio > 0:
        hot = hot_pixels(events, width, height, hot_ratio)
        if hot.size:
            flat = events.y.astype(np.int64) * width + events.x.astype(np.int64)
            keep &= ~np.isin(flat, hot)
            n_hot = int(n - keep.sum())
    if n and window_s > 0 and keep.any():
        # On the stream without the hot pixels: their events would vouch for a neighbour's.
        idx = np.flatnonzero(keep)
        sub = Events(t_us=events.t_us[idx], x=events.x[idx], y=events.y[idx], p=events.p[idx])
        keep[idx] = correlated_events(sub, width, height, window_s)
    frac = float(keep.mean()) if n else 1.0
    return keep, StreamStats(hot_pixels=hot, hot_events=n_hot, kept_fraction=frac)
