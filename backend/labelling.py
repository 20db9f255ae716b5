"""Which of several per-frame poses is the target's: decided over frames by the motion.

One image of the bracket in the paper's view often fits several poses (the P3P solutions of
``p1, p2`` and the apex, the labellings of a near-symmetric bracket), each verified by the
frontend (`satpose.frontend.bracket_lines.detect_partial`). A wrong solution is in general
not a rigid motion of the bracket over frames: `SequenceLabeller` links every frame's
candidate poses into hypothesis tracks (bounded multi-hypothesis tracking), scores each track
by how well the constant-twist motion prior explains it (the same factors as the smoothers:
`satpose.backend.motion.constant_twist_factor`, a Gaussian pose prior per frame, batch
Levenberg-Marquardt) plus the candidates' own image misfits, and reports a frame's pose only
when the track that carries it beats every track that disagrees there by a log-likelihood
ratio of at least ``log_lr_threshold`` (Wald's sequential probability ratio test).

Score (a negative log-likelihood, lower is better) of a track over the frames seen so far::

    cost = (E_fit - dof / 2) + sum over its frames of (image_chi2 - image_dim) / 2
           + miss_cost * (frames with candidates that the track does not explain)

``E_fit`` is the smoother's final error (half the chi-square of the pose and motion residuals)
and ``dof = 6 n - 6`` its degrees of freedom for ``n`` poses, so a track that explains its
frames as well as the noise allows scores ~0 whatever its length. The *null* track (none of the
candidates is the target's pose) leaves every frame unexplained. The comparison of two tracks'
costs is a generalised likelihood ratio on the same images: the pose covariances are those of
the image quantities at each solution's own pose (`partial_pose_covariance`), so their
normalisers are the images' and cancel.

Modes: ``online`` reports frame ``k`` from what frames ``0..k`` say (from the decision on);
``offline`` decides with the whole sequence and reports back to a track's start.

gtsam stays inside the backend; the candidates come in as frontend `PoseMeasurement` objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import gtsam
import numpy as np
from scipy.stats import chi2

from satpose.backend.errors import BackendError
from satpose.backend.factors import MeasurementConfig, pose_factor, tangent_basis
from satpose.backend.keys import PLANE_NORMAL, SHARED_BIAS, V, X
from satpose.backend.motion import (
    MotionConfig,
    constant_twist_factor,
    predict,
    process_covariance,
    twist_between,
    twist_prior_factor,
)
from satpose.backend.pose3 import from_state, local_error, state_to_pose_jacobian, to_state
from satpose.backend.solve import levenberg_marquardt
from satpose.datasets.geometry import Rigid3
from satpose.frontend.measurements import PlaneNormalMeasurement, PoseMeasurement

_GAUSSIAN = MeasurementConfig(coupling="loose", robust="none")


class ImageResidual(Protocol):
    """A frame's measured quantities as a function of the pose: whitened residuals ``r``
    (``dim``,) and their Jacobian (``dim`` x 6) for the right perturbation ``T Exp(xi)``,
    ``xi = [rotation, translation]`` (e.g. `satpose.frontend.bracket_lines.PartialImageModel`)."""

    @property
    def dim(self) -> int: ...

    @property
    def shared_groups(self) -> tuple[int, ...]:
        """Per residual, the group (0, 1, ...) whose members share a bias over the frames
        of a track (the same quantity measured the same way in every frame: a strut's
        taper), or -1 (independent)."""
        ...

    @property
    def shared_cap(self) -> float:
        """The largest whitened misfit a grouped quantity counts with (its residuals are
        truncated there: a truncated square)."""
        ...

    def residual_and_jacobian(self, pose: Rigid3) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """One consistent pose of a frame.

    Attributes:
        pose: the pose with its (first-order) covariance: the start of the fit, and what
            gates and rival distances are measured with.
        image: the frame's measured quantities as a function of the pose: the fit weighs
            these (not the Gaussian ``pose``) against the motion; None: ``pose`` is the
            measurement (a Gaussian prior).
        image_chi2: squared normalised misfit of what neither is about (strut widths); 0
            when nothing else is over-determined.
        image_dim: how many such quantities (the expected value of ``image_chi2``).
        group: candidates of a frame with the same ``group`` (>= 0) share their measured
            quantities (one labelling of the same struts, another P3P solution): a track
            may take that ``image`` with its own predicted pose when no candidate pose of the
            group is near it (the solution near the truth can vanish in noise).
        ref: the caller's handle (e.g. the detection), returned with the decision.
        plane: the frame's measured normal of a plane rigid with the target (a solar
            array's cell grid; the same for every candidate of the frame), or None; weighed
            when `LabellingConfig.plane_normals` is on.
    """

    pose: PoseMeasurement
    image: ImageResidual | None = None
    image_chi2: float = 0.0
    image_dim: int = 0
    group: int = -1
    ref: object = None
    plane: PlaneNormalMeasurement | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.image_chi2) and self.image_chi2 >= 0):
            raise BackendError(f"image_chi2 must be finite and >= 0, got {self.image_chi2}")
        if self.image_dim < 0:
            raise BackendError(f"image_dim must be >= 0, got {self.image_dim}")


@dataclass(frozen=True, kw_only=True)
class LabellingConfig:
    """Settings of `SequenceLabeller`.

    Attributes:
        motion: the motion prior tracks are scored with (white acceleration noise, target
            frame). The default allows what an approach with a rolling camera does between
            frames 1 s apart: set on the bracket family's tuning seeds so that the true
            trajectories score ~0 (docs/bracket.md, "Deciding over frames").
        log_lr_threshold: a frame's pose is reported when its track's log-likelihood exceeds
            that of every disagreeing track (and of the null track) by this much. Wald's
            bound ``log((1 - beta) / alpha)``: 6.9 for a wrong decision rate ``alpha`` of
            1e-3 at ``beta`` ~ 0.
        miss_cost: cost of a frame with candidates that a track does not explain (none in its
            gate, or outside its span): ``-log(1 - P_D)`` for a detector that finds the true
            pose among its candidates with probability ``P_D`` (0.95 -> 3.0).
        image_weight: weight of the candidates' image misfits in the score (1: as stated;
            0: motion only).
        gate_deg, gate_rel: a candidate continues a track when it lies within ``gate_deg`` in
            attitude and ``gate_rel`` x range (+ 2 cm) at ``centre_m`` of the track's
            constant-twist prediction, ...
        gate_chi2: ... or within this chi-square (6 dof; 22.5: 99.9 %) of it, with the
            candidate's covariance plus the track's last pose's and the motion's over the
            gap (a pose near a double P3P root is uncertain by tens of degrees in tilt).
            Every group of measured quantities that the predicted pose explains within this
            chi-square is also fitted from the prediction.
        fit_gate_quantile: ... or when the track refitted with it has a chi-square larger
            by at most this quantile of the chi-square distribution with the candidate's
            quantities' count as degrees of freedom (the same test for every track, whatever
            its prediction).
        rival_deg, rival_rel: two tracks disagree at a frame when their poses there differ by
            more than this (the frontend's rival distance: another labelling or P3P
            solution). Whatever the covariances: a second maximum of the likelihood 8-14 deg
            away (a neighbouring P3P root) is not described by the first one's covariance,
            and reporting either would be an error of that size.
        max_tracks: at most this many tracks are kept (the lowest costs), one per
            hypothesis: a track whose fitted poses agree with a better track's at every frame
            it explains, and which explains no other frame, is dropped.
        max_gap: a track is not continued over more than this many frames without a
            candidate in its gate.
        reach_back: a track that starts after the first frame is also carried back over the
            earlier frames whose measured quantities its backward prediction explains (the
            fit gate); False: tracks run forward only (the behaviour before).
        shared_variance: the variance of a bias that all frames of a track share, per group of
            grouped image residuals (``shared_groups``: a strut's taper), in the residuals'
            whitened units, on top of each frame's own unit variance (`fit_track`). 0: every
            frame independent (the behaviour before). The variance between struts and members
            of the mean measured minus true taper over its weighed sigma, on the bracket
            family's tuning seeds 0-99: 0.51, against 0.39 within (docs/bracket.md, "Strut
            taper"). Each frame keeps its full weight (not the 0.39 measured), so a track
            never costs more than with independent frames: a bias that every frame shows
            is evidence about once, and a misfit that changes from frame to frame counts as
            before. 0.5 is not the default: on tuning 76-99 it lost more frames than it
            gained (docs/bracket.md, "Narrow struts' tapers and a bias their frames
            share").
        plane_normals: weigh the candidates' measured plane normals (``Candidate.plane``):
            the plane is rigid with the target, so its normal is one direction of the target
            frame, unknown and fitted per track (`fit_track`); a track whose poses turn that
            direction from frame to frame misfits it. False: the normals are not used (the
            behaviour before).
        plane_cap: a frame's plane-normal misfit counts as at most this many sigmas (a
            truncated square: a frame where the grid's normal is wrong, or a plane that is
            not rigid with the target, cannot veto the true track).
    """

    motion: MotionConfig = field(
        default_factory=lambda: MotionConfig(
            angular_accel_noise_rad_s2_rthz=0.02, linear_accel_noise_m_s2_rthz=0.05
        )
    )
    log_lr_threshold: float = 6.9
    miss_cost: float = 3.0
    image_weight: float = 1.0
    gate_deg: float = 15.0
    gate_rel: float = 0.25
    gate_chi2: float = 22.5
    fit_gate_quantile: float = 0.999
    rival_deg: float = 8.0
    rival_rel: float = 0.05
    max_tracks: int = 16
    max_gap: int = 3
    reach_back: bool = True
    shared_variance: float = 0.0
    plane_normals: bool = False
    plane_cap: float = 3.0

    def __post_init__(self) -> None:
        for name in ("log_lr_threshold", "miss_cost", "gate_deg", "gate_rel", "plane_cap"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise BackendError(f"labelling.{name} must be positive, got {v}")
        if not (math.isfinite(self.image_weight) and self.image_weight >= 0):
            raise BackendError(f"labelling.image_weight must be >= 0, got {self.image_weight}")
        if not 0.0 < self.fit_gate_quantile < 1.0:
            raise BackendError(
                f"labelling.fit_gate_quantile must be in (0, 1), got {self.fit_gate_quantile}"
            )
        if not (math.isfinite(self.shared_variance) and self.shared_variance >= 0):
            raise BackendError(
                f"labelling.shared_variance must be >= 0, got {self.shared_variance}"
            )
        if self.max_tracks < 2 or self.max_gap < 0:
            raise BackendError("labelling.max_tracks must be >= 2 and max_gap >= 0")


@dataclass(frozen=True)
class TrackFit:
    """The smoother's fit of one track: final error (half chi-square), degrees of freedom,
    the smoothed poses and twists of its frames (in order)."""

    error: float
    dof: int
    poses: tuple[Rigid3, ...]
    twists: np.ndarray


def image_factor(i: int, model: ImageResidual, shared: float = 0.0) -> gtsam.CustomFactor:
    """The frame's measured quantities on ``X(i)`` (whitened: unit noise). The graph stores
    ``X = T^-1``; ``X Exp(d)`` is ``T Exp(-Ad_X d)`` (`state_to_pose_jacobian`).

    ``shared`` > 0 (a variance) and grouped residuals (``shared_groups``): the factor is also
    on ``SHARED_BIAS`` ``b`` and a grouped residual ``r`` becomes ``r - b[group]``: the
    group's bias common to the track's frames (its prior, variance ``shared``, is
    `fit_track`'s); truncated at ``shared_cap`` like ``r`` itself, so an outlying frame
    counts at most that many sigmas whatever the bias."""
    groups = np.asarray(model.shared_groups, dtype=int)
    rows = np.flatnonzero(groups >= 0) if shared > 0.0 else np.zeros(0, dtype=int)
    if rows.size and int(groups.max()) >= SHARED_GROUPS:
        raise BackendError(f"image_factor: shared group {groups.max()} >= {SHARED_GROUPS}")
    keys = [X(i), SHARED_BIAS] if rows.size else [X(i)]
    cap = float(model.shared_cap) if rows.size else math.inf

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        X_i = values.atPose3(this.keys()[0])
        r, J = model.residual_and_jacobian(from_state(X_i))
        if rows.size:
            r = np.array(r, dtype=float)
            r[rows] -= values.atVector(this.keys()[1])[groups[rows]]
            flat = rows[np.abs(r[rows]) > cap]  # beyond the cap the truncated square is flat
            r[rows] = np.clip(r[rows], -cap, cap)
            J = np.array(J, dtype=float)
            J[flat] = 0.0
        if H is not None:
            H[0] = np.asfortranarray(J @ state_to_pose_jacobian(X_i))
            if rows.size:
                Hb = np.zeros((len(r), SHARED_GROUPS))
                Hb[rows, groups[rows]] = -1.0
                Hb[flat] = 0.0
                H[1] = np.asfortranarray(Hb)
        return r

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(model.dim), keys, error)


def plane_factor(
    i: int, plane: PlaneNormalMeasurement, reference: np.ndarray, cap: float
) -> gtsam.CustomFactor:
    """The measured normal ``m`` (camera frame, up to sign) of a plane rigid with the target
    on ``X(i)`` and ``PLANE_NORMAL``: the track's normal in the target frame ``n = (n0 + B0
    d) / |n0 + B0 d|`` (``reference`` ``n0``, ``B0`` its tangent basis, ``d`` the 2-vector
    ``PLANE_NORMAL``) seen from the frame's pose, ``y = R n``, against ``m``: the residual
    ``B_m^T y / sigma`` (``B_m`` the tangent basis at ``m``, its sign toward ``y``), the
    angle between the two in radians over sigma to first order. Truncated at ``cap`` (its
    norm): beyond it the truncated square is flat."""
    n0 = np.asarray(reference, dtype=float) / np.linalg.norm(reference)
    B0 = tangent_basis(n0)
    m = np.asarray(plane.normal, dtype=float)
    sigma = float(plane.sigma_rad)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> Any:
        X_i = values.atPose3(this.keys()[0])
        d = values.atVector(this.keys()[1])
        u = n0 + B0 @ d
        nu = float(np.linalg.norm(u))
        n = u / nu
        R_k = X_i.rotation().matrix().T  # camera from target (X = T^-1)
        y = R_k @ n
        mm = m if float(m @ y) >= 0.0 else -m
        Bm = tangent_basis(mm)
        r = Bm.T @ y / sigma
        norm = float(np.linalg.norm(r))
        flat = norm > cap
        if H is not None:
            if flat:
                H[0] = np.asfortranarray(np.zeros((2, 6)))
                H[1] = np.asfortranarray(np.zeros((2, 2)))
            else:
                # X Exp([w, v]): R_k -> Exp(-w) R_k, y -> y + y x w
                yx = np.array([[0.0, -y[2], y[1]], [y[2], 0.0, -y[0]], [-y[1], y[0], 0.0]])
                H[0] = np.asfortranarray(np.c_[Bm.T @ yx / sigma, np.zeros((2, 3))])
                dn = (np.eye(3) - np.outer(n, n)) @ B0 / nu
                H[1] = np.asfortranarray(Bm.T @ R_k @ dn / sigma)
        return r * (cap / norm) if flat else r

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [X(i), PLANE_NORMAL], error)


def plane_reference(poses: list[Rigid3], planes: list[PlaneNormalMeasurement]) -> np.ndarray:
    """The target-frame direction that the measured normals point to from ``poses``: the
    principal direction of ``R_k^T m_k`` (each up to sign)."""
    A = np.array([T.R.T @ p.normal for T, p in zip(poses, planes, strict=True)])
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    return np.asarray(vt[0])


# the length of a track's ``SHARED_BIAS`` vector: groups 0 .. SHARED_GROUPS - 1 (the
# bracket's three struts)
SHARED_GROUPS = 3


def fit_track(
    t_s: np.ndarray,
    candidates: list[Candidate],
    motion: MotionConfig,
    initial: tuple[list[Rigid3], np.ndarray] | None = None,
    shared: float = 0.0,
    plane_cap: float | None = None,
) -> TrackFit:
    """Batch fit of the constant-twist prior to one candidate per frame: each frame's
    measured quantities (``image``) or, without them, its pose as a Gaussian prior (no
    robust kernel: the error is a likelihood). ``t_s`` increasing [s]; ``initial`` (poses,
    twists) warm start, else the candidates' poses and finite-difference twists. Degrees of
    freedom: the residuals' (``image.dim`` or 6 per frame) minus 6.

    ``shared`` > 0: the images' grouped residuals (``shared_groups``) share a bias per group
    over the track's frames (`image_factor`): a vector ``SHARED_BIAS`` with a zero-mean
    prior of variance ``shared`` (as many prior residuals as unknowns: the degrees of
    freedom do not change). A bias that every frame shows is then evidence once, not once
    per frame.

    ``plane_cap`` not None: the candidates' measured plane normals (``Candidate.plane``, two
    or more in the track) are weighed with one unknown normal in the target frame
    (`plane_factor`, truncated at ``plane_cap`` sigmas): two residuals per normal, two
    unknowns, so the degrees of freedom grow by ``2 (normals - 1)``."""
    n = len(candidates)
    if n == 0 or len(t_s) != n:
        raise BackendError(f"fit_track: {len(t_s)} times for {n} candidates")
    T = [c.pose.left_cam_from_target for c in candidates]
    dims = [c.image.dim if c.image is not None else 6 for c in candidates]
    if n == 1 and candidates[0].image is None:
        return TrackFit(0.0, 0, (T[0],), np.zeros((1, 6)))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(twist_prior_factor(0, motion))
    if initial is None:
        tw = [twist_between(T[i], T[i + 1], float(t_s[i + 1] - t_s[i])) for i in range(n - 1)]
        twists = np.array([*tw, tw[-1]]) if tw else np.zeros((1, 6))
        start = T
    else:
        start, twists = initial
    groups = [g for c in candidates if c.image is not None for g in c.image.shared_groups]
    if max(groups, default=-1) < 0:
        shared = 0.0
    if shared > 0.0:
        values.insert(SHARED_BIAS, np.zeros(SHARED_GROUPS))
        graph.add(
            gtsam.PriorFactorVector(
                SHARED_BIAS,
                np.zeros(SHARED_GROUPS),
                gtsam.noiseModel.Isotropic.Sigma(SHARED_GROUPS, math.sqrt(shared)),
            )
        )
    planes = {i: c.plane for i, c in enumerate(candidates) if c.plane is not None}
    if plane_cap is not None and len(planes) >= 2:
        ref = plane_reference([start[i] for i in planes], list(planes.values()))
        values.insert(PLANE_NORMAL, np.zeros(2))
        for i, plane in planes.items():
            graph.add(plane_factor(i, plane, ref, plane_cap))
        dims.append(2 * len(planes) - 2)
    for i, c in enumerate(candidates):
        if c.image is not None:
            graph.add(image_factor(i, c.image, shared))
        else:
            graph.add(pose_factor(c.pose, i, _GAUSSIAN))
        values.insert(X(i), to_state(start[i]))
        values.insert(V(i), np.asarray(twists[i], float))
        if i > 0:
            graph.add(constant_twist_factor(i - 1, i, float(t_s[i] - t_s[i - 1]), motion))
    # a likelihood to 1e-6 (relative) is all a ratio test of 6.9 needs
    sol = levenberg_marquardt(graph, values, 20, 1e-6, 1e-6)
    out = sol.values
    return TrackFit(
        float(sol.error),
        sum(dims) - 6,
        tuple(from_state(out.atPose3(X(i))) for i in range(n)),
        np.array([out.atVector(V(i)) for i in range(n)]),
    )


def _distance(a: Rigid3, b: Rigid3, centre: np.ndarray) -> tuple[float, float]:
    """(attitude difference [deg], distance between the two poses' images of ``centre`` [m])."""
    c = (float(np.trace(a.R.T @ b.R)) - 1.0) / 2.0
    ang = math.degrees(math.acos(max(-1.0, min(1.0, c))))
    return ang, float(np.linalg.norm(a.apply(centre[None])[0] - b.apply(centre[None])[0]))


@dataclass
class _Track:
    """One hypothesis: a candidate index per frame it explains (``picks``: frame position ->
    candidate index), its fit and cost."""

    picks: dict[int, int]
    fit: TrackFit
    image_cost: float
    misses: int
    cost: float = 0.0
    starts: dict[int, Rigid3] = field(default_factory=dict)

    @property
    def first(self) -> int:
        return min(self.picks)

    @property
    def last(self) -> int:
        return max(self.picks)


@dataclass(frozen=True)
class Decision:
    """What a frame reports.

    Attributes:
        frame: position of the frame in the sequence (0-based, in the order given).
        candidate: the index of the reported candidate among that frame's, or None.
        log_lr: the answering track's log-likelihood ratio over the best track that
            disagrees at this frame (or the null track); NaN when the frame had no candidate.
        reason: why nothing is reported ("" when a candidate is).
        tracks: how many tracks were alive.
        pose: the answering track's fitted pose at this frame (the candidate's measured
            quantities weighed with the motion; the best track's, or where it leaves the
            frame out the best track of the same hypothesis that explains it) or, where no
            track of the hypothesis explains it, that track's prediction there
            (`SequenceLabeller._answer_at`); or None.
    """

    frame: int
    candidate: int | None
    log_lr: float
    reason: str
    tracks: int
    pose: Rigid3 | None = None


class SequenceLabeller:
    """Bounded multi-hypothesis tracking of per-frame candidate poses with a sequential
    likelihood-ratio decision (module docstring).

    Call `step` once per frame in time order (an empty candidate list for a frame without
    any); `online_decision` is frame ``k``'s report from frames ``0..k``, `decide` the report of
    every frame from all frames seen (offline).

    Args:
        centre_m: target-frame point at which positions are compared (the bracket's
            centroid), (3,).
        config: settings.
    """

    def __init__(self, centre_m: np.ndarray, config: LabellingConfig | None = None) -> None:
        self.config = LabellingConfig() if config is None else config
        self.centre = np.asarray(centre_m, dtype=float).reshape(3)
        self.t_s: list[float] = []
        self.candidates: list[list[Candidate]] = []
        self.tracks: list[_Track] = []
        self.fits = 0

    # -- tracks ----------------------------------------------------------------------------

    def _frames_with_candidates(self) -> int:
        return sum(1 for c in self.candidates if c)

    def _score(self, tr: _Track) -> float:
        cfg = self.config
        explained = len(tr.picks)
        misses = self._frames_with_candidates() - explained
        tr.misses = misses
        return (
            (tr.fit.error - 0.5 * tr.fit.dof)
            + cfg.image_weight * tr.image_cost
            + cfg.miss_cost * misses
        )

    def _fit(
        self, picks: dict[int, int], parent: _Track | None, start: Rigid3 | None = None
    ) -> TrackFit:
        ks = sorted(picks)
        t = np.array([self.t_s[k] for k in ks])
        cands = [self.candidates[k][picks[k]] for k in ks]
        init = None
        if parent is not None and len(parent.fit.poses) == len(ks) - 1:
            # warm start: the parent's solution and the new pose (or ``start``) with the
            # last twist
            new = cands[-1].pose.left_cam_from_target if start is None else start
            init = (
                [*parent.fit.poses, new],
                np.vstack([parent.fit.twists, parent.fit.twists[-1:]]),
            )
        self.fits += 1
        return fit_track(
            t, cands, self.config.motion, init, self.config.shared_variance, self._plane_cap()
        )

    def _plane_cap(self) -> float | None:
        return self.config.plane_cap if self.config.plane_normals else None

    def _added_dim(self, c: Candidate) -> int:
        """The quantities a candidate adds to a track's fit: its image's and, when weighed,
        its plane normal's."""
        image = c.image.dim if c.image is not None else 6
        return image + (2 if self.config.plane_normals and c.plane is not None else 0)

    def _image_cost(self, picks: dict[int, int]) -> float:
        return sum(
            0.5 * (self.candidates[k][j].image_chi2 - self.candidates[k][j].image_dim)
            for k, j in picks.items()
        )

    def _prediction(self, tr: _Track, k: int) -> Rigid3:
        last = tr.last
        T = tr.fit.poses[-1]
        if len(tr.picks) < 2:
            return T
        return predict(T, tr.fit.twists[-1], self.t_s[k] - self.t_s[last])

    def _fit_gate(self, dim: int) -> float:
        return float(chi2.ppf(self.config.fit_gate_quantile, dim))

    def _in_gate(self, pose: Rigid3, pred: Rigid3) -> bool:
        ang, dist = _distance(pose, pred, self.centre)
        rng = float(np.linalg.norm(pred.apply(self.centre[None])[0]))
        return ang <= self.config.gate_deg and dist <= self.config.gate_rel * rng + 0.02

    def _in_chi2_gate(self, pose: Rigid3, pred: Rigid3, S: np.ndarray) -> bool:
        """Whether ``pose`` is within ``gate_chi2`` of the prediction ``pred``, their
        difference having covariance ``S``."""
        d = local_error(pred, pose)
        return float(d @ np.linalg.solve(S, d)) <= self.config.gate_chi2

    def _prediction_covariance(self, tr: _Track, f: int, k: int) -> np.ndarray:
        """The spread of the track's prediction at frame ``k`` from its frame ``f``: that
        frame's candidate covariance plus the motion's over the gap."""
        last = self.candidates[f][tr.picks[f]].pose.covariance
        return last + process_covariance(self.t_s[k] - self.t_s[f], self.config.motion)[:6, :6]

    def _image_gate(self, image: ImageResidual, pred: Rigid3, cov: np.ndarray) -> bool:
        """Whether the predicted pose (covariance ``cov``) explains the measured quantities
        within ``gate_chi2``: ``r^T (I + J cov J^T)^-1 r`` at the prediction."""
        r, J = image.residual_and_jacobian(pred)
        S = np.eye(len(r)) + J @ cov @ J.T
        return float(r @ np.linalg.solve(S, r)) <= self.config.gate_chi2

    def step(self, t_s: float, candidates: list[Candidate]) -> None:
        """Add the next frame (time ``t_s`` [s], increasing) with its candidate poses (an
        empty list: nothing consistent found). Nothing changes if it raises."""
        if self.t_s and not t_s > self.t_s[-1]:
            raise BackendError(f"frame times must increase: {t_s} after {self.t_s[-1]}")
        cands = list(candidates)
        k = len(self.t_s)
        self.t_s.append(float(t_s))
        self.candidates.append(cands)
        try:
            self.tracks = self._extend(k, cands)
        except Exception:
            del self.t_s[-1], self.candidates[-1]
            raise

    def _extend(self, k: int, candidates: list[Candidate]) -> list[_Track]:
        cfg = self.config
        new: list[_Track] = []
        used: set[int] = set()
        for tr in self.tracks:
            if k - tr.last > cfg.max_gap + 1:
                new.append(tr)  # too long without a candidate: kept as it is, not continued
                continue
            pred = self._prediction(tr, k)
            spread = self._prediction_covariance(tr, tr.last, k)
            hit = [
                j
                for j, c in enumerate(candidates)
                if self._in_gate(c.pose.left_cam_from_target, pred)
                or self._in_chi2_gate(c.pose.left_cam_from_target, pred, c.pose.covariance + spread)
            ]
            for j in hit:
                picks = {**tr.picks, k: j}
                fit = self._fit(picks, tr)
                new.append(_Track(picks, fit, self._image_cost(picks), 0))
                self._use(used, j, candidates[j], fit)
            # a candidate outside the prediction's gate still continues the track when the
            # refit with it explains it within the noise (the fit's chi-square grows by at
            # most ``fit_gate_quantile`` of its quantities' count): a track's prediction is
            # only as good as its own history, and a wrong track's history can hold the
            # true hypothesis's frames (tuning seed 2: the true pose of frame 8 lay 17 deg
            # from the prediction of the track that carried frames 0-7 for both)
            if len(tr.picks) >= 2:
                for j, c in enumerate(candidates):
                    if j in hit or c.image is None:
                        continue
                    picks = {**tr.picks, k: j}
                    fit = self._fit(picks, tr)
                    if 2.0 * (fit.error - tr.fit.error) <= self._fit_gate(self._added_dim(c)):
                        new.append(_Track(picks, fit, self._image_cost(picks), 0))
                        self._use(used, j, c, fit)
            # every group of measured quantities that the predicted pose explains, also fitted
            # from the prediction: the track's likelihood is a function of the quantities,
            # and a candidate pose only chooses the basin the fit ends in. Started only from
            # the candidates, a track whose own solution has vanished (the true pair of P3P
            # roots turned complex in noise) is pulled into a neighbouring root's basin when
            # that root lies within the gate, and the hypothesis is lost (tuning seed 2,
            # frames 4-7). Where both starts end in one basin the two are one track (below).
            if len(tr.picks) >= 2:
                for g in sorted({c.group for c in candidates if c.group >= 0}):
                    j = next(i for i, c in enumerate(candidates) if c.group == g)
                    image = candidates[j].image
                    if image is not None and self._image_gate(image, pred, spread):
                        picks = {**tr.picks, k: j}
                        fit = self._fit(picks, tr, pred)
                        new.append(_Track(picks, fit, self._image_cost(picks), 0))
            new.append(tr)  # the track without this frame's candidates (a miss if any)
        for j in range(len(candidates)):
            if j not in used:
                picks = {k: j}
                new.append(_Track(picks, self._fit(picks, None), self._image_cost(picks), 0))
        # a track that starts late reaches back over the earlier frames its motion explains:
        # a neighbouring P3P root that lies within the rival distance of the truth in the
        # first frames is carried there by the true track, and its own track only starts
        # where the two part. Charged a miss for every earlier frame, that rival was a
        # mutilated copy of the hypothesis (tuning seed 0 on its exact images: the root
        # 4-14 deg from the truth started at frame 5 and lost by 15 = 5 misses; rendered,
        # where noise kept it apart from frame 0, it tied with the truth)
        if cfg.reach_back:
            new += [
                back
                for tr in list(new)
                if k in tr.picks and len(tr.picks) >= 2 and tr.first > 0
                for back in [self._reach_back(tr)]
                if back is not None
            ]
        for tr in new:
            tr.cost = self._score(tr)
        # one track per hypothesis: a track whose fitted poses agree with a better one's at
        # every frame it explains, and which explains no frame the better one does not
        # (the same hypothesis reached twice, from two starts in one basin, or with frames
        # left out), is dropped. Kept, such copies of the leading hypothesis filled the
        # pool (11 of 16 tracks on tuning seed 2) and pushed out the one that disagreed.
        kept: list[_Track] = []
        for tr in sorted(new, key=lambda x: x.cost):
            if len(kept) >= cfg.max_tracks:
                break
            if any(self._covered(tr, q) for q in kept):
                continue
            kept.append(tr)
        return kept

    def _reach_back(self, tr: _Track) -> _Track | None:
        """``tr`` carried back frame by frame (to the nearest earlier frame with candidates,
        at most ``max_gap + 1`` back) while a group of that frame's measured quantities lies
        within the image gate of the track's backward prediction and the refit from that
        prediction raises the fit's chi-square by at most the fit gate; the lowest-error
        group each time. None when not even one frame is added."""
        cfg = self.config
        cur: _Track | None = None
        at = tr
        while at.first > 0:
            f0 = at.first
            f = next(
                (g for g in range(f0 - 1, max(-1, f0 - 2 - cfg.max_gap), -1) if self.candidates[g]),
                None,
            )
            if f is None:
                break
            dt = self.t_s[f] - self.t_s[f0]
            pred = predict(at.fit.poses[0], at.fit.twists[0], dt)
            first = self.candidates[f0][at.picks[f0]].pose.covariance
            cov = first + process_covariance(-dt, cfg.motion)[:6, :6]
            best: _Track | None = None
            seen: set[int] = set()
            for j, c in enumerate(self.candidates[f]):
                if c.image is None or (c.group >= 0 and c.group in seen):
                    continue
                seen.add(c.group)
                if not self._image_gate(c.image, pred, cov):
                    continue
                picks = {f: j, **at.picks}
                ks = sorted(picks)
                init = ([pred, *at.fit.poses], np.vstack([at.fit.twists[:1], at.fit.twists]))
                self.fits += 1
                fit = fit_track(
                    np.array([self.t_s[i] for i in ks]),
                    [self.candidates[i][picks[i]] for i in ks],
                    cfg.motion,
                    init,
                    cfg.shared_variance,
                    self._plane_cap(),
                )
                if 2.0 * (fit.error - at.fit.error) > self._fit_gate(self._added_dim(c)):
                    continue
                if best is None or fit.error < best.fit.error:
                    best = _Track(picks, fit, self._image_cost(picks), 0)
            if best is None:
                break
            cur = at = best
        return cur

    def _use(self, used: set[int], j: int, cand: Candidate, fit: TrackFit) -> None:
        """Mark candidate ``j`` as followed when the extended track's fitted pose at the new
        frame agrees with it: an extension whose fit ended in another basin does not stand
        for the candidate, which then starts a track of its own (else no track would carry
        that alternative, and a decision against it would be against nothing)."""
        if not self._disagree(cand.pose.left_cam_from_target, fit.poses[-1]):
            used.add(j)

    def _covered(self, a: _Track, b: _Track) -> bool:
        """Whether ``b`` explains every frame ``a`` explains, with fitted poses that agree
        (within the rival distance) at each of them."""
        if not set(a.picks) <= set(b.picks):
            return False
        kb = sorted(b.picks)
        return all(
            not self._disagree(p, b.fit.poses[kb.index(f)])
            for f, p in zip(sorted(a.picks), a.fit.poses, strict=True)
        )

    def predictions(self, t_s: float, n: int = 3) -> list[Rigid3]:
        """The constant-twist predictions at time ``t_s`` of the ``n`` best tracks that were
        continued within the last ``max_gap + 1`` frames, one per hypothesis (predictions
        within the rival distance of a better track's are left out): where a detector
        searching near a prediction may find a pose its open search missed."""
        k = len(self.t_s)
        out: list[Rigid3] = []
        for tr in self.tracks:
            if len(out) >= n:
                break
            if k - tr.last > self.config.max_gap + 1:
                continue
            T = tr.fit.poses[-1]
            if len(tr.picks) >= 2:
                T = predict(T, tr.fit.twists[-1], t_s - self.t_s[tr.last])
            if all(self._disagree(T, q) for q in out):
                out.append(T)
        return out

    # -- decisions -------------------------------------------------------------------------

    def _pose_at(self, tr: _Track, k: int) -> Rigid3 | None:
        """The track's fitted pose at frame ``k``: at its frames, else predicted from the
        previous one within its span, else None (outside its span)."""
        ks = sorted(tr.picks)
        if k in tr.picks:
            return tr.fit.poses[ks.index(k)]
        if not ks[0] < k < ks[-1]:
            return None
        i = max(i for i, f in enumerate(ks) if f < k)
        return predict(tr.fit.poses[i], tr.fit.twists[i], self.t_s[k] - self.t_s[ks[i]])

    def _answer_at(self, tr: _Track, k: int) -> Rigid3 | None:
        """What the track says the pose is at frame ``k``: `_pose_at`, or beyond its ends its
        constant-twist prediction from the nearest end, at most ``max_gap + 1`` frames away
        (as far as a track is continued without a candidate); else None."""
        pose = self._pose_at(tr, k)
        if pose is not None or len(tr.picks) < 2:
            return pose
        end = tr.last if k > tr.last else tr.first
        if abs(k - end) > self.config.max_gap + 1:
            return None
        i = -1 if end == tr.last else 0
        return predict(tr.fit.poses[i], tr.fit.twists[i], self.t_s[k] - self.t_s[end])

    def agree(self, a: Rigid3, b: Rigid3) -> bool:
        """Whether two poses of the target are the same answer: within the rival distance
        (``rival_deg`` in attitude and ``rival_rel`` x range at the centre)."""
        return not self._disagree(a, b)

    def _disagree(self, a: Rigid3, b: Rigid3 | None) -> bool:
        """Whether ``b`` is another answer than ``a``: farther than the rival distance."""
        if b is None:
            return True
        ang, dist = _distance(a, b, self.centre)
        rng = float(np.linalg.norm(a.apply(self.centre[None])[0]))
        return ang > self.config.rival_deg or dist > self.config.rival_rel * rng

    def _rival(self, best: _Track, tr: _Track, k: int, mine: Rigid3 | None = None) -> bool:
        """Whether track ``tr`` gives another answer than ``best`` at frame ``k``: its pose
        there disagrees with ``best``'s (``mine``; None: `_pose_at`), or it has none there (a
        gap or outside its span) and disagrees with ``best`` at a frame where both have one.
        A track that agrees wherever both have a pose (e.g. ``best`` without its last frame)
        is no rival. Nor is a track of the same hypothesis (`_same_hypothesis`) that skips
        frame ``k`` inside its span when ``mine`` lies within the noise of its prediction
        there (`_within_prediction`): it claims no other candidate at ``k``, and its
        constant-twist prediction across the frames it skips is not another labelling
        (tuning seed 74: at 0.6 m a side-lit vertex drifts, the track through every frame
        fits the motion worse than copies that skip frames 8-10, and those copies'
        predictions there lay 59-86 mm from the answer, beyond the rival distance, so the
        true labelling was refused). Beyond that noise its prediction still counts: the
        hypothesis' own motion then says the frame's answer is something else."""
        mine = self._pose_at(best, k) if mine is None else mine
        assert mine is not None
        other = self._pose_at(tr, k)
        if other is not None and k in tr.picks:
            return self._disagree(mine, other)
        if (
            other is not None
            and self._same_hypothesis(tr, best)
            and self._within_prediction(tr, k, mine)
        ):
            return False
        if other is not None and self._disagree(mine, other):
            return True
        for f in best.picks:
            if f == k:
                continue
            theirs = self._pose_at(tr, f)
            ours = self._pose_at(best, f)
            if theirs is None or ours is None:
                continue
            if self._disagree(ours, theirs):
                return True
        return False

    def _within_prediction(self, tr: _Track, k: int, pose: Rigid3) -> bool:
        """Whether ``pose`` is within ``gate_chi2`` of the track's prediction at frame ``k``
        (inside its span, not one of its frames) from its previous frame, with that
        prediction's spread (`_prediction_covariance`, the gate a track is continued with,
        without a candidate's own covariance)."""
        prev = max(f for f in tr.picks if f < k)
        pred = self._pose_at(tr, k)
        assert pred is not None
        return self._in_chi2_gate(pose, pred, self._prediction_covariance(tr, prev, k))

    def _decide_frame(self, k: int) -> Decision:
        n = len(self.tracks)
        if not self.candidates[k]:
            return Decision(k, None, math.nan, "no consistent pose", n)
        null_cost = self.config.miss_cost * self._frames_with_candidates()
        best = min(self.tracks, key=lambda x: x.cost) if self.tracks else None
        if best is None:
            return Decision(k, None, 0.0, "the best track has no pose here", n)
        # who answers for frame k: the best track, or where it leaves the frame out (its
        # candidates there cost more than a miss, e.g. one strut's taper measured far off
        # while p1, p2, the directions and the stub lengths fit: tuning seeds 31 and 35) a
        # track of the same hypothesis (it agrees with the best track wherever both have a
        # pose): the best one that explains the frame, else the best one that predicts it
        # (within its span, or at most ``max_gap + 1`` frames beyond its ends) with the
        # frame's candidate that agrees with that prediction. The answer is then decided as
        # any other: against every track that disagrees there (the best one included), from
        # the answering track's cost
        subject, pick, mine = best, best.picks.get(k), self._pose_at(best, k)
        if pick is None:
            family = sorted(
                [tr for tr in self.tracks if tr is best or self._same_hypothesis(tr, best)],
                key=lambda x: x.cost,
            )
            explain = [tr for tr in family if k in tr.picks]
            if explain:
                subject = explain[0]
                pick, mine = subject.picks[k], self._pose_at(subject, k)
            else:
                for tr in family:
                    mine = self._answer_at(tr, k)
                    pick = None if mine is None else self._agreeing_candidate(k, mine)
                    if pick is not None:
                        subject = tr
                        break
                if pick is None:
                    return Decision(k, None, 0.0, "the best track has no pose here", n)
        assert pick is not None and mine is not None
        rival = min(
            [
                tr.cost
                for tr in self.tracks
                if tr is not subject and self._rival(subject, tr, k, mine)
            ]
            + [null_cost]
        )
        lr = rival - subject.cost
        if lr >= self.config.log_lr_threshold:
            return Decision(k, pick, lr, "", n, mine)
        return Decision(
            k,
            None,
            lr,
            f"labelling ambiguous over frames: log-likelihood ratio {lr:.1f} "
            f"(need {self.config.log_lr_threshold:.1f}) among {n} tracks",
            n,
        )

    def _same_hypothesis(self, a: _Track, b: _Track) -> bool:
        """Whether two tracks are one hypothesis: they share a frame, and their fitted poses
        agree (within the rival distance) at every frame both explain."""
        ka, kb = sorted(a.picks), sorted(b.picks)
        common = set(ka) & set(kb)
        return bool(common) and all(
            self.agree(a.fit.poses[ka.index(f)], b.fit.poses[kb.index(f)]) for f in common
        )

    def _agreeing_candidate(self, k: int, pose: Rigid3) -> int | None:
        """The candidate of frame ``k`` nearest ``pose`` (attitude and position, each over
        its rival distance) among those that agree with it, or None."""
        cfg = self.config
        rng = float(np.linalg.norm(pose.apply(self.centre[None])[0]))
        near = []
        for j, c in enumerate(self.candidates[k]):
            q = c.pose.left_cam_from_target
            if self._disagree(pose, q):
                continue
            ang, dist = _distance(pose, q, self.centre)
            near.append(((ang / cfg.rival_deg) ** 2 + (dist / (cfg.rival_rel * rng)) ** 2, j))
        return min(near)[1] if near else None

    def online_decision(self) -> Decision:
        """The last frame's report from the frames seen so far."""
        if not self.t_s:
            raise BackendError("online_decision before the first step")
        return self._decide_frame(len(self.t_s) - 1)

    def decide(self) -> list[Decision]:
        """Every frame's report from all frames seen (offline)."""
        return [self._decide_frame(k) for k in range(len(self.t_s))]
