"""The bracket scene family (datasets/bracket_family.py): a function of the seed, its ranges,
the seed split, and a tiny render."""

from __future__ import annotations

import numpy as np
import pytest

from satpose.datasets import bracket_family as bf
from satpose.datasets.seed_split import split_of
from satpose.frontend.bracket import triangle_sides


def test_draw_is_a_function_of_the_seed() -> None:
    """The same seed gives the same scene (vertices, motion, light); another seed another."""
    a, b, c = bf.bracket_draw(3), bf.bracket_draw(3), bf.bracket_draw(4)
    assert np.array_equal(a.vertices_b, b.vertices_b)
    assert all(
        np.array_equal(p.R, q.R) and np.array_equal(p.t, q.t)
        for p, q in zip(a.b_from_cam, b.b_from_cam, strict=True)
    )
    assert np.array_equal(a.sun_b, b.sun_b)
    assert not np.array_equal(a.vertices_b, c.vertices_b)


@pytest.mark.parametrize("seed", [0, 7, 21, 1003])
def test_draw_respects_its_ranges(seed: int) -> None:
    """Base length, apex height, strut radius and visible fraction within their ranges; the
    measured points (p1, p2, the visible ends) inside the full-size image with the margin in
    every frame; the camera on the bracket's front face and closing in."""
    s = bf.bracket_draw(seed)
    base = triangle_sides(s.vertices_b)[0]
    assert bf.BASE_RANGE_M[0] <= base <= bf.BASE_RANGE_M[1]
    assert bf.STRUT_RADIUS_RANGE_M[0] <= s.strut_radius_m <= bf.STRUT_RADIUS_RANGE_M[1]
    assert bf.VISIBLE_FRACTION_RANGE[0] <= s.visible_fraction <= bf.VISIBLE_FRACTION_RANGE[1]
    pts = bf.measured_points_b(s.vertices_b, s.visible_fraction)
    for k in range(s.frames):
        assert bf._fits(s.camera, s.b_from_cam[k], pts)
        assert s.b_from_cam[k].t[2] > 0  # the camera on the +z (front) side
    ranges = [np.linalg.norm(p.t - pts.mean(axis=0)) for p in s.b_from_cam]
    assert ranges[-1] < ranges[0] <= bf.START_RANGE_M[1] + 0.2


def test_seed_split_and_bad_seed() -> None:
    assert split_of(0) == "tuning" and split_of(1099) == "validation"
    assert split_of(500) is None
    with pytest.raises(bf.BracketFamilyError, match="seed 500"):
        bf.bracket_draw(500)


def test_tiny_render_is_deterministic_and_shows_the_struts() -> None:
    """Two renders of one frame at 160x128 are identical (seeded noise) and the struts are
    brighter than the median of the image where they project."""
    s = bf.bracket_draw(1, frames=3, size=(160, 128))
    a, b = bf.render_frame(s, 0), bf.render_frame(s, 0)
    assert a.shape == (128, 160) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    from satpose.frontend.bracket import project

    T = s.cam_from_target(0)
    V = s.vertices_target()
    mid = project(T, (0.5 * (V[0] + V[1]))[None], s.camera.K)[0]
    x, y = round(float(mid[0])), round(float(mid[1]))
    assert a[y - 1 : y + 2, x - 1 : x + 2].max() > np.median(a) + 40
