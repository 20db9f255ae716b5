"""Shared fixtures: a synthetic sequence (no rendering) and a tiny rendered one."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration, Ring, SequenceWriter, TargetGeometry

TINY = ["--frames", "3", "--size", "320x256", "--spp", "4"]
"""Arguments that scale a preset down for tests (see the brief: 320x256, 4 spp)."""

BOARD_SIZE = (640, 480)
BOARD_VIEWS = 20
"""The rendered calibration board of `board_sequence`: image size and number of views."""


def synthetic_calibration(width: int = 48, height: int = 32) -> Calibration:
    K = np.array([[60.0, 0, 23.5], [0, 60.0, 15.5], [0, 0, 1]])
    cam = PinholeCamera(width=width, height=height, K=K, dist=[-0.05, 0.01, 0.0, 0.0, 0.0])
    return Calibration(
        left=cam, right=cam, right_from_left=Rigid3.from_rotvec([0.0, 0.01, 0.0], [-0.3, 0.0, 0.0])
    )


def write_synthetic_sequence(path: Path, frames: int = 4, seed: int = 0) -> Path:
    """A small valid stereo sequence with random images, truth and target geometry."""
    rng = np.random.default_rng(seed)
    calib = synthetic_calibration()
    target = TargetGeometry(
        ring=Ring(radius_m=0.3),
        panel_corners=rng.normal(size=(4, 3)),
        components=rng.normal(size=(3, 3)),
        extras={"note": "synthetic"},
    )
    with SequenceWriter(
        path,
        name="synthetic",
        kind="stereo",
        rate_hz=2.0,
        calibration=calib,
        target=target,
        generator={"tool": "tests"},
    ) as w:
        for k in range(frames):
            left = rng.integers(0, 256, size=(32, 48, 3), dtype=np.uint8)
            right = rng.integers(0, 256, size=(32, 48), dtype=np.uint8)
            pose = Rigid3.from_rotvec(
                rng.normal(size=3), rng.normal(size=3) + np.array([0.0, 0.0, 5.0])
            )
            masks = {"left": (left[..., 0] > 128).astype(np.uint8)}
            w.add_frame(
                k,
                0.5 * k,
                left,
                right,
                truth=pose,
                angular_velocity=rng.normal(size=3),
                linear_velocity=rng.normal(size=3),
                masks=masks,
            )
    return path


@pytest.fixture
def synthetic_sequence(tmp_path: Path) -> Path:
    return write_synthetic_sequence(tmp_path / "seq")


@pytest.fixture
def make_sequence():  # type: ignore[no-untyped-def]
    """The `write_synthetic_sequence` function, for tests that need several sequences."""
    return write_synthetic_sequence


@pytest.fixture(scope="session")
def rendered_tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper-docking, 3 frames, 320x256, 4 spp, rendered once per test session via the CLI."""
    from satpose.tools.cli import main

    out = tmp_path_factory.mktemp("render") / "paper-docking"
    assert main(["render", "paper-docking", "--out", str(out), *TINY]) == 0
    return out


@pytest.fixture(scope="session")
def docking_small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper-docking at 640x480 (8 spp), 6 frames starting at 4.5 m."""
    from satpose.datasets.render import render_sequence
    from satpose.datasets.scenarios import preset, scaled

    s = scaled(preset("paper-docking"), frames=6, size=(640, 480), spp=8)
    s = replace(s, motion=replace(s.motion, start_position_m=(0.15, 0.05, 4.5)))
    out = tmp_path_factory.mktemp("docking") / "docking"
    render_sequence(s, out)
    return out


@pytest.fixture(scope="session")
def rendered_spin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """spin-far (mono, 60 deg/s at 1 Hz), 22 frames at 320x256, 4 spp, no masks: enough for
    four 19-frame spin windows. Rendered once per test session."""
    from satpose.datasets.render import render_sequence
    from satpose.datasets.scenarios import preset, scaled

    s = scaled(preset("spin-far"), frames=22, size=(320, 256), spp=4)
    s = replace(s, render=replace(s.render, masks=False))
    out = tmp_path_factory.mktemp("spin") / "spin-far"
    render_sequence(s, out)
    return out


@pytest.fixture(scope="session")
def board_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The calibration preset: 20 views at 640x480, 4 spp, rendered once per test session
    through the CLI."""
    from satpose.tools.cli import main

    out = tmp_path_factory.mktemp("calib") / "calibration"
    size = f"{BOARD_SIZE[0]}x{BOARD_SIZE[1]}"
    args = ["--frames", str(BOARD_VIEWS), "--size", size, "--spp", "4"]
    assert main(["render", "calibration", "--out", str(out), *args]) == 0
    return out


@pytest.fixture(scope="session", autouse=True)
def star_database_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Saved star databases go to a folder of the test session, not the user's cache."""
    from satpose.frontend.stars import CACHE_ENV

    old = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(tmp_path_factory.mktemp("star-databases"))
    yield
    if old is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = old
