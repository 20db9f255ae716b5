"""Helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

from pathlib import Path

from satpose.datasets.render import render_sequence
from satpose.datasets.scenarios import preset


def ensure_rendered(name: str, root: Path) -> Path:
    """The preset ``name`` rendered at full size under ``root`` (rendered now if missing)."""
    out = root / name
    if not (out / "frames.csv").is_file():
        print(f"rendering {name} into {out} (a few minutes)", flush=True)
        render_sequence(preset(name), out, overwrite=True)
    return out


def write_page(path: Path, text: str) -> None:
    """Write a results page whole or not at all (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    print(f"wrote {path}")
