"""Recordings without their own clock: a video file per camera, or an image folder.

Times come from a timestamps file (`read_timestamps`: one time per row, seconds or EuRoC-style
nanoseconds) or from a stated rate (frame k at ``k / rate_hz``). Stereo is two videos or two
folders (a folder holding ``left/`` and ``right/`` — or ``cam0/`` and ``cam1/`` — also counts),
frame k of one paired with frame k of the other; both must have as many frames as there are
times. A video is read with OpenCV's ``VideoCapture`` (FFmpeg) to the end, so a video shorter
(or longer) than its timestamp list is found whatever its header claims.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from satpose.datasets.importers.common import (
    FrameSource,
    RecordingError,
    StereoFrame,
    check_image,
    image_files,
    nominal_rate_hz,
    read_image_file,
    read_timestamps,
)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv")


def _times(
    count: int | None, timestamps: Path | None, rate_hz: float | None, what: Path, hint: str = ""
) -> np.ndarray | None:
    """The frame times: from ``timestamps``, or ``k / rate_hz`` for ``count`` frames (None
    while the count is not known yet: a video's frames are counted as they are read)."""
    if timestamps is not None and rate_hz is not None:
        raise RecordingError(what, "--timestamps/--rate", "give one of them, not both")
    if timestamps is not None:
        return read_timestamps(Path(timestamps))
    if rate_hz is None:
        raise RecordingError(
            what, "--timestamps/--rate", f"a video or image folder needs frame times{hint}"
        )
    if not rate_hz > 0:
        raise RecordingError(what, "--rate", f"must be positive, got {rate_hz}")
    return None if count is None else np.arange(count) / float(rate_hz)


class VideoSource(FrameSource):
    """One video (mono) or two (stereo: ``right`` the right camera's video).

    Args:
        left, right: video files.
        timestamps: a timestamps file with one time per frame (shared by both videos).
        rate_hz: or a stated frame rate [Hz].
    """

    def __init__(
        self,
        left: Path,
        right: Path | None = None,
        *,
        timestamps: Path | None = None,
        rate_hz: float | None = None,
    ) -> None:
        self.path = Path(left)
        self.paths = [Path(left)] + ([Path(right)] if right is not None else [])
        self.kind: Literal["stereo", "mono"] = "stereo" if right is not None else "mono"
        self.timestamps_path = Path(timestamps) if timestamps is not None else None
        self.stated_rate = rate_hz
        caps = [self._open(p) for p in self.paths]
        fps = caps[0].get(cv2.CAP_PROP_FPS)
        for cap in caps:
            cap.release()
        hint = (
            f" (the container says {fps:g} frames/s: --rate {fps:g} if that is true)"
            if fps > 0
            else ""
        )
        self.times = _times(None, self.timestamps_path, rate_hz, self.path, hint)
        self.count = 0
        self.grey: dict[Path, bool] = {}

    def _open(self, path: Path) -> cv2.VideoCapture:
        if not path.is_file():
            raise RecordingError(path, None, "video file does not exist")
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise RecordingError(path, None, "OpenCV (FFmpeg) cannot open this video")
        return cap

    def image_origin(self, camera: Literal["left", "right"]) -> str:
        return str(self.paths[0 if camera == "left" else 1])

    def _frame(self, cap: cv2.VideoCapture, path: Path) -> np.ndarray | None:
        ok, img = cap.read()
        if not ok or img is None:
            return None
        # Decoders hand out BGR even for a grey video: a first frame with three equal
        # channels makes the whole video grey (exact for such frames).
        if path not in self.grey:
            self.grey[path] = img.ndim == 3 and bool(
                np.array_equal(img[..., 0], img[..., 1])
                and np.array_equal(img[..., 1], img[..., 2])
            )
        if self.grey[path] and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return check_image(img, path, "frames")

    def frames(self) -> Iterator[StereoFrame]:
        caps = [self._open(p) for p in self.paths]
        try:
            k = 0
            while True:
                imgs = [self._frame(cap, p) for cap, p in zip(caps, self.paths, strict=True)]
                ended = [img is None for img in imgs]
                if all(ended):
                    break
                if any(ended):
                    short = self.paths[ended.index(True)]
                    raise RecordingError(
                        short, "frame count", f"ends after {k} frames, the other video goes on"
                    )
                if self.times is not None and k >= self.times.size:
                    assert self.timestamps_path is not None
                    raise RecordingError(
                        self.path,
                        "frame count",
                        f"has more frames than the {self.times.size} times of "
                        f"{self.timestamps_path}",
                    )
                if self.times is None:
                    assert self.stated_rate is not None
                    t = k / self.stated_rate
                else:
                    t = float(self.times[k])
                yield t, imgs[0], imgs[1] if self.kind == "stereo" else None
                k += 1
            self.count = k
            if self.times is not None and k < self.times.size:
                assert self.timestamps_path is not None
                raise RecordingError(
                    self.path,
                    "frame count",
                    f"has {k} frames but {self.timestamps_path} lists {self.times.size} times",
                )
            if k == 0:
                raise RecordingError(self.path, "frame count", "has no frames")
        finally:
            for cap in caps:
                cap.release()

    def notes(self) -> list[str]:
        out = [f"video: {self.count} frames from {', '.join(map(str, self.paths))}"]
        for path, grey in self.grey.items():
            if grey:
                out.append(f"{path}: grey frames (three equal channels), written as grey")
        return out

    def rate_hz(self) -> float | None:
        return self.stated_rate

    def provenance(self) -> dict[str, object]:
        out: dict[str, object] = {"video": [str(p) for p in self.paths]}
        if self.timestamps_path is not None:
            out["timestamps"] = str(self.timestamps_path)
        else:
            out["rate_hz"] = self.stated_rate
        return out


def stereo_folders(folder: Path) -> tuple[Path, Path] | None:
    """``(left, right)`` subfolders of ``folder`` (``left/right`` or ``cam0/cam1``), or None."""
    for a, b in (("left", "right"), ("cam0", "cam1")):
        if (folder / a).is_dir() and (folder / b).is_dir():
            return folder / a, folder / b
    return None


class FolderSource(FrameSource):
    """Image files in natural name order: one folder (mono) or two (stereo).

    Args:
        left, right: folders of images (``right`` None: ``left`` may hold ``left/`` and
            ``right/`` or ``cam0/`` and ``cam1/``; else it is mono).
        timestamps, rate_hz: the frame times (module docstring).
    """

    def __init__(
        self,
        left: Path,
        right: Path | None = None,
        *,
        timestamps: Path | None = None,
        rate_hz: float | None = None,
        mono: bool = False,
    ) -> None:
        self.path = Path(left)
        if right is None and not mono and (pair := stereo_folders(self.path)) is not None:
            left, right = pair
        self.folders = [Path(left)] + ([Path(right)] if right is not None else [])
        self.kind: Literal["stereo", "mono"] = "stereo" if right is not None else "mono"
        self.files = [image_files(f) for f in self.folders]
        for folder, files in zip(self.folders, self.files, strict=True):
            if not files:
                raise RecordingError(folder, None, "holds no image files")
        if len(self.files) == 2 and len(self.files[0]) != len(self.files[1]):
            raise RecordingError(
                self.folders[1],
                "image count",
                f"{len(self.files[1])} images but {self.folders[0]} has {len(self.files[0])}",
            )
        n = len(self.files[0])
        self.timestamps_path = Path(timestamps) if timestamps is not None else None
        times = _times(n, self.timestamps_path, rate_hz, self.path)
        assert times is not None
        if times.size != n:
            raise RecordingError(
                self.timestamps_path or self.path,
                "row count",
                f"lists {times.size} times for the {n} images of {self.folders[0]}",
            )
        self.times = times
        self.stated_rate = rate_hz

    def image_origin(self, camera: Literal["left", "right"]) -> str:
        return str(self.folders[0 if camera == "left" else 1])

    def frames(self) -> Iterator[StereoFrame]:
        for k, t in enumerate(self.times):
            left = read_image_file(self.files[0][k])
            right = read_image_file(self.files[1][k]) if self.kind == "stereo" else None
            yield float(t), left, right

    def notes(self) -> list[str]:
        return [f"image folder: {len(self.times)} frames from {', '.join(map(str, self.folders))}"]

    def rate_hz(self) -> float | None:
        return self.stated_rate if self.stated_rate else nominal_rate_hz(self.times)

    def provenance(self) -> dict[str, object]:
        out: dict[str, object] = {"folders": [str(f) for f in self.folders]}
        if self.timestamps_path is not None:
            out["timestamps"] = str(self.timestamps_path)
        else:
            out["rate_hz"] = self.stated_rate
        return out
