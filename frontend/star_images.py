"""Lost in space on real star images (issue 18): extraction, identification, refinement, check.

A single image of the sky, from an unknown camera whose horizontal field of view is known
within a range, to ``inertial_from_camera`` with its covariance:

1. **Extraction** (`extract_stars`, numpy/OpenCV): background from block medians (a smooth
   gradient: stray light, twilight, a lit horizon), noise from block MADs (so a textured
   roof or tree line raises its own threshold), hot pixels (one pixel far above all eight
   neighbours) replaced by their neighbourhood median, a Gaussian matched filter, threshold,
   connected blobs, and a centroid per blob: intensity-weighted over the blob grown by one
   pixel; blobs with saturated pixels keep that centroid (a flat top has no peak to refine),
   get a larger position sigma and are ordered first (their summed flux is clipped).
2. **Identification**: tetra3rs' lost-in-space pattern search (frontend/stars.py's database
   loader), brightest spots first. Only its star matches are used.
3. **Refinement** (`refine_camera`): attitude, focal length and (optionally) one radial
   distortion coefficient by Gauss-Newton on all matched stars' pixel residuals; the
   attitude covariance is the rotation block of ``(J^T W J)^-1`` (right perturbation,
   camera frame), scaled by the reduced chi-square when that exceeds 1.
4. **Verification**: every catalogue star the solution predicts in the image is looked for;
   the solution is kept only if enough are found, beyond the identifying pattern's, where
   the spots' local density makes a chance match improbable, among the brightest predicted
   stars at nested magnitude cuts (`_false_alarm_bright`), the
   residuals are small and brighter catalogue stars are brighter spots (rank
   correlation). Matches found here join the refinement, which is repeated.

Camera frame OpenCV (x right, y down, z along the boresight), principal point at the image
centre ``((W-1)/2, (H-1)/2)`` (pixel (0, 0) is the centre of the top-left pixel), square
pixels. Distortion model: ``r_d = r_u (1 + k (r_u / (W/2))^2)`` in pixels from the centre, so
``k`` is the fractional radial distortion at half the image width (negative: barrel).
Attitude ``inertial_from_camera`` (ICRS; catalogue places at ``epoch_yr``, no aberration
correction). Roll convention: `radec_roll_deg`. Never imports gtsam.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import rankdata

from satpose.datasets.geometry import rotvec_to_matrix
from satpose.frontend.stars import (
    ARCSEC,
    SolverCatalogue,
    StarTrackerError,
    solver_catalogue,
    solver_database,
    wahba,
)

# --------------------------------------------------------------------------------------------
# Extraction
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class StarExtractionConfig:
    """Star extraction from one image.

    Attributes:
        block_px: side of the background blocks [px]; the background is the block medians
            interpolated bilinearly, the noise the block MADs (1.4826 MAD).
        k_sigma: detection threshold on the matched-filtered image, in its noise sigmas.
        filter_sigma_px: Gaussian matched filter sigma [px] (detection only; centroids use
            the unfiltered image).
        min_pixels: fewest pixels of a blob above threshold.
        max_pixels: most pixels of a blob, unless it is compact (larger and not compact: an
            extended object, not a star).
        max_spread, max_fill: a blob above ``max_pixels`` is still a star when it is compact:
            its flux-weighted RMS radius per axis at most ``max_spread`` of the radius of a
            disc of its area, and its mean signal at most ``max_fill`` of its peak. A bright
            star's halo and spikes widen the blob above threshold while its flux stays in a
            peaked core. A uniform disc gives a spread of 0.5 (0.44 once the matched filter
            widens it) and a fill near 1. Measured: stars with diffraction spikes in a
            stretched JPEG 0.31-0.40 and 0.11-0.14; a comet's head 0.52 and 0.53; lit
            foregrounds 0.58-1.6, their fill 0.02-0.97.
        max_elongation: largest ratio of a blob's second-moment axes (streaks, edges).
        hot_pixel_ratio: a pixel whose brightest neighbour is below this fraction of it
            (above background, both) and that is above ``k_sigma`` is a hot pixel: a star's
            PSF spreads over its neighbours (0.15: a Gaussian PSF with sigma >= 0.6 px keeps
            more than that in its brightest neighbour).
        saturation_level: pixel value at or above which the sensor is saturated; None: the
            integer type's maximum (255, 65535), no saturation for float images.
        sigma_floor_px: centroid sigma floor [px] (PSF model, pixel response).
        saturated_sigma_px: centroid sigma added in quadrature for saturated spots [px].
        max_stars: most spots kept (brightest first).
    """

    block_px: int = 32
    k_sigma: float = 5.0
    filter_sigma_px: float = 1.0
    min_pixels: int = 2
    max_pixels: int = 400
    max_spread: float = 0.45
    max_fill: float = 0.25
    max_elongation: float = 3.0
    hot_pixel_ratio: float = 0.15
    saturation_level: float | None = None
    sigma_floor_px: float = 0.1
    saturated_sigma_px: float = 0.3
    max_stars: int = 300

    def __post_init__(self) -> None:
        if self.block_px < 8 or self.k_sigma <= 0 or self.filter_sigma_px <= 0:
            raise StarTrackerError("block_px >= 8, k_sigma > 0 and filter_sigma_px > 0 needed")
        if not (1 <= self.min_pixels <= self.max_pixels) or self.max_stars < 1:
            raise StarTrackerError("1 <= min_pixels <= max_pixels and max_stars >= 1 needed")
        if not (0 < self.hot_pixel_ratio < 1) or self.max_elongation < 1:
            raise StarTrackerError("0 < hot_pixel_ratio < 1 and max_elongation >= 1 needed")
        if self.max_spread <= 0 or self.max_fill <= 0:
            raise StarTrackerError("max_spread > 0 and max_fill > 0 needed")


@dataclass(frozen=True)
class ImageStars:
    """Star spots of one image, brightest first (saturated spots first, by area).

    Attributes:
        px: centroids (N, 2) [px], pixel (0, 0) the centre of the top-left pixel.
        flux: background-subtracted sum over the spot (N,) [image units].
        snr: peak signal over the local noise (N,).
        saturated: whether the spot holds saturated pixels (N,).
        sigma_px: centroid sigma (N,) [px].
        width, height: image size [px].
        noise: median background noise sigma [image units].
        hot_pixels: number of hot pixels replaced.
        texture: the largest block noise around each spot (its 32x32 block and the 8
            neighbours) over ``noise`` (N,): about 1 on a clear sky, several times that on
            or next to a textured foreground (`StarSolveConfig.foreground_texture`).
    """

    px: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    saturated: np.ndarray
    sigma_px: np.ndarray
    width: int
    height: int
    noise: float
    hot_pixels: int
    texture: np.ndarray

    def __len__(self) -> int:
        return int(self.px.shape[0])


def to_gray(image: np.ndarray) -> np.ndarray:
    """A 2-D image from gray (H, W), gray+alpha, BGR or BGRA (H, W, C): channel mean."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (1, 2, 3, 4):
        ch = {1: 1, 2: 1, 3: 3, 4: 3}[img.shape[2]]
        return img[:, :, :ch].mean(axis=2, dtype=np.float32).astype(img.dtype, copy=False)
    if img.ndim != 2:
        raise StarTrackerError(f"expected a 2-D image or one with 1-4 channels, got {img.shape}")
    return img


def _median_last(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=-1)`` of a finite array, the same values: a sort along the last
    axis (numpy's vectorised sort; several times faster than the median's partition on
    blocks of a few hundred values)."""
    n = a.shape[-1]
    s = np.sort(a, axis=-1)
    return s[..., n // 2] if n % 2 else np.mean(s[..., n // 2 - 1 : n // 2 + 1], axis=-1)


def _block_stats(
    img: np.ndarray, block: int, stride: int, zero_median: bool = False
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Per ``block`` x ``block`` block, from every ``stride``-th pixel of every
    ``stride``-th row: the median and the MAD sigma (1.4826 MAD; about 0 when
    ``zero_median``), each interpolated to full size (bilinear), the median of the
    blocks' sigmas, and the blocks' own sigmas (before the 3x3 median over blocks)."""
    h, w = img.shape
    nby, nbx = -(-h // block), -(-w // block)
    per = block // stride
    sub = img[::stride, ::stride]
    sub = cv2.copyMakeBorder(
        sub, 0, nby * per - sub.shape[0], 0, nbx * per - sub.shape[1], cv2.BORDER_REFLECT
    )
    cells = sub.reshape(nby, per, nbx, per).transpose(0, 2, 1, 3).reshape(nby, nbx, -1)
    if zero_median:
        med = np.zeros((nby, nbx), np.float32)
        mad = (1.4826 * _median_last(np.abs(cells))).astype(np.float32)
    else:
        med = _median_last(cells).astype(np.float32)
        mad = (1.4826 * _median_last(np.abs(cells - med[:, :, None]))).astype(np.float32)
    own = mad
    # A 3x3 median over blocks removes blocks dominated by a bright star or a small object.
    if nby >= 3 and nbx >= 3:
        med = cv2.medianBlur(med, 3)
        mad = cv2.medianBlur(mad, 3)
    size = (nbx * block, nby * block)
    sig = cv2.resize(mad, size, interpolation=cv2.INTER_LINEAR)[:h, :w]
    bg = med if zero_median else cv2.resize(med, size, interpolation=cv2.INTER_LINEAR)[:h, :w]
    return bg, sig, float(np.median(mad)), own


def extract_stars(image: np.ndarray, config: StarExtractionConfig | None = None) -> ImageStars:
    """Star spots of one image (module docstring, step 1).

    Args:
        image: (H, W) or (H, W, C) array, any integer or float type, finite.
        config: extraction settings.

    Returns:
        `ImageStars`, brightest first, at most ``config.max_stars``.
    """
    c = config or StarExtractionConfig()
    raw = to_gray(image)
    if raw.shape[0] < 16 or raw.shape[1] < 16:
        raise StarTrackerError(f"image too small for star extraction: {raw.shape}")
    sat_level = c.saturation_level
    if sat_level is None and np.issubdtype(raw.dtype, np.integer):
        sat_level = float(np.iinfo(raw.dtype).max)
    img = raw.astype(np.float32)
    if not np.issubdtype(raw.dtype, np.integer) and not np.isfinite(img).all():
        raise StarTrackerError("image holds non-finite values")
    h, w = img.shape
    sat = img >= sat_level if sat_level is not None else np.zeros(img.shape, bool)

    bg, noise, noise_med, block_noise = _block_stats(img, c.block_px, 2)
    # An integer image resolves no noise below one count: a zero MAD means a quantised or
    # clipped background (8-bit JPEGs with a black sky), not a noiseless one; without this
    # floor every isolated count of 1 would be a detection or a hot pixel.
    floor = 1.0 if np.issubdtype(raw.dtype, np.integer) else 1e-6
    # In place where an array is ours (full-size temporaries cost more than the arithmetic).
    np.maximum(noise, max(noise_med * 0.5, floor), out=noise)
    sig = np.subtract(img, bg, out=img)

    # Hot pixels: far above every neighbour. Replaced by the 3x3 median of the signal.
    thr = np.multiply(noise, c.k_sigma, out=bg)  # bg's memory: no longer needed
    cand = np.flatnonzero(sig > thr)  # few pixels: the other tests on them only
    sig_c = sig.ravel()[cand]
    nbr_max = _window_max(sig, cand, centre=False)
    hot = cand[(nbr_max < c.hot_pixel_ratio * sig_c) & ~sat.ravel()[cand]]
    n_hot = int(hot.size)
    if n_hot:
        sig.ravel()[hot] = _window_median(sig, hot)

    # Matched filter. Its noise is measured on the filtered image (block MADs), not
    # predicted from white noise: a textured foreground (roof, foliage) is correlated over
    # several pixels and survives the filter.
    s = c.filter_sigma_px
    filt = cv2.GaussianBlur(sig, (0, 0), s, dst=thr)  # thr's memory when it fits
    _, filt_noise, filt_med, _ = _block_stats(filt, c.block_px, 4, zero_median=True)
    # White noise of sigma n has sigma n / (2 sqrt(pi) s) after the Gaussian of sigma s.
    np.maximum(
        filt_noise, max(0.5 * filt_med, floor / (2 * math.sqrt(math.pi) * s)), out=filt_noise
    )
    filt_noise *= c.k_sigma  # now the threshold
    mask = np.greater(filt, filt_noise)
    mask |= sat
    mask = mask.view(np.uint8)
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    pts = cv2.findNonZero(mask)
    if n <= 1 or pts is None:
        return _empty(w, h, noise_med, n_hot)
    pts = pts.reshape(-1, 2)  # (x, y) rows (OpenCV 4 adds a middle axis, 5 does not)
    area = np.bincount(labels[pts[:, 1], pts[:, 0]], minlength=n)
    keep = area >= c.min_pixels  # too large and not compact: dropped after the moments
    keep[0] = False
    if not keep.any():
        return _empty(w, h, noise_med, n_hot)
    # Grow each blob by one pixel (the PSF's wings below threshold), then centroid the kept
    # ones (a pixel next to two blobs goes to the larger label: rare among stars).
    pts = cv2.findNonZero(cv2.dilate(mask, np.ones((3, 3), np.uint8))).reshape(-1, 2)
    ys, xs = pts[:, 1], pts[:, 0]
    gl = labels[ys, xs].astype(np.int64)
    rim = np.flatnonzero(gl == 0)  # the grown ring: the largest label of the 3x3 window
    gl[rim] = _window_max(labels, ys[rim] * w + xs[rim], centre=True)
    kept = keep[gl]
    ys, xs, gl = ys[kept], xs[kept], gl[kept]
    v = np.clip(sig[ys, xs], 0, None).astype(np.float64)
    flux = np.bincount(gl, weights=v, minlength=n)
    sx = np.bincount(gl, weights=v * xs, minlength=n)
    sy = np.bincount(gl, weights=v * ys, minlength=n)
    sxx = np.bincount(gl, weights=v * xs * xs, minlength=n)
    syy = np.bincount(gl, weights=v * ys * ys, minlength=n)
    sxy = np.bincount(gl, weights=v * xs * ys, minlength=n)
    peak = np.zeros(n)
    np.maximum.at(peak, gl, v)
    nsat = np.bincount(gl, weights=sat[ys, xs].astype(float), minlength=n)
    loc_noise = np.zeros(n)
    np.maximum.at(loc_noise, gl, noise[ys, xs].astype(float))

    idx = np.flatnonzero(keep & (flux > 0))
    f = flux[idx]
    cx, cy = sx[idx] / f, sy[idx] / f
    vxx = sxx[idx] / f - cx**2
    vyy = syy[idx] / f - cy**2
    vxy = sxy[idx] / f - cx * cy
    tr, det = vxx + vyy, vxx * vyy - vxy**2
    disc = np.sqrt(np.clip(tr**2 / 4 - det, 0, None))
    l1, l2 = tr / 2 + disc, np.clip(tr / 2 - disc, 1e-6, None)
    elong = np.sqrt(l1 / l2)
    saturated = nsat[idx] > 0
    ok = (elong <= c.max_elongation) | saturated
    # A blob over max_pixels is a star when compact: its flux in the core (RMS radius) and
    # peaked (mean signal against the peak).
    spread = np.sqrt(np.clip(tr / 2, 0, None) * np.pi / area[idx])
    fill = f / (np.maximum(peak[idx], 1e-12) * area[idx])
    compact = (spread <= c.max_spread) & (fill <= c.max_fill)
    ok &= (area[idx] <= c.max_pixels) | compact

    idx, f, cx, cy, saturated = idx[ok], f[ok], cx[ok], cy[ok], saturated[ok]
    size = np.sqrt(np.clip(tr[ok] / 2, 0.25, None))
    snr = peak[idx] / loc_noise[idx]
    # Centroid sigma: PSF size over SNR of the summed flux, plus a floor; saturated spots
    # (clipped flat top, possible blooming) get more.
    flux_snr = f / (loc_noise[idx] * np.sqrt(np.maximum(area[idx], 1)))
    sigma = np.sqrt(c.sigma_floor_px**2 + (size / np.maximum(flux_snr, 1e-3)) ** 2)
    sigma = np.where(saturated, np.hypot(sigma, c.saturated_sigma_px), sigma)
    # Brightest first, by flux over local noise (the same order as flux where the noise is
    # uniform; spots on a bright noisy foreground fall behind the sky's stars). Not by the
    # flux's SNR: dividing by sqrt(area) put small faint spots before large bright stars,
    # and the pattern search needs the catalogue's brightness order (a dense JPEG field
    # with a comet was not identified).
    order = np.lexsort((-f / loc_noise[idx], -(nsat[idx] * saturated)))[: c.max_stars]
    # Texture next to each spot: the largest own noise of its block and the 8 around it
    # (before the median over blocks, which lets a sky block next to foliage or a roof
    # keep the sky's noise) over the image's median noise. A star on a clear sky is near
    # 1; a spot on or along a lit foreground (leaves, a roof's edge) is several times that.
    near = cv2.dilate(block_noise, np.ones((3, 3), np.uint8))
    bi = np.clip((cy // c.block_px).astype(np.int64), 0, near.shape[0] - 1)
    bj = np.clip((cx // c.block_px).astype(np.int64), 0, near.shape[1] - 1)
    texture = near[bi, bj] / max(noise_med, floor)
    return ImageStars(
        px=np.column_stack([cx, cy])[order],
        flux=f[order],
        snr=snr[order],
        saturated=saturated[order],
        sigma_px=sigma[order],
        width=w,
        height=h,
        noise=noise_med,
        hot_pixels=n_hot,
        texture=texture[order],
    )


def _window_max(a: np.ndarray, flat: np.ndarray, centre: bool) -> np.ndarray:
    """Largest value of 2-D ``a`` in the 3x3 window of each pixel ``flat`` (flat indices),
    the centre included or not, pixels outside the image ignored: ``cv2.dilate`` at a few
    pixels, without a full-size pass."""
    h, w = a.shape
    y, x = np.divmod(np.asarray(flat, np.int64), w)
    out = np.full(y.shape, -np.inf if a.dtype.kind == "f" else np.iinfo(a.dtype).min, a.dtype)
    flat_a = a.ravel()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0 and not centre:
                continue
            yy, xx = y + dy, x + dx
            ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            v = flat_a[np.where(ok, yy * w + xx, 0)]
            np.maximum(out, np.where(ok, v, out), out=out)
    return out


def _window_median(a: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """Median of 2-D ``a`` over the 3x3 window of each pixel ``flat`` (flat indices), the
    image's edge replicated: ``cv2.medianBlur(a, 3)`` at a few pixels."""
    h, w = a.shape
    y, x = np.divmod(np.asarray(flat, np.int64), w)
    yy = np.clip(y[None, :] + np.array([-1, -1, -1, 0, 0, 0, 1, 1, 1])[:, None], 0, h - 1)
    xx = np.clip(x[None, :] + np.array([-1, 0, 1, -1, 0, 1, -1, 0, 1])[:, None], 0, w - 1)
    return np.sort(a[yy, xx], axis=0)[4]


def _empty(w: int, h: int, noise: float, hot: int) -> ImageStars:
    z = np.zeros(0)
    return ImageStars(np.zeros((0, 2)), z, z, np.zeros(0, bool), z, w, h, noise, hot, z)


# --------------------------------------------------------------------------------------------
# Camera model and refinement
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SkyCamera:
    """Pinhole camera with the principal point at the image centre and one radial term.

    Attributes:
        width, height: image size [px].
        f_px: focal length [px].
        k: fractional radial distortion at half the width (``r_d = r_u (1 + k (r_u /
            (W/2))^2)``, pixels from the centre; negative: barrel).
    """

    width: int
    height: int
    f_px: float
    k: float = 0.0

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view [deg]: the angle between the directions seen at the left
        and right edges of the image's middle row (through the distortion; tetra3's and
        cedar-solve's ``FOV``). Without distortion ``2 atan(W / 2f)``."""
        mid = (self.height - 1) / 2.0
        edge = np.array([[-0.5, mid], [self.width - 0.5, mid]])
        b = self.bearings(edge)
        return math.degrees(math.acos(float(np.clip(b[0] @ b[1], -1.0, 1.0))))

    def project(self, v_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame directions (N, 3) with z > 0."""
        u = v_cam[:, :2] / v_cam[:, 2:3] * self.f_px
        r2 = np.sum(u * u, axis=1, keepdims=True) / (self.width / 2.0) ** 2
        return u * (1 + self.k * r2) + self.center

    def bearings(self, px: np.ndarray) -> np.ndarray:
        """Unit camera-frame bearings (N, 3) of pixels (N, 2) (distortion inverted by
        fixed-point iterations: |k| is small for star-tracker optics)."""
        d = np.asarray(px, float) - self.center
        u = d.copy()
        for _ in range(8):
            r2 = np.sum(u * u, axis=1, keepdims=True) / (self.width / 2.0) ** 2
            u = d / (1 + self.k * r2)
        v = np.column_stack([u / self.f_px, np.ones(u.shape[0])])
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def fov_to_focal(fov_deg: float, width: int) -> float:
    """Focal length [px] of a horizontal field of view [deg] over ``width`` pixels."""
    return width / (2 * math.tan(math.radians(fov_deg) / 2))


@dataclass(frozen=True)
class Refinement:
    """Result of `refine_camera`.

    Attributes:
        R: ``inertial_from_camera`` (3, 3).
        camera: the refined camera.
        cov_rot: 3x3 covariance of ``delta`` in ``R_true = R Exp(delta)`` [rad^2].
        residual_px: per-star residual norms (N,) [px].
        inlier: which of the given stars the final fit kept (N,).
        chi2_red: reduced chi-square of the final fit.
    """

    R: np.ndarray
    camera: SkyCamera
    cov_rot: np.ndarray
    residual_px: np.ndarray
    inlier: np.ndarray
    chi2_red: float


_JAC_STEP = 1e-7
_JAC_ROT = rotvec_to_matrix(_JAC_STEP * np.eye(3))
"""``Exp(h e_j)`` for the numerical Jacobian's three rotation columns (computed once)."""


def _residuals(R: np.ndarray, cam: SkyCamera, r_inertial: np.ndarray, px: np.ndarray) -> np.ndarray:
    v = r_inertial @ R
    return cam.project(v) - px


def refine_camera(
    R0: np.ndarray,
    cam0: SkyCamera,
    r_inertial: np.ndarray,
    px: np.ndarray,
    sigma_px: np.ndarray,
    fit_distortion: bool,
    outlier_sigma: float = 5.0,
    iterations: int = 6,
) -> Refinement:
    """Attitude, focal length and (optionally) distortion from matched stars.

    Gauss-Newton on the weighted pixel residuals ``project((R Exp(delta))^T r) - px`` over
    ``delta`` (camera frame), ``log f`` and ``k``; numerical Jacobians (forward differences,
    each a vectorised projection of all stars). Stars with a residual above
    ``outlier_sigma`` sigmas (after scaling by the reduced chi-square) are dropped once and
    the fit repeated.

    Args:
        R0: starting ``inertial_from_camera`` (3, 3).
        cam0: starting camera.
        r_inertial: catalogue unit vectors (N, 3), ICRS.
        px: measured pixels (N, 2).
        sigma_px: centroid sigmas (N,) [px].
        fit_distortion: also fit ``k``.
        outlier_sigma: residual gate in sigmas.
        iterations: Gauss-Newton steps per pass.
    """
    n = px.shape[0]
    keep = np.ones(n, bool)
    R, cam = R0, cam0
    npar = 5 if fit_distortion else 4
    for _pass in range(2):
        rr, pp, ss = r_inertial[keep], px[keep], sigma_px[keep]
        w = 1.0 / np.repeat(ss, 2)
        for _ in range(iterations):
            e0 = _residuals(R, cam, rr, pp).ravel() * w
            J = np.empty((e0.size, npar))
            h = _JAC_STEP
            for j in range(3):
                J[:, j] = (_residuals(R @ _JAC_ROT[j], cam, rr, pp).ravel() * w - e0) / h
            cf = SkyCamera(cam.width, cam.height, cam.f_px * math.exp(h), cam.k)
            J[:, 3] = (_residuals(R, cf, rr, pp).ravel() * w - e0) / h
            if fit_distortion:
                ck = SkyCamera(cam.width, cam.height, cam.f_px, cam.k + h)
                J[:, 4] = (_residuals(R, ck, rr, pp).ravel() * w - e0) / h
            step = np.linalg.lstsq(J, -e0, rcond=None)[0]
            R = R @ rotvec_to_matrix(step[:3])
            cam = SkyCamera(
                cam.width,
                cam.height,
                cam.f_px * math.exp(step[3]),
                cam.k + (step[4] if fit_distortion else 0.0),
            )
            if np.max(np.abs(step[:3])) < 1e-10 and abs(step[3]) < 1e-10:
                break
        res_all = _residuals(R, cam, r_inertial, px)
        norm = np.linalg.norm(res_all, axis=1)
        dof = max(2 * int(keep.sum()) - npar, 1)
        chi2 = float(np.sum((norm[keep] / sigma_px[keep]) ** 2)) / dof
        gate = outlier_sigma * sigma_px * math.sqrt(max(chi2, 1.0))
        new_keep = norm < gate
        if np.array_equal(new_keep, keep) or new_keep.sum() < npar + 2:
            break
        keep = new_keep
    e = _residuals(R, cam, r_inertial[keep], px[keep]).ravel() / np.repeat(sigma_px[keep], 2)
    J = np.empty((e.size, npar))
    h = _JAC_STEP
    for j in range(3):
        ej = _residuals(R @ _JAC_ROT[j], cam, r_inertial[keep], px[keep]).ravel()
        J[:, j] = (ej / np.repeat(sigma_px[keep], 2) - e) / h
    cf = SkyCamera(cam.width, cam.height, cam.f_px * math.exp(h), cam.k)
    J[:, 3] = (
        _residuals(R, cf, r_inertial[keep], px[keep]).ravel() / np.repeat(sigma_px[keep], 2) - e
    ) / h
    if fit_distortion:
        ck = SkyCamera(cam.width, cam.height, cam.f_px, cam.k + h)
        J[:, 4] = (
            _residuals(R, ck, r_inertial[keep], px[keep]).ravel() / np.repeat(sigma_px[keep], 2) - e
        ) / h
    dof = max(e.size - npar, 1)
    chi2 = float(e @ e) / dof
    cov = np.linalg.pinv(J.T @ J)[:3, :3] * max(1.0, chi2)
    norm = np.linalg.norm(_residuals(R, cam, r_inertial, px), axis=1)
    return Refinement(R, cam, 0.5 * (cov + cov.T), norm, keep, chi2)


# --------------------------------------------------------------------------------------------
# Solve
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class StarSolveConfig:
    """Lost in space on one image.

    Attributes:
        fov_ranges_deg: horizontal fields of view the camera may have, ``(min, max)``
            pairs [deg] (edge to edge of the image width), tried in order, each with its
            own tetra3rs database, until one gives a verified solution (whose fitted field
            may lie outside the band that found it, within the searched range:
            `searched_fov_deg`; the solution names the band). A database covers
            patterns from the short side at ``min`` to the diagonal at ``max``; a wide range
            costs time and memory once per process (about 4 s for 10.4-12.4 deg, 10 s for
            8-25 deg). The default, for an unknown camera, covers 3-70 deg in three bands,
            the star-tracker band first (a star tracker's frame costs no more than with
            that band alone); a known field is one pair.
        epoch_yr: epoch of the catalogue's proper motions (the observation date).
        fit_distortion: estimate the radial distortion ``k`` (`SkyCamera`).
        identify_stars: most spots (brightest first) handed to tetra3rs.
        solve_timeout_ms: tetra3rs' wall-clock limit.
        match_radius_px: verification: a predicted star matches a spot within this many
            pixels of it (or 3 sigma of the spot, the larger).
        min_matches: fewest verified matches for a solution.
        max_false_alarm: largest probability that the verified matches are chance
            coincidences of the spots with the predicted stars (`_false_alarm_bright`, per
            solution).
        max_rmse_px: largest RMS residual of the verified matches [px].
        min_rank_correlation: smallest Spearman correlation between spot flux and catalogue
            brightness over the matches (checked with 10 or more matches).
        foreground_texture: when the brightness order gives tetra3rs no pattern, it is
            given a second order with the spots whose `ImageStars.texture` exceeds this
            last (a textured foreground's spots outranked the stars of a sky above
            trees); 0: no second search.
        extraction: star extraction settings.
    """

    fov_ranges_deg: tuple[tuple[float, float], ...] = ((8.0, 25.0), (25.0, 70.0), (3.0, 8.0))
    epoch_yr: float = 2026.0
    fit_distortion: bool = True
    identify_stars: int = 40
    solve_timeout_ms: int = 2000
    match_radius_px: float = 2.0
    min_matches: int = 8
    max_false_alarm: float = 1e-9
    max_rmse_px: float = 1.5
    min_rank_correlation: float = 0.2
    foreground_texture: float = 3.0
    extraction: StarExtractionConfig = field(default_factory=StarExtractionConfig)

    def __post_init__(self) -> None:
        if not self.fov_ranges_deg:
            raise StarTrackerError("at least one field of view range needed")
        for lo, hi in self.fov_ranges_deg:
            if not (0.5 <= lo <= hi <= 90.0):
                raise StarTrackerError(
                    f"field of view range must satisfy 0.5 <= min <= max <= 90 deg, got {lo}, {hi}"
                )
        if self.min_matches < 4 or self.identify_stars < 4:
            raise StarTrackerError("min_matches >= 4 and identify_stars >= 4 needed")
        if self.foreground_texture < 0:
            raise StarTrackerError("foreground_texture must be >= 0 (0: off)")
        if not (0 < self.max_false_alarm < 1) or self.match_radius_px <= 0:
            raise StarTrackerError("0 < max_false_alarm < 1 and match_radius_px > 0 needed")


@dataclass(frozen=True)
class StarSolution:
    """Result of `solve_image` for one image.

    Attributes:
        status: ``solved`` or ``no_solution``.
        reason: why there is no solution ('' when solved).
        R: ``inertial_from_camera`` (3, 3), or None.
        cov: 3x3 covariance of ``delta`` (``R_true = R Exp(delta)``, camera frame) [rad^2].
        camera: the estimated camera (field of view, distortion), or None.
        star_ids: catalogue ids of the verified matches (M,).
        star_mag: their catalogue magnitudes (M,).
        px: their spots' pixels (M, 2).
        rmse_arcsec: RMS residual of the matches, converted at the focal length [arcsec].
        stars: the extracted spots.
        predicted: stars the solution predicts in the image (verification) (K,).
        false_alarm: probability of the matches by chance (`_false_alarm_bright`).
        cpu_ms: CPU time of extraction, identification, refinement and checks [ms].
        band_deg: the field-of-view band ``(min, max)`` [deg] whose database identified
            the stars (`StarSolveConfig.fov_ranges_deg`); the fitted field of view may lie
            outside it (`_verify`), or None.
    """

    status: str
    reason: str
    R: np.ndarray | None
    cov: np.ndarray | None
    camera: SkyCamera | None
    star_ids: np.ndarray
    star_mag: np.ndarray
    px: np.ndarray
    rmse_arcsec: float
    stars: ImageStars | None
    predicted: int = 0
    false_alarm: float = 1.0
    cpu_ms: float = 0.0
    band_deg: tuple[float, float] | None = None


def no_solution(reason: str, stars: ImageStars | None = None, cpu_ms: float = 0.0) -> StarSolution:
    """A refused image with its reason."""
    z = np.zeros(0)
    return StarSolution(
        "no_solution",
        reason,
        None,
        None,
        None,
        np.zeros(0, np.int64),
        z,
        np.zeros((0, 2)),
        math.nan,
        stars,
        cpu_ms=cpu_ms,
    )


def database_fov_range(fov_range_deg: tuple[float, float], width: int, height: int) -> tuple:
    """The tetra3rs database's pattern scales for a horizontal field-of-view range: the
    short side at the smallest field to the diagonal at the largest [deg], rounded to 0.1
    so that nearby requests share one database."""
    lo, hi = fov_range_deg
    t_lo, t_hi = math.tan(math.radians(lo) / 2), math.tan(math.radians(hi) / 2)
    short = 2 * math.degrees(math.atan(t_lo * min(width, height) / width))
    diag = 2 * math.degrees(math.atan(t_hi * math.hypot(width, height) / width))
    return math.floor(short * 10) / 10, math.ceil(diag * 10) / 10


def radec_roll_deg(R: np.ndarray) -> tuple[float, float, float]:
    """Boresight right ascension, declination and roll [deg] of ``inertial_from_camera``.

    Roll: position angle of the camera's +y axis (image down) at the boresight, from
    celestial north through east, in (-180, 180]: 0 when image down points north, 90 when
    it points east. tetra3rs' ``roll_deg`` is this angle; tetra3's and cedar-solve's
    ``Roll`` (north counter-clockwise from image up) is ``180 - roll`` (mod 360).
    """
    z = R[:, 2]
    ra = math.atan2(z[1], z[0])
    dec = math.asin(float(np.clip(z[2], -1.0, 1.0)))
    north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    y = R[:, 1]
    roll = math.atan2(float(y @ east), float(y @ north))
    return math.degrees(ra) % 360.0, math.degrees(dec), math.degrees(roll)


def match_radius(c: StarSolveConfig, stars: ImageStars) -> np.ndarray:
    """Per spot, the radius within which a predicted star matches it [px]:
    ``match_radius_px`` or 3 sigma of the spot's centroid, the larger (N,)."""
    return np.maximum(c.match_radius_px, 3 * stars.sigma_px)


def _match(
    pred_px: np.ndarray, spots_px: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between predicted stars and spots within ``radius`` (per
    spot) [px]: (predicted index, spot index) pairs."""
    if pred_px.shape[0] == 0 or spots_px.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = cKDTree(spots_px).query(pred_px)[1]
    i = cKDTree(pred_px).query(spots_px)[1]
    pi = np.flatnonzero(i[j] == np.arange(pred_px.shape[0]))
    sj = j[pi]
    d2 = np.sum((pred_px[pi] - spots_px[sj]) ** 2, axis=1)
    ok = d2 < radius[sj] ** 2
    return pi[ok], sj[ok]


def _predict(
    cat: SolverCatalogue, R: np.ndarray, cam: SkyCamera, mag_limit: float
) -> tuple[np.ndarray, np.ndarray]:
    """Catalogue rows with mag <= ``mag_limit`` inside the image and their pixels."""
    half_diag = math.atan(math.hypot(cam.width, cam.height) / (2 * cam.f_px))
    near = cat.unit @ R[:, 2] > math.cos(min(half_diag * 1.05, math.pi / 2 - 0.01))
    rows = np.flatnonzero(near & (cat.mag <= mag_limit))
    v = cat.unit[rows] @ R
    px = cam.project(v)
    inside = (px[:, 0] >= 0) & (px[:, 0] <= cam.width - 1) & (px[:, 1] >= 0)
    inside &= px[:, 1] <= cam.height - 1
    return rows[inside], px[inside]


def solve_image(image: np.ndarray, config: StarSolveConfig | None = None) -> StarSolution:
    """Lost in space on one sky image (module docstring, steps 1-4).

    Args:
        image: (H, W) or (H, W, C) array (8/16-bit integer or float).
        config: solve settings (field-of-view range, epoch, thresholds).

    Returns:
        `StarSolution`: ``solved`` with the attitude, covariance and camera, or
        ``no_solution`` with a reason. Never a solution that failed verification.
    """
    c = config or StarSolveConfig()
    start = time.process_time()
    stars = extract_stars(image, c.extraction)
    return solve_stars(stars, c, start)


def solve_stars(
    stars: ImageStars, config: StarSolveConfig | None = None, start: float | None = None
) -> StarSolution:
    """Steps 2-4 of `solve_image` on extracted spots. ``start``: `time.process_time` at
    the beginning of the work to count in ``cpu_ms`` (default: now)."""
    c = config or StarSolveConfig()
    t0 = time.process_time() if start is None else start
    if len(stars) < 4:
        cpu_ms = (time.process_time() - t0) * 1e3
        return no_solution(f"too few star candidates ({len(stars)}, need 4)", stars, cpu_ms)
    # One field-of-view band after the other; each band's database and catalogue are built
    # once per process (cached) and not counted.
    first: StarSolution | None = None
    ranges = c.fov_ranges_deg
    for fov_range in ranges:
        t_db = time.process_time()
        scales = database_fov_range(fov_range, stars.width, stars.height)
        solver_database(scales[0], scales[1], c.epoch_yr)
        solver_catalogue(scales[0], scales[1], c.epoch_yr)
        t0 += time.process_time() - t_db
        sol = _solve_band(stars, c, fov_range, t0)
        if sol.status == "solved":
            return sol
        first = first or sol
    assert first is not None
    if len(ranges) == 1:
        return first
    bands = ", ".join(f"{lo:g}-{hi:g}" for lo, hi in ranges)
    cpu_ms = (time.process_time() - t0) * 1e3
    return no_solution(f"{first.reason} (also no solution for {bands} deg)", stars, cpu_ms)


def _solve_band(
    stars: ImageStars, c: StarSolveConfig, fov_range: tuple[float, float], t0: float
) -> StarSolution:
    """Identification, refinement and verification for one field-of-view range."""
    w, h = stars.width, stars.height
    scales = database_fov_range(fov_range, w, h)
    db = solver_database(scales[0], scales[1], c.epoch_yr)
    cat = solver_catalogue(scales[0], scales[1], c.epoch_yr)

    def cpu() -> float:
        return (time.process_time() - t0) * 1e3

    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    lo, hi = fov_range

    def identify(order: np.ndarray) -> tuple[Any, np.ndarray]:
        """tetra3rs on the first ``identify_stars`` spots of ``order``; its result and
        the spots it was given."""
        sel = order[: c.identify_stars]
        rank = np.arange(sel.size, 0, -1, dtype=float)  # brightness order only
        cent = np.column_stack([stars.px[sel] - centre, rank])
        res = db.solve_from_centroids(
            cent,
            fov_estimate_deg=0.5 * (lo + hi),
            fov_max_error_deg=0.5 * (hi - lo) + 1e-6,
            image_width=w,
            image_height=h,
            solve_timeout_ms=c.solve_timeout_ms,
        )
        return res, sel

    res, sel = identify(np.arange(len(stars)))
    retried = ""
    if not res and c.foreground_texture > 0:
        # Spots on or along a textured foreground (lit leaves, a roof's edge) can outrank
        # the sky's stars; a second search puts them last (module docstring, step 2).
        fg = stars.texture > c.foreground_texture
        if fg[: c.identify_stars].any() and int((~fg).sum()) >= 4:
            retried = f"; also with the {int(fg.sum())} spots on a textured foreground last"
            res2, sel2 = identify(np.concatenate([np.flatnonzero(~fg), np.flatnonzero(fg)]))
            if res2:
                res, sel = res2, sel2
    if not res:
        status = getattr(res, "status", "no_match")
        return no_solution(
            f"no star pattern identified (tetra3rs: {status}) among {len(stars)} spots" + retried,
            stars,
            cpu(),
        )
    idx = sel[np.asarray(res.matched_centroids, dtype=np.int64)]
    ids = np.asarray(res.matched_catalog_ids, dtype=np.int64)
    known = np.array([int(i) in cat.row_of for i in ids], dtype=bool)
    idx, ids = idx[known], ids[known]
    if idx.size < 4:
        return no_solution(f"too few identified stars ({idx.size})", stars, cpu())
    cam = SkyCamera(w, h, fov_to_focal(float(res.fov_deg), w))
    rows = np.array([cat.row_of[int(i)] for i in ids])
    R, _ = wahba(cam.bearings(stars.px[idx]), cat.unit[rows], 1.0)
    # Refine on the identified stars, then look for every predicted star and refine on all.
    ref = refine_camera(
        R, cam, cat.unit[rows], stars.px[idx], stars.sigma_px[idx], c.fit_distortion
    )
    mag_limit = float(np.max(cat.mag))
    match_r = match_radius(c, stars)
    pi = sj = np.zeros(0, np.int64)
    prow = np.zeros(0, np.int64)
    for _ in range(2):
        prow, ppx = _predict(cat, ref.R, ref.camera, mag_limit)
        pi, sj = _match(ppx, stars.px, match_r)
        if pi.size < c.min_matches:
            break
        ref = refine_camera(
            ref.R,
            ref.camera,
            cat.unit[prow[pi]],
            stars.px[sj],
            stars.sigma_px[sj],
            c.fit_distortion,
        )
        pi, sj = pi[ref.inlier], sj[ref.inlier]
    elapsed = cpu()
    verdict, fa = _verify(c, stars, prow, ppx, pi, sj, match_r, ref.R, ref.camera, cat)
    if verdict:
        return no_solution(f"verification failed: {verdict}", stars, elapsed)
    r = cat.unit[prow[pi]]
    res_px = np.linalg.norm(_residuals(ref.R, ref.camera, r, stars.px[sj]), axis=1)
    rmse_px = float(np.sqrt(np.mean(res_px**2)))
    return StarSolution(
        "solved",
        "",
        ref.R,
        ref.cov_rot,
        ref.camera,
        cat.ids[prow[pi]],
        cat.mag[prow[pi]],
        stars.px[sj],
        rmse_px / ref.camera.f_px / ARCSEC,
        stars,
        int(prow.size),
        fa,
        cpu(),
        (lo, hi),
    )


_SEGMENT = 16
"""Stars per segment of `_chance_counts`."""

PATTERN_STARS = 4
"""Stars of the identifying pattern (tetra3rs' 4-star patterns): matched by construction,
so `_false_alarm` does not count them as confirmations (they also fix more than the
refinement's 5 parameters)."""


def _chance_match(stars: ImageStars, pred_px: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Probability that a predicted star at each pixel (K, 2) lands within the match radius
    of some spot by chance (K,), from the spots' *local* density: the spots' match areas
    (``pi radius^2``) summed over a window of about a quarter of the image's short side
    around the star, over the window's area inside the image. Spots cluster on a textured
    foreground (a tree line, a roof's edge), so an image-wide density would make a match
    there look more significant than it is (and one on the clear sky less)."""
    cell = 16
    gh, gw = -(-stars.height // cell), -(-stars.width // cell)
    area = np.zeros((gh, gw), np.float64)
    if len(stars):
        gi = np.clip((stars.px[:, 1] // cell).astype(np.int64), 0, gh - 1)
        gj = np.clip((stars.px[:, 0] // cell).astype(np.int64), 0, gw - 1)
        np.add.at(area, (gi, gj), np.pi * radius**2)
    k = max(5, round(min(stars.width, stars.height) / 4 / cell) | 1)
    summed = cv2.boxFilter(area, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    full = np.full((gh, gw), float(cell * cell))
    inside = cv2.boxFilter(full, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    qi = np.clip((pred_px[:, 1] // cell).astype(np.int64), 0, gh - 1)
    qj = np.clip((pred_px[:, 0] // cell).astype(np.int64), 0, gw - 1)
    return np.asarray(1.0 - np.exp(-summed[qi, qj] / inside[qi, qj]))


def _chance_counts(p: np.ndarray, need: int, cuts: list[int]) -> np.ndarray:
    """Distribution of the number of chance matches among the first ``k`` stars, for each
    ``k`` in ``cuts`` (ascending, at most ``len(p)``), the stars matching independently
    with probabilities ``p``: rows (len(cuts), need + 1), column ``i`` the probability of
    exactly ``i`` matches, the last column of ``need`` or more (exact; ``need`` >= 1).

    The generating polynomial ``prod_j (1 - p_j + p_j x)``, truncated at ``x^need`` (the
    higher terms summed into it): the stars go in segments of at most `_SEGMENT` that end
    at the cuts; every segment's own polynomial is built at once for all segments (one
    vectorised step per star of a segment), then multiplied in one after the other. All
    terms are sums of products of probabilities: no cancellation for tiny tails."""
    p = np.asarray(p, float)
    bounds = sorted({0, *range(_SEGMENT, p.size, _SEGMENT), *cuts})
    seg_p = np.zeros((max(len(bounds) - 1, 0), _SEGMENT))
    for s, (a, b) in enumerate(itertools.pairwise(bounds)):
        seg_p[s, : b - a] = p[a:b]
    poly = np.zeros((seg_p.shape[0], _SEGMENT + 1))
    poly[:, 0] = 1.0
    for col in seg_p.T[:, :, None]:  # one star of every segment (p = 0 past a short one)
        poly[:, 1:] = poly[:, 1:] * (1 - col) + poly[:, :-1] * col
        poly[:, :1] *= 1 - col
    dist = np.zeros(need + 1)
    dist[0] = 1.0
    rows = np.zeros((len(cuts), need + 1))
    c = 0
    for s, start in enumerate(bounds):
        while c < len(cuts) and cuts[c] == start:
            rows[c] = dist
            c += 1
        if c == len(cuts) or s == poly.shape[0]:
            break
        full = np.convolve(dist[:need], poly[s])
        dist[need] += full[need:].sum()
        dist[:need] = full[:need]
    return rows


def _false_alarm(stars: ImageStars, pred_px: np.ndarray, m: int, radius: np.ndarray) -> float:
    """Probability that ``m - PATTERN_STARS`` or more of the predicted stars (pixels
    (K, 2)) land within a match radius of some spot by chance: the upper tail of the
    Poisson-binomial distribution of the stars' `_chance_match` probabilities
    (`_chance_counts`)."""
    need = m - PATTERN_STARS
    if need <= 0:
        return 1.0
    p = _chance_match(stars, pred_px, radius)
    return float(min(_chance_counts(p, need, [p.size])[0, need], 1.0))


def _false_alarm_bright(
    stars: ImageStars, pred_px: np.ndarray, pred_mag: np.ndarray, pi: np.ndarray, radius: np.ndarray
) -> float:
    """`_false_alarm` of the matches among the brightest predicted stars, for nested cuts
    (the brightest 16, 32, 64, ... and all of them), the smallest times the number of cuts
    (Bonferroni: the test's false-alarm rate stays at most the threshold).

    An image shows the catalogue only down to its own limiting magnitude, which no solver
    knows beforehand. Against a catalogue deeper than that, most predicted stars cannot
    be seen and the matches look no better than chance: a noisy 6 deg frame
    (openstartracker's img9.png) matched 10 of 127 predicted stars, p = 1.2e-8, its
    brightest ones. A chance coincidence favours no magnitude; real stars come brightest
    first.

    Args:
        pred_px: predicted pixels (K, 2); pred_mag: their catalogue magnitudes (K,).
        pi: indices of the matched predicted stars.
    """
    k_all = pred_px.shape[0]
    need_max = int(pi.size) - PATTERN_STARS
    if need_max <= 0:
        return 1.0
    cuts = [k for k in (16 * 2**j for j in range(16)) if k < k_all] + [k_all]
    order = np.argsort(pred_mag, kind="stable")
    matched = np.zeros(k_all, bool)
    matched[pi] = True
    m_cum = np.concatenate([[0], np.cumsum(matched[order])])
    # One pass over the stars in brightness order gives every cut's distribution; each
    # tail is a sum of its upper terms (no cancellation for tiny probabilities).
    rows = _chance_counts(_chance_match(stars, pred_px[order], radius), need_max, cuts)
    best = 1.0
    for row, k in zip(rows, cuts, strict=True):
        need = int(m_cum[k]) - PATTERN_STARS
        best = min(best, float(row[need:].sum()) if need > 0 else 1.0)
    return min(1.0, best * len(cuts))


def searched_fov_deg(c: StarSolveConfig) -> tuple[float, float]:
    """The horizontal fields of view the search covers [deg]: from the smallest band's
    minimum to the largest band's maximum, 2 % wider each side (a field fitted just past
    a band's edge). The bands are an order in which to search one range (the default's
    three cover 3-70 deg), not separate allowed ranges."""
    lo = min(b[0] for b in c.fov_ranges_deg)
    hi = max(b[1] for b in c.fov_ranges_deg)
    return 0.98 * lo, 1.02 * hi


def _verify(
    c: StarSolveConfig,
    stars: ImageStars,
    prow: np.ndarray,
    ppx: np.ndarray,
    pi: np.ndarray,
    sj: np.ndarray,
    match_r: np.ndarray,
    R: np.ndarray,
    cam: SkyCamera,
    cat: SolverCatalogue,
) -> tuple[str, float]:
    """('', false-alarm probability) if the predicted stars confirm the solution, else
    (why not, the probability or 1 where not computed). ``match_r``: the spots' match
    radii the matches were made with (`match_radius`)."""
    m = int(pi.size)
    if m < c.min_matches:
        return f"{m} of {prow.size} predicted stars found (need {c.min_matches})", 1.0
    fa = _false_alarm_bright(stars, ppx, cat.mag[prow], pi, match_r)
    if fa > c.max_false_alarm:
        return f"{m} of {prow.size} predicted stars found, as likely by chance (p = {fa:.1e})", fa
    r = cat.unit[prow[pi]]
    res = np.linalg.norm(_residuals(R, cam, r, stars.px[sj]), axis=1)
    rmse = float(np.sqrt(np.mean(res**2)))
    if rmse > c.max_rmse_px:
        return f"residuals {rmse:.2f} px RMS over {m} stars (max {c.max_rmse_px})", fa
    if m >= 10:
        # Spearman's rank correlation (ties: average ranks).
        rho = float(np.corrcoef(rankdata(stars.flux[sj]), rankdata(-cat.mag[prow[pi]]))[0, 1])
        if not rho >= c.min_rank_correlation:
            return f"spot brightness does not follow catalogue magnitude (rank corr. {rho:.2f})", fa
    # The field of view against the whole search, not the band that identified the stars:
    # a band's database holds patterns beyond its nominal range (from its short side at
    # the minimum), and a verified solution found by the 8-25 deg band at 6.07 deg (an
    # openstartracker frame) was refused while the 3-8 deg band found no pattern.
    fov = cam.fov_deg
    lo, hi = searched_fov_deg(c)
    if not (lo <= fov <= hi):
        return f"field of view {fov:.3f} deg outside the searched {lo:.3g}-{hi:.3g} deg", fa
    return "", fa


def check_attitude(
    stars: ImageStars, R: np.ndarray, camera: SkyCamera, config: StarSolveConfig | None = None
) -> tuple[str, int, int]:
    """Verification of any attitude: predict the catalogue stars in the image and look for
    them among the spots (the check `solve_image` applies to its own solutions).

    Args:
        stars: the image's spots.
        R: ``inertial_from_camera`` (3, 3) to check.
        camera: the camera to project with.
        config: thresholds and catalogue (field-of-view range, epoch).

    Returns:
        ``(reason, matches, predicted)``: reason '' if the attitude is confirmed.
    """
    c = config or StarSolveConfig()
    fov = camera.fov_deg  # the band holding the camera's field (its catalogue), else the first
    fov_range = next((r for r in c.fov_ranges_deg if r[0] <= fov <= r[1]), c.fov_ranges_deg[0])
    scales = database_fov_range(fov_range, stars.width, stars.height)
    cat = solver_catalogue(scales[0], scales[1], c.epoch_yr)
    prow, ppx = _predict(cat, R, camera, float(np.max(cat.mag)))
    match_r = match_radius(c, stars)
    pi, sj = _match(ppx, stars.px, match_r)
    verdict, _ = _verify(c, stars, prow, ppx, pi, sj, match_r, R, camera, cat)
    return verdict, int(pi.size), int(prow.size)
