"""Campaign specs: a YAML file naming the axes whose product is the set of cells.

A spec (docs/campaigns.md)::

    name: smoke
    time_limit_s: 240          # per cell: render, run and eval each stop at this budget
    base:                      # the value of every axis the cells do not vary
      scenario: paper-docking
      frames: 4
      size: 160x120
      spp: 2
    axes:                      # the product of these lists is the campaign
      seed: [0, 1]
      estimator: [online, offline, kalman]
      config:                  # named variants of dotted PipelineConfig keys
        default: {}
        no-compare: {compare: false}

The axes (each may stand in ``base`` or in ``axes``):

- ``scenario``: a preset name or ``random`` (the random family, member ``seed``);
- ``sequence``: a recorded sequence folder (relative to the spec file), instead of a scenario;
- ``seed``, ``frames``, ``size`` (``WxH``), ``spp``: passed to ``scaled`` (synthetic only);
- ``perturb``: dotted `Scenario` overrides (noise, calibration, light; synthetic only);
- ``estimator``: ``online``, ``offline`` or ``kalman``;
- ``config``: dotted `PipelineConfig` overrides.

``perturb`` and ``config`` take a mapping of named variants, or a list of variants (named by
their keys and values). Everything is checked before any work starts: unknown keys (of the
spec, of an axis, or a dotted key that is not a field) are one-line errors naming the file
and the key. The *values* of ``config`` and ``perturb`` keys are converted in each cell, so a
value one cell cannot use fails that cell only (recorded as ``failed``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from satpose.datasets.config import to_plain, yaml_problem
from satpose.datasets.errors import ConfigError

ESTIMATORS = ("online", "offline", "kalman")
AXES = ("scenario", "sequence", "seed", "frames", "size", "spp", "perturb", "estimator", "config")
"""Every axis name, in the order of the results table's columns."""
SYNTHETIC_ONLY = ("scenario", "seed", "frames", "size", "spp", "perturb")
SPEC_KEYS = ("name", "time_limit_s", "base", "axes")
DEFAULT_TIME_LIMIT_S = 1800.0


@dataclass(frozen=True, kw_only=True)
class Cell:
    """One task of a campaign: the axis values (labels for ``perturb``/``config``) and the
    resolved overrides behind the labels.

    Attributes:
        axes: axis name -> value as written to the results table (str, int or None).
        perturb: nested `Scenario` overrides (synthetic cells).
        config: nested `PipelineConfig` overrides.
        sequence: absolute path of a recorded sequence, or None for a synthetic cell.
    """

    axes: dict[str, Any]
    perturb: dict[str, Any]
    config: dict[str, Any]
    sequence: str | None

    @property
    def cell_id(self) -> str:
        """A content hash of everything that defines the cell (labels and what they stand
        for): the key under which a re-run finds it in the table."""
        text = json.dumps(
            {"axes": self.axes, "perturb": self.perturb, "config": self.config},
            sort_keys=True,
            default=str,
        )
        return hashlib.sha1(text.encode()).hexdigest()[:12]


@dataclass(frozen=True, kw_only=True)
class CampaignSpec:
    """A parsed and checked spec (see the module docstring)."""

    name: str
    path: Path
    time_limit_s: float
    cells: list[Cell]


def _fail(path: Path, key: str, msg: str) -> typing.NoReturn:
    raise ConfigError(f"{path}: {key}: {msg}")


def unflatten(dotted: dict[str, Any]) -> dict[str, Any]:
    """``{"backend.isam2.x": 1}`` -> ``{"backend": {"isam2": {"x": 1}}}`` (nested mappings
    are merged, so both spellings may be mixed)."""
    out: dict[str, Any] = {}
    for key, value in dotted.items():
        parts = str(key).split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{key}: {p} is both a value and a mapping")
        if isinstance(value, dict) and isinstance(node.get(parts[-1]), dict):
            node[parts[-1]] = {**node[parts[-1]], **unflatten(value)}
        else:
            node[parts[-1]] = unflatten(value) if isinstance(value, dict) else value
    return out


def check_keys(cls: type, nested: dict[str, Any], where: str) -> None:
    """Refuse any key of ``nested`` that is not a field of the (nested) dataclass ``cls``;
    values are not checked here. Raises ConfigError naming the dotted key."""
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    for key, value in nested.items():
        if key not in fields:
            raise ConfigError(f"{where}{key}: unknown key; known keys: {sorted(fields)}")
        sub = _dataclass_in(hints[key])
        if sub is not None and isinstance(value, dict):
            check_keys(sub, value, f"{where}{key}.")


def _dataclass_in(tp: Any) -> type | None:
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return tp
    for arg in typing.get_args(tp):  # Optional[SomeConfig]
        if dataclasses.is_dataclass(arg) and isinstance(arg, type):
            return arg
    return None


def _label(variant: dict[str, Any]) -> str:
    if not variant:
        return "default"
    return ",".join(f"{k}={json.dumps(v, separators=(',', ':'))}" for k, v in variant.items())


def _variants(path: Path, key: str, value: Any, cls: type) -> list[tuple[str, dict[str, Any]]]:
    """Named override variants of ``perturb`` or ``config``: (label, nested overrides)."""
    if isinstance(value, dict) and all(isinstance(v, dict) or v is None for v in value.values()):
        named = [(str(k), v or {}) for k, v in value.items()]
    elif isinstance(value, list) and all(isinstance(v, dict) for v in value):
        named = [(_label(v), v) for v in value]
    else:
        _fail(path, key, "expected a mapping of named variants or a list of mappings")
    out = []
    for name, v in named:
        try:
            nested = unflatten(v)
            check_keys(cls, nested, "")
        except ConfigError as exc:
            _fail(path, f"{key}.{name}", str(exc))
        out.append((name, nested))
    return out


def _size(path: Path, key: str, v: Any) -> str:
    try:
        w, h = (int(x) for x in (v if isinstance(v, list) else str(v).lower().split("x")))
    except (TypeError, ValueError):
        _fail(path, key, f"expected WIDTHxHEIGHT such as 160x120, got {v!r}")
    if w < 16 or h < 16:
        _fail(path, key, f"image size {w}x{h} is too small")
    return f"{w}x{h}"


def _values(path: Path, axis: str, where: str, values: list[Any]) -> list[Any]:
    """Check the plain values of one axis; return them as the table stores them."""
    key = where
    from satpose.datasets.random_family import scenario_names

    out: list[Any] = []
    for v in values:
        if axis == "scenario":
            if v not in scenario_names():
                _fail(path, key, f"unknown scenario {v!r}; choose from {scenario_names()}")
            out.append(str(v))
        elif axis == "sequence":
            from satpose.datasets.sequence import load_sequence

            folder = Path(str(v)).expanduser()
            folder = folder if folder.is_absolute() else (path.parent / folder)
            if not folder.is_dir():
                _fail(path, key, f"sequence folder {folder} does not exist")
            try:
                seq = load_sequence(folder)
            except ValueError as exc:
                _fail(path, key, str(exc).splitlines()[0])
            if seq.truth is None:
                _fail(path, key, f"{folder} has no groundtruth.csv: nothing to evaluate against")
            out.append(str(folder.resolve()))
        elif axis == "seed":
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                _fail(path, key, f"expected an integer or null, got {v!r}")
            out.append(v)
        elif axis in ("frames", "spp"):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                _fail(path, key, f"expected a positive integer, got {v!r}")
            out.append(v)
        elif axis == "size":
            out.append(_size(path, key, v))
        elif axis == "estimator":
            if v not in ESTIMATORS:
                _fail(path, key, f"unknown estimator {v!r}; choose from {list(ESTIMATORS)}")
            out.append(str(v))
    return out


def load_spec(path: str | Path) -> CampaignSpec:
    """Read and check a campaign spec; expand its axes into cells.

    Raises:
        ConfigError: one line naming the file and the key (malformed YAML, unknown key,
            unknown axis, preset or estimator, missing sequence folder, bad value).
    """
    from satpose.datasets.scenarios import Scenario
    from satpose.tools.pipeline import PipelineConfig

    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read campaign spec ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: a campaign spec is a mapping (name, time_limit_s, base, axes)")
    for key in data:
        if key not in SPEC_KEYS:
            _fail(p, str(key), f"unknown key; known keys: {list(SPEC_KEYS)}")
    name = data.get("name", p.stem)
    if not isinstance(name, str) or not name:
        _fail(p, "name", f"expected a non-empty string, got {name!r}")
    limit = data.get("time_limit_s", DEFAULT_TIME_LIMIT_S)
    if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not limit > 0:
        _fail(p, "time_limit_s", f"expected a positive number of seconds, got {limit!r}")
    base = data.get("base") or {}
    axes = data.get("axes") or {}
    for section, mapping in (("base", base), ("axes", axes)):
        if not isinstance(mapping, dict):
            _fail(p, section, "expected a mapping of axis -> value")
        for key in mapping:
            if key not in AXES:
                _fail(p, f"{section}.{key}", f"unknown axis; known axes: {list(AXES)}")
    both = sorted(set(base) & set(axes))
    if both:
        _fail(p, f"axes.{both[0]}", "is given in both base and axes")

    # Every axis as a list of (label, payload) choices; payload = the label for plain axes.
    choices: dict[str, list[tuple[Any, Any]]] = {}
    for key in AXES:
        if key in axes:
            raw, where = axes[key], f"axes.{key}"
            if key in ("perturb", "config"):
                if raw is None or raw == {} or raw == []:
                    _fail(p, where, "lists no value")
            elif not isinstance(raw, list) or not raw:
                _fail(p, where, "expected a non-empty list of values")
        elif key in base:
            raw, where = base[key], f"base.{key}"
            if key in ("perturb", "config"):
                raw = [raw] if isinstance(raw, dict) else raw
            else:
                raw = [raw]
        else:
            continue
        if key in ("perturb", "config"):
            cls = Scenario if key == "perturb" else PipelineConfig
            choices[key] = list(_variants(p, where, raw, cls))
        else:
            choices[key] = [(v, v) for v in _values(p, key, where, raw)]

    synthetic = [k for k in SYNTHETIC_ONLY if k in choices]
    if "sequence" in choices:
        if synthetic:
            _fail(p, synthetic[0], "applies to synthetic scenarios only, not to a sequence")
    elif "scenario" not in choices:
        raise ConfigError(f"{p}: needs a scenario or a sequence (in base or axes)")
    if "random" in [v for v, _ in choices.get("scenario", [])] and not any(
        s is not None for s, _ in choices.get("seed", [])
    ):
        _fail(p, "seed", "scenario random needs a seed (base.seed or axes.seed)")
    choices.setdefault("estimator", [("online", "online")])

    keys = list(choices)
    cells = []
    for combo in itertools.product(*(choices[k] for k in keys)):
        picked = dict(zip(keys, combo, strict=True))
        cells.append(
            Cell(
                axes={k: label for k, (label, _) in picked.items()},
                perturb=picked["perturb"][1] if "perturb" in picked else {},
                config=picked["config"][1] if "config" in picked else {},
                sequence=picked["sequence"][1] if "sequence" in picked else None,
            )
        )
    ids = [c.cell_id for c in cells]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{p}: axes list the same value twice (cells would repeat)")
    return CampaignSpec(name=name, path=p, time_limit_s=float(limit), cells=cells)


def scenario_of(cell: Cell) -> Any:
    """The synthetic `Scenario` of a cell (named scenario, perturbed, then scaled).

    Raises:
        ConfigError: a ``perturb`` value the scenario refuses.
    """
    from satpose.datasets.config import replace_nested
    from satpose.datasets.random_family import named_scenario
    from satpose.datasets.scenarios import scaled

    a = cell.axes
    seed = a.get("seed")
    scenario = named_scenario(a["scenario"], seed)
    if cell.perturb:
        scenario = replace_nested(scenario, cell.perturb)
    size = tuple(int(v) for v in a["size"].split("x")) if a.get("size") else None
    return scaled(scenario, frames=a.get("frames"), size=size, spp=a.get("spp"), seed=seed)


def scenario_hash(scenario: Any) -> str:
    """Content hash of a scenario (its plain YAML form): the render cache key."""
    text = yaml.safe_dump(to_plain(scenario), sort_keys=True)
    return hashlib.sha1(text.encode()).hexdigest()[:12]
