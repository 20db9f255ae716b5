"""Mitsuba 3 scene of the procedural target, laid out in the target frame T.

Only this module and `render` import Mitsuba. The scene is built once per sequence; per frame
only the cameras and the light move (the target is static in its own frame), which keeps
textures uploaded and kernels cached.

Variant: ``llvm_ad_rgb`` needs an LLVM shared library >= 16 (Debian: ``libllvm19``); with
only LLVM 14/15 Dr.Jit aborts the process ("Cannot select: fminimum"), so we look for the
library ourselves and fall back to ``scalar_rgb`` (about 4x slower, same images up to noise).
"""

from __future__ import annotations

import glob
import logging
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.target import (
    FoilConfig,
    MetalConfig,
    TargetConfig,
    bracket_points_p,
    layout,
)
from satpose.datasets.textures import foil_texture, solar_cell_texture

log = logging.getLogger(__name__)

MIN_LLVM_MAJOR = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)


class RenderError(SatposeError):
    """The renderer cannot run as configured (missing LLVM, unsupported camera, ...)."""


def find_llvm() -> str | None:
    """Path of the newest LLVM shared library usable by Dr.Jit (major >= 16), or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return env if os.path.isfile(env) else None
    best: tuple[int, str] | None = None
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if m is None:
                continue
            major = int(m.group(1))
            if major >= MIN_LLVM_MAJOR and (best is None or major > best[0]):
                best = (major, path)
    return None if best is None else best[1]


def load_mitsuba(variant: str = "auto") -> tuple[ModuleType, str]:
    """Import Mitsuba with ``variant`` (``auto``, ``llvm_ad_rgb`` or ``scalar_rgb``) set.

    Returns:
        (the mitsuba module, the variant actually used).
    """
    if variant not in ("auto", "llvm_ad_rgb", "scalar_rgb"):
        raise RenderError(
            f"render.variant must be auto, llvm_ad_rgb or scalar_rgb, got {variant!r}"
        )
    if variant in ("auto", "llvm_ad_rgb"):
        llvm = find_llvm()
        if llvm is not None:
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
            variant = "llvm_ad_rgb"
        elif variant == "llvm_ad_rgb":
            raise RenderError(
                "render.variant llvm_ad_rgb needs LLVM >= 16 (Debian: apt-get "
                "install libllvm19); none was found"
            )
        else:
            log.warning(
                "no LLVM >= %d found (Debian: apt-get install libllvm19); rendering with "
                "scalar_rgb, about 4x slower",
                MIN_LLVM_MAJOR,
            )
            variant = "scalar_rgb"
    import mitsuba as mi

    mi.set_variant(variant)
    return mi, variant


# --------------------------------------------------------------------------------------------
# Shape helpers (all matrices are target-frame placements)
# --------------------------------------------------------------------------------------------


def _frame_matrix(
    center: np.ndarray, u: np.ndarray, v: np.ndarray, half_u: float, half_v: float
) -> np.ndarray:
    """4x4 placing Mitsuba's [-1, 1]^2 rectangle (normal +z) with axes u, v at ``center``."""
    n = np.cross(u, v)
    M = np.eye(4)
    M[:3, 0] = u * half_u
    M[:3, 1] = v * half_v
    M[:3, 2] = n
    M[:3, 3] = center
    return M


@dataclass(frozen=True)
class _Placer:
    """Maps panel-frame geometry into the target frame."""

    target_from_panel: Rigid3

    def point(self, p: np.ndarray) -> list[float]:
        return [float(x) for x in self.target_from_panel.apply(np.asarray(p, float))]

    def dir(self, d: np.ndarray) -> np.ndarray:
        return self.target_from_panel.rotate(np.asarray(d, float))

    def rect(
        self,
        mi: ModuleType,
        center: np.ndarray,
        u: np.ndarray,
        v: np.ndarray,
        half_u: float,
        half_v: float,
    ) -> Any:
        M = _frame_matrix(
            self.target_from_panel.apply(center), self.dir(u), self.dir(v), half_u, half_v
        )
        return mi.ScalarTransform4f(M.tolist())


def _bitmap(mi: ModuleType, array: np.ndarray, raw: bool = True) -> dict[str, Any]:
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(array, np.float32)),
        "raw": raw,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }


def _foil_bsdf(
    mi: ModuleType, width_m: float, height_m: float, cfg: FoilConfig, rng: np.random.Generator
) -> dict[str, Any]:
    tex = foil_texture(width_m, height_m, cfg, rng)
    conductor = {
        "type": "roughconductor",
        "material": cfg.metal,
        "distribution": "ggx",
        "alpha": _bitmap(mi, tex.roughness),
        "specular_reflectance": _bitmap(mi, np.clip(tex.reflectance, 0.0, 1.0)),
    }
    label = {"type": "diffuse", "reflectance": _bitmap(mi, tex.label_albedo)}
    blend = {
        "type": "blendbsdf",
        "weight": _bitmap(mi, tex.label_weight),
        "bsdf_0": conductor,
        "bsdf_1": label,
    }
    return {"type": "normalmap", "normalmap": _bitmap(mi, tex.normal), "bsdf": blend}


def _metal_bsdf(cfg: MetalConfig) -> dict[str, Any]:
    if cfg.finish == "painted":
        return {
            "type": "twosided",
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "rgb", "value": list(cfg.diffuse_rgb)},
            },
        }
    if cfg.finish == "anodised":
        return {
            "type": "twosided",
            "bsdf": {
                "type": "roughplastic",
                "distribution": "ggx",
                "alpha": float(cfg.roughness),
                "diffuse_reflectance": {"type": "rgb", "value": list(cfg.diffuse_rgb)},
                "int_ior": 1.5,
            },
        }
    return {
        "type": "twosided",
        "bsdf": {
            "type": "blendbsdf",
            "weight": float(cfg.diffuse_fraction),
            "bsdf_0": {
                "type": "roughconductor",
                "material": cfg.metal,
                "distribution": "ggx",
                "alpha": float(cfg.roughness),
            },
            "bsdf_1": {
                "type": "diffuse",
                "reflectance": {"type": "rgb", "value": list(cfg.diffuse_rgb)},
            },
        },
    }


def _annulus_mesh(
    mi: ModuleType,
    name: str,
    r_in: float,
    r_out: float,
    z: float,
    placer: _Placer,
    attach: dict[str, Any],
    segments: int = 1024,
) -> Any:
    """Flat annulus in the plane z (panel frame), normal +z, as a triangle mesh.

    With 1024 segments the polygon departs from the true circle by < 2e-5 of the radius.
    """
    a = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    ring_out = np.c_[r_out * np.cos(a), r_out * np.sin(a), np.full(segments, z)]
    ring_in = np.c_[r_in * np.cos(a), r_in * np.sin(a), np.full(segments, z)]
    verts = placer.target_from_panel.apply(np.vstack([ring_out, ring_in]))
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.vstack([np.c_[i, j, segments + i], np.c_[j, segments + j, segments + i]])
    return triangle_mesh(mi, name, verts, faces, attach)


def rounded_rim_profile(
    r_in: float, r_out: float, fillet: float, arc_points: int = 12
) -> tuple[np.ndarray, np.ndarray]:
    """Cross-section of a rounded front rim in the (radius, z) half-plane.

    From the top of the inner wall (r_in, -fillet) a quarter circle to (r_in + fillet, 0),
    flat to (r_out - fillet, 0) (nothing when the rim is half-round), a quarter circle down to
    (r_out, -fillet).

    Returns:
        (P, 2) profile points and (P, 2) unit outward normals, both as (radius, z).
    """
    a_in = np.linspace(math.pi, math.pi / 2, arc_points + 1)
    a_out = np.linspace(math.pi / 2, 0.0, arc_points + 1)
    c_in, c_out = r_in + fillet, r_out - fillet
    n = np.vstack([np.c_[np.cos(a_in), np.sin(a_in)], np.c_[np.cos(a_out), np.sin(a_out)]])
    pts = np.vstack(
        [
            np.c_[c_in + fillet * np.cos(a_in), -fillet + fillet * np.sin(a_in)],
            np.c_[c_out + fillet * np.cos(a_out), -fillet + fillet * np.sin(a_out)],
        ]
    )
    if c_out - c_in < 1e-9:  # half-round: the two arcs meet at the crest
        keep = np.ones(len(pts), bool)
        keep[arc_points + 1] = False
        pts, n = pts[keep], n[keep]
    return pts, n


def _revolved_mesh(
    mi: ModuleType,
    name: str,
    profile: np.ndarray,
    normals: np.ndarray,
    placer: _Placer,
    attach: dict[str, Any],
    segments: int = 1024,
) -> Any:
    """A surface of revolution about the panel-frame z axis (through the ring centre) from a
    (radius, z) profile with per-vertex normals (smooth shading)."""
    a = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    ca, sa = np.cos(a), np.sin(a)
    P = len(profile)
    # vertex (k, j): profile point k at angle j -> index k * segments + j
    verts = np.concatenate([np.c_[r * ca, r * sa, np.full(segments, z)] for r, z in profile])
    nrm = np.concatenate([np.c_[nr * ca, nr * sa, np.full(segments, nz)] for nr, nz in normals])
    j = np.arange(segments)
    j1 = (j + 1) % segments
    faces = []
    for k in range(P - 1):
        a0, a1 = k * segments + j, k * segments + j1
        b0, b1 = (k + 1) * segments + j, (k + 1) * segments + j1
        faces += [np.c_[a0, b0, a1], np.c_[a1, b0, b1]]
    f = np.vstack(faces)
    # Wind the faces so that their geometric normals agree with the shading normals.
    e1 = verts[f[:, 1]] - verts[f[:, 0]]
    e2 = verts[f[:, 2]] - verts[f[:, 0]]
    if float(np.sum(np.cross(e1, e2) * nrm[f[:, 0]])) < 0:
        f = f[:, [0, 2, 1]]
    R = placer.target_from_panel
    return triangle_mesh(mi, name, R.apply(verts), f, attach, normals=R.rotate(nrm))


def triangle_mesh(
    mi: ModuleType,
    name: str,
    verts: np.ndarray,
    faces: np.ndarray,
    attach: dict[str, Any],
    normals: np.ndarray | None = None,
) -> Any:
    """A Mitsuba mesh from vertices (V, 3) and faces (F, 3); ``attach`` maps "bsdf" (and
    optionally "emitter") to plugin dicts; ``normals`` (V, 3): per-vertex shading normals
    (None = flat faces)."""
    props = mi.Properties()
    for key, plugin in attach.items():
        props[key] = mi.load_dict(plugin)
    mesh = mi.Mesh(
        name,
        vertex_count=verts.shape[0],
        face_count=faces.shape[0],
        props=props,
        has_vertex_normals=normals is not None,
        has_vertex_texcoords=False,
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(normals.astype(np.float32).ravel())
    params.update()
    return mesh


# --------------------------------------------------------------------------------------------
# The target
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TargetShapes:
    """Mitsuba shape dicts of the target (target frame), keyed by shape id.

    Attributes:
        shapes: ``{shape_id: mitsuba dict}``.
        part_of: ``{shape_id: part name}`` where part names are the keys of ``MASK_IDS``.
    """

    shapes: dict[str, dict[str, Any]]
    part_of: dict[str, str]


def target_shapes(
    mi: ModuleType, cfg: TargetConfig, seed: int, emissive: Mapping[str, float] | None = None
) -> TargetShapes:
    """Build every shape of the target, with materials and textures, in the target frame.

    Textures come from ``seed``: the same config and seed give the same satellite.

    Args:
        emissive: ``{part or shape id: radiance}`` for truth renders. If given, only shapes
            of these parts (keys of ``MASK_IDS``) or with these ids (e.g. ``ring_front``) are
            built, black and uniformly emissive, so that a render shows exactly where their
            geometry lands (radiance 1: coverage; radiance = mask id: an object-id image).
    """
    rng = np.random.default_rng([seed, 0x5A7])
    lay = layout(cfg)
    P = _Placer(lay.target_from_panel)
    shapes: dict[str, dict[str, Any]] = {}
    part_of: dict[str, str] = {}
    ex, ey, ez = np.eye(3)
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}

    def glow(part: str, shape_id: str) -> dict[str, Any]:
        assert emissive is not None
        value = float(emissive.get(shape_id, emissive.get(part, 0.0)))
        return {"type": "area", "radiance": {"type": "rgb", "value": [value] * 3}}

    def wanted(part: str, shape_id: str) -> bool:
        return emissive is None or part in emissive or shape_id in emissive

    def add(shape_id: str, part: str, shape: dict[str, Any], material: Any) -> None:
        """Add a shape; ``material`` is a BSDF dict or a zero-argument function making one."""
        if not wanted(part, shape_id):
            return
        if emissive is not None:
            shape = {**shape, "bsdf": black, "emitter": glow(part, shape_id)}
        else:
            shape = {**shape, "bsdf": material() if callable(material) else material}
        shapes[shape_id] = shape
        part_of[shape_id] = part

    # Front panel: textured front, thin metal edges.
    pc = lay.panel_center
    pw, ph, pt = cfg.panel.width_m, cfg.panel.height_m, cfg.panel.thickness_m
    add(
        "panel_front",
        "panel",
        {"type": "rectangle", "to_world": P.rect(mi, pc, ex, ey, pw / 2, ph / 2)},
        (
            (lambda: _foil_bsdf(mi, pw, ph, cfg.panel.foil, rng))
            if cfg.panel.paint is None
            else _metal_bsdf(cfg.panel.paint)
        ),
    )
    edge_metal = _metal_bsdf(
        MetalConfig(metal="Al", roughness=0.35, diffuse_fraction=0.5, diffuse_rgb=(0.6, 0.6, 0.6))
    )
    zc = pc[2] - pt / 2
    for k, (d, u, half_u) in enumerate(
        [(ex, ey, ph / 2), (-ex, -ey, ph / 2), (ey, -ex, pw / 2), (-ey, ex, pw / 2)]
    ):
        c = np.array([pc[0], pc[1], zc]) + d * (pw / 2 if abs(d[0]) else ph / 2)
        add(
            f"panel_edge{k}",
            "panel",
            {"type": "rectangle", "to_world": P.rect(mi, c, u, ez, half_u, pt / 2)},
            edge_metal,
        )

    # Bus box behind the panel: four sides and the back, each with its own foil texture.
    bw, bh, bd = cfg.bus.width_m, cfg.bus.height_m, cfg.bus.depth_m
    zm = 0.5 * (lay.bus_front_z + lay.bus_back_z)
    faces = [
        ("bus_px", np.array([pc[0] + bw / 2, pc[1], zm]), -ez, ey, bd, bh),
        ("bus_nx", np.array([pc[0] - bw / 2, pc[1], zm]), ez, ey, bd, bh),
        ("bus_py", np.array([pc[0], pc[1] + bh / 2, zm]), ex, -ez, bw, bd),
        ("bus_ny", np.array([pc[0], pc[1] - bh / 2, zm]), ex, ez, bw, bd),
        ("bus_back", np.array([pc[0], pc[1], lay.bus_back_z]), -ex, ey, bw, bh),
    ]
    for shape_id, c, u, v, su, sv in faces:
        add(
            shape_id,
            "bus",
            {"type": "rectangle", "to_world": P.rect(mi, c, u, v, su / 2, sv / 2)},
            lambda su=su, sv=sv: _foil_bsdf(mi, su, sv, cfg.bus.foil, rng),
        )

    # Docking ring: front annulus (its outer edge is the target-frame origin circle), two walls;
    # optionally a rounded rim, a lip, bolt heads and a foil-wrapped outer wall.
    r = cfg.ring
    ring_bsdf = _metal_bsdf(r.material)
    if wanted("ring", "ring_front"):
        attach = (
            {"bsdf": black, "emitter": glow("ring", "ring_front")}
            if emissive is not None
            else {"bsdf": ring_bsdf}
        )
        if r.rim_fillet_m > 0:
            prof, nrm = rounded_rim_profile(r.inner_radius_m, r.outer_radius_m, r.rim_fillet_m)
            front = _revolved_mesh(mi, "ring_front", prof, nrm, P, attach)
        else:
            front = _annulus_mesh(
                mi, "ring_front", r.inner_radius_m, r.outer_radius_m, 0.0, P, attach
            )
        shapes["ring_front"] = {"type": "mesh", "mesh": front}
        part_of["ring_front"] = "ring"
    base = P.point(np.array([0.0, 0.0, lay.panel_front_z]))
    top = P.point(np.zeros(3))
    # The walls end where the rounding or the lip begins.
    wall_top = P.point(np.array([0.0, 0.0, -max(r.rim_fillet_m, r.lip_thickness_m)]))
    inner_top = P.point(np.array([0.0, 0.0, -r.rim_fillet_m])) if r.rim_fillet_m > 0 else top
    outer_bsdf: Any = ring_bsdf
    if r.wall_foil is not None:
        wall_len = r.height_m - max(r.rim_fillet_m, r.lip_thickness_m)
        foil = r.wall_foil
        outer_bsdf = lambda: _foil_bsdf(  # noqa: E731
            mi, 2 * math.pi * r.wall_outer_radius_m, wall_len, foil, rng
        )
    add(
        "ring_outer",
        "ring",
        {
            "type": "cylinder",
            "p0": base,
            "p1": top if r.rim_fillet_m == 0 and r.lip_width_m == 0 else wall_top,
            "radius": r.wall_outer_radius_m,
        },
        outer_bsdf,
    )
    add(
        "ring_inner",
        "ring",
        {
            "type": "cylinder",
            "p0": base,
            "p1": inner_top,
            "radius": r.inner_radius_m,
            "flip_normals": True,
        },
        ring_bsdf,
    )
    if r.lip_width_m > 0:
        lip_z = -r.lip_thickness_m
        add(
            "ring_lip_edge",
            "ring",
            {
                "type": "cylinder",
                "p0": P.point(np.array([0.0, 0.0, lip_z])),
                "p1": top,
                "radius": r.outer_radius_m,
            },
            ring_bsdf,
        )
        if wanted("ring", "ring_lip_under"):
            attach = (
                {"bsdf": black, "emitter": glow("ring", "ring_lip_under")}
                if emissive is not None
                else {"bsdf": ring_bsdf}
            )
            shapes["ring_lip_under"] = {
                "type": "mesh",
                "mesh": _annulus_mesh(
                    mi,
                    "ring_lip_under",
                    r.wall_outer_radius_m,
                    r.outer_radius_m,
                    lip_z,
                    P,
                    attach,
                ),
            }
            part_of["ring_lip_under"] = "ring"
    if r.bolts > 0:
        bolt_bsdf = _metal_bsdf(r.bolt_material)
        rb = r.bolt_circle_radius_m
        for k in range(r.bolts):
            phi = 2 * math.pi * (k + 0.5) / r.bolts
            b0 = np.array([rb * math.cos(phi), rb * math.sin(phi), 0.0])
            b1 = b0 + ez * r.bolt_height_m
            add(
                f"ring_bolt{k}_wall",
                "ring",
                {
                    "type": "cylinder",
                    "p0": P.point(b0),
                    "p1": P.point(b1),
                    "radius": r.bolt_radius_m,
                },
                bolt_bsdf,
            )
            add(
                f"ring_bolt{k}_top",
                "ring",
                {
                    "type": "disk",
                    "to_world": P.rect(mi, b1, ex, ey, r.bolt_radius_m, r.bolt_radius_m),
                },
                bolt_bsdf,
            )

    # Dark components: short cylinders with a top disk.
    comp = cfg.components
    comp_bsdf = {
        "type": "roughplastic",
        "distribution": "ggx",
        "alpha": comp.roughness,
        "diffuse_reflectance": {"type": "rgb", "value": [comp.albedo] * 3},
        "int_ior": 1.49,
    }
    for k, (x, y) in enumerate(comp.positions_m):
        c0 = np.array([pc[0] + x, pc[1] + y, lay.panel_front_z])
        c1 = c0 + ez * comp.height_m
        add(
            f"component{k}_wall",
            "components",
            {"type": "cylinder", "p0": P.point(c0), "p1": P.point(c1), "radius": comp.radius_m},
            comp_bsdf,
        )
        add(
            f"component{k}_top",
            "components",
            {"type": "disk", "to_world": P.rect(mi, c1, ex, ey, comp.radius_m, comp.radius_m)},
            comp_bsdf,
        )

    # Solar wings on triangular brackets.
    w = cfg.wings
    if w.enabled:
        strut = _metal_bsdf(w.strut_material)
        for side, tag in ((1, "px"), (-1, "nx")):
            P1, P2, P5 = bracket_points_p(cfg, side)
            wing_x0 = P5[0] + side * w.gap_m
            for name, a, b in (
                ("p1p2", P1, P2),
                ("p1p5", P1, P5),
                ("p2p5", P2, P5),
                ("yoke", P5, np.array([wing_x0, P5[1], P5[2]])),
            ):
                add(
                    f"bracket_{tag}_{name}",
                    "brackets",
                    {
                        "type": "cylinder",
                        "p0": P.point(a),
                        "p1": P.point(b),
                        "radius": w.strut_radius_m,
                    },
                    strut,
                )
            span = w.span_m if side > 0 or w.nx_span_m is None else w.nx_span_m
            wc = np.array([wing_x0 + side * span / 2, P5[1], P5[2]])
            u = ex * side
            add(
                f"wing_{tag}_front",
                "wings",
                {
                    "type": "rectangle",
                    "to_world": P.rect(mi, wc, u, ey * side, span / 2, w.chord_m / 2),
                },
                lambda span=span: {  # called at once by add(); bound for clarity
                    "type": "roughplastic",
                    "distribution": "ggx",
                    "alpha": 0.08,
                    "diffuse_reflectance": _bitmap(
                        mi,
                        solar_cell_texture(span, w.chord_m, w.cell_size_m, w.cell_rgb, 0.002, rng),
                    ),
                },
            )
            add(
                f"wing_{tag}_back",
                "wings",
                {
                    "type": "rectangle",
                    "to_world": P.rect(
                        mi, wc - ez * w.thickness_m, u, -ey * side, span / 2, w.chord_m / 2
                    ),
                },
                {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7] * 3}},
            )
    return TargetShapes(shapes=shapes, part_of=part_of)


def scene_dict(
    shapes: dict[str, dict[str, Any]],
    light: dict[str, Any],
    max_depth: int,
    ambient_radiance: float = 0.0,
) -> dict[str, Any]:
    """Assemble a Mitsuba scene dict (no sensor: sensors are passed per render).

    Shapes of type ``mesh`` are pre-built ``mi.Mesh`` objects carrying their own BSDF.
    ``ambient_radiance`` > 0 adds a uniform environment of that radiance (earthshine), hidden
    from camera rays so that space stays black behind the target.
    """
    integrator: dict[str, Any] = {"type": "path", "max_depth": max_depth}
    d: dict[str, Any] = {"type": "scene", "integrator": integrator, "light": light}
    if ambient_radiance > 0:
        integrator["hide_emitters"] = True
        d["earthshine"] = {
            "type": "constant",
            "radiance": {"type": "rgb", "value": [float(ambient_radiance)] * 3},
        }
    for shape_id, s in shapes.items():
        d[shape_id] = s["mesh"] if s["type"] == "mesh" else s
    return d
