"""Image preparation: grey float images with lens distortion removed, and quality checks.

Everything downstream works on undistorted ("ideal") images of each camera with calib.yaml's
own ``K`` (no rectification): straight panel edges stay straight, the ring stays an exact
ellipse, and a pixel maps through ``K`` alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import SatposeError


class ImageError(SatposeError):
    """An image cannot be used at all (wrong shape or type)."""


_INTERPOLATION = {
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "lanczos4": cv2.INTER_LANCZOS4,
}


@dataclass(frozen=True, kw_only=True)
class PreprocessConfig:
    """Image checks.

    Attributes:
        dark_level: an image whose 99.5th percentile is below this (fraction of full scale)
            is "too dark": nothing is detected in it.
        saturated_fraction: an image with more than this fraction of saturated pixels is
            "saturated": nothing is detected in it.
        interpolation: how the undistorted image is resampled from the raw one,
            ``"linear"``, ``"cubic"`` or ``"lanczos4"``.
    """

    dark_level: float = 0.02
    saturated_fraction: float = 0.5
    interpolation: str = "linear"

    def __post_init__(self) -> None:
        if self.interpolation not in _INTERPOLATION:
            raise ValueError(
                f"preprocess.interpolation must be one of {sorted(_INTERPOLATION)}, "
                f"got {self.interpolation!r}"
            )


@dataclass(frozen=True)
class PreparedImage:
    """One camera's image ready for detection.

    Attributes:
        gray: (H, W) float32 in [0, 1], undistorted.
        gray8: the same as uint8 (for OpenCV functions that need 8-bit input).
        problem: why the image is unusable (``"too dark"``, ``"saturated"``,
            ``"non-finite pixel values (NaN/inf) in N pixels"``), or None.
    """

    gray: np.ndarray
    gray8: np.ndarray
    problem: str | None


class Undistorter:
    """Removes one camera's lens distortion (maps computed once)."""

    def __init__(self, camera: PinholeCamera, config: PreprocessConfig | None = None) -> None:
        self.camera = camera
        self.config = config or PreprocessConfig()
        if camera.has_distortion:
            # Fixed-point maps (integer pixel + 1/32 px fraction): bilinear remap with float
            # maps quantises the fraction to 1/32 px in OpenCV 4.x but interpolates exactly
            # in 5.x (up to 2/255 apart on a rendered frame, enough to change which line
            # segments LSD reports); with fixed-point maps both give the same image.
            mx, my = cv2.initUndistortRectifyMap(
                camera.K, camera.dist, None, camera.K, camera.size, cv2.CV_32FC1
            )
            self._maps: tuple[np.ndarray, np.ndarray] | None = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        else:
            self._maps = None

    def __call__(self, image: np.ndarray) -> PreparedImage:
        """Grey, [0, 1], undistorted. Accepts (H, W) or (H, W, 3) BGR, uint8 or uint16."""
        img = self._checked(image)
        return self._undistorted(img, self._gray(img))

    def colour_contrast(
        self, image: np.ndarray, dominant: np.ndarray | None = None
    ) -> PreparedImage | None:
        """The colour-contrast image of a BGR ``image``, undistorted like `__call__`: per
        pixel the length of its colour's component off the ``dominant`` colour (a unit BGR
        vector, `dominant_colour`; None: this image's own), [0, 1]. A surface of the
        dominant colour is 0 there whatever its brightness, so the brightness texture of
        the panel that fills most of the view (foil facets, MLI wrinkles) vanishes, while a
        surface of another colour is an edge: a blue anodised rim on grey foil of the same
        luminance, a neutral or dark blue rim on gold foil. The component is linear in the
        colour, so a pixel that mixes a rim and a panel of the dominant colour (an edge) is
        the same mixture of their values and the edge keeps its place. None for a grey
        (2-D) image; an image without another colour is "too dark" (its
        `PreparedImage.problem`)."""
        img = self._checked(image)
        if img.ndim != 3 or img.shape[2] != 3:
            return None
        bgr = cv2.merge([self._gray(np.ascontiguousarray(img[..., k])) for k in range(3)])
        u = dominant_colour([image]) if dominant is None else dominant
        if u is None:
            u = np.full(3, 1.0 / math.sqrt(3.0))
        along = cv2.transform(bgr, np.asarray(u, np.float32).reshape(1, 3))
        off = cv2.subtract(bgr, cv2.merge([along * np.float32(c) for c in u]))
        length = cv2.sqrt(cv2.transform(off * off, np.ones((1, 3), np.float32)))
        return self._undistorted(img, length)

    def _checked(self, image: np.ndarray) -> np.ndarray:
        """``image`` as an array, (H, W) or (H, W, C) of this camera's size.

        Raises:
            ImageError: another shape."""
        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.shape[:2] != (self.camera.height, self.camera.width):
            raise ImageError(
                f"image of shape {img.shape} does not match the camera "
                f"({self.camera.width}x{self.camera.height})"
            )
        return img

    def _undistorted(self, img: np.ndarray, gray: np.ndarray) -> PreparedImage:
        """``gray`` (float32 [0, 1] of the raw ``img``) undistorted, prepared and checked."""
        if self._maps is not None:
            gray = cv2.remap(
                gray,
                self._maps[0],
                self._maps[1],
                _INTERPOLATION[self.config.interpolation],
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.0,
            )
        return self._prepared(gray, _nonfinite(img))

    def crop(self, image: np.ndarray, box: tuple[int, int, int, int]) -> PreparedImage:
        """`__call__` restricted to the undistorted pixels ``x0 <= x < x1, y0 <= y < y1``
        (``box``, clipped to the image): the same values as that part of the full result, at
        a cost that scales with the box (a small far target in a large image). The checks
        ("too dark", "saturated") look at the box only.

        Raises:
            ImageError: as `__call__`, or an empty box.
        """
        img = self._checked(image)
        h, w = img.shape[:2]
        x0, y0 = max(int(box[0]), 0), max(int(box[1]), 0)
        x1, y1 = min(int(box[2]), w), min(int(box[3]), h)
        if x1 <= x0 or y1 <= y0:
            raise ImageError(f"empty crop box {box} for a {w}x{h} image")
        if self._maps is None:
            sx0, sy0, sx1, sy1 = x0, y0, x1, y1
        else:
            xy = self._maps[0][y0:y1, x0:x1]  # integer parts (x, y); [1] holds the fraction
            # source pixels the interpolation's taps need (Lanczos-4's reach 3 before and
            # 4 after; +1 margin each side)
            sx0 = max(int(xy[..., 0].min()) - 4, 0)
            sy0 = max(int(xy[..., 1].min()) - 4, 0)
            sx1 = min(int(xy[..., 0].max()) + 6, w)
            sy1 = min(int(xy[..., 1].max()) + 6, h)
        # The source window keeps the image's own border, so the constant border of remap
        # applies exactly where it applies to the full image.
        src = self._gray(img[sy0:sy1, sx0:sx1])
        if self._maps is None:
            gray = src
        else:
            gray = cv2.remap(
                src,
                xy - np.array([sx0, sy0], np.int16),
                self._maps[1][y0:y1, x0:x1],
                _INTERPOLATION[self.config.interpolation],
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.0,
            )
        return self._prepared(np.ascontiguousarray(gray), _nonfinite(img[y0:y1, x0:x1]))

    def _gray(self, img: np.ndarray) -> np.ndarray:
        """(H, W) float32 grey in [0, 1] of an (H, W[, 3]) uint8/uint16/float image."""
        if img.dtype == np.uint8:
            scale = 1 / 255.0
        elif img.dtype == np.uint16:
            scale = 1 / 65535.0
        elif np.issubdtype(img.dtype, np.floating):
            scale = 1.0
            img = np.nan_to_num(img, nan=0.0, posinf=1.0, neginf=0.0)
        else:
            raise ImageError(f"unsupported pixel type {img.dtype}")
        if img.ndim == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
        return img.astype(np.float32) * np.float32(scale)

    def _prepared(self, gray: np.ndarray, nonfinite: int = 0) -> PreparedImage:
        """The 8-bit copy and the image checks of an undistorted grey image (``nonfinite``:
        NaN/inf pixels of the input, zeroed in ``gray``; any makes the image unusable: no
        camera writes them, so the data is corrupt)."""
        # Rounded, saturated 8-bit copy (OpenCV: far faster than numpy's clip + astype).
        gray8 = cv2.convertScaleAbs(np.maximum(gray, 0.0), alpha=255.0)
        # Image checks from the 8-bit histogram (1/255 resolution is plenty for them).
        hist = cv2.calcHist([gray8], [0], None, [256], [0, 256]).ravel()
        cum = np.cumsum(hist) / gray8.size
        problem = None
        if nonfinite:
            problem = f"non-finite pixel values (NaN/inf) in {nonfinite} pixels"
        elif np.searchsorted(cum, 0.995) / 255.0 < self.config.dark_level:
            problem = "too dark"
        elif 1.0 - cum[253] > self.config.saturated_fraction:  # pixels >= 254/255
            problem = "saturated"
        return PreparedImage(gray, gray8, problem)

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Raw (distorted) pixels (N, 2) to undistorted pixels (N, 2)."""
        xy = self.camera.undistort_points(pixels)
        return self.camera.normalized_to_pixels(xy, distort=False)


def dominant_colour(images: Sequence[np.ndarray], lit_fraction: float = 0.1) -> np.ndarray | None:
    """The commonest colour of the lit pixels of BGR ``images`` (one camera's, or both of a
    stereo pair, so that both get the same colour contrast) as a unit BGR vector: the median
    chromaticity (each channel over the sum of the three) of the pixels whose sum exceeds
    ``lit_fraction`` of the images' 99.5th percentile. None for grey images, non-finite
    values or nothing lit."""
    bgr = [np.asarray(im, np.float32) for im in images if np.ndim(im) == 3 and im.shape[2] == 3]
    if not bgr:
        return None
    pixels = np.concatenate([b[::2, ::2].reshape(-1, 3) for b in bgr])  # every 4th: plenty
    total = pixels.sum(axis=1)
    if not np.all(np.isfinite(total)):
        return None
    top = float(np.percentile(total, 99.5))
    lit = total > lit_fraction * top
    if not (top > 0 and lit.any()):
        return None
    c = np.median(pixels[lit] / total[lit, None], axis=0)
    n = float(np.linalg.norm(c))
    return c / n if n > 0 else None


def _nonfinite(img: np.ndarray) -> int:
    """Number of pixels of ``img`` (H, W[, C]) with a NaN or infinite value (0 for integers)."""
    if not np.issubdtype(img.dtype, np.floating):
        return 0
    bad = ~np.isfinite(img)
    return int(np.count_nonzero(bad.any(axis=2) if bad.ndim == 3 else bad))
