"""A second, deliberately different event-camera model ("dvs") for testing the star tracker on
events it was not written against (issue 18 part 3).

What differs from `satpose.datasets.events` (the ESIM model the tracker was developed on):

- **Pixel reset** (DVS pixel): after an event the pixel is blind for ``refractory_s``; at the
  end of that time its reference is reset to the *current* log intensity (ESIM here: the
  reference moves by exactly ``C`` per crossing and a crossing inside the dead time still
  moves it). A rising pixel therefore fires at levels ``L(t_k + refractory) + C``, not at
  ``L0 + k C``, and whatever the intensity did while blind is lost.
- **Thresholds**: ON and OFF thresholds drawn independently per pixel, ``N(C, sigma_C)``
  with a larger mean and spread than the ESIM presets (0.30 +- 0.05 vs 0.25 +- 0.03).
- **Background activity** is a reset too: a noise event (Poisson, ``ba_rate_hz`` per pixel,
  ``ba_on_fraction`` of them ON, the leak current's bias) resets the pixel's reference to
  the current intensity and starts a dead time, so near a star it shifts the levels of the
  events after it.
- **Hot pixels**: ``hot_fraction`` of the pixels fire Poisson events at a log-normal rate
  around ``hot_rate_hz``, mostly ON, through the same dead time (an event within
  ``refractory_s`` of the pixel's last one is not fired).
- **Timestamp jitter**: Gaussian ``timestamp_jitter_s`` on every event (then re-sorted,
  microsecond ticks).
- **Optics**: a defocused star image, a uniform disk of radius ``defocus_radius_px``
  convolved with a Gaussian of ``blur_sigma_px`` (ESIM presets: a focused Gaussian of
  0.8 px), integrated over each pixel through a table of sub-pixel offsets (1/16 px,
  bilinear between them).
- **Sky and band** (`satpose.datasets.sky.load_gaia`): Gaia DR3 positions with a magnitude
  in a red-weighted band between BP and RP (ESIM presets: Hipparcos Hp).

Not modelled (by either model): the photoreceptor's intensity-dependent bandwidth (latency
of dim pixels), log-domain shot noise, readout bus saturation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.events import Attitude, EventError, Events, _max_rate_px_s, _stars_near_path
from satpose.datasets.sky import StarCatalogue, project_stars

_SUB = 16
"""Sub-pixel offsets per pixel in the PSF table."""


@dataclass(frozen=True, kw_only=True)
class DvsSensor:
    """The second event sensor: DVS pixel, defocused optics, photometry.

    Attributes:
        contrast_threshold: mean ON and OFF log-intensity threshold C.
        threshold_sigma: per-pixel standard deviation of each threshold (drawn separately
            for ON and OFF, fixed per sensor).
        refractory_s: dead time after an event; the reference is reset at its end [s].
        ba_rate_hz: background-activity events per pixel per second (they reset the pixel).
        ba_on_fraction: share of background-activity events that are ON.
        hot_fraction: share of pixels that are hot.
        hot_rate_hz: median event rate of a hot pixel (log-normal, sigma 0.7) [Hz].
        timestamp_jitter_s: Gaussian jitter on each event time [s].
        defocus_radius_px: radius of the defocus disk [px].
        blur_sigma_px: Gaussian blur on top of it [px].
        flux_mag0_e_s: photo-electrons per second from a magnitude-0 star (sensor band).
        background_e_s: per-pixel background [e-/s].
        mag_limit: faintest star simulated (sensor band; 9.0: a star needs about 8.6 to
            lift its brightest pixel by one mean threshold).
        max_step_px: largest star motion between two log-intensity samples [px].
    """

    contrast_threshold: float = 0.30
    threshold_sigma: float = 0.05
    refractory_s: float = 3e-4
    ba_rate_hz: float = 0.2
    ba_on_fraction: float = 0.7
    hot_fraction: float = 2e-4
    hot_rate_hz: float = 100.0
    timestamp_jitter_s: float = 2e-5
    defocus_radius_px: float = 1.5
    blur_sigma_px: float = 0.6
    flux_mag0_e_s: float = 4.0e6
    background_e_s: float = 400.0
    mag_limit: float = 9.0
    max_step_px: float = 0.15

    def __post_init__(self) -> None:
        pos = ("contrast_threshold", "flux_mag0_e_s", "background_e_s", "max_step_px")
        for name in pos:
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise EventError(f"dvs.{name} must be positive")
        nonneg = (
            "threshold_sigma",
            "refractory_s",
            "ba_rate_hz",
            "hot_fraction",
            "hot_rate_hz",
            "timestamp_jitter_s",
            "defocus_radius_px",
            "blur_sigma_px",
        )
        for name in nonneg:
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise EventError(f"dvs.{name} must be >= 0")
        if self.defocus_radius_px == 0 and self.blur_sigma_px == 0:
            raise EventError("dvs: defocus_radius_px or blur_sigma_px must be positive")
        if not (0 <= self.ba_on_fraction <= 1 and self.hot_fraction < 0.01):
            raise EventError("dvs: ba_on_fraction in [0, 1], hot_fraction < 0.01")

    def flux_e_s(self, mag: np.ndarray) -> np.ndarray:
        return self.flux_mag0_e_s * 10.0 ** (-0.4 * np.asarray(mag, dtype=float))

    @property
    def psf_radius_px(self) -> int:
        """Half-width of the pixel patch a star's light is spread over."""
        return max(1, math.ceil(self.defocus_radius_px + 4 * self.blur_sigma_px))


def defocus_psf_table(radius_px: float, sigma_px: float, half: int) -> np.ndarray:
    """Pixel-integrated defocused PSF for sub-pixel offsets: shape ``(S, S, B, B)`` with
    ``S = 17`` offsets ``o = -1/2 .. 1/2`` (step 1/16) per axis and ``B = 2 half + 1`` pixels:
    ``table[iy, ix, r, c]`` is the fraction of the light of a star at ``(o_x, o_y)`` from a
    pixel centre that falls on the pixel ``(c - half, r - half)`` from it (rows = y).

    The star image is a uniform disk (``radius_px``) convolved with a Gaussian
    (``sigma_px``), sampled on a 1/16 px grid (each sample 4x4 supersampled on the disk edge)
    and summed over pixels with a summed-area table. Sums to 1 over the patch (the light
    beyond it, < 1e-4 for ``half >= radius + 4 sigma``, is dropped)."""
    n = (2 * half + 3) * _SUB
    c = (n - 1) / 2
    fine = (np.arange(n) - c) / _SUB
    # Disk with a 4x4 supersampled edge.
    ss = (np.arange(4) - 1.5) / (4 * _SUB)
    disk = np.zeros((n, n))
    for dy in ss:
        for dx in ss:
            disk += (fine[None, :] + dx) ** 2 + (fine[:, None] + dy) ** 2 <= radius_px**2
    if disk.sum() == 0:  # a point (radius 0): one sample
        disk[int(c), int(c)] = 1.0
    if sigma_px > 0:
        disk = cv2.GaussianBlur(disk, (0, 0), sigma_px * _SUB, borderType=cv2.BORDER_CONSTANT)
    disk /= disk.sum()
    sat = np.zeros((n + 1, n + 1))
    sat[1:, 1:] = disk.cumsum(0).cumsum(1)
    B = 2 * half + 1
    table = np.zeros((_SUB + 1, _SUB + 1, B, B))
    pix = np.arange(-half, half + 1)
    for iy in range(_SUB + 1):
        for ix in range(_SUB + 1):
            # A star at offset o from the pixel centre: pixel k from it spans
            # [k - o - 1/2, k - o + 1/2] in star-centred coordinates.
            ox, oy = ix / _SUB - 0.5, iy / _SUB - 0.5
            x0 = np.rint((pix - ox - 0.5) * _SUB + c + 0.5).astype(int)
            y0 = np.rint((pix - oy - 0.5) * _SUB + c + 0.5).astype(int)
            x0, y0 = np.clip(x0, 0, n), np.clip(y0, 0, n)
            x1, y1 = np.clip(x0 + _SUB, 0, n), np.clip(y0 + _SUB, 0, n)
            table[iy, ix] = (
                sat[y1[:, None], x1[None, :]]
                - sat[y0[:, None], x1[None, :]]
                - sat[y1[:, None], x0[None, :]]
                + sat[y0[:, None], x0[None, :]]
            )
    return table


def table_patches(
    px: np.ndarray, flux: np.ndarray, table: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel values of stars at ``px`` (M, 2) with ``flux`` (M,) through a `defocus_psf_table`
    (bilinear between its sub-pixel offsets): ``(flat_index, value)`` inside the image."""
    B = table.shape[-1]
    half = B // 2
    cx = np.rint(px[:, 0]).astype(np.int64)
    cy = np.rint(px[:, 1]).astype(np.int64)
    fx = (px[:, 0] - cx + 0.5) * _SUB
    fy = (px[:, 1] - cy + 0.5) * _SUB
    ix = np.clip(np.floor(fx).astype(np.int64), 0, _SUB - 1)
    iy = np.clip(np.floor(fy).astype(np.int64), 0, _SUB - 1)
    ax = (fx - ix)[:, None, None]
    ay = (fy - iy)[:, None, None]
    val = (
        (1 - ay) * ((1 - ax) * table[iy, ix] + ax * table[iy, ix + 1])
        + ay * ((1 - ax) * table[iy + 1, ix] + ax * table[iy + 1, ix + 1])
    ) * flux[:, None, None]
    off = np.arange(-half, half + 1)
    X = np.broadcast_to((cx[:, None] + off[None])[:, None, :], val.shape)
    Y = np.broadcast_to((cy[:, None] + off[None])[:, :, None], val.shape)
    ok = (X >= 0) & (X < width) & (Y >= 0) & (Y < height)
    return Y[ok] * width + X[ok], val[ok]


def _dead_time_thinning(pix: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    """Mask of the events ``(pix, t)`` a pixel fires with a dead time ``tau`` after each of
    its fired events (drawn without one)."""
    keep = np.ones(t.size, dtype=bool)
    if tau <= 0 or t.size < 2:
        return keep
    order = np.lexsort((t, pix))
    ps, ts = pix[order].tolist(), t[order].tolist()
    last_pix, last_t = -1, -math.inf
    for k, (q, tk) in enumerate(zip(ps, ts, strict=True)):
        if q == last_pix and tk - last_t < tau:
            keep[order[k]] = False
        else:
            last_pix, last_t = q, tk
    return keep


def simulate_dvs_events(
    cat: StarCatalogue,
    attitude: Attitude,
    cam: PinholeCamera,
    sensor: DvsSensor,
    t0_s: float,
    t1_s: float,
    rng: np.random.Generator,
) -> Events:
    """Events of the star field seen along ``attitude`` during ``[t0_s, t1_s)`` (DVS model,
    module docstring). ``cat`` magnitudes are in the sensor band."""
    if not (t1_s > t0_s):
        raise EventError(f"empty time span [{t0_s}, {t1_s})")
    W, H = cam.width, cam.height
    npix = W * H
    cat = _stars_near_path(cat.brighter_than(sensor.mag_limit), attitude, cam, t0_s, t1_s)
    flux = sensor.flux_e_s(cat.mag)
    half = sensor.psf_radius_px
    table = defocus_psf_table(sensor.defocus_radius_px, sensor.blur_sigma_px, half)
    speed = _max_rate_px_s(attitude, cam, t0_s, t1_s)
    n_steps = max(1, math.ceil(speed * (t1_s - t0_s) / sensor.max_step_px))
    ts = np.linspace(t0_s, t1_s, n_steps + 1)
    Rs = attitude(ts)
    log_bg = math.log(sensor.background_e_s)
    c_on = np.maximum(
        sensor.contrast_threshold + sensor.threshold_sigma * rng.standard_normal(npix),
        0.3 * sensor.contrast_threshold,
    )
    c_off = np.maximum(
        sensor.contrast_threshold + sensor.threshold_sigma * rng.standard_normal(npix),
        0.3 * sensor.contrast_threshold,
    )
    tau = sensor.refractory_s

    # Background activity: drawn up front (it resets pixels it lands on near a star).
    n_ba = rng.poisson(sensor.ba_rate_hz * npix * (t1_s - t0_s))
    ba_t = np.sort(rng.uniform(t0_s, t1_s, n_ba))
    ba_i = rng.integers(0, npix, n_ba)
    ba_p = (rng.random(n_ba) < sensor.ba_on_fraction).astype(np.uint8)

    def log_at(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, px = project_stars(cat, R, cam, half + 1.0)
        idx, val = table_patches(px, flux[rows], table, W, H)
        u, inv = np.unique(idx, return_inverse=True)
        return u, np.log(np.bincount(inv, weights=val) + sensor.background_e_s)

    L_now = np.full(npix, log_bg)
    u, lv = log_at(Rs[0])
    L_now[u] = lv
    L_ref = L_now.copy()
    blind_until = np.full(npix, -np.inf)
    touched_prev = u
    out_t: list[np.ndarray] = []
    out_i: list[np.ndarray] = []
    out_p: list[np.ndarray] = []
    ba_k = np.searchsorted(ba_t, ts)
    for k in range(1, ts.size):
        ta, tb = ts[k - 1], ts[k]
        u, lv = log_at(Rs[k])
        pix = np.union1d(u, touched_prev)
        La = L_now[pix]
        Lb = np.full(pix.size, log_bg)
        Lb[np.searchsorted(pix, u)] = lv
        slope = (Lb - La) / (tb - ta)
        start = np.full(pix.size, ta)
        ref = L_ref[pix]
        blind = blind_until[pix]
        # Events one at a time per pixel: each starts a dead time, at whose end (if inside
        # this step) the reference is reset to the intensity then.
        while True:
            reset = (blind > start) & (blind <= tb)
            if reset.any():
                start[reset] = blind[reset]
                ref[reset] = La[reset] + slope[reset] * (blind[reset] - ta)
                blind[reset] = -np.inf
            live = blind <= start
            Ls = La + slope * (start - ta)
            up = live & (slope > 0) & (Lb > ref + c_on[pix])
            dn = live & (slope < 0) & (Lb < ref - c_off[pix])
            fire = up | dn
            if not fire.any():
                break
            level = np.where(up, ref + c_on[pix], ref - c_off[pix])
            te = start + (level - Ls) / np.where(slope == 0, 1.0, slope)
            te = np.clip(te, start, tb)
            f = np.flatnonzero(fire)
            out_t.append(te[f])
            out_i.append(pix[f])
            out_p.append(up[f].astype(np.uint8))
            ref[f] = level[f]
            blind[f] = te[f] + tau
            start[f] = te[f]
        # Background-activity events in this step that land on a lit pixel reset it.
        j0, j1 = ba_k[k - 1], ba_k[k]
        if j1 > j0:
            hit = np.searchsorted(pix, ba_i[j0:j1])
            hit = np.clip(hit, 0, pix.size - 1)
            on_pix = pix[hit] == ba_i[j0:j1]
            h = hit[on_pix]
            if h.size:
                t_ba = ba_t[j0:j1][on_pix]
                ref[h] = La[h] + slope[h] * (t_ba - ta)
                blind[h] = np.maximum(blind[h], t_ba + tau)
        L_ref[pix] = ref
        blind_until[pix] = blind
        L_now[pix] = Lb
        touched_prev = u
    out_t.append(ba_t)
    out_i.append(ba_i)
    out_p.append(ba_p)
    n_hot = round(sensor.hot_fraction * npix)
    if n_hot and sensor.hot_rate_hz > 0:
        hot = rng.choice(npix, n_hot, replace=False)
        rate = sensor.hot_rate_hz * np.exp(0.7 * rng.standard_normal(n_hot))
        counts = rng.poisson(rate * (t1_s - t0_s))
        t_hot = rng.uniform(t0_s, t1_s, int(counts.sum()))
        i_hot = np.repeat(hot, counts)
        p_hot = (rng.random(int(counts.sum())) < 0.85).astype(np.uint8)
        # The same pixel circuit: an event within the dead time of the pixel's last one is
        # not fired (a non-paralysable dead time: intervals tau + exponential).
        alive = _dead_time_thinning(i_hot, t_hot, tau)
        out_t.append(t_hot[alive])
        out_i.append(i_hot[alive])
        out_p.append(p_hot[alive])
    t = np.concatenate(out_t)
    i = np.concatenate(out_i)
    p = np.concatenate(out_p)
    t = t + sensor.timestamp_jitter_s * rng.standard_normal(t.size)
    t_us = np.floor(np.clip(t, t0_s, np.nextafter(t1_s, t0_s)) * 1e6).astype(np.int64)
    order = np.argsort(t_us, kind="stable")
    return Events(
        t_us=t_us[order],
        x=(i[order] % W).astype(np.uint16),
        y=(i[order] // W).astype(np.uint16),
        p=p[order],
    )
