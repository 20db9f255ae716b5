"""A sequence folder still being written: when `FolderSource` counts a frame complete, and the
recorder that writes such a folder (`Recorder`, `replay_sequence`)."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from satpose.datasets.errors import SequenceError
from satpose.datasets.importers import ImportOptions, RecordingError
from satpose.datasets.importers.writers import BagWriter, write_bag
from satpose.datasets.live import (
    RECORDING_DONE,
    BagReplay,
    FolderSource,
    Recorder,
    replay_sequence,
    wait_for_header,
)
from satpose.datasets.sequence import calibration_to_yaml, load_sequence


def _started(src: Path, out: Path) -> Recorder:
    rec = Recorder(src, out)
    rec.start()
    return rec


def _row(rec: Recorder, k: int) -> str:
    fr = rec.seq.frames[k]
    assert fr.right_path is not None
    return f"{fr.index},{fr.t_s!r},left/{fr.left_path.name},right/{fr.right_path.name}"


def _copy_images(rec: Recorder, k: int) -> None:
    fr = rec.seq.frames[k]
    for cam, path in (("left", fr.left_path), ("right", fr.right_path)):
        assert path is not None
        (rec.out / cam).mkdir(exist_ok=True)
        shutil.copyfile(path, rec.out / cam / path.name)


def test_frames_arrive_as_the_recorder_writes_them(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    assert source.poll() == ([], [])
    rec.write(0)
    frames, skipped = source.poll()
    assert [f.index for f in frames] == [0] and skipped == []
    rec.write(1)
    rec.write(2)
    frames, _ = source.poll()
    assert [f.index for f in frames] == [1, 2]
    left, right = frames[0].read()
    np.testing.assert_array_equal(left, rec.seq.frames[1].left())  # exact: a byte copy
    np.testing.assert_array_equal(right, rec.seq.frames[1].right())
    assert frames[0].t_s == rec.seq.frames[1].t_s
    assert all(f.arrival_s <= f.seen_s for f in frames)
    assert not source.ended()
    rec.finish()
    assert source.poll() == ([], [])
    assert source.ended()


def test_a_row_counts_only_once_it_ends_with_a_newline(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    _copy_images(rec, 0)
    line = _row(rec, 0)
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write(line[:5])
    assert source.poll() == ([], [])
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write(line[5:])
    assert source.poll() == ([], [])  # the whole row, still no newline
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write("\n")
    frames, _ = source.poll()
    assert [(f.index, f.t_s) for f in frames] == [(0, rec.seq.frames[0].t_s)]


def test_a_partly_written_png_is_waited_for(synthetic_sequence: Path, tmp_path: Path) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    _copy_images(rec, 0)
    left = rec.out / "left" / rec.seq.frames[0].left_path.name
    data = left.read_bytes()
    with open(rec.out / "frames.csv", "a") as fh:  # the row first, then the image
        fh.write(_row(rec, 0) + "\n")
    for cut in (0, 5, 40, len(data) // 2, len(data) - 1):
        left.write_bytes(data[:cut])
        assert source.poll() == ([], []), f"{cut} of {len(data)} bytes counted as whole"
    left.unlink()
    assert source.poll() == ([], [])  # missing: not yet
    left.write_bytes(data)
    frames, skipped = source.poll()
    assert [f.index for f in frames] == [0] and skipped == []
    np.testing.assert_array_equal(frames[0].read()[0], rec.seq.frames[0].left())


def test_an_incomplete_frame_is_given_up_when_a_later_one_is_complete(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write(_row(rec, 0) + "\n")  # its images never come
    assert source.poll() == ([], [])
    assert [s.index for s in source.incomplete()] == [0]
    rec.write(1)
    frames, skipped = source.poll()
    assert [f.index for f in frames] == [1]
    assert [(s.index, s.reason) for s in skipped] == [
        (0, f"incomplete: left/{rec.seq.frames[0].left_path.name} missing")
    ]
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write(_row(rec, 2) + "\n")  # the recorder dies ...
    (rec.out / RECORDING_DONE).touch()  # ... or says it is done: frame 2 is given up
    frames, skipped = source.poll()
    assert frames == [] and [s.index for s in skipped] == [2]
    assert "at the end" in skipped[0].reason
    assert source.ended()


def test_frames_csv_replaced_by_rename_gives_each_row_once(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    rec.write(0)
    assert [f.index for f in source.poll()[0]] == [0]
    _copy_images(rec, 1)
    header = (rec.out / "frames.csv").read_text().splitlines()[0]
    tmp = rec.out / "frames.tmp"
    tmp.write_text("\n".join([header, _row(rec, 0), _row(rec, 1)]) + "\n")
    os.replace(tmp, rec.out / "frames.csv")
    assert [f.index for f in source.poll()[0]] == [1]


def test_a_bad_row_is_skipped_with_a_warning(
    synthetic_sequence: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write("zero,0.0,left/a.png,right/a.png\n")
    rec.write(0)
    frames, _ = source.poll()
    assert [f.index for f in frames] == [0] and source.bad_rows == 1
    assert "frames.csv: row 1: frame and t_s must be numbers" in caplog.text


def test_a_wrong_header_names_the_file(synthetic_sequence: Path, tmp_path: Path) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    (rec.out / "frames.csv").write_text("frame,time,left,right\n")
    with pytest.raises(SequenceError, match=r"frames\.csv: frame,time,left,right: header must be"):
        FolderSource(rec.out).poll()


def test_a_file_that_is_no_png_is_complete_and_bad(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    rec = _started(synthetic_sequence, tmp_path / "live")
    source = FolderSource(rec.out)
    _copy_images(rec, 0)
    (rec.out / "left" / rec.seq.frames[0].left_path.name).write_bytes(b"GIF89a" + bytes(100))
    with open(rec.out / "frames.csv", "a") as fh:
        fh.write(_row(rec, 0) + "\n")
    frames, _ = source.poll()
    assert [f.index for f in frames] == [0]
    with pytest.raises(SequenceError, match="not a readable PNG"):
        frames[0].read()


def test_wait_for_header_gives_up_naming_the_file(tmp_path: Path) -> None:
    (tmp_path / "seq").mkdir()
    t0 = time.monotonic()
    with pytest.raises(SequenceError, match=r"sequence\.yaml: required file is missing \(waited"):
        wait_for_header(tmp_path / "seq", timeout_s=0.1)
    assert time.monotonic() - t0 >= 0.1
    assert wait_for_header(tmp_path / "seq", timeout_s=None, stop=lambda: True) is None


def test_replay_writes_the_same_sequence(synthetic_sequence: Path, tmp_path: Path) -> None:
    out = tmp_path / "replayed"
    done = []
    n = replay_sequence(synthetic_sequence, out, 200.0, progress=lambda k, _n: done.append(k))
    src, dst = load_sequence(synthetic_sequence), load_sequence(out)
    assert n == len(src) == len(dst) and done == list(range(1, n + 1))
    assert [(f.index, f.t_s) for f in dst] == [(f.index, f.t_s) for f in src]  # exact
    for a, b in zip(src, dst, strict=True):
        assert a.left_path.read_bytes() == b.left_path.read_bytes()
        assert a.right_path is not None and b.right_path is not None
        assert a.right_path.read_bytes() == b.right_path.read_bytes()
    assert src.truth is not None and dst.truth is not None
    np.testing.assert_array_equal(dst.truth.translation, src.truth.translation)
    assert dst.rate_hz == src.rate_hz
    assert calibration_to_yaml(dst.calibration) == calibration_to_yaml(src.calibration)
    assert (out / RECORDING_DONE).is_file()
    assert not [p for p in out.rglob("*") if p.name.startswith(".")]  # no temporary left


def test_replay_of_some_frames_is_a_valid_sequence(
    synthetic_sequence: Path, tmp_path: Path
) -> None:
    assert replay_sequence(synthetic_sequence, tmp_path / "r", 500.0, frames=2) == 2
    seq = load_sequence(tmp_path / "r")
    assert len(seq) == 2 and seq.truth is not None and len(seq.truth) == 2
    with pytest.raises(SequenceError, match="not empty"):
        replay_sequence(synthetic_sequence, tmp_path / "r", 5.0)


def test_replay_keeps_its_pace(synthetic_sequence: Path, tmp_path: Path) -> None:
    stamps: list[float] = []
    t0 = time.monotonic()
    replay_sequence(
        synthetic_sequence,
        tmp_path / "r",
        20.0,
        progress=lambda k, n: stamps.append(time.monotonic()),
    )
    # frame k is written no earlier than k / rate after the start (a lower bound, not timing)
    assert all(s - t0 >= k / 20.0 for k, s in enumerate(stamps))


# --------------------------------------------------------------------------------------------
# A ROS bag replayed at its recorded rate (`BagReplay`)
# --------------------------------------------------------------------------------------------


class _Clock:
    """A wall clock the test sets (Unix time [s]): the replay's schedule without waiting."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize(("ros", "rate"), [(1, 1.0), (2, 4.0)])
def test_a_bag_replays_its_pairs_at_their_recorded_times(
    synthetic_sequence: Path, tmp_path: Path, ros: int, rate: float
) -> None:
    seq = load_sequence(synthetic_sequence)  # 4 frames 0.5 s apart
    bag = write_bag(seq, tmp_path / ("rec.bag" if ros == 1 else "rec"), ros=ros)  # type: ignore[arg-type]
    clock = _Clock(1000.0)
    replay = BagReplay(bag, rate=rate, clock=clock)
    head = replay.header
    assert head.kind == "stereo" and head.root == bag
    assert head.rate_hz == pytest.approx(2.0, rel=1e-9)  # from the first two stamps
    for cam in ("left", "right"):
        a, b = head.calibration.camera(cam), seq.calibration.camera(cam)  # type: ignore[arg-type]
        assert a.size == b.size
        np.testing.assert_allclose(a.K, b.K, rtol=0, atol=1e-9)  # the import's bound
        np.testing.assert_allclose(a.dist, b.dist, rtol=0, atol=1e-9)
    frames, skipped = replay.poll()  # the replay starts: pair 0 arrives now
    assert [f.index for f in frames] == [0] and skipped == []
    assert frames[0].arrival_s == 1000.0 and frames[0].files == ()
    clock.now = 1000.0 + 0.5 / rate - 1e-6  # just before pair 1 is due
    assert replay.poll() == ([], [])
    clock.now = 1000.0 + 1.2 / rate  # pairs 1 and 2 are due, 3 is not
    frames, _ = replay.poll()
    assert [f.index for f in frames] == [1, 2]
    assert [f.arrival_s for f in frames] == [1000.0 + 0.5 / rate, 1000.0 + 1.0 / rate]
    assert all(f.seen_s == clock.now for f in frames)
    for f in frames:
        fr = seq.frames[f.index]
        assert f.t_s == round(fr.t_s * 1e9) / 1e9  # the header stamp, in ns
        left, right = f.read()  # decoded only now, exactly the images written
        np.testing.assert_array_equal(left, fr.left())
        np.testing.assert_array_equal(right, fr.right())
    assert not replay.ended()
    clock.now += 10.0
    frames, _ = replay.poll()
    assert [f.index for f in frames] == [3] and replay.ended()
    notes = replay.notes()
    assert any("pairing within 5 ms: 4 pairs" in n for n in notes)
    assert any("calibration: from the recording" in n for n in notes)
    replay.close()


def test_bag_replay_takes_the_import_options(synthetic_sequence: Path, tmp_path: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    topics = ("/a/image_raw", "/b/image_raw")
    bag = write_bag(seq, tmp_path / "rec", ros=2, topics=topics, camera_info=False)
    with pytest.raises(RecordingError, match="calibration: the recording carries none"):
        BagReplay(bag)
    opts = ImportOptions(
        left=topics[1], right=topics[0], calib=synthetic_sequence / "calib.yaml", grey=True
    )
    replay = BagReplay(bag, opts, clock=_Clock(0.0))
    (f,), _ = replay.poll()
    left, right = f.read()
    np.testing.assert_array_equal(left, seq.frames[0].right())  # the topics as given
    assert right.ndim == 2  # --grey: the colour camera converted
    replay.close()


def test_bag_replay_refuses_what_it_cannot_track(synthetic_sequence: Path, tmp_path: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    missing = tmp_path / "none.bag"
    with pytest.raises(RecordingError, match=f"^{missing}: does not exist"):
        BagReplay(missing)
    bag = tmp_path / "info_only"
    with BagWriter(bag, 2) as w:
        w.write("/cam0/camera_info", 1, w.camera_info_msg(1, seq.calibration.left))
    with pytest.raises(RecordingError, match=f"^{bag}: topics: no sensor_msgs/Image"):
        BagReplay(bag)
    mono = tmp_path / "mono.bag"
    with BagWriter(mono, 1) as w:
        w.write("/cam0/image_raw", 1, w.image_msg(1, seq.frames[0].right()))
    with pytest.raises(RecordingError, match=f"^{mono}: topics: live tracking needs a stereo"):
        BagReplay(mono)
    with pytest.raises(RecordingError, match="not a ROS bag"):
        BagReplay(synthetic_sequence)
