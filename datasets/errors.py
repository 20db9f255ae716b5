"""Error types. ``SatposeError`` is the root of every error satpose raises on bad input.

The CLIs catch ``SatposeError`` and print its message on one line with a non-zero exit status;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


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
