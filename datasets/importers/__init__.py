"""Importers: a lab's recordings (ROS 1/2 bags, EuRoC folders, videos, image folders) and
calibrations (Kalibr, OpenCV, ROS CameraInfo) into the sequence format v1.

`import_recording` is the one entry point the CLI (`satpose import`) calls; `BagSource` is the
bag reader, whose `BagSource.frames` streams ``(t_s, left, right)`` for a live consumer. The
design and every file key are in docs/import.md.
"""

from satpose.datasets.importers.bag import BagSource, decode_image
from satpose.datasets.importers.calib import read_calibration_file
from satpose.datasets.importers.common import (
    FrameSource,
    RecordingError,
    SourceCalibration,
    SourceCamera,
    read_timestamps,
)
from satpose.datasets.importers.euroc import EurocSource
from satpose.datasets.importers.files import FolderSource, VideoSource
from satpose.datasets.importers.recording import (
    ImportOptions,
    ImportReport,
    import_recording,
    open_source,
    source_kind,
)
from satpose.datasets.importers.truth import (
    TRUTH_FRAMES,
    HandEye,
    TruthAligner,
    TruthTrajectory,
    read_hand_eye,
)

__all__ = [
    "TRUTH_FRAMES",
    "BagSource",
    "EurocSource",
    "FolderSource",
    "FrameSource",
    "HandEye",
    "ImportOptions",
    "ImportReport",
    "RecordingError",
    "SourceCalibration",
    "SourceCamera",
    "TruthAligner",
    "TruthTrajectory",
    "VideoSource",
    "decode_image",
    "import_recording",
    "open_source",
    "read_calibration_file",
    "read_hand_eye",
    "read_timestamps",
    "source_kind",
]
