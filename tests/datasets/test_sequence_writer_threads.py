"""SequenceWriter's PNG options (used by `satpose import`): threads and a zlib level change
neither the images nor the atomicity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from satpose.datasets.sequence import SequenceWriter, load_sequence


def test_threads_and_levels_write_the_same_images(tmp_path: Path, synthetic_sequence: Path) -> None:
    calib = load_sequence(synthetic_sequence).calibration
    rng = np.random.default_rng(5)
    frames = [
        (rng.integers(0, 256, (32, 48, 3), np.uint8), rng.integers(0, 65536, (32, 48), np.uint16))
        for _ in range(12)
    ]
    for level, workers in ((None, 1), (9, 2), (0, 3)):
        out = tmp_path / f"seq-{level}-{workers}"
        with SequenceWriter(
            out,
            name="t",
            kind="stereo",
            rate_hz=1.0,
            calibration=calib,
            png_compression=level,
            workers=workers,
        ) as w:
            for k, (left, right) in enumerate(frames):
                w.add_frame(k, float(k), left, right)
        seq = load_sequence(out)
        for fr, (left, right) in zip(seq, frames, strict=True):
            np.testing.assert_array_equal(fr.left(), left)
            np.testing.assert_array_equal(fr.right(), right)


def test_a_failure_with_threads_leaves_nothing(tmp_path: Path, synthetic_sequence: Path) -> None:
    calib = load_sequence(synthetic_sequence).calibration
    out = tmp_path / "out" / "seq"
    img = np.zeros((32, 48), np.uint8)
    with pytest.raises(RuntimeError, match="stop"):
        with SequenceWriter(
            out, name="t", kind="stereo", rate_hz=1.0, calibration=calib, workers=2
        ) as w:
            for k in range(8):
                w.add_frame(k, float(k), img, img)
            raise RuntimeError("stop")
    assert not out.exists() and not list(out.parent.iterdir())
