"""The spin-far preset (seed 001's far, fast spinner) and the turning light.

Tolerances: rotations are exact up to floating point (1e-12); the preset's requirements are
stated ranges (satellite 40-200 px across, spin axis not along the line of sight).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from satpose.datasets.errors import ConfigError
from satpose.datasets.scenarios import LightConfig, preset, scaled, trajectory
from satpose.datasets.target import bracket_points_p, layout


def _wing_tips_target(s) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The 8 outer corners of the solar wings and the bus' 8 corners, target frame [m]."""
    cfg = s.target
    lay = layout(cfg)
    w = cfg.wings
    pts = []
    for side in (1, -1):
        _, _, P5 = bracket_points_p(cfg, side)
        x = P5[0] + side * (w.gap_m + w.span_m)
        for dy in (-w.chord_m / 2, w.chord_m / 2):
            for dz in (0.0, -w.thickness_m):
                pts.append([x, P5[1] + dy, P5[2] + dz])
    c = lay.panel_center
    for sx in (-1, 1):
        for sy in (-1, 1):
            for z in (lay.bus_front_z, lay.bus_back_z):
                pts.append([c[0] + sx * cfg.bus.width_m / 2, c[1] + sy * cfg.bus.height_m / 2, z])
    return lay.target_from_panel.apply(np.array(pts))


def test_spin_far_preset() -> None:
    s = preset("spin-far")
    assert not s.rig.stereo and s.rate_hz == 1.0 and s.frames == 150
    assert s.rig.calibration().right is None
    tr = trajectory(s)
    np.testing.assert_allclose(np.degrees(np.linalg.norm(tr.angular_velocity, axis=1)), 60.0)
    cam = s.rig.calibration().left
    pts = _wing_tips_target(s)
    for T in tr.left_cam_from_target:
        uv = cam.project(T.apply(pts))
        extent = float(np.max(np.linalg.norm(uv[:, None] - uv[None], axis=-1)))
        assert 40.0 <= extent <= 200.0, extent
        assert np.all((uv > 0) & (uv < [cam.width - 1, cam.height - 1]))
        axis = T.R @ tr.angular_velocity[0] / np.linalg.norm(tr.angular_velocity[0])
        los = T.t / np.linalg.norm(T.t)
        angle = math.degrees(math.acos(abs(float(axis @ los))))
        assert 20.0 < angle < 70.0, angle  # neither along the line of sight nor in the image


def test_light_turns_about_its_axis() -> None:
    fixed = LightConfig(kind="sun", direction=(0.0, 0.0, 1.0))
    assert fixed.at(123.0) is fixed  # a fixed light is the same object (renders unchanged)
    turning = replace(
        fixed, rotation_deg_s=2.0, rotation_axis=(0.0, 3.0, 0.0), position_m=(0, 0, 1)
    )
    at = turning.at(45.0)  # 90 deg about +y: z -> x
    np.testing.assert_allclose(at.direction, (1.0, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(at.position_m, (1.0, 0.0, 0.0), atol=1e-12)
    assert at.rotation_deg_s == 2.0 and turning.at(0.0).direction == turning.direction
    s = preset("spin-far")
    d0 = np.asarray(s.light.at(0.0).direction)
    d1 = np.asarray(s.light.at(149.0).direction)
    turned = math.degrees(math.acos(d0 @ d1 / np.linalg.norm(d0) / np.linalg.norm(d1)))
    assert 10.0 < turned < 15.0  # 0.1 deg/s about y, the direction partly along y


@pytest.mark.parametrize(
    "kwargs",
    [{"rotation_deg_s": math.inf}, {"rotation_axis": (0.0, 0.0, 0.0)}],
)
def test_light_config_validation(kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match=r"light\.rotation"):
        LightConfig(**kwargs)  # type: ignore[arg-type]


@pytest.mark.render
def test_turning_light_changes_the_images_after_the_first_frame() -> None:
    """Frame 0 renders identically with and without the turn; later frames differ."""
    from satpose.datasets.render import StereoRenderer

    s = scaled(preset("tumble"), frames=6, size=(64, 48), spp=2)
    t = s.target
    coarse = replace(  # 2 cm foil texels: the scene builds in a second instead of ten
        t,
        bus=replace(t.bus, foil=replace(t.bus.foil, texel_m=0.02)),
        panel=replace(t.panel, foil=replace(t.panel.foil, texel_m=0.02)),
    )
    s = replace(
        s, target=coarse, rig=replace(s.rig, stereo=False), render=replace(s.render, masks=False)
    )
    turning = replace(s, light=replace(s.light, rotation_deg_s=3.0))
    poses = trajectory(s).left_cam_from_target
    a, b = StereoRenderer(s), StereoRenderer(turning)
    first = [r.frame_images(0, poses[0])[0]["left"] for r in (a, b)]
    np.testing.assert_array_equal(first[0], first[1])
    later = [r.frame_images(5, poses[5])[0]["left"].astype(float) for r in (a, b)]
    assert np.abs(later[0] - later[1]).mean() > 1.0  # 30 deg of sun motion at t = 10 s
