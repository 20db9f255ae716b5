"""What the event tracker learns about a sensor from its own stream (issue 18 part 3).

- `hot_pixels`: pixels that fire far more than every neighbour (a star lights several
  neighbouring pixels alike; a hot pixel is alone).
- `correlated_events`: the background-activity filter (Delbruck 2008): an event is kept when
  one of its 8 neighbours fired at about the same time (same or adjacent ``window_s`` bin).
  Noise is uncorrelated in space;
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
    events: Events,
    width: int,
    height: int,
    ratio: float = 4.0,
    min_events: int = 20,
    flat: np.ndarray | None = None,
) -> np.ndarray:
    """Flat indices ``y * width + x`` of pixels with at least ``min_events`` events and more
    than ``ratio`` times the events of each of their 8 neighbours. ``flat``: the events'
    flat indices if the caller has them (a stream-long array less)."""
    if len(events) == 0:
        return np.zeros(0, dtype=np.int64)
    if flat is None:
        flat = events.y.astype(np.int64) * width + events.x.astype(np.int64)
    cnt = np.bincount(flat, minlength=width * height).reshape(height, width)
    pad = np.pad(cnt, 1)
    nmax = np.zeros_like(cnt)
    for dx, dy in _NEIGHBOURS:
        nmax = np.maximum(nmax, pad[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width])
    hot = (cnt >= min_events) & (cnt > ratio * nmax)
    return np.flatnonzero(hot.ravel())


def correlated_events(events: Events, width: int, height: int, window_s: float) -> np.ndarray:
    """Mask of the events with an event at one of the 8 neighbouring pixels in the same or an
    adjacent time bin of ``window_s`` (so within ``window_s`` always, within ``2 window_s``
    at most). Linear in the events plus one 3x3 box sum of the sensor per bin (an exact
    per-event search cost 8 binary searches of the whole stream: 8 ms per output at
    6 deg/s)."""
    flat = events.y.astype(np.int32) * width + events.x
    return _correlated(flat, events.t_us, width, height, window_s)


def _correlated(
    flat: np.ndarray, t_us: np.ndarray, width: int, height: int, window_s: float
) -> np.ndarray:
    import cv2

    n = flat.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    w_us = max(1, round(window_s * 1e6))
    edges = np.searchsorted(t_us, t_us[0] + w_us * np.arange(int((t_us[-1] - t_us[0]) // w_us) + 2))
    n_bins = edges.size - 1
    npix = width * height

    def neighbours(k: int) -> np.ndarray:
        """Events of the 8 neighbours of each pixel in bin k (flat, float32)."""
        if k < 0 or k >= n_bins or edges[k] == edges[k + 1]:
            return np.zeros(npix, dtype=np.float32)
        cnt = np.bincount(flat[edges[k] : edges[k + 1]], minlength=npix).astype(np.float32)
        img = cnt.reshape(height, width)
        box = cv2.boxFilter(img, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        return (box - img).ravel()

    keep = np.zeros(n, dtype=bool)
    prev, cur = np.zeros(npix, dtype=np.float32), neighbours(0)
    for k in range(n_bins):
        nxt = neighbours(k + 1)
        i0, i1 = edges[k], edges[k + 1]
        if i1 > i0:
            f = flat[i0:i1]
            keep[i0:i1] = (prev[f] + cur[f] + nxt[f]) > 0.5
        prev, cur = cur, nxt
    return keep


@dataclass(frozen=True, kw_only=True)
class StreamStats:
    """What `stream_noise` found: hot pixels (flat indices), their events, the share of the
    events kept."""

    hot_pixels: np.ndarray
    hot_events: int
    kept_fraction: float


def stream_noise(
    events: Events,
    width: int,
    height: int,
    window_s: float,
    hot_ratio: float,
    min_share: float = 0.0,
    probe_s: float = 0.2,
) -> tuple[np.ndarray, np.ndarray, StreamStats]:
    """Masks of the events that are neither from a `hot_pixels` pixel (``hot_ratio`` 0: none
    is) nor uncorrelated (`correlated_events`; ``window_s`` 0: not filtered), and of those
    not from a hot pixel; and what was found. The correlation filter runs on the whole
    stream only if it drops at least ``min_share`` of the first ``probe_s`` (a fast slew's
    stream is 99 % star events: filtering it cost 0.7 ms per output at 16 deg/s)."""
    n = len(events)
    keep = np.ones(n, dtype=bool)
    hot = np.zeros(0, dtype=np.int64)
    n_hot = 0
    flat = events.y.astype(np.int32) * width + events.x
    if n and hot_ratio > 0:
        hot = hot_pixels(events, width, height, hot_ratio, flat=flat)
        if hot.size:
            is_hot = np.zeros(width * height, dtype=bool)
            is_hot[hot] = True
            keep &= ~is_hot[flat]
            n_hot = int(n - keep.sum())
    not_hot = keep.copy()
    if n and window_s > 0 and keep.any() and min_share > 0:
        i1 = int(np.searchsorted(events.t_us, events.t_us[0] + round(probe_s * 1e6)))
        head = keep[:i1]
        probe = _correlated(flat[:i1][head], events.t_us[:i1][head], width, height, window_s)
        if probe.size == 0 or 1.0 - float(probe.mean()) < min_share:
            window_s = 0.0  # too little noise to be worth filtering
    if n and window_s > 0 and keep.any():
        # On the stream without the hot pixels: their events would vouch for a neighbour's.
        if n_hot:
            keep[keep] = _correlated(flat[keep], events.t_us[keep], width, height, window_s)
        else:
            keep = _correlated(flat, events.t_us, width, height, window_s)
    frac = float(keep.mean()) if n else 1.0
    return keep, not_hot, StreamStats(hot_pixels=hot, hot_events=n_hot, kept_fraction=frac)
