"""Stereo pairing, triangulation and track ids of point landmarks (satpose.frontend.landmarks).

Detections are synthetic: known 3-D points projected through a known rig. For Lucas-Kanade the
images are a smoothed random texture (seeded), moved by whole pixels, so that the carried
track positions are known exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3
from satpose.frontend.landmarks import LandmarkConfig, LandmarkTracker, stereo_pairs
from satpose.frontend.measurements import LandmarkKind
from satpose.frontend.stereo import StereoRig

W, H, F, BASE_M = 640, 480, 800.0, 0.3
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RECTIFIED = StereoRig(
    K_left=K, K_right=K, right_from_left=Rigid3(R=np.eye(3), t=np.array([-BASE_M, 0.0, 0.0]))
)
"""Parallel cameras, the right one 0.3 m to the right: epipolar lines are image rows."""
VERGED = StereoRig(
    K_left=K,
    K_right=K,
    right_from_left=Rigid3.from_rotvec([0.01, -0.04, 0.02], [-BASE_M, 0.01, 0.005]),
)
"""A rig with rotation and an offset: epipolar lines are not rows."""
CONFIG = LandmarkConfig()
CORNER, COMPONENT = LandmarkKind.CORNER, LandmarkKind.COMPONENT


def _points(rng: np.random.Generator, n: int, z: tuple[float, float] = (3.0, 8.0)) -> np.ndarray:
    """n points (n, 3) in the left frame whose projections fall well inside both images."""
    depth = rng.uniform(*z, n)
    px = np.c_[rng.uniform(80, W - 80, n), rng.uniform(60, H - 60, n)]
    return np.c_[(px - K[:2, 2]) / F * depth[:, None], depth]


def _texture(seed: int, pad: int = 40) -> np.ndarray:
    """A smoothed random texture (H + 2 pad, W + 2 pad), uint8: a good image for LK."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((H + 2 * pad, W + 2 * pad)).astype(np.float32), (0, 0), 2.0)
    t = (t - t.min()) / (t.max() - t.min())
    return np.round(255 * t).astype(np.uint8)


def _view(tex: np.ndarray, shift: tuple[int, int], pad: int = 40) -> np.ndarray:
    """The texture seen moved by ``shift`` = (dx, dy) whole pixels."""
    dx, dy = shift
    return np.ascontiguousarray(tex[pad - dy : pad - dy + H, pad - dx : pad - dx + W])


@pytest.fixture(scope="module")
def textures() -> tuple[np.ndarray, np.ndarray]:
    """Left and right textures (padded by 40 px for moved views)."""
    return _texture(1), _texture(2)


@pytest.fixture(scope="module")
def images(textures) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Left and right images (H, W) of the textures, not moved."""
    return _view(textures[0], (0, 0)), _view(textures[1], (0, 0))


def _jacobian_rectified(X: np.ndarray) -> np.ndarray:
    """d(x_l, y_l, x_r, y_r) / d(X, Y, Z) for the rectified rig (closed form)."""
    x, y, z = X
    return (
        np.array(
            [
                [1 / z, 0, -x / z**2],
                [0, 1 / z, -y / z**2],
                [1 / z, 0, -(x - BASE_M) / z**2],
                [0, 1 / z, -y / z**2],
            ]
        )
        * F
    )


def test_stereo_pairs_recover_the_true_pairing() -> None:
    """Noise-free, 40 points at 3-8 m, right points shuffled, on a verged rig: every left point
    is paired with its own right point (distance to its epipolar line ~1e-12 px; every wrong
    candidate is farther, so the closest-first greedy takes the true pairs first)."""
    rng = np.random.default_rng(0)
    X = _points(rng, 40)
    left, right = VERGED.project(X)
    perm = rng.permutation(40)
    pairs = stereo_pairs(VERGED, left, right[perm], CONFIG, None)
    assert len(pairs) == 40
    inverse = np.argsort(perm)
    assert all(j == inverse[i] for i, j in pairs)


def test_stereo_pairs_gates() -> None:
    """The gates, each on its boundary (rectified rig: the epipolar distance is the row
    difference, depth z = f b / disparity):
    - a right point 1.9 px off its row is paired, 2.1 px is not (max_epipolar_px = 2);
    - with the ring at 5 m, a point at 6.4 m is paired and one at 6.6 m is not (1.5 m);
    - without the ring depth, 0.3-100 m: 0.29 m and 101 m are not paired, nor a point behind
      the cameras (negative disparity);
    - each point is used once: two left points on one right point's row, the closer to the
      line wins;
    - no points on either side, or NaN rows: no pairs (no exception)."""

    def one(z: float, dy: float = 0.0, ring: float | None = None) -> list[tuple[int, int]]:
        left, right = RECTIFIED.project(np.array([[0.2, -0.1, z]]))
        return stereo_pairs(RECTIFIED, left, right + np.array([0.0, dy]), CONFIG, ring)

    assert one(5.0, dy=1.9) == [(0, 0)]
    assert one(5.0, dy=2.1) == []
    assert one(6.4, ring=5.0) == [(0, 0)]
    assert one(6.6, ring=5.0) == []
    assert one(0.31) == [(0, 0)] and one(0.29) == []
    assert one(99.0) == [(0, 0)] and one(101.0) == []
    assert one(-5.0) == []
    left = np.array([[300.0, 200.0], [310.0, 200.8]])
    right = np.array([[250.0, 200.3]])
    assert stereo_pairs(RECTIFIED, left, right, CONFIG, None) == [(0, 0)]
    assert stereo_pairs(RECTIFIED, left[::-1], right, CONFIG, None) == [(1, 0)]
    assert stereo_pairs(RECTIFIED, np.zeros((0, 2)), right, CONFIG, None) == []
    assert stereo_pairs(RECTIFIED, left, np.zeros((0, 2)), CONFIG, None) == []
    nan_left = np.array([[np.nan, 200.0], [300.0, 200.0]])
    assert stereo_pairs(RECTIFIED, nan_left, right, CONFIG, None) == [(1, 0)]


def _by_point(out, left: np.ndarray) -> dict[int, object]:  # type: ignore[no-untyped-def]
    """Measurements keyed by the index of the detection (left pixel) they are of (the order
    of measurements is that of the stereo pairs, closest to the epipolar line first)."""
    got = {}
    for m in out:
        d = np.linalg.norm(left - m.left_px, axis=1)
        assert d.min() < 1e-9
        got[int(d.argmin())] = m
    return got


def test_first_frame_measurements_are_exact(images) -> None:  # type: ignore[no-untyped-def]
    """Noise-free corners and components on the rectified rig: one measurement per point,
    new ids ``first_id`` .. ``first_id + 5``, each point's kind and its sigma_px, the
    triangulated point equal to the truth (1e-9 m), and the covariance equal to the closed form
    ``sigma^2 (J^T J)^-1`` of the rectified rig's projection Jacobian (1e-6 relative: the
    refined point differs from the truth by round-off only)."""
    rng = np.random.default_rng(1)
    X = _points(rng, 6, z=(4.0, 6.0))
    X[:, 1] = np.linspace(-0.8, 0.8, 6)  # distinct rows: no pairing ambiguity
    left, right = RECTIFIED.project(X)
    tracker = LandmarkTracker(RECTIFIED, first_id=100)
    det = [(CORNER, left[:4], right[:4]), (COMPONENT, left[4:], right[4:])]
    out = tracker.update(*images, det)
    assert sorted(m.track_id for m in out) == list(range(100, 106))
    got = _by_point(out, left)
    assert sorted(got) == list(range(6))
    for k, m in got.items():
        assert m.kind == (CORNER if k < 4 else COMPONENT)
        sigma = CONFIG.sigma_px[m.kind.value]
        assert m.sigma_px == sigma
        np.testing.assert_allclose(m.right_px, right[k], atol=1e-12)
        np.testing.assert_allclose(m.point_m, X[k], atol=1e-9)
        J = _jacobian_rectified(X[k])
        np.testing.assert_allclose(
            m.covariance, sigma**2 * np.linalg.inv(J.T @ J), rtol=1e-6, atol=0
        )


def test_noisy_points_are_consistent_with_their_covariance(images) -> None:  # type: ignore[no-untyped-def]
    """Pixel noise at the corner sigma (0.3 px) on both images, 40 points at 3-8 m on rows
    10 px apart (no mispairing: a wrong row is > 20 sigma away), 10 seeds: the NEES of the
    400 triangulated points against the truth with their reported covariance is chi2(3):
    mean 3 within 3 sigma of the mean of 400 draws, 3 * sqrt(6 / 400) = 0.37. No point is lost
    (a true pair leaves the 2 px epipolar gate, 4.7 sigma of the row difference, with
    probability ~3e-6)."""
    sigma = CONFIG.sigma_px["corner"]
    nees = []
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        X = _points(rng, 40)
        rows = 40 + 10 * rng.permutation(40)
        X[:, :2] = (np.c_[X[:, 0] / X[:, 2] * F + K[0, 2], rows] - K[:2, 2]) / F * X[:, 2:]
        left, right = RECTIFIED.project(X)
        left = left + rng.normal(0, sigma, left.shape)
        right = right + rng.normal(0, sigma, right.shape)
        out = LandmarkTracker(RECTIFIED).update(*images, [(CORNER, left, right)])
        assert len(out) == 40
        for m in out:
            k = int(np.argmin(np.linalg.norm(left - m.left_px, axis=1)))
            d = m.point_m - X[k]
            nees.append(float(d @ np.linalg.solve(m.covariance, d)))
    assert abs(np.mean(nees) - 3.0) < 3 * np.sqrt(6 / len(nees))


def _frame(X: np.ndarray, shift: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Left and right pixels of points X moved by ``shift`` px in both images (the rectified
    rig keeps rows and disparities: still a valid stereo pair)."""
    left, right = RECTIFIED.project(X)
    return left + shift, right + shift


def test_tracks_follow_the_image_motion(textures) -> None:  # type: ignore[no-untyped-def]
    """Frame 2 moves both images and all detections by (3, -2) px: Lucas-Kanade carries each
    track onto its detection, so every landmark keeps its id and kind; a new corner gets the
    next id (5). Ids are per kind: in frame 3 a component at a corner's place gets a new id
    (6) and that corner is not reported."""
    tex_l, tex_r = textures
    X = _points(np.random.default_rng(2), 5, z=(4.0, 6.0))
    X[:, 1] = np.linspace(-0.6, 0.6, 5)
    tracker = LandmarkTracker(RECTIFIED)
    l1, r1 = _frame(X, (0, 0))
    out1 = tracker.update(_view(tex_l, (0, 0)), _view(tex_r, (0, 0)), [(CORNER, l1, r1)])
    id1 = {k: m.track_id for k, m in _by_point(out1, l1).items()}
    assert sorted(id1.values()) == [0, 1, 2, 3, 4]
    shift = (3, -2)
    l2, r2 = _frame(np.r_[X, [[0.9, 0.9, 5.0]]], shift)
    out2 = tracker.update(_view(tex_l, shift), _view(tex_r, shift), [(CORNER, l2, r2)])
    id2 = {k: m.track_id for k, m in _by_point(out2, l2).items()}
    assert id2 == {**id1, 5: 5}
    l3, r3 = l2[:5], r2[:5]
    det = [(CORNER, l3[1:], r3[1:]), (COMPONENT, l3[:1], r3[:1])]
    out3 = tracker.update(_view(tex_l, shift), _view(tex_r, shift), det)
    got = _by_point(out3, l3)
    assert {k: m.track_id for k, m in got.items() if k > 0} == {k: id1[k] for k in range(1, 5)}
    assert got[0].kind == COMPONENT and got[0].track_id == 6


@pytest.mark.parametrize(("offset_px", "same"), [(5.5, True), (6.5, False)])
def test_association_gate(images, offset_px: float, same: bool) -> None:  # type: ignore[no-untyped-def]
    """Static images, the detection moved by ``offset_px`` along its row in both images: the
    summed left + right distance to the carried track, 2 * offset, is within ``2 * gate_px``
    (12 px) at 5.5 px and the id continues; at 6.5 px it starts a new track."""
    X = np.array([[0.1, 0.05, 5.0]])
    tracker = LandmarkTracker(RECTIFIED)
    l1, r1 = _frame(X, (0, 0))
    assert tracker.update(*images, [(CORNER, l1, r1)])[0].track_id == 0
    off = np.array([offset_px, 0.0])
    out = tracker.update(*images, [(CORNER, l1 + off, r1 + off)])
    assert (out[0].track_id == 0) is same


@pytest.mark.parametrize(("gap", "same"), [(2, True), (3, False)])
def test_missed_frames(images, gap: int, same: bool) -> None:  # type: ignore[no-untyped-def]
    """A track missed for ``gap`` frames (another landmark seen meanwhile): kept through
    max_missed = 2 frames, so it continues after a 2-frame gap; after 3 it was dropped and the
    point gets a new id (ids are never reused)."""
    X = np.array([[0.1, 0.05, 5.0], [-0.4, -0.3, 5.5]])
    left, right = _frame(X, (0, 0))
    tracker = LandmarkTracker(RECTIFIED)
    tracker.update(*images, [(CORNER, left, right)])
    for _ in range(gap):
        (m,) = tracker.update(*images, [(CORNER, left[1:], right[1:])])
        assert m.track_id == 1
    ids = sorted(m.track_id for m in tracker.update(*images, [(CORNER, left, right)]))
    assert ids == ([0, 1] if same else [1, 2])


def test_reidentification_after_reset_by_prediction(images) -> None:  # type: ignore[no-untyped-def]
    """After `reset` (tracks forgotten), a detection within 2 * gate_px of a known landmark's
    predicted pixels takes its id back, but only for the landmark's own kind; a prediction
    farther away, or of another kind, leaves a new id. `rename` gives a track an old id."""
    X = np.array([[0.1, 0.05, 5.0], [-0.4, -0.3, 5.5]])
    left, right = _frame(X, (0, 0))
    tracker = LandmarkTracker(RECTIFIED)
    assert [m.track_id for m in tracker.update(*images, [(CORNER, left, right)])] == [0, 1]
    tracker.reset()
    d = np.array([4.0, 0.0])  # 8 px summed: within 12
    predicted = {0: (left[0] + d, right[0] + d), 1: (left[1] + 4 * d, right[1] + 4 * d)}
    out = tracker.update(*images, [(CORNER, left, right)], predicted=predicted)
    assert [m.track_id for m in out] == [0, 2]  # 1 predicted 32 px off: a new id
    tracker.reset()
    out = tracker.update(*images, [(COMPONENT, left[:1], right[:1])], predicted=predicted)
    assert [m.track_id for m in out] == [3]  # id 0 is a corner
    tracker.rename({3: 1})  # re-identified elsewhere as landmark 1 (not tracked now)
    assert set(tracker.tracks) == {1}
    out = tracker.update(*images, [(COMPONENT, left[:1], right[:1])])
    assert [m.track_id for m in out] == [1]


def test_bad_detections_are_skipped(images) -> None:  # type: ignore[no-untyped-def]
    """NaN pixels, an empty kind, and a left point without a right partner give no measurement
    and no exception; the good point is still measured."""
    X = np.array([[0.1, 0.05, 5.0]])
    left, right = _frame(X, (0, 0))
    tracker = LandmarkTracker(RECTIFIED)
    bad_left = np.r_[left, [[np.nan, 100.0]], [[50.0, 400.0]]]
    out = tracker.update(
        *images,
        [
            (CORNER, bad_left, np.r_[right, [[np.nan, np.nan]]]),
            (COMPONENT, np.zeros((0, 2)), right),
        ],
    )
    assert len(out) == 1 and out[0].track_id == 0
    np.testing.assert_allclose(out[0].point_m, X[0], atol=1e-9)
    assert tracker.update(*images, []) == []
