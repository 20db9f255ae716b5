"""EuRoC / ASL folders: ``mav0/cam0`` (left) and ``mav0/cam1`` (right, if present).

Each camera folder holds ``data.csv`` (``#timestamp [ns],filename``), ``data/<filename>``
and ``sensor.yaml`` with the Kalibr-style intrinsics (``camera_model``, ``intrinsics: [fu,
fv, pu, pv]``, ``distortion_model: radial-tangential | equidistant``,
``distortion_coefficients``, ``resolution``, ``rate_hz``) and ``T_BS`` (``{rows, cols,
data}``: ``body_from_sensor``). The stereo extrinsic is
``right_from_left = inv(T_BS(cam1)) @ T_BS(cam0)``. cam0 and cam1 rows pair by timestamp
like a bag's topics (`pair_by_stamp`). SOURCE may be the dataset folder or its ``mav0``.
The MAV's own ground truth (``state_groundtruth_estimate0``, ``leica0``) is the body in the
world, not the target in the camera: it is not imported (give ``--truth``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import yaml

from satpose.datasets.config import yaml_problem
from satpose.datasets.importers.calib import kalibr_camera, matrix4, rigid_from_matrix
from satpose.datasets.importers.common import (
    DEFAULT_MAX_UNPAIRED,
    DEFAULT_TOLERANCE_S,
    FrameSource,
    RecordingError,
    SourceCalibration,
    StereoFrame,
    TopicStats,
    check_pairing,
    pair_by_stamp,
    pairing_note,
    read_image_file,
)


def euroc_root(path: Path) -> Path | None:
    """The ``mav0`` folder of an EuRoC dataset at ``path`` (or ``path`` itself), or None."""
    for cand in (path / "mav0", path):
        if (cand / "cam0" / "data.csv").is_file():
            return cand
    return None


def _read_rows(csv_path: Path) -> list[tuple[int, str]]:
    """data.csv rows ``(timestamp_ns, filename)``; the header line starts with ``#``."""
    try:
        lines = csv_path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(csv_path, None, f"cannot read ({exc})") from None
    rows: list[tuple[int, str]] = []
    for k, line in enumerate(lines):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) < 2 or not cells[0].isdigit() or not cells[1]:
            raise RecordingError(
                csv_path, f"line {k + 1}", f"expected 'timestamp_ns,filename', got {line!r}"
            )
        rows.append((int(cells[0]), cells[1]))
    if not rows:
        raise RecordingError(csv_path, None, "lists no images")
    return rows


class EurocSource(FrameSource):
    """An EuRoC/ASL folder (module docstring). ``mono`` imports cam0 only."""

    def __init__(
        self,
        path: Path,
        *,
        mono: bool = False,
        tolerance_s: float = DEFAULT_TOLERANCE_S,
        max_unpaired: float = DEFAULT_MAX_UNPAIRED,
    ) -> None:
        root = euroc_root(Path(path))
        if root is None:
            raise RecordingError(path, "mav0/cam0/data.csv", "not an EuRoC folder")
        self.path = Path(path)
        self.root = root
        cams = ["cam0"] if mono or not (root / "cam1" / "data.csv").is_file() else ["cam0", "cam1"]
        self.cams = cams
        self.kind: Literal["stereo", "mono"] = "stereo" if len(cams) == 2 else "mono"
        self.rows = {c: _read_rows(root / c / "data.csv") for c in cams}
        self.tolerance_s = float(tolerance_s)
        self.max_unpaired = float(max_unpaired)
        names = ("left", "right")
        self.stats = {n: TopicStats(str(root / c)) for n, c in zip(names, cams, strict=False)}
        self._sensor: dict[str, dict[str, Any]] = {}

    def _sensor_yaml(self, cam: str) -> dict[str, Any]:
        if cam not in self._sensor:
            p = self.root / cam / "sensor.yaml"
            if not p.is_file():
                raise RecordingError(p, None, "missing (the camera's calibration)")
            try:
                data = yaml.safe_load(p.read_text(encoding="utf-8"))
            except yaml.YAMLError as exc:
                raise RecordingError(p, None, f"not valid YAML: {yaml_problem(exc)}") from None
            if not isinstance(data, dict):
                raise RecordingError(p, None, "must hold a YAML mapping")
            self._sensor[cam] = data
        return self._sensor[cam]

    def calibration(self) -> SourceCalibration:
        cams = [
            kalibr_camera(
                self._sensor_yaml(c), self.root / c / "sensor.yaml", "", "distortion_coefficients"
            )
            for c in self.cams
        ]
        if len(cams) == 1:
            return SourceCalibration(left=cams[0], path=self.root / "cam0" / "sensor.yaml")
        body_from = []
        for c in self.cams:
            p = self.root / c / "sensor.yaml"
            raw = self._sensor_yaml(c).get("T_BS")
            if raw is None:
                raise RecordingError(p, "T_BS", "required for a stereo pair")
            body_from.append(rigid_from_matrix(matrix4(raw, p, "T_BS"), p, "T_BS"))
        rfl = body_from[1].inverse() @ body_from[0]
        return SourceCalibration(
            left=cams[0],
            right=cams[1],
            right_from_left=rfl,
            path=self.root / "cam1" / "sensor.yaml",
        )

    def rate_hz(self) -> float | None:
        rate = self._sensor_yaml("cam0").get("rate_hz")
        return float(rate) if isinstance(rate, (int, float)) and rate > 0 else None

    def image_origin(self, camera: Literal["left", "right"]) -> str:
        return str(self.root / self.cams[0 if camera == "left" else 1] / "data")

    def _items(self) -> Iterator[tuple[str, int, Path]]:
        names = ("left", "right")
        merged = sorted(
            (ns, k, name, self.root / cam / "data" / fname)
            for k, (name, cam) in enumerate(zip(names, self.cams, strict=False))
            for ns, fname in self.rows[cam]
        )
        for ns, _k, name, p in merged:
            stats = self.stats[name]
            stats.messages += 1
            if ns <= stats.last_ns:
                stats.out_of_order += 1
                continue
            stats.last_ns = ns
            yield name, ns, p

    def frames(self) -> Iterator[StereoFrame]:
        if self.kind == "mono":
            for _name, ns, p in self._items():
                self.stats["left"].paired += 1
                yield ns / 1_000_000_000, read_image_file(p), None
            return
        tol = round(self.tolerance_s * 1e9)
        for ns, pl, pr in pair_by_stamp(
            self._items(), tol, self.stats["left"], self.stats["right"]
        ):
            yield ns / 1_000_000_000, read_image_file(pl), read_image_file(pr)

    def notes(self) -> list[str]:
        out = [f"EuRoC cameras: {', '.join(self.cams)} in {self.root}"]
        if self.kind == "stereo":
            out.append(pairing_note(self.stats["left"], self.stats["right"], self.tolerance_s))
        for s in self.stats.values():
            if s.out_of_order:
                out.append(f"{s.topic}: {s.out_of_order} rows dropped (time not increasing)")
        return out

    def check(self) -> None:
        if self.kind == "stereo":
            check_pairing(
                self.root / "cam1" / "data.csv",
                self.stats["left"],
                self.stats["right"],
                self.tolerance_s,
                self.max_unpaired,
            )

    def provenance(self) -> dict[str, object]:
        return {"euroc": str(self.root), "cameras": list(self.cams)}
