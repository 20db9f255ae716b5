"""The pose a bracket frame reports once the decision over frames chose its labelling
(`decided_frame_pose`): the points' own maximum near the decided track, the struts' tapers
only where the points alone leave the track, and nothing where neither stays near it."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from satpose.datasets.bracket_family import bracket_draw
from satpose.datasets.geometry import Rigid3
from satpose.frontend import bracket_lines as bl
from satpose.frontend.bracket import BracketGeometry
from satpose.frontend.bracket_lines import (
    StrutDetectorConfig,
    decided_frame_pose,
    noise_free_hypotheses,
    refine_partial_pose,
)


def truth_model() -> tuple[Rigid3, bl.PartialImageModel]:
    """Bracket family tuning member 1, frame 0 (visible fraction 0.16: short stubs, one
    strut wide enough for a taper): the true pose and the exact image's model."""
    scene = bracket_draw(1)
    T = scene.cam_from_target(0)
    geo = BracketGeometry(vertices_m=scene.vertices_target())
    cfg = StrutDetectorConfig(strut_radius_m=scene.strut_radius_m)
    hyps = noise_free_hypotheses(T, geo, scene.camera.K, scene.visible_fraction, cfg)
    assert bl._rotation_deg(hyps[0].refined, T) < 1e-5  # the truth first
    return T, hyps[0].model


def within(tol_deg: float) -> Callable[[Rigid3, Rigid3], bool]:
    """Two poses are one answer when their attitudes are within ``tol_deg``."""
    return lambda a, b: bl._rotation_deg(a, b) < tol_deg


def test_exact_image_reports_the_truth() -> None:
    """Noise-free, started 2 deg off: the truth within 1e-5 deg, with a symmetric positive
    definite covariance; the same without a track pose to compare with."""
    T, model = truth_model()
    start = T @ Rigid3.from_rotvec(np.radians([1.2, -1.0, 1.2]), np.array([0.01, 0.0, -0.01]))
    for decided in (T, None):
        out = decided_frame_pose(start, model, decided, within(1.0))
        assert out is not None
        pose, cov = out
        assert bl._rotation_deg(pose, T) < 1e-5
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_tapers_only_where_the_points_leave_the_track_and_nothing_beyond() -> None:
    """Both stub directions 1 deg off (a biased detector): the points alone have their
    maximum 4.2 deg from the decided (true) pose, the points with the taper 2.7 deg (measured
    on this frame). With the rival distance at 5 deg the untapered pose is reported, at 3.5
    deg the tapered one, at 2 deg none; without a track pose the untapered one."""
    T, model = truth_model()
    z = model.z.copy()
    z[4] += math.radians(1.0)
    z[5] -= math.radians(1.0)
    biased = replace(model, z=z)
    assert biased.tapers  # the fallback has something to add
    plain, _, _ = refine_partial_pose(T, replace(biased, tapers=()))
    tapered, _, _ = refine_partial_pose(T, biased)
    d_plain, d_tapered = bl._rotation_deg(plain, T), bl._rotation_deg(tapered, T)
    assert 3.9 < d_plain < 4.5 and 2.4 < d_tapered < 3.1, (d_plain, d_tapered)

    def reported(decided: Rigid3 | None, tol: float) -> Rigid3 | None:
        out = decided_frame_pose(T, biased, decided, within(tol))
        return None if out is None else out[0]

    for decided, tol, expected in ((T, 5.0, plain), (T, 3.5, tapered), (None, 0.1, plain)):
        got = reported(decided, tol)
        assert got is not None and bl._rotation_deg(got, expected) < 1e-9, (decided, tol)
    assert reported(T, 2.0) is None
