"""``satpose spin``: the rate series, its files, one-line errors."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from satpose.tools.cli import main
from satpose.tools.files import read_measurements
from satpose.tools.spin_cli import SPIN_CSV_COLUMNS


def test_spin_cli_writes_the_rate_series(
    rendered_spin: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["spin", str(rendered_spin), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    with (out / "spin.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0].keys()) == SPIN_CSV_COLUMNS
    assert len(rows) == 22 - 18  # one estimate per frame once the 19-frame buffer is full
    for r in rows:
        assert r["status"] == "ok"
        assert abs(float(r["rate_deg_s"]) - 60.0) < 0.05 and float(r["sigma_deg_s"]) > 0
    assert [float(r["t_s"]) for r in rows] == [18.0, 19.0, 20.0, 21.0]
    assert printed.count(" ok") == 4 and "4 estimates, 4 accepted" in printed
    assert (out / "spin.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(read_measurements(out / "measurements.parquet")) == 22
    assert "window_frames: 19" in (out / "config.yaml").read_text()
    angles = (out / "spin_angles.csv").read_text().splitlines()
    assert angles[0] == "frame,t_s,theta_deg,elongation,failure" and len(angles) == 23
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_spin_cli_errors_are_one_line(
    rendered_spin: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["spin", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("satpose spin: error:") and "\n" not in err
    cfg = tmp_path / "c.yaml"
    cfg.write_text("rate: {window_frames: 30}\n")
    assert (
        main(["spin", str(rendered_spin), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert "22 frames, but the spin buffer needs 30" in err and "\n" not in err
    assert not (tmp_path / "o").exists()
    cfg.write_text("rate: {windw_frames: 30}\n")
    assert (
        main(["spin", str(rendered_spin), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert "windw_frames" in err and "unknown key" in err and "\n" not in err
