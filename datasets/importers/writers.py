"""The other direction: a satpose sequence as a ROS 1/ROS 2 bag or an EuRoC folder.

Written with the formats' own tools (rosbags' ``Writer`` and typestore serialisers; EuRoC's
plain files), so that the importers can be checked on recordings made the way a lab makes
them, and a lab can feed a rendered sequence into its own ROS tools. `BagWriter` writes any
image / camera-info message (tests use it for malformed bags); `write_bag` and `write_euroc`
write a whole sequence. Outputs are built under a temporary name and renamed into place.

Camera infos of a stereo pair carry the rectification of ``cv2.stereoRectify`` (R1/R2,
P1/P2), as ROS's camera_calibration writes them, so `stereo_from_camera_infos` recovers the
extrinsic; a mono camera's info has R = I and P = [K | 0].
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import cv2
import numpy as np
import yaml

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Sequence, replace_dir

ENCODING_OF = {
    (np.dtype(np.uint8), 1): "mono8",
    (np.dtype(np.uint16), 1): "mono16",
    (np.dtype(np.uint8), 3): "bgr8",
    (np.dtype(np.uint16), 3): "bgr16",
}


@contextmanager
def _staged_path(path: Path) -> Iterator[Path]:
    """A path named like ``path`` inside a hidden staging folder beside it; renamed onto
    ``path`` on success (the bag writers name their files after the folder), removed on
    failure."""
    stage = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    stage.mkdir(parents=True)
    try:
        yield stage / path.name
        os.replace(stage / path.name, path)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


class BagWriter:
    """Write sensor_msgs images and camera infos into a new ROS 1 (``.bag``) or ROS 2 bag.

    Use as a context manager; the bag appears at ``path`` only when the block ends cleanly.

    Args:
        path: ``*.bag`` for ROS 1, a folder name for ROS 2.
        ros: 1 or 2.
        storage: ROS 2's storage plugin, ``sqlite3`` (``.db3``) or ``mcap``.
    """

    def __init__(
        self, path: Path, ros: Literal[1, 2], storage: Literal["sqlite3", "mcap"] = "sqlite3"
    ) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.ros = ros
        self.storage = storage
        self.typestore = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        self._stage_cm = _staged_path(self.path)
        self._writer: Any = None
        self._conns: dict[tuple[str, str], Any] = {}

    def __enter__(self) -> BagWriter:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        target = self._stage_cm.__enter__()
        if self.ros == 1:
            self._writer = Writer1(target)
        else:
            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            self._writer = Writer2(target, version=9, storage_plugin=plugin)
        self._writer.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            self._writer.close()
        finally:
            self._stage_cm.__exit__(exc_type, exc, tb)

    def _types(self, name: str) -> Any:
        return self.typestore.types[name]

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        Time = self._types("builtin_interfaces/msg/Time")
        Header = self._types("std_msgs/msg/Header")
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        if self.ros == 1:
            return Header(seq=0, stamp=stamp, frame_id=frame_id)
        return Header(stamp=stamp, frame_id=frame_id)

    def write(self, topic: str, receive_ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a typestore message) onto ``topic`` at bag time ``receive_ns``."""
        key = (topic, msg.__msgtype__)
        if key not in self._conns:
            self._conns[key] = self._writer.add_connection(
                topic, msg.__msgtype__, typestore=self.typestore
            )
        ser = self.typestore.serialize_ros1 if self.ros == 1 else self.typestore.serialize_cdr
        self._writer.write(self._conns[key], receive_ns, ser(msg, msg.__msgtype__))

    def image_msg(
        self,
        stamp_ns: int,
        img: np.ndarray,
        *,
        frame_id: str = "camera",
        encoding: str | None = None,
        data: np.ndarray | None = None,
    ) -> Any:
        """A ``sensor_msgs/Image`` of ``img`` (encoding from its dtype and channels unless
        given; ``data`` replaces the pixel bytes, for malformed messages)."""
        a = np.ascontiguousarray(img)
        channels = 1 if a.ndim == 2 else a.shape[2]
        enc = encoding or ENCODING_OF[(a.dtype, channels)]
        Image = self._types("sensor_msgs/msg/Image")
        return Image(
            header=self._header(stamp_ns, frame_id),
            height=a.shape[0],
            width=a.shape[1],
            encoding=enc,
            is_bigendian=0,
            step=a.shape[1] * channels * a.dtype.itemsize,
            data=a.reshape(-1).view(np.uint8) if data is None else data,
        )

    def compressed_msg(self, stamp_ns: int, img: np.ndarray, fmt: str = "png") -> Any:
        """A ``sensor_msgs/CompressedImage`` of ``img`` encoded as ``fmt`` (png, jpeg)."""
        ok, buf = cv2.imencode(f".{fmt}", img)
        assert ok
        Msg = self._types("sensor_msgs/msg/CompressedImage")
        return Msg(header=self._header(stamp_ns, "camera"), format=fmt, data=buf.reshape(-1))

    def camera_info_msg(
        self,
        stamp_ns: int,
        cam: PinholeCamera,
        R: np.ndarray | None = None,
        P: np.ndarray | None = None,
        *,
        frame_id: str = "camera",
        distortion_model: str = "plumb_bob",
        D: np.ndarray | None = None,
    ) -> Any:
        """A ``sensor_msgs/CameraInfo`` of ``cam`` (R = I and P = [K | 0] unless given)."""
        Info = self._types("sensor_msgs/msg/CameraInfo")
        Roi = self._types("sensor_msgs/msg/RegionOfInterest")
        R = np.eye(3) if R is None else np.asarray(R, float)
        P = np.c_[cam.K, np.zeros(3)] if P is None else np.asarray(P, float)
        arrays = {
            "d": np.asarray(cam.dist if D is None else D, float).copy(),
            "k": cam.K.reshape(-1).copy(),
            "r": R.reshape(-1).copy(),
            "p": P.reshape(-1).copy(),
        }
        if self.ros == 1:
            arrays = {k.upper(): v for k, v in arrays.items()}
        return Info(
            header=self._header(stamp_ns, frame_id),
            height=cam.height,
            width=cam.width,
            distortion_model=distortion_model,
            binning_x=0,
            binning_y=0,
            roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            **arrays,
        )


def rectification(
    left: PinholeCamera, right: PinholeCamera, right_from_left: Rigid3
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``R1, R2, P1, P2`` of ``cv2.stereoRectify`` for the pair (what ROS's stereo
    camera_calibration puts in the two camera infos)."""
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        left.K.copy(),
        left.dist.copy(),
        right.K.copy(),
        right.dist.copy(),
        left.size,
        right_from_left.R.copy(),
        right_from_left.t.reshape(3, 1).copy(),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0,
    )
    return R1, R2, P1, P2


def write_bag(
    sequence: Sequence,
    path: Path,
    *,
    ros: Literal[1, 2],
    topics: tuple[str, str] = ("/cam0/image_raw", "/cam1/image_raw"),
    camera_info: bool = True,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> Path:
    """Write ``sequence`` as a bag: per frame one Image per camera stamped ``round(t_s * 1e9)``
    ns (and, with ``camera_info``, one CameraInfo per camera on ``<ns>/camera_info``)."""
    calib = sequence.calibration
    stereo = sequence.kind == "stereo"
    infos: list[tuple[np.ndarray, np.ndarray] | tuple[None, None]] = [(None, None), (None, None)]
    if stereo and calib.right is not None and calib.right_from_left is not None:
        R1, R2, P1, P2 = rectification(calib.left, calib.right, calib.right_from_left)
        infos = [(R1, P1), (R2, P2)]
    with BagWriter(path, ros, storage) as bag:
        for fr in sequence:
            ns = round(fr.t_s * 1e9)
            cams: list[Literal["left", "right"]] = ["left", "right"] if stereo else ["left"]
            for k, cam in enumerate(cams):
                frame_id = f"cam{k}"
                bag.write(topics[k], ns, bag.image_msg(ns, fr.image(cam), frame_id=frame_id))
                if camera_info:
                    info_topic = topics[k].rsplit("/", 1)[0] + "/camera_info"
                    R, P = infos[k]
                    msg = bag.camera_info_msg(ns, calib.camera(cam), R, P, frame_id=frame_id)
                    bag.write(info_topic, ns, msg)
    return path


def write_euroc(sequence: Sequence, path: Path, rate_hz: float | None = None) -> Path:
    """Write ``sequence`` as an EuRoC/ASL folder ``path/mav0/cam0`` (and ``cam1``): data.csv
    with ns stamps, data/<ns>.png, sensor.yaml with T_BS (the body is the left camera)."""
    path = Path(path)
    stage = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        calib = sequence.calibration
        cams: list[Literal["left", "right"]] = (
            ["left", "right"] if sequence.kind == "stereo" else ["left"]
        )
        for k, cam in enumerate(cams):
            folder = stage / "mav0" / f"cam{k}"
            (folder / "data").mkdir(parents=True)
            rows = ["#timestamp [ns],filename"]
            for fr in sequence:
                ns = round(fr.t_s * 1e9)
                cv2.imwrite(str(folder / "data" / f"{ns}.png"), fr.image(cam))
                rows.append(f"{ns},{ns}.png")
            (folder / "data.csv").write_text("\n".join(rows) + "\n")
            c = calib.camera(cam)
            body_from_cam = Rigid3() if cam == "left" else calib.right_from_left.inverse()
            sensor = {
                "sensor_type": "camera",
                "comment": f"satpose sequence {sequence.name}, {cam} camera",
                "T_BS": {"cols": 4, "rows": 4, "data": body_from_cam.matrix().reshape(-1).tolist()},
                "rate_hz": float(rate_hz or sequence.rate_hz),
                "resolution": [c.width, c.height],
                "camera_model": "pinhole",
                "intrinsics": [c.fx, c.fy, c.cx, c.cy],
                "distortion_model": "radial-tangential",
                "distortion_coefficients": [float(v) for v in c.dist],
            }
            (folder / "sensor.yaml").write_text(yaml.safe_dump(sensor, sort_keys=False))
        replace_dir(stage, path, overwrite=False)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return path
