"""Star images and events of one simulated sensor: flux, PSF, frames with smear, ESIM events.

Photometry: a star of Hipparcos magnitude ``m`` gives ``flux_mag0_e_s * 10**(-0.4 m)``
photo-electrons per second, spread by a Gaussian PSF integrated over each pixel; every pixel
also collects ``background_e_s`` (dark current, zodiacal light, stray light).

Events (ESIM, Rebecq et al., CoRL 2018): each pixel keeps the log intensity ``L_ref`` at its
last event; whenever the current log intensity moves by the pixel's contrast threshold ``C``
from it, the pixel fires an event (polarity ON for an increase) and ``L_ref`` moves by ``C``.
The log intensity is sampled at steps short enough that a star moves at most ``max_step_px``,
and event times are linearly interpolated between samples. Per-pixel thresholds are drawn once
(``N(C, sigma_C)``, the fixed-pattern mismatch); an event within ``refractory_s`` of the
pixel's previous one is lost (its level crossing still moves ``L_ref``); a level must be
passed, not just reached (a pixel whose star has gone returns exactly to its starting level
and does not fire the last OFF event there); background activity
adds Poisson noise events of random polarity at ``noise_rate_hz`` per pixel. Only pixels near a
star change, so only those are evaluated.

Frames: the same optics and background, integrated over ``exposure_s`` along the trajectory
(motion smear), with Poisson shot noise, Gaussian read noise, gain and 12-bit quantisation.

Event arrays follow DSEC: ``t`` in microseconds (int64), ``x``, ``y`` (uint16), ``p`` (uint8,
1 = ON, 0 = OFF).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError
from satpose.datasets.sky import StarCatalogue, project_stars

TIE_LOG = 1e-9
"""Log-intensity margin by which a threshold level must be passed to fire (tie breaking)."""


class EventError(SatposeError):
    """Invalid event data or sensor parameters."""


@dataclass(frozen=True, kw_only=True)
class Photometry:
    """Optics and photometry shared by the event and the frame sensor.

    Attributes:
        psf_sigma_px: Gaussian PSF standard deviation [px].
        flux_mag0_e_s: photo-electrons per second from a magnitude-0 star.
        background_e_s: per-pixel background (dark current + sky) [e-/s].
        mag_limit: faintest star simulated (Hp).
    """

    psf_sigma_px: float = 0.8
    flux_mag0_e_s: float = 2.0e6
    background_e_s: float = 300.0
    mag_limit: float = 8.0

    def __post_init__(self) -> None:
        for name in ("psf_sigma_px", "flux_mag0_e_s", "background_e_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise EventError(f"photometry.{name} must be positive, got {v}")

    def flux_e_s(self, mag: np.ndarray) -> np.ndarray:
        """Total star signal [e-/s] for magnitudes ``mag``."""
        return self.flux_mag0_e_s * 10.0 ** (-0.4 * np.asarray(mag, dtype=float))


@dataclass(frozen=True, kw_only=True)
class EventSensor:
    """The event pixel (ESIM model).

    Attributes:
        contrast_threshold: mean log-intensity threshold C (ON and OFF).
        threshold_sigma: per-pixel standard deviation of C (mismatch), fixed per sensor.
        refractory_s: dead time after an event [s].
        noise_rate_hz: background-activity noise events per pixel per second.
        max_step_px: largest star motion between two log-intensity samples [px].
    """

    contrast_threshold: float = 0.25
    threshold_sigma: float = 0.03
    refractory_s: float = 1e-4
    noise_rate_hz: float = 0.05
    max_step_px: float = 0.1

    def __post_init__(self) -> None:
        if not (self.contrast_threshold > 0 and self.threshold_sigma >= 0):
            raise EventError("contrast_threshold must be > 0 and threshold_sigma >= 0")
        if not (self.refractory_s >= 0 and self.noise_rate_hz >= 0 and self.max_step_px > 0):
            raise EventError("refractory_s, noise_rate_hz must be >= 0, max_step_px > 0")


@dataclass(frozen=True, kw_only=True)
class FrameSensor:
    """The conventional sensor (same pixels and optics).

    Attributes:
        exposure_s: integration time [s].
        rate_hz: frame rate [Hz].
        read_noise_e: read noise [e- RMS].
        gain_e_per_dn: electrons per digital number.
        bits: ADC resolution.
    """

    exposure_s: float = 0.1
    rate_hz: float = 10.0
    read_noise_e: float = 10.0
    gain_e_per_dn: float = 2.0
    bits: int = 12

    def __post_init__(self) -> None:
        if not (0 < self.exposure_s <= 1.0 / self.rate_hz):
            raise EventError("frame exposure_s must be in (0, 1/rate_hz]")


@dataclass(frozen=True, kw_only=True)
class Events:
    """An event stream (DSEC conventions), sorted by time.

    Attributes:
        t_us: timestamps [microseconds], int64, non-decreasing.
        x, y: pixel coordinates, uint16.
        p: polarity, uint8 (1 = ON, 0 = OFF).
    """

    t_us: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        n = np.size(self.t_us)
        if not all(np.size(a) == n for a in (self.x, self.y, self.p)):
            raise EventError("events: t, x, y, p must have the same length")
        if n and np.any(np.diff(self.t_us) < 0):
            raise EventError("events: t must be non-decreasing")

    def __len__(self) -> int:
        return int(np.size(self.t_us))

    @property
    def t_s(self) -> np.ndarray:
        return self.t_us * 1e-6

    def slice_time(self, t0_s: float, t1_s: float) -> Events:
        """Events with ``t0 <= t < t1`` (seconds)."""
        i0, i1 = np.searchsorted(self.t_us, [round(t0_s * 1e6), round(t1_s * 1e6)])
        return Events(t_us=self.t_us[i0:i1], x=self.x[i0:i1], y=self.y[i0:i1], p=self.p[i0:i1])


def star_patches(
    px: np.ndarray, flux: np.ndarray, sigma_px: float, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-integrated Gaussian PSFs of stars at pixels ``px`` (M, 2) with total ``flux`` (M,).

    Returns ``(flat_index, value)`` of every pixel within ``4 sigma`` of a star (repeated
    indices where stars overlap), inside the image only.
    """
    r = max(1, math.ceil(4 * sigma_px))
    off = np.arange(-r, r + 1)
    cx = np.rint(px[:, 0]).astype(np.int64)
    cy = np.rint(px[:, 1]).astype(np.int64)
    xs = cx[:, None] + off[None]  # (M, B)
    ys = cy[:, None] + off[None]
    s = sigma_px
    wx = ndtr((xs + 0.5 - px[:, :1]) / s) - ndtr((xs - 0.5 - px[:, :1]) / s)
    wy = ndtr((ys + 0.5 - px[:, 1:2]) / s) - ndtr((ys - 0.5 - px[:, 1:2]) / s)
    val = flux[:, None, None] * wy[:, :, None] * wx[:, None, :]  # (M, B, B) rows = y
    X = np.broadcast_to(xs[:, None, :], val.shape)
    Y = np.broadcast_to(ys[:, :, None], val.shape)
    ok = (X >= 0) & (X < width) & (Y >= 0) & (Y < height)
    return (Y[ok] * width + X[ok]), val[ok]


Attitude = Callable[[np.ndarray], np.ndarray]
"""``inertial_from_camera`` at times (N,) -> (N, 3, 3)."""


def _stars_near_path(
    cat: StarCatalogue, attitude: Attitude, cam: PinholeCamera, t0: float, t1: float
) -> StarCatalogue:
    """Catalogue rows that can enter the image during [t0, t1] (cone around the boresights)."""
    ts = np.linspace(t0, t1, max(2, math.ceil((t1 - t0) * 20) + 1))
    bores = attitude(ts)[:, :, 2]  # camera z in the inertial frame
    half_diag = math.atan(math.hypot(cam.width, cam.height) / (2 * min(cam.fx, cam.fy)))
    step = float(np.max(np.arccos(np.clip(np.sum(bores[1:] * bores[:-1], 1), -1, 1)), initial=0))
    cos_r = math.cos(half_diag + step + math.radians(1.0))
    keep = np.max(cat.unit @ bores.T, axis=1) > cos_r
    return StarCatalogue(
        hip=cat.hip[keep], unit=cat.unit[keep], mag=cat.mag[keep], epoch_yr=cat.epoch_yr
    )


def _max_rate_px_s(attitude: Attitude, cam: PinholeCamera, t0: float, t1: float) -> float:
    ts = np.linspace(t0, t1, max(3, math.ceil((t1 - t0) * 2000) + 1))
    R = attitude(ts)
    d = np.einsum("nji,njk->nik", R[:-1], R[1:])
    ang = np.arccos(np.clip((np.trace(d, axis1=1, axis2=2) - 1) / 2, -1, 1))
    # Worst case at the image corner: pixel speed <= f (1 + r^2/f^2) * omega.
    corner = (cam.width**2 + cam.height**2) / (4 * cam.fx**2)
    return float(np.max(ang) / (ts[1] - ts[0]) * cam.fx * (1 + corner))


def flux_image(
    cat: StarCatalogue,
    R: np.ndarray,
    cam: PinholeCamera,
    phot: Photometry,
) -> np.ndarray:
    """Noise-free signal rate image [e-/s], shape (H, W), background included."""
    rows, px = project_stars(cat, R, cam, margin_px=5 * phot.psf_sigma_px)
    idx, val = star_patches(
        px, phot.flux_e_s(cat.mag[rows]), phot.psf_sigma_px, cam.width, cam.height
    )
    img = np.bincount(idx, weights=val, minlength=cam.width * cam.height)
    return (img + phot.background_e_s).reshape(cam.height, cam.width)


def simulate_events(
    cat: StarCatalogue,
    attitude: Attitude,
    cam: PinholeCamera,
    phot: Photometry,
    sensor: EventSensor,
    t0_s: float,
    t1_s: float,
    rng: np.random.Generator,
) -> Events:
    """Events of the star field seen along ``attitude`` during ``[t0_s, t1_s)``.

    Args:
        cat: catalogue (stars fainter than ``phot.mag_limit`` are ignored).
        attitude: ``inertial_from_camera`` at times.
        cam, phot, sensor: the sensor.
        rng: draws thresholds, noise events.
    """
    if not (t1_s > t0_s):
        raise EventError(f"empty time span [{t0_s}, {t1_s})")
    W, H = cam.width, cam.height
    cat = _stars_near_path(cat.brighter_than(phot.mag_limit), attitude, cam, t0_s, t1_s)
    flux = phot.flux_e_s(cat.mag)
    speed = _max_rate_px_s(attitude, cam, t0_s, t1_s)
    n_steps = max(1, math.ceil(speed * (t1_s - t0_s) / sensor.max_step_px))
    ts = np.linspace(t0_s, t1_s, n_steps + 1)
    Rs = attitude(ts)
    log_bg = math.log(phot.background_e_s)
    thr = np.maximum(
        sensor.contrast_threshold + sensor.threshold_sigma * rng.standard_normal(2 * H * W),
        0.2 * sensor.contrast_threshold,
    )
    c_on, c_off = thr[: H * W], thr[H * W :]
    margin = 5 * phot.psf_sigma_px

    def log_at(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, px = project_stars(cat, R, cam, margin)
        idx, val = star_patches(px, flux[rows], phot.psf_sigma_px, W, H)
        u, inv = np.unique(idx, return_inverse=True)
        tot = np.bincount(inv, weights=val) + phot.background_e_s
        return u, np.log(tot)

    # Only pixels a star touches ever leave the background level: sparse state.
    L_now = np.full(H * W, log_bg)
    u, lv = log_at(Rs[0])
    L_now[u] = lv
    L_ref = L_now.copy()
    last_t = np.full(H * W, -np.inf)
    touched_prev = u
    out_t: list[np.ndarray] = []
    out_i: list[np.ndarray] = []
    out_p: list[np.ndarray] = []
    for k in range(1, ts.size):
        u, lv = log_at(Rs[k])
        pix = np.union1d(u, touched_prev)
        L_new_full = np.full(pix.size, log_bg)
        L_new_full[np.searchsorted(pix, u)] = lv
        L_old = L_now[pix]
        d = L_new_full - L_ref[pix]
        con, coff = c_on[pix], c_off[pix]
        # A level is crossed only when passed by more than TIE_LOG: a pixel whose star has left
        # returns exactly to its starting log intensity, and floating-point ties must not
        # decide whether that fires (a real pixel's intensity never returns exactly).
        n_on = np.floor(np.maximum(d - TIE_LOG, 0) / con).astype(np.int64)
        n_off = np.floor(np.maximum(-d - TIE_LOG, 0) / coff).astype(np.int64)
        for pol, n, c, sign in ((1, n_on, con, 1.0), (0, n_off, coff, -1.0)):
            sel = np.flatnonzero(n > 0)
            if sel.size == 0:
                continue
            slope = L_new_full[sel] - L_old[sel]
            slope = np.where(slope == 0, 1e-12, slope)
            l_old, l_ref, c_sel, n_sel = L_old[sel], L_ref[pix[sel]], c[sel], n[sel]
            for j in range(1, int(n_sel.max()) + 1):
                m = n_sel >= j
                level = l_ref[m] + sign * j * c_sel[m]
                frac = np.clip((level - l_old[m]) / slope[m], 0.0, 1.0)
                te = ts[k - 1] + frac * (ts[k] - ts[k - 1])
                p_idx = pix[sel[m]]
                ok = te - last_t[p_idx] >= sensor.refractory_s
                last_t[p_idx[ok]] = te[ok]
                out_t.append(te[ok])
                out_i.append(p_idx[ok])
                out_p.append(np.full(int(ok.sum()), pol, dtype=np.uint8))
            L_ref[pix[sel]] = l_ref + sign * n_sel * c_sel
        L_now[pix] = L_new_full
        touched_prev = u
    n_noise = rng.poisson(sensor.noise_rate_hz * W * H * (t1_s - t0_s))
    out_t.append(rng.uniform(t0_s, t1_s, n_noise))
    out_i.append(rng.integers(0, W * H, n_noise))
    out_p.append(rng.integers(0, 2, n_noise).astype(np.uint8))
    t = np.concatenate(out_t)
    i = np.concatenate(out_i)
    p = np.concatenate(out_p)
    t_us = np.floor(t * 1e6).astype(np.int64)
    order = np.argsort(t_us, kind="stable")
    return Events(
        t_us=t_us[order],
        x=(i[order] % W).astype(np.uint16),
        y=(i[order] // W).astype(np.uint16),
        p=p[order],
    )


def render_frame(
    cat: StarCatalogue,
    attitude: Attitude,
    cam: PinholeCamera,
    phot: Photometry,
    sensor: FrameSensor,
    t_start_s: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """One exposure starting at ``t_start_s``: uint16 digital numbers, shape (H, W).

    The signal is integrated along the attitude during the exposure (smear), sampled so that a
    star moves at most 0.25 px between samples.
    """
    t1 = t_start_s + sensor.exposure_s
    sub = _stars_near_path(cat.brighter_than(phot.mag_limit), attitude, cam, t_start_s, t1)
    speed = _max_rate_px_s(attitude, cam, t_start_s, t1)
    n = max(4, math.ceil(speed * sensor.exposure_s / 0.25))
    ts = t_start_s + (np.arange(n) + 0.5) * sensor.exposure_s / n
    acc = np.zeros((cam.height, cam.width))
    for R in attitude(ts):
        acc += flux_image(sub, R, cam, phot)
    electrons = acc * (sensor.exposure_s / n)
    noisy = rng.poisson(electrons) + sensor.read_noise_e * rng.standard_normal(electrons.shape)
    dn = np.clip(np.rint(noisy / sensor.gain_e_per_dn), 0, 2**sensor.bits - 1)
    return dn.astype(np.uint16)
