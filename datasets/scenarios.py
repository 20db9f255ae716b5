"""Typed scenario configs, the named presets, and their exact kinematics.

A scenario = target + stereo (or mono) rig + light + sensor + motion + render settings. The
motion is a torque-free-looking rigid motion: the target's rotation centre (by default the bus
centroid) moves at constant velocity in the left camera frame while the body turns at a constant
angular velocity given in the target frame:

    R(t) = R0 Exp(omega t),   c(t) = c0 + v t,   left_cam_from_target(t) = [R(t), c(t) - R(t) r]

with ``r`` the rotation centre in the target frame. Ground truth carries ``omega`` (target
frame, rad/s) and the velocity of the target-frame origin in the left camera frame,
``v - R(t) (omega x r)`` [m/s].

Presets (`PRESETS`): ``paper-docking``, ``tumble``, ``close-approach`` (stereo),
``spin-far`` (mono, seed 001's far fast spinner), ``bracket-final`` (mono, seed 002's final
approach), ``rings-check`` (``bracket-final`` with the servicer's ring target),
``calibration`` (a ChArUco board instead of the satellite, at independent poses:
`satpose.datasets.board`) and ``turntable`` (the target turning in place: the SfM check's
scene). Each scales down with `scaled` (frames, image size, samples per pixel, seed) for
tests: fewer frames keep the per-frame motion and cut the sequence short.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from satpose.datasets.board import BoardConfig
from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.datasets.sequence import Calibration
from satpose.datasets.servicer_rings import ServicerRingsConfig
from satpose.datasets.target import TargetConfig, bracket_geometry, layout

Vec3 = tuple[float, float, float]
Dist5 = tuple[float, float, float, float, float]


@dataclass(frozen=True, kw_only=True)
class RigConfig:
    """A stereo pair of pinhole cameras (the right camera sits ``baseline_m`` along +x).

    Attributes:
        width, height: image size [px].
        focal_px: focal length of the left camera [px] (square pixels: the renderer needs them).
        principal_offset_px: left principal point minus the image centre ((W-1)/2, (H-1)/2).
        right_focal_scale: right focal length / left focal length.
        right_principal_offset_px: same as ``principal_offset_px`` for the right camera.
        baseline_m: distance between the camera centres [m].
        right_rotation_deg: rotation vector of ``right_from_left`` [deg] (a real rig is never
            perfectly parallel).
        dist_left, dist_right: ``[k1, k2, p1, p2, k3]`` distortion applied to the images.
        stereo: False renders the left camera only (a mono sequence).
    """

    width: int = 1024
    height: int = 768
    focal_px: float = 1500.0
    principal_offset_px: tuple[float, float] = (6.0, -4.0)
    right_focal_scale: float = 1.002
    right_principal_offset_px: tuple[float, float] = (-3.0, 5.0)
    baseline_m: float = 0.3
    right_rotation_deg: Vec3 = (0.12, -0.35, 0.05)
    dist_left: Dist5 = (-0.06, 0.04, 2e-4, -1e-4, 0.0)
    dist_right: Dist5 = (-0.055, 0.035, -1e-4, 2e-4, 0.0)
    stereo: bool = True

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"rig image size {self.width}x{self.height} is too small")
        if self.focal_px <= 0 or self.right_focal_scale <= 0:
            raise ConfigError("rig focal lengths must be positive")
        if self.stereo and self.baseline_m <= 0:
            raise ConfigError("rig.baseline_m must be positive for a stereo rig")

    def scaled(self, width: int, height: int) -> RigConfig:
        """The same rig with another image size (same horizontal field of view)."""
        s = width / self.width
        sy = height / self.height
        return replace(
            self,
            width=width,
            height=height,
            focal_px=self.focal_px * s,
            principal_offset_px=(self.principal_offset_px[0] * s, self.principal_offset_px[1] * sy),
            right_principal_offset_px=(
                self.right_principal_offset_px[0] * s,
                self.right_principal_offset_px[1] * sy,
            ),
        )

    def calibration(self) -> Calibration:
        """The exact calibration of this rig, as written to calib.yaml."""

        def camera(f: float, off: tuple[float, float], dist: Dist5) -> PinholeCamera:
            cx = (self.width - 1) / 2 + off[0]
            cy = (self.height - 1) / 2 + off[1]
            K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
            return PinholeCamera(width=self.width, height=self.height, K=K, dist=np.array(dist))

        left = camera(self.focal_px, self.principal_offset_px, self.dist_left)
        if not self.stereo:
            return Calibration(left=left)
        right = camera(
            self.focal_px * self.right_focal_scale, self.right_principal_offset_px, self.dist_right
        )
        R = rotvec_to_matrix(np.radians(self.right_rotation_deg))
        centre = np.array([self.baseline_m, 0.0, 0.0])  # right camera centre in the left frame
        return Calibration(left=left, right=right, right_from_left=Rigid3(R=R, t=-R @ centre))


@dataclass(frozen=True, kw_only=True)
class LightConfig:
    """The single light.

    Attributes:
        kind: ``point`` (a lamp at ``position_m`` in the left camera frame, e.g. beside the
            cameras) or ``sun`` (parallel light travelling along ``direction``).
        position_m: lamp position in the left camera frame [m].
        direction: direction the sunlight travels, left camera frame (normalised on use);
            ``[0, 0, 1]`` lights the target from behind the cameras.
        intensity: lamp intensity [W/sr] or sun irradiance [W/m^2]. Only matters with
            ``sensor.exposure = fixed``.
        rotation_deg_s: rate at which the light turns about ``rotation_axis`` [deg/s]: at
            time ``t`` the sun's ``direction`` and the lamp's ``position_m`` are rotated by
            ``rotation_deg_s * t`` about that axis through the left camera centre (the light
            slowly changing direction during a long observation). 0 = a fixed light.
        rotation_axis: axis of that rotation, left camera frame (normalised on use).
        earthshine: a weak fill light, as a fraction of the sun's irradiance (sun only; 0 =
            none). Modelled as a uniform environment (Mitsuba ``constant`` emitter, hidden from
            camera rays) whose irradiance on a surface open to a full hemisphere is
            ``earthshine * intensity``: it lights every side alike, not only the side facing
            the Earth, and is seen in the reflections of polished metal.
    """

    kind: Literal["point", "sun"] = "point"
    position_m: Vec3 = (0.15, -0.12, 0.0)
    direction: Vec3 = (0.0, 0.0, 1.0)
    intensity: float = 50.0
    rotation_deg_s: float = 0.0
    rotation_axis: Vec3 = (0.0, 1.0, 0.0)
    earthshine: float = 0.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.rotation_deg_s):
            raise ConfigError(f"light.rotation_deg_s must be finite, got {self.rotation_deg_s}")
        if not 0 <= self.earthshine <= 1:
            raise ConfigError(f"light.earthshine must be in [0, 1], got {self.earthshine}")
        if self.earthshine > 0 and self.kind != "sun":
            raise ConfigError("light.earthshine needs light.kind sun")
        axis = np.asarray(self.rotation_axis, float)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise ConfigError(f"light.rotation_axis must be a non-zero 3-vector, got {axis}")

    def at(self, t_s: float) -> LightConfig:
        """The light at time ``t_s`` [s]: ``direction`` and ``position_m`` turned by
        ``rotation_deg_s * t_s`` about ``rotation_axis`` (the same object when the light
        does not turn, so fixed lights render bit-identically)."""
        if self.rotation_deg_s == 0.0:
            return self
        axis = np.asarray(self.rotation_axis, float)
        R = rotvec_to_matrix(axis / np.linalg.norm(axis) * math.radians(self.rotation_deg_s * t_s))
        d = R @ np.asarray(self.direction, float)
        p = R @ np.asarray(self.position_m, float)
        return replace(
            self,
            direction=(float(d[0]), float(d[1]), float(d[2])),
            position_m=(float(p[0]), float(p[1]), float(p[2])),
        )


@dataclass(frozen=True, kw_only=True)
class SensorConfig:
    """Image formation after the optics: exposure, noise, quantisation.

    Attributes:
        bit_depth: 8 or 16 (PNG).
        full_well_e: electrons at full scale (sets the shot noise).
        read_noise_e: Gaussian read noise [electrons].
        exposure: ``auto`` scales so that a white Lambertian surface facing the light at the
            target's distance reads ``white_level``; ``fixed`` multiplies radiance by ``gain``.
        white_level: fraction of full scale for that white surface (auto exposure).
        gain: radiance to full-scale factor (fixed exposure).
        mono: write single-channel (luminance) images instead of colour.
    """

    bit_depth: Literal[8, 16] = 8
    full_well_e: float = 12000.0
    read_noise_e: float = 8.0
    exposure: Literal["auto", "fixed"] = "auto"
    white_level: float = 0.55
    gain: float = 1.0
    mono: bool = False


@dataclass(frozen=True, kw_only=True)
class MotionConfig:
    """Rigid motion of the target relative to the left camera (see the module docstring).

    Attributes:
        start_position_m: target-frame origin (ring centre) in the left camera frame at t = 0.
        velocity_m_s: velocity of the rotation centre in the left camera frame.
        facing_tilt_deg: angle between the ring normal and the direction to the camera at t=0.
        tilt_azimuth_deg: direction of that tilt, about the optical axis.
        spin_phase_deg: initial rotation about the ring normal.
        angular_velocity_deg_s: constant angular velocity in the target frame.
        rotation_center_m: point of the target (target frame) the rotation is about; None =
            the bus centroid.
    """

    start_position_m: Vec3 = (0.15, 0.05, 7.0)
    velocity_m_s: Vec3 = (0.0, 0.0, -0.01)
    facing_tilt_deg: float = 8.0
    tilt_azimuth_deg: float = 30.0
    spin_phase_deg: float = 0.0
    angular_velocity_deg_s: Vec3 = (0.0, 0.0, 2.0)
    rotation_center_m: Vec3 | None = None


@dataclass(frozen=True, kw_only=True)
class RenderConfig:
    """Mitsuba settings.

    Attributes:
        spp: samples per pixel.
        variant: ``auto`` (LLVM if available, else scalar), ``llvm_ad_rgb`` or ``scalar_rgb``.
        max_depth: path length (2 = direct light only, 3 = one inter-reflection).
        masks: also render per-pixel object ids into masks/.
        resampling: how the pinhole canvas is resampled into the distorted image: ``linear``
            (bilinear, one canvas sample per output pixel, as every sequence before it),
            ``cubic`` (cubic spline) or ``area`` (a canvas 3x finer, resampled bilinearly at
            3 x 3 sub-pixels per output pixel and averaged: each pixel integrates its own
            distorted footprint, as a sensor does; the same samples per pixel in all).
            Bilinear resampling of a canvas of the output's resolution blurs by an amount
            that changes with the sub-pixel phase of the distortion map across the image,
            which a real lens does not (benchmarks/ring_clean_annulus.py measures what that
            does to the ring).
    """

    spp: int = 16
    variant: Literal["auto", "llvm_ad_rgb", "scalar_rgb"] = "auto"
    max_depth: int = 3
    masks: bool = True
    resampling: Literal["linear", "cubic", "area"] = "linear"

    def __post_init__(self) -> None:
        if self.spp < 1:
            raise ConfigError(f"render.spp must be >= 1, got {self.spp}")
        if self.max_depth < 2:
            raise ConfigError("render.max_depth must be >= 2 (direct light)")
        if self.resampling not in ("linear", "cubic", "area"):
            raise ConfigError(
                f"render.resampling must be linear, cubic or area, got {self.resampling!r}"
            )


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """Everything needed to render a sequence. Written to sequence.yaml as provenance.

    ``board``: a calibration board replaces the satellite and ``motion`` (see
    `satpose.datasets.board`); None renders the satellite.
    ``servicer_rings``: the servicer's concentric-ring calibration target, fixed in the left
    camera frame (`satpose.datasets.servicer_rings`); None = not in view.
    """

    name: str
    frames: int
    rate_hz: float
    seed: int = 0
    rig: RigConfig = field(default_factory=RigConfig)
    light: LightConfig = field(default_factory=LightConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    board: BoardConfig | None = None
    servicer_rings: ServicerRingsConfig | None = None

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")
        if not self.rate_hz > 0:
            raise ConfigError(f"rate_hz must be positive, got {self.rate_hz}")

    def _with_centre_at(self, position_m: tuple[float, float, float]) -> Scenario:
        """The same scenario with the start position chosen so that the rotation centre is at
        ``position_m`` in the left camera frame at t = 0."""
        r = rotation_center(self)
        start = np.asarray(position_m, float) - initial_rotation(self.motion) @ r
        motion = replace(
            self.motion, start_position_m=(float(start[0]), float(start[1]), float(start[2]))
        )
        return replace(self, motion=motion)


# --------------------------------------------------------------------------------------------
# Kinematics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Trajectory:
    """Exact ground truth of a scenario at its frame times.

    Attributes:
        t_s: (N,) frame times [s].
        left_cam_from_target: N poses.
        angular_velocity: (N, 3) target angular velocity in the target frame [rad/s].
        linear_velocity: (N, 3) velocity of the target-frame origin in the left camera frame [m/s].
    """

    t_s: np.ndarray
    left_cam_from_target: tuple[Rigid3, ...]
    angular_velocity: np.ndarray
    linear_velocity: np.ndarray


def initial_rotation(m: MotionConfig) -> np.ndarray:
    """``left_cam_from_target`` rotation at t = 0 from the facing/tilt/spin parameters."""
    facing = np.diag([1.0, -1.0, -1.0])  # target z toward the camera, target x along camera x
    az = math.radians(m.tilt_azimuth_deg)
    tilt = rotvec_to_matrix(
        np.array([math.cos(az), math.sin(az), 0.0]) * math.radians(m.facing_tilt_deg)
    )
    spin = rotvec_to_matrix(np.array([0.0, 0.0, math.radians(m.spin_phase_deg)]))
    return tilt @ facing @ spin


def rotation_center(s: Scenario) -> np.ndarray:
    """The point (target frame) the target rotates about [m]."""
    if s.motion.rotation_center_m is not None:
        return np.asarray(s.motion.rotation_center_m, float)
    lay = layout(s.target)
    return lay.target_from_panel.apply(lay.center_of_mass)


def pose_at(s: Scenario, t: float) -> tuple[Rigid3, np.ndarray, np.ndarray]:
    """``(left_cam_from_target, omega_target [rad/s], v_origin_cam [m/s])`` at time ``t`` [s]."""
    m = s.motion
    r = rotation_center(s)
    R0 = initial_rotation(m)
    omega = np.radians(np.asarray(m.angular_velocity_deg_s, float))
    v = np.asarray(m.velocity_m_s, float)
    c0 = np.asarray(m.start_position_m, float) + R0 @ r
    R = R0 @ rotvec_to_matrix(omega * t)
    trans = c0 + v * t - R @ r
    v_origin = v - R @ np.cross(omega, r)
    return Rigid3(R=R, t=trans), omega, v_origin


def trajectory(s: Scenario) -> Trajectory:
    """Ground truth at every frame time ``t_k = k / rate_hz``."""
    if s.board is not None:
        raise ConfigError(
            f"scenario {s.name!r} shows a calibration board at independent poses, not a motion; "
            "see satpose.datasets.board.board_poses"
        )
    t = np.arange(s.frames) / s.rate_hz
    poses, omegas, vels = zip(*(pose_at(s, float(tk)) for tk in t), strict=True)
    return Trajectory(
        t_s=t,
        left_cam_from_target=tuple(poses),
        angular_velocity=np.array(omegas),
        linear_velocity=np.array(vels),
    )


RIM_SAMPLES = 180  # points on the outer front edge (every 2 deg) for `rim_in_view`


def _view_limits(camera: PinholeCamera) -> tuple[float, float]:
    """Largest ``|x|`` and ``|y|`` (normalised, undistorted) of any pixel of the image."""
    W, H = camera.width, camera.height
    u = np.linspace(-0.5, W - 0.5, 64)
    v = np.linspace(-0.5, H - 0.5, 48)
    border = np.vstack(
        [
            np.c_[u, np.full_like(u, -0.5)],
            np.c_[u, np.full_like(u, H - 0.5)],
            np.c_[np.full_like(v, -0.5), v],
            np.c_[np.full_like(v, W - 0.5), v],
        ]
    )
    xy = camera.undistort_points(border)
    return float(np.max(np.abs(xy[:, 0]))), float(np.max(np.abs(xy[:, 1])))


def rim_in_view(s: Scenario, traj: Trajectory | None = None) -> np.ndarray:
    """Fraction of the ring's outer front edge inside each camera's image, per frame.

    The edge (target.yaml's ring circle, ``RIM_SAMPLES`` points) is projected through the
    calibration (distortion included) with the true pose; a point counts when it lies in
    front of the camera and inside the image (pixel centres 0 .. W-1, plus half a pixel).
    Occlusion is not modelled (nothing of the target stands in front of the rim but bolt
    heads).

    Returns:
        (N, C) fractions in [0, 1]; columns left, right (right only for stereo rigs).
    """
    traj = trajectory(s) if traj is None else traj
    calib = s.rig.calibration()
    a = np.linspace(0, 2 * math.pi, RIM_SAMPLES, endpoint=False)
    rim = s.target.ring.outer_radius_m * np.c_[np.cos(a), np.sin(a), np.zeros_like(a)]
    cams: list[tuple[PinholeCamera, Rigid3]] = [(calib.left, Rigid3.identity())]
    if calib.right is not None and calib.right_from_left is not None:
        cams.append((calib.right, calib.right_from_left))
    out = np.zeros((len(traj.left_cam_from_target), len(cams)))
    for c, (cam, cam_from_left) in enumerate(cams):
        lim_x, lim_y = _view_limits(cam)
        for k, pose in enumerate(traj.left_cam_from_target):
            p = (cam_from_left @ pose).apply(rim)
            ok = p[:, 2] > 1e-3
            xy = p[:, :2] / np.where(ok, p[:, 2], 1.0)[:, None]
            # Outside the undistorted field the polynomial model can fold back into the image.
            ok &= (np.abs(xy[:, 0]) <= lim_x) & (np.abs(xy[:, 1]) <= lim_y)
            uv = cam.normalized_to_pixels(xy)
            ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5)
            ok &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
            out[k, c] = float(np.mean(ok))
    return out


# --------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------


def paper_docking() -> Scenario:
    """Seed 000's experiment: 7 m -> 3 m at 5 cm/frame, spinning 10 deg/frame about the ring
    axis, one lamp between the cameras, stereo 1024x768, one frame every 5 s (81 frames)."""
    return Scenario(
        name="paper-docking",
        frames=81,
        rate_hz=0.2,
        motion=MotionConfig(
            start_position_m=(0.15, 0.05, 7.0),
            velocity_m_s=(0.0, 0.0, -0.01),
            facing_tilt_deg=8.0,
            tilt_azimuth_deg=30.0,
            spin_phase_deg=15.0,
            angular_velocity_deg_s=(0.0, 0.0, 2.0),
        ),
    )


def tumble() -> Scenario:
    """Constant angular velocity (1 deg/s, 2 deg per frame) about an axis 55 deg from the ring
    normal, lateral drift, sunlight 30 deg off the optical axis; 60 frames at 0.5 Hz. The
    start attitude is chosen so that the ring stays visible: the angle between the ring
    normal and the line of sight sweeps 15-41 deg."""
    cone, beta = math.radians(55.0), math.radians(328.3)
    axis = np.array(
        [math.sin(cone) * math.cos(beta), math.sin(cone) * math.sin(beta), math.cos(cone)]
    )
    wx, wy, wz = (float(x) for x in axis * 1.0)  # deg/s
    sun = (math.sin(math.radians(30)), -0.15, math.cos(math.radians(30)))
    return Scenario(
        name="tumble",
        frames=60,
        rate_hz=0.5,
        light=LightConfig(kind="sun", direction=sun, intensity=1.0),
        # Sunlit foil sends little light back at 30 deg; expose brighter than the lamp presets.
        sensor=SensorConfig(white_level=1.0),
        motion=MotionConfig(
            start_position_m=(-0.35, 0.2, 5.5),
            velocity_m_s=(0.006, -0.003, -0.004),
            facing_tilt_deg=44.4,
            tilt_azimuth_deg=264.3,
            spin_phase_deg=268.4,
            angular_velocity_deg_s=(wx, wy, wz),
        ),
    )


def close_approach() -> Scenario:
    """4 m -> 1.5 m at 5 cm/frame, spinning 5 deg/frame: panel corners and components leave
    the field of view near the end, where seed 000 switches to ORB features (51 frames)."""
    return Scenario(
        name="close-approach",
        frames=51,
        rate_hz=0.2,
        motion=MotionConfig(
            start_position_m=(0.15, 0.0, 4.0),
            velocity_m_s=(0.0, 0.0, -0.01),
            facing_tilt_deg=6.0,
            tilt_azimuth_deg=120.0,
            spin_phase_deg=-20.0,
            angular_velocity_deg_s=(0.0, 0.0, 1.0),
        ),
    )


def spin_far() -> Scenario:
    """Seed 001's case: one camera, a far target spinning fast. 60 deg/s about the ring normal
    (through the bus centroid; perpendicular to the solar wings, so the silhouette's long
    axis turns with the spin), the spin axis 35 deg from the line of sight; 60 m -> 52.5 m
    (the ~4.7 m satellite 115-135 px across); mono 1024x768 at 1 Hz for 150 s; sunlight
    30 deg off the optical axis, turning 0.1 deg/s (30 -> 45 deg over the run)."""
    sun = (math.sin(math.radians(30)), -0.15, math.cos(math.radians(30)))
    return Scenario(
        name="spin-far",
        frames=150,
        rate_hz=1.0,
        rig=RigConfig(stereo=False),
        light=LightConfig(
            kind="sun",
            direction=sun,
            intensity=1.0,
            rotation_deg_s=0.1,
            rotation_axis=(0.0, 1.0, 0.0),
        ),
        # Sunlit foil at 30 deg phase: expose like `tumble`.
        sensor=SensorConfig(white_level=1.0),
        motion=MotionConfig(
            start_position_m=(0.4, -0.25, 60.0),
            velocity_m_s=(0.005, -0.003, -0.05),
            facing_tilt_deg=35.0,
            tilt_azimuth_deg=20.0,
            spin_phase_deg=0.0,
            angular_velocity_deg_s=(0.0, 0.0, 60.0),
        ),
    )


def bracket_final() -> Scenario:
    """Seed 002's final approach on the rendered satellite: one camera 1.4 m -> 0.8 m from the
    +x solar-wing bracket, 40 deg off its normal on the wing side (so the front panel does not
    hide the base strut), spinning 0.5 deg/s about the ring axis through the bracket centroid,
    lamp beside the camera, mono 1024x768 luminance images, 1 frame/s (41 frames)."""
    target = TargetConfig()
    b = bracket_geometry(target, 1)
    centroid = (b.P1 + b.P2 + b.P5) / 3
    return Scenario(
        name="bracket-final",
        frames=41,
        rate_hz=1.0,
        rig=RigConfig(stereo=False),
        sensor=SensorConfig(mono=True),
        target=target,
        motion=MotionConfig(
            start_position_m=(0.0, 0.0, 0.0),  # replaced below: centroid on the optical axis
            velocity_m_s=(0.0, 0.0, -0.015),
            facing_tilt_deg=40.0,
            tilt_azimuth_deg=129.0,
            spin_phase_deg=0.0,
            angular_velocity_deg_s=(0.0, 0.0, 0.5),
            rotation_center_m=(float(centroid[0]), float(centroid[1]), float(centroid[2])),
        ),
    )._with_centre_at((0.03, -0.02, 1.4))


def rings_check() -> Scenario:
    """`bracket-final` with the servicer's concentric-ring calibration target in view (seed
    002, sec. 1: red rings on the servicer, in the boom camera's field of view together with
    the target): three red bands (edges 10/15, 25/30, 40/45 mm) on a grey plate 0.6 m from the
    camera in the lower-left corner of the image, tilted 50 deg; 11 frames (the first 11 s of
    the approach), colour images so that the rings look red. `satpose rings` checks the
    camera's mounting against it."""
    s = bracket_final()
    return replace(
        s,
        name="rings-check",
        frames=11,
        sensor=SensorConfig(mono=False),
        servicer_rings=ServicerRingsConfig(),
    )


def calibration() -> Scenario:
    """A ChArUco board (14 x 10 squares of 4.5 cm, `BoardConfig`) shown to the stereo rig at
    60 poses 0.5-1.2 m away, tilted 20-55 deg, evenly lit; the rig's true distortion applied;
    no masks. Truth: ``left_cam_from_board`` (board frame = target frame)."""
    return Scenario(
        name="calibration",
        frames=60,
        rate_hz=1.0,
        board=BoardConfig(),
        sensor=SensorConfig(exposure="fixed", gain=0.8),
        render=RenderConfig(masks=False),
    )


def turntable() -> Scenario:
    """A static stereo rig watching the target turn in place, the structure-from-motion check's
    scene (docs/checks.md): paper-docking's target turning 4 deg per frame about its y axis
    (plus 1 deg per frame about the ring axis), the bus centroid fixed on the optical axis
    4.5 m away; 36 frames (144 deg) at 0.2 Hz."""
    s = replace(paper_docking(), frames=36)
    m = MotionConfig(
        velocity_m_s=(0.0, 0.0, 0.0),
        facing_tilt_deg=20.0,
        tilt_azimuth_deg=90.0,
        spin_phase_deg=15.0,
        angular_velocity_deg_s=(0.0, -0.8, 0.2),
    )
    s = replace(s, name="turntable", motion=m)
    start = np.array([0.0, 0.0, 4.5]) - initial_rotation(m) @ rotation_center(s)
    return replace(s, motion=replace(m, start_position_m=tuple(start)))


PRESETS: dict[str, Callable[[], Scenario]] = {
    "paper-docking": paper_docking,
    "tumble": tumble,
    "close-approach": close_approach,
    "spin-far": spin_far,
    "bracket-final": bracket_final,
    "rings-check": rings_check,
    "calibration": calibration,
    "turntable": turntable,
}


def preset(name: str) -> Scenario:
    """The named preset scenario."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None


def scaled(
    s: Scenario,
    *,
    frames: int | None = None,
    size: tuple[int, int] | None = None,
    spp: int | None = None,
    seed: int | None = None,
) -> Scenario:
    """Scale a scenario down (or up): fewer frames (same per-frame motion), another image size
    (same field of view), other samples per pixel, another seed."""
    out = s
    if frames is not None:
        out = replace(out, frames=frames)
    if size is not None:
        out = replace(out, rig=out.rig.scaled(*size))
    if spp is not None:
        out = replace(out, render=replace(out.render, spp=spp))
    if seed is not None:
        out = replace(out, seed=seed)
    return out
