"""The randomised scene family: a different satellite and scene for every seed.

``random_scenario(seed)`` draws (``np.random.default_rng(seed)``) a target (ring radius,
wall height and thickness, a flat or rounded rim, with or without bolt heads or a lip, panel
and foil styles, components, wings, materials), a light (a lamp beside the cameras, or the
sun off axis with hard shadows and optional earthshine), lens distortion, exposure and a
motion (approach, spin or tumble) at 2-10 m, and returns an ordinary `Scenario`: it renders
through the same path as the presets and is written to sequence.yaml's
``generator.scenario``, so a sequence can be re-rendered from its file alone.

Every draw is checked geometrically over its ``DEFAULT_FRAMES`` frames before it is
returned (`rim_in_view`): the whole outer front edge in both images at frame 0, at least
80 % of it in both images in at least 90 % of the frames, the ring centre 2-10 m away, the
ring normal at most 75 deg from the line of sight, and the ring's front face lit at most
70 deg off its normal at frame 0. A motion that fails is drawn again from the same
generator, so the result is still a function of the seed. The exposure is then metered on
the ring's front plane.

The seeds are split once, for every family (`satpose.datasets.seed_split`; docs/renderer.md,
"Random family"): `TUNING_SEEDS` may be looked at while developing; `VALIDATION_SEEDS` are only
scored, never looked at to change a
parameter.

All ranges are module constants (``*_RANGE``), documented in docs/renderer.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from satpose.datasets.errors import ConfigError
from satpose.datasets.scenarios import (
    PRESETS,
    LightConfig,
    MotionConfig,
    RenderConfig,
    RigConfig,
    Scenario,
    SensorConfig,
    preset,
    rim_in_view,
    trajectory,
)
from satpose.datasets.seed_split import seed_sets
from satpose.datasets.target import (
    BusConfig,
    ComponentsConfig,
    FoilConfig,
    MetalConfig,
    PanelConfig,
    RingConfig,
    TargetConfig,
    WingsConfig,
)

RANDOM_NAME = "random"
"""The name ``satpose render`` takes for this family (``--seed`` picks the member)."""


DEFAULT_FRAMES = 30
RATE_HZ = 0.5

# Ranges of the draw (uniform unless said otherwise); docs/renderer.md tabulates them.
RING_RADIUS_RANGE_M = (0.2, 0.7)
WALL_HEIGHT_RANGE_M = (0.03, 0.15)
WALL_THICKNESS_RANGE_M = (0.012, 0.06)  # and at most 0.2 x the radius
RIM_FILLET_RANGE = (0.5, 1.0)  # x half the wall thickness (rounded rims)
LIP_WIDTH_RANGE_M = (0.008, 0.03)
LIP_THICKNESS_RANGE_M = (0.004, 0.015)  # and at most half the wall height
BOLT_COUNT_RANGE = (8, 36)
BOLT_RADIUS_RANGE_M = (0.004, 0.012)  # and at most 0.35 x the rim width
BOLT_HEIGHT_RANGE_M = (0.003, 0.01)
TILT_RANGE_DEG = (0.0, 65.0)  # ring normal vs the optical axis at frame 0
RANGE_M = (2.0, 10.0)  # ring centre distance, every frame
SUN_OFF_AXIS_RANGE_DEG = (0.0, 70.0)
EARTHSHINE_RANGE = (0.02, 0.15)  # fraction of the sun's irradiance
MAX_VIEW_ANGLE_DEG = 75.0  # ring normal vs line of sight, every frame
MIN_RIM_IN_VIEW = 0.8
MIN_FRAMES_IN_VIEW = 0.9
MAX_LIGHT_INCIDENCE_DEG = 70.0  # ring front lit at frame 0 (normal vs direction to the light)
METERED_LEVEL_LAMP = (0.35, 0.8)  # exposure: a white surface in the ring's front plane reads
METERED_LEVEL_SUN = (0.5, 1.2)  # this fraction of full scale at frame 0
MIN_METERED_COS = 0.4
FILL_LIMIT = 0.65  # ring diameter at most this fraction of the image height (sets a min range)

MotionKind = Literal["approach", "spin", "tumble"]
MOTION_KINDS: tuple[MotionKind, ...] = ("approach", "spin", "tumble")
_MAX_ATTEMPTS = 200


def named_scenario(name: str, seed: int | None) -> Scenario:
    """A preset by name, or the random family's member ``seed`` for ``name == "random"``.

    Raises:
        ConfigError: ``random`` without a seed, or an unknown name.
    """
    if name == RANDOM_NAME:
        if seed is None:
            raise ConfigError(f"render {RANDOM_NAME} needs --seed N ({seed_sets()})")
        return random_scenario(seed)
    return preset(name)


def scenario_names() -> list[str]:
    """Every name ``named_scenario`` accepts: the presets and ``random``."""
    return sorted([*PRESETS, RANDOM_NAME])


# --------------------------------------------------------------------------------------------
# The draw
# --------------------------------------------------------------------------------------------


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def _rgb(v: float) -> tuple[float, float, float]:
    return (v, v, v)


def _foil(rng: np.random.Generator, dark: bool = True) -> FoilConfig:
    """One MLI foil style: gold, silver, aluminium, amber or (if ``dark``) black Kapton."""
    style = int(rng.integers(5 if dark else 4))
    metal, tint = [
        ("Au", (1.0, 1.0, 1.0)),
        ("Ag", (0.95, 0.95, 0.97)),
        ("Al", (0.92, 0.92, 0.95)),
        ("Al", (1.0, 0.72, 0.38)),  # amber Kapton over aluminium
        ("Al", (0.08, 0.08, 0.09)),  # black Kapton
    ][style]
    rmin = _u(rng, (0.05, 0.2))
    return FoilConfig(
        metal=metal,
        tint_rgb=tint,
        roughness_min=rmin,
        roughness_max=min(1.0, rmin + _u(rng, (0.1, 0.4))),
        facet_size_m=_u(rng, (0.015, 0.06)),
        facet_tilt_deg=_u(rng, (2.0, 10.0)),
        stains_per_m2=_u(rng, (0.0, 8.0)),
        seams_per_m=_u(rng, (0.0, 3.0)),
        labels_per_m2=_u(rng, (0.0, 3.0)),
    )


def _ring_material(rng: np.random.Generator) -> MetalConfig:
    """Polished or machined metal, anodised (dyed) or painted."""
    kind = int(rng.integers(4))
    if kind == 0:  # polished
        return MetalConfig(roughness=_u(rng, (0.02, 0.08)), diffuse_fraction=_u(rng, (0.0, 0.1)))
    if kind == 1:  # machined / bead-blasted
        return MetalConfig(
            roughness=_u(rng, (0.15, 0.4)),
            diffuse_fraction=_u(rng, (0.2, 0.5)),
            diffuse_rgb=_rgb(_u(rng, (0.6, 0.85))),
        )
    if kind == 2:  # anodised: black, grey, blue or gold dye
        colour = [(0.03, 0.03, 0.035), (0.12, 0.12, 0.13), (0.05, 0.1, 0.3), (0.5, 0.36, 0.1)][
            int(rng.integers(4))
        ]
        return MetalConfig(finish="anodised", roughness=_u(rng, (0.1, 0.35)), diffuse_rgb=colour)
    return MetalConfig(finish="painted", diffuse_rgb=_rgb(_u(rng, (0.45, 0.88))))


RimStyle = Literal["flat", "rounded", "lip"]


def _is_dark(m: MetalConfig) -> bool:
    return m.finish == "anodised" and max(m.diffuse_rgb) < 0.2


def _ring(rng: np.random.Generator) -> RingConfig:
    r = _u(rng, RING_RADIUS_RANGE_M)
    h = _u(rng, WALL_HEIGHT_RANGE_M)
    t = float(rng.uniform(WALL_THICKNESS_RANGE_M[0], min(WALL_THICKNESS_RANGE_M[1], 0.2 * r)))
    rim: RimStyle = ("flat", "rounded", "lip")[int(rng.choice(3, p=[0.4, 0.3, 0.3]))]
    fillet = lip_w = lip_t = 0.0
    if rim == "rounded":
        fillet = min(_u(rng, RIM_FILLET_RANGE) * t / 2, 0.8 * h)
    elif rim == "lip":
        lip_w = _u(rng, LIP_WIDTH_RANGE_M)
        lip_t = float(rng.uniform(LIP_THICKNESS_RANGE_M[0], min(LIP_THICKNESS_RANGE_M[1], h / 2)))
    wall_outer = r - lip_w
    inner = wall_outer - t
    material = _ring_material(rng)
    bolts, bolt_r, bolt_h = 0, 0.006, 0.005
    if rim != "rounded" and rng.random() < 0.5:
        bolt_r = float(rng.uniform(BOLT_RADIUS_RANGE_M[0], min(BOLT_RADIUS_RANGE_M[1], 0.35 * t)))
        bolt_h = _u(rng, BOLT_HEIGHT_RANGE_M)
        circle = 0.5 * (inner + wall_outer)
        # Heads at least one head diameter apart.
        most = int(math.pi * circle / (2 * bolt_r))
        bolts = int(rng.integers(BOLT_COUNT_RANGE[0], min(BOLT_COUNT_RANGE[1], most) + 1))
    wall_foil = _foil(rng) if rng.random() < 0.25 else None
    return RingConfig(
        outer_radius_m=r,
        inner_radius_m=inner,
        height_m=h,
        center_offset_m=(0.0, 0.0),  # set with the panel
        material=material,
        rim_fillet_m=fillet,
        lip_width_m=lip_w,
        lip_thickness_m=lip_t,
        bolts=bolts,
        bolt_radius_m=bolt_r,
        bolt_height_m=bolt_h,
        wall_foil=wall_foil,
    )


def _target(rng: np.random.Generator) -> TargetConfig:
    ring = _ring(rng)
    r = ring.outer_radius_m
    ox, oy = _u(rng, (-0.08, 0.08)), _u(rng, (-0.08, 0.08))
    hw = r + abs(ox) + _u(rng, (0.06, 0.4))
    hh = r + abs(oy) + _u(rng, (0.06, 0.3))
    paint = (
        MetalConfig(finish="painted", diffuse_rgb=_rgb(_u(rng, (0.6, 0.9))))
        if rng.random() < 0.3
        else None
    )
    panel = PanelConfig(
        width_m=2 * hw,
        height_m=2 * hh,
        thickness_m=_u(rng, (0.015, 0.04)),
        # A dark anodised ring stays visible: no black Kapton behind it.
        foil=_foil(rng, dark=not _is_dark(ring.material)),
        corner0=int(rng.integers(4)),
        paint=paint,
    )
    bus = BusConfig(
        width_m=2 * hw - _u(rng, (0.0, 0.15)),
        height_m=2 * hh - _u(rng, (0.0, 0.15)),
        depth_m=_u(rng, (0.5, 1.4)),
        foil=_foil(rng),
    )
    comp_r = _u(rng, (0.02, 0.06))
    positions: list[tuple[float, float]] = []
    n_comp = int(rng.integers(0, 9))
    for _ in range(50 * n_comp):
        if len(positions) == n_comp:
            break
        x = _u(rng, (-hw + comp_r, hw - comp_r))
        y = _u(rng, (-hh + comp_r, hh - comp_r))
        if math.hypot(x - ox, y - oy) < r + comp_r + 0.02:
            continue
        if any(math.hypot(x - a, y - b) < 2 * comp_r + 0.02 for a, b in positions):
            continue
        positions.append((x, y))
    components = ComponentsConfig(
        positions_m=tuple(positions),
        radius_m=comp_r,
        height_m=_u(rng, (0.01, 0.06)),
        albedo=_u(rng, (0.02, 0.25)),
        roughness=_u(rng, (0.15, 0.5)),
    )
    wings = WingsConfig(
        enabled=bool(rng.random() < 0.75),
        bracket_base_m=min(_u(rng, (0.3, 0.6)), 0.8 * bus.height_m),
        bracket_height_m=_u(rng, (0.25, 0.5)),
        span_m=_u(rng, (0.8, 2.2)),
        chord_m=_u(rng, (0.4, 0.9)),
    )
    ring = replace(ring, center_offset_m=(ox, oy))
    return TargetConfig(bus=bus, panel=panel, ring=ring, components=components, wings=wings)


def _light(rng: np.random.Generator) -> tuple[LightConfig, SensorConfig]:
    if rng.random() < 0.4:  # a lamp beside the cameras
        pos = (
            float(rng.choice([-1, 1]) * rng.uniform(0.08, 0.4)),
            float(rng.choice([-1, 1]) * rng.uniform(0.05, 0.3)),
            _u(rng, (-0.1, 0.05)),
        )
        return LightConfig(kind="point", position_m=pos), SensorConfig(
            white_level=_u(rng, METERED_LEVEL_LAMP)
        )
    light = LightConfig(
        kind="sun",
        direction=_sun_direction(rng),
        intensity=1.0,
        earthshine=_u(rng, EARTHSHINE_RANGE) if rng.random() < 0.5 else 0.0,
    )
    return light, SensorConfig(white_level=_u(rng, METERED_LEVEL_SUN))


def _sun_direction(rng: np.random.Generator) -> tuple[float, float, float]:
    """Direction the sunlight travels (left camera frame): ``off_axis`` from the optical axis
    (0 = the sun behind the cameras)."""
    off = math.radians(_u(rng, SUN_OFF_AXIS_RANGE_DEG))
    az = _u(rng, (0.0, 2 * math.pi))
    return (math.sin(off) * math.cos(az), math.sin(off) * math.sin(az), math.cos(off))


def _rig(rng: np.random.Generator) -> RigConfig:
    k1, k2 = _u(rng, (-0.15, 0.05)), _u(rng, (-0.05, 0.08))
    p1, p2 = _u(rng, (-8e-4, 8e-4)), _u(rng, (-8e-4, 8e-4))

    def jitter(v: float, amount: float) -> float:
        return v + _u(rng, (-amount, amount))

    left = (k1, k2, p1, p2, 0.0)
    right = (jitter(k1, 0.01), jitter(k2, 0.01), jitter(p1, 2e-4), jitter(p2, 2e-4), 0.0)
    return RigConfig(dist_left=left, dist_right=right)


def _motion(
    rng: np.random.Generator, s: Scenario, kind: MotionKind, min_range_m: float
) -> MotionConfig:
    """One motion of ``kind`` with the ring centre ``min_range_m``-10 m away."""
    T = (DEFAULT_FRAMES - 1) / RATE_HZ  # duration of the default sequence [s]
    calib = s.rig.calibration()
    # Ring centre at frame 0: a random direction within the central part of the image.
    half_x = (calib.left.width / 2) / calib.left.fx
    half_y = (calib.left.height / 2) / calib.left.fy
    direction = np.array([_u(rng, (-0.5, 0.5)) * half_x, _u(rng, (-0.5, 0.5)) * half_y, 1.0])
    direction /= np.linalg.norm(direction)
    tilt = _u(rng, TILT_RANGE_DEG)
    tilt_az = _u(rng, (0.0, 360.0))
    phase = _u(rng, (0.0, 360.0))
    lo, hi = min_range_m, RANGE_M[1]
    lateral = np.array([_u(rng, (-0.004, 0.004)), _u(rng, (-0.004, 0.004)), 0.0])  # m/s
    if kind == "approach":  # closes at least 0.5 m over the default sequence
        r0 = _u(rng, (min(lo + 0.5, hi), hi))
        r1 = _u(rng, (lo, max(lo, r0 - 0.5)))
        velocity = direction * (r1 - r0) / T + lateral
        omega = np.array([0.0, 0.0, _u(rng, (-4.0, 4.0)) * RATE_HZ])
    elif kind == "spin":  # about the ring normal (through the bus centroid)
        r0 = _u(rng, (lo, hi))
        velocity = direction * _u(rng, (-0.004, 0.004)) + lateral
        rate = _u(rng, (2.0, 12.0)) * float(rng.choice([-1, 1]))  # deg/frame
        omega = np.array([0.0, 0.0, rate * RATE_HZ])
    else:  # tumble: about an axis 20-90 deg from the ring normal
        r0 = _u(rng, (lo, hi))
        velocity = direction * _u(rng, (-0.004, 0.004)) + lateral
        cone = math.radians(_u(rng, (20.0, 90.0)))
        beta = _u(rng, (0.0, 2 * math.pi))
        axis = np.array(
            [math.sin(cone) * math.cos(beta), math.sin(cone) * math.sin(beta), math.cos(cone)]
        )
        omega = axis * _u(rng, (0.5, 3.0)) * RATE_HZ  # deg/s
    start = direction * r0
    return MotionConfig(
        start_position_m=(float(start[0]), float(start[1]), float(start[2])),
        velocity_m_s=(float(velocity[0]), float(velocity[1]), float(velocity[2])),
        facing_tilt_deg=tilt,
        tilt_azimuth_deg=tilt_az,
        spin_phase_deg=phase,
        angular_velocity_deg_s=(float(omega[0]), float(omega[1]), float(omega[2])),
    )


def min_range_m(ring_radius_m: float, rig: RigConfig) -> float:
    """Nearest ring-centre distance of the draw: the ring's diameter fills at most
    ``FILL_LIMIT`` of the image height, and never nearer than ``RANGE_M[0]``."""
    calib = rig.calibration()
    return max(RANGE_M[0], 2 * ring_radius_m * calib.left.fy / (FILL_LIMIT * rig.height))


@dataclass(frozen=True, kw_only=True)
class Validity:
    """The geometric checks of a drawn scenario over its frames.

    Attributes:
        rim_in_view: (N, C) fraction of the outer front edge inside each image.
        range_m: (N,) distance of the ring centre from the left camera.
        view_angle_deg: (N,) angle between the ring normal and the line of sight to it.
        light_incidence_deg: (N,) angle between the ring normal and the direction from the
            ring centre to the light (the lamp, or the sun).
    """

    rim_in_view: np.ndarray
    range_m: np.ndarray
    view_angle_deg: np.ndarray
    light_incidence_deg: np.ndarray

    def problems(self) -> list[str]:
        """Why the scenario is refused (empty: it is fine)."""
        out = []
        if np.any(self.rim_in_view[0] < 1.0):
            out.append("ring not wholly in view at frame 0")
        good = np.all(self.rim_in_view >= MIN_RIM_IN_VIEW, axis=1)
        if np.mean(good) < MIN_FRAMES_IN_VIEW:
            out.append(f"ring in view in only {np.mean(good):.0%} of the frames")
        if np.any(self.range_m < RANGE_M[0] - 1e-9) or np.any(self.range_m > RANGE_M[1] + 1e-9):
            out.append("range leaves 2-10 m")
        if np.any(self.view_angle_deg > MAX_VIEW_ANGLE_DEG):
            out.append("ring seen too obliquely")
        if self.light_incidence_deg[0] > MAX_LIGHT_INCIDENCE_DEG:
            out.append("ring front lit too obliquely at frame 0")
        return out


def validity(s: Scenario) -> Validity:
    """The geometric checks of a scenario over its frames (`Validity`)."""
    traj = trajectory(s)
    ranges, views, lights = [], [], []
    for k, pose in enumerate(traj.left_cam_from_target):
        n = pose.R[:, 2]  # ring normal in the left camera frame
        ranges.append(float(np.linalg.norm(pose.t)))
        views.append(_angle_deg(n, -pose.t))
        lc = s.light.at(float(traj.t_s[k]))
        if lc.kind == "sun":
            lights.append(_angle_deg(n, -np.asarray(lc.direction, float)))
        else:
            lights.append(_angle_deg(n, np.asarray(lc.position_m, float) - pose.t))
    return Validity(
        rim_in_view=rim_in_view(s, traj),
        range_m=np.array(ranges),
        view_angle_deg=np.array(views),
        light_incidence_deg=np.array(lights),
    )


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def metered(s: Scenario, light_incidence_deg: float) -> Scenario:
    """Meter the exposure on the ring's front plane: ``sensor.white_level`` (drawn as the
    level a white Lambertian surface there should read) divided by the cosine of the
    light's incidence on it at frame 0 (at least ``MIN_METERED_COS``); the sensor's auto
    exposure refers to a surface facing the light."""
    cos_i = max(math.cos(math.radians(light_incidence_deg)), MIN_METERED_COS)
    return replace(s, sensor=replace(s.sensor, white_level=s.sensor.white_level / cos_i))


@dataclass(frozen=True, kw_only=True)
class RandomDraw:
    """A member of the family with the labels of its discrete choices.

    Attributes:
        scenario: what to render.
        motion: ``approach``, ``spin`` or ``tumble``.
        rim: ``flat``, ``rounded`` or ``lip``.
        light: ``lamp`` or ``sun``.
        attempts: motions drawn until one passed the checks (1 = the first).
    """

    scenario: Scenario
    motion: MotionKind
    rim: RimStyle
    light: Literal["lamp", "sun"]
    attempts: int


def random_draw(seed: int) -> RandomDraw:
    """The random family's member ``seed`` with its labels (deterministic per seed).

    ``DEFAULT_FRAMES`` frames at ``RATE_HZ``; `scaled` cuts it short like every preset. The
    texture and noise seed of the scenario is ``seed`` too. The target, lamp, exposure and
    lens are drawn once; the motion (and a sun's direction) is drawn until the scenario
    passes `Validity`.

    Raises:
        ConfigError: a negative seed; no valid motion in ``_MAX_ATTEMPTS`` draws.
    """
    if seed < 0:
        raise ConfigError(f"random scenario seeds are >= 0, got {seed}")
    rng = np.random.default_rng(seed)
    target = _target(rng)
    light, sensor = _light(rng)
    rig = _rig(rng)
    kind = MOTION_KINDS[int(rng.integers(len(MOTION_KINDS)))]
    base = Scenario(
        name=f"{RANDOM_NAME}-{seed}",
        frames=DEFAULT_FRAMES,
        rate_hz=RATE_HZ,
        seed=seed,
        rig=rig,
        light=light,
        sensor=sensor,
        target=target,
        # each pixel integrates its distorted footprint (benchmarks/ring_clean_annulus.py)
        render=RenderConfig(resampling="area"),
    )
    r = target.ring
    rim: RimStyle = "rounded" if r.rim_fillet_m > 0 else "lip" if r.lip_width_m > 0 else "flat"
    lo = min_range_m(r.outer_radius_m, rig)
    for attempt in range(1, _MAX_ATTEMPTS + 1):
        s = replace(base, motion=_motion(rng, base, kind, lo))
        if light.kind == "sun" and attempt > 1:
            s = replace(s, light=replace(light, direction=_sun_direction(rng)))
        v = validity(s)
        if not v.problems():
            return RandomDraw(
                scenario=metered(s, float(v.light_incidence_deg[0])),
                motion=kind,
                rim=rim,
                light="sun" if light.kind == "sun" else "lamp",
                attempts=attempt,
            )
    raise ConfigError(f"random scenario {seed}: no valid motion in {_MAX_ATTEMPTS} draws")


def random_scenario(seed: int) -> Scenario:
    """The random family's member ``seed`` (`random_draw` without the labels)."""
    return random_draw(seed).scenario
