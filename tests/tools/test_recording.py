"""run.rrd's compact batching keeps the recording's content: the same entities, rows, static
data and blueprint as the SDK's default batching, in one chunk per entity."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from satpose.datasets.geometry import Rigid3
from satpose.frontend.measurements import FrameMeasurements, LandmarkKind, LandmarkMeasurement
from satpose.tools.recording import (
    CAMERA,
    PLOTS,
    TRAJECTORY,
    RecordingConfig,
    RunRecorder,
)

FRAMES = 12


def _record(path: Path, compact: bool, calibration) -> Path:  # type: ignore[no-untyped-def]
    """The calls `satpose run` makes, on synthetic frames: images, landmarks, three causal
    estimates with a covariance, truth, spin and timings per frame, then two final series."""
    rng = np.random.default_rng(5)
    rec = RunRecorder(path, calibration, None, replace(RecordingConfig(), compact=compact))
    truth = [
        Rigid3.from_rotvec([0.0, 0.0, 0.1 * k], [0.01 * k, 0.0, 5.0 - 0.05 * k])
        for k in range(FRAMES)
    ]
    h, w = calibration.left.height, calibration.left.width
    for k in range(FRAMES):
        m = FrameMeasurements(
            frame=k,
            t_s=0.5 * k,
            landmarks=(
                LandmarkMeasurement(
                    track_id=1, kind=LandmarkKind.CORNER, left_px=np.array([10.0, 12.0 + k])
                ),
            ),
            failures=("ring: no ellipse",) if k == 3 else (),
        )
        images = {
            cam: rng.integers(0, 256, size=(h, w), dtype=np.uint8) for cam in ("left", "right")
        }
        est = {
            name: T @ Rigid3.from_rotvec(0.01 * rng.normal(size=3), 0.01 * rng.normal(size=3))
            for name, T in (("per_frame", truth[k]), ("kalman", truth[k]), ("isam2", truth[k]))
        }
        rec.log_frame(
            k,
            images,
            m,
            est,  # type: ignore[arg-type]
            covariance=np.eye(6) * 1e-4,
            truth=truth[k],
            spin_deg_per_frame={"isam2": 9.8, "truth": 10.0},
            timings_ms={"ring": 3.0, "backend_online": 2.0},
        )
    frames = list(range(FRAMES))
    smooth = [T @ Rigid3.from_rotvec([0.0, 0.0, 0.001], [0.0, 0.0, 0.001]) for T in truth]
    rec.log_final("smoothed", frames, smooth, truth, [10.0] * FRAMES, [0.5 * k for k in frames])
    rec.close()
    return path


def _content(path: Path) -> tuple[Counter[str], set[str], Counter[str]]:
    """Temporal rows per entity, static entities, temporal chunks per entity."""
    rows: Counter[str] = Counter()
    chunks: Counter[str] = Counter()
    static = set()
    for c in RrdReader(str(path)).store().stream():
        key = c.entity_path.lstrip("/")
        if c.is_static:
            static.add(key)
        else:
            rows[key] += c.num_rows
            chunks[key] += 1
    return rows, static, chunks


def test_compact_recording_has_the_same_content(tmp_path: Path, make_sequence) -> None:  # type: ignore[no-untyped-def]
    from satpose.datasets.sequence import load_sequence

    calib = load_sequence(make_sequence(tmp_path / "seq", frames=2)).calibration
    default = _record(tmp_path / "default.rrd", False, calib)
    compact = _record(tmp_path / "compact.rrd", True, calib)
    rows_d, static_d, _ = _content(default)
    rows_c, static_c, chunks_c = _content(compact)
    assert rows_c == rows_d and static_c == static_d
    for entity in (
        f"{CAMERA['left']}/image",
        f"{CAMERA['right']}/landmarks/corner",
        f"{PLOTS}/error/position_cm/isam2",
        f"{PLOTS}/spin/truth",
        f"{PLOTS}/timing_ms/ring",
        f"{PLOTS}/error/position_cm/smoothed",
        f"{PLOTS}/spin/smoothed",
    ):
        assert rows_c[entity] == FRAMES, (entity, rows_c[entity])
    assert rows_c[f"{TRAJECTORY}/isam2"] == FRAMES - 1  # a line from the second frame on
    assert rows_c["log/failures"] == 1
    assert {CAMERA["left"], f"{TRAJECTORY}/smoothed"} <= static_c
    # each entity's rows (48x32 images: a few kB in all) fit in one chunk
    assert max(chunks_c.values()) == 1, chunks_c.most_common(3)
    for path in (default, compact):
        assert len(RrdReader(str(path)).blueprints()) == 1


def test_final_series_lie_on_both_timelines(tmp_path: Path, make_sequence) -> None:  # type: ignore[no-untyped-def]
    """The smoothed series are placed at their frames' times on the ``time`` timeline too
    (they used to inherit the last frame's time)."""
    from satpose.datasets.sequence import load_sequence

    calib = load_sequence(make_sequence(tmp_path / "seq", frames=2)).calibration
    path = _record(tmp_path / "r.rrd", True, calib)
    chunks = [
        c
        for c in RrdReader(str(path)).store().stream()
        if c.entity_path.lstrip("/") == f"{PLOTS}/spin/smoothed" and not c.is_static
    ]
    assert len(chunks) == 1 and {"frame", "time"} <= set(chunks[0].timeline_names)
    batch = chunks[0].to_record_batch()
    frames = batch.column(batch.schema.get_field_index("frame")).to_pylist()
    times = batch.column(batch.schema.get_field_index("time")).to_pylist()
    assert frames == list(range(FRAMES))
    np.testing.assert_allclose(
        [t.total_seconds() for t in times], 0.5 * np.arange(FRAMES), atol=1e-9
    )


def test_jpeg_image_holds_the_image() -> None:
    """The logged JPEG decodes to the camera image (BGR and grey, 8 and 16 bit) within what
    JPEG at quality 95 loses on a smooth image."""
    import cv2

    from satpose.tools.recording import jpeg_image

    y, x = np.mgrid[0:96, 0:128]
    grey = (100 + 60 * np.sin(x / 9.0) * np.cos(y / 7.0)).astype(np.uint8)
    bgr = np.dstack([grey, (grey // 2).astype(np.uint8), (255 - grey).astype(np.uint8)])
    for img, flag in ((bgr, cv2.IMREAD_COLOR), (grey, cv2.IMREAD_GRAYSCALE)):
        for stored in (img, img.astype(np.uint16) * 257):
            logged = jpeg_image(stored, 95)
            assert logged.media_type is not None
            assert logged.media_type.as_arrow_array().to_pylist() == ["image/jpeg"]
            assert logged.blob is not None
            data = np.asarray(logged.blob.as_arrow_array().to_pylist()[0], dtype=np.uint8)
            back = cv2.imdecode(data, flag)
            assert back.shape == img.shape
            err = np.abs(back.astype(int) - img.astype(int))
            assert err.mean() < 2.0 and err.max() <= 20  # JPEG q95 on a smooth image
