"""Camera pose from a concentric-ring target of known radii (seed 002's on-orbit calibration
check: rings on the servicer, always in the boom camera's view).

Each ring's image conic back-projects to an elliptic cone with two circular sections
(`satpose.frontend.stereo.cone_circle_candidates`); with the ring's known radius each section
gives a centre (`circle_scale`). Concentric coplanar rings share the true section (same
normal, same centre); the false ones differ from ring to ring. So the sections that agree
best across rings give the target's plane; their spread (centre, normal) measures how
consistent the detected rings are. It does not reveal a focal-length error in one view (a 5 %
error changes it by ~5 %, tests/frontend/test_rings.py): the calibration check is the
per-frame pose of the servicer's ring target against the boom camera's nominal mounting.

The rotation about the rings' axis is not observable from circles; what is estimated per
frame is the target centre and normal in the camera frame (5 degrees of freedom).

Images (`detect_rings`): the arc-support ellipse detector (`satpose.frontend.ellipses`) finds
the band edges, concentric ones are grouped, and the group is associated with the known edge
radii (sorted by size, inner and outer band edges of opposite polarity, the size ratios and
then the agreement of the rings' circular sections decide); each associated ellipse is refined
on sub-pixel edges of its polarity (`satpose.frontend.edges`, geometric fit
`satpose.frontend.conics.refine_ellipse`), `rings_pose` gives centre and normal, and the fit
covariances of the ellipses are propagated to them and weight the rings (first order, rings
independent, `weighted_rings_pose`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from satpose.datasets.errors import SatposeError
from satpose.datasets.geometry import Rigid3
from satpose.frontend.conics import (
    ConicError,
    Ellipse,
    circle_to_conic,
    conic_to_ellipse,
    refine_ellipse,
    sampson_distance,
)
from satpose.frontend.edges import EdgeSearchConfig, edges_along_normals, smoothed
from satpose.frontend.ellipses import DetectedEllipse, EllipseDetectorConfig, detect_ellipses
from satpose.frontend.preprocess import PreparedImage
from satpose.frontend.stereo import circle_scale, cone_circle_candidates


@dataclass(frozen=True)
class RingsPose:
    """The concentric-ring target seen by one camera.

    Attributes:
        center_m: target centre in the camera frame (3,), or None.
        normal: unit normal toward the camera (3,), or None.
        normal_spread_deg: largest angle between a ring's normal and the mean normal.
        center_spread_m: largest distance between a ring's centre and the mean centre.
        reason: why there is no pose ("" when found).
        choice: index of the circular section taken for each ring (0 or 1), () if none.
        ambiguity: cost of this solution over that of the best one with a normal more than
            10 deg away (0 = none such; near 1 = the mirror tilt fits about as well).
    """

    center_m: np.ndarray | None
    normal: np.ndarray | None
    normal_spread_deg: float = math.nan
    center_spread_m: float = math.nan
    reason: str = ""
    choice: tuple[int, ...] = ()
    ambiguity: float = math.nan


def rings_pose(
    K: np.ndarray,
    conics: Sequence[np.ndarray],
    radii_m: Sequence[float],
    prior_normal: np.ndarray | None = None,
    max_prior_deg: float = 20.0,
) -> RingsPose:
    """Centre and normal of a concentric-ring target from its rings' image conics.

    Small rings far away are seen almost in weak perspective, where the false circular
    sections of all rings nearly agree too (the mirror tilt): ``ambiguity`` (the best cost
    over the best cost of a solution whose normal differs by more than 10 deg) near 1 says
    so. A ``prior_normal`` (the nominal mounting) settles it: only solutions within
    ``max_prior_deg`` of it are considered.

    Args:
        K: 3x3 intrinsics of the undistorted image.
        conics: one 3x3 image conic per ring (any scale and sign).
        radii_m: the rings' known radii [m], same order.
        prior_normal: expected unit normal (toward the camera), or None.
        max_prior_deg: see ``prior_normal``.

    Returns:
        A `RingsPose`; ``center_m`` is None with a ``reason`` when fewer than two rings are
        given, a conic is not an ellipse in front of the camera, or no solution lies near
        the prior.
    """
    if len(conics) != len(radii_m):
        return RingsPose(None, None, reason=f"{len(conics)} conics for {len(radii_m)} radii")
    if len(conics) < 2:
        return RingsPose(None, None, reason="need at least two rings (one ring is two-fold)")
    per_ring = []
    for i, (C, r) in enumerate(zip(conics, radii_m, strict=True)):
        Cm = np.asarray(C, dtype=float)
        if Cm.shape != (3, 3) or not np.all(np.isfinite(Cm)) or not r > 0:
            return RingsPose(None, None, reason=f"ring {i}: invalid conic or radius")
        try:
            per_ring.append(_sections(K, Cm, float(r)))
        except SatposeError as exc:
            return RingsPose(None, None, reason=f"ring {i}: {exc}")
    scale = float(np.mean([np.linalg.norm(c[0][1]) for c in per_ring]))
    sols = []
    for idx in itertools.product(*(range(len(c)) for c in per_ring)):
        choice = [per_ring[i][k] for i, k in enumerate(idx)]
        c_mean, n_mean, ang, spread = _combine(choice)
        if prior_normal is not None and _deg(n_mean, prior_normal) > max_prior_deg:
            continue
        sols.append((math.radians(ang) + spread / scale, c_mean, n_mean, ang, spread, idx))
    if not sols:
        return RingsPose(None, None, reason=f"no solution within {max_prior_deg} deg of the prior")
    sols.sort(key=lambda x: x[0])
    cost, c_mean, n_mean, ang, spread, idx_best = sols[0]
    others = [x[0] for x in sols[1:] if _deg(x[2], n_mean) > 10.0]
    ambiguity = cost / others[0] if others and others[0] > 0 else 0.0
    return RingsPose(
        c_mean,
        n_mean,
        normal_spread_deg=ang,
        center_spread_m=spread,
        choice=tuple(idx_best),
        ambiguity=ambiguity,
    )


def _deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b, -1.0, 1.0))))


def _sections(K: np.ndarray, C: np.ndarray, r: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The two circular sections ``(normal, centre [m])`` of one ring's cone."""
    return [(n, r * circle_scale(K, C, n, d) * d) for n, d in cone_circle_candidates(K, C)]


def _combine(
    choice: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Mean centre, mean normal, largest normal deviation [deg], largest centre deviation [m]."""
    normals = np.array([n for n, _ in choice])
    centres = np.array([c for _, c in choice])
    n_mean = normals.mean(axis=0)
    n_mean /= np.linalg.norm(n_mean)
    c_mean = centres.mean(axis=0)
    ang = float(np.degrees(np.max(np.arccos(np.clip(normals @ n_mean, -1.0, 1.0)))))
    spread = float(np.max(np.linalg.norm(centres - c_mean, axis=1)))
    return c_mean, n_mean, ang, spread


def weighted_rings_pose(
    K: np.ndarray,
    ellipses: Sequence[Ellipse],
    covariances: Sequence[np.ndarray],
    radii_m: Sequence[float],
    pose: RingsPose,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse-variance weighted centre and normal over the rings, with their covariance.

    Each ring's section (the one `rings_pose` chose) gets a first-order covariance from its
    ellipse's 5x5 parameter covariance (``[cx, cy, a, b, theta]``, e.g. from
    `refine_ellipse`) by central differences; centres are averaged with weights 1 / trace of
    their covariance, normals likewise (a small ring's normal is far less certain than a
    large one's). The rings are taken as independent (separate edges).

    Returns:
        (centre [m] (3,), unit normal (3,), 3x3 centre covariance [m^2], 3x3 normal
        covariance (rank 2)).
    """
    if pose.center_m is None or len(pose.choice) != len(ellipses):
        raise SatposeError("weighted_rings_pose needs a pose with its section choice")
    steps = np.array([0.05, 0.05, 0.05, 0.05, 1e-3])  # px, px, px, px, rad
    cs, ns, Ccs, Cns = [], [], [], []
    for e, S, r, k in zip(ellipses, covariances, radii_m, pose.choice, strict=True):
        n0, c0 = _sections(K, e.conic(), float(r))[k]
        J = np.zeros((6, 5))
        for j in range(5):
            out = []
            for sgn in (1.0, -1.0):
                p = e.params.copy()
                p[j] += sgn * steps[j]
                secs = _sections(K, Ellipse.from_params(p).conic(), float(r))
                n, c = max(secs, key=lambda s: float(s[0] @ n0))  # the same branch
                out.append(np.r_[c, n])
            J[:, j] = (out[0] - out[1]) / (2 * steps[j])
        C6 = J @ S @ J.T
        cs.append(c0)
        ns.append(n0)
        Ccs.append(C6[:3, :3])
        Cns.append(C6[3:, 3:])
    wc = np.array([1.0 / max(float(np.trace(C)), 1e-30) for C in Ccs])
    wn = np.array([1.0 / max(float(np.trace(C)), 1e-30) for C in Cns])
    centre = np.einsum("i,ij->j", wc, np.array(cs)) / wc.sum()
    cov_c = sum(w * w * C for w, C in zip(wc, Ccs, strict=True)) / wc.sum() ** 2
    m = np.einsum("i,ij->j", wn, np.array(ns))
    normal = m / np.linalg.norm(m)
    P = np.eye(3) - np.outer(normal, normal)  # normalisation removes the radial part
    cov_n = P @ (sum(w * w * C for w, C in zip(wn, Cns, strict=True))) @ P / float(m @ m)
    return centre, normal, 0.5 * (cov_c + cov_c.T), 0.5 * (cov_n + cov_n.T)


# --------------------------------------------------------------------------------------------
# Detection in an image
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RingsDetectorConfig:
    """Settings of `detect_rings` (distances in pixels of the undistorted image).

    Attributes:
        ellipses: the arc-support ellipse detector's settings.
        min_support: detections with less perimeter support are ignored.
        min_axis_px: smallest semi-minor axis of a usable band edge.
        concentric_tol: ellipses belong to one concentric family when their centres lie
            within this fraction of the larger one's semi-major axis (the centres of the
            images of concentric circles are not the same point: perspective shifts them by
            a few per cent of the size at 50 deg tilt) and their axis ratios within
            ``shape_tol``.
        shape_tol: largest difference of the axis ratios b/a within a family.
        ratio_tol: an association is tried only when the log size ratio of consecutive
            ellipses matches the log ratio of their radii within this.
        max_rel_center_spread: an association is accepted when the rings' centres agree
            within this fraction of the distance (wrong radii put the rings at different
            depths).
        max_normal_spread_deg: ... and their normals within this [deg].
        max_members: at most this many (largest-support) ellipses of a family are associated.
        edge_points: normals sampled per ellipse for the sub-pixel refinement.
        edge_search_px: half-width of the first search along each normal.
        min_edge_fraction: fraction of the normals that must find an edge of the polarity.
        outlier_sigma: edge points beyond this many robust standard deviations are dropped.
        max_refine_rms_px: largest accepted RMS distance of the edge points to the fit.
        edges: sub-pixel edge settings (a painted band edge is a plain step: gradient peak).
        roi_margin: with a nominal pose, the search window is the projected outer edge's box
            grown by this fraction of its semi-major axis plus ``roi_margin_px`` (at 0.6 m a
            0.5 fraction covers a mounting error of several degrees).
        roi_margin_px: see ``roi_margin``.
    """

    ellipses: EllipseDetectorConfig = field(default_factory=EllipseDetectorConfig)
    min_support: float = 0.35
    min_axis_px: float = 4.0
    concentric_tol: float = 0.12
    shape_tol: float = 0.15
    ratio_tol: float = 0.15
    max_rel_center_spread: float = 0.02
    max_normal_spread_deg: float = 4.0
    max_members: int = 8
    edge_points: int = 180
    edge_search_px: float = 2.5
    min_edge_fraction: float = 0.5
    outlier_sigma: float = 3.0
    max_refine_rms_px: float = 0.6
    edges: EdgeSearchConfig = field(
        default_factory=lambda: EdgeSearchConfig(smooth_sigma_px=0.7, step_px=0.25)
    )
    roi_margin: float = 0.5
    roi_margin_px: int = 20


@dataclass(frozen=True, kw_only=True)
class RingsDetection:
    """The ring target found in one image.

    Attributes:
        pose: centre and normal (inverse-variance weighted over the rings,
            `weighted_rings_pose`), the spreads of `rings_pose` (unweighted), and ``reason``
            when there is none.
        ellipses: the refined band-edge ellipses used, smallest first.
        radii_m: the edge radius each of them was associated with.
        cov_center: 3x3 covariance of the centre [m^2] from the ellipse fits, or None.
        cov_normal: 3x3 covariance of the unit normal (rank 2), or None.
        candidates: ellipses the detector returned (before association).
    """

    pose: RingsPose
    ellipses: tuple[Ellipse, ...] = ()
    radii_m: tuple[float, ...] = ()
    cov_center: np.ndarray | None = None
    cov_normal: np.ndarray | None = None
    candidates: int = 0

    @property
    def reason(self) -> str:
        return self.pose.reason

    @property
    def sigma_center_m(self) -> float:
        """sqrt of the trace of the centre covariance [m] (NaN without one)."""
        return math.nan if self.cov_center is None else math.sqrt(np.trace(self.cov_center))

    @property
    def sigma_normal_deg(self) -> float:
        """sqrt of the trace of the normal covariance, as an angle [deg] (NaN without one)."""
        if self.cov_normal is None:
            return math.nan
        return math.degrees(math.sqrt(max(float(np.trace(self.cov_normal)), 0.0)))


def _none(reason: str, candidates: int = 0) -> RingsDetection:
    return RingsDetection(pose=RingsPose(None, None, reason=reason), candidates=candidates)


def rings_roi(
    K: np.ndarray,
    cam_from_rings: Rigid3,
    outer_radius_m: float,
    shape: tuple[int, int],
    config: RingsDetectorConfig,
) -> tuple[int, int, int, int] | None:
    """Search window ``(x0, y0, x1, y1)`` around the projection of the outer edge at a
    (nominal) pose ``cam_from_rings`` (a `Rigid3`); None if it does not project to an ellipse
    in the image."""
    try:
        e = conic_to_ellipse(circle_to_conic(K, cam_from_rings, outer_radius_m))
    except ConicError:
        return None
    m = config.roi_margin * e.a + config.roi_margin_px
    H, W = shape
    x0, y0 = max(int(e.cx - e.a - m), 0), max(int(e.cy - e.a - m), 0)
    x1, y1 = min(int(e.cx + e.a + m) + 1, W), min(int(e.cy + e.a + m) + 1, H)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    return (x0, y0, x1, y1)


def _size(e: Ellipse) -> float:
    return math.sqrt(e.a * e.b)


def _families(cands: list[DetectedEllipse], cfg: RingsDetectorConfig) -> list[list[int]]:
    """Concentric families (indices into ``cands``), the most members first."""
    order = sorted(range(len(cands)), key=lambda i: -cands[i].ellipse.a)
    fams: list[list[int]] = []
    for i in order:
        e = cands[i].ellipse
        for fam in fams:
            a = cands[fam[0]].ellipse
            close = float(np.linalg.norm(e.center - a.center)) < cfg.concentric_tol * a.a
            if close and abs(e.b / e.a - a.b / a.a) < cfg.shape_tol:
                fam.append(i)
                break
        else:
            fams.append([i])
    fams = [f for f in fams if len(f) >= 2]
    fams.sort(key=lambda f: (-len(f), -sum(cands[i].support for i in f)))
    return fams


def _associate(
    K: np.ndarray,
    members: list[DetectedEllipse],
    radii: np.ndarray,
    cfg: RingsDetectorConfig,
    prior_normal: np.ndarray | None,
) -> tuple[list[int], list[int], int] | None:
    """Best monotone association of ``members`` (sorted by size) with edge indices: returns
    (member indices, edge indices, band polarity) or None. Edge ``2k`` is band ``k``'s inner
    edge, ``2k + 1`` its outer edge; inner edges have polarity ``s`` and outer ones ``-s``."""
    sizes = np.array([_size(m.ellipse) for m in members])
    pol = np.array([m.polarity for m in members])
    conics = [m.ellipse.conic() for m in members]
    n_e = len(radii)
    for m in range(min(len(members), n_e), 1, -1):
        best: tuple[float, list[int], list[int], int] | None = None
        for mi in itertools.combinations(range(len(members)), m):
            ls = np.log(sizes[list(mi)])
            for ei in itertools.combinations(range(n_e), m):
                lr = np.log(radii[list(ei)])
                if np.max(np.abs(np.diff(ls) - np.diff(lr))) > cfg.ratio_tol:
                    continue
                role = np.where(np.array(ei) % 2 == 0, 1, -1)  # inner +1, outer -1
                p = pol[list(mi)]
                signs = {int(x) for x in np.sign(p * role) if x != 0}
                if len(signs) > 1:
                    continue
                pose = rings_pose(
                    K, [conics[i] for i in mi], radii[list(ei)].tolist(), prior_normal
                )
                if pose.center_m is None:
                    continue
                rel = pose.center_spread_m / float(np.linalg.norm(pose.center_m))
                if rel > cfg.max_rel_center_spread or (
                    pose.normal_spread_deg > cfg.max_normal_spread_deg
                ):
                    continue
                cost = rel + math.radians(pose.normal_spread_deg)
                if best is None or cost < best[0]:
                    best = (cost, list(mi), list(ei), signs.pop() if signs else 0)
        if best is not None:
            return best[1], best[2], best[3]
    return None


def _plane_pose(center: np.ndarray, normal: np.ndarray) -> Rigid3:
    """A pose of the rings' plane (z = ``normal``; the rotation about the axis is arbitrary:
    an image conic needs only the plane)."""
    z = normal / np.linalg.norm(normal)
    x = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return Rigid3(R=np.c_[x, np.cross(z, x), z], t=np.asarray(center, float))


def _refine_on_edges(
    image_s: np.ndarray, e: Ellipse, polarity: int, cfg: RingsDetectorConfig
) -> tuple[Ellipse, np.ndarray] | None:
    """Sub-pixel edges of ``polarity`` (+1: brighter inside) along the normals of ``e`` and a
    robust geometric fit; (ellipse, 5x5 covariance) or None."""
    n = cfg.edge_points
    half = cfg.edge_search_px
    ell, cov = e, np.eye(5)
    for _ in range(2):
        pts, _ = edges_along_normals(
            image_s, ell.points(n), ell.normals(n), polarity, half, cfg.edges
        )
        P = pts[np.isfinite(pts[:, 0])]
        if P.shape[0] < cfg.min_edge_fraction * n:
            return None
        try:
            for _ in range(2):
                r = sampson_distance(P, ell.conic())
                sigma = max(1.4826 * float(np.median(np.abs(r))), 0.05)
                keep = np.abs(r) < cfg.outlier_sigma * sigma
                if keep.sum() < cfg.min_edge_fraction * n:
                    return None
                ell, cov, rms = refine_ellipse(P[keep], ell)
        except ConicError:
            return None
        half = 1.5  # the second pass searches close to the refined ellipse
    if rms > cfg.max_refine_rms_px or ell.b < cfg.min_axis_px:
        return None
    return ell, cov


def detect_rings(
    image: PreparedImage,
    K: np.ndarray,
    edge_radii_m: Sequence[float],
    config: RingsDetectorConfig | None = None,
    roi: tuple[int, int, int, int] | None = None,
    prior_normal: np.ndarray | None = None,
) -> RingsDetection:
    """Find the concentric-ring target in an undistorted image and estimate its centre and
    normal in the camera frame.

    Args:
        image: the undistorted grey image (`satpose.frontend.preprocess.Undistorter`).
        K: 3x3 intrinsics of that image.
        edge_radii_m: the target's band-edge radii, increasing [m]: inner and outer edge of
            each painted band in turn (`satpose.datasets.servicer_rings`).
        roi: search window ``(x0, y0, x1, y1)`` (e.g. `rings_roi` at the nominal pose), or
            None for the whole image.
        prior_normal: the nominal normal (unit, camera frame): settles the two-fold
            ambiguity of small rings (`rings_pose`); None: the best-agreeing solution.

    Returns:
        A `RingsDetection`; without a pose its ``reason`` says why (dark image, no
        concentric ellipses, no consistent association, refinement failed). Never raises on
        image content.
    """
    cfg = config or RingsDetectorConfig()
    radii = np.asarray(edge_radii_m, float)
    if radii.ndim != 1 or radii.size < 2 or np.any(np.diff(radii) <= 0) or radii[0] <= 0:
        raise SatposeError(f"edge radii must be >= 2 increasing positive numbers, got {radii}")
    if image.problem is not None:
        return _none(f"image {image.problem}")
    found = detect_ellipses(image.gray8, cfg.ellipses, roi)
    cands = [d for d in found if d.support >= cfg.min_support and d.ellipse.b >= cfg.min_axis_px]
    if len(cands) < 2:
        return _none(f"{len(cands)} ellipse(s) found, need two concentric rings", len(found))
    fams = _families(cands, cfg)
    if not fams:
        return _none("no concentric ellipses", len(found))
    image_s = smoothed(image.gray, cfg.edges)
    reason = "no association of the ellipses with the known radii"
    for fam in fams[:4]:
        top = sorted(fam, key=lambda i: -cands[i].support)[: cfg.max_members]
        members = sorted((cands[i] for i in top), key=lambda d: _size(d.ellipse))
        assoc = _associate(K, members, radii, cfg, prior_normal)
        if assoc is None:
            continue
        mi, ei, sign = assoc
        ells, covs, rads = [], [], []
        for i, j in zip(mi, ei, strict=True):
            role = 1 if j % 2 == 0 else -1
            pol = sign * role if sign != 0 else members[i].polarity
            if pol == 0:
                continue
            ref = _refine_on_edges(image_s, members[i].ellipse, pol, cfg)
            if ref is not None:
                ells.append(ref[0])
                covs.append(ref[1])
                rads.append(float(radii[j]))
        if len(ells) < 2:
            reason = f"only {len(ells)} ring edge(s) survived the sub-pixel refinement"
            continue
        pose = rings_pose(K, [e.conic() for e in ells], rads, prior_normal)
        if pose.center_m is None or pose.normal is None:
            reason = pose.reason
            continue
        if sign != 0 and len(ells) < len(radii):
            # Edges the detector missed (small, faint, partly hidden): predicted from the
            # pose, refined on sub-pixel edges of their polarity like the others.
            plane = _plane_pose(pose.center_m, pose.normal)
            for j in sorted(
                set(range(len(radii))) - {int(np.argmin(np.abs(radii - r))) for r in rads}
            ):
                try:
                    guess = conic_to_ellipse(circle_to_conic(K, plane, float(radii[j])))
                except ConicError:
                    continue
                if guess.b < cfg.min_axis_px:
                    continue
                ref = _refine_on_edges(image_s, guess, sign * (1 if j % 2 == 0 else -1), cfg)
                if ref is not None:
                    ells.append(ref[0])
                    covs.append(ref[1])
                    rads.append(float(radii[j]))
            order = np.argsort(rads)
            ells = [ells[i] for i in order]
            covs = [covs[i] for i in order]
            rads = [rads[i] for i in order]
            pose = rings_pose(K, [e.conic() for e in ells], rads, prior_normal)
            if pose.center_m is None:
                reason = pose.reason
                continue
        centre, normal, cov_c, cov_n = weighted_rings_pose(K, ells, covs, rads, pose)
        pose = replace(pose, center_m=centre, normal=normal)
        return RingsDetection(
            pose=pose,
            ellipses=tuple(ells),
            radii_m=tuple(rads),
            cov_center=cov_c,
            cov_normal=cov_n,
            candidates=len(found),
        )
    return _none(reason, len(found))
