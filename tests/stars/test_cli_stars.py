"""`satpose stars render|track` end to end on a short slew, and its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

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
    for entity in (
        "/camera/sky",
        "/camera/events",
        "/camera/event_image",
        "/camera/identified_stars",
        "/error_arcsec/x",
        "/rate_deg_s/y",
        "/timing_ms/tracking",
        "/stars_used",
    ):
        assert entity in summary
    # An existing output is refused with a one-line error, exit status 2.
    assert main(["stars", "track", str(seq), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    # A sequence without events.
    (seq / "events.h5").unlink()
    assert main(["stars", "track", str(seq), "--out", str(tmp_path / "x")]) == 2
    assert "events.h5" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_coverage_counts_time_measured_not_what_the_smoother_filled() -> None:
    """Outputs every 5 ms, two lost: the frontend measured 8 of 10 outputs = 80 % of the
    50 ms; the smoother has an attitude at all 10, and the summary says it filled 2."""
    from satpose.frontend.stars import AttitudeSolution
    from satpose.tools.stars import TrackResult, coverage_line, measured_coverage

    t = 0.005 * np.arange(1, 11)
    sols = [
        AttitudeSolution(
            t_s=float(tk),
            R=None if k in (3, 4) else np.eye(3),
            cov=None,
            status="lost" if k in (3, 4) else "tracking",
        )
        for k, tk in enumerate(t)
    ]
    res = TrackResult(
        solutions=sols,
        t_s=t,
        R=np.tile(np.eye(3), (10, 1, 1)),
        cov=np.zeros((10, 3, 3)),
        estimator="offline",
    )
    n, frac, duration = measured_coverage(res)
    assert n == 8 and frac == pytest.approx(0.8) and duration == pytest.approx(0.05)
    assert "8/10 outputs, 80.0 % of the 0.050 s" in coverage_line(res)
    assert "(2 filled by the smoother)" in coverage_line(res)


def test_event_only_recording_is_tracked(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A recording with events and no frames (no frames.csv, images or groundtruth.csv) is
    tracked by the events pipeline; the frames pipeline refuses it in one line naming
    frames.csv."""
    import shutil

    seq = tmp_path / "slew"
    assert main(["stars", "render", "slew", "--out", str(seq), "--duration", "0.2"]) == 0
    for name in ("frames.csv", "groundtruth.csv"):
        (seq / name).unlink()
    shutil.rmtree(seq / "left")
    capsys.readouterr()
    out = tmp_path / "trk"
    assert main(["stars", "track", str(seq), "--out", str(out), "--rerun"]) == 0
    assert "attitude measured in" in capsys.readouterr().out
    df = pd.read_csv(out / "windows.csv")
    assert (df["status"] == "tracking").mean() >= 0.7
    assert np.nanmax(np.abs(df[["err_x_arcsec", "err_y_arcsec"]].to_numpy())) < 60.0
    assert (
        main(["stars", "track", str(seq), "--out", str(tmp_path / "f"), "--pipeline", "frames"])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "frames.csv" in err and "--pipeline events" in err
    assert not (tmp_path / "f").exists()


@pytest.mark.parametrize("layout", ["events.txt", "events.aedat4"])
def test_recording_with_other_event_layouts_gives_the_same_attitude(
    tmp_path: Path, capsys, layout: str
) -> None:  # type: ignore[no-untyped-def]
    """The same events as the Event Camera Dataset's text lines or an AEDAT4 file instead of
    events.h5: `stars track` finds the file and gives the same attitudes (microsecond
    timestamps survive both round trips exactly)."""
    import shutil

    from satpose.datasets.event_io import read_events, write_events_aedat4, write_events_txt
    from satpose.datasets.sequence import load_calibration

    seq = tmp_path / "slew"
    assert main(["stars", "render", "slew", "--out", str(seq), "--duration", "0.2"]) == 0
    ref = tmp_path / "ref"
    assert main(["stars", "track", str(seq), "--out", str(ref)]) == 0
    other = tmp_path / "other"
    shutil.copytree(seq, other)
    ev = read_events(other / "events.h5")
    (other / "events.h5").unlink()
    if layout == "events.txt":
        write_events_txt(ev, other / layout)
    else:
        cam = load_calibration(other / "calib.yaml").left
        write_events_aedat4(ev, other / layout, cam.width, cam.height)
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["stars", "track", str(other), "--out", str(out)]) == 0, capsys.readouterr().err
    a = pd.read_csv(ref / "windows.csv")
    b = pd.read_csv(out / "windows.csv")
    assert len(a) == len(b)
    cols = ["err_x_arcsec", "err_y_arcsec"]
    np.testing.assert_allclose(b[cols].to_numpy(), a[cols].to_numpy(), atol=1e-9, equal_nan=True)
