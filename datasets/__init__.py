"""satpose.datasets: sequences on disk, cameras, geometry, configs and the test-scene renderer.

The renderer (`satpose.datasets.render`) imports Mitsuba; nothing here imports it at package
import time.
"""

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError, SatposeError, SequenceError
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import (
    FORMAT_VERSION,
    Calibration,
    Frame,
    GroundTruth,
    Sequence,
    SequenceWriter,
    TargetGeometry,
    load_sequence,
    write_sequence,
)

__all__ = [
    "FORMAT_VERSION",
    "Calibration",
    "ConfigError",
    "Frame",
    "GroundTruth",
    "PinholeCamera",
    "Rigid3",
    "SatposeError",
    "Sequence",
    "SequenceError",
    "SequenceWriter",
    "TargetGeometry",
    "load_sequence",
    "write_sequence",
]
