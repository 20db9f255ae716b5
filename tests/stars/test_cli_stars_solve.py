"""`satpose stars solve` end to end: a real frame, a corrupt file, a FITS file, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from satpose.tools.cli import main

DATA = Path(__file__).resolve().parents[1] / "data" / "tetra3"
LEADING = "image,status,ra_deg,dec_deg,roll_deg,fov_deg,qx,qy,qz,qw".split(",")
THEN = "matches,rmse_arcsec,sigma_cross_arcsec,sigma_roll_arcsec,cpu_ms,reason".split(",")
FOV = ["--fov-deg", "11.4", "--fov-tolerance-deg", "1", "--epoch-yr", "2019.58"]


def test_solve_writes_rows_overlays_and_summary(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    real = sorted(DATA.glob("*.tiff"))[0]
    corrupt = tmp_path / "corrupt.tiff"
    corrupt.write_bytes(real.read_bytes()[:5000])
    fits = tmp_path / "frame.fits"
    fits.write_bytes(b"SIMPLE  =                    T")
    out = tmp_path / "out"
    args = [str(real), str(corrupt), str(fits), "--out", str(out), *FOV]
    assert main(["stars", "solve", *args]) == 0
    captured = capsys.readouterr()
    last = captured.out.strip().splitlines()[-1]
    assert last.startswith("1/3 solved") and "solutions.csv" in last
    assert "Traceback" not in captured.err and "TIFF" not in captured.err
    df = pd.read_csv(out / "solutions.csv", keep_default_na=False)
    assert list(df.columns[: len(LEADING) + len(THEN)]) == LEADING + THEN
    assert df["status"].tolist() == ["solved", "no_solution", "no_solution"]
    assert "decode" in df.loc[1, "reason"] and "FITS" in df.loc[2, "reason"]
    ok = df.iloc[0]
    q = [float(ok[c]) for c in ("qx", "qy", "qz", "qw")]
    assert sum(v * v for v in q) == pytest.approx(1.0, abs=1e-9)
    assert float(ok["fov_deg"]) == pytest.approx(11.42, abs=0.02)
    assert int(ok["matches"]) >= 50 and float(ok["sigma_roll_arcsec"]) > 0
    for name in (real.stem, "corrupt", "frame"):
        assert (out / "overlays" / f"{name}.png").is_file()
    assert (out / "config.yaml").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp")]

    # An existing output folder is refused (one line, status 2) and left as it was.
    assert main(["stars", "solve", str(real), "--out", str(out), *FOV]) == 2
    assert "already exists" in capsys.readouterr().err


def test_bad_input_is_one_line_and_leaves_no_output(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    real = sorted(DATA.glob("*.tiff"))[0]
    shutil.copy(real, tmp_path / "a.tiff")
    out = tmp_path / "out"
    cases = [
        ([str(tmp_path / "missing.png")], "missing.png: no such file"),
        ([str(tmp_path / "a.tiff"), "--fov-range", "30", "10"], "field of view range"),
        ([str(tmp_path / "a.tiff"), "--fov-tolerance-deg", "1"], "needs --fov-deg"),
    ]
    for args, message in cases:
        assert main(["stars", "solve", *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0] and err[0].startswith("satpose stars: error")
        assert not out.exists()
