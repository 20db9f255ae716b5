"""The backend's error type."""

from __future__ import annotations

from satpose.datasets.errors import SatposeError


class BackendError(SatposeError):
    """The backend was asked for something its inputs cannot give (bad config, no data yet)."""
