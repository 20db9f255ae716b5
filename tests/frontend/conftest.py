"""A small rendered stereo sequence for the frontend tests (rendered once per session)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset, scaled


@pytest.fixture(scope="session")
def docking_small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper-docking at 640x480 (8 spp), 6 frames starting at 4.5 m."""
    s = scaled(preset("paper-docking"), frames=6, size=(640, 480), spp=8)
    s = replace(s, motion=replace(s.motion, start_position_m=(0.15, 0.05, 4.5)))
    out = tmp_path_factory.mktemp("frontend") / "docking"
    render_sequence(s, out)
    return out
