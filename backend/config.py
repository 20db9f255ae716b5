"""`BackendConfig`: the backend's settings, one nested dataclass per module."""

from __future__ import annotations

from dataclasses import dataclass, field

from satpose.backend.factors import MeasurementConfig
from satpose.backend.motion import MotionConfig
from satpose.backend.offline import OfflineConfig
from satpose.backend.online import Isam2Config


@dataclass(frozen=True, kw_only=True)
class BackendConfig:
    """Everything the three estimators can be told (YAML/TOML via
    `satpose.datasets.config.load_config`).

    Attributes:
        motion: the constant-twist motion prior (all estimators, the Kalman filter included).
        measurements: coupling, robust kernel, tight-coupling details (graph estimators).
        offline: batch Levenberg-Marquardt.
        online: iSAM2.
    """

    motion: MotionConfig = field(default_factory=MotionConfig)
    measurements: MeasurementConfig = field(default_factory=MeasurementConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)
    online: Isam2Config = field(default_factory=Isam2Config)
