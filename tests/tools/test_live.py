"""`satpose track --live` on a folder a recorder is writing, and `satpose record-replay`."""

from __future__ import annotations

import signal
import socket
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import rerun as rr
import yaml
from rerun.chunk import RrdReader

from satpose.datasets.importers.writers import BagWriter, write_bag
from satpose.datasets.live import RECORDING_DONE, BagReplay, Recorder
from satpose.datasets.sequence import SequenceWriter, load_sequence
from satpose.tools.cli import main
from satpose.tools.live import LIVE_COLUMNS, frame_ranges, track_bag, track_folder
from satpose.tools.pipeline import TRAJECTORY_COLUMNS, read_estimate_npz

REPLAY_HZ = 2.0
"""The replayed recording's rate when it is 'low': at most this, and the next frame only once
the tracker has processed the previous one, so that no frame is dropped however loaded the
machine is (a rate the tracker keeps up with, made deterministic)."""

DETERMINISTIC = [
    "trajectory.csv",
    "trajectory.tum",
    "trajectory_smoothed.csv",
    "trajectory_smoothed.tum",
    "estimate.npz",
    "estimate_smoothed.npz",
    "estimate_offline.npz",
    "estimate_kalman.npz",
    "frontend_pose.tum",
    "measurements.parquet",
    "config.yaml",
]
"""A run folder's outputs that do not depend on the wall clock (as in test_pipeline.py)."""


def _processed(run: Path) -> int:
    try:
        return (run / "live_frames.csv").read_text().count(",processed,")
    except FileNotFoundError:
        return 0


@pytest.fixture(scope="module")
def live_run(docking_small: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A recorder thread writes docking_small at a low rate (`REPLAY_HZ`) while `satpose track
    --live` runs: the recorded folder and the run folder."""
    base = tmp_path_factory.mktemp("live")
    seq, run = base / "recording", base / "run"
    errors: list[BaseException] = []

    def record() -> None:
        try:
            time.sleep(0.2)  # the tracker starts first and waits for sequence.yaml
            rec = Recorder(docking_small, seq)
            rec.start()
            start = time.monotonic()
            for k in range(len(rec)):
                while _processed(run) < k or time.monotonic() < start + k / REPLAY_HZ:
                    time.sleep(0.01)
                rec.write(k)
            rec.finish()
        except BaseException as exc:  # reported after the join
            errors.append(exc)

    thread = threading.Thread(target=record)
    thread.start()
    try:
        code = main(["track", str(seq), "--live", "--out", str(run), "--until-idle", "120"])
    finally:
        thread.join()
    assert not errors and code == 0
    return seq, run


def test_record_replay_writes_the_sequence_as_a_recorder(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rec"
    assert main(["record-replay", str(docking_small), "--out", str(out), "--rate", "500"]) == 0
    assert "then recording.done" in capsys.readouterr().out
    a, b = load_sequence(docking_small), load_sequence(out)
    assert [(f.index, f.t_s) for f in a] == [(f.index, f.t_s) for f in b]
    for x, y in zip(a, b, strict=True):
        assert x.left_path.read_bytes() == y.left_path.read_bytes()
    assert (out / RECORDING_DONE).is_file()
    assert main(["record-replay", str(docking_small), "--out", str(out), "--rate", "5"]) == 2
    assert "not empty" in capsys.readouterr().err


def test_every_frame_is_processed_at_a_low_rate(
    live_run: tuple[Path, Path], docking_small: Path
) -> None:
    seq, run = live_run
    n = len(load_sequence(docking_small))
    frames = pd.read_csv(run / "live_frames.csv")
    assert list(frames.columns) == LIVE_COLUMNS
    assert frames["frame"].tolist() == list(range(n))
    assert (frames["status"] == "processed").all()
    assert (frames["latency_ms"] > 0).all() and (frames["pickup_ms"] >= 0).all()
    prov = yaml.safe_load((run / "run.yaml").read_text())
    assert prov["state"] == "complete" and prov["mode"] == "live"
    live = prov["live"]
    assert live["processed"] == n and live["dropped"] == 0
    assert live["stopped_by"] == "the recording ended"
    assert live["latency_ms"]["median"] > 0
    timings = pd.read_csv(run / "timings.csv")
    assert timings["frame"].tolist() == list(range(n))
    assert {"latency_ms", "pickup_ms", "wait_ms", "frontend_total", "backend_online"} <= set(
        timings.columns
    )
    assert (seq / RECORDING_DONE).is_file()


def test_comparison_estimators_run_once_at_the_end(live_run: tuple[Path, Path]) -> None:
    """A live step is the frontend, iSAM2 and the recording; the offline smoother and the
    Kalman filter get every frame's measurements at the end (their files are written, and
    equal `satpose run`'s: test_live_equals_run_online_on_the_same_frames)."""
    _, run = live_run
    timings = pd.read_csv(run / "timings.csv")
    assert "backend_online" in timings.columns
    assert not {"backend_offline", "backend_kalman"} & set(timings.columns)
    live = yaml.safe_load((run / "run.yaml").read_text())["live"]
    assert live["compared_at_end"] == ["offline", "kalman"]
    assert live["end_of_run_ms"] > 0
    n = live["processed"]
    for name in ("offline", "kalman"):
        assert len(read_estimate_npz(run / f"estimate_{name}.npz")) == n
    # run.rrd: the Kalman filter's causal trajectory and spin rates, logged at the end (a live
    # run has no truth, so no error series)
    store = RrdReader(str(run / "run.rrd")).store()
    entities = Counter(c.entity_path.lstrip("/") for c in store.stream())
    assert "world/trajectory/kalman" in entities
    rows = sum(
        c.num_rows
        for c in store.stream()
        if c.entity_path.lstrip("/") == "plots/spin/kalman" and not c.is_static
    )
    assert rows == n


def _only(seq: Path, frames: list[int], out: Path) -> Path:
    """A copy of the sequence with only these frames."""
    src = load_sequence(seq)
    assert src.truth is not None
    with SequenceWriter(
        out, name=src.name, kind="stereo", rate_hz=src.rate_hz, calibration=src.calibration
    ) as w:
        for k, fr in enumerate(src):
            if fr.index in frames:
                w.add_frame(fr.index, fr.t_s, fr.left(), fr.right(), truth=src.truth.pose(k))
    return out


def test_live_equals_run_online_on_the_same_frames(
    live_run: tuple[Path, Path], tmp_path: Path
) -> None:
    seq, run = live_run  # the recorded folder is a finished sequence now
    processed = pd.read_csv(run / "live_frames.csv").query("status == 'processed'")["frame"]
    if len(processed) < len(load_sequence(seq)):  # a loaded machine dropped some: those frames
        seq = _only(seq, processed.tolist(), tmp_path / "processed")
    assert main(["run", str(seq), "--estimator", "online", "--out", str(tmp_path / "ref")]) == 0
    for name in DETERMINISTIC:
        assert (run / name).read_bytes() == (tmp_path / "ref" / name).read_bytes(), name
    # without --live, track is run --estimator online
    assert main(["track", str(seq), "--out", str(tmp_path / "track")]) == 0
    for name in DETERMINISTIC:
        assert (tmp_path / "track" / name).read_bytes() == (tmp_path / "ref" / name).read_bytes()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Lockstep:
    """A recorder paced by the tracker: after each processed frame it writes the next
    ``burst`` frames (the last time also the end marker), so the tracker finds them all
    complete at once: as if they arrived faster than its step, without any timing."""

    def __init__(self, source: Path, out: Path, burst: int) -> None:
        self.rec = Recorder(source, out)
        self.rec.start()
        self.rec.write(0)
        self.burst = burst
        self.prefixes: list[pd.DataFrame] = []

    def __call__(self, status: dict[str, Any]) -> None:
        # what a reader sees mid-run: trajectory.csv is a readable prefix
        self.prefixes.append(pd.read_csv(self.rec.out.parent / "run" / "trajectory.csv"))
        n = len(self.rec)
        for k in range(self.rec.written, min(self.rec.written + self.burst, n)):
            self.rec.write(k)
        if self.rec.written == n and not (self.rec.out / RECORDING_DONE).exists():
            self.rec.finish()


def test_frames_are_dropped_when_they_come_faster_than_the_step(
    docking_small: Path, tmp_path: Path
) -> None:
    recorder = _Lockstep(docking_small, tmp_path / "recording", burst=3)
    server = rr.RecordingStream("satpose-test-viewer")  # a Rerun gRPC server, as a viewer runs
    url = rr.serve_grpc(grpc_port=_free_port(), recording=server)
    result = track_folder(
        tmp_path / "recording",
        tmp_path / "run",
        until_idle_s=30,
        connect=url,
        progress=recorder,
    )
    # frame 0; then 1, 2, 3 complete at once: 3 processed; then 4, 5: 5 processed
    assert result.processed == 3 and result.dropped == [1, 2, 4]
    frames = pd.read_csv(tmp_path / "run" / "live_frames.csv")
    processed, dropped = "processed", "dropped"
    assert frames["status"].tolist() == [processed, dropped, dropped, processed, dropped, processed]
    assert set(frames.loc[frames["status"] == "dropped", "reason"]) == {"behind"}
    summary = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["live"]
    assert summary["dropped"] == 3 and summary["dropped_frames"] == "1-2, 4"
    assert summary["dropped_by_reason"] == {"behind": 3}
    final = pd.read_csv(tmp_path / "run" / "trajectory.csv")
    assert list(final.columns) == TRAJECTORY_COLUMNS
    assert final["frame"].tolist() == [0, 3, 5]
    for prefix in recorder.prefixes:  # each mid-run state is a prefix of the final file
        assert list(prefix.columns) == TRAJECTORY_COLUMNS
        np.testing.assert_array_equal(
            prefix.to_numpy(float), final.iloc[: len(prefix)].to_numpy(float)
        )
    assert len(recorder.prefixes[-1]) >= 2
    # the file sink is complete while streaming to the viewer: one image per processed frame
    rows = sum(
        c.num_rows
        for c in RrdReader(str(tmp_path / "run" / "run.rrd")).store().stream()
        if c.entity_path.lstrip("/") == "world/camera/left/image" and not c.is_static
    )
    assert rows == 3


def test_a_partly_written_image_is_retried_not_failed(docking_small: Path, tmp_path: Path) -> None:
    rec = Recorder(docking_small, tmp_path / "recording")
    rec.start()
    rec.write(0)
    rec.write(1)
    left = rec.out / "left" / rec.seq.frames[1].left_path.name
    data = left.read_bytes()
    left.write_bytes(data[: len(data) // 2])  # frame 1's row is there, its left image half

    def finish() -> None:
        while not (tmp_path / "run" / "live_frames.csv").is_file():
            time.sleep(0.01)
        time.sleep(0.3)  # the tracker polls the half image for a while
        with open(left, "ab") as fh:
            fh.write(data[len(data) // 2 :])
        rec.finish()

    thread = threading.Thread(target=finish)
    thread.start()
    try:
        result = track_folder(rec.out, tmp_path / "run", until_idle_s=30)
    finally:
        thread.join()
    frames = result.frames
    assert frames.loc[frames["frame"] == 1, "status"].item() == "processed"
    assert result.run.bad_frames.count == 0
    m1 = next(m for m in result.run.measurements if m.frame == 1)
    assert not [f for f in m1.failures if f.startswith("image")] and m1.ring is not None


def test_ctrl_c_leaves_a_complete_run_folder(docking_small: Path, tmp_path: Path) -> None:
    recorder = _Lockstep(docking_small, tmp_path / "recording", burst=1)

    def progress(status: dict[str, Any]) -> None:
        if status["processed"] == 3:
            signal.raise_signal(signal.SIGINT)  # what Ctrl-C sends; the tracker catches it
        else:
            recorder(status)

    result = track_folder(tmp_path / "recording", tmp_path / "run", progress=progress)
    run = tmp_path / "run"
    assert result.stopped_by == "Ctrl-C" and result.processed == 3 and result.dropped == []
    prov = yaml.safe_load((run / "run.yaml").read_text())
    assert prov["state"] == "complete" and prov["live"]["stopped_by"] == "Ctrl-C"
    est = read_estimate_npz(run / "estimate.npz")
    assert est.frame.tolist() == [0, 1, 2]
    traj = pd.read_csv(run / "trajectory.csv")
    np.testing.assert_allclose(traj[["tx", "ty", "tz"]], [T.t for T in est.left_cam_from_target])
    assert not (tmp_path / "recording" / RECORDING_DONE).exists()
    assert not [p.name for p in run.iterdir() if p.name.startswith(".")]


def test_frame_ranges() -> None:
    assert frame_ranges([9, 3, 4, 5, 7]) == "3-5, 7, 9"
    assert frame_ranges([]) == ""


def test_a_run_folder_is_not_replaced_without_overwrite(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    code = main(["track", str(docking_small), "--live", "--out", str(tmp_path / "run")])
    assert code == 2
    assert "not a run folder" in capsys.readouterr().err
    assert (tmp_path / "run" / "notes.txt").read_text() == "mine"


# --------------------------------------------------------------------------------------------
# A ROS bag replayed at its recorded rate
# --------------------------------------------------------------------------------------------


class _SteppedClock:
    """A bag replay's wall clock that moves one frame period per processed frame: the bag's
    frames come exactly as fast as the tracker takes them, so none is dropped however loaded
    the machine is (what `_Lockstep` does for a folder). Starts at the real time."""

    def __init__(self, period_s: float) -> None:
        self.now = time.time()
        self.period_s = period_s

    def __call__(self) -> float:
        return self.now

    def step(self, status: dict[str, Any]) -> None:
        self.now += self.period_s


def test_live_from_a_bag_gives_the_poses_of_track_on_the_folder(
    docking_small: Path, tmp_path: Path
) -> None:
    seq = load_sequence(docking_small)
    bag = write_bag(seq, tmp_path / "docking.bag", ros=1)
    clock = _SteppedClock(1.0 / seq.rate_hz)
    result = track_bag(BagReplay(bag, clock=clock), tmp_path / "run", progress=clock.step)
    assert result.processed == len(seq) and result.dropped == []
    assert main(["track", str(docking_small), "--out", str(tmp_path / "ref")]) == 0
    a = pd.read_csv(tmp_path / "ref" / "trajectory.csv")
    b = pd.read_csv(tmp_path / "run" / "trajectory.csv")
    assert list(a.columns) == list(b.columns) and len(b) == len(seq)
    # The same images; the stamps come back from integer ns (within 0.5 ns of t_s) and the
    # extrinsic through stereoRectify's R, P (1e-15). The solvers' stopping rules (steps of
    # 1e-10, relinearisation thresholds) can turn that into more than one rounding step of
    # trajectory.csv's 9 decimals on some CPUs (2.5e-9 seen on an AVX2 machine, 0 on an
    # AVX-512 one): 1e-6 (1 um, 1 urad) is still far below any mishandled input.
    np.testing.assert_allclose(a.to_numpy(), b.to_numpy(), rtol=0, atol=1e-6)


def test_a_bag_replayed_faster_than_the_step_drops_frames(
    docking_small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    three = load_sequence(_only(docking_small, [0, 1, 2], tmp_path / "three"))
    bag = write_bag(three, tmp_path / "rec", ros=2)
    run = tmp_path / "run"
    # recorded 5 s apart, replayed 5 ms apart: frames 1 and 2 both arrive during frame 0's
    # step (an acquisition: far longer than 10 ms), so 1 is dropped and 2 processed
    assert main(["track", str(bag), "--live", "--rate", "1000", "--out", str(run)]) == 0
    out = capsys.readouterr().out
    assert "pairing within 5 ms: 3 pairs; unpaired 0 of 3 left, 0 of 3 right" in out
    assert "2 of 3 frames processed, 1 dropped (behind 1: frames 1)" in out
    assert "stopped: the recording ended" in out
    frames = pd.read_csv(run / "live_frames.csv")
    assert frames["status"].tolist() == ["processed", "dropped", "processed"]
    assert (frames.loc[frames["status"] == "processed", "latency_ms"] > 0).all()
    prov = yaml.safe_load((run / "run.yaml").read_text())
    assert prov["state"] == "complete" and prov["sequence"] == str(bag.resolve())
    assert prov["live"]["dropped_frames"] == "1"
    assert pd.read_csv(run / "trajectory.csv")["frame"].tolist() == [0, 2]


@pytest.mark.parametrize("case", ["missing", "no image topic", "not live", "options on a folder"])
def test_bad_bag_input_is_one_line_exit_2(
    synthetic_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    seq = load_sequence(synthetic_sequence)
    run = tmp_path / "run"
    live = ["--live", "--out", str(run)]
    if case == "missing":
        bag = tmp_path / "absent.bag"
        args, where = [str(bag), *live], f"{bag}: does not exist"
    elif case == "no image topic":
        bag = tmp_path / "info_only"
        with BagWriter(bag, 2) as w:
            w.write("/cam0/camera_info", 1, w.camera_info_msg(1, seq.calibration.left))
        args, where = [str(bag), *live], f"{bag}: topics: no sensor_msgs/Image"
    elif case == "not live":
        bag = write_bag(seq, tmp_path / "rec", ros=2)
        args, where = [str(bag), "--out", str(run)], f"{bag}: a bag is tracked as it replays"
    else:
        args = [str(synthetic_sequence), *live, "--rate", "2"]
        where = f"{synthetic_sequence}: --rate, --left"
    assert main(["track", *args]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"satpose track: error: {where}"), lines[0]
    assert not run.exists()
