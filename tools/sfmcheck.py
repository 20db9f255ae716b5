"""Structure-from-motion check of a trajectory with pycolmap.

A static stereo rig watching a spinning target sees what a rig orbiting a static target would
see, so COLMAP's incremental mapper reconstructs the target and the rig poses in a world
frame glued to the target: ``left_cam_from_world`` per frame = ``left_cam_from_target`` up to
one fixed transform. The two cameras form a COLMAP rig with the calibrated, fixed
``right_from_left``, so the reconstruction is metric. Masks (the sequence's masks/ object ids)
keep features off the background and off parts that look alike from opposite sides (the two
solar wings and their brackets).

COLMAP can register every image with a small reprojection error and still be wrong (repeating
texture, symmetric parts), so the check reports COLMAP's own health and calls the
reconstruction ground truth only if it is consistent with itself:

- registered frames (fraction of the frames given), reprojection error, number of 3-D points
  and mean track length;
- **rig consistency**: each registered image is re-localised on its own (pycolmap absolute
  pose on its own 2-D/3-D correspondences); per frame, the right camera's pose relative to the
  left one must reproduce the calibrated ``right_from_left``. It bounds the per-frame pose
  noise from below and catches unsynchronised or mislabelled stereo pairs;
- **neighbour agreement**: the geometrically verified matches between images of consecutive
  frames (COLMAP's database) must be explained by the reconstruction: the 3-D point of one
  keypoint reprojects within ``neighbour_tolerance_px`` of its match. A reconstruction folded
  by a symmetry or repeated texture disagrees with its neighbours where it folds.

Then the reconstruction is aligned to the trajectory being checked (`align_poses`: SE(3), and
Sim(3) for the record) and the per-frame disagreement is reported. The alignment absorbs the
trajectory's own choice of target frame.

COLMAP conventions: pixel origin at the top-left corner of the top-left pixel (OpenCV's
origin + 0.5 px); ``cam_from_world``; the ``OPENCV`` camera model is OpenCV's k1, k2, p1, p2
(``FULL_OPENCV`` when k3 != 0, its k4..k6 set to 0).
"""

from __future__ import annotations

import itertools
import logging
import math
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.errors import ConfigError, SatposeError
from satpose.datasets.geometry import Rigid3, rotation_angle
from satpose.datasets.sequence import Sequence

log = logging.getLogger(__name__)

COLMAP_PIXEL_OFFSET = 0.5
"""COLMAP pixel coordinates minus OpenCV pixel coordinates [px]."""
TIME_MATCH_TOL_S = 1e-3
"""A trajectory time matches a frame time within this [s] (TUM files carry 9 decimals)."""
ALIGN_MAX_REFITS = 5
"""`align_poses` refits at most this often while its set of inlier frames changes."""


class SfmCheckError(SatposeError):
    """The structure-from-motion check cannot run (bad input, nothing reconstructed)."""


@dataclass(frozen=True, kw_only=True)
class SfmCheckConfig:
    """How `check_sfm` runs and when it refuses.

    Attributes:
        exclude_mask_ids: object ids of masks/ where no features are taken (0 background,
            5 brackets, 6 wings: the two wings and brackets look alike after a half turn).
            Ignored (and reported) when the sequence has no masks.
        mask_erode_px: shrink the kept region by this many pixels (features on a silhouette
            mix target and background).
        max_features: SIFT features per image.
        matching: ``sequential`` (each frame against the next ``overlap`` frames and, with
            quadratic overlap, frames 2^k apart) or ``exhaustive`` (all pairs; slow).
        overlap: sequential matching overlap [frames].
        first_frame, frame_step, max_frames: which frames to use (positions in the sequence).
        num_threads: COLMAP threads (-1: all cores).
        seed: COLMAP's random seed.
        min_registered_fraction: refuse if fewer frames are registered.
        max_reprojection_px: refuse above this mean reprojection error [px].
        min_points: refuse with fewer 3-D points.
        min_mean_track_length: refuse below this mean track length [images].
        max_rig_rotation_deg: refuse if the median per-frame rig consistency (rotation of the
            re-localised right_from_left against the calibration) exceeds this [deg].
        max_rig_translation_m: same for its translation [m].
        neighbour_tolerance_px: a verified match between consecutive frames agrees with the
            reconstruction if its 3-D point reprojects this close to the other keypoint [px].
        min_neighbour_agreement: refuse if any consecutive frame pair (with at least
            ``min_neighbour_matches`` verified matches) agrees less than this fraction.
        min_neighbour_matches: pairs with fewer verified matches are not judged.
        inlier_factor: the alignment is refitted on frames whose disagreement is below this
            multiple of the median (a trajectory's outliers must not drag the alignment).
    """

    exclude_mask_ids: tuple[int, ...] = (0, 5, 6)
    mask_erode_px: int = 3
    max_features: int = 2000
    matching: Literal["sequential", "exhaustive"] = "sequential"
    overlap: int = 5
    first_frame: int = 0
    frame_step: int = 1
    max_frames: int | None = None
    num_threads: int = -1
    seed: int = 0
    min_registered_fraction: float = 0.9
    max_reprojection_px: float = 1.0
    min_points: int = 200
    min_mean_track_length: float = 3.0
    max_rig_rotation_deg: float = 0.25
    max_rig_translation_m: float = 0.02
    neighbour_tolerance_px: float = 4.0
    min_neighbour_agreement: float = 0.8
    min_neighbour_matches: int = 20
    inlier_factor: float = 3.0

    def __post_init__(self) -> None:
        if any(not 0 <= i <= 255 for i in self.exclude_mask_ids):
            raise ConfigError("sfm check: exclude_mask_ids must be uint8 object ids")
        if self.mask_erode_px < 0 or self.max_features < 100 or self.overlap < 1:
            raise ConfigError(
                "sfm check: mask_erode_px >= 0, max_features >= 100, overlap >= 1 required"
            )
        if self.first_frame < 0 or self.frame_step < 1:
            raise ConfigError("sfm check: first_frame >= 0 and frame_step >= 1 required")
        if self.max_frames is not None and self.max_frames < 3:
            raise ConfigError("sfm check: max_frames must be >= 3")
        if not 0 < self.min_registered_fraction <= 1 or not 0 <= self.min_neighbour_agreement <= 1:
            raise ConfigError("sfm check: fractions must lie in [0, 1]")
        if self.inlier_factor <= 1:
            raise ConfigError("sfm check: inlier_factor must be > 1")


# --------------------------------------------------------------------------------------------
# Alignment (pure numpy)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Alignment:
    """``world_from_target`` taking COLMAP's world to the trajectory's target frame.

    ``left_cam_from_target ~ left_cam_from_world @ world_from_target``, with the COLMAP
    translation multiplied by ``scale`` (1 for SE(3)).

    Attributes:
        rotation: (3, 3) ``R`` of ``world_from_target``.
        translation: (3,) ``t`` of ``world_from_target`` in COLMAP units.
        scale: metres per COLMAP unit.
        used: (N,) bool, the frames the final fit used.
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    used: np.ndarray

    def apply(self, cam_from_world: Rigid3) -> Rigid3:
        """The aligned ``left_cam_from_target`` of one COLMAP ``left_cam_from_world`` [m]."""
        R = cam_from_world.R @ self.rotation
        t = self.scale * (cam_from_world.R @ self.translation + cam_from_world.t)
        return Rigid3(R=R, t=t)


def _fit(
    cw: list[Rigid3], ct: list[Rigid3], with_scale: bool
) -> tuple[np.ndarray, np.ndarray, float]:
    M = sum((a.R.T @ b.R for a, b in zip(cw, ct, strict=True)), np.zeros((3, 3)))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    if with_scale:
        # R_k u + s t_k = t_target_k, linear in (u, s); u = s t_A.
        A = np.vstack([np.c_[a.R, a.t] for a in cw])
        b = np.concatenate([p.t for p in ct])
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        s = float(x[3])
        if not s > 0:
            raise SfmCheckError("Sim(3) alignment gives a non-positive scale")
        return R, x[:3] / s, s
    u = np.mean([a.R.T @ (p.t - a.t) for a, p in zip(cw, ct, strict=True)], axis=0)
    return R, u, 1.0


def align_poses(
    cam_from_world: list[Rigid3],
    cam_from_target: list[Rigid3],
    *,
    with_scale: bool = False,
    inlier_factor: float | None = 3.0,
) -> Alignment:
    """Align COLMAP's ``left_cam_from_world`` to a trajectory's ``left_cam_from_target``.

    Closed form: the rotation of ``world_from_target`` is the Procrustes solution of
    ``R_world,k R ~ R_target,k`` (as `satpose.tools.metrics.body_rotation_offset`), the
    translation (and scale) the least-squares solution of the target origin's position in
    the camera frame. With ``inlier_factor``, the fit is repeated on the frames whose
    position and rotation disagreements are both below ``inlier_factor`` times their medians
    (plus 1 mm / 0.01 deg so that an exact fit keeps every frame), again until that set of
    frames stops changing (at most `ALIGN_MAX_REFITS` fits).

    Args:
        cam_from_world, cam_from_target: matched poses of the same N >= 3 frames.
    """
    if len(cam_from_world) != len(cam_from_target) or len(cam_from_world) < 3:
        raise SfmCheckError(
            f"alignment needs >= 3 matched frames, got {len(cam_from_world)}/{len(cam_from_target)}"
        )
    n = len(cam_from_world)
    used = np.ones(n, bool)
    R, t, s = _fit(cam_from_world, cam_from_target, with_scale)
    if inlier_factor is not None:
        # Refit until the inlier set stops changing: a gross outlier drags the first fit and
        # can hide a smaller one under the first threshold.
        for _ in range(ALIGN_MAX_REFITS):
            al = Alignment(rotation=R, translation=t, scale=s, used=used)
            pos, rot = pose_differences([al.apply(c) for c in cam_from_world], cam_from_target)
            inl = (pos <= inlier_factor * np.median(pos) + 1e-3) & (
                rot <= inlier_factor * np.median(rot) + 0.01
            )
            if inl.sum() < 3 or np.array_equal(inl, used):
                break
            used = inl
            sel = np.flatnonzero(used)
            R, t, s = _fit(
                [cam_from_world[i] for i in sel], [cam_from_target[i] for i in sel], with_scale
            )
    return Alignment(rotation=R, translation=t, scale=s, used=used)


def pose_differences(a: list[Rigid3], b: list[Rigid3]) -> tuple[np.ndarray, np.ndarray]:
    """Distances between the translations [m] and angles between the rotations [deg] of
    matched poses, (N,) each."""
    pos = np.array([np.linalg.norm(x.t - y.t) for x, y in zip(a, b, strict=True)])
    rot = np.degrees([rotation_angle(x.R.T @ y.R) for x, y in zip(a, b, strict=True)])
    return pos, np.asarray(rot, float)


# --------------------------------------------------------------------------------------------
# COLMAP run
# --------------------------------------------------------------------------------------------


def _colmap_camera(cam: PinholeCamera, camera_id: int) -> Any:
    import pycolmap

    fx, fy = cam.fx, cam.fy
    cx, cy = cam.cx + COLMAP_PIXEL_OFFSET, cam.cy + COLMAP_PIXEL_OFFSET
    k1, k2, p1, p2, k3 = (float(x) for x in cam.dist)
    if k3 == 0.0:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    camera = pycolmap.Camera(
        camera_id=camera_id, model=model, width=cam.width, height=cam.height, params=params
    )
    camera.has_prior_focal_length = True
    return camera


def _rigid(T: Rigid3) -> Any:
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(T.R), T.t.reshape(3, 1))


def _from_rigid(T: Any) -> Rigid3:
    return Rigid3(R=np.asarray(T.rotation.matrix()), t=np.asarray(T.translation, float).ravel())


def select_frames(sequence: Sequence, cfg: SfmCheckConfig) -> list[int]:
    """Positions (in the sequence) of the frames the check uses."""
    positions = list(range(cfg.first_frame, len(sequence), cfg.frame_step))
    if cfg.max_frames is not None:
        positions = positions[: cfg.max_frames]
    if len(positions) < 3:
        raise SfmCheckError(
            f"{sequence.root}: only {len(positions)} frames selected; the check needs >= 3"
        )
    return positions


def _write_masks(
    sequence: Sequence, positions: list[int], cfg: SfmCheckConfig, mask_dir: Path
) -> int:
    """COLMAP masks (``<image name>.png``, 0 = no features) from the object-id masks.

    Returns the number of masks written (0 if the sequence has none).
    """
    kernel = np.ones((2 * cfg.mask_erode_px + 1,) * 2, np.uint8) if cfg.mask_erode_px else None
    written = 0
    for pos in positions:
        frame = sequence[pos]
        for cam in ("left", "right"):
            ids = frame.mask(cam)
            if ids is None:
                continue
            keep = (~np.isin(ids, cfg.exclude_mask_ids)).astype(np.uint8) * 255
            if kernel is not None:
                keep = cv2.erode(keep, kernel)
            path = frame.left_path if cam == "left" else frame.right_path
            assert path is not None
            out = mask_dir / cam / f"{path.name}.png"
            out.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(out), keep):
                raise SfmCheckError(f"{out}: cannot write a COLMAP mask")
            written += 1
    return written


@dataclass(frozen=True, kw_only=True)
class ColmapRun:
    """The result of `run_colmap`: the largest reconstruction and what it took.

    Attributes:
        reconstruction: ``pycolmap.Reconstruction`` (rig: left = reference sensor).
        models: number of separate models COLMAP made.
        image_names: ``{frame position: (left name, right name)}`` as in the reconstruction.
        masked: whether masks were used.
        consecutive_matches: ``{(name a, name b): (M, 2) keypoint indices}``, COLMAP's
            geometrically verified matches between the same camera's images of consecutive
            frames (keypoint index = ``points2D`` index of the image in the reconstruction).
        timings_s: seconds per stage (extract, match, map).
    """

    reconstruction: Any
    models: int
    image_names: dict[int, tuple[str, str]]
    masked: bool
    consecutive_matches: dict[tuple[str, str], np.ndarray]
    timings_s: dict[str, float]


def _image_name(sequence: Sequence, path: Path) -> str:
    return path.relative_to(sequence.root).as_posix()


def run_colmap(
    sequence: Sequence,
    cfg: SfmCheckConfig,
    progress: Callable[[str], None] | None = None,
) -> ColmapRun:
    """Extract, match and map the selected frames with pycolmap in a temporary folder.

    Args:
        progress: called with a short message when a stage starts.
    """
    import pycolmap

    if sequence.kind != "stereo":
        raise SfmCheckError(
            f"{sequence.root}: the SfM check needs a stereo sequence (the rig fixes the scale)"
        )
    positions = select_frames(sequence, cfg)
    calib = sequence.calibration
    assert calib.right is not None and calib.right_from_left is not None
    names: dict[int, tuple[str, str]] = {}
    for pos in positions:
        fr = sequence[pos]
        assert fr.right_path is not None
        left, right = _image_name(sequence, fr.left_path), _image_name(sequence, fr.right_path)
        if not (left.startswith("left/") and right.startswith("right/")):
            raise SfmCheckError(
                f"{sequence.root}/frames.csv: frame {fr.index}: the SfM check needs images in "
                "left/ and right/ (COLMAP's rig is defined by these folders)"
            )
        names[pos] = (left, right)
    timings: dict[str, float] = {}
    say = progress or (lambda _m: None)
    with tempfile.TemporaryDirectory(prefix="satpose-colmap-") as tmp:
        work = Path(tmp)
        database = work / "database.db"
        masked = _write_masks(sequence, positions, cfg, work / "masks") > 0
        say(f"COLMAP: SIFT features in {2 * len(positions)} images")
        t0 = time.perf_counter()
        extraction = pycolmap.FeatureExtractionOptions(num_threads=cfg.num_threads)
        extraction.sift.max_num_features = cfg.max_features
        reader = pycolmap.ImageReaderOptions(camera_model="OPENCV")
        if masked:
            reader.mask_path = work / "masks"
        pycolmap.extract_features(
            database,
            sequence.root,
            image_names=[n for pair in names.values() for n in pair],
            camera_mode=pycolmap.CameraMode.PER_FOLDER,
            reader_options=reader,
            extraction_options=extraction,
        )
        rig = pycolmap.RigConfig(
            cameras=[
                pycolmap.RigConfigCamera(
                    ref_sensor=True, image_prefix="left/", camera=_colmap_camera(calib.left, 1)
                ),
                pycolmap.RigConfigCamera(
                    image_prefix="right/",
                    camera=_colmap_camera(calib.right, 2),
                    cam_from_rig=_rigid(calib.right_from_left),
                ),
            ]
        )
        with pycolmap.Database.open(database) as db:
            pycolmap.apply_rig_config([rig], db)
        timings["extract"] = time.perf_counter() - t0
        say(f"COLMAP: {cfg.matching} matching")
        t0 = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions(num_threads=cfg.num_threads)
        if cfg.matching == "sequential":
            pairing = pycolmap.SequentialPairingOptions(overlap=cfg.overlap, quadratic_overlap=True)
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing)
        else:
            pycolmap.match_exhaustive(database, matching_options=matching)
        timings["match"] = time.perf_counter() - t0
        say("COLMAP: incremental mapping")
        t0 = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions(
            num_threads=cfg.num_threads,
            random_seed=cfg.seed,
            ba_refine_sensor_from_rig=False,
            ba_refine_focal_length=False,
            ba_refine_principal_point=False,
            ba_refine_extra_params=False,
        )
        (work / "sparse").mkdir()
        models = pycolmap.incremental_mapping(database, sequence.root, work / "sparse", options)
        timings["map"] = time.perf_counter() - t0
        if not models:
            raise SfmCheckError(f"{sequence.root}: COLMAP reconstructed nothing")
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        matches = _consecutive_matches(database, positions, names)
    return ColmapRun(
        reconstruction=rec,
        models=len(models),
        image_names=names,
        masked=masked,
        consecutive_matches=matches,
        timings_s=timings,
    )


def _consecutive_matches(
    database: Path, positions: list[int], names: Mapping[int, tuple[str, str]]
) -> dict[tuple[str, str], np.ndarray]:
    """Verified inlier matches between the left (and the right) images of consecutive frames."""
    import pycolmap

    out: dict[tuple[str, str], np.ndarray] = {}
    with pycolmap.Database.open(database) as db:
        ids = {img.name: img.image_id for img in db.read_all_images()}
        for a, b in itertools.pairwise(positions):
            for cam in range(2):
                na, nb = names[a][cam], names[b][cam]
                ia, ib = ids[na], ids[nb]
                if not db.exists_two_view_geometry(ia, ib):
                    continue
                # Read in the stored order (smaller image id first), then put na's column first.
                lo, hi = min(ia, ib), max(ia, ib)
                m = np.asarray(db.read_two_view_geometry(lo, hi).inlier_matches, np.int64)
                out[(na, nb)] = m if ia == lo else m[:, ::-1]
    return out


def neighbour_agreement(
    rec: Any,
    image_names: Mapping[int, tuple[str, str]],
    matches: Mapping[tuple[str, str], np.ndarray],
    tolerance_px: float,
) -> tuple[dict[int, float], dict[int, int]]:
    """Per consecutive frame pair, the fraction of verified matches the reconstruction explains.

    A match between keypoints ``i`` of image A and ``j`` of image B (same camera, consecutive
    frames, both registered) is judged if ``i`` (else ``j``) has a 3-D point; it agrees if that
    point, projected into the other image, lands within ``tolerance_px`` of the other keypoint.

    Returns:
        ``({position of the first frame: agreeing / judged}, {same key: verified matches})``.
    """
    registered = {img.name: img for img in rec.images.values() if img.has_pose}
    positions = list(image_names)
    agreement: dict[int, float] = {}
    counts: dict[int, int] = {}
    for a, b in itertools.pairwise(positions):
        good = judged = total = 0
        for cam in range(2):
            key = (image_names[a][cam], image_names[b][cam])
            m = matches.get(key)
            A, B = registered.get(key[0]), registered.get(key[1])
            if m is None or m.size == 0 or A is None or B is None:
                continue
            total += len(m)
            g, j = _explained(rec, A, B, m, tolerance_px)
            good += g
            judged += j
        counts[a] = total
        if judged:
            agreement[a] = good / judged
    return agreement, counts


def _explained(
    rec: Any, A: Any, B: Any, matches: np.ndarray, tolerance_px: float
) -> tuple[int, int]:
    """(agreeing, judged) matches between registered images A and B (see
    `neighbour_agreement`)."""
    good = judged = 0
    for i, j in matches:
        for src, dst, ks, kd in ((A, B, int(i), int(j)), (B, A, int(j), int(i))):
            p = src.points2D[ks]
            if not p.has_point3D():
                continue
            cam_xyz = dst.cam_from_world() * rec.points3D[p.point3D_id].xyz
            judged += 1
            if cam_xyz[2] > 0:
                uv = np.asarray(rec.cameras[dst.camera_id].img_from_cam(cam_xyz)).ravel()
                target = np.asarray(dst.points2D[kd].xy)
                good += bool(np.linalg.norm(uv - target) <= tolerance_px)
            break
    return good, judged


# --------------------------------------------------------------------------------------------
# Health
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class FrameHealth:
    """COLMAP's view of one frame.

    Attributes:
        position: frame position in the sequence.
        registered: both images registered.
        left_cam_from_world: the reconstruction's pose (COLMAP world), or None.
        reprojection_px: mean reprojection error of the left and right image [px] (NaN if
            unregistered).
        points: 3-D points seen by the left and right image.
        rig_rotation_deg, rig_translation_m: re-localised ``right_from_left`` against the
            calibration (NaN if either image could not be re-localised).
        neighbour_agreement: agreement with the next frame (NaN if not judged).
    """

    position: int
    registered: bool
    left_cam_from_world: Rigid3 | None
    reprojection_px: tuple[float, float]
    points: tuple[int, int]
    rig_rotation_deg: float
    rig_translation_m: float
    neighbour_agreement: float


@dataclass(frozen=True, kw_only=True)
class Health:
    """COLMAP's own health and the verdict.

    Attributes:
        frames: per frame (every selected frame).
        registered_fraction: registered frames / selected frames.
        models: separate models COLMAP made (only the largest is used).
        points: 3-D points.
        mean_track_length: observations per 3-D point.
        reprojection_px: mean reprojection error [px].
        rig_rotation_deg, rig_translation_m: median per-frame rig consistency.
        rig_rotation_p90_deg: its 90th percentile [deg].
        worst_neighbour_agreement: the lowest judged neighbour agreement (NaN if none).
        neighbour_pairs_judged: consecutive frame pairs with enough verified matches.
        masked: masks were used.
        reasons: why the reconstruction is refused as ground truth (empty: accepted).
    """

    frames: tuple[FrameHealth, ...]
    registered_fraction: float
    models: int
    points: int
    mean_track_length: float
    reprojection_px: float
    rig_rotation_deg: float
    rig_translation_m: float
    rig_rotation_p90_deg: float
    worst_neighbour_agreement: float
    neighbour_pairs_judged: int
    masked: bool
    reasons: tuple[str, ...]

    @property
    def is_ground_truth(self) -> bool:
        return not self.reasons

    @property
    def verdict(self) -> str:
        """``ground truth`` or ``refused: <reasons>``."""
        return "ground truth" if self.is_ground_truth else "refused: " + "; ".join(self.reasons)


def _relocalise(rec: Any, image: Any) -> Rigid3 | None:
    """The image's pose from its own 2-D/3-D correspondences only (pycolmap LO-RANSAC + refine)."""
    import pycolmap

    pts = [p for p in image.points2D if p.has_point3D()]
    if len(pts) < 6:
        return None
    xy = np.array([p.xy for p in pts], float)
    xyz = np.array([rec.points3D[p.point3D_id].xyz for p in pts], float)
    result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, rec.cameras[image.camera_id])
    return None if result is None else _from_rigid(result["cam_from_world"])


def _image_reprojection(rec: Any, image: Any) -> tuple[float, int]:
    errs = []
    camera = rec.cameras[image.camera_id]
    cam_from_world = image.cam_from_world()
    for p in image.points2D:
        if p.has_point3D():
            uv = camera.img_from_cam(cam_from_world * rec.points3D[p.point3D_id].xyz)
            errs.append(float(np.linalg.norm(np.asarray(uv).ravel() - np.asarray(p.xy))))
    return (float(np.mean(errs)) if errs else math.nan), len(errs)


def assess(run: ColmapRun, right_from_left: Rigid3, cfg: SfmCheckConfig) -> Health:
    """COLMAP's health per frame and overall, and the reasons to refuse (see the module
    docstring and `SfmCheckConfig`)."""
    rec = run.reconstruction
    by_name = {img.name: img for img in rec.images.values() if img.has_pose}
    agreement, match_counts = neighbour_agreement(
        rec, run.image_names, run.consecutive_matches, cfg.neighbour_tolerance_px
    )
    frames = []
    for pos, (ln, rn) in run.image_names.items():
        L, R = by_name.get(ln), by_name.get(rn)
        registered = L is not None and R is not None
        f_reproj, npts = (math.nan, math.nan), (0, 0)
        f_rot = f_tr = math.nan
        pose = None
        if registered:
            assert L is not None and R is not None
            pose = _from_rigid(L.cam_from_world())
            (el, nl), (er, nr) = _image_reprojection(rec, L), _image_reprojection(rec, R)
            f_reproj, npts = (el, er), (nl, nr)
            a, b = _relocalise(rec, L), _relocalise(rec, R)
            if a is not None and b is not None:
                rfl = b @ a.inverse()
                f_rot = math.degrees(rotation_angle(rfl.R @ right_from_left.R.T))
                f_tr = float(np.linalg.norm(rfl.t - right_from_left.t))
        frames.append(
            FrameHealth(
                position=pos,
                registered=registered,
                left_cam_from_world=pose,
                reprojection_px=f_reproj,
                points=npts,
                rig_rotation_deg=f_rot,
                rig_translation_m=f_tr,
                neighbour_agreement=agreement.get(pos, math.nan),
            )
        )
    n_reg = sum(f.registered for f in frames)
    fraction = n_reg / len(frames)
    points = int(rec.num_points3D())
    track = float(rec.compute_mean_track_length()) if points else 0.0
    reproj = float(rec.compute_mean_reprojection_error()) if points else math.nan
    rig_rot = np.array([f.rig_rotation_deg for f in frames if math.isfinite(f.rig_rotation_deg)])
    rig_tr = np.array([f.rig_translation_m for f in frames if math.isfinite(f.rig_translation_m)])
    med_rot = float(np.median(rig_rot)) if rig_rot.size else math.nan
    p90_rot = float(np.percentile(rig_rot, 90)) if rig_rot.size else math.nan
    med_tr = float(np.median(rig_tr)) if rig_tr.size else math.nan
    judged = {
        p: x for p, x in agreement.items() if match_counts.get(p, 0) >= cfg.min_neighbour_matches
    }
    worst = float(min(judged.values())) if judged else math.nan
    reasons = []
    if fraction < cfg.min_registered_fraction:
        reasons.append(
            f"{n_reg}/{len(frames)} frames registered (< {cfg.min_registered_fraction:.0%})"
        )
    if run.models > 1:
        log.info("COLMAP made %d models; the largest is used", run.models)
    if points < cfg.min_points:
        reasons.append(f"{points} 3-D points (< {cfg.min_points})")
    if not reproj <= cfg.max_reprojection_px:
        reasons.append(f"mean reprojection error {reproj:.2f} px (> {cfg.max_reprojection_px})")
    if not track >= cfg.min_mean_track_length:
        reasons.append(f"mean track length {track:.1f} (< {cfg.min_mean_track_length})")
    if not med_rot <= cfg.max_rig_rotation_deg:
        reasons.append(
            f"left/right rig inconsistent: median {med_rot:.2f} deg (> {cfg.max_rig_rotation_deg})"
        )
    if not med_tr <= cfg.max_rig_translation_m:
        reasons.append(
            f"left/right rig inconsistent: median {100 * med_tr:.1f} cm "
            f"(> {100 * cfg.max_rig_translation_m:g})"
        )
    bad = [p for p, x in judged.items() if x < cfg.min_neighbour_agreement]
    if bad:
        reasons.append(
            f"consecutive frames disagree with the reconstruction at {len(bad)} pair(s) "
            f"(worst agreement {worst:.0%}; first after frame position {bad[0]})"
        )
    pairs = len(run.image_names) - 1
    if len(judged) < pairs / 2:
        reasons.append(
            f"only {len(judged)} of {pairs} consecutive frame pairs have >= "
            f"{cfg.min_neighbour_matches} verified matches between registered images "
            "(the reconstruction cannot be checked against its neighbours)"
        )
    return Health(
        frames=tuple(frames),
        registered_fraction=fraction,
        models=run.models,
        points=points,
        mean_track_length=track,
        reprojection_px=reproj,
        rig_rotation_deg=med_rot,
        rig_translation_m=med_tr,
        rig_rotation_p90_deg=p90_rot,
        worst_neighbour_agreement=worst,
        neighbour_pairs_judged=len(judged),
        masked=run.masked,
        reasons=tuple(reasons),
    )


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class FrameDisagreement:
    """COLMAP against the trajectory at one frame (after alignment).

    Attributes:
        position, frame, t_s: the frame.
        colmap: COLMAP's aligned ``left_cam_from_target``.
        trajectory: the trajectory's ``left_cam_from_target``.
        position_m: distance between the two target-origin positions [m].
        rotation_deg: angle between the two rotations [deg].
        used_in_fit: the frame took part in the alignment.
    """

    position: int
    frame: int
    t_s: float
    colmap: Rigid3
    trajectory: Rigid3
    position_m: float
    rotation_deg: float
    used_in_fit: bool


@dataclass(frozen=True, kw_only=True)
class SfmCheckResult:
    """Everything `check_sfm` found.

    Attributes:
        health: COLMAP's health and the verdict.
        alignment: SE(3) alignment to the trajectory (None without a trajectory).
        sim3_scale: the Sim(3) alignment's scale (metres per COLMAP unit; 1 for a metric rig).
        disagreement: per frame registered by COLMAP and present in the trajectory.
        run: the COLMAP run (reconstruction).
        timings_s: seconds per stage (extract, match, map, checks).
    """

    health: Health
    alignment: Alignment | None
    sim3_scale: float
    disagreement: tuple[FrameDisagreement, ...]
    run: ColmapRun
    timings_s: dict[str, float]


def match_trajectory(
    sequence: Sequence, t_s: np.ndarray, poses: list[Rigid3], where: str
) -> dict[int, Rigid3]:
    """``{frame position: left_cam_from_target}`` of a trajectory, matched by time."""
    times = np.array([f.t_s for f in sequence])
    out: dict[int, Rigid3] = {}
    for t, pose in zip(t_s, poses, strict=True):
        k = int(np.argmin(np.abs(times - t)))
        if abs(times[k] - t) > TIME_MATCH_TOL_S:
            raise SfmCheckError(
                f"{where}: time {t:.6f} s matches no frame of {sequence.root} "
                f"(tolerance {TIME_MATCH_TOL_S * 1e3:g} ms)"
            )
        out[k] = pose
    return out


def compare_to_trajectory(
    sequence: Sequence,
    health: Health,
    trajectory: Mapping[int, Rigid3],
    inlier_factor: float | None = 3.0,
) -> tuple[Alignment, float, tuple[FrameDisagreement, ...]]:
    """Align COLMAP's registered frames to a trajectory and measure the per-frame disagreement.

    Args:
        health: `assess`'s result (its frames carry COLMAP's poses).
        trajectory: ``{frame position: left_cam_from_target}`` (`match_trajectory`).
        inlier_factor: see `align_poses`.

    Returns:
        (SE(3) alignment, the Sim(3) alignment's scale, one row per frame registered by
        COLMAP and present in the trajectory).
    """
    common = [
        (f.position, f.left_cam_from_world)
        for f in health.frames
        if f.left_cam_from_world is not None and f.position in trajectory
    ]
    if len(common) < 3:
        raise SfmCheckError(
            f"only {len(common)} frames are both registered by COLMAP and in the trajectory;"
            " the alignment needs >= 3"
        )
    cw = [c for _, c in common]
    ct = [trajectory[p] for p, _ in common]
    alignment = align_poses(cw, ct, inlier_factor=inlier_factor)
    scale = align_poses(cw, ct, with_scale=True, inlier_factor=inlier_factor).scale
    aligned = [alignment.apply(c) for c in cw]
    pos, rot = pose_differences(aligned, ct)
    rows = []
    for i, (position, _) in enumerate(common):
        fr = sequence[position]
        rows.append(
            FrameDisagreement(
                position=position,
                frame=fr.index,
                t_s=fr.t_s,
                colmap=aligned[i],
                trajectory=ct[i],
                position_m=float(pos[i]),
                rotation_deg=float(rot[i]),
                used_in_fit=bool(alignment.used[i]),
            )
        )
    return alignment, scale, tuple(rows)


def check_sfm(
    sequence: Sequence,
    trajectory: Mapping[int, Rigid3] | None,
    cfg: SfmCheckConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> SfmCheckResult:
    """Reconstruct with pycolmap, judge COLMAP's health, align to ``trajectory`` and report
    the per-frame disagreement.

    Args:
        sequence: a stereo sequence (masks/ used if present).
        trajectory: ``{frame position: left_cam_from_target}`` (`match_trajectory`), or None
            for the health only.
        progress: called with a short message when a stage starts.
    """
    cfg = cfg or SfmCheckConfig()
    run = run_colmap(sequence, cfg, progress)
    calib = sequence.calibration
    assert calib.right_from_left is not None
    t0 = time.perf_counter()
    health = assess(run, calib.right_from_left, cfg)
    alignment: Alignment | None = None
    scale = math.nan
    rows: tuple[FrameDisagreement, ...] = ()
    if trajectory is not None:
        alignment, scale, rows = compare_to_trajectory(
            sequence, health, trajectory, cfg.inlier_factor
        )
    timings = {**run.timings_s, "checks": time.perf_counter() - t0}
    return SfmCheckResult(
        health=health,
        alignment=alignment,
        sim3_scale=scale,
        disagreement=rows,
        run=run,
        timings_s=timings,
    )
