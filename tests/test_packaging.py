"""The wheel installs exactly one top-level package, `satpose`, with the `satpose` script."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_contains_only_the_satpose_namespace(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
        check=True,
    )
    (wheel,) = tmp_path.glob("satpose-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"satpose", next(t for t in top if t.endswith(".dist-info"))}
    for pkg in ("datasets", "frontend", "backend", "tools"):
        assert f"satpose/{pkg}/__init__.py" in names
    assert "satpose/__init__.py" not in names  # a namespace package: nothing shadows others
    assert "satpose/datasets/sequence.py" in names and "satpose/tools/cli.py" in names
    assert "satpose/datasets/importers/bag.py" in names  # the one subpackage
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "satpose = satpose.tools.cli:main" in text
