"""The bracket scene family: a different triangular bracket, view and approach for every seed.

Seed 002's held-out case is a boom camera in the last metres: it sees the base strut ``P1P2``
and only the first part of the two side struts, the apex hidden behind the solar array whose
dense grid of cell lines fills much of the image, with a sun glint on it, while the camera
rolls and closes in. `bracket_draw(seed)` draws (``np.random.default_rng(seed)``) such a scene
and `render_bracket_sequence` writes it as an ordinary mono sequence folder (format v1) with
ground truth and target.yaml ``bracket: {P1, P2, P5, visible_fraction}`` plus the strut width
(``bracket_strut_width_m``), so ``satpose bracket`` runs on it unchanged.

Images are made by an exact ray caster in numpy (not Mitsuba): finite cylinders for the struts
(with spherical joints), the solar array as a plane 3 mm in front of the struts' tops whose
edge is parallel to the base at the visible fraction (so a strut passes behind it near that
fraction, where target.yaml puts its visible end, but shifted along the strut by the parallax
of the array's height above the struts, as on a real satellite: 0.7-7 px RMS per member at
960x768, `benchmarks/bracket_stub_parallax.py`), the bus wall (foil) behind, Lambertian
sun light with ambient light, a Blinn-Phong sun glint on the array, 2x2 supersampling, the
lens's radial distortion applied by casting each pixel's ray through the undistorted
coordinates, a Gaussian optics blur and shot + read noise, 8 bit. Why not Mitsuba: the
rendered satellite (`satpose.datasets.target`) has one bracket layout and no cell grid; the
family needs free bracket shapes, and exact, cheap, seeded images.

Seeds are split once, as for every family (`satpose.datasets.seed_split`): `TUNING_SEEDS` may
be looked at while developing; `VALIDATION_SEEDS` are only scored, never looked at to change a
parameter (docs/bracket.md, "Bracket family").
All ranges are module constants (``*_RANGE``).

Frames: the *bracket frame* ``B`` has ``x`` along ``P1 -> P2``, ``y`` in the bracket plane
toward the apex, ``z = x cross y`` toward the camera (``face_sign = +1``). The target frame's
origin is a point 0.3-1.2 m from the bracket (the bus centre), with its own random axes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.datasets.seed_split import seed_sets, split_of
from satpose.datasets.sequence import Bracket, Calibration, SequenceWriter, TargetGeometry

BRACKET_RANDOM_NAME = "bracket-random"
"""The name ``satpose render`` takes for this family (``--seed`` picks the member)."""


DEFAULT_FRAMES = 25
RATE_HZ = 1.0
DEFAULT_SIZE = (1280, 1024)
FOCAL_LENGTH_MM = 10.0
PIXEL_PITCH_UM = 12.0  # the paper's camera: f = 833.3 px at 1280 x 1024

# Ranges of the draw (uniform unless said otherwise).
BASE_RANGE_M = (0.3, 1.2)  # |P1P2|
APEX_ALONG_RANGE = (-0.3, 1.3)  # apex foot along the base, x |P1P2| from P1
APEX_HEIGHT_RANGE = (0.4, 1.2)  # apex height above the base, x |P1P2|
MIN_BASE_ANGLE_DEG = 25.0  # both base angles at least this (else redrawn)
STRUT_RADIUS_RANGE_M = (0.006, 0.02)
VISIBLE_FRACTION_RANGE = (0.15, 1.0)
FULL_VIEW_PROBABILITY = 0.15  # the whole triangle in view (fraction 1)
START_RANGE_M = (1.5, 2.5)  # camera to the visible part's centre at frame 0
END_RANGE_M = (0.3, 0.6)  # at the last frame (raised until the visible part fits the image)
TILT_RANGE_DEG = (0.0, 40.0)  # line of sight vs the bracket normal, frame 0
TILT_CHANGE_RANGE_DEG = (-10.0, 10.0)  # over the sequence
ROLL_RANGE_DEG = (0.0, 360.0)  # camera roll about its axis at frame 0
ROLL_CHANGE_RANGE_DEG = (-90.0, 90.0)  # camera roll over the sequence
AIM_OFFSET_RANGE = (-0.15, 0.15)  # aim point off the visible part's centre, x image size
CELL_PITCH_RANGE_M = (0.03, 0.12)  # solar cells
CELL_GAP_RANGE_M = (0.0015, 0.006)  # bright gaps between cells
ARRAY_CLEARANCE_M = 0.003  # the solar array's plane above the struts' tops
GRID_ANGLE_RANGE_DEG = (-6.0, 6.0)  # cell grid vs the array's edge
PANEL_FRAME_PROBABILITY = 0.5  # a bright frame bar along the array's edge
WALL_PROBABILITY = 0.7  # bus wall (foil) behind the bracket, else dark space
WALL_DEPTH_RANGE_M = (0.03, 0.3)
STRUT_ALBEDO_RANGE = (0.55, 0.9)
WALL_ALBEDO_RANGE = (0.08, 0.3)
CELL_ALBEDO_RANGE = (0.03, 0.1)
GAP_ALBEDO_RANGE = (0.3, 0.7)
AMBIENT_RANGE = (0.08, 0.25)  # x the sun's irradiance
GLINT_EXPONENT_RANGE = (1000.0, 8000.0)
DISTORTION_K1_RANGE = (-0.08, 0.08)  # mild radial distortion at 1280 x 1024
READ_NOISE_DN = 2.0
MARGIN_PX = 25  # the measured points stay this far inside the image


class BracketFamilyError(ConfigError):
    """A bracket-family member that cannot be drawn (a seed outside both sets, bad size)."""


@dataclass(frozen=True, kw_only=True)
class BracketScene:
    """One member of the family (all in the bracket frame ``B`` unless said otherwise).

    Attributes:
        seed: the member.
        vertices_b: (3, 3) ``P1, P2, P5`` [m].
        strut_radius_m: the struts' radius [m].
        visible_fraction: part of ``P1P5`` and ``P2P5`` visible from the base.
        target_from_b: the target frame (bus) relative to ``B``.
        camera: intrinsics and distortion at the drawn size.
        b_from_cam: (frames,) camera poses ``B_from_cam`` (camera frame OpenCV: z forward).
        t_s: (frames,) times [s].
        sun_b: unit sun direction (toward the sun) [B].
        albedo: strut, wall, cell, gap albedo.
        ambient: ambient light (x sun).
        wall_depth_m: the bus wall's distance behind the bracket plane, or None (space).
        cell_pitch_m, cell_gap_m, grid_angle_rad, grid_phase_m: the array's cell grid.
        panel_frame: a bright frame bar along the array's edge.
        glint_exponent: Blinn-Phong exponent of the array's glint.
        exposure: radiance -> digital number scale.
    """

    seed: int
    vertices_b: np.ndarray
    strut_radius_m: float
    visible_fraction: float
    target_from_b: Rigid3
    camera: PinholeCamera
    b_from_cam: tuple[Rigid3, ...]
    t_s: np.ndarray
    sun_b: np.ndarray
    albedo: tuple[float, float, float, float]
    ambient: float
    wall_depth_m: float | None
    cell_pitch_m: float
    cell_gap_m: float
    grid_angle_rad: float
    grid_phase_m: tuple[float, float]
    panel_frame: bool
    glint_exponent: float
    exposure: float

    @property
    def frames(self) -> int:
        return len(self.t_s)

    def vertices_target(self) -> np.ndarray:
        """``P1, P2, P5`` in the target frame [m] (what target.yaml holds)."""
        return self.target_from_b.apply(self.vertices_b)

    def cam_from_target(self, k: int) -> Rigid3:
        """``left_cam_from_target`` of frame ``k`` (the truth)."""
        return self.b_from_cam[k].inverse() @ self.target_from_b.inverse()

    def array_z(self) -> float:
        """``z`` of the solar array's plane [B]: ``ARRAY_CLEARANCE_M`` above the struts'
        tops (their axes lie in ``z = 0``)."""
        return self.strut_radius_m + ARRAY_CLEARANCE_M

    def panel_edge_y(self) -> float:
        """``y`` of the array's edge [B]: the struts are hidden beyond it."""
        h = float(self.vertices_b[2, 1])
        if self.visible_fraction >= 1.0:
            return h + 3 * self.strut_radius_m + 0.02
        return self.visible_fraction * h


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def family_camera(size: tuple[int, int] = DEFAULT_SIZE, k1: float = 0.0) -> PinholeCamera:
    """The paper's camera class (10 mm lens, 12 um pixels at 1280 x 1024) at ``size`` (same
    field of view), radial distortion ``k1`` (normalised radius)."""
    w, h = size
    if w < 64 or h < 64:
        raise BracketFamilyError(f"image size {w}x{h}: at least 64x64")
    f = FOCAL_LENGTH_MM / (PIXEL_PITCH_UM * 1e-3) * w / DEFAULT_SIZE[0]
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    return PinholeCamera(width=w, height=h, K=K, dist=np.array([k1, 0.0, 0.0, 0.0, 0.0]))


def _triangle(rng: np.random.Generator) -> np.ndarray:
    while True:
        base = _u(rng, BASE_RANGE_M)
        along = _u(rng, APEX_ALONG_RANGE) * base
        height = _u(rng, APEX_HEIGHT_RANGE) * base
        v = np.array([[0.0, 0.0, 0.0], [base, 0.0, 0.0], [along, height, 0.0]])
        a1 = math.degrees(math.atan2(height, along))
        a2 = math.degrees(math.atan2(height, base - along))
        if min(a1, a2) >= MIN_BASE_ANGLE_DEG:
            return v


def _look(cam_pos: np.ndarray, aim: np.ndarray, roll_rad: float, normal: np.ndarray) -> Rigid3:
    """``B_from_cam`` for a camera at ``cam_pos`` looking at ``aim``, rolled by ``roll_rad``
    about its axis from the orientation whose image ``-y`` points along the bracket's ``+y``."""
    z = aim - cam_pos
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) - normal * 0.0
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)  # columns: camera axes in B
    R = R @ rotvec_to_matrix(np.array([0.0, 0.0, roll_rad]))
    return Rigid3(R=R, t=cam_pos)


def measured_points_b(v: np.ndarray, fraction: float) -> np.ndarray:
    """``P1, P2`` and the visible strut ends ``P1 + f (P5 - P1)``, ``P2 + f (P5 - P2)`` [B]."""
    return np.array([v[0], v[1], v[0] + fraction * (v[2] - v[0]), v[1] + fraction * (v[2] - v[1])])


def _pixels(cam: PinholeCamera, cam_from_b: Rigid3, pts_b: np.ndarray) -> np.ndarray:
    pc = cam_from_b.apply(pts_b)
    if np.any(pc[:, 2] <= 1e-3):
        return np.full((len(pts_b), 2), np.nan)
    img, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return img.reshape(-1, 2)


def _fits(cam: PinholeCamera, pose: Rigid3, pts_b: np.ndarray) -> bool:
    px = _pixels(cam, pose.inverse(), pts_b)
    if not np.all(np.isfinite(px)):
        return False
    return bool(
        np.all(px[:, 0] >= MARGIN_PX)
        and np.all(px[:, 0] <= cam.width - 1 - MARGIN_PX)
        and np.all(px[:, 1] >= MARGIN_PX)
        and np.all(px[:, 1] <= cam.height - 1 - MARGIN_PX)
    )


_Motion = tuple[float, float, float, float, float, float, float, np.ndarray]


def _draw_motion(
    rng: np.random.Generator, centre: np.ndarray, normal: np.ndarray, ref: PinholeCamera
) -> _Motion:
    """``(r0, r1, tilt0, tilt1, azimuth, roll0, roll1, aim_end)`` [m, rad, image fraction]."""
    tilt0 = math.radians(_u(rng, TILT_RANGE_DEG))
    tilt1 = tilt0 + math.radians(_u(rng, TILT_CHANGE_RANGE_DEG))
    azim = _u(rng, (0.0, 2 * math.pi))
    roll0 = math.radians(_u(rng, ROLL_RANGE_DEG))
    roll1 = roll0 + math.radians(_u(rng, ROLL_CHANGE_RANGE_DEG))
    r0 = _u(rng, START_RANGE_M)
    r1 = _u(rng, END_RANGE_M)
    aim_end = np.array([_u(rng, AIM_OFFSET_RANGE), _u(rng, AIM_OFFSET_RANGE)])
    return (r0, r1, tilt0, tilt1, azim, roll0, roll1, aim_end)


def _camera_pose(
    m: _Motion, s: float, r_end: float, centre: np.ndarray, normal: np.ndarray, ref: PinholeCamera
) -> Rigid3:
    """``B_from_cam`` at the fraction ``s`` of the sequence."""
    r0, _, tilt0, tilt1, azim, roll0, roll1, aim_end = m
    tilt = (1 - s) * tilt0 + s * tilt1
    direction = np.array(
        [math.sin(tilt) * math.cos(azim), math.sin(tilt) * math.sin(azim), math.cos(tilt)]
    )
    rng_m = r0 * (r_end / r0) ** s  # geometric approach: constant closing per range
    # the aim point drifts off centre as the camera closes in (a fraction of the image)
    off = s * aim_end * rng_m * ref.width / ref.K[0, 0]
    aim = centre + np.array([off[0], off[1], 0.0])
    return _look(aim + rng_m * direction, aim, (1 - s) * roll0 + s * roll1, normal)


def bracket_draw(
    seed: int,
    frames: int = DEFAULT_FRAMES,
    size: tuple[int, int] = DEFAULT_SIZE,
    any_seed: bool = False,
) -> BracketScene:
    """The family's member ``seed`` (a function of the seed alone; ``frames`` and ``size``
    only sample it: the same draw at every size, the same motion at every frame count).

    Raises:
        BracketFamilyError: ``seed`` is in neither set (unless ``any_seed``), or bad sizes.
    """
    if not any_seed and split_of(seed) is None:
        raise BracketFamilyError(f"{BRACKET_RANDOM_NAME} seed {seed}: {seed_sets()}")
    if frames < 2:
        raise BracketFamilyError(f"frames: at least 2, got {frames}")
    rng = np.random.default_rng(seed)
    v = _triangle(rng)
    radius = _u(rng, STRUT_RADIUS_RANGE_M)
    fraction = (
        1.0
        if rng.uniform() < FULL_VIEW_PROBABILITY
        else _u(rng, (VISIBLE_FRACTION_RANGE[0], 0.6))
        if rng.uniform() < 0.7
        else _u(rng, (0.6, VISIBLE_FRACTION_RANGE[1]))
    )
    k1 = _u(rng, DISTORTION_K1_RANGE)
    cam = family_camera(size, k1)
    ref = family_camera(DEFAULT_SIZE, k1)  # the draw's checks at the family's full size
    pts = measured_points_b(v, fraction)
    if fraction >= 1.0:
        pts = np.vstack([pts, v[2]])
    centre = pts.mean(axis=0)
    normal = np.array([0.0, 0.0, 1.0])
    span = float(np.max(np.linalg.norm(pts - centre, axis=1)))
    # the motion: redrawn (from the same generator) until the measured points stay in the
    # image; the last frames' range is raised until they fit
    for _attempt in range(100):
        motion = _draw_motion(rng, centre, normal, ref)
        r_end = motion[1]
        while r_end <= motion[0] and not all(
            _fits(ref, _camera_pose(motion, s, r_end, centre, normal, ref), pts)
            for s in np.linspace(0, 1, 9)
        ):
            r_end *= 1.05
        if r_end <= motion[0]:
            break
    else:
        raise BracketFamilyError(f"seed {seed}: no motion keeps the bracket in the image")

    def pose(s: float, r_end: float) -> Rigid3:
        return _camera_pose(motion, s, r_end, centre, normal, ref)

    s_all = np.linspace(0.0, 1.0, frames)
    poses = tuple(pose(float(s), r_end) for s in s_all)
    # light: the sun on the camera's side of the bracket plane, off the line of sight
    while True:
        sun = rng.normal(size=3)
        sun[2] = abs(sun[2])
        sun /= np.linalg.norm(sun)
        if sun[2] > 0.3:
            break
    albedo = (
        _u(rng, STRUT_ALBEDO_RANGE),
        _u(rng, WALL_ALBEDO_RANGE),
        _u(rng, CELL_ALBEDO_RANGE),
        _u(rng, GAP_ALBEDO_RANGE),
    )
    ambient = _u(rng, AMBIENT_RANGE)
    wall = _u(rng, WALL_DEPTH_RANGE_M) if rng.uniform() < WALL_PROBABILITY else None
    pitch = _u(rng, CELL_PITCH_RANGE_M)
    gap = _u(rng, CELL_GAP_RANGE_M)
    grid_angle = math.radians(_u(rng, GRID_ANGLE_RANGE_DEG))
    phase = (_u(rng, (0.0, pitch)), _u(rng, (0.0, pitch)))
    panel_frame = bool(rng.uniform() < PANEL_FRAME_PROBABILITY)
    glint = _u(rng, GLINT_EXPONENT_RANGE)
    # the sun glint: turn the sun so that its mirror image on the array is seen mid-sequence
    # near a random point of the array in view
    mid = poses[frames // 2]
    edge_y = float(v[2, 1]) * (fraction if fraction < 1 else 1.0) + 0.05
    g = np.array([centre[0] + _u(rng, (-0.5, 0.5)) * span, edge_y + _u(rng, (0.05, 0.4)), 0.0])
    view = mid.t - g
    view /= np.linalg.norm(view)
    mirrored = 2 * view[2] * normal - view
    sun = mirrored + 0.05 * rng.normal(size=3)
    sun[2] = max(sun[2], 0.3)
    sun /= np.linalg.norm(sun)
    # the target (bus) frame: origin 0.3-1.2 m from the bracket, random axes
    origin = centre + np.array([_u(rng, (-0.3, 0.3)), -_u(rng, (0.3, 1.0)), -_u(rng, (0.1, 0.5))])
    target_from_b_rot = rotvec_to_matrix(rng.normal(size=3) * 1.0)
    target_from_b = Rigid3(R=target_from_b_rot, t=-target_from_b_rot @ origin)
    exposure = 200.0 / (albedo[0] * (1.0 + ambient))
    return BracketScene(
        seed=seed,
        vertices_b=v,
        strut_radius_m=radius,
        visible_fraction=fraction,
        target_from_b=target_from_b,
        camera=cam,
        b_from_cam=poses,
        t_s=np.arange(frames) / RATE_HZ,
        sun_b=sun,
        albedo=albedo,
        ambient=ambient,
        wall_depth_m=wall,
        cell_pitch_m=pitch,
        cell_gap_m=gap,
        grid_angle_rad=grid_angle,
        grid_phase_m=phase,
        panel_frame=panel_frame,
        glint_exponent=glint,
        exposure=exposure,
    )


# --------------------------------------------------------------------------------------------
# The ray caster
# --------------------------------------------------------------------------------------------


def _rays(cam: PinholeCamera, supersample: int) -> np.ndarray:
    """(H*W*s*s, 3) unit-z ray directions (camera frame) through the sub-pixel samples, the
    lens distortion undone (a distorted pixel sees the undistorted direction)."""
    key = (cam.width, cam.height, tuple(cam.K.ravel()), float(cam.dist[0]), supersample)
    if key not in _RAY_CACHE:
        _RAY_CACHE.clear()
        _RAY_CACHE[key] = _compute_rays(cam, supersample)
    return _RAY_CACHE[key]


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def _compute_rays(cam: PinholeCamera, supersample: int) -> np.ndarray:
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    xs = (np.arange(cam.width)[:, None] + off[None, :]).ravel()
    ys = (np.arange(cam.height)[:, None] + off[None, :]).ravel()
    X, Y = np.meshgrid(xs, ys)
    pts = np.stack([X.ravel(), Y.ravel()], axis=1).astype(np.float64)
    K = cam.K
    xd = np.stack([(pts[:, 0] - K[0, 2]) / K[0, 0], (pts[:, 1] - K[1, 2]) / K[1, 1]], axis=1)
    # the family's lenses are radial (k1 only): fixed-point inversion of x_d = x (1 + k1 r^2),
    # converged to < 1e-12 for |k1 r^2| < 0.2 in 60 steps (no OpenCV version dependence)
    k1 = float(cam.dist[0])
    n = xd.copy()
    for _ in range(60):
        n = xd / (1.0 + k1 * np.sum(n * n, axis=1, keepdims=True))
    return np.c_[n, np.ones(len(n))]


def _cylinder_hits(
    o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, r: float
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter of the first hit of rays ``o + t d`` with the capsule ``a-b`` of radius
    ``r`` (inf if none) and the surface normal there."""
    axis = b - a
    L = float(np.linalg.norm(axis))
    u = axis / L
    oa = o - a
    d_perp = d - np.outer(d @ u, u)
    o_perp = oa - (oa @ u) * u
    A = np.einsum("ij,ij->i", d_perp, d_perp)
    B = 2 * d_perp @ o_perp
    C = float(o_perp @ o_perp) - r * r
    disc = B * B - 4 * A * C
    t = np.full(len(d), np.inf)
    ok = (disc >= 0) & (A > 1e-12)
    tc = np.where(ok, (-B - np.sqrt(np.maximum(disc, 0))) / (2 * np.maximum(A, 1e-12)), np.inf)
    s = (oa @ u) + tc * (d @ u)
    side = ok & (tc > 0) & (s >= 0) & (s <= L)
    t[side] = tc[side]
    # spherical joints at both ends
    for c in (a, b):
        oc = o - c
        Bs = 2 * d @ oc
        As = np.einsum("ij,ij->i", d, d)
        Cs = float(oc @ oc) - r * r
        ds = Bs * Bs - 4 * As * Cs
        ts = np.where(ds >= 0, (-Bs - np.sqrt(np.maximum(ds, 0))) / (2 * As), np.inf)
        better = (ts > 0) & (ts < t)
        t[better] = ts[better]
    hit = np.isfinite(t)
    p = o + t[:, None] * d
    p[~hit] = 0.0
    sp = np.clip((p - a) @ u, 0, L)
    n = p - (a + sp[:, None] * u)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return t, n


def _near_segment(d_cam: np.ndarray, ends_cam: np.ndarray, r: float, pad: float) -> np.ndarray:
    """Rays (unit-z, camera frame) that pass within the projected capsule of radius ``r``
    around the segment ``ends_cam`` (2, 3) plus ``pad`` (normalised units); all rays when an
    end is behind the camera."""
    z = ends_cam[:, 2]
    if np.any(z <= 1e-3):
        return np.ones(len(d_cam), dtype=bool)
    a = ends_cam[0, :2] / z[0]
    b = ends_cam[1, :2] / z[1]
    ab = b - a
    L2 = float(ab @ ab)
    q = d_cam[:, :2] - a
    s = np.clip((q @ ab) / max(L2, 1e-18), 0.0, 1.0)
    dist2 = np.sum((q - s[:, None] * ab) ** 2, axis=1)
    band = r / float(z.min()) * 1.5 + pad
    return dist2 <= band * band


def render_frame(scene: BracketScene, k: int, supersample: int = 2) -> np.ndarray:
    """Frame ``k`` as an 8-bit grey image (H, W), noise seeded by ``(seed, k)``."""
    cam = scene.camera
    pose = scene.b_from_cam[k]
    d_cam = _rays(cam, supersample)
    d = d_cam @ pose.R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = pose.t
    v = scene.vertices_b
    r = scene.strut_radius_m
    sun = scene.sun_b
    n_rays = len(d)
    best_t = np.full(n_rays, np.inf)
    radiance = np.zeros(n_rays)
    a_strut, a_wall, a_cell, a_gap = scene.albedo
    amb = scene.ambient
    edge_y = scene.panel_edge_y()

    # the bus wall (or space) behind the bracket plane
    if scene.wall_depth_m is not None:
        zw = -scene.wall_depth_m
        tw = np.where(d[:, 2] < -1e-9, (zw - o[2]) / np.where(d[:, 2] < -1e-9, d[:, 2], -1), np.inf)
        tw = np.where(tw > 0, tw, np.inf)
        pw = o + np.where(np.isfinite(tw), tw, 0)[:, None] * d
        # foil: low-frequency brightness variation (no straight lines)
        mottle = 1.0 + 0.25 * np.sin(7.3 * pw[:, 0] + 2.1) * np.sin(5.1 * pw[:, 1] + 0.7)
        lw = a_wall * mottle * (max(sun[2], 0.0) + amb)
        hit = tw < best_t
        best_t[hit] = tw[hit]
        radiance[hit] = lw[hit]

    # the struts
    cam_from_b = pose.inverse()
    for i, j in ((0, 1), (0, 2), (1, 2)):
        sel = _near_segment(d_cam, cam_from_b.apply(v[[i, j]]), r, 3.0 / cam.K[0, 0])
        t_sel, n = _cylinder_hits(o, d[sel], v[i], v[j], r)
        t = np.full(n_rays, np.inf)
        t[sel] = t_sel
        hit_sel = t_sel < best_t[sel]
        idx = np.flatnonzero(sel)[hit_sel]
        n = n[hit_sel]
        lam = np.clip(n @ sun, 0.0, None)
        h = sun - d[idx]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        spec = 0.3 * np.clip(np.einsum("ij,ij->i", n, h), 0, None) ** 40
        best_t[idx] = t_sel[hit_sel]
        radiance[idx] = a_strut * (lam + amb) + spec

    # the solar array: the plane z = zp in front of the struts, beyond the edge y > edge_y
    zp = scene.array_z()
    tp = np.where(d[:, 2] < -1e-9, (zp - o[2]) / np.where(d[:, 2] < -1e-9, d[:, 2], -1), np.inf)
    tp = np.where(tp > 0, tp, np.inf)
    pp = o + np.where(np.isfinite(tp), tp, 0)[:, None] * d
    on_panel = np.isfinite(tp) & (pp[:, 1] >= edge_y)
    ca, sa = math.cos(scene.grid_angle_rad), math.sin(scene.grid_angle_rad)
    gx = ca * pp[:, 0] + sa * (pp[:, 1] - edge_y) + scene.grid_phase_m[0]
    gy = -sa * pp[:, 0] + ca * (pp[:, 1] - edge_y) + scene.grid_phase_m[1]
    pitch, gap = scene.cell_pitch_m, scene.cell_gap_m
    in_gap = (np.mod(gx, pitch) < gap) | (np.mod(gy, pitch) < gap)
    alb = np.where(in_gap, a_gap, a_cell)
    if scene.panel_frame:
        alb = np.where(pp[:, 1] - edge_y < 0.02, a_gap, alb)
    h = sun - d
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    glint = 3.0 * np.clip(h[:, 2], 0, None) ** scene.glint_exponent
    lp = alb * (max(sun[2], 0.0) + amb) + glint
    hit = on_panel & (tp < best_t)
    best_t[hit] = tp[hit]
    radiance[hit] = lp[hit]

    s = supersample
    img = radiance.reshape(cam.height, s, cam.width, s).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img * scene.exposure, (0, 0), 0.5)
    rng = np.random.default_rng([scene.seed, k, 7])
    img = img + rng.normal(size=img.shape) * np.sqrt(np.maximum(img, 0) / 4.0 + READ_NOISE_DN**2)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def target_yaml_of(scene: BracketScene) -> TargetGeometry:
    """target.yaml of a member: ``bracket`` (target frame) and the struts' width."""
    P = scene.vertices_target()
    return TargetGeometry(
        bracket=Bracket(P1=P[0], P2=P[1], P5=P[2], visible_fraction=scene.visible_fraction),
        extras={
            "bracket_strut_width_m": 2 * scene.strut_radius_m,
            "frame": "target (bus) frame; the bracket's plane is its own",
        },
    )


def render_bracket_sequence(
    seed: int,
    out: str | Path,
    *,
    frames: int = DEFAULT_FRAMES,
    size: tuple[int, int] = DEFAULT_SIZE,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
    any_seed: bool = False,
) -> Path:
    """Render member ``seed`` into the sequence folder ``out`` (format v1, mono, with truth).

    Returns:
        The sequence folder.
    """
    scene = bracket_draw(seed, frames, size, any_seed=any_seed)
    calib = Calibration(left=scene.camera)
    with SequenceWriter(
        out,
        name=f"{BRACKET_RANDOM_NAME}-{seed}",
        kind="mono",
        rate_hz=RATE_HZ,
        calibration=calib,
        target=target_yaml_of(scene),
        overwrite=overwrite,
        generator={
            "tool": "satpose-render",
            "family": BRACKET_RANDOM_NAME,
            "seed": seed,
            "split": split_of(seed),
            "renderer": "numpy ray caster (datasets/bracket_family.py)",
            "frames": frames,
            "size": list(size),
        },
    ) as writer:
        for k in range(frames):
            writer.add_frame(
                k, float(scene.t_s[k]), render_frame(scene, k), truth=scene.cam_from_target(k)
            )
            if progress is not None:
                progress(k)
    return Path(out)
