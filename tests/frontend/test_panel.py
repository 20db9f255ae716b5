"""Panel corners and dark components in one image (satpose.frontend.panel).

The images are drawn analytically, not rendered: every edge is a Gaussian-blurred step
``Phi(-d / 0.7 px)`` of the signed distance ``d`` to the true outline, so the half-level
crossing, where an edge locator must put the edge, is exactly on the true line (a symmetric
blur does not move it). The panel is a 1.2 m square seen through a pinhole camera at 4 m, tilted
~25 deg, with the docking ring (bright rim, dark hole) at its centre; components are dark
disks of known image centre. Same values on every CPU.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from satpose.datasets.geometry import Rigid3
from satpose.frontend.conics import Ellipse, fit_ellipse_direct
from satpose.frontend.edges import smoothed
from satpose.frontend.panel import (
    ComponentConfig,
    CornerConfig,
    PanelQuad,
    PanelTracker,
    _fill_fraction,
    find_components,
    find_panel,
)

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
BLUR_PX = 0.7
HALF_M, RING_M = 0.6, 0.3
PANEL = np.array(
    [[-HALF_M, -HALF_M, 0], [HALF_M, -HALF_M, 0], [HALF_M, HALF_M, 0], [-HALF_M, HALF_M, 0]]
)
CAM_FROM_TARGET = Rigid3.from_rotvec([0.25, -0.35, 0.1], [0.1, -0.05, 4.0])
"""The drawn panel's pose in the camera ([m])."""
BLOBS = np.array(
    [[414.5, 234.2, 6.0], [256.2, 244.4, 6.0], [326.7, 314.4, 5.5], [371.6, 142.2, 6.5]]
)
"""Dark components: image centre x, y and radius [px], on the panel between 1.3 and 2.3 ring
semi-axes from the ring centre."""
YY, XX = np.mgrid[0:H, 0:W].astype(np.float64)
CORNERS = CornerConfig()
COMPONENTS = ComponentConfig()


def _project(T: Rigid3, X: np.ndarray) -> np.ndarray:
    x = (X @ T.R.T + T.t) @ K.T
    return x[:, :2] / x[:, 2:3]


def _ring_ellipse(T: Rigid3) -> Ellipse:
    """The ring's image ellipse (a projected circle is an exact ellipse: fit to 64 points)."""
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    X = np.c_[RING_M * np.cos(a), RING_M * np.sin(a), np.zeros(64)]
    return fit_ellipse_direct(_project(T, X))


def _polygon_cover(corners: np.ndarray, wavy_side: int | None = None) -> np.ndarray:
    """Blurred indicator of a convex polygon: product of one blurred step per side (side k
    from corner k to k+1). ``wavy_side`` ripples that side's edge by 1 px (period 40 px):
    not a straight edge (RMS 0.71 px about its line)."""
    c = corners.mean(axis=0)
    out = np.ones((H, W))
    for k in range(len(corners)):
        a, b = corners[k], corners[(k + 1) % len(corners)]
        n = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
        if n @ (c - a) > 0:
            n = -n  # outward
        d = (XX - a[0]) * n[0] + (YY - a[1]) * n[1]
        if k == wavy_side:
            along = (XX - a[0]) * n[1] - (YY - a[1]) * n[0]
            d += np.sin(2 * np.pi * along / 40.0)
        out *= ndtr(-d / BLUR_PX)
    return out


def _ellipse_cover(e: Ellipse, scale: float = 1.0) -> np.ndarray:
    c, s = math.cos(e.theta), math.sin(e.theta)
    u = c * (XX - e.cx) + s * (YY - e.cy)
    v = -s * (XX - e.cx) + c * (YY - e.cy)
    rho = np.hypot(u / (scale * e.a), v / (scale * e.b))
    return ndtr(-(rho - 1) * scale * e.b / BLUR_PX)


def _draw(
    corners: np.ndarray,
    ring: Ellipse,
    blobs: np.ndarray = BLOBS,
    blob_level: float = 0.03,
    noise: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """(gray float32 in [0, 1], gray8): black space, panel 0.7, ring rim 0.9 with a 0.2 hole
    (80 % of the rim's size), dark disks ``blobs`` (x, y, r) at ``blob_level``, plus white
    Gaussian noise of std ``noise``."""
    img = 0.7 * _polygon_cover(corners)
    img += (0.9 - img) * _ellipse_cover(ring)
    img += (0.2 - img) * _ellipse_cover(ring, 0.8)
    for x, y, r in blobs:
        img += (blob_level - img) * ndtr(-(np.hypot(XX - x, YY - y) - r) / BLUR_PX)
    if noise:
        img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    g = np.clip(img, 0.0, 1.0).astype(np.float32)
    return g, np.round(g * 255).astype(np.uint8)


def _find(g: np.ndarray, g8: np.ndarray, ring: Ellipse) -> PanelQuad | None:
    return find_panel(g, g8, ring, CORNERS, smoothed(g, CORNERS.edges))


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, Ellipse, np.ndarray, np.ndarray]:
    truth = _project(CAM_FROM_TARGET, PANEL)
    ring = _ring_ellipse(CAM_FROM_TARGET)
    g, g8 = _draw(truth, ring)
    return truth, ring, g, g8


def test_corners_of_a_clean_panel_are_exact_and_ordered(scene) -> None:  # type: ignore[no-untyped-def]
    """Noise-free: each corner within 0.05 px of the projected 3-D corner (the sub-pixel edge
    search on a symmetric blurred step; measured 0.035 px). The quad's conventions: corner i is
    the intersection of lines i and i+1 (to 1e-9 px), the unit normals point out of the panel,
    all four corners visible, each side a clean line (rms below max_line_rms_px; measured
    < 0.03 px)."""
    truth, ring, g, g8 = scene
    quad = _find(g, g8, ring)
    assert quad is not None
    # Corners in any cyclic order and direction: match each to its nearest truth corner.
    d = np.linalg.norm(quad.corners[:, None] - truth[None], axis=2)
    match = d.argmin(axis=1)
    assert sorted(match) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.05
    for i in range(4):
        for ln in (quad.lines[i], quad.lines[(i + 1) % 4]):
            assert abs(ln[:2] @ quad.corners[i] + ln[2]) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(quad.lines[:, :2], axis=1), 1.0, atol=1e-12)
    centre = truth.mean(axis=0)
    assert np.all(quad.lines[:, :2] @ centre + quad.lines[:, 2] < 0)  # outward normals
    assert quad.visible.all()
    assert np.all(quad.rms_px < 0.05)


def test_noisy_corners_scatter_as_the_edge_fits_predict(scene) -> None:  # type: ignore[no-untyped-def]
    """Pixel noise 0.02 (of full scale), 10 seeds x 4 corners: the corner's displacement from
    the noise-free result against the covariance that the total-least-squares line fits
    predict from their own residual scatter (``rms_px``, 60 normals per side spread over 10-90 %
    of it, the corner extrapolated to the side's end; two lines crossing). For independent
    edge points the normalised squared error is chi2(2): mean 2. The Gaussian pre-smoothing
    (1 px) makes neighbouring normals correlated, which the independent-point prediction leaves
    out (measured mean 3.4), so the bounds are: mean over the 40 below 6 and every corner
    within 5 predicted sigma (25)."""
    truth, ring, g, g8 = scene
    q0 = _find(g, g8, ring)
    assert q0 is not None
    n = CORNERS.edge_samples
    z = []
    for seed in range(10):
        gn, gn8 = _draw(truth, ring, noise=0.02, seed=seed)
        q = _find(gn, gn8, ring)
        assert q is not None and q.visible.all()
        for k in range(4):
            sides = [k, (k + 1) % 4]  # corner k ends line k and starts line k+1
            var = []
            for j, end in zip(sides, (0.5, -0.5), strict=True):
                length = float(np.linalg.norm(q.corners[j] - q.corners[(j - 1) % 4]))
                u = (np.linspace(0.1, 0.9, n) - 0.5) * length
                var.append(q.rms_px[j] ** 2 * (1 / n + (end * length) ** 2 / np.sum(u**2)))
            Ni = np.linalg.inv(q.lines[sides, :2])
            cov = Ni @ np.diag(var) @ Ni.T
            d = q.corners[k] - q0.corners[k]
            z.append(float(d @ np.linalg.solve(cov, d)))
    assert np.mean(z) < 6.0
    assert max(z) < 25.0


def test_corners_outside_the_image_are_not_visible() -> None:
    """The panel shifted so that one corner lies 40 px beyond the right border: that corner
    is reported not visible, the in-image ones within 0.05 px (noise-free, as above)."""
    T = Rigid3(R=CAM_FROM_TARGET.R, t=CAM_FROM_TARGET.t + np.array([1.0, 0.05, 0.0]))
    truth = _project(T, PANEL)
    assert truth[:, 0].max() > W + 20 and (truth[:, 0] < W - 20).sum() == 3
    ring = _ring_ellipse(T)
    g, g8 = _draw(truth, ring, blobs=np.zeros((0, 3)))
    quad = _find(g, g8, ring)
    assert quad is not None
    inside = truth[:, 0] < W - 5
    d = np.linalg.norm(quad.corners[:, None] - truth[None], axis=2)
    match = d.argmin(axis=1)
    for i in range(4):
        assert quad.visible[i] == inside[match[i]]
        if inside[match[i]]:
            assert d[i, match[i]] < 0.05


def test_a_panel_with_one_side_beyond_the_image_gives_its_two_corners() -> None:
    """Close up (2.5 m) with the panel shifted down: its bottom side and both bottom corners
    lie beyond the image (25-55 px), so only three sides are in view, which pair into no
    quadrilateral of four found lines. The panel is the found pair and the line crossing it,
    closed by a side beyond the image: the two top corners visible within 0.05 px of the
    truth (noise-free, as above), the bottom two not visible."""
    T = Rigid3(R=CAM_FROM_TARGET.R, t=CAM_FROM_TARGET.t + np.array([0.0, 0.4, -1.5]))
    truth = _project(T, PANEL)
    assert (truth[:, 1] > H + 20).sum() == 2 and (truth[:, 1] < H - 100).sum() == 2
    ring = _ring_ellipse(T)
    g, g8 = _draw(truth, ring, blobs=np.zeros((0, 3)))
    quad = _find(g, g8, ring)
    assert quad is not None
    assert quad.visible.sum() == 2
    d = np.linalg.norm(quad.corners[quad.visible][:, None] - truth[None], axis=2)
    assert sorted(d.argmin(axis=1)) == [0, 1]
    assert d.min(axis=1).max() < 0.05


def test_the_rings_bore_and_shadow_are_part_of_the_panel(scene) -> None:  # type: ignore[no-untyped-def]
    """Hard sunlight: the ring's bore is black and its wall casts a black shadow on the panel
    (the ring's ellipse shifted by 0.6 of its semi-axes), together 16 % of the panel's
    inside, more than the 10 % of dark inside that a quadrilateral of struts with black
    space would show (``min_fill``). Enclosed by the lit panel, they are holes in it, not
    space: the panel is found, corners within 0.05 px (noise-free, as above)."""
    truth, ring, _, _ = scene
    img = 0.7 * _polygon_cover(truth)
    shadow = Ellipse(
        cx=ring.cx + 0.6 * ring.a, cy=ring.cy + 0.6 * ring.b, a=ring.a, b=ring.b, theta=ring.theta
    )
    img += (0.005 - img) * _ellipse_cover(shadow)
    img += (0.9 - img) * _ellipse_cover(ring)
    img += (0.005 - img) * _ellipse_cover(ring, 0.8)
    g = np.clip(img, 0, 1).astype(np.float32)
    filled, lit = _fill_fraction(smoothed(g, CORNERS.edges), truth, CORNERS.foreground_level)
    assert lit < CORNERS.min_fill - 0.05 and filled == 1.0
    quad = _find(g, np.round(g * 255).astype(np.uint8), ring)
    assert quad is not None and quad.visible.all()
    d = np.linalg.norm(quad.corners[:, None] - truth[None], axis=2)
    assert sorted(d.argmin(axis=1)) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.05


def test_corners_of_a_ragged_side_are_not_visible(scene) -> None:  # type: ignore[no-untyped-def]
    """One side drawn rippled (RMS 0.71 px about its line, above max_line_rms_px = 0.6): its
    rms_px is above the limit and exactly its two corners are not visible; the other two
    corners, on clean sides, stay within 0.05 px (noise-free, as above)."""
    truth, ring, _, _ = scene
    img = 0.7 * _polygon_cover(truth, wavy_side=1)  # side 1 runs from corner 1 to corner 2
    img += (0.9 - img) * _ellipse_cover(ring)
    img += (0.2 - img) * _ellipse_cover(ring, 0.8)
    g = np.clip(img, 0, 1).astype(np.float32)
    quad = _find(g, np.round(g * 255).astype(np.uint8), ring)
    assert quad is not None
    d = np.linalg.norm(quad.corners[:, None] - truth[None], axis=2)
    match = d.argmin(axis=1)
    assert sorted(match) == [0, 1, 2, 3]
    assert (quad.rms_px > CORNERS.max_line_rms_px).sum() == 1
    for i in range(4):
        assert quad.visible[i] == (match[i] in (0, 3))
        if quad.visible[i]:
            assert d[i, match[i]] < 0.05


def test_refusals_give_none(scene) -> None:  # type: ignore[no-untyped-def]
    """No panel -> None, never an exception: a black image; a ring too close to the border
    for a search window (< 16 px); a panel that does not surround the ring (the ring drawn
    beside it); an outline of thin bright struts with black space inside (the fill test: the
    black inside is enclosed by the struts, so it is the lit fraction that refuses it); and
    the struts' outline with a gap in one side, where the black inside reaches out."""
    truth, ring, g, g8 = scene
    dark = np.zeros_like(g)
    assert _find(dark, dark.astype(np.uint8), ring) is None
    corner_ring = Ellipse(cx=2.0, cy=2.0, a=3.0, b=2.0, theta=0.0)
    assert _find(g, g8, corner_ring) is None
    beside = Ellipse(cx=560.0, cy=400.0, a=30.0, b=25.0, theta=0.3)
    gb, gb8 = _draw(truth, beside, blobs=np.zeros((0, 3)))
    assert _find(gb, gb8, beside) is None
    # struts: the panel's outline as 6 px wide bright bands, black inside
    c = truth.mean(axis=0)
    inner = c + (truth - c) * 0.95
    struts = 0.7 * (_polygon_cover(truth) - _polygon_cover(inner)) + 0.9 * _ellipse_cover(ring)
    gs = np.clip(struts, 0, 1).astype(np.float32)
    assert _find(gs, np.round(gs * 255).astype(np.uint8), ring) is None
    gap = np.hypot(XX - 0.5 * (truth[1, 0] + truth[2, 0]), YY - 0.5 * (truth[1, 1] + truth[2, 1]))
    gs[gap < 20] = 0.0
    filled, _ = _fill_fraction(smoothed(gs, CORNERS.edges), truth, CORNERS.foreground_level)
    assert filled < 0.5
    assert _find(gs, np.round(gs * 255).astype(np.uint8), ring) is None


def test_tracker_follows_the_panel_without_searching() -> None:
    """Frame 2 moves the panel by (2.3, -1.7) px and gives a ring ellipse at the image corner,
    where a search is impossible (a fresh tracker returns None there): the tracker carries the
    previous outline by Lucas-Kanade and refines it, corners within 0.05 px of the moved truth
    (noise-free, as the detection). A black frame then loses it (None, no exception)."""
    truth = _project(CAM_FROM_TARGET, PANEL)
    ring = _ring_ellipse(CAM_FROM_TARGET)
    tracker = PanelTracker(CORNERS, COMPONENTS)
    g, g8 = _draw(truth, ring, blobs=np.zeros((0, 3)))
    quad, _ = tracker.update(g, g8, smoothed(g, CORNERS.edges), ring, with_components=False)
    assert quad is not None
    shift = np.array([2.3, -1.7])
    moved = Ellipse(
        cx=ring.cx + shift[0], cy=ring.cy + shift[1], a=ring.a, b=ring.b, theta=ring.theta
    )
    g2, g28 = _draw(truth + shift, moved, blobs=np.zeros((0, 3)))
    nowhere = Ellipse(cx=2.0, cy=2.0, a=3.0, b=2.0, theta=0.0)
    image_s = smoothed(g2, CORNERS.edges)
    fresh, _ = PanelTracker(CORNERS, COMPONENTS).update(g2, g28, image_s, nowhere, False)
    assert fresh is None
    quad2, comps = tracker.update(g2, g28, image_s, nowhere, with_components=False)
    assert quad2 is not None and quad2.visible.all()
    d = np.linalg.norm(quad2.corners[:, None] - (truth + shift)[None], axis=2)
    assert d.min(axis=1).max() < 0.05
    assert comps.shape == (0, 2)
    dark = np.zeros_like(g2)
    lost, _ = tracker.update(dark, dark.astype(np.uint8), dark, nowhere, with_components=False)
    assert lost is None and tracker.quad is None


def test_components_are_located_at_subpixel_precision(scene) -> None:  # type: ignore[no-untyped-def]
    """Four dark disks on the panel: all found, each centre within 0.05 px of the drawn
    centre (an ellipse fitted to sub-pixel edges of a blurred disk; measured 0.04 px)."""
    truth, ring, g, g8 = scene
    found = find_components(g, g8, ring, COMPONENTS, truth)
    assert found.shape == (4, 2)
    d = np.linalg.norm(found[:, None] - BLOBS[None, :, :2], axis=2)
    assert sorted(d.argmin(axis=1)) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.05


def test_components_filters(scene) -> None:  # type: ignore[no-untyped-def]
    """Only small, very dark, round blobs on the panel around the ring are components:
    - a grey disk (0.25 on the 0.7 panel: inside / outside 0.36 > max_darkness 0.2, yet dark
      enough in 8 bits, 64, for the blob detector's thresholds up to 130) is not;
    - a disk of radius 1.5 px (below min_radius_px 3) and one of 25 px (above 0.35 of the
      ring's semi-minor axis, ~19 px) are not;
    - with panel corners given, a dark disk outside that outline is not (the outline cut at
      x = 390 px leaves out the disk at x = 414.5, found with the full outline above);
    - a black image, or a ring too close to the border for a search window, give (0, 2)."""
    truth, ring, _, _ = scene
    extra = np.array([[300.0, 170.0, 1.5], [250.0, 330.0, 25.0]])
    g, g8 = _draw(truth, ring, blobs=np.r_[BLOBS, extra])
    found = find_components(g, g8, ring, COMPONENTS, truth)
    assert np.linalg.norm(found[:, None] - extra[None, :, :2], axis=2).min() > 10
    assert len(found) == 4
    gg, gg8 = _draw(truth, ring, blob_level=0.25)
    assert find_components(gg, gg8, ring, COMPONENTS, truth).shape == (0, 2)
    g, g8 = _draw(truth, ring)
    cut = truth.copy()
    cut[:, 0] = np.minimum(cut[:, 0], 390.0)  # the outline's right part cut off at x = 390
    without = find_components(g, g8, ring, COMPONENTS, cut)
    assert len(without) == 3
    assert np.linalg.norm(without - BLOBS[0, :2], axis=1).min() > 10
    dark = np.zeros_like(g)
    assert find_components(dark, dark.astype(np.uint8), ring, COMPONENTS).shape == (0, 2)
    corner_ring = Ellipse(cx=1.0, cy=1.0, a=2.0, b=1.5, theta=0.0)
    assert find_components(g, g8, corner_ring, COMPONENTS).shape == (0, 2)


def test_tracker_refines_tracked_components() -> None:
    """With components: frame 1 detects the four disks; frame 2 moves everything by
    (1.6, 0.9) px and is not a re-search frame (every 5th): the four components carried by
    Lucas-Kanade and refitted are the moved centres within 0.1 px, one each (noise-free; the
    refit starts from a radius guess of 0.12 ring semi-minor axes, not the blob's own; measured
    0.065 px)."""
    truth = _project(CAM_FROM_TARGET, PANEL)
    ring = _ring_ellipse(CAM_FROM_TARGET)
    tracker = PanelTracker(CORNERS, COMPONENTS)
    g, g8 = _draw(truth, ring)
    _, comps = tracker.update(g, g8, smoothed(g, CORNERS.edges), ring, with_components=True)
    assert comps.shape == (4, 2)
    shift = np.array([1.6, 0.9])
    moved = Ellipse(
        cx=ring.cx + shift[0], cy=ring.cy + shift[1], a=ring.a, b=ring.b, theta=ring.theta
    )
    blobs = BLOBS.copy()
    blobs[:, :2] += shift
    g2, g28 = _draw(truth + shift, moved, blobs=blobs)
    _, comps2 = tracker.update(g2, g28, smoothed(g2, CORNERS.edges), moved, True)
    assert comps2.shape == (4, 2)
    d = np.linalg.norm(comps2[:, None] - blobs[None, :, :2], axis=2)
    assert sorted(d.argmin(axis=1)) == [0, 1, 2, 3]
    assert d.min(axis=1).max() < 0.1


def test_components_are_searched_on_the_frame_after_reset(scene) -> None:  # type: ignore[no-untyped-def]
    """`reset` forgets the tracks so that the next frame acquires afresh (the pipeline resets
    the panel trackers whenever the ring is lost): that frame must search for components as
    a fresh tracker's first frame does."""
    _, ring, g, g8 = scene
    image_s = smoothed(g, CORNERS.edges)
    tracker = PanelTracker(CORNERS, COMPONENTS)
    for _ in range(2):
        assert tracker.update(g, g8, image_s, ring, with_components=True)[1].shape == (4, 2)
    tracker.reset()
    _, comps = tracker.update(g, g8, image_s, ring, with_components=True)
    assert comps.shape == (4, 2)
