"""Ring seeds from thin bands: a rim that is a closed dark or bright band on a busy panel.

The edge-chain detector (`satpose.frontend.ellipses`) finds a ring from arcs of its edges.
On a panel with strong texture (foil facets, MLI wrinkles) a rim seen as a thin band darker or
brighter than both its inside and its outside (an anodised or painted rim, a rim in shade)
can lose every long arc: the texture's edges cut the band's two edges into pieces that do not
link. A morphological black-hat (dark bands) or top-hat (bright bands) with a disc wider than
the band keeps thin structures of that polarity and flattens wide ones: the band becomes one
bright closed stroke on a darker, speckled background, whose edges the same detector links.
`band_seeds` runs the image's detector on those responses at a few disc sizes. The seeds are
only starting ellipses: `RingTracker.acquire` refines and verifies them on the image's own
sub-pixel edges exactly as it does the detector's candidates.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from satpose.frontend.conics import Ellipse


@dataclass(frozen=True, kw_only=True)
class BandSeedConfig:
    """Thin-band ring seeds (`band_seeds`).

    Attributes:
        enabled: look for band seeds when the detector's candidates give no ring.
        disc_radii_px: radii of the morphological discs (one pass each): a band up to about
            twice a radius wide is kept.
        min_response: a response whose maximum is below this (grey levels of 255) has no
            band and is not searched.
        max_seeds: at most this many seeds, the largest first.
    """

    enabled: bool = True
    disc_radii_px: tuple[int, ...] = (4, 8, 16)
    min_response: float = 12.0
    max_seeds: int = 6

    def __post_init__(self) -> None:
        if not self.disc_radii_px or min(self.disc_radii_px) < 1:
            raise ValueError("band seeds: disc_radii_px must be non-empty and >= 1")
        if self.max_seeds < 1:
            raise ValueError("band seeds: max_seeds must be >= 1")


def band_seeds(
    gray8: np.ndarray,
    detector: Callable[[np.ndarray], Sequence[Any]],
    min_axis_px: float,
    max_axis_ratio: float,
    config: BandSeedConfig,
) -> list[Ellipse]:
    """Ellipses the ``detector`` finds on the black-hat and top-hat responses of a uint8
    image (candidates with an ``ellipse`` attribute), plausible ring sizes only, largest
    first, duplicates merged."""
    found: list[Ellipse] = []
    for radius in config.disc_radii_px:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        for op in (cv2.MORPH_BLACKHAT, cv2.MORPH_TOPHAT):
            resp = cv2.morphologyEx(gray8, op, disc)
            if float(resp.max()) < config.min_response:
                continue
            for c in detector(resp):
                e = c.ellipse
                if not (e.b >= min_axis_px and e.a / e.b <= max_axis_ratio):
                    continue
                if not any(_same(e, f) for f in found):
                    found.append(e)
    found.sort(key=lambda e: -(e.a + e.b))
    return found[: config.max_seeds]


def _same(e: Ellipse, f: Ellipse) -> bool:
    return (
        math.hypot(e.cx - f.cx, e.cy - f.cy) < 0.1 * f.b
        and abs(e.a - f.a) < 0.05 * f.a
        and abs(e.b - f.b) < 0.05 * f.b
    )
