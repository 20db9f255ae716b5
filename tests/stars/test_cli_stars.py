"""`satpose stars render|track` end to end on a short slew, and its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from satpose.tools.cli import main


def test_render_and_track(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    seq = tmp_path / "slew"
    assert main(["stars", "render", "slew", "--out", str(seq), "--duration", "0.4"]) == 0
    for name in ("events.h5", "attitude_truth.csv", "groundtruth.csv", "frames.csv"):
        assert (seq / name).is_file()
    out = tmp_path / "trk"
    assert main(["stars", "track", str(seq), "--out", str(out), "--rerun"]) == 0
    tum = np.loadtxt(out / "attitude.tum")
    assert tum.shape[1] == 8 and np.all(tum[:, 1:4] == 0)  # zero translation
    df = pd.read_csv(out / "windows.csv")
    tracked = df[df["status"] == "tracking"]
    assert len(tracked) >= 0.7 * len(df)  # the first 50 ms go to the lost-in-space window
    # Smoothed cross-boresight errors: a few tens of arcsec at most (pixel = 112 arcsec).
    assert np.nanmax(np.abs(df[["err_x_arcsec", "err_y_arcsec"]].to_numpy())) < 60.0
    assert (out / "attitude_error.png").is_file()
    import rerun as rr

    summary = str(rr.chunk.RrdReader(out / "stars.rrd").store().summary())
    for entity in ("/camera/sky", "/camera/events", "/camera/identified_stars", "/error_arcsec/x"):
        assert entity in summary
    # An existing output is refused with a one-line error, exit status 2.
    assert main(["stars", "track", str(seq), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    # A sequence without events.
    (seq / "events.h5").unlink()
    assert main(["stars", "track", str(seq), "--out", str(tmp_path / "x")]) == 2
    assert "events.h5" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
