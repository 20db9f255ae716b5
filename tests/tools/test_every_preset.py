"""Every preset, rendered tiny (320x256, 4 spp), through the command a user runs on it: never
a traceback. Either the command succeeds (exit 0, its main output written) or it ends with one
clear line (exit 2) and leaves no output folder.

At this size many frames give no measurement (a ring of a few pixels, a bracket whose yoke is
not resolved): that must be a recorded, counted frame failure, never an exception; a sequence
where no frame gives a pose at all (the 7 m ring of paper-docking spans a few pixels here) ends
with the reason. Accuracy is not checked here (tests/tools/test_accuracy_smoke.py does that at
sizes that resolve it).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from satpose.datasets.star_scenarios import PRESETS as STAR_PRESETS
from satpose.tools.cli import main

# preset -> (frames, the command's name and extra arguments, a file the command must write)
COMMANDS: dict[str, tuple[int, list[str], str]] = {
    "paper-docking": (3, ["run"], "trajectory.csv"),
    "tumble": (3, ["run", "--estimator", "offline"], "trajectory.csv"),
    "close-approach": (3, ["run", "--estimator", "kalman"], "trajectory.csv"),
    "turntable": (3, ["frontend"], "measurements.parquet"),
    "spin-far": (20, ["spin"], "spin.csv"),  # one 19-frame window
    "bracket-final": (3, ["bracket"], "errors.csv"),
    "rings-check": (3, ["rings"], "rings.csv"),
    "calibration": (20, ["check-calib"], "calib.yaml"),
}


def test_the_table_covers_every_preset() -> None:
    from satpose.datasets.scenarios import PRESETS

    assert set(COMMANDS) == set(PRESETS)


@pytest.mark.render
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_preset_runs_without_a_traceback(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames, (command, *extra), output = COMMANDS[name]
    seq = tmp_path / "seq"
    tiny = ["--frames", str(frames), "--size", "320x256", "--spp", "4"]
    assert main(["render", name, "--out", str(seq), *tiny]) == 0
    out = tmp_path / "out"
    status = main([command, str(seq), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if status == 0:
        assert (out / output).is_file()
    else:
        assert status == 2
        assert err.strip().splitlines()[-1].startswith(f"satpose {command}: error: "), err
        assert not out.exists()


@pytest.mark.parametrize("name", sorted(STAR_PRESETS))
def test_star_preset_runs_without_a_traceback(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = tmp_path / "seq"
    assert main(["stars", "render", name, "--out", str(seq), "--duration", "0.2"]) == 0
    out = tmp_path / "out"
    status = main(["stars", "track", str(seq), "--out", str(out)])
    err = capsys.readouterr().err
    assert status == 0, err
    assert "Traceback" not in err
    assert (out / "attitude.tum").is_file()
