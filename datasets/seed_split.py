"""The one split of scene-family seeds into a tuning and a validation set.

Every randomised scene family (`satpose.datasets.random_family`, the ring targets;
`satpose.datasets.bracket_family`, the solar-panel brackets) draws its member from the seed
alone, and every family uses this split: `TUNING_SEEDS` may be looked at (images, errors) while
developing and tuning; `VALIDATION_SEEDS` are only scored, never looked at to change a
parameter (docs/renderer.md, "Random family").
"""

from __future__ import annotations

TUNING_SEEDS = range(0, 100)
"""Seeds that may be looked at (images, errors) while developing and tuning."""
VALIDATION_SEEDS = range(1000, 1100)
"""Seeds that are only scored: never looked at to change a parameter."""


def split_of(seed: int) -> str | None:
    """``"tuning"``, ``"validation"`` or None (a seed outside both sets)."""
    if seed in TUNING_SEEDS:
        return "tuning"
    if seed in VALIDATION_SEEDS:
        return "validation"
    return None


def seed_sets() -> str:
    """``"tuning seeds 0-99, validation seeds 1000-1099"``, for messages."""
    return (
        f"tuning seeds {TUNING_SEEDS.start}-{TUNING_SEEDS.stop - 1}, "
        f"validation seeds {VALIDATION_SEEDS.start}-{VALIDATION_SEEDS.stop - 1}"
    )
