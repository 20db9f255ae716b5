"""Error types. ``SatposeError`` is the root of every error satpose raises on bad input.

The CLIs catch ``SatposeError`` and print its message on one line with a non-zero exit status;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class SatposeError(ValueError):
    """Root of all satpose input errors (a ``ValueError`` subclass)."""


class SequenceError(SatposeError):
    """A sequence folder does not follow the satpose sequence format.

    The message always names the file and, where there is one, the field::

        SequenceError("/data/seq/calib.yaml", "cameras.left.K", "expected 9 numbers, got 6")
        -> "/data/seq/calib.yaml: cameras.left.K: expected 9 numbers, got 6"
    """

    def __init__(self, path: str | Path, field: str | None, problem: str) -> None:
        self.path = Path(path)
        self.field = field
        self.problem = problem
        where = f"{self.path}: {field}" if field else f"{self.path}"
        super().__init__(f"{where}: {problem}")


class ConfigError(SatposeError):
    """A configuration file or mapping has an unknown key or an invalid value."""


def shown(value: Any) -> str:
    """A value as an error message shows it: Python's ``repr`` (strings quoted), with numpy
    scalars and arrays turned into plain numbers and lists first (``20.0``, not
    ``np.float64(20.0)``), also inside lists, tuples and dicts."""
    return repr(_plain(value))


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    return value
