"""A procedural satellite: typed configuration and its geometry in the target frame.

The target is a box bus wrapped in MLI foil, a rectangular front panel (its four corners are
the paper's panel landmarks), a metallic docking ring with height on the panel, small dark
cylindrical components on the panel, and two solar wings on triangular brackets.

Frames:
- panel frame ``P``: origin at the centre of the ring's outer front edge, x along the panel
  width, y along the panel height, z along the ring normal, out of the front face. The scene
  is laid out in P.
- target frame ``T`` (the sequence format's body frame): same origin and z as P, x in the ring
  plane toward panel corner 0. ``target_from_panel`` is a rotation about z.

All lengths are metres. Geometry written to target.yaml is in T.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.datasets.sequence import Bracket, Ring, TargetGeometry

MASK_IDS = {
    "background": 0,
    "bus": 1,
    "panel": 2,
    "ring": 3,
    "components": 4,
    "brackets": 5,
    "wings": 6,
}
"""Object ids written to masks/ (uint8). Also written to target.yaml under ``mask_ids``."""

RGB = tuple[float, float, float]


@dataclass(frozen=True, kw_only=True)
class FoilConfig:
    """Crinkled multi-layer-insulation foil (a rough conductor with a normal map).

    Attributes:
        metal: Mitsuba conductor name of the coating: ``Au`` (gold Kapton look), ``Ag``, ``Al``.
        tint_rgb: multiplies the specular reflectance (e.g. amber Kapton over aluminium).
        roughness_min, roughness_max: range of the GGX roughness ``alpha`` across facets.
        facet_size_m: typical size of a crinkle facet.
        facet_tilt_deg: standard deviation of a facet's normal tilt.
        texel_m: texture resolution on the surface.
        stains_per_m2, seams_per_m, labels_per_m2: density of brightness variations.
    """

    metal: str = "Au"
    tint_rgb: RGB = (1.0, 1.0, 1.0)
    roughness_min: float = 0.12
    roughness_max: float = 0.45
    facet_size_m: float = 0.03
    facet_tilt_deg: float = 6.0
    texel_m: float = 0.002
    stains_per_m2: float = 4.0
    seams_per_m: float = 1.5
    labels_per_m2: float = 1.5

    def __post_init__(self) -> None:
        if not 0 < self.roughness_min <= self.roughness_max <= 1:
            raise ConfigError("foil roughness must satisfy 0 < roughness_min <= roughness_max <= 1")
        if self.texel_m <= 0 or self.facet_size_m <= 0:
            raise ConfigError("foil texel_m and facet_size_m must be positive")


Finish = Literal["metal", "painted", "anodised"]


@dataclass(frozen=True, kw_only=True)
class MetalConfig:
    """A solid (non-foil) surface finish; by default a machined metal part.

    Attributes:
        finish: ``metal``: a blend of a rough conductor and a diffuse coat (polished metal is
            a low ``roughness`` and a low ``diffuse_fraction``); ``painted``: Lambertian
            paint of albedo ``diffuse_rgb`` (``metal``, ``roughness`` and
            ``diffuse_fraction`` unused); ``anodised``: a dyed oxide layer, modelled as a
            rough dielectric coat (GGX ``roughness``, IOR 1.5) over a diffuse base of albedo
            ``diffuse_rgb`` (``metal`` and ``diffuse_fraction`` unused).
        metal: Mitsuba conductor name.
        roughness: GGX alpha of the conductor (or of the anodised coat).
        diffuse_fraction: weight of the diffuse layer in [0, 1].
        diffuse_rgb: albedo of the diffuse layer (of the paint, of the anodised base).
    """

    finish: Finish = "metal"
    metal: str = "Al"
    roughness: float = 0.25
    diffuse_fraction: float = 0.35
    diffuse_rgb: RGB = (0.75, 0.75, 0.75)

    def __post_init__(self) -> None:
        if not 0 < self.roughness <= 1:
            raise ConfigError(f"material roughness must be in (0, 1], got {self.roughness}")
        if not 0 <= self.diffuse_fraction <= 1:
            raise ConfigError(
                f"material diffuse_fraction must be in [0, 1], got {self.diffuse_fraction}"
            )
        if not all(0 <= c <= 1 for c in self.diffuse_rgb):
            raise ConfigError(f"material diffuse_rgb must be in [0, 1], got {self.diffuse_rgb}")


@dataclass(frozen=True, kw_only=True)
class BusConfig:
    """The box body behind the front panel."""

    width_m: float = 1.0
    height_m: float = 0.8
    depth_m: float = 0.9
    foil: FoilConfig = field(default_factory=FoilConfig)


@dataclass(frozen=True, kw_only=True)
class PanelConfig:
    """The rectangular front panel (a plate on the bus's front face).

    Its four front corners are the panel landmarks. ``corner0`` names which corner defines the
    target x axis: index into (+x+y, -x+y, -x-y, +x-y) of the panel frame. ``paint``: a solid
    finish (e.g. white paint) for the front face instead of ``foil``; None = foil.
    """

    width_m: float = 1.1
    height_m: float = 0.9
    thickness_m: float = 0.02
    foil: FoilConfig = field(
        default_factory=lambda: FoilConfig(metal="Al", tint_rgb=(0.92, 0.92, 0.95))
    )
    corner0: int = 0
    paint: MetalConfig | None = None


@dataclass(frozen=True, kw_only=True)
class RingConfig:
    """The docking ring: a wall of height ``height_m`` between two radii, on the panel.

    The target-frame origin is the centre of the ring's outer front edge: the circle of radius
    ``outer_radius_m`` in the plane z = 0 (the ring's front-most plane, bolt heads aside).

    Attributes:
        outer_radius_m: radius of the outer front edge (target.yaml's ring radius) [m].
        inner_radius_m: radius of the inner wall [m].
        height_m: from the panel's front face to the front plane z = 0 [m].
        center_offset_m: ring centre relative to the panel centre (panel frame x, y).
        material: finish of the ring (rim, walls, lip).
        rim_fillet_m: 0 = a flat front rim with sharp edges; > 0 rounds both front edges with
            this radius (at most half the wall thickness: a half-round rim). The outer front
            edge of a rounded rim is then the corner of its envelope: radius
            ``outer_radius_m`` in the plane z = 0, where a sharp rim would have its edge.
        lip_width_m, lip_thickness_m: an outward lip (flange) at the front: the front annulus
            reaches ``outer_radius_m`` while the outer wall below the lip has radius
            ``outer_radius_m - lip_width_m``; the lip is ``lip_thickness_m`` thick. 0 = no lip.
        bolts: number of bolt heads on the front face, evenly spaced on the circle midway
            between ``inner_radius_m`` and the outer wall (0 = none).
        bolt_radius_m, bolt_height_m: bolt-head cylinders standing on the front face (they
            reach ``bolt_height_m`` in front of the plane z = 0).
        bolt_material: finish of the bolt heads.
        wall_foil: MLI foil wrapped around the outer wall (the rim stays ``material``); None =
            the wall has the ring's material.
    """

    outer_radius_m: float = 0.30
    inner_radius_m: float = 0.26
    height_m: float = 0.10
    center_offset_m: tuple[float, float] = (0.0, 0.0)
    material: MetalConfig = field(default_factory=MetalConfig)
    rim_fillet_m: float = 0.0
    lip_width_m: float = 0.0
    lip_thickness_m: float = 0.0
    bolts: int = 0
    bolt_radius_m: float = 0.006
    bolt_height_m: float = 0.005
    bolt_material: MetalConfig = field(
        default_factory=lambda: MetalConfig(metal="Cr", roughness=0.2, diffuse_fraction=0.3)
    )
    wall_foil: FoilConfig | None = None

    @property
    def wall_outer_radius_m(self) -> float:
        """Radius of the outer wall (below the lip, if any) [m]."""
        return self.outer_radius_m - self.lip_width_m

    @property
    def bolt_circle_radius_m(self) -> float:
        """Radius of the circle through the bolt-head centres [m]."""
        return 0.5 * (self.inner_radius_m + self.wall_outer_radius_m)


@dataclass(frozen=True, kw_only=True)
class ComponentsConfig:
    """Small dark cylinders on the panel (positions relative to the panel centre, panel x, y)."""

    positions_m: tuple[tuple[float, float], ...] = (
        (0.43, 0.33),
        (-0.44, 0.31),
        (-0.42, -0.34),
        (0.40, -0.30),
        (0.02, 0.395),
        (-0.47, 0.0),
    )
    radius_m: float = 0.035
    height_m: float = 0.03
    albedo: float = 0.03
    roughness: float = 0.3


@dataclass(frozen=True, kw_only=True)
class WingsConfig:
    """Two solar wings, each on a triangular bracket on a side face (+x and -x of the bus).

    The bracket lies in a plane parallel to the panel at mid-depth of the bus: base P1P2 on the
    side face along y, apex P5 ``bracket_height_m`` out along x. The wing (cells facing +z)
    starts ``gap_m`` beyond the apex. ``nx_span_m`` gives the -x wing its own span (an
    asymmetric outline; None: both wings ``span_m``).
    """

    enabled: bool = True
    bracket_base_m: float = 0.5
    bracket_height_m: float = 0.45
    strut_radius_m: float = 0.015
    gap_m: float = 0.08
    span_m: float = 1.3
    nx_span_m: float | None = None
    chord_m: float = 0.7
    thickness_m: float = 0.03
    cell_size_m: tuple[float, float] = (0.08, 0.05)
    cell_rgb: RGB = (0.025, 0.035, 0.09)
    strut_material: MetalConfig = field(
        default_factory=lambda: MetalConfig(
            metal="Al", roughness=0.4, diffuse_fraction=0.7, diffuse_rgb=(0.8, 0.8, 0.8)
        )
    )


@dataclass(frozen=True, kw_only=True)
class TargetConfig:
    """Everything that shapes the satellite. Other satellites are one config away."""

    bus: BusConfig = field(default_factory=BusConfig)
    panel: PanelConfig = field(default_factory=PanelConfig)
    ring: RingConfig = field(default_factory=RingConfig)
    components: ComponentsConfig = field(default_factory=ComponentsConfig)
    wings: WingsConfig = field(default_factory=WingsConfig)

    def __post_init__(self) -> None:
        r = self.ring
        if not 0 < r.inner_radius_m < r.outer_radius_m:
            raise ConfigError("ring: need 0 < inner_radius_m < outer_radius_m")
        if r.height_m <= 0:
            raise ConfigError("ring.height_m must be positive")
        _check_ring_shape(r)
        if self.wings.nx_span_m is not None and not self.wings.nx_span_m > 0:
            raise ConfigError("wings.nx_span_m must be positive (or null: span_m)")
        ox, oy = r.center_offset_m
        if (
            abs(ox) + r.outer_radius_m > self.panel.width_m / 2
            or abs(oy) + r.outer_radius_m > self.panel.height_m / 2
        ):
            raise ConfigError("ring does not fit on the panel (outer radius + offset > half size)")
        for i, (x, y) in enumerate(self.components.positions_m):
            if abs(x) > self.panel.width_m / 2 or abs(y) > self.panel.height_m / 2:
                raise ConfigError(f"components.positions_m[{i}] lies off the panel")
            if math.hypot(x - ox, y - oy) < r.outer_radius_m + self.components.radius_m:
                raise ConfigError(f"components.positions_m[{i}] overlaps the ring")
        if self.panel.corner0 not in range(4):
            raise ConfigError("panel.corner0 must be 0, 1, 2 or 3")


def _check_ring_shape(r: RingConfig) -> None:
    """Rim, lip and bolt parameters that make a buildable ring (radii already checked)."""
    if r.lip_width_m < 0 or r.lip_thickness_m < 0 or r.rim_fillet_m < 0:
        raise ConfigError("ring: rim_fillet_m, lip_width_m and lip_thickness_m must be >= 0")
    if (r.lip_width_m > 0) != (r.lip_thickness_m > 0):
        raise ConfigError("ring: a lip needs both lip_width_m and lip_thickness_m > 0")
    if r.lip_width_m > 0:
        if r.wall_outer_radius_m <= r.inner_radius_m:
            raise ConfigError("ring: the lip is wider than the wall (lip_width_m too large)")
        if r.lip_thickness_m >= r.height_m:
            raise ConfigError("ring: lip_thickness_m must be less than height_m")
        if r.rim_fillet_m > 0:
            raise ConfigError("ring: a rounded rim (rim_fillet_m) with a lip is not supported")
    if r.rim_fillet_m > 0.5 * (r.outer_radius_m - r.inner_radius_m) + 1e-12:
        raise ConfigError("ring: rim_fillet_m must be at most half the wall thickness")
    if r.rim_fillet_m >= r.height_m:
        raise ConfigError("ring: rim_fillet_m must be less than height_m")
    if r.bolts < 0:
        raise ConfigError(f"ring.bolts must be >= 0, got {r.bolts}")
    if r.bolts > 0:
        if r.bolt_radius_m <= 0 or r.bolt_height_m <= 0:
            raise ConfigError("ring: bolt_radius_m and bolt_height_m must be positive")
        if 2 * r.bolt_radius_m > r.wall_outer_radius_m - r.inner_radius_m:
            raise ConfigError("ring: bolt heads are wider than the wall")
        spacing = 2 * r.bolt_circle_radius_m * math.sin(math.pi / r.bolts)
        if r.bolts > 1 and spacing <= 2 * r.bolt_radius_m:
            raise ConfigError("ring: bolt heads overlap (too many bolts or too large)")


# --------------------------------------------------------------------------------------------
# Derived geometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class TargetLayout:
    """Key heights and positions of the target in the panel frame P (derived, not configured).

    Attributes:
        panel_front_z: z of the panel's front surface (= -ring height).
        panel_center: (3,) panel front-surface centre.
        bus_front_z, bus_back_z: z of the bus box's front and back faces.
        center_of_mass: (3,) centroid of the bus box (the default rotation centre).
        target_from_panel: rotation about z taking P to the target frame T.
    """

    panel_front_z: float
    panel_center: np.ndarray
    bus_front_z: float
    bus_back_z: float
    center_of_mass: np.ndarray
    target_from_panel: Rigid3


def layout(cfg: TargetConfig) -> TargetLayout:
    """Derive the panel-frame layout of a target config."""
    ox, oy = cfg.ring.center_offset_m
    zf = -cfg.ring.height_m
    center = np.array([-ox, -oy, zf])
    bus_front = zf - cfg.panel.thickness_m
    bus_back = bus_front - cfg.bus.depth_m
    com = np.array([-ox, -oy, 0.5 * (bus_front + bus_back)])
    c0 = _panel_corners_p(cfg, center)[cfg.panel.corner0]
    phi = math.atan2(c0[1], c0[0])
    target_from_panel = Rigid3(R=rotvec_to_matrix(np.array([0.0, 0.0, -phi])), t=np.zeros(3))
    return TargetLayout(
        panel_front_z=zf,
        panel_center=center,
        bus_front_z=bus_front,
        bus_back_z=bus_back,
        center_of_mass=com,
        target_from_panel=target_from_panel,
    )


def _panel_corners_p(cfg: TargetConfig, center: np.ndarray) -> np.ndarray:
    w, h = cfg.panel.width_m / 2, cfg.panel.height_m / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)
    xy = center[:2] + signs * [w, h]
    order = np.roll(np.arange(4), -cfg.panel.corner0)
    return np.c_[xy[order], np.full(4, center[2])]


def bracket_points_p(cfg: TargetConfig, side: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P1, P2, P5 of the bracket on side ``+1`` (+x) or ``-1`` (-x), panel frame [m]."""
    lay = layout(cfg)
    w = cfg.wings
    x0 = lay.panel_center[0] + side * cfg.bus.width_m / 2
    y0 = lay.panel_center[1]
    zm = lay.center_of_mass[2]
    P1 = np.array([x0, y0 + side * w.bracket_base_m / 2, zm])
    P2 = np.array([x0, y0 - side * w.bracket_base_m / 2, zm])
    P5 = np.array([x0 + side * w.bracket_height_m, y0, zm])
    return P1, P2, P5


def geometry(cfg: TargetConfig) -> TargetGeometry:
    """The target's named features in the target frame T, as written to target.yaml."""
    lay = layout(cfg)
    tfp = lay.target_from_panel
    corners = tfp.apply(_panel_corners_p(cfg, lay.panel_center))
    comps_p = np.array(
        [
            [
                lay.panel_center[0] + x,
                lay.panel_center[1] + y,
                lay.panel_front_z + cfg.components.height_m,
            ]
            for x, y in cfg.components.positions_m
        ]
    ).reshape(-1, 3)
    extras: dict[str, object] = {
        "frame": "origin at the ring's outer front edge centre; z = ring normal out of the "
        "front face; x toward panel corner 0 in the ring plane",
        "center_of_mass": tfp.apply(lay.center_of_mass).tolist(),
        "panel_size_m": [cfg.panel.width_m, cfg.panel.height_m],
        "component_radius_m": cfg.components.radius_m,
        "mask_ids": dict(MASK_IDS),
    }
    if cfg.wings.enabled:
        extras["solar_brackets"] = [
            {
                k: tfp.apply(p).tolist()
                for k, p in zip(("P1", "P2", "P5"), bracket_points_p(cfg, s), strict=True)
            }
            for s in (1, -1)
        ]
    ring = Ring(
        radius_m=cfg.ring.outer_radius_m,
        center=np.zeros(3),
        normal=np.array([0.0, 0.0, 1.0]),
        extras=_ring_extras(cfg.ring),
    )
    return TargetGeometry(
        ring=ring, panel_corners=corners, components=tfp.apply(comps_p), bracket=None, extras=extras
    )


def _ring_extras(r: RingConfig) -> dict[str, object]:
    """target.yaml's extra ring keys; the rim, lip and bolt keys only where the ring has them
    (a default ring writes exactly what it wrote before these options existed)."""
    out: dict[str, object] = {"inner_radius_m": r.inner_radius_m, "height_m": r.height_m}
    if r.rim_fillet_m > 0:
        out["rim"] = "rounded"
        out["rim_fillet_m"] = r.rim_fillet_m
    if r.lip_width_m > 0:
        out["wall_outer_radius_m"] = r.wall_outer_radius_m
        out["lip_thickness_m"] = r.lip_thickness_m
    if r.bolts > 0:
        out["bolts"] = {
            "count": r.bolts,
            "circle_radius_m": r.bolt_circle_radius_m,
            "radius_m": r.bolt_radius_m,
            "height_m": r.bolt_height_m,
        }
    return out


def bracket_geometry(cfg: TargetConfig, side: int = 1) -> Bracket:
    """The bracket on one side in the target frame (for final-approach evaluation)."""
    tfp = layout(cfg).target_from_panel
    P1, P2, P5 = (tfp.apply(p) for p in bracket_points_p(cfg, side))
    return Bracket(P1=P1, P2=P2, P5=P5, visible_fraction=1.0)
