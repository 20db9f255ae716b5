"""Image messages decoded exactly (encodings, row padding, byte order, Bayer patterns,
compressed images), stereo pairing by stamp, and timestamp files."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from satpose.datasets.importers import RecordingError, decode_image, read_timestamps
from satpose.datasets.importers.common import TopicStats, pair_by_stamp

BAG = Path("rec.bag")


def image_msg(arr: np.ndarray, encoding: str, pad: int = 0, big_endian: bool = False) -> object:
    """A stand-in for a deserialised sensor_msgs/Image: the fields decode_image reads."""
    h, w = arr.shape[:2]
    raw = arr.astype(arr.dtype.newbyteorder(">") if big_endian else arr.dtype, copy=True)
    rows = raw.reshape(h, -1).view(np.uint8)
    padded = np.concatenate([rows, np.full((h, pad), 7, np.uint8)], axis=1)
    return SimpleNamespace(
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(big_endian),
        step=padded.shape[1],
        data=padded.reshape(-1),
    )


RNG = np.random.default_rng(3)
GREY8 = RNG.integers(0, 256, (5, 7), dtype=np.uint8)
GREY16 = RNG.integers(0, 65536, (5, 7), dtype=np.uint16)
BGR8 = RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8)
BGR16 = RNG.integers(0, 65536, (5, 7, 3), dtype=np.uint16)


@pytest.mark.parametrize(
    ("arr", "encoding", "expected"),
    [
        (GREY8, "mono8", GREY8),
        (GREY8, "8UC1", GREY8),
        (GREY16, "mono16", GREY16),
        (BGR8, "bgr8", BGR8),
        (BGR8[..., ::-1], "rgb8", BGR8),
        (np.dstack([BGR8, GREY8]), "bgra8", BGR8),
        (np.dstack([BGR8[..., ::-1], GREY8]), "rgba8", BGR8),
        (BGR16, "bgr16", BGR16),
        (BGR16[..., ::-1], "rgb16", BGR16),
    ],
)
@pytest.mark.parametrize("pad", [0, 3])
@pytest.mark.parametrize("big_endian", [False, True])
def test_raw_encodings_decode_exactly(
    arr: np.ndarray, encoding: str, expected: np.ndarray, pad: int, big_endian: bool
) -> None:
    out = decode_image(image_msg(np.ascontiguousarray(arr), encoding, pad, big_endian), BAG, "/c")
    np.testing.assert_array_equal(out, expected)
    assert out.dtype == expected.dtype


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_bayer_patterns_demosaic_a_flat_colour(pattern: str, dtype: type) -> None:
    # A flat colour mosaicked with the ROS pattern (the 2x2 block at the top-left pixel):
    # demosaicing must give the colour back everywhere away from the border.
    bgr = {"b": 10, "g": 100, "r": 200}
    if dtype is np.uint16:
        bgr = {k: v * 250 for k, v in bgr.items()}
    mosaic = np.zeros((12, 16), dtype=dtype)
    for dy in (0, 1):
        for dx in (0, 1):
            mosaic[dy::2, dx::2] = bgr[pattern[2 * dy + dx]]
    bits = 8 if dtype is np.uint8 else 16
    out = decode_image(image_msg(mosaic, f"bayer_{pattern}{bits}"), BAG, "/c")
    assert out.shape == (12, 16, 3)
    np.testing.assert_array_equal(out[2:-2, 2:-2].reshape(-1, 3)[0], [bgr["b"], bgr["g"], bgr["r"]])
    assert np.all(out[2:-2, 2:-2] == out[2, 2])


def test_yuv422_decodes_to_bgr() -> None:
    uyvy = np.full((4, 8, 2), 128, np.uint8)
    uyvy[..., 1] = 90  # Y = 90, U = V = 128: grey
    out = decode_image(image_msg(uyvy, "yuv422"), BAG, "/c")
    assert out.shape == (4, 8, 3)
    # BT.601 video range (OpenCV's and cv_bridge's conversion): 1.164 (Y - 16) = 86.1.
    assert np.all(np.abs(out.astype(float) - 1.164 * (90 - 16)) <= 1)


def test_compressed_png_and_bayer_prefix() -> None:
    ok, buf = cv2.imencode(".png", GREY16)
    assert ok
    msg = SimpleNamespace(format="png", data=buf.reshape(-1))
    np.testing.assert_array_equal(decode_image(msg, BAG, "/c/compressed"), GREY16)
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[0::2, 0::2] = 200
    mosaic[0::2, 1::2] = 100
    mosaic[1::2, 0::2] = 100
    mosaic[1::2, 1::2] = 10
    ok, buf = cv2.imencode(".png", mosaic)
    msg = SimpleNamespace(format="bayer_rggb8; png compressed ", data=buf.reshape(-1))
    np.testing.assert_array_equal(decode_image(msg, BAG, "/c/compressed")[4, 4], [10, 100, 200])


@pytest.mark.parametrize(
    ("msg", "field"),
    [
        (image_msg(GREY8.astype(np.float32), "32FC1"), "/c encoding"),
        (image_msg(GREY8, "mono16"), "/c data"),  # half the bytes a mono16 image needs
        (SimpleNamespace(format="jpeg", data=np.zeros(10, np.uint8)), "/c format"),
        (
            SimpleNamespace(format="16UC1; compressedDepth", data=np.zeros(10, np.uint8)),
            "/c format",
        ),
    ],
)
def test_undecodable_images_name_the_bag_and_field(msg: object, field: str) -> None:
    with pytest.raises(RecordingError) as err:
        decode_image(msg, BAG, "/c")
    assert str(err.value).startswith(f"{BAG}: {field}: ")


def _pair(
    left_ns: list[int], right_ns: list[int], tol_ns: int
) -> tuple[list, TopicStats, TopicStats]:
    items = sorted([(t, "left", t) for t in left_ns] + [(t, "right", t) for t in right_ns])
    L, R = TopicStats("l"), TopicStats("r")
    for _, cam, _t in items:
        (L if cam == "left" else R).messages += 1
    pairs = list(pair_by_stamp(((c, t, t) for t, c, _ in items), tol_ns, L, R))
    return pairs, L, R


def test_pairing_takes_mutual_nearest_stamps() -> None:
    # Right at 40 is within 45 of left 0, but left 50 is closer: 0 stays unpaired.
    pairs, L, R = _pair([0, 50, 100], [40, 101], tol_ns=45)
    assert [(t, a, b) for t, a, b in pairs] == [(50, 50, 40), (100, 100, 101)]
    assert (L.paired, L.unpaired, R.paired, R.unpaired) == (2, 1, 2, 0)


def test_pairing_counts_a_camera_at_half_the_rate() -> None:
    left = list(range(0, 1000, 10))
    right = list(range(0, 1000, 20))
    pairs, L, R = _pair(left, right, tol_ns=2)
    assert len(pairs) == 50 and L.unpaired == 50 and R.unpaired == 0
    assert all(a == b for _, a, b in pairs)


def test_timestamp_files(tmp_path: Path) -> None:
    p = tmp_path / "t.txt"
    p.write_text("0.5\n1.0\n1.25\n")
    np.testing.assert_array_equal(read_timestamps(p), [0.5, 1.0, 1.25])
    p.write_text("#timestamp [ns],filename\n1403636579763555584,a.png\n1403636579813555456,b.png\n")
    np.testing.assert_array_equal(
        read_timestamps(p), [1403636579763555584 / 10**9, 1403636579813555456 / 10**9]
    )
    p.write_text("frame,t_s\n0,0.1\n1,0.2\n")
    np.testing.assert_array_equal(read_timestamps(p), [0.1, 0.2])
    p.write_text("0.5\n0.5\n")
    with pytest.raises(RecordingError, match=r"t.txt: line 2: time 0.5 does not come after"):
        read_timestamps(p)
