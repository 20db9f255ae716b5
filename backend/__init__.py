"""satpose.backend: factor-graph estimation of the target's trajectory (the only gtsam user).

`make_estimator` builds one of three estimators sharing one interface (`Estimator`:
``add(measurements)``, ``estimate()``):

- ``offline``: batch Levenberg-Marquardt over the whole sequence, marginal covariances;
- ``online``: iSAM2 updated once per frame; ``filtered()`` gives each frame's estimate right
  after its own update, ``estimate()`` the smoothed one;
- ``kalman``: the paper's constant-velocity Kalman filter on per-frame poses (baseline).

What leaves the package is numpy: an `Estimate` (docs/backend.md).
"""

from __future__ import annotations

from typing import Literal

from satpose.backend.config import BackendConfig
from satpose.backend.errors import BackendError
from satpose.backend.estimate import Estimate, Estimator, Hook, StepReport
from satpose.backend.factors import MeasurementConfig
from satpose.backend.kalman import KalmanEstimator
from satpose.backend.motion import MotionConfig
from satpose.backend.offline import OfflineConfig, OfflineEstimator
from satpose.backend.online import Isam2Config, OnlineEstimator
from satpose.datasets.sequence import Calibration

ESTIMATORS = ("offline", "online", "kalman")

__all__ = [
    "ESTIMATORS",
    "BackendConfig",
    "BackendError",
    "Estimate",
    "Estimator",
    "Hook",
    "Isam2Config",
    "KalmanEstimator",
    "MeasurementConfig",
    "MotionConfig",
    "OfflineConfig",
    "OfflineEstimator",
    "OnlineEstimator",
    "StepReport",
    "make_estimator",
]


def make_estimator(
    name: Literal["offline", "online", "kalman"],
    calibration: Calibration,
    config: BackendConfig | None = None,
    hook: Hook | None = None,
) -> OfflineEstimator | OnlineEstimator | KalmanEstimator:
    """The estimator called ``name``.

    Args:
        name: ``offline``, ``online`` or ``kalman``.
        calibration: the sequence's calibration (undistorted intrinsics and
            ``right_from_left``; used by tight coupling).
        config: backend settings (defaults if None).
        hook: optional callable receiving a `StepReport` after every step (diagnostics only).
    """
    cfg = BackendConfig() if config is None else config
    if name == "offline":
        return OfflineEstimator(
            calibration,
            motion=cfg.motion,
            measurements=cfg.measurements,
            config=cfg.offline,
            hook=hook,
        )
    if name == "online":
        return OnlineEstimator(
            calibration,
            motion=cfg.motion,
            measurements=cfg.measurements,
            config=cfg.online,
            hook=hook,
        )
    if name == "kalman":
        return KalmanEstimator(motion=cfg.motion, hook=hook)
    raise BackendError(f"unknown estimator {name!r}; choose from {list(ESTIMATORS)}")
