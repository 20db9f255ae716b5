"""The one config loader: unknown keys rejected, defaults filled, types converted."""

from __future__ import annotations

from pathlib import Path

import pytest

from satpose.datasets.config import from_plain, load_config, replace_nested, to_plain
from satpose.datasets.errors import ConfigError
from satpose.datasets.scenarios import PRESETS, Scenario, preset


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_round_trips(name: str) -> None:
    s = preset(name)
    assert from_plain(Scenario, to_plain(s)) == s


def test_missing_keys_take_defaults() -> None:
    s = from_plain(Scenario, {"name": "x", "frames": 3, "rate_hz": 1.0})
    assert s.rig.width == 1024 and s.target.ring.outer_radius_m == 0.30


def test_unknown_key_names_its_path() -> None:
    with pytest.raises(ConfigError, match=r"Scenario\.target\.ring: unknown key\(s\) \['radius'\]"):
        from_plain(
            Scenario,
            {"name": "x", "frames": 3, "rate_hz": 1.0, "target": {"ring": {"radius": 0.4}}},
        )


def test_wrong_type_names_its_path() -> None:
    with pytest.raises(ConfigError, match=r"Scenario\.frames: expected an integer"):
        from_plain(Scenario, {"name": "x", "frames": "many", "rate_hz": 1.0})
    with pytest.raises(ConfigError, match=r"Scenario\.light\.kind: must be one of"):
        from_plain(Scenario, {"name": "x", "frames": 1, "rate_hz": 1.0, "light": {"kind": "laser"}})
    with pytest.raises(ConfigError, match=r"position_m: expected 3 values"):
        from_plain(
            Scenario, {"name": "x", "frames": 1, "rate_hz": 1.0, "light": {"position_m": [0, 0]}}
        )


def test_validation_inside_configs_is_reported() -> None:
    with pytest.raises(ConfigError, match="inner_radius_m < outer_radius_m"):
        replace_nested(preset("paper-docking"), {"target": {"ring": {"inner_radius_m": 0.5}}})


def test_replace_nested_keeps_everything_else() -> None:
    s = replace_nested(preset("tumble"), {"target": {"ring": {"outer_radius_m": 0.35}}})
    assert s.target.ring.outer_radius_m == 0.35
    assert s.light == preset("tumble").light


def test_load_config_yaml_and_toml(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("name: a\nframes: 2\nrate_hz: 0.5\nrender: {spp: 2}\n")
    (tmp_path / "b.toml").write_text('name = "b"\nframes = 2\nrate_hz = 0.5\n[render]\nspp = 3\n')
    assert load_config(Scenario, tmp_path / "a.yaml").render.spp == 2
    assert load_config(Scenario, tmp_path / "b.toml").render.spp == 3
    (tmp_path / "c.yaml").write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: not valid YAML"):
        load_config(Scenario, tmp_path / "c.yaml")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(Scenario, tmp_path / "missing.yaml")
