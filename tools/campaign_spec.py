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
- ``pipeline``: the cell kind, one per campaign (in ``base``; default ``stereo``):
  ``stereo`` (`run_pipeline` and `evaluate_run`; with ``estimator: frontend`` the stereo
  frontend alone, scored per frame), ``spin`` (the mono spin-rate frontend, `run_spin`) or
  ``bracket`` (the mono bracket method, `run_bracket`; ``scenario: bracket-random`` draws
  member ``seed`` of the bracket family) or ``bracket-mc`` (seed 002's Monte Carlo run on
  simulated image points, `satpose.tools.bracket_montecarlo`: no scene, no render; a
  ``seed`` and a ``config``);
- ``estimator``: ``online``, ``offline``, ``kalman`` or ``frontend`` (stereo); ``offline``,
  ``online``, ``kalman`` or ``none`` (bracket; default ``none``, the per-frame poses); not
  for spin;
- ``config``: dotted overrides of the pipeline's config: `PipelineConfig` (stereo),
  `SpinConfig` (spin), `StrutDetectorConfig` (bracket), `MonteCarloConfig` (bracket-mc).

``perturb`` and ``config`` take a mapping of named variants, or a list of variants (named by
their keys and values). Several independent override axes multiply: ``perturb.NAME`` and
``config.NAME`` (e.g. ``perturb.target`` and ``perturb.rate``), each its own column; their
overrides are merged in the order written. ``axes`` may also be a list of such mappings: the
union of their products (each with the same ``base``).

Everything is checked before any work starts: unknown keys (of the spec, of an axis, or a
dotted key that is not a field) are one-line errors naming the file and the key. The *values*
of ``config`` and ``perturb`` keys are converted in each cell, so a value one cell cannot use
fails that cell only (recorded as ``failed``).
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

PIPELINES = ("stereo", "spin", "bracket", "bracket-mc")
ESTIMATORS = {
    "stereo": ("online", "offline", "kalman", "frontend"),
    "spin": (),
    "bracket": ("none", "offline", "online", "kalman"),
    "bracket-mc": (),
}
"""The estimator axis's values per pipeline (the first is the default; spin has none)."""
AXES = (
    "pipeline",
    "scenario",
    "sequence",
    "seed",
    "frames",
    "size",
    "spp",
    "perturb",
    "estimator",
    "config",
)
"""Every axis name, in the order of the results table's columns (``perturb.NAME`` and
``config.NAME`` axes follow ``perturb`` and ``config``)."""
OVERRIDES = ("perturb", "config")
SYNTHETIC_ONLY = ("scenario", "seed", "frames", "size", "spp", "perturb")
BRACKET_FAMILY = "bracket-random"
"""The bracket family's scenario name (`satpose.datasets.bracket_family`, numpy ray caster)."""
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
    def pipeline(self) -> str:
        """The cell kind (`PIPELINES`)."""
        return str(self.axes.get("pipeline", "stereo"))

    @property
    def cell_id(self) -> str:
        """A content hash of everything that defines the cell (labels and what they stand
        for): the key under which a re-run finds it in the table."""
        # The stereo pipeline is left out: ids (and so resuming) are those of the tables
        # written before the pipeline axis existed.
        axes = {k: v for k, v in self.axes.items() if (k, v) != ("pipeline", "stereo")}
        text = json.dumps(
            {"axes": axes, "perturb": self.perturb, "config": self.config},
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


def is_axis(key: str) -> bool:
    """An axis name: one of `AXES`, or ``perturb.NAME`` / ``config.NAME``."""
    base, dot, name = str(key).partition(".")
    return key in AXES or (bool(dot) and bool(name) and base in OVERRIDES)


def axis_order(keys: list[str]) -> list[str]:
    """Axis names in the results table's column order (`AXES`, named override axes after
    their kind, in the order given)."""
    out = []
    for a in AXES:
        out += [k for k in keys if k == a or (a in OVERRIDES and k.startswith(f"{a}."))]
    return out


def _values(path: Path, axis: str, where: str, values: list[Any]) -> list[Any]:
    """Check the plain values of one axis; return them as the table stores them."""
    key = where
    from satpose.datasets.random_family import scenario_names

    out: list[Any] = []
    for v in values:
        if axis == "pipeline":
            if v not in PIPELINES:
                _fail(path, key, f"unknown pipeline {v!r}; choose from {list(PIPELINES)}")
            out.append(str(v))
        elif axis == "scenario":
            names = [*scenario_names(), BRACKET_FAMILY]
            if v not in names:
                _fail(path, key, f"unknown scenario {v!r}; choose from {names}")
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
            out.append(str(v))  # checked against the pipeline once it is known
    return out


def config_class(pipeline: str) -> type:
    """The config dataclass whose dotted keys a ``config`` axis overrides."""
    if pipeline == "spin":
        from satpose.frontend.spin import SpinConfig

        return SpinConfig
    if pipeline == "bracket":
        from satpose.frontend.bracket_lines import StrutDetectorConfig

        return StrutDetectorConfig
    if pipeline == "bracket-mc":
        from satpose.tools.bracket_montecarlo import MonteCarloConfig

        return MonteCarloConfig
    from satpose.tools.pipeline import PipelineConfig

    return PipelineConfig


def load_spec(path: str | Path) -> CampaignSpec:
    """Read and check a campaign spec; expand its axes into cells.

    Raises:
        ConfigError: one line naming the file and the key (malformed YAML, unknown key,
            unknown axis, preset, pipeline or estimator, missing sequence folder, bad value).
    """
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
    raw_axes = data.get("axes") or {}
    if not isinstance(base, dict):
        _fail(p, "base", "expected a mapping of axis -> value")
    # A list of axes mappings is the union of their products (each with the same base).
    products = raw_axes if isinstance(raw_axes, list) else [raw_axes]
    if not products:
        _fail(p, "axes", "lists no product")
    for key in base:
        if not is_axis(key):
            _fail(
                p,
                f"base.{key}",
                f"unknown axis; known axes: {list(AXES)} (and perturb.NAME, config.NAME)",
            )
    pipeline = _values(p, "pipeline", "base.pipeline", [base.get("pipeline", "stereo")])[0]
    cells = []
    for n, axes in enumerate(products):
        section = "axes" if not isinstance(raw_axes, list) else f"axes[{n}]"
        cells += _product(p, base, axes or {}, section, pipeline)
    ids = [c.cell_id for c in cells]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{p}: axes list the same value twice (cells would repeat)")
    return CampaignSpec(name=name, path=p, time_limit_s=float(limit), cells=cells)


def _product(p: Path, base: dict[str, Any], axes: Any, section: str, pipeline: str) -> list[Cell]:
    """The cells of one product: ``base`` with every combination of ``axes``."""
    from satpose.datasets.scenarios import Scenario

    if not isinstance(axes, dict):
        _fail(p, section, "expected a mapping of axis -> value")
    for key in axes:
        if not is_axis(key):
            _fail(
                p,
                f"{section}.{key}",
                f"unknown axis; known axes: {list(AXES)} (and perturb.NAME, config.NAME)",
            )
    both = sorted(set(base) & set(axes))
    if both:
        _fail(p, f"{section}.{both[0]}", "is given in both base and axes")
    if "pipeline" in axes:
        _fail(p, f"{section}.pipeline", "one pipeline per campaign: give it in base")

    # Every axis as a list of (label, payload) choices; payload = the label for plain axes.
    choices: dict[str, list[tuple[Any, Any]]] = {}
    for key in axis_order([*base, *axes]):
        kind = key.split(".")[0]
        if key in axes:
            raw, where = axes[key], f"{section}.{key}"
            if kind in OVERRIDES:
                if raw is None or raw == {} or raw == []:
                    _fail(p, where, "lists no value")
            elif not isinstance(raw, list) or not raw:
                _fail(p, where, "expected a non-empty list of values")
        else:
            raw, where = base[key], f"base.{key}"
            if kind in OVERRIDES:
                raw = [raw] if isinstance(raw, dict) else raw
            else:
                raw = [raw]
        if kind in OVERRIDES:
            cls = Scenario if kind == "perturb" else config_class(pipeline)
            choices[key] = list(_variants(p, where, raw, cls))
        else:
            choices[key] = [(v, v) for v in _values(p, key, where, raw)]
    if pipeline == "stereo":
        choices.pop("pipeline", None)  # the default: no column of its own in the cell id

    _check_pipeline(p, pipeline, choices)
    estimators = ESTIMATORS[pipeline]
    if estimators:
        for est, _ in choices.setdefault("estimator", [(estimators[0], estimators[0])]):
            if est not in estimators:
                where = f"{section}.estimator" if "estimator" in axes else "base.estimator"
                _fail(
                    p,
                    where,
                    f"unknown {pipeline} estimator {est!r}; choose from {list(estimators)}",
                )

    keys = list(choices)
    cells: list[Cell] = []
    for combo in itertools.product(*(choices[k] for k in keys)):
        picked = dict(zip(keys, combo, strict=True))
        merged = {
            kind: _merge([v for k, (_, v) in picked.items() if k.split(".")[0] == kind])
            for kind in OVERRIDES
        }
        cells.append(
            Cell(
                axes={"pipeline": pipeline} | {k: label for k, (label, _) in picked.items()},
                perturb=merged["perturb"],
                config=merged["config"],
                sequence=picked["sequence"][1] if "sequence" in picked else None,
            )
        )
    return cells


def _check_pipeline(p: Path, pipeline: str, choices: dict[str, list[tuple[Any, Any]]]) -> None:
    """The axes a pipeline cannot use (one line naming the key)."""
    if pipeline == "bracket-mc":
        scene = [k for k in choices if k.split(".")[0] in (*SYNTHETIC_ONLY, "sequence")]
        scene = [k for k in scene if k != "seed"]
        if scene:
            _fail(p, scene[0], "bracket-mc simulates image points: no scene (a seed, a config)")
        if not any(s is not None for s, _ in choices.get("seed", [])):
            _fail(p, "seed", "bracket-mc needs a seed (base.seed or axes.seed)")
        if "estimator" in choices:
            _fail(p, "estimator", "bracket-mc has no estimator axis (config: smooth)")
        return
    synthetic = [k for k in choices if k.split(".")[0] in SYNTHETIC_ONLY]
    scenarios = [v for v, _ in choices.get("scenario", [])]
    if "sequence" in choices:
        if synthetic:
            _fail(p, synthetic[0], "applies to synthetic scenarios only, not to a sequence")
    elif "scenario" not in choices:
        raise ConfigError(f"{p}: needs a scenario or a sequence (in base or axes)")
    seeds = [s for s, _ in choices.get("seed", [])]
    for family in ("random", BRACKET_FAMILY):
        if family in scenarios and not any(s is not None for s in seeds):
            _fail(p, "seed", f"scenario {family} needs a seed (base.seed or axes.seed)")
    if BRACKET_FAMILY in scenarios:
        if pipeline != "bracket":
            _fail(p, "scenario", f"{BRACKET_FAMILY} is a bracket scene: use pipeline: bracket")
        if len(scenarios) > 1:
            _fail(p, "scenario", f"{BRACKET_FAMILY} cannot share a campaign with presets")
        for key in ("spp", "perturb"):
            bad = [k for k in choices if k.split(".")[0] == key]
            if bad:
                _fail(
                    p,
                    bad[0],
                    f"does not apply to {BRACKET_FAMILY} (a numpy ray caster; "
                    "the scene is the seed's)",
                )
    if pipeline == "spin" and "estimator" in choices:
        _fail(p, "estimator", "the spin pipeline has no estimator axis (config: rate.*)")


def _merge(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Nested override mappings merged in order (later keys win)."""
    out: dict[str, Any] = {}
    for part in parts:
        for k, v in part.items():
            if isinstance(v, dict) and isinstance(out.get(k), dict):
                out[k] = _merge([out[k], v])
            else:
                out[k] = v
    return out


@dataclass(frozen=True, kw_only=True)
class BracketMember:
    """A member of the bracket family to render (`render_bracket_sequence`)."""

    name: str
    seed: int
    frames: int
    size: tuple[int, int]


def scenario_of(cell: Cell) -> Any:
    """What a synthetic cell renders: a `Scenario` (named scenario, perturbed, then scaled), or
    a `BracketMember` for ``bracket-random``.

    Raises:
        ConfigError: a ``perturb`` value the scenario refuses.
    """
    from satpose.datasets.config import replace_nested
    from satpose.datasets.random_family import named_scenario
    from satpose.datasets.scenarios import scaled

    a = cell.axes
    seed = a.get("seed")
    size = tuple(int(v) for v in a["size"].split("x")) if a.get("size") else None
    if a["scenario"] == BRACKET_FAMILY:
        from satpose.datasets.bracket_family import DEFAULT_FRAMES, DEFAULT_SIZE

        if seed is None:  # load_spec refuses this already
            raise ConfigError(f"{BRACKET_FAMILY} needs a seed")
        return BracketMember(
            name=f"{BRACKET_FAMILY}-{seed}",
            seed=int(seed),
            frames=int(a.get("frames") or DEFAULT_FRAMES),
            size=(size[0], size[1]) if size else DEFAULT_SIZE,
        )
    scenario = named_scenario(a["scenario"], seed)
    if cell.perturb:
        scenario = replace_nested(scenario, cell.perturb)
    return scaled(scenario, frames=a.get("frames"), size=size, spp=a.get("spp"), seed=seed)


def scenario_hash(scenario: Any) -> str:
    """Content hash of a scenario (its plain YAML form): the render cache key."""
    text = yaml.safe_dump(to_plain(scenario), sort_keys=True)
    return hashlib.sha1(text.encode()).hexdigest()[:12]
