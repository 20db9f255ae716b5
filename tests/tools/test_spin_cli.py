"""``satpose spin``: the rate series, its files, one-line errors."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from satpose.tools.cli import main
from satpose.tools.files import read_measurements
from satpose.tools.spin_cli import SPIN_CSV_COLUMNS


def test_spin_cli_writes_the_rate_series(
    rendered_spin: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With the paper's assumption stated (``--max-rate 89``: below the fold) every window of
    the 60 deg/s sequence is accepted."""
    out = tmp_path / "out"
    assert main(["spin", str(rendered_spin), "--out", str(out), "--max-rate", "89"]) == 0
    printed = capsys.readouterr().out
    with (out / "spin.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0].keys()) == SPIN_CSV_COLUMNS
    assert len(rows) == 22 - 18  # one estimate per frame once the 19-frame buffer is full
    for r in rows:
        assert r["status"] == "ok" and r["candidates_deg_s"] == "" and r["reason"] == ""
        assert abs(float(r["rate_deg_s"]) - 60.0) < 0.05 and float(r["sigma_deg_s"]) > 0
    assert [float(r["t_s"]) for r in rows] == [18.0, 19.0, 20.0, 21.0]
    assert printed.count(" ok") == 4 and "4 estimates: 4 accepted" in printed
    assert "0 ambiguous, 0 refused" in printed and "assumed below 89 deg/s" in printed
    assert "max_rate_deg_s: 89.0" in (out / "config.yaml").read_text()
    assert (out / "spin.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(read_measurements(out / "measurements.parquet")) == 22
    assert "window_frames: 19" in (out / "config.yaml").read_text()
    angles = (out / "spin_angles.csv").read_text().splitlines()
    assert angles[0] == "frame,t_s,theta_deg,elongation,failure" and len(angles) == 23
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_spin_cli_reports_the_fold_as_ambiguous_without_a_prior(
    rendered_spin: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """spin-far's outline is symmetric (two equal wings): 60 deg/s samples like 120 deg/s at
    1 Hz and nothing in the outline tells them apart, so by default every window lists both
    (spin.csv, measurements.parquet, the console), never one rate."""
    out = tmp_path / "out"
    assert main(["spin", str(rendered_spin), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    with (out / "spin.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4
    for r in rows:
        assert r["status"] == "ambiguous" and r["rate_deg_s"] == "", r
        cands = [float(c) for c in r["candidates_deg_s"].split(";")]
        assert len(cands) == 2 and abs(cands[0] - 60.0) < 0.05 and abs(cands[1] - 120.0) < 0.05
        assert float(r["sigma_deg_s"]) > 0 and "fit equally well" in r["reason"]
    spins = [m.spin for m in read_measurements(out / "measurements.parquet")[18:]]
    for s, r in zip(spins, rows, strict=True):
        assert s is not None and s.status.value == "ambiguous"
        got = [math.degrees(c) for c in s.candidates_rad_s]
        want = [float(c) for c in r["candidates_deg_s"].split(";")]
        assert np.allclose(got, want, atol=1e-5)
    assert "4 estimates: 0 accepted, 4 ambiguous" in printed and "below 180 deg/s" in printed
    assert printed.count(" ambiguous: ") == 4


def test_spin_cli_summary_counts_refusals_and_names_the_first_reasons(
    rendered_spin: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A window too short for the rate (``min_periods`` 30: theta' turns 6.3 times in 19 s)
    refuses every estimate; the summary counts them by kind with the reason."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("rate: {min_periods: 30}\n")
    out = tmp_path / "out"
    assert main(["spin", str(rendered_spin), "--out", str(out), "--config", str(cfg)]) == 0
    printed = capsys.readouterr().out
    assert "4 estimates: 0 accepted, 0 ambiguous, 4 refused (too-slow 4)" in printed
    assert "first reasons: too-slow: theta' turns fewer than 30 times" in printed
    with (out / "spin.csv").open() as f:
        assert all(r["reason"].startswith("theta' turns fewer") for r in csv.DictReader(f))


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
