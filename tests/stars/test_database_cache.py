"""Saved tetra3rs databases (`solver_database`, `database_cache_dir`): built once, then
loaded; an unreadable file is rebuilt with a warning naming it; an empty
``SATPOSE_CACHE_DIR`` saves nothing."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from satpose.frontend.stars import (
    CACHE_ENV,
    database_cache_dir,
    solver_catalogue,
    solver_database,
)

BAND = (30.0, 75.0, 2025.0)  # a wide field: the smallest database (about a second)


@pytest.fixture(autouse=True)
def fresh_process_cache() -> Iterator[None]:
    solver_catalogue.cache_clear()
    solver_database.cache_clear()
    yield
    solver_catalogue.cache_clear()
    solver_database.cache_clear()


def saved(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.t3db"))


def test_built_once_then_loaded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    db = solver_database(*BAND)
    files = saved(tmp_path)
    assert len(files) == 1 and files[0].parent == database_cache_dir()
    assert list(files[0].parent.iterdir()) == files  # the temporary file renamed, none left
    os.utime(files[0], (1e9, 1e9))
    solver_database.cache_clear()
    again = solver_database(*BAND)
    assert files[0].stat().st_mtime == 1e9  # loaded, not rebuilt and saved again
    assert again.num_patterns == db.num_patterns and again.num_stars == db.num_stars  # type: ignore[attr-defined]


def test_unreadable_file_is_rebuilt_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    solver_database(*BAND)
    (path,) = saved(tmp_path)
    path.write_bytes(b"not a database")
    solver_database.cache_clear()
    with caplog.at_level(logging.WARNING, logger="satpose.frontend.stars"):
        db = solver_database(*BAND)
    assert db.num_patterns > 0  # type: ignore[attr-defined]
    assert any(
        str(path) in r.getMessage() and "rebuilding" in r.getMessage() for r in caplog.records
    )
    assert path.stat().st_size > 1000  # replaced by the rebuilt database


def test_empty_setting_saves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert database_cache_dir() is None
    solver_database(*BAND)
    assert saved(tmp_path) == []
