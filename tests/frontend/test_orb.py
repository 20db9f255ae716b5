"""ORB landmarks, EPnP + RANSAC and the eq. 10 fusion (satpose.frontend.orb).

The ORB tests look at a textured plane (random rectangles and disks, seeded) at ~3 m, drawn
into both images of a verged stereo rig by the plane's exact homography: every feature lies on
a known plane. The EPnP tests use synthetic 3-D points projected with a known pose.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from satpose.datasets.geometry import Rigid3, matrix_to_rotvec, rotation_angle
from satpose.frontend.conics import Ellipse
from satpose.frontend.orb import (
    ORB_FIRST_ID,
    OrbConfig,
    OrbTracker,
    _epipolar_distance,
    _image_motion,
    epnp_ransac,
    pose_eq10,
)
from satpose.frontend.stereo import StereoRig

W, H, F = 640, 480, 800.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
RIG = StereoRig(
    K_left=K, K_right=K, right_from_left=Rigid3.from_rotvec([0.0, -0.03, 0.0], [-0.3, 0.0, 0.0])
)
CONFIG = OrbConfig()
CAM_FROM_PLANE = Rigid3.from_rotvec([0.2, -0.3, 0.05], [0.05, 0.0, 3.0])
"""The textured plane (z = 0 of its frame) in the left camera: 1.5 m square at ~3 m."""
TEX, M_PER_TEXEL = 1000, 0.0015


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.full((TEX, TEX), 140, np.uint8)
    for _ in range(500):
        x, y = (int(v) for v in rng.integers(0, TEX, 2))
        w, h = (int(v) for v in rng.integers(8, 40, 2))
        level = int(rng.integers(20, 250))
        if rng.random() < 0.5:
            cv2.rectangle(t, (x, y), (x + w, y + h), level, -1)
        else:
            cv2.circle(t, (x, y), w // 2, level, -1)
    return cv2.GaussianBlur(t, (0, 0), 1.0)


def _view(tex: np.ndarray, cam_from_plane: Rigid3) -> np.ndarray:
    """The plane seen by a camera with intrinsics K: the homography K [r1 r2 t] A, A mapping
    texels to plane metres; black space around it."""
    c = M_PER_TEXEL * (TEX - 1) / 2
    A = np.array([[M_PER_TEXEL, 0, -c], [0, M_PER_TEXEL, -c], [0, 0, 1]])
    Hm = K @ np.c_[cam_from_plane.R[:, :2], cam_from_plane.t] @ A
    return cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)


@pytest.fixture(scope="module")
def stereo() -> tuple[np.ndarray, np.ndarray]:
    tex = _texture(0)
    return _view(tex, CAM_FROM_PLANE), _view(tex, RIG.right_from_left @ CAM_FROM_PLANE)


def _plane_offsets(out) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Signed distance [m] of each landmark's point from the plane and its reported sigma."""
    n = CAM_FROM_PLANE.R[:, 2]
    d = np.array([n @ m.point_m - n @ CAM_FROM_PLANE.t for m in out])
    s = np.array([math.sqrt(n @ m.covariance @ n) for m in out])
    return d, s


def test_stereo_landmarks_lie_on_the_plane(stereo) -> None:  # type: ignore[no-untyped-def]
    """Every ORB landmark: kind orb, sigma_px of the orb kind, a right pixel within the 2 px
    epipolar gate, new unique ids from ORB_FIRST_ID, and its 3-D point on the plane within
    its reported uncertainty. Keypoints sit on a pyramid grid (not sub-pixel), the reported
    0.8 px is meant to cover that: the normalised distances d / sigma must not exceed 5 (a
    mismatched pair is off by its wrong disparity: metres), and their mean square is at most 1
    (the reported covariance is not optimistic; measured 0.45 and max 4.0 over 419 landmarks)."""
    left, right = stereo
    out = OrbTracker(RIG).update(left, right, None, None, None)
    assert len(out) >= 100  # measured 419 of 500 features
    ids = [m.track_id for m in out]
    assert sorted(ids) == list(range(ORB_FIRST_ID, ORB_FIRST_ID + len(out)))
    assert all(
        m.kind.value == "orb" and m.sigma_px == CONFIG.landmarks.sigma_px["orb"] for m in out
    )
    L = np.array([m.left_px for m in out])
    R = np.array([m.right_px for m in out])
    assert np.all(_epipolar_distance(RIG, L, R) < CONFIG.landmarks.max_epipolar_px)
    d, s = _plane_offsets(out)
    z = d / s
    assert np.abs(z).max() < 5.0
    assert np.mean(z**2) <= 1.0


def test_epipolar_distance_is_the_rigs() -> None:
    """The per-pair epipolar distance equals the diagonal of the rig's all-pairs one (1e-9
    px), and is the row difference for parallel cameras."""
    rng = np.random.default_rng(0)
    L = rng.uniform(0, 640, (20, 2))
    R = rng.uniform(0, 640, (20, 2))
    np.testing.assert_allclose(
        _epipolar_distance(RIG, L, R), np.diag(RIG.epipolar_distance(L, R)), atol=1e-9
    )
    parallel = StereoRig(K_left=K, K_right=K, right_from_left=Rigid3(t=np.array([-0.3, 0, 0])))
    np.testing.assert_allclose(_epipolar_distance(parallel, L, R), np.abs(L[:, 1] - R[:, 1]))


def test_track_ids_follow_features_near_their_prediction(stereo) -> None:  # type: ignore[no-untyped-def]
    """Frame to frame: the same images again keep every id. Both images moved 30 px right (beyond
    gate_px = 20): with the caller's prediction of the move, and without one (the image motion
    that the descriptor matches agree on predicts it, `_image_motion`), at least 80 % keep their
    id (measured 87 %: the moved view loses and gains features at the border, and the ratio test
    drops look-alikes), each the same feature: within 4 px of its old pixel + 30 px, far inside
    the 20 px gate (keypoints of the coarser pyramid levels lie on a 1.2^k px grid, up to 1.73
    px, that a 30 px move does not map onto itself; frame to frame measured max 2.35 px; with
    re-identification, which also searches within 8 px of the prediction, 13 more of 340
    features keep their id and one lands 3.67 px off: a neighbouring keypoint one pyramid level
    coarser, closer in descriptor than the one at the prediction). Another texture keeps almost
    no id (chance look-alikes within the gate: measured 2 of 312, bound 2 %), and ids are never
    reused. Ids stay unique."""
    left, right = stereo
    shift = np.float32([[1, 0, 30], [0, 1, 0]])
    left2, right2 = (cv2.warpAffine(im, shift, (W, H)) for im in (left, right))
    tracker = OrbTracker(RIG)
    first = tracker.update(left, right, None, None, None)
    again = tracker.update(left, right, None, None, None)
    assert {m.track_id for m in again} == {m.track_id for m in first}
    for with_prediction in (False, True):
        tracker = OrbTracker(RIG)
        first = tracker.update(left, right, None, None, None)
        old = {m.track_id: m.left_px for m in first}
        predicted = (
            {tid: px + np.array([30.0, 0.0]) for tid, px in old.items()}
            if with_prediction
            else None
        )
        moved = tracker.update(left2, right2, None, None, None, predicted)
        kept = [m for m in moved if m.track_id in old]
        assert len(kept) >= 0.8 * len(moved), with_prediction
        for m in kept:
            assert np.linalg.norm(m.left_px - (old[m.track_id] + [30.0, 0.0])) < 4.0
        assert len({m.track_id for m in moved}) == len(moved)
    tex = _texture(1)
    other = tracker.update(
        _view(tex, CAM_FROM_PLANE),
        _view(tex, RIG.right_from_left @ CAM_FROM_PLANE),
        None,
        None,
        None,
    )
    assert len(other) >= 20
    carried = sum(m.track_id in {k.track_id for k in moved} for m in other)
    assert carried <= 0.02 * len(other), (carried, len(other))  # chance look-alikes: 2 of 312
    new = [m.track_id for m in other if m.track_id not in {k.track_id for k in moved}]
    assert min(new) > max(m.track_id for m in moved)  # ids are never reused


def test_image_motion_is_the_similarity_most_matches_agree_on() -> None:
    """`_image_motion`: 40 points moved by a similarity (rotation 8 deg, scale 1.05, shift
    (25, -12) px) with 0.3 px noise, and 15 outliers anywhere: the transform is recovered
    (every inlier mapped within 1 px, measured 0.6 px); with fewer than 6 pairs, None."""
    rng = np.random.default_rng(3)
    src = rng.uniform(0, 500, (55, 2))
    c, s = 1.05 * math.cos(math.radians(8)), 1.05 * math.sin(math.radians(8))
    dst = src @ np.array([[c, s], [-s, c]]) + [25.0, -12.0]
    dst[:40] += rng.normal(0.0, 0.3, (40, 2))
    dst[40:] = rng.uniform(0, 500, (15, 2))
    motion = _image_motion(src, dst, 3.0, 200)
    assert motion is not None
    truth = src[:40] @ np.array([[c, s], [-s, c]]) + [25.0, -12.0]
    assert np.abs(motion(src[:40]) - truth).max() < 1.0
    assert _image_motion(src[:5], dst[:5], 3.0, 200) is None


def test_features_are_masked_by_the_ring_and_the_dark(stereo) -> None:  # type: ignore[no-untyped-def]
    """With ring ellipses given, features lie within max_extent semi-major axes of the ring
    centre and outside 1.15 x its ellipse (the rim's symmetric edges match anywhere), in both
    images; none on black space (grey <= 8)."""
    left, right = stereo
    rings = {
        "left": Ellipse(cx=330.0, cy=250.0, a=40.0, b=30.0, theta=0.3),
        "right": Ellipse(cx=230.0, cy=252.0, a=40.0, b=30.0, theta=0.3),
    }
    out = OrbTracker(RIG).update(left, right, rings["left"], rings["right"], None)
    assert len(out) >= 20
    for side, img in (("left", left), ("right", right)):
        e = rings[side]
        P = np.array([getattr(m, f"{side}_px") for m in out])
        c, s = math.cos(e.theta), math.sin(e.theta)
        u = c * (P[:, 0] - e.cx) + s * (P[:, 1] - e.cy)
        v = -s * (P[:, 0] - e.cx) + c * (P[:, 1] - e.cy)
        assert np.all(np.hypot(u / (1.15 * e.a), v / (1.15 * e.b)) > 1.0 - 0.02)
        assert np.all(np.hypot(P[:, 0] - e.cx, P[:, 1] - e.cy) < CONFIG.max_extent * e.a + 1)
        assert np.all(img[np.round(P[:, 1]).astype(int), np.round(P[:, 0]).astype(int)] > 8)


def test_refusals_give_no_landmarks_and_forget_tracks(stereo) -> None:  # type: ignore[no-untyped-def]
    """A black pair, and a ring depth 3 m behind the plane (every pair fails the 1.5 m depth
    gate), give no landmarks and the tracker forgets its tracks: the next frame's ids are all
    new."""
    left, right = stereo
    tracker = OrbTracker(RIG)
    first = tracker.update(left, right, None, None, ring_depth_m=3.0)
    assert len(first) >= 100  # the plane is at 2.8-3.2 m: the gate passes them
    dark = np.zeros_like(left)
    assert tracker.update(dark, dark, None, None, None) == [] and tracker.tracks == []
    again = tracker.update(left, right, None, None, None)
    assert min(m.track_id for m in again) > max(m.track_id for m in first)
    assert tracker.update(left, right, None, None, ring_depth_m=6.0) == []
    assert tracker.tracks == []


def test_features_that_came_back_keep_their_ids_by_projection(stereo) -> None:  # type: ignore[no-untyped-def]
    """Re-identification (`OrbConfig.reidentify`): frame 1 sees the plane, frame 2 is black (the
    tracker forgets its frame-to-frame tracks), frame 3 sees the plane again moved 30 px. Told
    where the earlier tracks should be (their old pixel + 30 px, as the pipeline predicts the
    mapped ones), at least 80 % of frame 3's features take back their frame-1 id (the frame-to-
    frame test's bound: border features and look-alikes), each within 4 px of where it was
    predicted (the frame-to-frame test's bound). Without predictions, or with ``reidentify =
    False``, every id is new. A different texture at the same predictions takes back at most 2 %
    (chance look-alikes within the gate: the frame-to-frame test's bound)."""
    left, right = stereo
    shift = np.float32([[1, 0, 30], [0, 1, 0]])
    left2, right2 = (cv2.warpAffine(im, shift, (W, H)) for im in (left, right))
    dark = np.zeros_like(left)
    tex = _texture(1)
    other = tuple(
        cv2.warpAffine(_view(tex, T), shift, (W, H))
        for T in (CAM_FROM_PLANE, RIG.right_from_left @ CAM_FROM_PLANE)
    )
    for reidentify, with_prediction, images in (
        (True, True, (left2, right2)),
        (True, False, (left2, right2)),
        (False, True, (left2, right2)),
        (True, True, other),
    ):
        tracker = OrbTracker(RIG, OrbConfig(reidentify=reidentify))
        first = tracker.update(left, right, None, None, None)
        old = {m.track_id: m.left_px for m in first}
        assert tracker.update(dark, dark, None, None, None) == [] and tracker.tracks == []
        predicted = (
            {tid: px + np.array([30.0, 0.0]) for tid, px in old.items()}
            if with_prediction
            else None
        )
        back = tracker.update(*images, None, None, None, predicted)
        assert len(back) >= 100
        kept = [m for m in back if m.track_id in old]
        assert len({m.track_id for m in back}) == len(back)
        if images is other:
            assert len(kept) <= 0.02 * len(back), (len(kept), len(back))
        elif reidentify and with_prediction:
            assert len(kept) >= 0.8 * len(back), (len(kept), len(back))
            for m in kept:
                assert np.linalg.norm(m.left_px - (old[m.track_id] + [30.0, 0.0])) < 4.0
        else:
            assert kept == []


CAM_FROM_TARGET = Rigid3.from_rotvec([0.3, -0.5, 0.2], [0.1, -0.2, 3.0])


def _project(T: Rigid3, X: np.ndarray) -> np.ndarray:
    x = (X @ T.R.T + T.t) @ K.T
    return x[:, :2] / x[:, 2:]


def _target_points(seed: int, n: int = 40, depth_m: float = 0.3) -> np.ndarray:
    """n points in a 1.2 m box of ``depth_m`` in the target frame."""
    return np.random.default_rng(seed).uniform(-0.6, 0.6, (n, 3)) * [1, 1, depth_m / 1.2]


@pytest.mark.parametrize("depth_m", [0.3, 0.0])
def test_epnp_is_exact_without_noise(depth_m: float) -> None:
    """Noise-free, 40 points (a box, and a plane): the pose to 1e-4 deg and 1e-6 m (EPnP is
    closed form up to its Gauss-Newton on the control-point weights; measured 3.5e-6 deg
    (box) and 1.0e-5 deg (plane), 2e-8 m), every point an inlier."""
    P = _target_points(0, depth_m=depth_m)
    res = epnp_ransac(K, P, _project(CAM_FROM_TARGET, P), CONFIG)
    assert res is not None
    pose, inliers = res
    assert math.degrees(rotation_angle(pose.R @ CAM_FROM_TARGET.R.T)) < 1e-4
    assert np.linalg.norm(pose.t - CAM_FROM_TARGET.t) < 1e-6
    assert inliers.all()


def test_epnp_rejects_outliers_and_nan() -> None:
    """30 % of 40 points moved 20-60 px (far beyond ransac_px = 2) and one NaN pixel: the
    inlier mask is exactly the untouched points and the pose is exact (as above)."""
    rng = np.random.default_rng(1)
    P = _target_points(1)
    px = _project(CAM_FROM_TARGET, P)
    bad = rng.choice(40, 12, replace=False)
    angle = rng.uniform(0, 2 * np.pi, 12)
    px[bad] += rng.uniform(20, 60, 12)[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    good = np.setdiff1d(np.arange(40), bad)
    px[good[0]] = np.nan
    res = epnp_ransac(K, P, px, CONFIG)
    assert res is not None
    pose, inliers = res
    expected = np.zeros(40, bool)
    expected[good[1:]] = True
    np.testing.assert_array_equal(inliers, expected)
    assert math.degrees(rotation_angle(pose.R @ CAM_FROM_TARGET.R.T)) < 1e-4
    assert np.linalg.norm(pose.t - CAM_FROM_TARGET.t) < 1e-6


def _pose_information(P: np.ndarray, sigma_px: float) -> np.ndarray:
    """Fisher information of the pose (left-multiplied [rotation, translation] perturbation)
    from pixel noise sigma_px: J^T J / sigma^2, J by central differences (step 1e-6)."""
    J = np.zeros((2 * len(P), 6))
    for i in range(6):
        cols = []
        for h in (1e-6, -1e-6):
            d = np.zeros(6)
            d[i] = h
            dT = Rigid3.from_rotvec(d[:3], d[3:])
            cols.append(_project(dT @ CAM_FROM_TARGET, P).ravel())
        J[:, i] = (cols[0] - cols[1]) / 2e-6
    return J.T @ J / sigma_px**2


def test_epnp_noisy_pose_against_the_cramer_rao_bound() -> None:
    """Pixel noise 0.5 px on 40 points, 50 seeds. The squared pose error weighted by the
    Fisher information (NEES against the Cramer-Rao bound) has mean >= 6 for any unbiased
    estimator and = 6 for the maximum-likelihood one; EPnP without refinement is not the ML
    estimate (measured mean 8.2). Bounds: mean of the 50 above 6 - 3 sqrt(12 / 50) = 4.5 (it
    cannot beat the bound) and below 2 x 6 (within twice the bound's variance)."""
    nees = []
    for seed in range(50):
        rng = np.random.default_rng(seed)
        P = _target_points(seed)
        px = _project(CAM_FROM_TARGET, P) + rng.normal(0, 0.5, (40, 2))
        res = epnp_ransac(K, P, px, CONFIG)
        assert res is not None
        pose, _ = res
        dR = pose.R @ CAM_FROM_TARGET.R.T
        e = np.r_[matrix_to_rotvec(dR), pose.t - dR @ CAM_FROM_TARGET.t]
        nees.append(float(e @ _pose_information(P, 0.5) @ e))
    assert 6 - 3 * math.sqrt(12 / 50) < np.mean(nees) < 12.0


def test_epnp_refuses_too_few_or_inconsistent_points() -> None:
    """None, not an exception: fewer points than max(6, min_inliers = 8); 40 points at random
    pixels (no pose explains 8 of them to 2 px)."""
    P = _target_points(2)
    assert epnp_ransac(K, P[:7], _project(CAM_FROM_TARGET, P[:7]), CONFIG) is None
    rng = np.random.default_rng(2)
    assert epnp_ransac(K, P, rng.uniform(0, [W, H], (40, 2)), CONFIG) is None


def test_eq10_fusion() -> None:
    """Seed 000 eq. 10: with the ring normal equal to the PnP z axis and the ring centre at
    the PnP origin, the fusion returns the PnP pose (1e-12). With the normal tilted by 20 deg
    about the PnP x axis and the centre 4 cm off, z is the bisector (10 deg from each, 1e-9),
    x stays the PnP x, the result is a rotation, t the midpoint; the inputs are not changed."""
    pnp = CAM_FROM_TARGET
    same = pose_eq10(pnp.t.copy(), pnp.R[:, 2].copy(), pnp)
    np.testing.assert_allclose(same.R, pnp.R, atol=1e-12)
    np.testing.assert_allclose(same.t, pnp.t, atol=1e-12)
    tilt = Rigid3.from_rotvec(math.radians(20.0) * pnp.R[:, 0], np.zeros(3))
    normal = tilt.R @ pnp.R[:, 2]
    centre = pnp.t + np.array([0.04, 0.0, 0.0])
    n0, c0 = normal.copy(), centre.copy()
    fused = pose_eq10(centre, normal, pnp)
    z = fused.R[:, 2]
    assert abs(math.degrees(math.acos(np.clip(z @ normal, -1, 1))) - 10.0) < 1e-9
    assert abs(math.degrees(math.acos(np.clip(z @ pnp.R[:, 2], -1, 1))) - 10.0) < 1e-9
    np.testing.assert_allclose(fused.R[:, 0], pnp.R[:, 0], atol=1e-12)
    np.testing.assert_allclose(fused.t, 0.5 * (centre + pnp.t), atol=1e-15)
    np.testing.assert_array_equal(normal, n0)
    np.testing.assert_array_equal(centre, c0)


def test_each_right_feature_serves_one_landmark(stereo) -> None:  # type: ignore[no-untyped-def]
    """A right keypoint is the partner of at most one left keypoint: the same corner found at
    two pyramid levels of the left image (0-5 px apart) must not become two landmarks sharing
    one right observation. Landmarks are compared by right pixel, and two distinct right
    keypoints can sit on one pixel (two pyramid levels: 1 of the 500 here), so up to 1 % may
    share one (with cross-checked matches: 2 of 339)."""
    left, right = stereo
    out = OrbTracker(RIG).update(left, right, None, None, None)
    _, counts = np.unique(np.array([m.right_px for m in out]), axis=0, return_counts=True)
    assert counts[counts > 1].sum() <= 0.01 * len(out)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("consensus_px", 0.0),
        ("consensus_px", math.nan),
        ("consensus_iterations", 0),
        ("reidentify_px", 0.0),
        ("reidentify_px", math.inf),
        ("library_size", -1),
    ],
)
def test_image_motion_settings_are_checked(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"orb.{field}"):
        OrbConfig(**{field: value})  # type: ignore[arg-type]
