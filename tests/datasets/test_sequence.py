"""Sequence format v1: round trip, every bad-input error, atomic writes."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from satpose.datasets.errors import SequenceError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import (
    FORMAT_VERSION,
    SequenceWriter,
    load_sequence,
    write_sequence,
)


def test_round_trip_is_exact(synthetic_sequence: Path, tmp_path: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    copy = load_sequence(write_sequence(seq, tmp_path / "copy"))
    assert (copy.name, copy.kind, copy.rate_hz) == ("synthetic", "stereo", 2.0)
    assert len(copy) == len(seq) == 4
    for a, b in zip(seq, copy, strict=True):
        assert (a.index, a.t_s) == (b.index, b.t_s)
        np.testing.assert_array_equal(a.left(), b.left())  # PNG is lossless
        np.testing.assert_array_equal(a.right(), b.right())
        np.testing.assert_array_equal(a.mask("left"), b.mask("left"))
    np.testing.assert_allclose(copy.calibration.left.K, seq.calibration.left.K, rtol=0, atol=0)
    np.testing.assert_allclose(
        copy.calibration.right_from_left.matrix(),
        seq.calibration.right_from_left.matrix(),
        atol=1e-15,
    )
    assert seq.truth is not None and copy.truth is not None
    # 15 significant digits in the CSV: poses survive to 1e-14.
    np.testing.assert_allclose(copy.truth.translation, seq.truth.translation, atol=1e-13)
    np.testing.assert_allclose(copy.truth.quat_xyzw, seq.truth.quat_xyzw, atol=1e-14)
    np.testing.assert_allclose(copy.truth.angular_velocity, seq.truth.angular_velocity, atol=1e-14)
    assert copy.target is not None and copy.target.ring is not None
    assert copy.target.ring.radius_m == 0.3
    np.testing.assert_allclose(copy.target.panel_corners, seq.target.panel_corners, atol=1e-15)
    assert copy.target.extras["note"] == "synthetic"


def test_frames_are_lazy_and_typed(synthetic_sequence: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    fr = seq[1]
    assert fr.left().shape == (32, 48, 3) and fr.left().dtype == np.uint8
    assert fr.right().shape == (32, 48)
    assert fr.mask("right") is None  # only left masks were written
    seq.verify()


def test_truth_rotations_are_rotations(tmp_path: Path, make_sequence) -> None:  # type: ignore[no-untyped-def]
    truth = load_sequence(make_sequence(tmp_path / "s", seed=3)).truth
    assert truth is not None
    R = truth.rotations()
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    assert isinstance(truth.pose(0), Rigid3)


# ------------------------------------------------------------------------------------------
# Bad input: each case names the file and the field.
# ------------------------------------------------------------------------------------------


def _edit_csv(path: Path, fn) -> None:  # type: ignore[no-untyped-def]
    """Rewrite a CSV through ``fn``, which edits the frame in place or returns a new one."""
    df = pd.read_csv(path)
    out = fn(df)
    (df if out is None else out).to_csv(path, index=False)


def _edit_yaml(path: Path, fn) -> None:  # type: ignore[no-untyped-def]
    data = yaml.safe_load(path.read_text())
    fn(data)
    path.write_text(yaml.safe_dump(data))


def _expect(seq: Path, file: str, field: str | None, words: str) -> SequenceError:
    with pytest.raises(SequenceError) as info:
        load_sequence(seq).verify()
    err = info.value
    assert err.path.name == Path(file).name, str(err)
    if field is not None:
        assert err.field == field, str(err)
    assert words in str(err), str(err)
    return err


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(SequenceError, match="does not exist"):
        load_sequence(tmp_path / "nope")


@pytest.mark.parametrize("name", ["sequence.yaml", "calib.yaml", "frames.csv"])
def test_missing_required_file(synthetic_sequence: Path, name: str) -> None:
    (synthetic_sequence / name).unlink()
    _expect(synthetic_sequence, name, None, "required file is missing")


def test_missing_image(synthetic_sequence: Path) -> None:
    (synthetic_sequence / "right" / "000002.png").unlink()
    _expect(synthetic_sequence, "000002.png", None, "is missing")


def test_unknown_format_version(synthetic_sequence: Path) -> None:
    _edit_yaml(
        synthetic_sequence / "sequence.yaml", lambda d: d.update(format="satpose-sequence/2")
    )
    _expect(synthetic_sequence, "sequence.yaml", "format", "unknown format version")


def test_missing_format_key(synthetic_sequence: Path) -> None:
    _edit_yaml(synthetic_sequence / "sequence.yaml", lambda d: d.pop("format"))
    _expect(synthetic_sequence, "sequence.yaml", "format", FORMAT_VERSION)


def test_bad_kind(synthetic_sequence: Path) -> None:
    _edit_yaml(synthetic_sequence / "sequence.yaml", lambda d: d.update(kind="trinocular"))
    _expect(synthetic_sequence, "sequence.yaml", "kind", "stereo")


def test_missing_column(synthetic_sequence: Path) -> None:
    _edit_csv(synthetic_sequence / "groundtruth.csv", lambda df: df.drop(columns=["qw"]))
    _expect(synthetic_sequence, "groundtruth.csv", "qw", "missing column")


def test_wrong_column(synthetic_sequence: Path) -> None:
    _edit_csv(synthetic_sequence / "frames.csv", lambda df: df.rename(columns={"t_s": "time"}))
    err = _expect(synthetic_sequence, "frames.csv", None, "column")
    assert "t_s" in str(err) or "time" in str(err)


def test_partial_velocity_columns(synthetic_sequence: Path) -> None:
    _edit_csv(synthetic_sequence / "groundtruth.csv", lambda df: df.drop(columns=["wz"]))
    _expect(synthetic_sequence, "groundtruth.csv", "wx,wy,wz", "all three")


def test_non_increasing_time(synthetic_sequence: Path) -> None:
    def swap(df: pd.DataFrame) -> None:
        df.loc[2, "t_s"] = df.loc[1, "t_s"]

    _edit_csv(synthetic_sequence / "frames.csv", swap)
    err = _expect(synthetic_sequence, "frames.csv", "t_s", "strictly greater")
    # plain numbers, not numpy reprs (np.float64(0.5))
    assert str(err).endswith("row 3: 0.5 is not strictly greater than the previous row's 0.5")


def test_non_increasing_frame_index(synthetic_sequence: Path) -> None:
    def dup(df: pd.DataFrame) -> None:
        df.loc[3, "frame"] = 1

    _edit_csv(synthetic_sequence / "frames.csv", dup)
    _expect(synthetic_sequence, "frames.csv", "frame", "strictly greater")


def test_nan_in_truth(synthetic_sequence: Path) -> None:
    def nan(df: pd.DataFrame) -> None:
        df.loc[1, "ty"] = np.nan

    _edit_csv(synthetic_sequence / "groundtruth.csv", nan)
    err = _expect(synthetic_sequence, "groundtruth.csv", "ty", "NaN")
    assert "row 2" in str(err)


def test_nan_in_calibration(synthetic_sequence: Path) -> None:
    _edit_yaml(
        synthetic_sequence / "calib.yaml",
        lambda d: d["cameras"]["left"]["K"].__setitem__(2, float("nan")),
    )
    _expect(synthetic_sequence, "calib.yaml", "cameras.left.K[2]", "finite")


def test_wrong_calibration_shape(synthetic_sequence: Path) -> None:
    _edit_yaml(
        synthetic_sequence / "calib.yaml", lambda d: d["cameras"]["right"].update(K=[1, 2, 3])
    )
    _expect(synthetic_sequence, "calib.yaml", "cameras.right.K", "expected 9 numbers")


def test_non_unit_quaternion_truth(synthetic_sequence: Path) -> None:
    def scale(df: pd.DataFrame) -> None:
        df.loc[0, ["qx", "qy", "qz", "qw"]] *= 1.01

    _edit_csv(synthetic_sequence / "groundtruth.csv", scale)
    _expect(synthetic_sequence, "groundtruth.csv", "qx,qy,qz,qw", "not unit norm")


def test_non_unit_quaternion_extrinsics(synthetic_sequence: Path) -> None:
    _edit_yaml(
        synthetic_sequence / "calib.yaml",
        lambda d: d["right_from_left"].update(quat_xyzw=[0.0, 0.0, 0.0, 0.9]),
    )
    _expect(synthetic_sequence, "calib.yaml", "right_from_left.quat_xyzw", "not unit norm")


def test_image_size_not_matching_calib(synthetic_sequence: Path) -> None:
    cv2.imwrite(str(synthetic_sequence / "left" / "000001.png"), np.zeros((30, 48, 3), np.uint8))
    _expect(synthetic_sequence, "000001.png", "width/height", "48x30")
    # The lazy path raises the same error when the frame is read.
    with pytest.raises(SequenceError, match=r"calib\.yaml says 48x32"):
        load_sequence(synthetic_sequence)[1].left()


def test_unreadable_png(synthetic_sequence: Path) -> None:
    (synthetic_sequence / "left" / "000003.png").write_bytes(b"not a png at all, just text")
    _expect(synthetic_sequence, "000003.png", None, "not a readable PNG")
    with pytest.raises(SequenceError, match="not a readable PNG"):
        load_sequence(synthetic_sequence)[3].left()


def test_truncated_png(synthetic_sequence: Path) -> None:
    p = synthetic_sequence / "right" / "000000.png"
    p.write_bytes(p.read_bytes()[:60])  # the header survives, the data does not
    with pytest.raises(SequenceError, match="not a readable PNG"):
        load_sequence(synthetic_sequence)[0].right()


def test_truth_frames_must_match(synthetic_sequence: Path) -> None:
    _edit_csv(synthetic_sequence / "groundtruth.csv", lambda df: df.drop(index=[2]))
    _expect(synthetic_sequence, "groundtruth.csv", "frame", "one row per frame")


def test_corrupt_yaml(synthetic_sequence: Path) -> None:
    (synthetic_sequence / "calib.yaml").write_text("cameras: [unclosed\n")
    _expect(synthetic_sequence, "calib.yaml", None, "not valid YAML")


def test_truncated_yaml_names_the_line(synthetic_sequence: Path) -> None:
    path = synthetic_sequence / "calib.yaml"
    lines = path.read_text().splitlines(keepends=True)
    cut = next(i for i, line in enumerate(lines) if "K: [" in line)
    # cut inside the first K list: the parser runs into the end of the file
    path.write_text("".join(lines[:cut]) + lines[cut][: lines[cut].index("[") + 4])
    err = _expect(synthetic_sequence, "calib.yaml", None, "not valid YAML")
    assert f"line {cut + 1}, column " in str(err)
    assert "<stream end>" in str(err)


def test_mono_sequence_has_no_right_column(tmp_path: Path) -> None:
    from satpose.datasets.camera import PinholeCamera
    from satpose.datasets.sequence import Calibration

    cam = PinholeCamera(width=16, height=16, K=np.array([[20.0, 0, 7.5], [0, 20, 7.5], [0, 0, 1]]))
    with SequenceWriter(
        tmp_path / "mono", name="m", kind="mono", rate_hz=1.0, calibration=Calibration(left=cam)
    ) as w:
        w.add_frame(0, 0.0, np.zeros((16, 16), np.uint16))
    seq = load_sequence(tmp_path / "mono")
    assert list(pd.read_csv(tmp_path / "mono" / "frames.csv").columns) == ["frame", "t_s", "left"]
    assert seq.truth is None and seq.target is None
    assert seq[0].left().dtype == np.uint16
    with pytest.raises(SequenceError, match="mono"):
        seq[0].right()


# ------------------------------------------------------------------------------------------
# Writer: atomic, refuses to clobber, validates.
# ------------------------------------------------------------------------------------------


def test_writer_failure_leaves_nothing(tmp_path: Path, synthetic_sequence: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with SequenceWriter(
            out, name="x", kind="stereo", rate_hz=1.0, calibration=seq.calibration
        ) as w:
            w.add_frame(0, 0.0, seq[0].left(), seq[0].right())
            raise RuntimeError("simulated crash mid-sequence")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [synthetic_sequence]  # no temporary folder left behind


def test_writer_refuses_existing_folder(synthetic_sequence: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    with pytest.raises(SequenceError, match="already exists"):
        SequenceWriter(
            synthetic_sequence, name="x", kind="stereo", rate_hz=1.0, calibration=seq.calibration
        )


def test_writer_overwrite_replaces_only_when_complete(tmp_path: Path, make_sequence) -> None:  # type: ignore[no-untyped-def]
    path = make_sequence(tmp_path / "s", frames=4)
    seq = load_sequence(path)
    snapshot = tmp_path / "snapshot"
    shutil.copytree(path, snapshot)
    with pytest.raises(RuntimeError):
        with SequenceWriter(
            path, name="x", kind="stereo", rate_hz=1.0, calibration=seq.calibration, overwrite=True
        ) as w:
            w.add_frame(0, 0.0, seq[0].left(), seq[0].right())
            raise RuntimeError("crash")
    assert len(load_sequence(path)) == 4  # the old sequence is intact
    make_sequence_path = write_sequence(load_sequence(snapshot), path, overwrite=True)
    assert len(load_sequence(make_sequence_path)) == 4


def test_writer_rejects_wrong_image_size(synthetic_sequence: Path, tmp_path: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    w = SequenceWriter(
        tmp_path / "o", name="x", kind="stereo", rate_hz=1.0, calibration=seq.calibration
    )
    with pytest.raises(SequenceError, match=r"calib\.yaml says 48x32"):
        w.add_frame(0, 0.0, np.zeros((10, 10), np.uint8), seq[0].right())
    w.abort()
    assert not (tmp_path / "o").exists()


def test_writer_rejects_time_going_back(synthetic_sequence: Path, tmp_path: Path) -> None:
    seq = load_sequence(synthetic_sequence)
    with pytest.raises(SequenceError, match="does not come after"):
        with SequenceWriter(
            tmp_path / "o", name="x", kind="stereo", rate_hz=1.0, calibration=seq.calibration
        ) as w:
            w.add_frame(0, 1.0, seq[0].left(), seq[0].right())
            w.add_frame(1, 1.0, seq[0].left(), seq[0].right())
    assert not (tmp_path / "o").exists()
