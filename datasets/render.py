"""Render a scenario into a sequence folder (format v1) with Mitsuba 3.

Image formation per camera and frame:

1. Mitsuba path-traces an undistorted pinhole "canvas" camera (box reconstruction filter,
   so a pixel is the mean radiance over its square). The canvas has the output camera's
   focal length and is just large enough to cover the distorted field of view.
2. Lens distortion: every output pixel is undistorted (OpenCV's radial-tangential model run
   to convergence) and the canvas is sampled there (bilinear). Without distortion the
   canvas is the output image.
3. Sensor: exposure (auto: a white Lambertian surface facing the light reads ``white_level``),
   photon shot noise (Poisson in electrons), Gaussian read noise, quantisation to 8/16 bit.

Masks (object ids, ``target.MASK_IDS``) come from a one-sample-per-pixel ``shape_index`` AOV
remapped with nearest-neighbour sampling.

Mitsuba conventions bridged here (measured, see tests/datasets/test_render.py): its camera
looks along +z with +x to the left and +y up, so the OpenCV camera is ``diag(-1, -1, 1)`` of
it; its principal-point offset is ``(W/2 - 0.5 - cx) / W`` (opposite sign to OpenCV's
``cx - W/2``), the 0.5 being OpenCV's pixel-centre origin.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from scipy import ndimage, sparse

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.config import to_plain
from satpose.datasets.geometry import Rigid3
from satpose.datasets.scenarios import Scenario, trajectory
from satpose.datasets.scene import RenderError, load_mitsuba, scene_dict, target_shapes
from satpose.datasets.sequence import SequenceWriter, TargetGeometry
from satpose.datasets.servicer_rings import RingsShapes
from satpose.datasets.servicer_rings import to_yaml as rings_to_yaml
from satpose.datasets.target import MASK_IDS, geometry

log = logging.getLogger(__name__)

CANVAS_MARGIN_PX = 3
AREA_SUPERSAMPLE = 3
"""Sub-pixels per output pixel and axis of ``render.resampling: area`` (odd: masks take the
centre sub-pixel)."""
_CV_FROM_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


def _version() -> str:
    try:
        return metadata.version("satpose")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True, kw_only=True)
class View:
    """One camera of the rig as the renderer sees it.

    Attributes:
        name: ``left`` or ``right``.
        camera: the output camera (with distortion), as written to calib.yaml.
        canvas: the undistorted camera Mitsuba renders.
        sample_rc: (2, s H, s W) canvas (row, col) coordinates of every output pixel (``s``:
            ``supersample``; of every sub-pixel of an s x s grid per output pixel), or None when
            the camera has no distortion (canvas == output).
        cam_from_left: this camera's pose relative to the left camera.
        supersample: the canvas and the distortion map at this many times the output
            resolution; each output pixel is the mean of its s x s sub-pixels (1: one sample
            of the canvas per output pixel).
    """

    name: str
    camera: PinholeCamera
    canvas: PinholeCamera
    sample_rc: np.ndarray | None
    cam_from_left: Rigid3
    supersample: int = 1
    _resamplers: dict[str, Any] = field(default_factory=dict, init=False, compare=False, repr=False)
    """`distort`'s precomputed bilinear operator and nearest indices, built on first use
    (the map is the same for every frame)."""


def make_view(
    name: str, camera: PinholeCamera, cam_from_left: Rigid3, supersample: int = 1
) -> View:
    """Build the canvas and the distortion sampling map of a camera.

    With ``supersample = s > 1`` (and distortion) the canvas is ``s`` times finer and the map
    gives the canvas position of every sub-pixel centre of an ``s x s`` grid per output
    pixel: output pixel ``u`` covers ``[u - 1/2, u + 1/2]``, its sub-pixel ``k`` is centred
    at ``u + (k + 1/2) / s - 1/2``; canvas pixel ``U`` of the finer canvas is centred at
    ``(U + 1/2) / s - 1/2`` of the coarse one."""
    if abs(camera.fx - camera.fy) > 1e-9 * camera.fx or camera.K[0, 1] != 0.0:
        raise RenderError(
            f"the renderer needs square pixels and zero skew; camera {name} has "
            f"fx={camera.fx}, fy={camera.fy}, skew={camera.K[0, 1]}"
        )
    if not camera.has_distortion:
        return View(
            name=name, camera=camera, canvas=camera, sample_rc=None, cam_from_left=cam_from_left
        )
    if supersample < 1:
        raise RenderError(f"supersample must be >= 1, got {supersample}")
    s = supersample
    f = camera.fx
    sub = (np.arange(s) + 0.5) / s - 0.5  # sub-pixel centres within a pixel
    vv = (np.arange(camera.height)[:, None] + sub[None, :]).ravel()
    uu = (np.arange(camera.width)[:, None] + sub[None, :]).ravel()
    V, U = np.meshgrid(vv, uu, indexing="ij")
    xy = camera.undistort_points(np.stack([U.ravel(), V.ravel()], axis=1))
    if not np.all(np.isfinite(xy)):
        raise RenderError(f"camera {name}: distortion cannot be inverted over the image")
    u_ideal = f * xy[:, 0]
    v_ideal = f * xy[:, 1]
    cx = -math.floor(u_ideal.min()) + CANVAS_MARGIN_PX
    cy = -math.floor(v_ideal.min()) + CANVAS_MARGIN_PX
    width = math.ceil(u_ideal.max() + cx) + CANVAS_MARGIN_PX + 1
    height = math.ceil(v_ideal.max() + cy) + CANVAS_MARGIN_PX + 1
    # the finer canvas: coarse position x is fine position s * (x + 1/2) - 1/2
    canvas = PinholeCamera(
        width=s * width,
        height=s * height,
        K=np.array(
            [[s * f, 0, s * (cx + 0.5) - 0.5], [0, s * f, s * (cy + 0.5) - 0.5], [0, 0, 1.0]]
        ),
    )
    rc = np.stack(
        [
            (s * (v_ideal + cy + 0.5) - 0.5).reshape(V.shape),
            (s * (u_ideal + cx + 0.5) - 0.5).reshape(U.shape),
        ]
    )
    return View(
        name=name,
        camera=camera,
        canvas=canvas,
        sample_rc=rc,
        cam_from_left=cam_from_left,
        supersample=s,
    )


def sensor_dict(
    mi: ModuleType, camera: PinholeCamera, target_from_cam: Rigid3, spp: int
) -> dict[str, Any]:
    """Mitsuba perspective sensor reproducing an undistorted OpenCV pinhole camera exactly."""
    W, H = camera.width, camera.height
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": math.degrees(2.0 * math.atan(W / (2.0 * camera.fx))),
        "principal_point_offset_x": (W / 2 - 0.5 - camera.cx) / W,
        "principal_point_offset_y": (H / 2 - 0.5 - camera.cy) / H,
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f((target_from_cam.matrix() @ _CV_FROM_MITSUBA).tolist()),
        "film": {
            "type": "hdrfilm",
            "width": W,
            "height": H,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "component_format": "float32",
        },
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }


def _bilinear_operator(view: View) -> sparse.csr_matrix:
    """The sparse (H W, H' W') matrix of ``distort``'s bilinear path: output pixel = mean over
    its s x s sub-pixels of the bilinear interpolation of the canvas at each sub-pixel's
    position. Canvas pixels outside the canvas count as 0 (``map_coordinates``'s constant
    mode). Built once per view: applying it is a sparse product instead of one
    interpolation per frame, channel and sub-pixel (the same numbers to float rounding)."""
    assert view.sample_rc is not None
    s = view.supersample
    H, W = view.camera.height, view.camera.width
    Hc, Wc = view.canvas.height, view.canvas.width
    # sub-pixels grouped by output pixel: (H, W, s, s), row-major over output pixels
    rc = view.sample_rc.reshape(2, H, s, W, s).transpose(0, 1, 3, 2, 4).reshape(2, -1)
    r0, c0 = np.floor(rc[0]), np.floor(rc[1])
    fr, fc = rc[0] - r0, rc[1] - c0
    r0, c0 = r0.astype(np.int64), c0.astype(np.int64)
    cols = np.empty((r0.size, 4), np.int32)
    vals = np.empty((r0.size, 4))
    for k, (dr, dc, w) in enumerate(
        (
            (0, 0, (1 - fr) * (1 - fc)),
            (0, 1, (1 - fr) * fc),
            (1, 0, fr * (1 - fc)),
            (1, 1, fr * fc),
        )
    ):
        rr, cc = r0 + dr, c0 + dc
        inside = (rr >= 0) & (rr < Hc) & (cc >= 0) & (cc < Wc)
        cols[:, k] = np.where(inside, rr * Wc + cc, 0)
        vals[:, k] = np.where(inside, w / (s * s), 0.0)
    per_row = 4 * s * s  # duplicate columns are allowed in CSR: the product sums them
    indptr = np.arange(0, H * W * per_row + 1, per_row, dtype=np.int64)
    return sparse.csr_matrix((vals.ravel(), cols.ravel(), indptr), shape=(H * W, Hc * Wc))


def _nearest_indices(view: View) -> np.ndarray:
    """Flat canvas index sampled by every output pixel for ids (the centre sub-pixel's
    nearest canvas pixel, as ``map_coordinates(order=0)``; -1 outside the canvas)."""
    assert view.sample_rc is not None
    s = view.supersample
    rc = view.sample_rc[:, s // 2 :: s, s // 2 :: s]
    r = np.floor(rc[0] + 0.5).astype(np.int64)
    c = np.floor(rc[1] + 0.5).astype(np.int64)
    Hc, Wc = view.canvas.height, view.canvas.width
    ok = (r >= 0) & (r < Hc) & (c >= 0) & (c < Wc)
    return np.where(ok, r * Wc + c, -1)


def distort(
    view: View, canvas_image: np.ndarray, nearest: bool = False, cubic: bool = False
) -> np.ndarray:
    """Resample a canvas image (H', W'[, C]) into the distorted output image (H, W[, C]):
    nearest neighbour (ids), bilinear, or cubic spline (``cubic``; clipped at 0, since the
    spline overshoots next to an edge). With ``view.supersample = s > 1`` each output pixel is
    the mean of its s x s sub-pixels (ids: the centre sub-pixel)."""
    if view.sample_rc is None:
        return canvas_image
    img = canvas_image if canvas_image.ndim == 3 else canvas_image[..., None]
    H, W = view.camera.height, view.camera.width
    flat = img.reshape(-1, img.shape[2])
    if nearest:
        if "nearest" not in view._resamplers:
            view._resamplers["nearest"] = _nearest_indices(view)
        idx = view._resamplers["nearest"]
        out = np.where((idx >= 0)[..., None], flat[np.maximum(idx, 0)], 0).astype(img.dtype)
    elif not cubic:
        if "bilinear" not in view._resamplers:
            view._resamplers["bilinear"] = _bilinear_operator(view)
        out = (view._resamplers["bilinear"] @ flat).astype(img.dtype).reshape(H, W, -1)
    else:
        s = view.supersample
        out = np.stack(
            [
                ndimage.map_coordinates(
                    img[..., c], view.sample_rc, order=3, mode="constant", cval=0.0
                )
                for c in range(img.shape[2])
            ],
            axis=-1,
        )
        out = np.maximum(out, 0.0)
        if s > 1:
            out = out.reshape(H, s, W, s, -1).mean(axis=(1, 3))
    return out if canvas_image.ndim == 3 else out[..., 0]


def _look_along(direction: np.ndarray) -> np.ndarray:
    """4x4 rotation whose +z column is ``direction`` (for Mitsuba's directional emitter)."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    M = np.eye(4)
    M[:3, :3] = np.c_[x, np.cross(z, x), z]
    return M


class StereoRenderer:
    """Renders a scenario's rig around the target, frame by frame.

    The scene is built once (textures uploaded once); per frame only the sensors and the light
    move, in the target frame (and the servicer's ring target, which is fixed in the camera
    frame, if the scenario has one).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        parts: Mapping[str, float] | None = None,
        extra_shapes: Mapping[str, dict[str, Any]] | None = None,
    ) -> None:
        """Args:
        scenario: what to render.
        parts: truth-render mode: only these parts, black and emitting the given radiance
            (see `target_shapes`); no light.
        extra_shapes: more Mitsuba shapes in the target frame (e.g. emissive markers).
        """
        self.scenario = scenario
        mi, self.variant = load_mitsuba(scenario.render.variant)
        self.mi = mi
        calib = scenario.rig.calibration()
        ss = AREA_SUPERSAMPLE if scenario.render.resampling == "area" else 1
        self.views = [make_view("left", calib.left, Rigid3.identity(), ss)]
        if calib.right is not None and calib.right_from_left is not None:
            self.views.append(make_view("right", calib.right, calib.right_from_left, ss))
        shapes = target_shapes(mi, scenario.target, scenario.seed, emissive=parts)
        all_shapes = {**shapes.shapes, **(extra_shapes or {})}
        rings_cfg = scenario.servicer_rings if parts is None else None
        self._rings = RingsShapes(mi, rings_cfg) if rings_cfg is not None else None
        self._rings_ids: RingsShapes | None = None
        if self._rings is not None:
            all_shapes.update(self._rings.shapes)
        dark = {
            "type": "point",
            "position": [0.0, 0.0, 0.0],
            "intensity": {"type": "rgb", "value": [0.0] * 3},
        }
        light = self._light_dict(Rigid3.identity()) if parts is None else dark
        # optimize=False: Mitsuba would otherwise merge shapes that share a BSDF.
        lc = scenario.light
        # Earthshine: radiance L of a uniform environment gives irradiance pi L.
        ambient = lc.earthshine * lc.intensity / math.pi if parts is None else 0.0
        self.scene = mi.load_dict(
            scene_dict(all_shapes, light, scenario.render.max_depth, ambient), optimize=False
        )
        self.params = mi.traverse(self.scene)
        self._id_scene = None
        self._id_params: Any = None
        if parts is None and scenario.render.masks:
            # Object ids: every part emits its mask id; one sample per pixel, no light.
            ids = target_shapes(
                mi,
                scenario.target,
                scenario.seed,
                emissive={p: float(i) for p, i in MASK_IDS.items() if i > 0},
            )
            id_shapes = dict(ids.shapes)
            if rings_cfg is not None:
                # The ring plate is not the target: black (id 0), but it hides what is behind.
                self._rings_ids = RingsShapes(mi, rings_cfg, black=True)
                id_shapes.update(self._rings_ids.shapes)
            self._id_scene = mi.load_dict(scene_dict(id_shapes, dark, 1), optimize=False)
            self._id_params = mi.traverse(self._id_scene)

    def _light_dict(self, target_from_left: Rigid3) -> dict[str, Any]:
        lc = self.scenario.light
        if lc.kind == "point":
            pos = target_from_left.apply(np.asarray(lc.position_m, float))
            return {
                "type": "point",
                "position": pos.tolist(),
                "intensity": {"type": "rgb", "value": [lc.intensity] * 3},
            }
        d = target_from_left.rotate(np.asarray(lc.direction, float))
        return {
            "type": "directional",
            "to_world": self.mi.ScalarTransform4f(_look_along(d).tolist()),
            "irradiance": {"type": "rgb", "value": [lc.intensity] * 3},
        }

    def _move_light(self, target_from_left: Rigid3, t_s: float) -> None:
        lc = self.scenario.light.at(t_s)
        if "light.position" in self.params:
            if lc.kind == "point":
                pos = target_from_left.apply(np.asarray(lc.position_m, float))
                self.params["light.position"] = self.mi.Point3f(*pos.tolist())
        elif "light.to_world" in self.params:
            d = target_from_left.rotate(np.asarray(lc.direction, float))
            self.params["light.to_world"] = self.mi.Transform4f(_look_along(d).tolist())
        self.params.update()

    def exposure_scale(self, left_cam_from_target: Rigid3, t_s: float = 0.0) -> float:
        """Radiance -> fraction-of-full-scale factor for this frame at time ``t_s`` [s] (see
        SensorConfig; a turning lamp changes its distance to the target)."""
        sc, lc = self.scenario.sensor, self.scenario.light.at(t_s)
        if sc.exposure == "fixed":
            return sc.gain
        if lc.kind == "point":
            d2 = float(np.sum((left_cam_from_target.t - np.asarray(lc.position_m)) ** 2))
            irradiance = lc.intensity / d2
        else:
            irradiance = lc.intensity
        return sc.white_level * math.pi / irradiance

    def frame_time(self, frame: int) -> float:
        """Time [s] of frame index ``frame`` (``frame / rate_hz``, as `trajectory`)."""
        return frame / self.scenario.rate_hz

    def _seed(self, frame: int, view: int, stream: int) -> int:
        return (self.scenario.seed * 1_000_003 + frame * 8 + view * 2 + stream) % (2**32)

    def radiance(
        self, frame: int, left_cam_from_target: Rigid3, spp: int | None = None
    ) -> dict[str, np.ndarray]:
        """Linear radiance per camera, (H, W, 3) float32, distortion applied, no noise. The
        light is placed as at the frame's time (`frame_time`)."""
        target_from_left = left_cam_from_target.inverse()
        self._move_light(target_from_left, self.frame_time(frame))
        if self._rings is not None:
            self._rings.place(self.params, target_from_left @ self._rings.cfg.true_pose())
            self.params.update()
        out = {}
        for k, view in enumerate(self.views):
            target_from_cam = target_from_left @ view.cam_from_left.inverse()
            n = spp or self.scenario.render.spp
            # the same samples per output pixel, spread over its sub-pixels
            n = max(1, math.ceil(n / view.supersample**2))
            sensor = self.mi.load_dict(sensor_dict(self.mi, view.canvas, target_from_cam, n))
            img = np.array(
                self.mi.render(self.scene, sensor=sensor, seed=self._seed(frame, k, 0)),
                dtype=np.float32,
            )
            out[view.name] = distort(view, img, cubic=self.scenario.render.resampling == "cubic")
        return out

    def masks(self, frame: int, left_cam_from_target: Rigid3) -> dict[str, np.ndarray]:
        """Object-id masks per camera, (H, W) uint8 (``MASK_IDS``; one sample per pixel)."""
        if self._id_scene is None:
            raise RenderError("this renderer was built without masks (render.masks = false)")
        target_from_left = left_cam_from_target.inverse()
        if self._rings_ids is not None:
            self._rings_ids.place(
                self._id_params, target_from_left @ self._rings_ids.cfg.true_pose()
            )
            self._id_params.update()
        out = {}
        for k, view in enumerate(self.views):
            target_from_cam = target_from_left @ view.cam_from_left.inverse()
            sensor = self.mi.load_dict(sensor_dict(self.mi, view.canvas, target_from_cam, 1))
            ids = np.array(
                self.mi.render(self._id_scene, sensor=sensor, spp=1, seed=self._seed(frame, k, 1))
            )[..., 0]
            out[view.name] = np.rint(distort(view, ids, nearest=True)).astype(np.uint8)
        return out

    def expose(self, frame: int, view_index: int, radiance: np.ndarray, scale: float) -> np.ndarray:
        """Sensor model: radiance (H, W, 3) -> noisy quantised image, BGR or grey."""
        sc = self.scenario.sensor
        rng = np.random.default_rng([self.scenario.seed, frame, view_index, 7])
        x = np.clip(radiance.astype(np.float64) * scale, 0.0, 8.0)
        if sc.mono:
            x = x @ np.array([0.2126, 0.7152, 0.0722])
        electrons = rng.poisson(x * sc.full_well_e).astype(np.float64)
        electrons += rng.normal(0.0, sc.read_noise_e, size=electrons.shape)
        top = 2**sc.bit_depth - 1
        dn = np.clip(np.rint(electrons / sc.full_well_e * top), 0, top)
        img = dn.astype(np.uint8 if sc.bit_depth == 8 else np.uint16)
        return img if sc.mono else np.ascontiguousarray(img[..., ::-1])

    def frame_images(
        self, frame: int, left_cam_from_target: Rigid3
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
        """Final images (and masks, if configured) of one frame, keyed by camera name."""
        rad = self.radiance(frame, left_cam_from_target)
        scale = self.exposure_scale(left_cam_from_target, self.frame_time(frame))
        images = {
            v.name: self.expose(frame, k, rad[v.name], scale) for k, v in enumerate(self.views)
        }
        masks = self.masks(frame, left_cam_from_target) if self.scenario.render.masks else None
        return images, masks


def target_geometry(scenario: Scenario) -> TargetGeometry:
    """target.yaml of a rendered scenario: the target's geometry, plus the servicer's ring
    target (extra key ``servicer_rings``, `satpose.datasets.servicer_rings.to_yaml`) if any."""
    tg = geometry(scenario.target)
    if scenario.servicer_rings is None:
        return tg
    return replace(
        tg, extras={**tg.extras, "servicer_rings": rings_to_yaml(scenario.servicer_rings)}
    )


def render_sequence(
    scenario: Scenario,
    out: str | Path,
    *,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Render ``scenario`` into the sequence folder ``out`` (format v1, written atomically).

    Args:
        progress: called with the frame index after each frame is written.

    Returns:
        The sequence folder.
    """
    if scenario.board is not None:
        from satpose.datasets.board import render_board_sequence

        return render_board_sequence(scenario, out, overwrite=overwrite, progress=progress)
    calib = scenario.rig.calibration()
    traj = trajectory(scenario)
    # Open the writer first: a bad output folder fails before the scene is built.
    writer = SequenceWriter(
        out,
        name=scenario.name,
        kind="stereo" if calib.is_stereo else "mono",
        rate_hz=scenario.rate_hz,
        calibration=calib,
        target=target_geometry(scenario),
        overwrite=overwrite,
    )
    with writer:
        renderer = StereoRenderer(scenario)
        writer.generator = {
            "tool": "satpose-render",
            "version": _version(),
            "variant": renderer.variant,
            "scenario": to_plain(scenario),
        }
        for k in range(scenario.frames):
            pose = traj.left_cam_from_target[k]
            images, masks = renderer.frame_images(k, pose)
            writer.add_frame(
                k,
                float(traj.t_s[k]),
                images["left"],
                images.get("right"),
                truth=pose,
                angular_velocity=traj.angular_velocity[k],
                linear_velocity=traj.linear_velocity[k],
                masks=masks,
            )
            if progress is not None:
                progress(k)
    return Path(out)
