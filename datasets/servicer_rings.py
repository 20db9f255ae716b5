"""The servicer's concentric-ring calibration target (seed 002, sec. 1): red painted rings on
the servicer's surface, always in the boom camera's view together with the target.

The target is fixed to the servicer, and so is the boom camera: its pose is constant in the
camera frame. ``rings`` frame: origin at the rings' common centre on the painted surface, z the
surface normal pointing out of it (toward the camera), x and y in the surface. Each painted
band ``(r_in, r_out)`` has two edge circles (its inner and outer boundary) in the plane z = 0;
these radii are what the `rings` check (`satpose.frontend.rings`) measures. The bands lie on a
square plate of lighter paint (``plate_half_m``), 0.2 mm below them.

``mount_error_deg`` perturbs the camera's mounting: the rings are rendered at
``left_cam_from_rings = Exp(mount_error) @ left_cam_from_rings_nominal`` (the camera turned
about its own centre relative to its nominal mounting), while the nominal pose, which the
check compares against, stays the design value.

Both poses go to target.yaml under the extra key ``servicer_rings`` (`to_yaml`): the nominal
one is the known geometry the check reads, the rendered one is truth (evaluation only).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from satpose.datasets.errors import ConfigError, SequenceError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix

Vec3 = tuple[float, float, float]

PLATE_DEPTH_M = 2e-4
"""The plate lies this far below the painted bands (avoids coincident surfaces)."""


@dataclass(frozen=True, kw_only=True)
class ServicerRingsConfig:
    """A concentric-ring target fixed in the (left) camera frame.

    Attributes:
        bands_m: painted bands ``(inner radius, outer radius)`` [m], increasing, disjoint.
        plate_half_m: half side of the square plate the bands are painted on [m].
        band_rgb: band albedo (the paper's red rings).
        plate_rgb: plate albedo (light grey paint).
        position_m: nominal rings centre in the left camera frame [m].
        rotation_deg: rotation vector of the nominal ``left_cam_from_rings`` [deg]. The
            default tilts the plate 50 deg: a deck below the boom camera seen from above.
        mount_error_deg: rotation vector of the camera's mounting error [deg] (see the module
            docstring); zero = the camera is where the calibration says.
    """

    bands_m: tuple[tuple[float, float], ...] = ((0.010, 0.015), (0.025, 0.030), (0.040, 0.045))
    plate_half_m: float = 0.065
    band_rgb: Vec3 = (0.35, 0.02, 0.02)
    plate_rgb: Vec3 = (0.30, 0.30, 0.30)
    position_m: Vec3 = (-0.14, 0.095, 0.60)
    rotation_deg: Vec3 = (130.0, 0.0, 0.0)
    mount_error_deg: Vec3 = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if len(self.bands_m) < 1:
            raise ConfigError("servicer_rings.bands_m needs at least one band")
        edges = [r for band in self.bands_m for r in band]
        if not all(math.isfinite(r) for r in edges) or edges[0] <= 0:
            raise ConfigError("servicer_rings.bands_m: radii must be finite and positive")
        if any(b <= a for a, b in itertools.pairwise(edges)):
            raise ConfigError(
                "servicer_rings.bands_m: radii must increase (inner < outer, bands disjoint)"
            )
        if not self.plate_half_m > edges[-1]:
            raise ConfigError("servicer_rings.plate_half_m must exceed the largest radius")
        if not self.position_m[2] > 0:
            raise ConfigError("servicer_rings.position_m must lie in front of the camera (z > 0)")

    @property
    def edge_radii_m(self) -> np.ndarray:
        """All band edges, increasing [m] (inner, outer of band 0, inner, outer of band 1, ...)."""
        return np.array([r for band in self.bands_m for r in band], float)

    def nominal_pose(self) -> Rigid3:
        """``left_cam_from_rings`` as designed."""
        return Rigid3(
            R=rotvec_to_matrix(np.radians(self.rotation_deg)),
            t=np.asarray(self.position_m, float),
        )

    def true_pose(self) -> Rigid3:
        """``left_cam_from_rings`` as rendered (the mounting error applied)."""
        err = Rigid3(R=rotvec_to_matrix(np.radians(self.mount_error_deg)), t=np.zeros(3))
        return err @ self.nominal_pose()


def _pose_yaml(T: Rigid3) -> dict[str, list[float]]:
    return {"t": [float(v) for v in T.t], "quat_xyzw": [float(v) for v in T.quat_xyzw]}


def to_yaml(cfg: ServicerRingsConfig) -> dict[str, Any]:
    """The ``servicer_rings`` entry of target.yaml (plain data)."""
    return {
        "frame": "fixed in the left camera frame (servicer-mounted); rings frame: origin at the "
        "common centre on the painted surface, z out of the surface",
        "bands_m": [[float(a), float(b)] for a, b in cfg.bands_m],
        "radius_refers_to": "each band's inner and outer edge circle on the painted surface",
        "left_cam_from_rings_nominal": _pose_yaml(cfg.nominal_pose()),
        "left_cam_from_rings": _pose_yaml(cfg.true_pose()),
        "mount_error_deg": [float(v) for v in cfg.mount_error_deg],
    }


@dataclass(frozen=True, kw_only=True)
class RingsTargetInfo:
    """What a sequence says about its servicer ring target (target.yaml ``servicer_rings``).

    Attributes:
        edge_radii_m: the band edges, increasing [m].
        nominal: nominal ``left_cam_from_rings``, or None.
        truth: rendered ``left_cam_from_rings`` (truth), or None.
    """

    edge_radii_m: np.ndarray
    nominal: Rigid3 | None
    truth: Rigid3 | None


def from_yaml(raw: Any, path: Any) -> RingsTargetInfo:
    """Parse target.yaml's ``servicer_rings`` entry; `SequenceError` naming the field if bad."""
    if not isinstance(raw, dict):
        raise SequenceError(path, "servicer_rings", "must be a mapping")
    bands = raw.get("bands_m")
    try:
        arr = np.asarray(bands, dtype=float)
    except (TypeError, ValueError):
        arr = np.zeros((0,))
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 1 or not np.all(np.isfinite(arr)):
        raise SequenceError(path, "servicer_rings.bands_m", "must be a list of [r_in, r_out] [m]")
    edges = arr.ravel()
    if edges[0] <= 0 or np.any(np.diff(edges) <= 0):
        raise SequenceError(path, "servicer_rings.bands_m", "radii must be positive and increasing")

    def pose(key: str) -> Rigid3 | None:
        v = raw.get(key)
        if v is None:
            return None
        try:
            t = np.asarray(v["t"], float).reshape(3)
            q = np.asarray(v["quat_xyzw"], float).reshape(4)
        except (KeyError, TypeError, ValueError):
            raise SequenceError(
                path, f"servicer_rings.{key}", "must be {t: [x, y, z], quat_xyzw: [...]}"
            ) from None
        if not (np.all(np.isfinite(t)) and abs(np.linalg.norm(q) - 1.0) < 1e-6):
            raise SequenceError(path, f"servicer_rings.{key}", "not finite / not a unit quaternion")
        return Rigid3.from_quat_xyzw(q / np.linalg.norm(q), t)

    return RingsTargetInfo(
        edge_radii_m=edges,
        nominal=pose("left_cam_from_rings_nominal"),
        truth=pose("left_cam_from_rings"),
    )


# --------------------------------------------------------------------------------------------
# Mitsuba shapes (moved every frame: they are fixed in the camera frame, the scene in the
# target frame)
# --------------------------------------------------------------------------------------------


def _mesh(mi: ModuleType, name: str, verts: np.ndarray, faces: np.ndarray, bsdf: Any) -> Any:
    from satpose.datasets.scene import triangle_mesh  # mitsuba-side module, imported lazily

    return triangle_mesh(mi, name, verts, faces, {"bsdf": bsdf})


def _annulus(r_in: float, r_out: float, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat annulus in z = 0 (normal +z): vertices (2S, 3), faces (2S, 3). With 1024 segments
    the polygon departs from the circles by < 2e-5 of the radius."""
    a = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    c, s, z = np.cos(a), np.sin(a), np.zeros(segments)
    verts = np.vstack([np.c_[r_out * c, r_out * s, z], np.c_[r_in * c, r_in * s, z]])
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.vstack([np.c_[i, j, segments + i], np.c_[j, segments + j, segments + i]])
    return verts, faces


class RingsShapes:
    """The plate and bands as Mitsuba meshes, placed per frame (`place`)."""

    def __init__(self, mi: ModuleType, cfg: ServicerRingsConfig, black: bool = False) -> None:
        """``black``: non-emitting black surfaces (they only occlude: for object-id renders)."""
        self.cfg = cfg
        h = cfg.plate_half_m
        z = -PLATE_DEPTH_M
        plate_v = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
        plate_f = np.array([[0, 1, 2], [0, 2, 3]])

        def diffuse(rgb: Vec3) -> dict[str, Any]:
            value = [0.0] * 3 if black else list(rgb)
            return {"type": "diffuse", "reflectance": {"type": "rgb", "value": value}}

        self.local: dict[str, np.ndarray] = {"servicer_rings_plate": plate_v}
        self.shapes: dict[str, dict[str, Any]] = {
            "servicer_rings_plate": {
                "type": "mesh",
                "mesh": _mesh(mi, "servicer_rings_plate", plate_v, plate_f, diffuse(cfg.plate_rgb)),
            }
        }
        for k, (r_in, r_out) in enumerate(cfg.bands_m):
            key = f"servicer_rings_band{k}"
            v, f = _annulus(r_in, r_out, 1024)
            self.local[key] = v
            self.shapes[key] = {"type": "mesh", "mesh": _mesh(mi, key, v, f, diffuse(cfg.band_rgb))}
        self.mi = mi

    def place(self, params: Any, target_from_rings: Rigid3) -> None:
        """Move the meshes of a traversed scene to ``target_from_rings`` (call
        ``params.update()`` afterwards)."""
        for key, v in self.local.items():
            w = target_from_rings.apply(v).astype(np.float32).ravel()
            params[f"{key}.vertex_positions"] = self.mi.Float(w)
