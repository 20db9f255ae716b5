"""Star-tracker scenarios and the event sequence folder (docs/event_sequence_format.md).

A scenario is one sensor (event pixels and conventional frames sharing optics) slewing over
the Hipparcos sky. `render_star_sequence` writes a mono satpose sequence (the conventional
frames, groundtruth.csv holding ``inertial_from_camera`` with zero translation) plus
``events.h5`` and ``attitude_truth.csv`` (truth at 1 kHz) beside it.

``event_model="dvs"`` (presets ``dvs-*``) selects the second, deliberately different event
model instead (`satpose.datasets.dvs_events`: DVS pixel reset, defocused optics, hot
pixels, timestamp jitter, a Gaia DR3 sky): an event-only recording (sequence.yaml,
calib.yaml, events.h5, attitude_truth.csv; no frames).
"""

from __future__ import annotations

import math
import os
import shutil
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from satpose.datasets.config import to_plain
from satpose.datasets.dvs_events import DvsSensor, simulate_dvs_events
from satpose.datasets.errors import ConfigError, SequenceError
from satpose.datasets.event_io import write_events_h5
from satpose.datasets.events import (
    EventSensor,
    FrameSensor,
    Photometry,
    render_frame,
    simulate_events,
)
from satpose.datasets.geometry import Rigid3, matrix_to_quat_xyzw
from satpose.datasets.sequence import (
    FORMAT_VERSION,
    Calibration,
    SequenceWriter,
    calibration_to_yaml,
    replace_dir,
)
from satpose.datasets.sky import (
    SlewTrajectory,
    load_gaia,
    load_hipparcos,
    random_rotation,
    star_camera,
)

TRUTH_RATE_HZ = 1000.0
EVENTS_FILE = "events.h5"
ATTITUDE_TRUTH_FILE = "attitude_truth.csv"


@dataclass(frozen=True, kw_only=True)
class StarScenario:
    """One simulated star-tracker run.

    Attributes:
        name: preset name.
        width, height: sensor size [px]; hfov_deg: horizontal field of view.
        duration_s: length of the run.
        slew_rate_deg_s: magnitude of the constant body rate; slew_axis: its direction in the
            camera frame (normalised).
        jitter_arcsec: jitter amplitude per axis at each of ``jitter_freq_hz``.
        epoch_yr: observation epoch (catalogue propagated to it).
        seed: seeds the start attitude, jitter phases, thresholds and noise.
        event_model: ``esim`` (`satpose.datasets.events`, Hipparcos sky, with frames;
            ``photometry``, ``events``, ``frames``) or ``dvs`` (`satpose.datasets.dvs_events`,
            Gaia DR3 sky in a red-weighted band, event-only; ``dvs``).
    """

    name: str
    width: int = 640
    height: int = 480
    hfov_deg: float = 20.0
    duration_s: float = 3.0
    slew_rate_deg_s: float = 1.0
    slew_axis: tuple[float, float, float] = (0.2, 1.0, 0.1)
    jitter_arcsec: float = 10.0
    jitter_freq_hz: tuple[float, ...] = (3.0, 17.0)
    epoch_yr: float = 2026.9
    seed: int = 4
    photometry: Photometry = field(default_factory=Photometry)
    events: EventSensor = field(default_factory=EventSensor)
    frames: FrameSensor = field(default_factory=FrameSensor)
    event_model: Literal["esim", "dvs"] = "esim"
    dvs: DvsSensor = field(default_factory=DvsSensor)

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16 or not (0 < self.hfov_deg < 120):
            raise ConfigError(f"{self.name}: bad sensor size or field of view")
        if not (self.duration_s > 0 and self.slew_rate_deg_s >= 0 and self.jitter_arcsec >= 0):
            raise ConfigError(f"{self.name}: duration must be > 0, rates >= 0")
        if np.linalg.norm(self.slew_axis) == 0:
            raise ConfigError(f"{self.name}: slew_axis must be non-zero")
        if self.event_model not in ("esim", "dvs"):
            raise ConfigError(f"{self.name}: event_model must be esim or dvs")

    def trajectory(self) -> SlewTrajectory:
        rng = np.random.default_rng(self.seed)
        axis = np.asarray(self.slew_axis, float) / np.linalg.norm(self.slew_axis)
        k = len(self.jitter_freq_hz)
        return SlewTrajectory(
            start=random_rotation(rng),
            rate_rad_s=math.radians(self.slew_rate_deg_s) * axis,
            jitter_amp_rad=np.full((k, 3), math.radians(self.jitter_arcsec / 3600)),
            jitter_freq_hz=np.asarray(self.jitter_freq_hz, float),
            jitter_phase_rad=rng.uniform(0, 2 * np.pi, (k, 3)),
        )

    def camera_calibration(self) -> Calibration:
        return Calibration(left=star_camera(self.width, self.height, self.hfov_deg))


PRESETS: dict[str, StarScenario] = {
    "slew": StarScenario(name="slew"),
    "stare": StarScenario(name="stare", slew_rate_deg_s=0.1, duration_s=2.0),
    "fast-slew": StarScenario(name="fast-slew", slew_rate_deg_s=5.0, duration_s=2.0),
}
_DVS = StarScenario(
    name="dvs",
    event_model="dvs",
    width=640,
    height=480,
    hfov_deg=14.0,
    slew_axis=(0.3, 1.0, -0.15),
    jitter_arcsec=15.0,
    jitter_freq_hz=(8.0,),
    seed=18,
)
PRESETS.update(
    {
        "dvs-slew": replace(_DVS, name="dvs-slew", slew_rate_deg_s=1.0, duration_s=2.0),
        "dvs-fast-slew": replace(_DVS, name="dvs-fast-slew", slew_rate_deg_s=6.0, duration_s=1.5),
        "dvs-stare": replace(
            _DVS,
            name="dvs-stare",
            slew_rate_deg_s=0.05,
            duration_s=2.0,
            jitter_arcsec=30.0,
            jitter_freq_hz=(3.0,),
        ),
    }
)


def star_preset(name: str) -> StarScenario:
    if name not in PRESETS:
        raise ConfigError(f"unknown star preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]


def scenario_dict(s: StarScenario) -> dict[str, Any]:
    return dict(to_plain(s))


def render_star_sequence(
    scenario: StarScenario, out: str | Path, *, overwrite: bool = False
) -> Path:
    """Simulate ``scenario`` and write the event sequence folder ``out`` atomically."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise SequenceError(out, None, "output folder already exists")
    out.parent.mkdir(parents=True, exist_ok=True)
    work = out.parent / f".{out.name}.work-{uuid.uuid4().hex[:8]}"
    work.mkdir()
    try:
        seq = work / out.name
        traj = scenario.trajectory()
        if scenario.event_model == "dvs":
            _render_dvs(scenario, traj, seq)
            _write_attitude_truth(scenario, traj, seq)
            done = work.parent / f".{out.name}.new-{uuid.uuid4().hex[:8]}"
            os.replace(seq, done)
            replace_dir(done, out, overwrite)
            return out
        cam = star_camera(scenario.width, scenario.height, scenario.hfov_deg)
        cat = load_hipparcos(scenario.epoch_yr, scenario.photometry.mag_limit)
        rng = np.random.default_rng(scenario.seed + 1)
        fs = scenario.frames
        n_frames = max(1, math.floor(scenario.duration_s * fs.rate_hz))
        with SequenceWriter(
            seq,
            name=scenario.name,
            kind="mono",
            rate_hz=fs.rate_hz,
            calibration=scenario.camera_calibration(),
            generator={
                "tool": "satpose stars render",
                "truth": "groundtruth.csv holds inertial_from_camera (ICRS), zero translation, "
                "at mid-exposure",
                "events": EVENTS_FILE,
                "scenario": scenario_dict(scenario),
            },
        ) as w:
            for k in range(n_frames):
                t0 = k / fs.rate_hz
                img = render_frame(cat, traj.attitude, cam, scenario.photometry, fs, t0, rng)
                t_mid = t0 + fs.exposure_s / 2
                w.add_frame(
                    k,
                    t_mid,
                    img,
                    truth=Rigid3(R=traj.attitude(t_mid), t=np.zeros(3)),
                    angular_velocity=traj.body_rate(np.array([t_mid]))[0],
                )
        ev = simulate_events(
            cat,
            traj.attitude,
            cam,
            scenario.photometry,
            scenario.events,
            0.0,
            scenario.duration_s,
            rng,
        )
        write_events_h5(ev, seq / EVENTS_FILE)
        _write_attitude_truth(scenario, traj, seq)
        done = work.parent / f".{out.name}.new-{uuid.uuid4().hex[:8]}"
        os.replace(seq, done)
        replace_dir(done, out, overwrite)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out


def _write_attitude_truth(scenario: StarScenario, traj: SlewTrajectory, seq: Path) -> None:
    ts = np.arange(0.0, scenario.duration_s + 1e-9, 1.0 / TRUTH_RATE_HZ)
    q = matrix_to_quat_xyzw(traj.attitude(ts))
    wv = traj.body_rate(ts)
    pd.DataFrame(
        {
            "t_s": ts,
            "qx": q[:, 0],
            "qy": q[:, 1],
            "qz": q[:, 2],
            "qw": q[:, 3],
            "wx": wv[:, 0],
            "wy": wv[:, 1],
            "wz": wv[:, 2],
        }
    ).to_csv(seq / ATTITUDE_TRUTH_FILE, index=False, float_format="%.12g")


def _render_dvs(scenario: StarScenario, traj: SlewTrajectory, seq: Path) -> None:
    """The event-only recording of the second event model (no frames, no groundtruth.csv)."""
    import yaml

    seq.mkdir(parents=True)
    cam = star_camera(scenario.width, scenario.height, scenario.hfov_deg)
    cat = load_gaia(scenario.dvs.mag_limit)
    rng = np.random.default_rng(scenario.seed + 1)
    ev = simulate_dvs_events(cat, traj.attitude, cam, scenario.dvs, 0.0, scenario.duration_s, rng)
    meta = {
        "format": FORMAT_VERSION,
        "name": scenario.name,
        "kind": "mono",
        "rate_hz": 1.0 / scenario.duration_s,
        "generator": {
            "tool": "satpose stars render",
            "truth": "attitude_truth.csv holds inertial_from_camera (ICRS) at 1 kHz",
            "events": EVENTS_FILE,
            "event_model": "dvs (satpose.datasets.dvs_events)",
            "scenario": scenario_dict(scenario),
        },
    }
    for name, data in (
        ("sequence.yaml", meta),
        ("calib.yaml", calibration_to_yaml(scenario.camera_calibration())),
    ):
        (seq / name).write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    write_events_h5(ev, seq / EVENTS_FILE)


def with_overrides(s: StarScenario, **kw: Any) -> StarScenario:
    """``dataclasses.replace`` for top-level scenario fields."""
    return replace(s, **kw)


@dataclass(frozen=True)
class AttitudeTruth:
    """High-rate attitude truth: ``inertial_from_camera`` and body rate at times ``t_s``."""

    t_s: np.ndarray
    R: np.ndarray
    rate_rad_s: np.ndarray

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """``inertial_from_camera`` at ``t_s`` (N,) by SLERP, shape (N, 3, 3)."""
        from scipy.spatial.transform import Rotation, Slerp

        t = np.clip(np.asarray(t_s, float), self.t_s[0], self.t_s[-1])
        return Slerp(self.t_s, Rotation.from_matrix(self.R))(t).as_matrix()


def load_attitude_truth(path: str | Path) -> AttitudeTruth:
    """Read attitude_truth.csv (``t_s,qx,qy,qz,qw,wx,wy,wz``)."""
    from satpose.datasets.geometry import quat_xyzw_to_matrix

    path = Path(path)
    cols = ["t_s", "qx", "qy", "qz", "qw", "wx", "wy", "wz"]
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise SequenceError(path, None, f"cannot read ({exc})") from None
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise SequenceError(path, ",".join(missing), "missing column(s)")
    if df.empty or not np.isfinite(df[cols].to_numpy()).all():
        raise SequenceError(path, "t_s", "empty or non-finite values")
    q = df[["qx", "qy", "qz", "qw"]].to_numpy()
    return AttitudeTruth(
        t_s=df["t_s"].to_numpy(),
        R=quat_xyzw_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True)),
        rate_rad_s=df[["wx", "wy", "wz"]].to_numpy(),
    )
