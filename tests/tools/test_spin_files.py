"""The spin-rate measurement: validation and its round trip through measurements.parquet."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from satpose.frontend.measurements import (
    FrameMeasurements,
    MeasurementError,
    SpinRateMeasurement,
    SpinStatus,
)
from satpose.tools.files import read_measurements, write_measurements


def test_spin_measurement_round_trips_through_parquet(tmp_path: Path) -> None:
    ok = SpinRateMeasurement(
        rate_rad_s=1.0471975511965976,
        sigma_rad_s=4.2e-5,
        status=SpinStatus.OK,
        window_start_s=0.0,
        window_end_s=18.0,
        samples=19,
    )
    refused = SpinRateMeasurement(
        rate_rad_s=math.nan,
        sigma_rad_s=math.nan,
        status=SpinStatus.TOO_SLOW,
        reason="theta' turns fewer than 1.5 times in the 19 s window",
        window_start_s=1.0,
        window_end_s=19.0,
        samples=17,
    )
    ambiguous = SpinRateMeasurement(
        rate_rad_s=math.nan,
        sigma_rad_s=2e-4,
        status=SpinStatus.AMBIGUOUS,
        reason="80.00 or 100.00 deg/s fit equally well",
        window_start_s=2.0,
        window_end_s=20.0,
        samples=19,
        candidates_rad_s=(math.radians(100.0), math.radians(80.0)),
    )
    items = [
        FrameMeasurements(frame=0, t_s=0.0),
        FrameMeasurements(frame=18, t_s=18.0, spin=ok, failures=("spin: no bright region",)),
        FrameMeasurements(frame=19, t_s=19.0, spin=refused, timings_ms={"region": 3.0}),
        FrameMeasurements(frame=20, t_s=20.0, spin=ambiguous),
    ]
    back = read_measurements(write_measurements(items, tmp_path / "m.parquet"))
    assert back[0].spin is None
    assert back[1].spin == ok and back[1].failures == items[1].failures
    b = back[2].spin
    assert b is not None and b.status is SpinStatus.TOO_SLOW and b.reason == refused.reason
    assert math.isnan(b.rate_rad_s) and math.isnan(b.sigma_rad_s)
    assert (b.window_start_s, b.window_end_s, b.samples) == (1.0, 19.0, 17)
    assert b.candidates_rad_s == () and back[1].spin is not None
    a = back[3].spin
    assert a is not None and a.status is SpinStatus.AMBIGUOUS and math.isnan(a.rate_rad_s)
    # sorted on construction; exact float round trip
    assert a.candidates_rad_s == (math.radians(80.0), math.radians(100.0))
    assert a.sigma_rad_s == 2e-4 and a.reason == ambiguous.reason


def test_spin_measurement_validation() -> None:
    with pytest.raises(MeasurementError, match="sigma"):
        SpinRateMeasurement(
            rate_rad_s=1.0,
            sigma_rad_s=0.0,
            status="ok",
            window_start_s=0,
            window_end_s=1,
            samples=2,
        )
    with pytest.raises(MeasurementError, match="needs a reason"):
        SpinRateMeasurement(
            rate_rad_s=math.nan,
            sigma_rad_s=math.nan,
            status="aliasing",
            window_start_s=0,
            window_end_s=1,
            samples=2,
        )
    with pytest.raises(MeasurementError, match="two finite candidates"):
        SpinRateMeasurement(
            rate_rad_s=math.nan,
            sigma_rad_s=0.1,
            status="ambiguous",
            reason="one candidate only",
            window_start_s=0,
            window_end_s=1,
            samples=2,
            candidates_rad_s=(1.0,),
        )
    with pytest.raises(MeasurementError, match="only an ambiguous"):
        SpinRateMeasurement(
            rate_rad_s=1.0,
            sigma_rad_s=0.1,
            status="ok",
            window_start_s=0,
            window_end_s=1,
            samples=2,
            candidates_rad_s=(1.0, 2.0),
        )
    with pytest.raises(MeasurementError, match="ends"):
        SpinRateMeasurement(
            rate_rad_s=1.0,
            sigma_rad_s=0.1,
            status="ok",
            window_start_s=2,
            window_end_s=1,
            samples=2,
        )
