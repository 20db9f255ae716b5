"""Procedural, non-repeating surface textures (numpy + OpenCV).

Each face of the target gets its own texture generated from the scene seed, sized to the face
at ``texel_m`` per texel and mapped once across it: nothing tiles, so no two places on the
target look alike (repeating foil fools feature matching and structure from motion).

MLI foil = Voronoi facets with random normal tilts (the crinkles), a slow undulation, per-facet
roughness, plus stains (darker blotches), tape seams (straight strips of a different tint and
a smoother finish) and labels (white diffuse rectangles with dark text bars).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from satpose.datasets.target import FoilConfig

MAX_TEXELS = 2048
"""Largest texture side; faces bigger than MAX_TEXELS * texel_m get coarser texels."""


@dataclass(frozen=True, kw_only=True)
class FoilTexture:
    """Per-texel maps of one face, all float32, rows = v, columns = u.

    Attributes:
        normal: (H, W, 3) tangent-space normals encoded as ``0.5 * n + 0.5``.
        roughness: (H, W, 1) GGX alpha.
        reflectance: (H, W, 3) specular reflectance multiplier of the foil.
        label_weight: (H, W, 1) 1 where a diffuse label covers the foil, else 0.
        label_albedo: (H, W, 3) diffuse albedo of the labels.
    """

    normal: np.ndarray
    roughness: np.ndarray
    reflectance: np.ndarray
    label_weight: np.ndarray
    label_albedo: np.ndarray


def texture_shape(width_m: float, height_m: float, texel_m: float) -> tuple[int, int]:
    """``(rows, cols)`` of a texture covering a ``width_m`` x ``height_m`` face."""
    texel = max(texel_m, max(width_m, height_m) / MAX_TEXELS)
    return max(8, math.ceil(height_m / texel)), max(8, math.ceil(width_m / texel))


def foil_texture(
    width_m: float, height_m: float, cfg: FoilConfig, rng: np.random.Generator
) -> FoilTexture:
    """Generate the foil maps of one ``width_m`` x ``height_m`` face."""
    rows, cols = texture_shape(width_m, height_m, cfg.texel_m)
    texel = width_m / cols  # metres per texel along u (v is within rounding of the same)
    area = width_m * height_m

    # Crinkle facets: Voronoi cells of random seeds, each tilted at random; a coarse layer of
    # folds and a fine layer of wrinkles, both stretched along a random direction per face so
    # that the creases look folded rather than cellular.
    yy, xx = np.mgrid[0:rows, 0:cols]
    grid = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(float)
    tilt = math.tan(math.radians(cfg.facet_tilt_deg))
    gx = np.zeros((rows, cols))
    gy = np.zeros((rows, cols))
    cell = np.zeros((rows, cols), np.int64)
    n_seeds = 0
    for scale, weight in ((1.0, 1.0), (0.4, 0.6)):
        n = max(4, int(area / (cfg.facet_size_m * scale) ** 2))
        seeds = rng.random((n, 2)) * [cols, rows]
        angle = rng.uniform(0, math.pi)
        rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        A = rot @ np.diag([1.0, rng.uniform(1.3, 2.2)]) @ rot.T
        _, idx = cKDTree(seeds @ A.T).query(grid @ A.T, workers=1)
        idx = idx.reshape(rows, cols)
        slopes = rng.normal(0.0, tilt * weight, size=(n, 2))
        gx += slopes[idx, 0]
        gy += slopes[idx, 1]
        if scale == 1.0:
            cell, n_seeds = idx, n
    # Slow undulation of the blanket (period ~ 10-20 cm), a few degrees.
    sigma_lf = 0.06 / texel
    undulation = math.tan(math.radians(3.0))
    for g in (gx, gy):
        noise = cv2.GaussianBlur(rng.normal(size=(rows, cols)), (0, 0), sigma_lf)
        g += noise * (undulation / max(float(noise.std()), 1e-9))
    # Soften facet boundaries to about one texel so the normal map does not alias.
    gx = np.asarray(cv2.GaussianBlur(gx.astype(np.float32), (0, 0), 0.8), dtype=np.float32)
    gy = np.asarray(cv2.GaussianBlur(gy.astype(np.float32), (0, 0), 0.8), dtype=np.float32)

    log_a = rng.uniform(math.log(cfg.roughness_min), math.log(cfg.roughness_max), size=n_seeds)
    roughness = np.exp(log_a)[cell].astype(np.float32)
    edges = (cv2.Laplacian(cell.astype(np.float32), cv2.CV_32F) != 0).astype(np.float32)
    roughness = np.clip(
        roughness + 0.15 * cv2.GaussianBlur(edges, (0, 0), 1.0), cfg.roughness_min, 1.0
    )

    reflectance = np.ones((rows, cols), np.float32)
    # Per-facet brightness jitter (layers of the blanket show through differently).
    reflectance *= (1.0 + rng.normal(0, 0.04, size=n_seeds))[cell].astype(np.float32)
    # Stains: soft darker blotches of 3-15 cm.
    stains = np.zeros((rows, cols), np.float32)
    for _ in range(rng.poisson(cfg.stains_per_m2 * area)):
        c = (int(rng.uniform(0, cols)), int(rng.uniform(0, rows)))
        ax = (
            max(1, int(rng.uniform(0.015, 0.075) / texel)),
            max(1, int(rng.uniform(0.01, 0.05) / texel)),
        )
        cv2.ellipse(
            stains, c, ax, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(0.15, 0.5)), -1
        )
    stains = np.asarray(cv2.GaussianBlur(stains, (0, 0), 0.01 / texel), dtype=np.float32)
    reflectance *= 1.0 - np.clip(stains, 0, 0.7)

    tint = np.ones((rows, cols, 3), np.float32) * np.asarray(cfg.tint_rgb, np.float32)
    # Tape seams: straight strips 2-5 cm wide, mostly along u or v, smoother and tinted.
    n_seams = rng.poisson(cfg.seams_per_m * max(width_m, height_m))
    seam_mask = np.zeros((rows, cols), np.float32)
    for _ in range(n_seams):
        width_px = max(2, int(rng.uniform(0.02, 0.05) / texel))
        theta = rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.03)
        p = np.array([rng.uniform(0, cols), rng.uniform(0, rows)])
        d = np.array([math.cos(theta), math.sin(theta)]) * 4 * max(rows, cols)
        a, b = (p - d).astype(int), (p + d).astype(int)
        cv2.line(seam_mask, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1.0, width_px)
    if n_seams:
        seam_tint = np.asarray(rng.choice([(1.15, 1.15, 1.15), (1.0, 0.78, 0.5)]), np.float32)
        tint = tint * (1 - seam_mask[..., None]) + seam_tint * seam_mask[..., None]
        roughness = roughness * (1 - seam_mask) + 0.06 * seam_mask
        gx *= 1 - 0.8 * seam_mask
        gy *= 1 - 0.8 * seam_mask

    # Labels: white rectangles with dark "text" bars; diffuse, flat.
    label_weight = np.zeros((rows, cols), np.float32)
    label_albedo = np.full((rows, cols, 3), 0.8, np.float32)
    for _ in range(rng.poisson(cfg.labels_per_m2 * area)):
        w = int(rng.uniform(0.05, 0.16) / texel)
        h = int(rng.uniform(0.03, 0.08) / texel)
        x0, y0 = int(rng.uniform(0, max(1, cols - w))), int(rng.uniform(0, max(1, rows - h)))
        label_weight[y0 : y0 + h, x0 : x0 + w] = 1.0
        bar_h = max(1, int(0.006 / texel))
        for y in range(y0 + bar_h, y0 + h - bar_h, 2 * bar_h):
            xe = x0 + bar_h + int(rng.uniform(0.3, 0.95) * (w - 2 * bar_h))
            label_albedo[y : y + bar_h, x0 + bar_h : xe] = 0.05
    gx *= 1 - label_weight
    gy *= 1 - label_weight

    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return FoilTexture(
        normal=(0.5 * normal + 0.5).astype(np.float32),
        roughness=roughness[..., None].astype(np.float32),
        reflectance=(reflectance[..., None] * tint).astype(np.float32),
        label_weight=label_weight[..., None],
        label_albedo=label_albedo,
    )


def solar_cell_texture(
    span_m: float,
    chord_m: float,
    cell_size_m: tuple[float, float],
    cell_rgb: tuple[float, float, float],
    texel_m: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Diffuse albedo (H, W, 3) of a solar wing: cells with per-cell tint, light gaps, busbars."""
    rows, cols = texture_shape(span_m, chord_m, texel_m)
    texel = span_m / cols
    cw, ch = (max(3, round(s / texel)) for s in cell_size_m)
    gap = max(1, round(0.003 / texel))
    albedo = np.empty((rows, cols, 3), np.float32)
    albedo[:] = (0.35, 0.35, 0.38)  # substrate between cells
    for y in range(0, rows, ch):
        for x in range(0, cols, cw):
            tint = np.asarray(cell_rgb, np.float32) * rng.uniform(0.8, 1.25)
            albedo[y + gap : y + ch - gap, x + gap : x + cw - gap] = tint
            for bx in (x + cw // 3, x + 2 * cw // 3):  # two thin busbars per cell
                albedo[y + gap : y + ch - gap, bx : bx + 1] = (0.45, 0.45, 0.45)
    return albedo
