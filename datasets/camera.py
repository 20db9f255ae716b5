"""Pinhole camera with radial-tangential distortion (OpenCV's 5-parameter model).

Pixel convention: the centre of the top-left pixel is (0, 0) (OpenCV). Camera frame: OpenCV,
x right, y down, z forward. Distortion ``dist = [k1, k2, p1, p2, k3]`` maps normalised
coordinates ``(x, y) = (X/Z, Y/Z)`` to distorted ones exactly as ``cv2.projectPoints`` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from satpose.datasets.errors import SatposeError

_UNDISTORT_BLOCK = 1 << 15
"""Points per Newton block in `PinholeCamera.undistort_points`."""


class CameraError(SatposeError):
    """Invalid camera parameters."""


@dataclass(frozen=True, kw_only=True)
class PinholeCamera:
    """Intrinsics of one camera.

    Attributes:
        width, height: image size [px].
        K: 3x3 intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` [px].
        dist: ``[k1, k2, p1, p2, k3]`` radial-tangential distortion (all zero = none).
        model: model name as written in calib.yaml; only ``pinhole-radtan`` exists in format v1.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    model: str = "pinhole-radtan"

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=float).reshape(3, 3) if np.size(self.K) == 9 else None
        if K is None:
            raise CameraError(f"K must have 9 numbers, got {np.size(self.K)}")
        dist = np.array(self.dist, dtype=float).reshape(-1)
        if dist.size == 4:
            dist = np.append(dist, 0.0)
        if dist.size != 5:
            raise CameraError(
                f"dist must have 4 or 5 numbers [k1, k2, p1, p2, k3], got {dist.size}"
            )
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
            raise CameraError("K or dist holds a NaN or infinite value")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise CameraError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        if self.model != "pinhole-radtan":
            raise CameraError(
                f"unknown camera model {self.model!r}; format v1 knows 'pinhole-radtan'"
            )
        K.setflags(write=False)
        dist.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (self.width, self.height)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion to normalised coordinates ``(N, 2)`` -> distorted ``(N, 2)``."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def normalized_to_pixels(self, xy: np.ndarray, distort: bool = True) -> np.ndarray:
        """Normalised coordinates ``(N, 2)`` to pixels ``(N, 2)``, distorting first if asked."""
        d = self.distort_normalized(xy) if distort else np.asarray(xy, float).reshape(-1, 2)
        u = self.K[0, 0] * d[:, 0] + self.K[0, 1] * d[:, 1] + self.K[0, 2]
        v = self.K[1, 1] * d[:, 1] + self.K[1, 2]
        return np.stack([u, v], axis=1)

    def project(self, points_cam: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project 3-D points ``(N, 3)`` in this camera's frame [m] to pixels ``(N, 2)``.

        Points with ``Z <= 0`` come out as NaN.
        """
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        return self.normalized_to_pixels(xy, distort=distort)

    def distortion_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(distorted normalised) / d(normalised) at ``xy`` (N, 2) -> (N, 2, 2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        J = np.empty((xy.shape[0], 2, 2))
        J[:, 0, 0] = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
        J[:, 0, 1] = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
        J[:, 1, 0] = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
        J[:, 1, 1] = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
        return J

    def undistort_points(self, pixels: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted pixels ``(N, 2)`` to undistorted normalised coordinates ``(N, 2)``.

        Newton's method on the distortion model (analytic Jacobian), so that
        ``normalized_to_pixels(undistort_points(p)) == p`` to ~1e-10 px wherever the model is
        invertible (inside the image for any sane lens).
        """
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        Kinv = np.linalg.inv(self.K)
        h = np.c_[px, np.ones(px.shape[0])] @ Kinv.T
        xd = h[:, :2] / h[:, 2:3]
        if not self.has_distortion:
            return xd
        x = xd.copy()
        # Newton per block of points: blocks that fit the cache are several times faster
        # than whole-array passes over millions of points (the renderer's distortion map).
        for a in range(0, x.shape[0], _UNDISTORT_BLOCK):
            x[a : a + _UNDISTORT_BLOCK] = self._undistort_block(
                x[a : a + _UNDISTORT_BLOCK], xd[a : a + _UNDISTORT_BLOCK], iterations
            )
        return x

    def _undistort_block(self, x: np.ndarray, xd: np.ndarray, iterations: int) -> np.ndarray:
        for _ in range(iterations):
            r = self.distort_normalized(x) - xd
            if np.max(np.abs(r), initial=0.0) < 1e-14:
                break
            J = self.distortion_jacobian(x)
            # the 2x2 Newton step in closed form (np.linalg.solve is several times slower)
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            x = x - np.stack(
                [
                    (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det,
                    (J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0]) / det,
                ],
                axis=1,
            )
        return x

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same camera resampled to another image size (same field of view horizontally).

        The principal point keeps its relative position (pixel-centre convention respected).
        Focal lengths scale with the width ratio on both axes, so square pixels stay square.
        """
        s = width / self.width
        sy = height / self.height
        K = self.K.copy()
        K[0, 0] *= s
        K[0, 1] *= s
        K[1, 1] *= s
        K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return PinholeCamera(width=width, height=height, K=K, dist=self.dist, model=self.model)
