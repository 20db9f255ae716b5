"""ROS 1 and ROS 2 bags through the ``rosbags`` library (no ROS install).

`BagSource` opens a bag (a ROS 1 ``.bag``, a ROS 2 folder with metadata.yaml, or a ROS 2
``.db3``/``.mcap`` file), picks the image topics, reads the calibration from the bag's
CameraInfo topics and streams stereo pairs with `BagSource.frames`, a generator of
``(t_s, left, right)`` that a live consumer can read as the bag is decoded.

- **Images**: ``sensor_msgs/Image`` in `ENCODINGS` (mono8/16, bgr/rgb(a) 8/16, Bayer 8/16
  demosaiced to BGR, yuv422) and ``sensor_msgs/CompressedImage`` (anything ``cv2.imdecode``
  reads; a Bayer ``format`` prefix is demosaiced after decoding).
- **Times**: the header stamp (the exposure time the driver stamped), in seconds; a zero stamp
  falls back to the bag's receive time (counted). Per topic, a stamp that does not increase
  is dropped (counted).
- **Topics**: ``left``/``right`` given, or picked when the bag has exactly two image topics
  (stereo: the one whose name says ``left`` or sorts first is left) or exactly one (mono);
  otherwise refused in one line naming the topics.
- **Pairing**: a left and a right image pair when their stamps differ by at most
  ``tolerance_s`` and neither has a closer partner among the next message of the other topic
  (mutual nearest neighbours over a one-message lookahead). Unpaired images are counted;
  `check` refuses a bag where more than ``max_unpaired`` of the images found no partner.
- **Calibration**: for ``/ns/image_raw`` (or ``/ns/image_raw/compressed``) the first message
  on ``/ns/camera_info``. A stereo extrinsic needs the R and P of both infos with a baseline
  (`stereo_from_camera_infos`); without one the import asks for ``--calib``.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np

from satpose.datasets.importers.calib import camera_info, stereo_from_camera_infos
from satpose.datasets.importers.common import (
    DEFAULT_MAX_UNPAIRED,
    DEFAULT_TOLERANCE_S,
    FrameSource,
    RecordingError,
    SourceCalibration,
    SourceCamera,
    StereoFrame,
    TopicStats,
    check_image,
    check_pairing,
    debayer,
    pair_by_stamp,
    pairing_note,
)

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"

# encoding -> (channels, dtype, OpenCV conversion to BGR or None, Bayer pattern or None)
ENCODINGS: dict[str, tuple[int, type, int | None, str | None]] = {
    "mono8": (1, np.uint8, None, None),
    "8uc1": (1, np.uint8, None, None),
    "mono16": (1, np.uint16, None, None),
    "16uc1": (1, np.uint16, None, None),
    "bgr8": (3, np.uint8, None, None),
    "8uc3": (3, np.uint8, None, None),
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR, None),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR, None),
    "8uc4": (4, np.uint8, cv2.COLOR_BGRA2BGR, None),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR, None),
    "bgr16": (3, np.uint16, None, None),
    "16uc3": (3, np.uint16, None, None),
    "rgb16": (3, np.uint16, cv2.COLOR_RGB2BGR, None),
    "bgra16": (4, np.uint16, cv2.COLOR_BGRA2BGR, None),
    "rgba16": (4, np.uint16, cv2.COLOR_RGBA2BGR, None),
    "yuv422": (2, np.uint8, cv2.COLOR_YUV2BGR_UYVY, None),
    "uyvy": (2, np.uint8, cv2.COLOR_YUV2BGR_UYVY, None),
    "yuv422_yuy2": (2, np.uint8, cv2.COLOR_YUV2BGR_YUY2, None),
    "yuyv": (2, np.uint8, cv2.COLOR_YUV2BGR_YUY2, None),
    **{
        f"bayer_{p}{bits}": (1, np.uint8 if bits == 8 else np.uint16, None, p)
        for p in ("rggb", "bggr", "gbrg", "grbg")
        for bits in (8, 16)
    },
}


def decode_image(msg: Any, path: Path, topic: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` or ``CompressedImage`` message as an OpenCV array (grey or
    BGR, uint8/uint16). Raises `RecordingError` naming the bag and ``<topic> encoding``."""
    if hasattr(msg, "format"):  # CompressedImage
        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt:
            raise RecordingError(
                path, f"{topic} format", f"{msg.format!r}: depth images are not camera images"
            )
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise RecordingError(
                path, f"{topic} format", f"{msg.format!r}: cv2.imdecode cannot decode the data"
            )
        original = fmt.split(";")[0].strip()
        if original.startswith("bayer_") and img.ndim == 2:
            img = debayer(img, original[6:10], path, f"{topic} format")
        return check_image(img, path, f"{topic} format")
    enc = str(msg.encoding).lower()
    spec = ENCODINGS.get(enc)
    if spec is None:
        raise RecordingError(
            path,
            f"{topic} encoding",
            f"{msg.encoding!r} is not supported (supported: {', '.join(sorted(ENCODINGS))})",
        )
    channels, dtype, conversion, bayer = spec
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row_bytes = w * (channels if channels != 2 else 2) * itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < row_bytes or data.size < h * step:
        raise RecordingError(
            path,
            f"{topic} data",
            f"{w}x{h} {msg.encoding} with step {step} needs {h * step} bytes, got {data.size}",
        )
    rows = data[: h * step].reshape(h, step)[:, :row_bytes]
    img = np.ascontiguousarray(rows).view(dtype)
    if itemsize > 1 and bool(msg.is_bigendian) != (sys.byteorder == "big"):
        img = img.byteswap()
    img = img.reshape(h, w, channels) if channels > 1 else img.reshape(h, w)
    if channels == 2:  # packed YUV 4:2:2: OpenCV wants (h, w, 2) uint8
        img = img.reshape(h, w, 2)
    if bayer is not None:
        img = debayer(img, bayer, path, f"{topic} encoding")
    elif conversion is not None:
        img = cv2.cvtColor(img, conversion)
    return check_image(img, path, f"{topic} encoding")


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def info_topic_for(image_topic: str) -> str:
    """``/ns/image_raw`` or ``/ns/image_raw/compressed`` -> ``/ns/camera_info``."""
    base = image_topic.removesuffix("/compressed")
    ns = base.rsplit("/", 1)[0]
    return f"{ns}/camera_info"


class BagSource(FrameSource):
    """A ROS 1 or ROS 2 bag as a stream of frames (module docstring for the rules).

    Args:
        path: ``.bag`` (ROS 1), a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.
        left, right: image topics; None picks them (see the module docstring). ``left``
            alone imports a mono sequence from that topic.
        mono: import one camera even if the bag has two image topics (needs ``left`` then).
        tolerance_s: the largest stamp difference of a stereo pair [s].
        max_unpaired: the largest fraction of images without a partner `check` accepts.
        prefer_topics: topics a calibration file names (Kalibr ``rostopic``), used when
            ``left``/``right`` are not given and the bag holds them.
    """

    def __init__(
        self,
        path: Path,
        *,
        left: str | None = None,
        right: str | None = None,
        mono: bool = False,
        tolerance_s: float = DEFAULT_TOLERANCE_S,
        max_unpaired: float = DEFAULT_MAX_UNPAIRED,
        prefer_topics: tuple[str, ...] = (),
    ) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.tolerance_s = float(tolerance_s)
        self.max_unpaired = float(max_unpaired)
        self.is_ros1 = self.path.suffix == ".bag"
        store = get_typestore(Stores.ROS1_NOETIC if self.is_ros1 else Stores.ROS2_HUMBLE)
        try:
            self._reader: AnyReader | None = AnyReader([self.path], default_typestore=store)
            self._reader.open()
            topics = {name: str(info.msgtype) for name, info in self._reader.topics.items()}
            counts = {name: int(info.msgcount) for name, info in self._reader.topics.items()}
        except Exception as exc:  # rosbags raises many types for corrupt or truncated bags
            raise RecordingError(
                self.path, "contents", f"not a readable ROS bag ({_why(exc)})"
            ) from None
        try:
            self._setup(topics, counts, left, right, mono, prefer_topics)
        except BaseException:
            self.close()
            raise

    def _setup(
        self,
        topics: dict[str, str],
        counts: dict[str, int],
        left: str | None,
        right: str | None,
        mono: bool,
        prefer_topics: tuple[str, ...],
    ) -> None:
        images = sorted(t for t, typ in topics.items() if typ in IMAGE_TYPES)
        self.all_image_topics = images
        if not images:
            listed = ", ".join(f"{t} ({typ})" for t, typ in sorted(topics.items())) or "none"
            raise RecordingError(
                self.path,
                "topics",
                f"no sensor_msgs/Image or CompressedImage topic (topics: {listed})",
            )
        self.left_topic, self.right_topic, self.choice = self._pick(
            images, left, right, mono, prefer_topics
        )
        self.kind: Literal["stereo", "mono"] = "mono" if self.right_topic is None else "stereo"
        self.counts = counts
        self._topics = topics
        self.stats = {"left": TopicStats(self.left_topic)}
        if self.right_topic is not None:
            self.stats["right"] = TopicStats(self.right_topic)
        self._zero_stamps = 0

    def close(self) -> None:
        """Close the bag (the generator closes it too when exhausted)."""
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None and reader.stack is not None:
            reader.close()

    def _pick(
        self,
        images: list[str],
        left: str | None,
        right: str | None,
        mono: bool,
        prefer: tuple[str, ...],
    ) -> tuple[str, str | None, str]:
        listed = ", ".join(images)
        for name, topic in (("--left", left), ("--right", right)):
            if topic is not None and topic not in images:
                raise RecordingError(
                    self.path, f"{name} {topic}", f"no such image topic (image topics: {listed})"
                )
        if right is not None and left is None:
            raise RecordingError(self.path, "--right", "give --left too")
        if left is not None:
            if mono and right is not None:
                raise RecordingError(self.path, "--right", "a mono import takes only --left")
            return left, right, "as given"
        if prefer and all(t in images for t in prefer):
            if mono:
                return prefer[0], None, "named by the calibration file (rostopic)"
            if len(prefer) == 2:
                return prefer[0], prefer[1], "named by the calibration file (rostopic)"
        if len(images) == 1:
            if not mono and prefer and len(prefer) == 2:
                raise RecordingError(
                    self.path,
                    "topics",
                    f"the calibration is stereo but the bag has one image topic ({listed})",
                )
            return images[0], None, "the bag's only image topic"
        if len(images) == 2 and not mono:
            a, b = images
            # A name saying left/right decides; else the sorted order (cam0 before cam1).
            if "right" in a.lower() and "left" in b.lower():
                a, b = b, a
            return a, b, "the bag's two image topics"
        want = "--left TOPIC" if mono else "--left TOPIC --right TOPIC"
        raise RecordingError(
            self.path, "topics", f"{len(images)} image topics ({listed}): choose with {want}"
        )

    # ----------------------------------------------------------------------------------------

    def image_origin(self, camera: Literal["left", "right"]) -> str:
        topic = self.left_topic if camera == "left" else self.right_topic
        return f"{self.path}: {topic}"

    def _first_messages(self, topics: list[str]) -> dict[str, Any]:
        assert self._reader is not None
        conns = [c for c in self._reader.connections if c.topic in topics]
        found: dict[str, Any] = {}
        if not conns:
            return found
        try:
            for conn, _t, raw in self._reader.messages(connections=conns):
                if conn.topic not in found:
                    found[conn.topic] = self._reader.deserialize(raw, conn.msgtype)
                if len(found) == len(topics):
                    break
        except Exception as exc:  # corrupt or truncated bag
            raise RecordingError(
                self.path, "contents", f"not a readable ROS bag ({_why(exc)})"
            ) from None
        return found

    def calibration(self) -> SourceCalibration | None:
        """The camera infos of the chosen topics (None when the bag has none for them)."""
        names = [info_topic_for(self.left_topic)]
        if self.right_topic is not None:
            names.append(info_topic_for(self.right_topic))
        present = [n for n in names if self._topics.get(n) == INFO_TYPE]
        if len(present) != len(names):
            return None
        msgs = self._first_messages(present)
        if len(msgs) != len(names):
            return None
        cams = [self._camera(msgs[n], n) for n in names]
        if len(cams) == 1:
            return SourceCalibration(left=cams[0], path=self.path)
        left, right = (msgs[n] for n in names)
        rfl = stereo_from_camera_infos(
            _field(left, "r"),
            _field(left, "p"),
            _field(right, "r"),
            _field(right, "p"),
            self.path,
            names[1],
        )
        # Without a baseline (two monocular infos) the intrinsics stay and the import asks for
        # the extrinsic (--calib).
        return SourceCalibration(left=cams[0], right=cams[1], right_from_left=rfl, path=self.path)

    def _camera(self, msg: Any, topic: str) -> SourceCamera:
        return camera_info(
            width=int(msg.width),
            height=int(msg.height),
            distortion_model=str(msg.distortion_model),
            D=np.asarray(_field(msg, "d"), dtype=float).tolist(),
            K=np.asarray(_field(msg, "k"), dtype=float).tolist(),
            path=self.path,
            field=topic,
            binning=(int(msg.binning_x), int(msg.binning_y)),
            roi_size=(int(msg.roi.width), int(msg.roi.height)),
        )

    # ----------------------------------------------------------------------------------------

    def _messages(self) -> Iterator[tuple[str, int, Any]]:
        """``(camera, stamp_ns, message)`` of the chosen topics in bag order."""
        assert self._reader is not None
        reader = self._reader
        by_topic = {self.left_topic: "left"}
        if self.right_topic is not None:
            by_topic[self.right_topic] = "right"
        conns = [c for c in reader.connections if c.topic in by_topic]
        it = reader.messages(connections=conns)
        while True:
            try:
                item = next(it, None)
                if item is None:
                    return
                conn, t_bag, raw = item
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # corrupt or truncated bag
                raise RecordingError(
                    self.path, "contents", f"not a readable ROS bag ({_why(exc)})"
                ) from None
            cam = by_topic[conn.topic]
            stats = self.stats[cam]
            stats.messages += 1
            ns = _stamp_ns(msg)
            if ns == 0 and t_bag != 0:
                ns = int(t_bag)
                self._zero_stamps += 1
            if ns <= stats.last_ns:
                stats.out_of_order += 1
                continue
            stats.last_ns = ns
            yield cam, ns, msg

    def frames(self) -> Iterator[StereoFrame]:
        """``(t_s, left, right)`` in stamp order; ``right`` None for mono. Decodes only the
        images that pair. Closes the bag when exhausted."""
        try:
            if self.kind == "mono":
                for _cam, ns, msg in self._messages():
                    self.stats["left"].paired += 1
                    yield ns / 1_000_000_000, decode_image(msg, self.path, self.left_topic), None
                return
            for t_s, ml, mr in self.pairs():
                yield t_s, self.decode(ml, "left"), self.decode(mr, "right")
        finally:
            self.close()

    def pairs(self) -> Iterator[tuple[float, Any, Any]]:
        """``(t_s, left message, right message)`` of a stereo bag in stamp order, not decoded
        (`decode`): a live replay decodes only the frames it processes. Closes the bag when
        exhausted."""
        assert self.right_topic is not None
        stream = pair_by_stamp(
            self._messages(), round(self.tolerance_s * 1e9), self.stats["left"], self.stats["right"]
        )
        try:
            for ns, ml, mr in stream:
                yield ns / 1_000_000_000, ml, mr
        finally:
            self.close()

    def decode(self, msg: Any, camera: Literal["left", "right"]) -> np.ndarray:
        """An image message of ``camera``'s topic as an OpenCV array (`decode_image`)."""
        topic = self.left_topic if camera == "left" else self.right_topic
        assert topic is not None
        return decode_image(msg, self.path, topic)

    # ----------------------------------------------------------------------------------------

    def notes(self) -> list[str]:
        out = [
            f"topics: left {self.left_topic}"
            + (f", right {self.right_topic}" if self.right_topic else "")
            + f" ({self.choice})"
        ]
        if self.kind == "stereo":
            out.append(pairing_note(self.stats["left"], self.stats["right"], self.tolerance_s))
        for s in self.stats.values():
            if s.out_of_order:
                out.append(f"{s.topic}: {s.out_of_order} images dropped (stamp not increasing)")
        if self._zero_stamps:
            out.append(f"{self._zero_stamps} images had a zero header stamp: bag time used")
        return out

    def check(self) -> None:
        if self.kind == "mono":
            if self.stats["left"].paired == 0:
                raise RecordingError(self.path, self.left_topic, "has no images")
            return
        check_pairing(
            self.path, self.stats["left"], self.stats["right"], self.tolerance_s, self.max_unpaired
        )

    def provenance(self) -> dict[str, object]:
        out: dict[str, object] = {
            "bag": str(self.path),
            "format": "rosbag1" if self.is_ros1 else "rosbag2",
            "left_topic": self.left_topic,
        }
        if self.right_topic is not None:
            L, R = self.stats["left"], self.stats["right"]
            out.update(
                right_topic=self.right_topic,
                pair_tolerance_s=self.tolerance_s,
                unpaired_left=L.unpaired,
                unpaired_right=R.unpaired,
            )
        return out


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo array field: ROS 2 spells it lower case (``k``), ROS 1 upper (``K``)."""
    value = getattr(msg, name, None)
    return value if value is not None else getattr(msg, name.upper())


def _why(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
