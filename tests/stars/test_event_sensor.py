"""Issue 18 part 3: the refractory period and the contrast thresholds measured from the stream
(frontend.star_sensor), the dead time in the spot fit's levels, and Prophesee files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from satpose.datasets.dvs_events import DvsSensor, simulate_dvs_events
from satpose.datasets.errors import SequenceError
from satpose.datasets.event_io import find_events_file, read_events
from satpose.datasets.events import Events, EventSensor, Photometry, simulate_events
from satpose.datasets.geometry import rotvec_to_matrix
from satpose.datasets.sky import StarCatalogue, star_camera
from satpose.frontend.star_events import hot_pixels
from satpose.frontend.star_sensor import (
    Refractory,
    _distinct,
    _fit_c,
    estimate_refractory,
    estimate_thresholds,
    pixel_intervals,
    refractory_from_stream,
    same_polarity_intervals,
    star_passes,
)
from satpose.frontend.stars import stream_levels, stream_levels_dead_time

W, H, HFOV = 160, 120, 6.0


def _scene(speed_px_s: float) -> tuple[StarCatalogue, object, object]:
    """Twelve isolated stars of magnitudes 2-6.4 on a small sensor, slewing along x at
    ``speed_px_s``: catalogue, camera, attitude."""
    cam = star_camera(W, H, HFOV)
    rows = np.arange(12)
    px = np.column_stack([30.0 + 3.3 * (rows % 3), 12.0 + 8.7 * rows + 0.37 * (rows % 2)])
    b = np.column_stack([(px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy, np.ones(12)])
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    mag = 2.0 + 0.4 * rows
    cat = StarCatalogue(hip=rows + 1, unit=b, mag=mag, epoch_yr=2016.0)
    w = np.array([0.0, -speed_px_s / cam.fx, 0.0])  # stars move towards +x

    def att(t: np.ndarray) -> np.ndarray:
        return rotvec_to_matrix(np.atleast_1d(np.asarray(t, float))[:, None] * w[None])

    return cat, cam, att


def _dvs(speed: float, duration: float, seed: int, **kw: float) -> tuple[Events, object, object]:
    cat, cam, att = _scene(speed)
    base = {
        "ba_rate_hz": 0.0,
        "hot_fraction": 0.0,
        "mag_limit": 20.0,
        "flux_mag0_e_s": 2.0e6,
    }
    sensor = DvsSensor(**{**base, **kw})  # type: ignore[arg-type]
    ev = simulate_dvs_events(cat, att, cam, sensor, 0.0, duration, np.random.default_rng(seed))
    return ev, cat, (cam, att)


def _esim(speed: float, duration: float, seed: int, **kw: float) -> tuple[Events, object, object]:
    cat, cam, att = _scene(speed)
    phot = Photometry(mag_limit=20.0)
    sensor = EventSensor(**{"noise_rate_hz": 0.0, **kw})  # type: ignore[arg-type]
    ev = simulate_events(cat, att, cam, phot, sensor, 0.0, duration, np.random.default_rng(seed))
    return ev, cat, (cam, att)


def _refractory(ev: Events) -> Refractory:
    """What the tracker measures (`run_event_tracker`): hot pixels out of the stream, their
    intervals and the star passes' same-polarity intervals."""
    hot = hot_pixels(ev, W, H)
    flat = ev.y.astype(np.int64) * W + ev.x
    is_hot = np.isin(flat, hot)
    hot_dt = pixel_intervals(ev.t_us[is_hot], ev.x[is_hot], ev.y[is_hot]) if hot.size else None
    star_dt = same_polarity_intervals(ev.t_us, ev.x, ev.y, ev.p, ~is_hot)
    return refractory_from_stream(star_dt, hot_dt)


@pytest.mark.parametrize("tau", [3e-4, 0.0])
def test_refractory_from_hot_pixels(tau: float) -> None:
    """Seeded, second model with 0.5 % hot pixels (~200 Hz) and 20 us timestamp jitter:
    the dead time comes from the hot pixels' intervals, within 3 sigma and 40 us of the
    truth (the edge is blurred by the jitter of both events); a sensor without one gives
    0 within 20 us."""
    ev, _, _ = _dvs(
        900.0,
        0.12,
        1,
        refractory_s=tau,
        timestamp_jitter_s=2e-5,
        hot_fraction=0.005,
        hot_rate_hz=200.0,
    )
    r = _refractory(ev)
    assert r.identified and r.source == "hot pixels"
    err = abs(r.refractory_s - tau)
    assert err <= (4e-5 if tau > 0 else 2e-5) and err <= max(3 * r.sigma_s, 2e-5)


def test_refractory_from_star_passes_is_a_bound() -> None:
    """Seeded, no hot pixels. The second model (a pixel resets after its 0.3 ms): the star
    passes' shortest intervals are the dead time plus the fastest pixel's time per
    threshold, so only a bound above it (within 0.2 ms at 900 px/s). ESIM (a crossing
    inside the 0.3 ms is lost): the intervals pile up at the dead time itself, a bound
    within 40 us. ESIM without one at 3000 px/s: a bound within 50 us of 0. A slow slew
    (60 px/s): the bound is milliseconds, not the 0.1 ms dead time."""
    ev, _, _ = _dvs(900.0, 0.12, 1, refractory_s=3e-4, timestamp_jitter_s=2e-5)
    r = _refractory(ev)
    assert not r.identified and 3e-4 <= r.refractory_s <= 5e-4
    ev, _, _ = _esim(900.0, 0.12, 1, refractory_s=3e-4)
    r = _refractory(ev)
    assert not r.identified and 3e-4 - 5e-6 <= r.refractory_s <= 3.4e-4
    ev, _, _ = _esim(3000.0, 0.035, 1, refractory_s=0.0)
    r = _refractory(ev)
    assert r.refractory_s <= 5e-5
    ev, _, _ = _dvs(60.0, 0.4, 2, refractory_s=1e-4, timestamp_jitter_s=0.0)
    r = _refractory(ev)
    assert not r.identified and r.refractory_s >= 1e-4


@pytest.mark.parametrize("model", ["dvs", "esim"])
def test_thresholds_from_star_passes_and_magnitudes(model: str) -> None:
    """Seeded, both simulators, 150 px/s, true C 0.30 (second model) and 0.25 (ESIM),
    per-pixel spread 0.03: ON and OFF thresholds within 3 sigma (bootstrap over the 12
    stars) and within 12 % of the truth. The second model's pixels reset after their
    0.3 ms dead time (its intervals are counted with it); ESIM's 0.1 ms loses no crossing
    at this speed and moves the reference by whole thresholds (counted without)."""
    if model == "dvs":
        c_true, tau = 0.30, 3e-4
        ev, cat, (cam, att) = _dvs(
            150.0, 0.45, 3, contrast_threshold=c_true, threshold_sigma=0.03, refractory_s=tau
        )
    else:
        c_true, tau = 0.25, 0.0
        ev, cat, (cam, att) = _esim(
            150.0, 0.45, 3, contrast_threshold=c_true, threshold_sigma=0.03, refractory_s=1e-4
        )
    passes = star_passes(ev.t_us, ev.x, ev.y, ev.p, None, tau)
    th = estimate_thresholds(
        passes,
        att,  # type: ignore[arg-type]
        cam.fx,  # type: ignore[attr-defined]
        cam.fy,  # type: ignore[attr-defined]
        cam.cx,  # type: ignore[attr-defined]
        cam.cy,  # type: ignore[attr-defined]
        cat.unit,  # type: ignore[attr-defined]
        cat.mag,  # type: ignore[attr-defined]
    )
    assert th is not None and th.stars >= 8
    for c, s in ((th.c_on, th.sigma_on), (th.c_off, th.sigma_off)):
        assert abs(c - c_true) <= max(3 * s, 0.01) and abs(c - c_true) <= 0.12 * c_true


def test_thresholds_need_a_range_of_magnitudes() -> None:
    """One magnitude only: the threshold is not identifiable from counts (None)."""
    ev, cat, (cam, att) = _dvs(150.0, 0.3, 4, refractory_s=0.0)
    flat = StarCatalogue(
        hip=cat.hip,  # type: ignore[attr-defined]
        unit=cat.unit,  # type: ignore[attr-defined]
        mag=np.full(12, 4.0),
        epoch_yr=2016.0,
    )
    passes = star_passes(ev.t_us, ev.x, ev.y, ev.p)
    assert (
        estimate_thresholds(
            passes,
            att,  # type: ignore[arg-type]
            cam.fx,  # type: ignore[attr-defined]
            cam.fy,  # type: ignore[attr-defined]
            cam.cx,  # type: ignore[attr-defined]
            cam.cy,  # type: ignore[attr-defined]
            flat.unit,
            flat.mag,
        )
        is None
    )


@pytest.mark.parametrize("hot_fraction", [0.005, 0.0])
def test_stream_levels_measure_dead_time_as_refractory_from_stream(hot_fraction: float) -> None:
    """Seeded second model (0.3 ms dead time): the tracker's whole-stream step measures the
    same dead time as `refractory_from_stream` on the hot pixels' and the star passes'
    intervals (exactly: the same intervals), from the hot pixels when there are some and
    from the star passes (forming them only then) when not; ``ladder=False`` (the tracker's
    default) gives the same levels and measurement without the dead-time ladder."""
    ev, _, _ = _dvs(
        900.0,
        0.12,
        3,
        refractory_s=3e-4,
        timestamp_jitter_s=2e-5,
        hot_fraction=hot_fraction,
        hot_rate_hz=200.0,
    )
    expect = _refractory(ev)
    flat = ev.y.astype(np.int64) * W + ev.x
    is_hot = np.isin(flat, hot_pixels(ev, W, H))
    hot_dt = pixel_intervals(ev.t_us[is_hot], ev.x[is_hot], ev.y[is_hot]) if is_hot.any() else None
    keep = ~is_hot
    args = (ev.t_s[keep], ev.x[keep], ev.y[keep], ev.p[keep], None)
    full = stream_levels_dead_time(*args, hot_intervals_us=hot_dt)
    lean = stream_levels_dead_time(*args, hot_intervals_us=hot_dt, ladder=False)
    assert full.refractory == expect and lean.refractory == expect
    assert (expect.source == "hot pixels") == (hot_fraction > 0)
    assert lean.dead_time is None and lean.refractory_used_s == 0.0
    np.testing.assert_array_equal(lean.levels, full.levels)
    np.testing.assert_array_equal(lean.peak, full.peak)


def test_dead_time_levels() -> None:
    """Noise-free: without a dead time the levels are `stream_levels`' and nothing is added;
    with one, an in-run interval dt adds tau / (dt - tau) thresholds (capped), signed like
    the run, counted from the pixel's first event."""
    t = np.array([0.0, 1e-3, 1.4e-3, 2.0e-3, 10e-3, 10.5e-3])
    x = np.zeros(6, dtype=np.uint16)
    y = np.zeros(6, dtype=np.uint16)
    p = np.array([1, 1, 1, 0, 0, 1], dtype=np.uint8)
    ref_levels, ref_peak = stream_levels(t, x, y, p, edge_s=0.0)
    none = stream_levels_dead_time(t, x, y, p, 0.0, edge_s=0.0)
    assert none.dead_time is None and np.array_equal(none.levels, ref_levels)
    assert np.array_equal(none.peak, ref_peak)
    tau = 2e-4
    lv = stream_levels_dead_time(t, x, y, p, tau, edge_s=0.0)
    g1, g2 = tau / (1e-3 - tau), tau / (0.4e-3 - tau)
    g_off = tau / (8e-3 - tau)
    expect = [0.0, g1, g1 + g2, g1 + g2, g1 + g2 - g_off, g1 + g2 - g_off]
    assert lv.dead_time is not None
    np.testing.assert_allclose(lv.dead_time, expect, atol=1e-12)
    assert lv.refractory_used_s == tau
    np.testing.assert_array_equal(lv.levels, [1, 2, 3, 2, 1, 2])


def _evt3_words(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> bytes:
    """EVT 3.0 words written from Prophesee's format description (16-bit little-endian;
    type in the top 4 bits: 0x8 time high (timestamp bits 12-23), 0x6 time low (bits 0-11),
    0x0 y address, 0x2 x address with the polarity in bit 11)."""
    words: list[int] = []
    last: dict[str, int] = {}
    for ti, xi, yi, pi in zip(t.tolist(), x.tolist(), y.tolist(), p.tolist(), strict=True):
        th, tl = (ti >> 12) & 0xFFF, ti & 0xFFF
        for key, val, word in (("th", th, 0x8000 | th), ("tl", tl, 0x6000 | tl), ("y", yi, yi)):
            if last.get(key) != val:
                words.append(word)
                last[key] = val
        words.append(0x2000 | (pi << 11) | xi)
    return np.array(words, dtype="<u2").tobytes()


def _random_events(n: int, t_max_us: int, seed: int) -> Events:
    rng = np.random.default_rng(seed)
    return Events(
        t_us=np.sort(rng.integers(0, t_max_us, n)).astype(np.int64),
        x=rng.integers(0, 640, n).astype(np.uint16),
        y=rng.integers(0, 480, n).astype(np.uint16),
        p=rng.integers(0, 2, n).astype(np.uint8),
    )


def _same(a: Events, b: Events) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("t_us", "x", "y", "p"))


def test_prophesee_raw_evt3(tmp_path: Path) -> None:
    """An EVT 3.0 file written from the format description (40 s: past the 24-bit
    timestamp's 16.8 s wrap) reads back exactly; events.raw is found in a recording
    folder; a file that is not RAW is a one-line error naming it."""
    ev = _random_events(3000, 40_000_000, 5)
    header = b"% evt 3.0\n% format EVT3;height=480;width=640\n% geometry 640x480\n% end\n"
    (tmp_path / "events.raw").write_bytes(header + _evt3_words(ev.t_us, ev.x, ev.y, ev.p))
    assert find_events_file(tmp_path) == tmp_path / "events.raw"
    assert _same(read_events(tmp_path / "events.raw"), ev)
    bad = tmp_path / "bad.raw"
    bad.write_bytes(b"not an event file")
    with pytest.raises(SequenceError, match=r"bad\.raw"):
        read_events(bad)


def test_prophesee_dat(tmp_path: Path) -> None:
    """A DAT file built byte by byte (header, type 0x0C, size 8, uint32 t and packed
    x | y << 14 | p << 28) reads back exactly; a truncated one is a one-line error."""
    ev = _random_events(2000, 3_000_000, 6)
    rec = np.zeros(len(ev), dtype=[("t", "<u4"), ("d", "<u4")])
    rec["t"] = ev.t_us
    rec["d"] = ev.x.astype(np.uint32) + ev.y.astype(np.uint32) * 2**14 + ev.p * np.uint32(2**28)
    data = b"% Data file containing CD events.\n% Version 2\n" + bytes([0x0C, 8]) + rec.tobytes()
    path = tmp_path / "events.dat"
    path.write_bytes(data)
    assert _same(read_events(path), ev)
    path.write_bytes(data[:-3])
    with pytest.raises(SequenceError, match=r"events\.dat.*truncated"):
        read_events(path)


def test_refractory_none_from_too_few_intervals() -> None:
    """Fewer than 200 intervals: not identified, the shortest interval as the bound."""
    r = estimate_refractory(np.array([500.0, 800.0, 900.0]))
    assert not r.identified and r.refractory_s == pytest.approx(5e-4)
    assert math.isfinite(r.sigma_s)


def test_threshold_fit_on_distinct_rows_equals_the_fit_on_every_pass() -> None:
    """Seeded: 20,000 passes of 60 stars with integer counts (Poisson around the model,
    C_on 0.3, C_off 0.28, plus 2 % outliers). The fits on the distinct (star, count) rows
    weighted by their passes equal the fits on every pass to 1e-6 relative (both converge
    to the same minimum of the same cost; the tolerance is the solver's), with at most a
    tenth as many rows."""
    rng = np.random.default_rng(21)
    star_mag = rng.uniform(3.0, 8.0, 60)
    star = rng.integers(0, 60, 20_000)
    mag = star_mag[star]
    peak = np.log1p(np.exp(9.0 - 0.4 * math.log(10.0) * mag))
    on = rng.poisson(peak / 0.3).astype(float)
    off = rng.poisson(np.maximum(peak - 0.15, 0.0) / 0.28).astype(float)
    bad = rng.uniform(size=star.size) < 0.02
    on[bad] += rng.integers(5, 30, int(bad.sum()))
    y_on, y_off = on + 0.5, off + 0.5
    a, c_on = _fit_c(mag, y_on)
    _, c_off = _fit_c(mag, y_off, a0=a, c_on=c_on)
    s_on, yd_on, k_on = _distinct(star, y_on)
    s_off, yd_off, k_off = _distinct(star, y_off)
    assert k_on.sum() == star.size and s_on.size <= star.size // 10
    a_w, c_on_w = _fit_c(star_mag[s_on], yd_on, weight=k_on)
    _, c_off_w = _fit_c(star_mag[s_off], yd_off, a0=a_w, c_on=c_on_w, weight=k_off)
    np.testing.assert_allclose([a_w, c_on_w, c_off_w], [a, c_on, c_off], rtol=1e-6)
    assert abs(c_on - 0.3) < 0.03 and abs(c_off - 0.28) < 0.03  # the model is recovered
