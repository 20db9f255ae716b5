"""Checks that the renderer's truth is exact: projected ground truth vs rendered features.

Two independent checks, run by the tests (small images) and by
``benchmarks/render_truth.py`` (full size):

- `marker_errors`: small emissive spheres at the truth points (ring centre, ring rim, panel
  corners, components) are rendered through the full camera path (canvas, distortion,
  both cameras); their intensity centroids are compared with the points projected by
  ``PinholeCamera.project`` with calib + truth. This validates intrinsics, distortion,
  extrinsics and pose conventions.
- `geometry_errors`: the target's own ring front face and panel front face are rendered
  emissive (no distortion); the area, centroid and second moments of their images are
  compared with the analytic projections of target.yaml's ring circle and panel corners.
  This validates that the rendered target is where target.yaml says it is.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.render import StereoRenderer
from satpose.datasets.scenarios import Scenario
from satpose.datasets.sequence import TargetGeometry
from satpose.datasets.target import geometry

Moments = tuple[float, np.ndarray, np.ndarray]
"""(area [px^2], centroid (2,) [px], covariance (2, 2) [px^2]) of an image region."""


def camera_poses(
    s: Scenario, left_cam_from_target: Rigid3
) -> Iterator[tuple[str, PinholeCamera, Rigid3]]:
    """``(name, camera, cam_from_target)`` for each camera of the scenario's rig."""
    calib = s.rig.calibration()
    yield "left", calib.left, left_cam_from_target
    if calib.right is not None and calib.right_from_left is not None:
        yield "right", calib.right, calib.right_from_left @ left_cam_from_target


def truth_points(s: Scenario, rim_points: int = 8) -> dict[str, np.ndarray]:
    """Named truth points in the target frame: ring centre and rim, corners, components."""
    g = geometry(s.target)
    assert g.ring is not None and g.panel_corners is not None and g.components is not None
    a = np.linspace(0, 2 * np.pi, rim_points, endpoint=False)
    rim = np.c_[g.ring.radius_m * np.cos(a), g.ring.radius_m * np.sin(a), np.zeros(rim_points)]
    return {
        "ring_centre": g.ring.center[None, :],
        "ring_rim": rim,
        "panel_corners": g.panel_corners,
        "components": g.components,
    }


def blob_centroids(
    image: np.ndarray, expected_px: np.ndarray, threshold: float = 0.01
) -> np.ndarray:
    """Intensity-weighted centroid (N, 2) of the blob under each expected pixel (N, 2).

    Raises:
        AssertionError: no blob at an expected position.
    """
    gray = image.mean(axis=2) if image.ndim == 3 else image
    _, labels = cv2.connectedComponents((gray > threshold).astype(np.uint8))
    yy, xx = np.mgrid[0 : gray.shape[0], 0 : gray.shape[1]]
    out = []
    for u, v in expected_px:
        lab = labels[round(v), round(u)]
        if lab == 0:
            raise AssertionError(f"no rendered marker at ({u:.1f}, {v:.1f})")
        w = gray * (labels == lab)
        out.append([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])
    return np.array(out)


def marker_errors(
    s: Scenario, left_cam_from_target: Rigid3, blob_radius_px: float = 2.5, spp: int = 256
) -> dict[str, dict[str, np.ndarray]]:
    """Distance [px] between projected truth points and rendered markers, per camera and
    point group (see the module docstring)."""
    points = truth_points(s)
    stacked = np.vstack(list(points.values()))
    radius = blob_radius_px * float(left_cam_from_target.t[2]) / s.rig.focal_px
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}}
    glow = {"type": "area", "radiance": {"type": "rgb", "value": [1.0] * 3}}
    markers = {
        f"marker{i}": {
            "type": "sphere",
            "center": p.tolist(),
            "radius": radius,
            "bsdf": black,
            "emitter": glow,
        }
        for i, p in enumerate(stacked)
    }
    images = StereoRenderer(s, parts={}, extra_shapes=markers).radiance(
        0, left_cam_from_target, spp=spp
    )
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, cam, cam_from_target in camera_poses(s, left_cam_from_target):
        expected = cam.project(cam_from_target.apply(stacked))
        err = np.linalg.norm(blob_centroids(images[name], expected) - expected, axis=1)
        sizes = np.cumsum([0] + [len(p) for p in points.values()])
        out[name] = {k: err[a:b] for k, a, b in zip(points, sizes[:-1], sizes[1:], strict=True)}
    return out


def circle_moments(K: np.ndarray, cam_from_target: Rigid3, radius: float) -> Moments:
    """Moments of the image of the filled circle of ``radius`` about the target origin in the
    target z = 0 plane, through an undistorted camera ``K``."""
    R, t = cam_from_target.R, cam_from_target.t
    Hinv = np.linalg.inv(K @ np.c_[R[:, 0], R[:, 1], t])
    C = Hinv.T @ np.diag([1.0, 1.0, -(radius**2)]) @ Hinv
    centre = -np.linalg.solve(C[:2, :2], C[:2, 2])
    M = C[:2, :2] / -(C[2, 2] + C[:2, 2] @ centre)
    return float(np.pi / np.sqrt(np.linalg.det(M))), centre, np.linalg.inv(M) / 4


def combine_moments(parts: list[Moments]) -> Moments:
    """Moments of a union (positive areas) minus holes (negative areas)."""
    A = float(sum(a for a, _, _ in parts))
    c = np.sum([a * m for a, m, _ in parts], axis=0) / A
    S = np.sum([a * (cov + np.outer(m, m)) for a, m, cov in parts], axis=0) / A - np.outer(c, c)
    return A, c, S


def polygon_moments(p: np.ndarray) -> Moments:
    """Moments of the filled polygon with vertices ``p`` (N, 2) in order."""
    x, y = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cr = x * y1 - x1 * y
    A = cr.sum() / 2
    c = np.array([((x + x1) * cr).sum(), ((y + y1) * cr).sum()]) / (6 * A)
    sxx = ((x * x + x * x1 + x1 * x1) * cr).sum() / 12
    syy = ((y * y + y * y1 + y1 * y1) * cr).sum() / 12
    sxy = ((x * y1 + 2 * x * y + 2 * x1 * y1 + x1 * y) * cr).sum() / 24
    S = np.array([[sxx, sxy], [sxy, syy]]) / A - np.outer(c, c)
    return float(abs(A)), c, S


def image_moments(image: np.ndarray) -> Moments:
    """Moments of a coverage image (pixel centres at integer coordinates, OpenCV)."""
    w = (image.mean(axis=2) if image.ndim == 3 else image).astype(np.float64)
    yy, xx = np.mgrid[0 : w.shape[0], 0 : w.shape[1]]
    A = w.sum()
    c = np.array([(w * xx).sum(), (w * yy).sum()]) / A
    dx, dy = xx - c[0], yy - c[1]
    S = (
        np.array(
            [[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]
        )
        / A
    )
    return float(A), c, S


@dataclass(frozen=True, kw_only=True)
class MomentError:
    """Rendered vs analytic moments of one part in one camera."""

    centroid_px: float
    area_rel: float
    axes_px: np.ndarray


def geometry_errors(
    s: Scenario, left_cam_from_target: Rigid3, spp: int = 256, truth: TargetGeometry | None = None
) -> dict[str, dict[str, MomentError]]:
    """Rendered ring front face and panel front face vs the analytic projections of the
    ring and panel corners of ``truth`` (default: the target.yaml geometry of ``s``), per
    camera (distortion switched off)."""
    s = replace(s, rig=replace(s.rig, dist_left=(0.0,) * 5, dist_right=(0.0,) * 5))
    g = geometry(s.target) if truth is None else truth
    assert g.ring is not None and g.panel_corners is not None
    r_in = float(g.ring.extras["inner_radius_m"])
    ring = StereoRenderer(s, parts={"ring_front": 1.0}).radiance(0, left_cam_from_target, spp=spp)
    panel = StereoRenderer(s, parts={"panel_front": 1.0}).radiance(0, left_cam_from_target, spp=spp)
    out: dict[str, dict[str, MomentError]] = {}
    for name, cam, cam_from_target in camera_poses(s, left_cam_from_target):
        A_o, c_o, S_o = circle_moments(cam.K, cam_from_target, g.ring.radius_m)
        A_i, c_i, S_i = circle_moments(cam.K, cam_from_target, r_in)
        expected = {
            "ring": combine_moments([(A_o, c_o, S_o), (-A_i, c_i, S_i)]),
            "panel": polygon_moments(cam.project(cam_from_target.apply(g.panel_corners))),
        }
        out[name] = {}
        for part, img in (("ring", ring[name]), ("panel", panel[name])):
            A, c, S = image_moments(img)
            A_ref, c_ref, S_ref = expected[part]
            out[name][part] = MomentError(
                centroid_px=float(np.linalg.norm(c - c_ref)),
                area_rel=abs(A / A_ref - 1),
                axes_px=np.abs(np.sqrt(np.linalg.eigvalsh(S)) - np.sqrt(np.linalg.eigvalsh(S_ref))),
            )
    return out
