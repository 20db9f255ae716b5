"""``online``: iSAM2, updated once per frame.

`OnlineEstimator.filtered` is the estimate each frame had right after its own update (what a
real-time tracker would have reported); `estimate` is the current smoothed trajectory.

Cost (docs/backend.md, "iSAM2 cost"): the constant-twist prior is stiff and the target frame
is fixed by estimated variables (ring centre, anchor landmark), so every new frame moves the
whole smoothed trajectory a little, and the landmarks and ring radii are shared by many
frames: relinearising old states or a shared variable re-eliminates most of the Bayes tree.
During the online loop, variables are relinearised freely only while they are being learned:
the states of the last ``relinearize_window`` frames and the landmarks and radii that entered
the graph within that many frames. Older variables keep their linearisation point (they are
still updated through the linear system) until their delta exceeds
``held_relinearize_factor`` times the ordinary threshold, which bounds the linearisation
error. `OnlineEstimator.estimate` relinearises everything in its final updates. The
elimination order puts the newest state last, the keys of the new factors and the recent
states before it, so the Bayes tree's root holds the frames that change.

Warm-up: until two frames have fixed a whole pose, the twist is known only from its weak
prior and the linear system is too ill-conditioned for iSAM2's Cholesky factorisation
(`satpose.backend.solve`). Those first frames are solved in batch (Levenberg-Marquardt, dense
marginals); the whole warm-up graph then enters iSAM2 in one update, initialised at that
solution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from satpose.backend.errors import BackendError
from satpose.backend.estimate import Estimate, Hook, StepReport
from satpose.backend.factors import FactorClock, MeasurementConfig
from satpose.backend.graph import GraphBuilder, GraphUpdate
from satpose.backend.keys import (
    BIAS_CHAR,
    LANDMARK_CHAR,
    POSE_CHAR,
    RADIUS_CHAR,
    RIG_CHAR,
    TWIST_CHAR,
    L,
    V,
    X,
)
from satpose.backend.motion import MotionConfig
from satpose.backend.offline import estimate_from_values, not_started_message
from satpose.backend.pose3 import from_state, state_covariance_to_pose, tangent
from satpose.backend.solve import Covariances, levenberg_marquardt
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration
from satpose.frontend.measurements import FrameMeasurements


@dataclass(frozen=True, kw_only=True)
class Isam2Config:
    """iSAM2 settings.

    A variable is relinearised when a component of its tangent delta exceeds its type's
    threshold (per component). The pose variable is the camera in the target frame
    (`satpose.backend.pose3`): its translation moves by the 3-7 m lever arm times any
    rotation change, so its threshold is that of the rotation times a few metres. The twists
    are ~100x smaller than the poses' increments (0.035 rad/s, cm/s). The ring radius is
    shared by every ring factor and measured to ~0.2 mm per frame. Measured on a 100-frame
    tight sequence (docs/backend.md): these defaults keep iSAM2's final estimate within
    0.01 sigma of the batch solution; 3x coarser ones halve the update time for 0.1 sigma.
    Variables outside ``relinearize_window`` use ``held_relinearize_factor`` times these
    thresholds until `OnlineEstimator.estimate`.

    Attributes:
        relinearize_rotation: threshold for the rotation part of poses [rad].
        relinearize_translation: threshold for the translation part of poses [m].
        relinearize_twist: threshold for twists [rad/s and m/s].
        relinearize_landmark: threshold for landmarks [m].
        relinearize_radius: threshold for the ring radius [m]. A stale linearisation point
            would give every ring factor a stale robust weight (GTSAM computes it when it
            linearises).
        relinearize_bias: threshold for the ring edges' common disparity bias [px].
        relinearize_rig: threshold for the rig as the landmarks see it (``RIG``, with
            ``landmark_disparity_bias_px``; rotation [rad] and translation [m]: only its yaw
            moves, by about bias / f, ~1e-4 rad).
        relinearize_window: during the online loop only the states of the newest this many
            frames (besides the new one) and the landmarks and ring radii that entered the
            graph within this many frames are relinearised at the thresholds above; None:
            every variable. Measured on the rendered presets (docs/backend.md, "iSAM2 cost"):
            with 5 the update's median CPU time drops 1.7-2.9x (2.9-6.9x over the last 10
            frames), the filtered mean errors move by < 0.015 cm / deg (single poses by up to
            0.07 cm / 0.32 deg), and the final estimate is as close to the batch solution as
            without the window.
        held_relinearize_factor: the variables outside the window are relinearised once a
            component of their delta exceeds this many times its threshold (the gauge and
            depth corrections move the whole trajectory: held poses reach 40x the threshold
            on paper-docking without this bound). 3: nearly no saving; 10: the default.
        relinearize_skip: check for relinearisation every this many updates.
        extra_updates: additional ``update()`` calls (Gauss-Newton steps) per frame.
        final_updates: at most this many ``update()`` calls without new factors before
            `OnlineEstimator.estimate` reads the smoothed solution (stops as soon as nothing
            is relinearised): the newest frames have had one Gauss-Newton step only, and
            robust weights are recomputed only on relinearisation.
        factorization: ``cholesky`` (fast) or ``qr`` (more robust to ill-conditioning).
    """

    relinearize_rotation: float = 1e-3
    relinearize_translation: float = 3e-3
    relinearize_twist: float = 1e-4
    relinearize_landmark: float = 1e-3
    relinearize_radius: float = 1e-5
    relinearize_bias: float = 1e-2
    relinearize_rig: float = 1e-5
    relinearize_window: int | None = 5
    held_relinearize_factor: float = 10.0
    relinearize_skip: int = 1
    extra_updates: int = 0
    final_updates: int = 10
    factorization: Literal["cholesky", "qr"] = "cholesky"

    def __post_init__(self) -> None:
        for name in (
            "relinearize_rotation",
            "relinearize_translation",
            "relinearize_twist",
            "relinearize_landmark",
            "relinearize_radius",
            "relinearize_bias",
            "relinearize_rig",
        ):
            if not getattr(self, name) > 0:
                raise BackendError(f"online.{name} must be positive")
        if self.relinearize_window is not None and self.relinearize_window < 0:
            raise BackendError("online.relinearize_window must be >= 0 (or None)")
        if not self.held_relinearize_factor >= 1:
            raise BackendError("online.held_relinearize_factor must be >= 1")
        if self.relinearize_skip < 1 or self.extra_updates < 0 or self.final_updates < 0:
            raise BackendError("online: relinearize_skip >= 1, extra/final_updates >= 0 required")
        if self.factorization not in ("cholesky", "qr"):
            raise BackendError(f"online.factorization: cholesky or qr, got {self.factorization}")


@dataclass
class _Filtered:
    pose: Rigid3
    twist: np.ndarray
    pose_cov: np.ndarray
    twist_cov: np.ndarray


def _merged(
    first: tuple[gtsam.NonlinearFactorGraph, gtsam.Values],
    then: tuple[gtsam.NonlinearFactorGraph, gtsam.Values],
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Two updates' factors and new values as one."""
    factors = gtsam.NonlinearFactorGraph()
    factors.push_back(first[0])
    factors.push_back(then[0])
    values = gtsam.Values(first[1])
    extra = gtsam.Values(then[1])
    for key in then[1].keys():
        if values.exists(key):
            extra.erase(key)
    values.insert(extra)
    return factors, values


_UNKNOWN_SIGMA = np.r_[np.full(3, 1.0), np.full(3, 10.0)]
"""Standard deviations (rotation [rad] or angular rate [rad/s], then translation [m] or
velocity [m/s]) stated for a frame whose update failed and that reports its prediction
(`OnlineEstimator._degrade`): not an estimate of the error, a statement that there is none."""


def _gtsam_message(exc: RuntimeError) -> str:
    """GTSAM's message in one line: its first two lines (what and near which key)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return " ".join(lines[:2]) or type(exc).__name__


class OnlineEstimator:
    """iSAM2 tracker: one incremental update per frame."""

    name = "online"

    def __init__(
        self,
        calibration: Calibration,
        *,
        motion: MotionConfig,
        measurements: MeasurementConfig,
        config: Isam2Config,
        hook: Hook | None = None,
    ) -> None:
        self.config = config
        self.hook = hook
        self.clock = FactorClock()
        self.builder = GraphBuilder(calibration, motion, measurements, self.clock)
        params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()
        thresholds_by_char = (
            (
                POSE_CHAR,
                tangent(
                    np.full(3, config.relinearize_rotation),
                    np.full(3, config.relinearize_translation),
                ),
            ),
            (TWIST_CHAR, np.full(6, config.relinearize_twist)),
            (LANDMARK_CHAR, np.full(3, config.relinearize_landmark)),
            (RADIUS_CHAR, np.full(1, config.relinearize_radius)),
            (BIAS_CHAR, np.full(1, config.relinearize_bias)),
            (RIG_CHAR, np.full(6, config.relinearize_rig)),
        )
        for char, value in thresholds_by_char:
            thresholds.insert((char, value))
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = config.relinearize_skip
        params.setFactorization("CHOLESKY" if config.factorization == "cholesky" else "QR")
        self._params = params
        self.isam = gtsam.ISAM2(params)
        self._filtered: dict[int, _Filtered] = {}
        # relinearisation window: held keys, and landmarks/radii by the state they entered at
        self._thresholds = dict(thresholds_by_char)
        self._held_keys: list[int] = []
        self._held_thresholds = np.zeros(0)  # the held keys' thresholds, concatenated
        self._held_starts: list[int] = []  # where each held key starts in that vector
        self._held = gtsam.KeyList()  # this update's hold list
        self._held_states = 0  # states 0 .. _held_states - 1 are held
        self._entered: dict[int, int] = {}
        self._estimate: Estimate | None = None
        # warm-up (see the module docstring)
        self._released = False
        self._staged = gtsam.NonlinearFactorGraph()
        self._staged_values = gtsam.Values()
        self._warm: gtsam.Values | None = None
        self._warm_estimate: Estimate | None = None
        self.final_note: str | None = None
        """Why `estimate` gave iSAM2's estimate without its final updates (None: it did not)."""
        self._pending: tuple[gtsam.NonlinearFactorGraph, gtsam.Values] | None = None
        """The factors and new values of an update that raised: they enter with the next."""

    def add(self, measurements: FrameMeasurements) -> None:
        """Add one frame and update iSAM2; records the frame's filtered estimate."""
        t0 = time.perf_counter()
        update = self.builder.add(measurements, prefer="prediction")
        t1, p1 = time.perf_counter(), time.process_time()
        c0 = self.clock.seconds
        timings = {"build": 1e3 * (t1 - t0)}
        relinearized: int | None = None
        notes = list(update.notes)
        if not self._released:
            self._staged.push_back(update.factors)
            self._staged_values.insert(update.values)
        try:
            relinearized = self._update(update, timings, notes, t1, p1)
        except Exception:
            self._degrade(update.created)
            self._estimate = None
            raise
        timings["python_factors"] = 1e3 * (self.clock.seconds - c0)
        self._estimate = None
        if self.hook is not None:
            self.hook(
                StepReport(
                    estimator=self.name,
                    step="add",
                    frame=int(measurements.frame),
                    timings_ms=timings,
                    factors=(
                        self.isam.getFactorsUnsafe() if self._released else self._staged
                    ).size(),
                    variables=self.isam.size() if self._released else self._staged_values.size(),
                    new_factors=update.factors.size(),
                    relinearized=relinearized,
                    notes=tuple(notes),
                )
            )

    def _degrade(self, created: list[int]) -> None:
        """The frames an update that raised has created get their prediction (the builder's
        initial value: the constant-twist prediction from the last estimate) as their filtered
        estimate, with `_UNKNOWN_SIGMA` standard deviations: the run goes on and says so (the
        exception is the frame's failure note); the smoothed estimate (`estimate`) estimates
        them from everything, if iSAM2 recovers."""
        for i in created:
            if i not in self._filtered:
                pose, twist = self.builder.hint(i)
                cov = np.diag(np.square(_UNKNOWN_SIGMA))
                self._filtered[i] = _Filtered(pose, twist, cov, cov.copy())

    def _update(
        self,
        update: GraphUpdate,
        timings: dict[str, float],
        notes: list[str],
        t1: float,
        p1: float,
    ) -> int | None:
        """Warm-up or iSAM2 update of one frame's factors; the frames' filtered estimates."""
        relinearized: int | None = None
        if update.created and not self._released and self.builder.full_frames < 2:
            self._warm_up(update.created)
            timings["warm_up"] = 1e3 * (time.perf_counter() - t1)
            notes.append("warm-up: batch solve (twist not yet determined)")
        elif update.created or self._released:
            first = not self._released
            if first:
                factors, values = self._staged, gtsam.Values(self._staged_values)
                if self._warm is not None:
                    values.update(self._warm)
                self._released = True
            else:
                factors, values = update.factors, update.values
            if self._pending is not None:  # an update that raised: its factors enter now
                factors, values = _merged(self._pending, (factors, values))
            self._pending = (factors, values)
            newest = update.created[-1] if update.created else len(self.builder) - 1
            hold = self._hold(values, newest, first)
            stored = self.isam.getFactorsUnsafe().size()
            try:
                result = self.isam.update(
                    factors, values, [], self._ordering(factors, newest), hold
                )
                relinearized = result.getVariablesRelinearized()
                held = None if self.config.relinearize_window is None else self._held
                for _ in range(self.config.extra_updates):
                    relinearized += self.isam.update(
                        gtsam.NonlinearFactorGraph(), gtsam.Values(), [], None, held
                    ).getVariablesRelinearized()
            except RuntimeError as exc:
                relinearized = self._restart(exc, factors, values, stored, notes)
            self._pending = None
            t2 = time.perf_counter()
            timings["update"] = 1e3 * (t2 - t1)
            timings["update_cpu"] = 1e3 * (time.process_time() - p1)
            for i in update.created:
                X_i = self.isam.calculateEstimatePose3(X(i))
                pose = from_state(X_i)
                twist = np.asarray(self.isam.calculateEstimateVector(V(i)), float)
                pose_cov = state_covariance_to_pose(X_i, self.isam.marginalCovariance(X(i)))
                twist_cov = self.isam.marginalCovariance(V(i))
                self.builder.set_hint(i, pose, twist, (pose_cov, twist_cov))
                self._filtered[i] = _Filtered(pose, twist, pose_cov, twist_cov)
            timings["estimate"] = 1e3 * (time.perf_counter() - t2)
        return relinearized

    def _restart(
        self,
        exc: RuntimeError,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stored: int,
        notes: list[str],
    ) -> int:
        """Recover from an update that threw (it leaves iSAM2's Bayes tree unusable).

        Seen in a live run with dropped frames: a landmark whose linearisation point had run
        away along its viewing ray (the relinearisation window's held variables) ended up
        behind every camera that saw it; its projection factors then have no gradient and
        the system is indeterminate. Such *dead* landmarks (every factor's Jacobian on them
        zero at iSAM2's linearisation point) are dropped with their factors and start again
        at their next sighting; the rest of the graph, this frame's factors included, is
        solved again (Levenberg-Marquardt from the linearisation point) and iSAM2 restarts
        there. With nothing dead the whole graph is solved again the same way: a system that
        iSAM2's undamped update finds indeterminate at its linearisation point can still
        be solved by Levenberg-Marquardt's damped steps, and iSAM2 restarts from there. The
        frame's notes say so. Raises the original error if the anchor was dead or the
        restart fails too (`add` then reports the frame's prediction, `_degrade`)."""
        why = _gtsam_message(exc)
        old = self.isam.getFactorsUnsafe()
        graph = gtsam.NonlinearFactorGraph()
        for n in range(old.size()):
            if old.exists(n):
                graph.push_back(old.at(n))
        if old.size() == stored:  # the failed update had not stored its factors
            graph.push_back(factors)
        theta = gtsam.Values(self.isam.getLinearizationPoint())
        missing = gtsam.Values(values)
        for key in values.keys():
            if theta.exists(key):
                missing.erase(key)
        theta.insert(missing)
        live: set[int] = set()
        seen: set[int] = set()
        for n in range(graph.size()):
            f = graph.at(n)
            for k in f.keys():
                if chr(gtsam.Symbol(k).chr()) != LANDMARK_CHAR or k in live:
                    continue
                seen.add(k)
                A = f.linearize(theta).jacobian()[0]  # columns in the factor's key order
                offset = 0
                for kk in f.keys():
                    d = len(self._thresholds[chr(gtsam.Symbol(kk).chr())])  # its dimension
                    if kk == k and np.any(A[:, offset : offset + d]):
                        live.add(k)
                    offset += d
        dead = seen - live
        anchor = self.builder.anchor
        if anchor is not None and L(anchor) in dead:
            raise exc
        kept = gtsam.NonlinearFactorGraph()
        for n in range(graph.size()):
            if not set(graph.at(n).keys()) & dead:
                kept.push_back(graph.at(n))
        for k in dead:
            theta.erase(k)
            self._entered.pop(k, None)
            self.builder.forget_landmark(gtsam.Symbol(k).index())
        if set(self._held_keys) & dead:
            keep = [k for k in self._held_keys if k not in dead]
            self._held_keys, self._held_starts, self._held_thresholds = [], [], np.zeros(0)
            self._add_held(keep)
        try:
            theta = levenberg_marquardt(kept, theta, 100, 1e-10, 1e-12).values
            self.isam = gtsam.ISAM2(self._params)
            relinearized = int(self.isam.update(kept, theta).getVariablesRelinearized())
        except RuntimeError:
            raise exc from None
        if not dead:
            notes.append(
                f"iSAM2: {why}; restarted from a batch solve (Levenberg-Marquardt) of the "
                "whole graph"
            )
            return relinearized
        names = ", ".join(sorted(gtsam.DefaultKeyFormatter(k) for k in dead))
        notes.append(
            f"iSAM2: {why}; landmark(s) {names} behind every camera that saw them were "
            "dropped (they restart at their next sighting) and iSAM2 restarted from a batch "
            "solve of the rest"
        )
        return relinearized

    def _ordering(self, factors: gtsam.NonlinearFactorGraph, newest: int) -> gtsam.KeyGroupMap:
        """Elimination constraints: the newest state last (group 2), the keys of the new factors
        and the states of the window before it (1), the rest first (0). GTSAM keeps only the
        keys it re-eliminates, and CCOLAMD needs the group numbers below their count: the
        new factors always include the motion factor's four keys, so three groups are safe."""
        groups = gtsam.KeyGroupMap()
        recent = {X(newest), V(newest)}
        window = self.config.relinearize_window
        first = 0 if window is None else max(0, newest - window)
        keys = {k for j in range(first, newest) for k in (X(j), V(j))}
        for n in range(factors.size()):
            keys.update(factors.at(n).keys())
        for key in keys - recent:
            groups.insert2(key, 1)
        for key in recent:
            groups.insert2(key, 2)
        return groups

    def _hold(self, values: gtsam.Values, newest: int, first: bool) -> gtsam.KeyList | None:
        """Keys iSAM2 must not relinearise in this update (``relinearize_window``): the states
        older than the window and the landmarks and radii that entered before it, except those
        whose delta has grown beyond ``held_relinearize_factor`` times their threshold."""
        window = self.config.relinearize_window
        if window is None:
            return None
        for key in values.keys():
            if chr(gtsam.Symbol(key).chr()) in (LANDMARK_CHAR, RADIUS_CHAR, BIAS_CHAR, RIG_CHAR):
                self._entered[key] = newest
        if first:  # the warm-up graph enters at once: nothing to hold yet
            return None
        new = [k for j in range(self._held_states, newest - window) for k in (X(j), V(j))]
        self._held_states = max(self._held_states, newest - window)
        for key in [k for k, j in self._entered.items() if j < newest - window]:
            new.append(key)
            del self._entered[key]
        if new:
            self._add_held(new)
        self._held = gtsam.KeyList()
        if self._held_keys:
            delta = np.abs(self.isam.getDelta().vector(self._held_keys))
            ratio = np.maximum.reduceat(delta / self._held_thresholds, self._held_starts)
            for key, r in zip(self._held_keys, ratio, strict=True):
                if r <= self.config.held_relinearize_factor:
                    self._held.push_back(key)
        return self._held

    def _add_held(self, keys: list[int]) -> None:
        """Append keys to the held keys, their thresholds to the concatenated vector."""
        thr = [self._thresholds[chr(gtsam.Symbol(k).chr())] for k in keys]
        size = len(self._held_thresholds)
        self._held_starts += list(size + np.cumsum([0] + [len(t) for t in thr[:-1]]))
        self._held_thresholds = np.concatenate([self._held_thresholds, *thr])
        self._held_keys += keys

    def _warm_up(self, created: list[int]) -> None:
        initial = gtsam.Values(self._staged_values)
        if self._warm is not None:
            initial.update(self._warm)
        solution = levenberg_marquardt(self._staged, initial, 100, 1e-10, 1e-12)
        self._warm = solution.values
        covariances = Covariances(self._staged, solution.values)
        self._warm_estimate = estimate_from_values(self.builder, solution.values, covariances)
        for i in range(len(self.builder)):
            if not self._staged_values.exists(X(i)):
                continue
            e = self._warm_estimate
            covs = (e.pose_covariance[i], e.twist_covariance[i])
            self.builder.set_hint(i, e.left_cam_from_target[i], e.twist[i], covs)
            if i in created:
                self._filtered[i] = _Filtered(e.left_cam_from_target[i], e.twist[i], *covs)

    def _require_start(self) -> None:
        if not self.builder.started:
            raise BackendError(not_started_message(self.builder))

    def filtered(self) -> Estimate:
        """Each frame's estimate right after its own update (frames added before the graph
        started get theirs from the starting update)."""
        self._require_start()
        n = len(self.builder)
        rows = [self._filtered[i] for i in range(n)]
        return Estimate(
            frame=np.array(self.builder.frames),
            t_s=np.array(self.builder.t_s),
            left_cam_from_target=tuple(r.pose for r in rows),
            twist=np.array([r.twist for r in rows]),
            pose_covariance=np.array([r.pose_cov for r in rows]),
            twist_covariance=np.array([r.twist_cov for r in rows]),
        )

    def _final_updates(self) -> None:
        """Up to ``final_updates`` Gauss-Newton steps without new factors, relinearising every
        variable, on a copy of iSAM2 that replaces it if they succeed. Relinearising a
        variable that the windowed updates held can make the system indeterminate (seen with
        a landmark of a live run whose dropped frames left it barely constrained); an update
        that throws leaves iSAM2 unusable, so the copy is dropped and the estimate stays
        iSAM2's after the last frame (`final_note` says why)."""
        if self.config.final_updates == 0:
            return
        trial = gtsam.ISAM2(self.isam)  # a deep copy (Bayes tree, linearisation point)
        try:
            for _ in range(self.config.final_updates):
                if trial.update().getVariablesRelinearized() == 0:
                    break
        except RuntimeError as exc:
            self.final_note = f"final relinearisation skipped: {_gtsam_message(exc)}"
            return
        self.isam = trial

    def estimate(self) -> Estimate:
        """The current smoothed estimate of every frame: iSAM2's solution after up to
        ``final_updates`` Gauss-Newton steps without new factors (which also benefit the
        frames added later), relinearising every variable (also those outside
        ``relinearize_window``; skipped if that fails: `_final_updates`). If iSAM2 cannot give
        its solution (left unusable by an update that raised), the filtered estimate, and
        `final_note` says so."""
        self._require_start()
        if not self._released:
            if self._warm_estimate is None:
                raise BackendError("no estimate: the warm-up's batch solve failed in every frame")
            return self._warm_estimate
        if self._estimate is None:
            self._final_updates()
            try:
                self._estimate = self._smoothed()
            except RuntimeError as exc:  # iSAM2 left unusable by an update that raised
                self.final_note = (
                    f"no smoothed estimate ({_gtsam_message(exc)}); the filtered one is given"
                )
                self._estimate = self.filtered()
        return self._estimate

    def _smoothed(self) -> Estimate:
        """iSAM2's current solution of every frame, with its marginal covariances."""
        values = self.isam.calculateBestEstimate()  # full back-substitution
        n = len(self.builder)
        return Estimate(
            frame=np.array(self.builder.frames),
            t_s=np.array(self.builder.t_s),
            left_cam_from_target=tuple(from_state(values.atPose3(X(i))) for i in range(n)),
            twist=np.array([values.atVector(V(i)) for i in range(n)]),
            pose_covariance=np.array(
                [
                    state_covariance_to_pose(
                        values.atPose3(X(i)), self.isam.marginalCovariance(X(i))
                    )
                    for i in range(n)
                ]
            ),
            twist_covariance=np.array([self.isam.marginalCovariance(V(i)) for i in range(n)]),
        )
