"""The servicer's ring target: config checks, target.yaml round trip, the mounting error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from satpose.datasets.errors import ConfigError, SequenceError
from satpose.datasets.geometry import rotation_angle
from satpose.datasets.scenarios import preset
from satpose.datasets.servicer_rings import ServicerRingsConfig, from_yaml, to_yaml


def test_round_trip_and_mount_error() -> None:
    cfg = ServicerRingsConfig(mount_error_deg=(0.5, 0.0, 0.0))
    info = from_yaml(to_yaml(cfg), "target.yaml")
    assert np.allclose(info.edge_radii_m, [0.010, 0.015, 0.025, 0.030, 0.040, 0.045])
    assert info.nominal is not None and info.truth is not None
    assert np.allclose(info.nominal.t, cfg.position_m, atol=1e-12)
    # the camera turned 0.5 deg about its centre: the rings move by 0.5 deg, same distance
    dR = info.truth.R @ info.nominal.R.T
    assert math.degrees(float(rotation_angle(dR))) == pytest.approx(0.5, abs=1e-9)
    assert np.linalg.norm(info.truth.t) == pytest.approx(np.linalg.norm(info.nominal.t))
    # the rings-check preset carries the target; bracket-final does not
    assert preset("rings-check").servicer_rings is not None
    assert preset("bracket-final").servicer_rings is None


def test_bad_config_and_yaml() -> None:
    with pytest.raises(ConfigError, match="increase"):
        ServicerRingsConfig(bands_m=((0.02, 0.01),))
    with pytest.raises(ConfigError, match="plate"):
        ServicerRingsConfig(plate_half_m=0.03)
    with pytest.raises(SequenceError, match="bands_m"):
        from_yaml({"bands_m": [[0.01]]}, "target.yaml")
    with pytest.raises(SequenceError, match="left_cam_from_rings_nominal"):
        from_yaml(
            {"bands_m": [[0.01, 0.02]], "left_cam_from_rings_nominal": {"t": [0, 0]}},
            "target.yaml",
        )
