"""The ``satpose`` command line.

Each subcommand parses its arguments, builds a config, calls one library function and maps
satpose's own errors (`SatposeError`) to a one-line message and exit status 2. Anything else is
a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from satpose.datasets.errors import ConfigError, SatposeError
from satpose.tools import colmap_cli, spin_cli
from satpose.tools.argtypes import positive_int

if TYPE_CHECKING:
    from satpose.datasets.scenarios import Scenario

log = logging.getLogger("satpose")

DEMO_OUT = Path("runs/demo")
DEMO_FRAMES = 40  # 7 m to 5 m
DEMO_SPP = 8


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 320x256, got {text!r}"
        ) from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"image size {w}x{h} is too small")
    return w, h


def _render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=positive_int, help="render only the first N frames")
    p.add_argument("--size", type=_size, metavar="WxH", help="image size (same field of view)")
    p.add_argument("--spp", type=positive_int, help="samples per pixel")
    p.add_argument(
        "--seed", type=int, help="seed of textures and noise (random: also of the scene)"
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="YAML/TOML with scenario overrides, shaped like sequence.yaml's "
        "generator.scenario (e.g. target: {ring: {outer_radius_m: 0.4}})",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def build_parser() -> argparse.ArgumentParser:
    from satpose.datasets.random_family import scenario_names

    parser = argparse.ArgumentParser(
        prog="satpose",
        description="Relative pose and motion of a non-cooperative satellite from cameras.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "render",
        help="render a preset scenario into a sequence folder",
        description="Render a preset scenario with Mitsuba 3 into a sequence "
        "folder (format satpose-sequence/1) with ground truth.",
    )
    p.add_argument(
        "preset",
        choices=[*scenario_names(), "bracket-random"],
        metavar="PRESET",
        help=f"one of: {', '.join(scenario_names())}, bracket-random (random: a different "
        "satellite and scene per --seed, docs/renderer.md 'Random family'; bracket-random: a "
        "different bracket in the paper's view per --seed, docs/bracket.md)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output sequence folder")
    _render_args(p)

    p = sub.add_parser(
        "frontend",
        help="measure a stereo sequence (seed 000's frontend)",
        description="Run the stereo frontend (docking ring, panel landmarks, ORB) on every "
        "frame; write measurements.parquet and the per-frame pose as frontend_pose.tum.",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="sequence folder")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="YAML/TOML frontend config (unknown keys are refused)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing frontend output folder (once the new one is complete)",
    )

    p = sub.add_parser(
        "run",
        help="frontend + backend over a sequence: trajectory, measurements, recording",
        description="Measure every frame with the stereo frontend, estimate the trajectory "
        "with the chosen estimator and write the run folder (trajectory.csv/.tum, "
        "measurements.parquet, timings.csv, config.yaml, run.rrd; docs/pipeline.md).",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="sequence folder")
    p.add_argument(
        "--estimator",
        choices=["online", "offline", "kalman"],
        default="online",
        help="online (iSAM2, default), offline (batch smoother) or kalman (baseline)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="run folder")
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="YAML/TOML pipeline config (frontend:, backend:, recording:, compare:)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing run folder (once the new run is complete)",
    )
    p.add_argument("--spawn", action="store_true", help="also stream to a Rerun viewer")

    p = sub.add_parser(
        "eval",
        help="metrics of a run or a trajectory file against the sequence's ground truth",
        description="Compare a run's trajectories, or a TUM/CSV trajectory file another tool "
        "wrote, with groundtruth.csv: errors in seed 000's terms (per range band), ATE/RPE as "
        "evo defines them, NEES (where covariances exist), the ESA SPEC score. Prints a table, "
        "writes metrics.json, metrics.csv and groundtruth.tum into the run folder (a file: into "
        "--out, default <file stem>_eval/ beside it). A file's poses are left_cam_from_target "
        "(--inverse: target_from_left_cam) and are matched to frames by time (docs/pipeline.md).",
    )
    p.add_argument("sequence", type=Path, metavar="SEQUENCE", help="sequence folder")
    p.add_argument(
        "trajectory",
        type=Path,
        metavar="TRAJECTORY",
        help="run folder (satpose run --out), or a TUM or CSV trajectory file",
    )
    p.add_argument(
        "--format",
        choices=["tum", "csv"],
        help="trajectory file format (default: .csv is CSV, .tum/.txt TUM, else by content)",
    )
    p.add_argument(
        "--inverse",
        action="store_true",
        help="the file holds target_from_left_cam (the camera in the target frame)",
    )
    p.add_argument(
        "--max-dt",
        type=float,
        metavar="S",
        help="match a pose to the nearest frame within S seconds (default 0.01)",
    )
    p.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="folder for a trajectory file's metrics (default: <file stem>_eval/ beside it)",
    )

    p = sub.add_parser(
        "report",
        help="PNG plots of a run",
        description="Plot range, rotation angle, errors with 3-sigma bounds, spin rate and "
        "timing of a run folder (PNG files in the folder).",
    )
    p.add_argument("run", type=Path, metavar="DIR", help="run folder (satpose run --out)")
    p.add_argument(
        "--sequence",
        type=Path,
        metavar="SEQUENCE",
        help="sequence with ground truth (default: the one in DIR/run.yaml)",
    )

    p = sub.add_parser(
        "demo",
        help="the main job on the built-in default scenario",
        description="Render a short paper-docking sequence (40 frames, 7 m to 5 m, 1024x768, "
        "8 spp), run the frontend and the online estimator on it, print the metric table against "
        "the truth and write the plots and the Rerun recording.",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=DEMO_OUT,
        metavar="DIR",
        help=f"output folder (default {DEMO_OUT})",
    )
    for register in EXTRA_COMMANDS:
        register(sub)
    return parser


def _scenario_from_args(args: argparse.Namespace) -> Scenario:
    from satpose.datasets.config import replace_nested, yaml_problem
    from satpose.datasets.random_family import named_scenario
    from satpose.datasets.scenarios import scaled

    scenario = named_scenario(args.preset, args.seed)
    if args.config is not None:
        try:
            overrides = yaml.safe_load(args.config.read_text(encoding="utf-8")) or {}
        except OSError as exc:
            raise ConfigError(f"{args.config}: cannot read ({exc.strerror or exc})") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{args.config}: not valid YAML: {yaml_problem(exc)}") from None
        if not isinstance(overrides, dict):
            raise ConfigError(f"{args.config}: must hold a mapping of scenario overrides")
        try:
            scenario = replace_nested(scenario, overrides)
        except ConfigError as exc:
            raise ConfigError(f"{args.config}: {exc}") from None
    return scaled(scenario, frames=args.frames, size=args.size, spp=args.spp, seed=args.seed)


def _render(scenario: Scenario, out: Path, overwrite: bool) -> None:
    from tqdm import tqdm

    from satpose.datasets.render import render_sequence
    from satpose.datasets.sequence import load_sequence

    start = time.perf_counter()
    with tqdm(
        total=scenario.frames,
        desc=f"render {scenario.name}",
        unit="frame",
        file=sys.stderr,
        dynamic_ncols=True,
        delay=0.5,
    ) as bar:
        render_sequence(scenario, out, overwrite=overwrite, progress=lambda _k: bar.update(1))
    elapsed = time.perf_counter() - start
    rig = scenario.rig
    variant = load_sequence(out).generator.get("variant", "unknown")
    print(
        f"wrote {scenario.frames} {'stereo' if rig.stereo else 'mono'} frames "
        f"({rig.width}x{rig.height}, {scenario.render.spp} spp) to {out} "
        f"in {elapsed:.1f} s ({elapsed / scenario.frames:.2f} s/frame, Mitsuba {variant})"
    )
    if variant == "scalar_rgb":
        log.warning(
            "rendered with Mitsuba's scalar_rgb variant, several times slower than "
            "llvm_ad_rgb (Debian: apt-get install libllvm19)"
        )


def cmd_render(args: argparse.Namespace) -> None:
    if args.preset == "bracket-random":
        from satpose.tools.bracket import render_family_member

        render_family_member(args)
        return
    _render(_scenario_from_args(args), args.out, args.overwrite)


def run_frontend_on(
    sequence_path: Path, out: Path, config_path: Path | None, overwrite: bool = False
) -> None:
    """Frontend over a whole sequence, with a progress bar; writes the result files into a
    staging folder renamed to ``out`` at the end (an existing frontend output folder is
    replaced only with ``overwrite``). A frame that raises is that frame's failure; bad
    frames are named as warnings and counted in the summary line."""

    from satpose.datasets.config import load_config, to_plain
    from satpose.datasets.sequence import load_sequence
    from satpose.frontend.pipeline import FrontendConfig, StereoFrontend
    from satpose.tools.badframes import BadFrames, measure_frames
    from satpose.tools.files import atomic_write, staged_output, write_measurements, write_tum

    seq = load_sequence(sequence_path)
    if seq.kind != "stereo":
        raise ConfigError(
            f"{sequence_path}: the stereo frontend needs a stereo sequence (this one is {seq.kind})"
        )
    config = load_config(FrontendConfig, config_path) if config_path else FrontendConfig()
    with staged_output(out, overwrite, marker="measurements.parquet", what="a frontend") as stage:
        frontend = StereoFrontend(seq.calibration, config)
        bad = BadFrames(seq.root)
        results = measure_frames(seq, "frontend", frontend.process_frame, bad)
        write_measurements(results, stage / "measurements.parquet")
        with_pose = [m for m in results if m.pose is not None]
        write_tum(
            [m.t_s for m in with_pose],
            [m.pose.left_cam_from_target for m in with_pose],
            stage / "frontend_pose.tum",
        )
        text = yaml.safe_dump({"frontend": to_plain(config)}, sort_keys=False)
        atomic_write(stage / "config.yaml", lambda tmp: Path(tmp).write_text(text))
    totals = [sum(m.timings_ms.values()) for m in results]
    rings = sum(m.ring is not None for m in results)
    print(
        f"{len(results)} frames: ring in {rings}, pose in {len(with_pose)}; frontend "
        f"{np.median(totals):.0f} ms per frame (median); wrote {out}/measurements.parquet, "
        f"{out}/frontend_pose.tum"
    )
    if bad.count:
        print(bad.summary(len(results)))


def cmd_frontend(args: argparse.Namespace) -> None:
    run_frontend_on(args.sequence, args.out, args.config, overwrite=args.overwrite)


@contextmanager
def _frame_progress(desc: str) -> Iterator[Callable[[int, int], None]]:
    """A tqdm bar on stderr for `run_pipeline`'s ``progress(done, total)`` callback."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, delay=0.5)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        yield progress
    finally:
        bar.close()


def cmd_run(args: argparse.Namespace) -> None:
    from satpose.datasets.config import load_config
    from satpose.tools.pipeline import PipelineConfig, run_pipeline

    config = load_config(PipelineConfig, args.config) if args.config else PipelineConfig()
    with _frame_progress(f"run {args.estimator}") as progress:
        result = run_pipeline(
            args.sequence,
            args.estimator,
            args.out,
            config,
            overwrite=args.overwrite,
            spawn=args.spawn,
            connect=getattr(args, "connect", None),
            progress=progress,
        )
    n = len(result.measurements)
    poses = sum(m.pose is not None for m in result.measurements)
    print(
        f"{n} frames ({poses} with a frontend pose); {args.estimator} estimate of "
        f"{len(result.estimate)} frames in {args.out}/trajectory.csv; recording "
        f"{args.out}/run.rrd (open: rerun {args.out}/run.rrd)"
    )
    if result.bad_frames.count:
        print(result.bad_frames.summary(n))


def cmd_eval(args: argparse.Namespace) -> None:
    from satpose.tools.evaluate import (
        DEFAULT_MAX_DT_S,
        evaluate_file,
        evaluate_run,
        table,
        write_metrics,
    )

    path: Path = args.trajectory
    if path.is_dir():
        used = [
            o
            for o, v in (
                ("--format", args.format),
                ("--inverse", args.inverse),
                ("--max-dt", args.max_dt),
                ("--out", args.out),
            )
            if v
        ]
        if used:
            raise ConfigError(
                f"{path}: is a run folder; {', '.join(used)} only apply to a trajectory file"
            )
        results = evaluate_run(args.sequence, path)
        print(table(results))
        write_metrics(results, path, args.sequence)
        print(f"wrote {path}/metrics.json, metrics.csv and groundtruth.tum")
        return
    max_dt = DEFAULT_MAX_DT_S if args.max_dt is None else args.max_dt
    results, assoc = evaluate_file(
        args.sequence, path, fmt=args.format, inverse=args.inverse, max_dt_s=max_dt
    )
    print(table(results))
    m = next(iter(results.values()))
    print(
        f"{path.name}: {m.frames} of {m.frames + assoc.unmatched_poses.size} poses matched a "
        f"frame within {max_dt:g} s; {assoc.unmatched_poses.size} matched none; "
        f"{assoc.unmatched_frames.size} of {m.frames_in_sequence} frames have no pose"
    )
    out = args.out if args.out is not None else path.parent / f"{path.stem}_eval"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{out}: cannot create the folder ({exc.strerror or exc})") from None
    write_metrics(results, out, args.sequence)
    print(f"wrote {out}/metrics.json, metrics.csv and groundtruth.tum")


def cmd_report(args: argparse.Namespace) -> None:
    from satpose.tools.report import make_report

    for path in make_report(args.run, args.sequence):
        print(f"wrote {path}")


def cmd_demo(args: argparse.Namespace) -> None:
    from satpose.datasets.scenarios import preset, scaled
    from satpose.tools.evaluate import evaluate_run, table, write_metrics
    from satpose.tools.pipeline import run_pipeline
    from satpose.tools.report import make_report

    scenario = scaled(preset("paper-docking"), frames=DEMO_FRAMES, spp=DEMO_SPP)
    seq = args.out / "paper-docking"
    run = args.out / "run-online"
    _render(scenario, seq, overwrite=True)
    print(f"running frontend + iSAM2 backend on {seq} ...", flush=True)
    start = time.perf_counter()
    with _frame_progress("estimate (frontend + iSAM2)") as progress:
        run_pipeline(seq, "online", run, overwrite=True, progress=progress)
    elapsed = time.perf_counter() - start
    print(
        f"estimated {DEMO_FRAMES} frames in {elapsed:.1f} s ({elapsed / DEMO_FRAMES:.2f} s/frame)"
    )
    results = evaluate_run(seq, run)
    write_metrics(results, run, seq)
    print(table(results))
    plots = make_report(run)
    print(
        f"\nsequence: {seq}\nrun: {run} (trajectory.csv, metrics.json, "
        f"{len(plots)} PNG plots)\nrecording: rerun {run}/run.rrd"
    )


COMMANDS = {
    "render": cmd_render,
    "frontend": cmd_frontend,
    "run": cmd_run,
    "eval": cmd_eval,
    "report": cmd_report,
    "demo": cmd_demo,
}


# More subcommands live in their own modules: each provides ``register(subparsers)``, which
# adds its parser and sets ``handler=<function taking the parsed args>`` as a default.
def _register_stars(subparsers: Any) -> None:
    from satpose.tools.stars import register

    register(subparsers)


def _register_bracket(subparsers: Any) -> None:
    from satpose.tools.bracket import register

    register(subparsers)


def _register_rings(subparsers: Any) -> None:
    from satpose.tools.rings_cli import register

    register(subparsers)


def _register_campaign(subparsers: Any) -> None:
    from satpose.tools.campaign import register

    register(subparsers)


def _register_import(subparsers: Any) -> None:
    from satpose.tools.import_cli import register

    register(subparsers)


def _register_live(subparsers: Any) -> None:
    from satpose.tools.live import register

    register(subparsers)


def _register_export(subparsers: Any) -> None:
    from satpose.tools.export import register

    register(subparsers)


EXTRA_COMMANDS: list[Callable[[Any], None]] = [
    colmap_cli.register,
    spin_cli.register,
    _register_stars,
    _register_bracket,
    _register_rings,
    _register_campaign,
    _register_import,
    _register_live,
    _register_export,
]


class _BarAwareHandler(logging.StreamHandler):
    """Log lines on stderr that print above a visible progress bar instead of into it
    (``tqdm.write``), and plainly while no bar is shown (a bar still within its ``delay``
    must not be drawn by the write: it would then never be ended by its ``close``)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        bars = list(getattr(tqdm, "_instances", ()))
        if not any(b.last_print_t >= b.start_t + b.delay for b in bars if not b.disable):
            super().emit(record)
            return
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:
            self.handleError(record)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``satpose`` console script. Returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
        handlers=[_BarAwareHandler()],
    )
    handler = getattr(args, "handler", None) or COMMANDS[args.command]
    try:
        handler(args)
    except SatposeError as exc:
        print(f"satpose {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"satpose {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
