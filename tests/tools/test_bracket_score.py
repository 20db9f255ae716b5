"""The second poses of an exact bracket image (`nearest_rival_offsets`): what the benchmark's
bound on the bracket family (docs/results/bracket_family_*.md, 'The bound') is made of."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from satpose.datasets.bracket_family import measured_points_b
from satpose.datasets.geometry import Rigid3
from satpose.frontend.bracket import project
from satpose.tools.bracket_score import ambiguous_noise_free, nearest_rival_offsets


def _seed0(k: int) -> tuple[Rigid3, np.ndarray, np.ndarray, float]:
    data = json.loads(
        (Path(__file__).parents[1] / "data" / "bracket_labelling" / "seed0_truth.json").read_text()
    )
    f = data["frames"][k]
    T = Rigid3(R=np.array(f["R"]), t=np.array(f["t"]))
    return T, np.array(data["vertices"]), np.array(data["K"]), float(data["fraction"])


def test_whole_triangle_rival_reprojects_exactly() -> None:
    """Tuning seed 0's bracket at frame 8 with the whole triangle visible: the second pose is
    another P3P solution of ``p1, p2`` and the apex, so it puts every measured point exactly
    where the truth does (noise-free: within 1e-6 px) while its attitude is 8+ deg off."""
    T, V, K_, _ = _seed0(8)
    end_px, vertex_px, deg = nearest_rival_offsets(T, V, K_, 1.0)
    assert end_px < 1e-6 and vertex_px < 1e-6
    assert deg > 8.0
    assert ambiguous_noise_free(T, V, K_, 1.0)


def test_partial_view_rival_within_the_verification_tolerance() -> None:
    """Tuning seed 0, frame 8 (84 % of the side struts visible): the neighbouring P3P root
    8-20 deg off fits ``p1, p2`` to under 1 px and puts the stub ends within the
    detector's 3 sigma (``3 px + 5 %`` of each stub) of the true ones: it passed the
    verification, so it must lie inside it."""
    T, V, K_, frac = _seed0(8)
    end_px, vertex_px, deg = nearest_rival_offsets(T, V, K_, frac)
    assert 8.0 < deg < 20.0
    assert vertex_px < 1.0
    px = project(T, measured_points_b(V, frac), K_)
    stub = min(float(np.linalg.norm(px[2] - px[0])), float(np.linalg.norm(px[3] - px[1])))
    assert 0.0 < end_px <= 3.0 * (3.0 + 0.05 * stub)


def test_no_rival_gives_nans() -> None:
    """Seed 0's frame 0 with only 20 % of the side struts visible has no second pose within
    the verification: NaNs, and not ambiguous."""
    T, V, K_, _ = _seed0(0)
    assert all(math.isnan(x) for x in nearest_rival_offsets(T, V, K_, 0.2))
    assert not ambiguous_noise_free(T, V, K_, 0.2)
