"""Issue 18 part 3: the second event model (datasets.dvs_events), the Gaia sky, the tracker's
stream measurements (frontend.star_events) and bad event files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from satpose.datasets.dvs_events import DvsSensor, defocus_psf_table, simulate_dvs_events
from satpose.datasets.event_io import write_events_h5
from satpose.datasets.events import Events
from satpose.datasets.geometry import rotvec_to_matrix
from satpose.datasets.sequence import calibration_to_yaml
from satpose.datasets.sky import StarCatalogue, load_gaia, sensor_magnitude, star_camera
from satpose.datasets.star_scenarios import star_preset
from satpose.frontend.star_events import correlated_events, hot_pixels, stream_noise
from satpose.frontend.stars import StarTracker
from satpose.tools.cli import main


def _quiet(**kw: float) -> DvsSensor:
    base = {
        "ba_rate_hz": 0.0,
        "hot_fraction": 0.0,
        "timestamp_jitter_s": 0.0,
        "threshold_sigma": 0.0,
        "mag_limit": 20.0,
    }
    return DvsSensor(**{**base, **kw})  # type: ignore[arg-type]


def test_defocus_table_moments() -> None:
    """Noise-free: the pixel-integrated disk*Gaussian sums to 1, its centroid is the
    sub-pixel offset and its per-axis variance is r^2/4 + sigma^2 + 1/12 (disk, blur, pixel),
    to the 1/16 px sampling (tolerances 2e-3 and 2 %)."""
    r, s = 1.5, 0.6
    tab = defocus_psf_table(r, s, 4)
    off = np.arange(-4, 5)
    np.testing.assert_allclose(tab.sum(axis=(2, 3)), 1.0, atol=2e-3)
    for iy, ix in ((8, 8), (0, 16), (12, 3)):
        t = tab[iy, ix] / tab[iy, ix].sum()
        mx, my = (t.sum(0) * off).sum(), (t.sum(1) * off).sum()
        assert mx == pytest.approx(ix / 16 - 0.5, abs=2e-3)
        assert my == pytest.approx(iy / 16 - 0.5, abs=2e-3)
    t = tab[8, 8]
    var = (t.sum(0) * off**2).sum()
    assert var == pytest.approx(r**2 / 4 + s**2 + 1 / 12, rel=0.02)


def _one_star_run(sensor: DvsSensor, rate_deg_s: float = 2.0) -> tuple[Events, float]:
    cam = star_camera(64, 48, 4.0)
    cat = StarCatalogue(
        hip=np.array([1]), unit=np.array([[0.0, 0.0, 1.0]]), mag=np.array([3.0]), epoch_yr=2016.0
    )
    w = np.radians([0.0, rate_deg_s, 0.0])
    R0 = rotvec_to_matrix(np.array([0.0, -math.radians(1.2), 0.0]))

    def att(t: np.ndarray) -> np.ndarray:
        return R0[None] @ rotvec_to_matrix(np.atleast_1d(t)[:, None] * w[None])

    ev = simulate_dvs_events(cat, att, cam, sensor, 0.0, 1.0, np.random.default_rng(3))
    return ev, cam.fx


def test_dvs_pixel_is_blind_for_the_refractory_period() -> None:
    """A pixel fires again no sooner than the refractory period (exact up to the 1 us tick),
    and a longer dead time loses events (the reset discards what happened while blind)."""
    tau = 5e-4
    ev, _ = _one_star_run(_quiet(refractory_s=tau))
    flat = ev.y.astype(np.int64) * 64 + ev.x
    order = np.argsort(flat, kind="stable")
    same = flat[order][1:] == flat[order][:-1]
    gaps = np.diff(ev.t_us[order])[same]
    assert gaps.size > 100 and gaps.min() >= tau * 1e6 - 1
    ev0, _ = _one_star_run(_quiet(refractory_s=0.0))
    ev_long, _ = _one_star_run(_quiet(refractory_s=10 * tau))
    assert len(ev_long) < len(ev) < len(ev0) and len(ev_long) < 0.8 * len(ev0)
    # A star passing: as many ON as OFF (the level returns to the background) within the
    # threshold asymmetry: ON and OFF thresholds equal here, so within 10 %.
    assert abs(int(ev0.p.sum()) - int((ev0.p == 0).sum())) < 0.1 * len(ev0)


def test_dvs_noise_and_hot_pixels_are_found_by_the_stream_filter() -> None:
    """Statistical (seeded): with the star, background activity and hot pixels, the hot
    pixels are found from the stream alone (all of them, and no star pixel), and the
    correlation filter keeps most star events and drops most noise events."""
    sensor = _quiet(ba_rate_hz=2.0, hot_fraction=0.005, hot_rate_hz=200.0)
    ev, _ = _one_star_run(sensor)
    quiet, _ = _one_star_run(_quiet())
    star_pix = set((quiet.y.astype(np.int64) * 64 + quiet.x).tolist())
    hot = hot_pixels(ev, 64, 48)
    n_hot = round(0.005 * 64 * 48)
    # A hot pixel whose log-normal rate came out low is not "hot"; most are.
    assert n_hot - 3 <= hot.size <= n_hot and not (set(hot.tolist()) & star_pix)
    keep, not_hot, stats = stream_noise(ev, 64, 48, 0.01, 4.0)
    flat = ev.y.astype(np.int64) * 64 + ev.x
    on_star = np.isin(flat, list(star_pix))
    assert keep[on_star].mean() > 0.9
    # Noise away from the star: kept only by a chance neighbour event within 10 ms
    # (8 neighbours x 2 Hz x 20 ms = 0.32 expected: about 27 % kept).
    assert keep[~on_star].mean() < 0.4
    assert stats.hot_events == int((~not_hot).sum()) > 0 and 0 < stats.kept_fraction < 1
    assert not np.isin(flat[not_hot], hot).any() and np.isin(flat[~not_hot], hot).all()


def test_correlated_events_window() -> None:
    """Noise-free, 10 ms bins: neighbours in the same bin (5 ms apart) or adjacent bins (15
    ms) are kept; a neighbour 25 ms later (bins 0 and 3) does not count, nor does another
    event of the same pixel."""
    ev = Events(
        t_us=np.array([0, 1000, 5000, 9000, 12000, 16000, 20000, 32000, 34000]),
        x=np.array([10, 40, 11, 30, 50, 41, 50, 50, 31], dtype=np.uint16),
        y=np.array([10, 40, 10, 30, 5, 41, 5, 6, 30], dtype=np.uint16),
        p=np.ones(9, dtype=np.uint8),
    )
    keep = correlated_events(ev, 64, 48, 0.01)
    assert keep.tolist() == [True, True, True, False, False, True, True, True, False]


def test_gaia_sky_band() -> None:
    """The Gaia DR3 sky: Barnard's star (G 8.19, BP 9.79, RP 6.96 in the file) comes out
    between RP and BP in the red-weighted band; the density to magnitude 9 is Gaia-like
    (tens of thousands of stars, more than Hipparcos to 8)."""
    m = sensor_magnitude(np.array([8.19]), np.array([9.79]), np.array([6.96]), 0.7)[0]
    assert 6.96 < m < 9.79 and m == pytest.approx(
        -2.5 * math.log10(0.3 * 10 ** (-0.4 * 9.79) + 0.7 * 10 ** (-0.4 * 6.96)), abs=1e-9
    )
    cat = load_gaia(9.0)
    assert 200_000 < len(cat) < 350_000
    np.testing.assert_allclose(np.linalg.norm(cat.unit, axis=1), 1.0, atol=1e-12)


def test_rate_is_shrunk_by_its_noise_only_when_small() -> None:
    """Closed form w^2 / (w^2 + s^2), s^2 = 2 var / dt^2: two attitudes 10 ms apart with 30
    arcsec noise and 0.05 deg/s between them are mostly noise (shrunk below 0.2); a 5 deg/s
    slew over 0.1 s is left within 0.1 %."""
    p = star_preset("dvs-stare")
    tr = StarTracker(star_camera(p.width, p.height, p.hfov_deg))
    var = (30 * math.pi / 648000) ** 2
    for rate_deg_s, dt, lo, hi in ((0.05, 0.01, 0.0, 0.2), (5.0, 0.1, 0.999, 1.0)):
        w = np.radians([rate_deg_s, 0.0, 0.0])
        cov = np.eye(3) * var
        tr.history[:] = [(0.0, np.eye(3), cov), (dt, rotvec_to_matrix(w * dt), cov)]
        tr._rate_src = None
        ratio = tr.body_rate_rad_s()[0] / w[0]
        assert ratio == pytest.approx(w[0] ** 2 / (w[0] ** 2 + 2 * var / dt**2), rel=1e-9)
        assert lo <= ratio <= hi


def _event_only(tmp_path: Path, ev: Events) -> Path:
    seq = tmp_path / "rec"
    seq.mkdir()
    p = star_preset("dvs-stare")
    (seq / "calib.yaml").write_text(
        yaml.safe_dump(calibration_to_yaml(p.camera_calibration())), encoding="utf-8"
    )
    write_events_h5(ev, seq / "events.h5")
    return seq


@pytest.mark.parametrize(
    ("case", "words"),
    [
        ("empty", "no events"),
        ("outside", "outside the 640x480 sensor"),
        ("backwards", "non-decreasing"),
    ],
)
def test_bad_event_files_are_one_line_errors(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    words: str,
) -> None:
    """An empty event file, events outside the sensor and timestamps that go backwards: one
    line naming events.h5, exit 2, no output folder."""
    t = np.array([10, 20, 30], dtype=np.int64)
    x = np.array([5, 6, 7], dtype=np.uint16)
    if case == "outside":
        x = np.array([5, 700, 7], dtype=np.uint16)
    ev = Events(t_us=t, x=x, y=np.array([5, 5, 5], np.uint16), p=np.ones(3, np.uint8))
    if case == "empty":
        ev = Events(t_us=t[:0], x=x[:0], y=np.zeros(0, np.uint16), p=np.zeros(0, np.uint8))
    seq = _event_only(tmp_path, ev)
    if case == "backwards":
        import h5py

        with h5py.File(seq / "events.h5", "r+") as f:
            f["events/t"][...] = np.array([10, 30, 20])
    out = tmp_path / "out"
    assert main(["stars", "track", str(seq), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "events.h5" in err and words in err
    assert not out.exists()


def test_event_sensor_calibration_keys(tmp_path: Path) -> None:
    """calib.yaml's event_sensor block is read (calib.yaml over sequence.yaml); unknown keys
    and non-positive values are refused naming the file and key."""
    from satpose.datasets.errors import SequenceError
    from satpose.tools.stars import event_sensor_calibration

    (tmp_path / "sequence.yaml").write_text(
        "event_sensor: {contrast_threshold: 0.3, psf_sigma_px: 1.2}\n", encoding="utf-8"
    )
    (tmp_path / "calib.yaml").write_text("event_sensor: {psf_sigma_px: 0.9}\n", encoding="utf-8")
    assert event_sensor_calibration(tmp_path) == {"contrast_threshold": 0.3, "psf_sigma_px": 0.9}
    bads = (
        ("{refractory: 1}", "event_sensor.refractory"),
        ("{psf_sigma_px: 0}", "psf"),
        ("{refractory_s: -1e-4}", "event_sensor.refractory_s"),
    )
    for bad, key in bads:
        (tmp_path / "calib.yaml").write_text(f"event_sensor: {bad}\n", encoding="utf-8")
        with pytest.raises(SequenceError, match=key) as info:
            event_sensor_calibration(tmp_path)
        assert "calib.yaml" in str(info.value)


def test_frames_only_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recording with frames and no events.h5 is tracked by the frames pipeline (a
    conventional 10 Hz star tracker, within 60 arcsec of truth per frame: the frame
    pipeline's RMS is 12-15 arcsec); the events pipeline refuses it in one line."""
    import pandas as pd

    seq = tmp_path / "slew"
    assert main(["stars", "render", "slew", "--out", str(seq), "--duration", "0.3"]) == 0
    (seq / "events.h5").unlink()
    capsys.readouterr()
    assert main(["stars", "track", str(seq), "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "events.h5" in err and "--pipeline frames" in err
    out = tmp_path / "f"
    assert main(["stars", "track", str(seq), "--out", str(out), "--pipeline", "frames"]) == 0
    df = pd.read_csv(out / "windows.csv")
    assert len(df) == 3 and (df["status"] != "lost").all()
    assert np.nanmax(np.abs(df[["err_x_arcsec", "err_y_arcsec"]].to_numpy())) < 60.0


def test_psf_measurement_finds_the_cost_minimum() -> None:
    """Noise-free oracle: with a cost that is a parabola in log sigma (minimum at 1.13 px),
    `_measure_psf` returns it exactly after ``psf_outputs`` outputs; a minimum outside the
    tried range ends at the range's edge (within one grid step)."""
    from satpose.frontend.stars import SpotFit, StarTrackerConfig

    p = star_preset("dvs-stare")
    cam = star_camera(p.width, p.height, p.hfov_deg)
    for target, tol in ((1.13, 1e-9), (5.0, 0.25)):
        tr = StarTracker(cam, StarTrackerConfig(psf_outputs=3))

        def run_fit(sigma: float, target: float = target) -> SpotFit:
            z = np.zeros(0)
            cost = (math.log(sigma / target)) ** 2
            return SpotFit(z, z, z, z, z.astype(bool), cost=cost)

        for _ in range(3):
            assert tr.psf_sigma_px == 0.8
            tr._measure_psf(run_fit)
        if tol < 1e-6:
            assert tr.psf_sigma_px == pytest.approx(target, rel=tol)
        else:
            assert 1.6 * (1 - tol) <= tr.psf_sigma_px <= 1.6 * (1 + tol)


def test_second_model_stare_keeps_lock(tmp_path: Path) -> None:
    """End to end on the second model's stare (0.05 deg/s, 30 arcsec of 3 Hz jitter; 1 s,
    seeded): after acquisition the outputs keep tracking (the issue's first attempt lost lock
    once per jitter period) and the smoothed cross-boresight error is <= 30 arcsec RMS (9 arcsec
    measured over 2 s in docs/results/stars_second_model.md; statistical tolerance 3x)."""
    from dataclasses import replace

    from satpose.datasets.star_scenarios import load_attitude_truth, render_star_sequence
    from satpose.tools.stars import attitude_errors_arcsec, track_sequence

    seq = tmp_path / "stare"
    render_star_sequence(replace(star_preset("dvs-stare"), duration_s=1.0), seq)
    res = track_sequence(seq, "events", "offline")
    status = [s.status for s in res.solutions]
    first = status.index("lost_in_space")
    after = status[first + 1 :]
    # Seeded; 2 % of the outputs may fail (another CPU's rounding). Before this work the
    # tracker lost lock at turns of the jitter and 11 % of this recording was uncovered.
    assert len(after) > 150 and after.count("tracking") >= 0.98 * len(after)
    truth = load_attitude_truth(seq / "attitude_truth.csv")
    ok = np.isfinite(res.R[:, 0, 0])
    e = attitude_errors_arcsec(res.R[ok], truth.at(res.t_s[ok]))
    assert math.sqrt(float(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))) <= 30.0


def test_track_records_what_it_measured(tmp_path: Path) -> None:
    """config.yaml of `satpose stars track` records what the tracker measured on a second-
    model recording (seeded, 0.4 s): the hot pixels it dropped (the simulator made 61,
    0.02 % of 640x480; a few low-rate ones are not told from quiet pixels) and a PSF
    sigma; the dead time from the hot pixels' intervals (0.3 ms simulated, 20 us jitter:
    within 60 us) and the contrast threshold's record (measured or not, and used); with
    psf_sigma_px and refractory_s stated in calib.yaml, the stated ones."""
    from dataclasses import replace

    from satpose.datasets.star_scenarios import render_star_sequence

    seq = tmp_path / "rec"
    render_star_sequence(replace(star_preset("dvs-stare"), duration_s=0.4), seq)
    out = tmp_path / "out"
    assert main(["stars", "track", str(seq), "--out", str(out)]) == 0
    measured = yaml.safe_load((out / "config.yaml").read_text(encoding="utf-8"))["measured"]
    assert 45 <= measured["hot_pixels"] <= 61 and measured["hot_pixel_events"] > 0
    assert measured["psf_sigma_px"] > 0
    ref = measured["refractory"]
    assert ref["source"] == "hot pixels" and ref["identified"]
    assert abs(ref["measured_s"] - 3e-4) <= 6e-5 and ref["used_s"] == 0.0  # ladder off
    assert measured["contrast_threshold"]["used"] == 0.25
    assert "measured" in measured["contrast_threshold"]
    calib = yaml.safe_load((seq / "calib.yaml").read_text(encoding="utf-8"))
    calib["event_sensor"] = {"psf_sigma_px": 1.1, "refractory_s": 0.0}
    (seq / "calib.yaml").write_text(yaml.safe_dump(calib), encoding="utf-8")
    assert main(["stars", "track", str(seq), "--out", str(tmp_path / "o2")]) == 0
    cfg = yaml.safe_load((tmp_path / "o2" / "config.yaml").read_text(encoding="utf-8"))
    assert cfg["measured"]["psf_sigma_source"] == "stated"
    assert cfg["frontend"]["psf_sigma_px"] == 1.1 == cfg["measured"]["psf_sigma_px"]
    assert cfg["measured"]["refractory"]["used_s"] == 0.0
    assert cfg["measured"]["refractory"]["source"].startswith("stated")
