"""The satpose CLI: one-line errors with exit status 2, nothing half-written."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from satpose.tools.cli import main


def test_unknown_preset_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["render", "no-such-preset", "--out", "x"])
    assert info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("size", ["320", "axb", "8x8"])
def test_bad_size_is_a_usage_error(size: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["render", "tumble", "--out", "x", "--size", size])
    assert "--size" in capsys.readouterr().err


def test_existing_output_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "out").mkdir()
    assert main(["render", "tumble", "--out", str(tmp_path / "out"), "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "already exists" in err and "out" in err


def test_config_with_unknown_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target:\n  ring:\n    diameter_m: 0.8\n")
    assert main(["render", "tumble", "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "c.yaml" in err and "diameter_m" in err and "unknown key" in err
    assert not (tmp_path / "o").exists()


def test_missing_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(
            [
                "render",
                "tumble",
                "--out",
                str(tmp_path / "o"),
                "--config",
                str(tmp_path / "nope.yaml"),
            ]
        )
        == 2
    )
    assert "nope.yaml: cannot read" in capsys.readouterr().err


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        assert (
            main(
                [
                    "render",
                    "tumble",
                    "--out",
                    str(ro / "seq"),
                    "--frames",
                    "1",
                    "--size",
                    "32x24",
                    "--spp",
                    "1",
                ]
            )
            == 2
        )
        assert "cannot create the output folder" in capsys.readouterr().err
    finally:
        ro.chmod(0o700)


def test_output_under_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert (
        main(
            [
                "render",
                "tumble",
                "--out",
                str(blocker / "seq"),
                "--frames",
                "1",
                "--size",
                "32x24",
                "--spp",
                "1",
            ]
        )
        == 2
    )
    assert "cannot create the output folder" in capsys.readouterr().err


def test_config_with_a_yaml_error_names_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target:\n  ring:\n    outer_radius_m: [0.4\n")
    assert main(["render", "tumble", "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "c.yaml: not valid YAML: line " in err and "column" in err
    assert not (tmp_path / "o").exists()


def test_run_with_a_truncated_calibration_names_the_line(
    synthetic_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    calib = synthetic_sequence / "calib.yaml"
    calib.write_text(calib.read_text()[:120])
    assert main(["run", str(synthetic_sequence), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "calib.yaml: not valid YAML: line " in err, err
    assert not (tmp_path / "o").exists()
