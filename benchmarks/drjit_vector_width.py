"""pytest plugin: render with Dr.Jit's LLVM backend compiled for another x86-64 vector unit.

Renders differ in their last bits (and in Monte Carlo noise) between CPUs with AVX-512 and
AVX2, because Dr.Jit vectorises its kernels to the host's width. A test that passes only with
the noise of one machine is a test that fails on the next one. This plugin lets one machine
check the suite against the other vector unit:

    PYTHONPATH=benchmarks .venv/bin/python -m pytest -p drjit_vector_width            # AVX2
    PYTHONPATH=benchmarks .venv/bin/python -m pytest -p drjit_vector_width --drjit-cpu=x86-64

``--drjit-cpu`` takes an LLVM CPU name (``znver2``: AVX2, 8 lanes, the default;
``skylake-avx512``: AVX-512, 16 lanes; ``x86-64``: SSE2, 4 lanes). It uses Dr.Jit-core's
``jit_llvm_set_target`` (exported by libdrjit-core.so, not wrapped in Python), so it is a
developer's check, not part of the library.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import pytest

# Each CPU's features, spelled out: a target CPU alone keeps the host's feature string.
TARGETS = {
    "znver2": (
        b"+avx,+avx2,+fma,+f16c,+sse4.2,+popcnt,+bmi,+bmi2,+lzcnt,+movbe,"
        b"-avx512f,-avx512vl,-avx512dq,-avx512bw,-avx512cd",
        8,
    ),
    "skylake-avx512": (
        b"+avx,+avx2,+fma,+f16c,+sse4.2,+popcnt,+avx512f,+avx512vl,+avx512dq,+avx512bw,+avx512cd",
        16,
    ),
    "x86-64": (b"+sse2,-avx,-avx2,-fma,-avx512f", 4),
}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--drjit-cpu",
        default="znver2",
        choices=sorted(TARGETS),
        help="LLVM CPU that Dr.Jit compiles render kernels for (default: znver2, AVX2)",
    )


def pytest_configure(config: pytest.Config) -> None:
    cpu = config.getoption("--drjit-cpu")
    # Kernels compiled for one target must not be served to another from Dr.Jit's disk cache.
    os.environ["DRJIT_CACHE_DIR"] = str(Path.home() / ".cache" / f"satpose-drjit-{cpu}")
    from satpose.datasets.scene import load_mitsuba

    _, variant = load_mitsuba("auto")
    if variant != "llvm_ad_rgb":
        raise pytest.UsageError("drjit_vector_width needs Mitsuba's llvm_ad_rgb variant")
    import drjit

    core = ctypes.CDLL(str(Path(drjit.__file__).parent / "libdrjit-core.so"))
    set_target = core._Z19jit_llvm_set_targetPKcS0_j  # jit_llvm_set_target(cpu, features, width)
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    target_cpu = core._Z19jit_llvm_target_cpuv
    target_cpu.restype = ctypes.c_char_p
    width = core._Z21jit_llvm_vector_widthv
    width.restype = ctypes.c_uint32
    features, lanes = TARGETS[cpu]
    set_target(cpu.encode(), features, lanes)
    config._drjit_target = f"{target_cpu().decode()}, {width()} lanes"  # type: ignore[attr-defined]


def pytest_report_header(config: pytest.Config) -> str:
    return f"Dr.Jit LLVM target: {getattr(config, '_drjit_target', '?')}"
