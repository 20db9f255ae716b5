"""`satpose rings` end to end on tiny `rings-check` renders: the check passes on the nominal
mounting, flags a 0.5 deg mounting rotation and a 1 % focal-length error, and bad input gives
one-line errors or per-frame reasons."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from satpose.datasets.sequence import load_sequence, write_sequence
from satpose.tools.cli import main

# 512x384: the smallest band edge (10 mm at 0.6 m) is ~12 px across; 4 spp, 2 frames.
TINY = ["--frames", "2", "--size", "512x384", "--spp", "4"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    seq = tmp_path_factory.mktemp("rc") / "seq"
    assert main(["render", "rings-check", "--out", str(seq), *TINY]) == 0
    return seq


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "rings.csv") as fh:
        return list(csv.DictReader(fh))


def _summary(out: Path) -> dict[str, object]:
    return json.loads((out / "summary.json").read_text())


def test_rings_cli_nominal_mounting(tiny: Path, tmp_path: Path) -> None:
    """Every frame gets a pose from all six band edges; against the rendered pose the centre
    is within 2 mm and the normal within 0.5 deg (measured 0.1-0.7 mm, 0.2 deg at this
    size); the check finds the mounting consistent."""
    out = tmp_path / "run"
    assert main(["rings", str(tiny), "--out", str(out), "--overlay-every", "1"]) == 0
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert all(int(r["n_edges"]) == 6 for r in rows)
    assert all(float(r["truth_center_err_mm"]) < 2.0 for r in rows), rows
    assert all(float(r["truth_normal_err_deg"]) < 0.5 for r in rows), rows
    assert _summary(out)["verdict"] == "consistent"
    assert len(list((out / "overlay").glob("*.png"))) == 2


def test_rings_cli_flags_a_rotated_mounting(tmp_path: Path) -> None:
    """The camera rotated 0.5 deg about its x axis relative to its nominal mounting: the
    measured centre departs by ~5 mm (0.6 m x 0.5 deg), far beyond its scatter, and the
    implied mounting rotation is within 0.25 deg of the truth (measured 0.6, -0.04, -0.18)."""
    cfg = tmp_path / "mount.yaml"
    cfg.write_text(yaml.safe_dump({"servicer_rings": {"mount_error_deg": [0.5, 0.0, 0.0]}}))
    seq = tmp_path / "seq"
    assert main(["render", "rings-check", "--out", str(seq), *TINY, "--config", str(cfg)]) == 0
    out = tmp_path / "run"
    assert main(["rings", str(seq), "--out", str(out)]) == 0
    s = _summary(out)
    assert s["verdict"] == "departs"
    assert 4.0 < float(s["center_departure_mm"]) < 6.5  # type: ignore[arg-type]
    rot = np.array(s["mount_rotation_deg"])
    assert np.linalg.norm(rot - [0.5, 0.0, 0.0]) < 0.25, rot
    # against the rendered (perturbed) pose the estimate is as good as on the nominal one
    assert all(float(r["truth_center_err_mm"]) < 2.0 for r in _rows(out))


def test_rings_cli_flags_a_focal_length_error(tiny: Path, tmp_path: Path) -> None:
    """calib.yaml's focal length 1 % too long: the rings appear 1 % farther (~6 mm at 0.6 m),
    which no camera rotation explains (range_departure_mm), and the check flags it."""
    s = load_sequence(tiny)
    K = s.calibration.left.K.copy()
    K[0, 0] *= 1.01
    K[1, 1] *= 1.01
    bad = replace(s, calibration=replace(s.calibration, left=replace(s.calibration.left, K=K)))
    seq = write_sequence(bad, tmp_path / "seq")
    out = tmp_path / "run"
    assert main(["rings", str(seq), "--out", str(out)]) == 0
    summary = _summary(out)
    assert summary["verdict"] == "departs"
    assert 4.0 < float(summary["range_departure_mm"]) < 8.0  # type: ignore[arg-type]


def test_rings_cli_bad_input(
    tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an existing non-empty output folder
    out = tmp_path / "busy"
    out.mkdir()
    (out / "x").write_text("x")
    assert main(["rings", str(tiny), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    # no sequence
    assert main(["rings", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.startswith("satpose rings: error:")
    # bad radii
    assert main(["rings", str(tiny), "--out", str(tmp_path / "o"), "--radii-mm", "30,10"]) == 2
    assert "--radii-mm" in capsys.readouterr().err
    # target.yaml without the ring target and no radii given
    plain = tmp_path / "plain"
    shutil.copytree(tiny, plain)
    t = yaml.safe_load((plain / "target.yaml").read_text())
    del t["servicer_rings"]
    (plain / "target.yaml").write_text(yaml.safe_dump(t))
    assert main(["rings", str(plain), "--out", str(tmp_path / "o")]) == 2
    assert "servicer_rings" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    # ... with the radii given it runs (whole-image search, no nominal pose to compare with)
    radii = "10,15,25,30,40,45"
    assert main(["rings", str(plain), "--out", str(tmp_path / "o"), "--radii-mm", radii]) == 0
    assert _summary(tmp_path / "o")["verdict"] == "no_nominal"
    # a black frame: a reason in rings.csv, not an exception
    dark = tmp_path / "dark"
    shutil.copytree(tiny, dark)
    img = cv2.imread(str(dark / "left" / "000001.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(dark / "left" / "000001.png"), np.zeros_like(img))
    assert main(["rings", str(dark), "--out", str(tmp_path / "d")]) == 0
    rows = _rows(tmp_path / "d")
    assert rows[0]["status"] == "ok"
    assert rows[1]["status"] == "no_pose" and "dark" in rows[1]["reason"]
    # a zero-byte frame: an error row with the reason, a warning, the other frames measured
    empty = tmp_path / "empty"
    shutil.copytree(tiny, empty)
    (empty / "left" / "000001.png").write_bytes(b"")
    assert main(["rings", str(empty), "--out", str(tmp_path / "e")]) == 0
    rows = _rows(tmp_path / "e")
    assert rows[0]["status"] == "ok"
    assert rows[1]["status"] == "error" and "not a readable PNG" in rows[1]["reason"]
    assert _summary(tmp_path / "e")["bad_frames"] == "1 bad frame (of 2): unreadable image 1"
