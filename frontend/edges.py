"""Sub-pixel edge localisation along given normals (numpy + OpenCV).

Used to refine the ring ellipse and the panel edge lines: the image is smoothed once
(Gaussian, ``sigma_px``), intensity profiles are sampled along each normal with bicubic
interpolation (`sample_image`: exact at the sample positions whatever the OpenCV version), and
the edge is the extremum of the profile's derivative of the expected sign, located to sub-pixel
precision by a parabola through the three samples around it. Whole-pixel Canny edges scatter
by ~0.5 px; these by ~0.05 px on a clean step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np


@dataclass(frozen=True, kw_only=True)
class EdgeSearchConfig:
    """Settings of the search along normals.

    Attributes:
        smooth_sigma_px: Gaussian smoothing before sampling (suppresses noise and pixel
            locking; a blur of the edge is symmetric and does not move it).
        step_px: sample spacing along the normal.
        min_step: smallest accepted intensity change across the edge (fraction of full
            scale, measured as the derivative peak times 2 * smooth_sigma_px).
        locate: ``gradient``: the edge is the derivative's extremum. ``midlevel``: found
            there first, then moved to where the profile crosses half-way between the bright
            plateau (``plateau_px`` inward from it) and the darkest value within 1.5 px on the
            dark side. A narrow dark band just outside an edge (a wall seen at grazing angle,
            a shadow) pulls the derivative's extremum into the bright side by up to a pixel;
            the half-level crossing is far less sensitive to it.
        plateau_px: where the bright plateau is measured (distance range from the edge).
        model_window_px: ``model``: found by the derivative first, then refined by fitting a
            blurred step ``B + (A - B) * Phi((s0 - s) / w)`` (levels A, B and position s0 per
            normal, blur w shared by all normals) to the *unsmoothed* profile over this range
            relative to the first estimate. The range reaches far into the bright side and
            only one pixel into the dark side, so texture just beyond an edge (crinkled foil
            beside a rim) hardly moves it.
        dark_band: after the edge is located, normals whose profile dips just past it
            (darker than both the plateau inside and the level outside by
            ``dark_band_min_depth``) are re-located by moments: a thin dark band beside an
            edge (a gap, a shadow's sliver, a wall at grazing angle: in space, nearly black)
            is not resolved by the blur, and every local locator (derivative, step fit,
            half level) then puts the edge up to the blur width inside it, by an amount that
            grows with the blur. Over ``dark_band_window_px`` the profile's integral and first
            moment are blur-invariant; with the plateaus ``A`` inside and ``B`` outside and
            the band at ``dark_band_level`` they give the edge ``u`` and the band's far side
            ``v`` in closed form (`_dark_band_edges`; a moment-preserving locator in the
            manner of Tabatabai and Mitchell, 1984, with a band instead of a second level).
    """

    smooth_sigma_px: float = 1.0
    step_px: float = 0.5
    min_step: float = 0.03
    locate: Literal["gradient", "midlevel", "model"] = "gradient"
    plateau_px: tuple[float, float] = (1.0, 2.5)
    model_window_px: tuple[float, float] = (-2.0, 1.0)
    dark_band: bool = False
    dark_band_window_px: tuple[float, float] = (-3.0, 3.5)
    dark_band_level: float = 0.0
    dark_band_min_depth: float = 0.03


def sample_image(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, method: Literal["linear", "cubic"]
) -> np.ndarray:
    """``image`` (H, W) interpolated at the points ``(x, y)`` (any equal shapes) with the
    border replicated: ``linear`` (bilinear) or ``cubic`` (Keys, a = -0.75, as OpenCV's
    INTER_CUBIC), float32.

    Exact at the given positions: OpenCV 4.x ``remap`` with float maps rounds them to 1/32 px
    and 5.x does not, which moves sub-pixel edges by up to ~1/64 px between versions.
    """
    # the taps are read from the image as it is and widen to float64 in the products below
    # (exactly: float32 and integer pixels are float64 values); converting the whole image
    # first cost a full-image copy per call (~6 MB at 1024x768, most of this function's time)
    img = np.asarray(image)
    h, w = img.shape
    xs = np.asarray(x, dtype=np.float64)
    ys = np.asarray(y, dtype=np.float64)
    x0, y0 = np.floor(xs), np.floor(ys)
    tx, ty = xs - x0, ys - y0
    x0i, y0i = x0.astype(np.int64), y0.astype(np.int64)
    offsets: tuple[int, ...]
    if method == "linear":
        offsets = (0, 1)
        wx = [1.0 - tx, tx]
        wy = [1.0 - ty, ty]
    else:
        a = -0.75
        offsets = (-1, 0, 1, 2)

        def keys(t: np.ndarray) -> list[np.ndarray]:
            # weights of the taps at -1, 0, 1, 2 for a fraction t in [0, 1)
            return [
                ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a,
                ((a + 2) * t - (a + 3)) * t * t + 1,
                ((a + 2) * (1 - t) - (a + 3)) * (1 - t) * (1 - t) + 1,
                ((a * (2 - t) - 5 * a) * (2 - t) + 8 * a) * (2 - t) - 4 * a,
            ]

        wx, wy = keys(tx), keys(ty)
    out = np.zeros(xs.shape)
    for j, dy in enumerate(offsets):
        row = np.clip(y0i + dy, 0, h - 1)
        acc = np.zeros(xs.shape)
        for i, dx in enumerate(offsets):
            acc += wx[i] * img[row, np.clip(x0i + dx, 0, w - 1)]
        out += wy[j] * acc
    return out.astype(np.float32)


def smoothed(gray: np.ndarray, config: EdgeSearchConfig) -> np.ndarray:
    """The Gaussian-smoothed float32 image the profiles are sampled from."""
    return cv2.GaussianBlur(gray.astype(np.float32), (0, 0), config.smooth_sigma_px)


def edges_along_normals(
    image_s: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    polarity: int,
    half_width_px: float,
    config: EdgeSearchConfig,
    raw: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Find one edge per normal.

    Args:
        image_s: smoothed image from `smoothed`, (H, W) float32 in [0, 1].
        points: (N, 2) predicted edge positions [px].
        normals: (N, 2) unit normals pointing from the bright side to the dark side when
            ``polarity = +1`` (i.e. the intensity decreases along the normal), the reverse
            for ``polarity = -1``.
        half_width_px: search interval ``[-half_width, +half_width]`` along each normal.
        raw: the unsmoothed image, needed by ``locate = "model"``.

    Returns:
        edge points (N, 2) and their contrast (N,) (intensity step across the edge); points
        without an edge of the right sign and contrast are NaN with contrast 0.
    """
    n = points.shape[0]
    s = np.arange(-half_width_px, half_width_px + 1e-9, config.step_px, dtype=np.float32)
    pos = points[:, None, :] + s[None, :, None] * normals[:, None, :]  # (N, S, 2)
    prof = sample_image(
        image_s, pos[..., 0].astype(np.float32), pos[..., 1].astype(np.float32), "cubic"
    )
    deriv = -polarity * (prof[:, 2:] - prof[:, :-2]) / (2 * config.step_px)  # at s[1:-1]
    k = np.argmax(deriv, axis=1)
    peak = deriv[np.arange(n), k]
    contrast = peak * 2.0 * config.smooth_sigma_px * np.sqrt(np.pi / 2)
    interior = (k > 0) & (k < deriv.shape[1] - 1)
    kk = np.clip(k, 1, deriv.shape[1] - 2)
    y0, y1, y2 = deriv[np.arange(n), kk - 1], deriv[np.arange(n), kk], deriv[np.arange(n), kk + 1]
    denom = y0 - 2 * y1 + y2
    frac = np.where(np.abs(denom) > 1e-12, 0.5 * (y0 - y2) / np.where(denom == 0, 1, denom), 0.0)
    offset = s[1:-1][kk] + np.clip(frac, -0.5, 0.5) * config.step_px
    ok = interior & (contrast >= config.min_step) & (denom < 0)
    if config.locate == "midlevel":
        offset, ok2 = _midlevel(prof * -polarity, s, offset, config)
        ok &= ok2
    elif config.locate == "model" and raw is not None:
        offset, ok2 = _step_model(raw, points, normals, polarity, offset, ok, config)
        ok &= ok2
    if config.dark_band and raw is not None and polarity != 0:
        offset = _dark_band_edges(raw, points, normals, polarity, offset, ok, config)
    out = points + offset[:, None] * normals
    out[~ok] = np.nan
    return out, np.where(ok, contrast, 0.0)


def edges_of_polarity(
    image_s: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    polarity: int,
    half_width_px: float,
    config: EdgeSearchConfig,
    raw: np.ndarray | None = None,
) -> np.ndarray:
    """`edges_along_normals`' edge points (NaN where none), with ``polarity`` 0 too: an edge
    brighter on one side of a curve and darker on the other (side light: lit foil beside a
    rim, shadow on the far side), each normal keeping the stronger of both signs."""
    if polarity != 0:
        return edges_along_normals(
            image_s, points, normals, polarity, half_width_px, config, raw=raw
        )[0]
    brighter, c_b = edges_along_normals(
        image_s, points, normals, +1, half_width_px, config, raw=raw
    )
    darker, c_d = edges_along_normals(image_s, points, normals, -1, half_width_px, config, raw=raw)
    return np.where((c_d > c_b)[:, None], darker, brighter)


def _midlevel(
    prof: np.ndarray, s: np.ndarray, coarse: np.ndarray, config: EdgeSearchConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Half-level crossing near ``coarse`` for profiles that *rise* along ``s`` (dark side at
    larger s after the sign flip done by the caller: ``prof = -polarity * intensity``)."""
    n = prof.shape[0]
    rel = s[None, :] - coarse[:, None]  # (N, S) position relative to the coarse edge
    bright = (rel <= -config.plateau_px[0]) & (rel >= -config.plateau_px[1])
    dark = (rel >= 0.0) & (rel <= 1.5)
    with np.errstate(invalid="ignore"):
        # After the flip, the bright side has the *lower* values: plateau = mean of the
        # bright samples, dark level = the largest value just past the edge.
        lo = np.where(bright, prof, np.nan)
        hi = np.where(dark, prof, np.nan)
        a = np.nanmean(lo, axis=1)
        b = np.nanmax(hi, axis=1)
    level = 0.5 * (a + b)
    window = (rel >= -1.5) & (rel <= 1.5)
    above = (prof >= level[:, None]) & window
    # First sample in the window at or above the level, and the one before it.
    first = np.where(above.any(axis=1), np.argmax(above, axis=1), 0)
    k0 = np.clip(first - 1, 0, s.size - 1)
    y0 = prof[np.arange(n), k0]
    y1 = prof[np.arange(n), first]
    t = np.where(y1 > y0, (level - y0) / np.where(y1 > y0, y1 - y0, 1.0), 0.0)
    out = s[k0] + np.clip(t, 0.0, 1.0) * (s[first] - s[k0])
    ok = above.any(axis=1) & np.isfinite(a) & np.isfinite(b) & (first > 0) & (b > a)
    return np.where(ok, out, coarse), ok


def _step_model(
    raw: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    polarity: int,
    coarse: np.ndarray,
    valid: np.ndarray,
    config: EdgeSearchConfig,
    iterations: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Blurred-step fit along each normal (see ``EdgeSearchConfig.model_window_px``)."""
    from scipy.special import erf

    n = points.shape[0]
    lo, hi = config.model_window_px
    t = np.arange(lo, hi + 1e-9, 0.25, dtype=np.float64)  # relative to the coarse edge
    y = _raw_profiles(raw, points, normals, coarse, t)
    y = -polarity * y  # now rising from the bright (low) side to the dark (high) side
    A = y[:, : max(2, int(0.25 * len(t)))].mean(axis=1)  # bright side level (low after flip)
    B = y[:, -2:].mean(axis=1)
    s0 = np.zeros(n)
    w = 0.6
    for it in range(iterations):
        z = (t[None, :] - s0[:, None]) / w
        F = 0.5 * (1 + erf(z / np.sqrt(2)))  # 0 on the bright side, 1 on the dark side
        dF = np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi) / w
        r = A[:, None] + (B - A)[:, None] * F - y
        J = np.stack([1 - F, F, -(B - A)[:, None] * dF], axis=2)  # d r / d(A, B, s0)
        H = np.einsum("nsi,nsj->nij", J, J) + np.eye(3) * 1e-9
        g = np.einsum("nsi,ns->ni", J, r)
        try:
            d = -np.linalg.solve(H, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        A, B, s0 = A + d[:, 0], B + d[:, 1], np.clip(s0 + d[:, 2], lo + 0.5, hi - 0.25)
        if it >= 2 and np.all(np.abs(d[valid, 2]) < 1e-4):
            break  # converged (the blur is fixed after iteration 1)
        if it == 1:
            # Shared blur: the median over the strong, valid profiles of a 1-D refit of w.
            strong = valid & ((B - A) > 2 * config.min_step)
            if strong.sum() >= 8:
                w = float(
                    np.clip(_fit_width(t, y[strong], A[strong], B[strong], s0[strong]), 0.3, 1.5)
                )
    ok = (B - A) > config.min_step
    return coarse + s0, ok


def _raw_profiles(
    raw: np.ndarray, points: np.ndarray, normals: np.ndarray, at: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Bilinear profiles (N, T) of the unsmoothed image along each normal, at offsets ``t``
    from ``points + at * normals``."""
    pos = points[:, None, :] + (at[:, None] + t[None, :])[..., None] * normals[:, None, :]
    return sample_image(
        raw.astype(np.float32),
        pos[..., 0].astype(np.float32),
        pos[..., 1].astype(np.float32),
        "linear",
    ).astype(np.float64)


def _fit_width(t: np.ndarray, y: np.ndarray, A: np.ndarray, B: np.ndarray, s0: np.ndarray) -> float:
    """Blur width in [0.3, 1.5] px minimising the squared residuals of all given profiles
    (golden-section search to 0.01 px: 12 evaluations)."""
    from scipy.special import erf

    def cost(w: float) -> float:
        F = 0.5 * (1 + erf((t[None, :] - s0[:, None]) / (w * np.sqrt(2))))
        r = A[:, None] + (B - A)[:, None] * F - y
        return float(np.sum(r * r))

    g = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = 0.3, 1.5
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = cost(c), cost(d)
    while b - a > 0.01:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = cost(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = cost(d)
    return 0.5 * (a + b)


def _dark_band_edges(
    raw: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    polarity: int,
    edge: np.ndarray,
    valid: np.ndarray,
    config: EdgeSearchConfig,
) -> np.ndarray:
    """Edge offsets re-located where a dark band follows the edge (``dark_band``).

    The unblurred profile across the edge at ``u`` is ``A`` (inside) up to ``u``, the band
    level ``D`` from ``u`` to ``v`` and ``B`` beyond. Any symmetric blur keeps its integral
    ``I0`` and first moment ``I1`` over a window whose ends lie on the plateaus, so
    ``I0 = (A - D) u + (D - B) v + B R - A L`` and
    ``2 I1 = (A - D) u^2 + (D - B) v^2 + B R^2 - A L^2``: a quadratic in ``u``. Normals
    without a dip, or whose solution is not a band (``v < u``) inside the window, keep
    ``edge``."""
    if polarity < 0:  # the band is darker than both sides: only for a bright inside
        return edge
    lo, hi = config.dark_band_window_px
    t = np.arange(lo, hi + 1e-9, 0.25)
    y = _raw_profiles(raw, points, normals, edge, t)
    k = 3  # plateaus: the 0.75 px at each end of the window
    A = y[:, :k].mean(axis=1)
    B = y[:, -k:].mean(axis=1)
    D = config.dark_band_level
    near = (t >= -0.5) & (t <= 2.0)
    dip = np.min(y[:, near], axis=1)
    has_dip = valid & (dip < np.minimum(A, B) - config.dark_band_min_depth) & (B > D) & (A > D)
    if not has_dip.any():
        return edge
    L, R = t[0], t[-1]
    I0 = np.trapezoid(y, t, axis=1)
    I1 = np.trapezoid(y * t[None, :], t, axis=1)
    a_ = A - D
    b_ = D - B
    E0 = I0 - (B * R - A * L)
    E1 = 2 * I1 - (B * R * R - A * L * L)
    # a (a + b) u^2 - 2 a E0 u + (E0^2 - b E1) = 0
    qa = a_ * (a_ + b_)
    qb = -2 * a_ * E0
    qc = E0 * E0 - b_ * E1
    out = edge.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = qb * qb - 4 * qa * qc
        sq = np.sqrt(np.maximum(disc, 0.0))
        roots = np.stack(
            [
                np.where(np.abs(qa) > 1e-9, (-qb - sq) / (2 * qa), -qc / qb),
                np.where(np.abs(qa) > 1e-9, (-qb + sq) / (2 * qa), -qc / qb),
            ],
            axis=1,
        )
        v = (E0[:, None] - a_[:, None] * roots) / b_[:, None]
        good = (
            (disc[:, None] >= 0)
            & (v >= roots - 1e-9)
            & (roots > L + 0.5)
            & (v < R - 0.5)
            & np.isfinite(roots)
        )
        # the root nearest the first estimate among the admissible ones
        cost = np.where(good, np.abs(roots), np.inf)
        j = np.argmin(cost, axis=1)
        u = roots[np.arange(len(j)), j]
        ok = has_dip & np.isfinite(cost[np.arange(len(j)), j])
    out[ok] = edge[ok] + u[ok]
    return out
