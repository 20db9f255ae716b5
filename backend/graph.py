"""Frame-by-frame construction of the factor graph shared by the batch and iSAM2 estimators.

States: ``X(i)`` (``target_from_left_cam``, see `satpose.backend.pose3`) and ``V(i)`` (body
twist) for the ``i``-th frame added; in tight coupling also ``L(j)`` (landmarks, target frame)
and ``R(k)`` (the radius of each circle of the ring the frontend measured).

An accepted spin rate (`FrameMeasurements.spin`, one camera) adds a factor on ``|omega|`` of
the frame's twist in either coupling, for windows disjoint from the last one used.

The graph starts at the first frame that can fix the target frame — one with a pose (loose
coupling) or with the ring and a landmark usable as the x-axis anchor (tight coupling).
Frames added before it are kept and receive states then, tied to it by the motion prior only,
so the estimate always covers every frame added. A frame without measurements gets its states
and the motion factor: prediction only. The first state's twist has a weak zero-mean prior, so
the first frames are never singular.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np
from scipy.stats import chi2

from satpose.backend.errors import BackendError
from satpose.backend.factors import (
    KIND_PRIORITY,
    FactorClock,
    MeasurementConfig,
    StereoRig,
    choose_anchor,
    gauge_factor,
    gauge_pose,
    landmark_factors,
    pose_factor,
    ring_factor,
    ring_radius_factor,
    spin_rate_factor,
)
from satpose.backend.keys import DISPARITY_BIAS, RIG, L, R, V, X
from satpose.backend.motion import (
    MotionConfig,
    constant_twist_factor,
    predict,
    process_covariance,
    twist_between,
    twist_prior_factor,
)
from satpose.backend.pose3 import local_error, to_state
from satpose.datasets.geometry import Rigid3
from satpose.datasets.sequence import Calibration
from satpose.frontend.measurements import FrameMeasurements, LandmarkKind, LandmarkMeasurement


@dataclass
class GraphUpdate:
    """What one added frame contributes: new factors, initial values of new variables, and
    the state indices created (several when the graph starts, none while waiting)."""

    factors: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    created: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


class GraphBuilder:
    """Turns `FrameMeasurements` into factors and initial values, one frame at a time.

    Args:
        calibration: the stereo calibration (undistorted intrinsics + ``right_from_left``).
        motion, measurements: the motion prior and measurement settings.
        clock: accumulates time spent inside Python factors.
    """

    def __init__(
        self,
        calibration: Calibration,
        motion: MotionConfig,
        measurements: MeasurementConfig,
        clock: FactorClock | None = None,
    ) -> None:
        self.rig = StereoRig.from_calibration(calibration)
        self.motion = motion
        self.config = measurements
        self.clock = clock
        self.frames: list[int] = []
        self.t_s: list[float] = []
        self.start: int | None = None  # index of the frame that started the graph
        self.anchor: int | None = None
        self.landmarks: set[int] = set()
        # landmarks seen once, not yet in the graph: track id -> (state index, sighting)
        self._first_sightings: dict[int, tuple[int, LandmarkMeasurement]] = {}
        self._sightings: dict[int, int] = {}  # sightings of the landmarks in the graph
        self.circles: list[list[float]] = []  # the radii measured of each circle of the ring
        self._bias_in_graph = False  # DISPARITY_BIAS and its prior added
        self._rig_in_graph = False  # RIG and its prior added
        self.full_frames = 0  # frames whose measurements fix a whole pose
        self._pending: list[FrameMeasurements] = []
        self._spin_until_s = -np.inf  # end of the last spin-rate window used
        self._hint: dict[int, tuple[Rigid3, np.ndarray]] = {}
        self._hint_cov: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # tight coupling: the frontend's target frame relative to the graph's gauge, from the
        # first frame with a frontend pose from the start on (its per-frame poses are only
        # initial values and gates; the frontend fixes its frame one ring sighting later);
        # None until then (and in loose coupling, where the two frames are one)
        self._frontend_from_gauge: Rigid3 | None = None

    # -- bookkeeping ------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self.start is not None

    def __len__(self) -> int:
        return len(self.frames)

    def forget_landmark(self, track_id: int) -> None:
        """Take a landmark out of the graph's bookkeeping (its variable and factors were
        dropped): its next sighting starts it afresh as a first sighting."""
        self.landmarks.discard(track_id)
        self._sightings.pop(track_id, None)

    def set_hint(
        self,
        i: int,
        pose: Rigid3,
        twist: np.ndarray,
        covariances: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Record the current best pose and twist of state ``i`` (used for predictions), and
        optionally their covariances (used to gate a measured initial pose)."""
        self._hint[i] = (pose, np.asarray(twist, float))
        if covariances is not None:
            self._hint_cov[i] = covariances

    def hint(self, i: int) -> tuple[Rigid3, np.ndarray]:
        return self._hint[i]

    # -- adding a frame ---------------------------------------------------------------------

    def add(
        self, m: FrameMeasurements, prefer: Literal["measurement", "prediction"]
    ) -> GraphUpdate:
        """Factors and initial values for frame ``m``.

        Args:
            prefer: initial pose of a new state when the frame has a pose measurement (the
                frontend's per-frame pose, also in tight coupling, where it is not a factor):
                ``measurement`` takes it (batch); ``prediction`` (iSAM2) takes it only if it
                agrees with the constant-twist prediction (chi-square gate at
                ``robust_quantile`` with the measurement's and the prediction's covariance)
                or the twist is not known yet (first two states), else the prediction. iSAM2
                computes a factor's robust weight once, at the linearisation point it gets
                when inserted: an initial value several sigma away from the measurements
                would down-weight them until the state is relinearised.
        """
        if self.t_s and not m.t_s > self.t_s[-1]:
            raise BackendError(
                f"frame {m.frame}: time {m.t_s} s does not follow the previous {self.t_s[-1]} s"
            )
        self.frames.append(int(m.frame))
        self.t_s.append(float(m.t_s))
        i = len(self.frames) - 1
        update = GraphUpdate()
        if not self.started:
            if not self._can_start(m):
                self._pending.append(m)
                update.notes.append(
                    "waiting for a first pose"
                    if self.config.coupling == "loose"
                    else "waiting for the ring and an anchor landmark"
                )
                return update
            self._start(m, update)
            return update
        prev_pose, prev_twist = self._hint[i - 1]
        dt = self.t_s[i] - self.t_s[i - 1]
        predicted = predict(prev_pose, prev_twist, dt)
        if (
            self._frontend_from_gauge is None
            and m.pose is not None
            and self.config.coupling == "tight"
        ):
            self._relate_frontend_frame(m, predicted)
        measured = self._measured_pose(m)
        assert self.start is not None
        use_measurement = measured is not None and (
            prefer == "measurement" or i - self.start < 2 or self._agrees(m, predicted, i - 1, dt)
        )
        pose = measured if use_measurement and measured is not None else predicted
        twist = twist_between(prev_pose, pose, dt) if use_measurement else prev_twist
        self._new_state(i, pose, twist, update)
        update.factors.push_back(constant_twist_factor(i - 1, i, dt, self.motion, self.clock))
        n = update.factors.size()
        self._measurement_factors(i, m, update)
        if update.factors.size() == n:
            update.notes.append("prediction only")
        return update

    def _measured_pose(self, m: FrameMeasurements) -> Rigid3 | None:
        """The frame's per-frame pose in the graph's target frame, or None (only an initial
        value and a gate, so its covariance is not re-expressed: the two frames differ by
        the frontend's few-degree bootstrap error)."""
        if m.pose is None:
            return None
        if self._frontend_from_gauge is None:  # loose coupling: the frontend's frame
            return m.pose.left_cam_from_target
        return m.pose.left_cam_from_target @ self._frontend_from_gauge

    def _agrees(self, m: FrameMeasurements, predicted: Rigid3, prev: int, dt: float) -> bool:
        """Is the frame's pose measurement within the gate of the prediction from ``prev``?
        (prediction covariance to first order: previous pose + dt^2 twist + process noise,
        cross terms ignored — it only chooses an initial value)."""
        assert m.pose is not None
        if self.config.robust == "none" or prev not in self._hint_cov:
            return True
        pose_cov, twist_cov = self._hint_cov[prev]
        C = pose_cov + dt**2 * twist_cov + process_covariance(dt, self.motion)[:6, :6]
        C = C + m.pose.covariance
        measured = self._measured_pose(m)
        assert measured is not None
        e = local_error(predicted, measured)
        return float(e @ np.linalg.solve(C, e)) < chi2.ppf(self.config.robust_quantile, 6)

    def _relate_frontend_frame(self, m: FrameMeasurements, predicted: Rigid3) -> None:
        """The frontend fixed its target frame after the graph started (it waits for the
        ring's second sighting): relate the two at its first pose, by the gauge's own rule
        in this frame (ring and anchor) if the anchor is seen, else through the prediction
        (a gate and an initial value need no better). Not through the start frame's pose:
        its ring may be the circle the frontend refused."""
        assert m.pose is not None
        point = next((lm.point_m for lm in m.landmarks if lm.track_id == self.anchor), None)
        here = gauge_pose(m.ring, point) if m.ring is not None and point is not None else predicted
        self._frontend_from_gauge = m.pose.left_cam_from_target.inverse() @ here

    def _can_start(self, m: FrameMeasurements) -> bool:
        if self.config.coupling == "loose":
            return m.pose is not None
        return m.ring is not None and choose_anchor(m.ring, m.landmarks, self.config) is not None

    def _start(self, m: FrameMeasurements, update: GraphUpdate) -> None:
        i = len(self.frames) - 1
        self.start = i
        if self.config.coupling == "loose":
            assert m.pose is not None
            pose = m.pose.left_cam_from_target
        else:
            assert m.ring is not None
            anchor = choose_anchor(m.ring, m.landmarks, self.config)
            assert anchor is not None and anchor.point_m is not None
            pose = gauge_pose(m.ring, anchor.point_m)
            self.anchor = anchor.track_id
            if m.pose is not None:
                self._frontend_from_gauge = m.pose.left_cam_from_target.inverse() @ pose
            update.factors.push_back(gauge_factor(anchor.track_id, self.config))
        # Frames added before the start have no usable measurement: same pose, zero twist.
        for j in range(i + 1):
            self._new_state(j, pose, np.zeros(6), update)
        update.factors.push_back(twist_prior_factor(0, self.motion))
        for j in range(i):
            dt = self.t_s[j + 1] - self.t_s[j]
            update.factors.push_back(constant_twist_factor(j, j + 1, dt, self.motion, self.clock))
        for j, pending in enumerate(self._pending):
            self._measurement_factors(j, pending, update)
        self._pending = []
        self._measurement_factors(i, m, update)
        if i:
            update.notes.append(f"started: {i} earlier frame(s) tied by the motion prior")

    def _new_state(self, i: int, pose: Rigid3, twist: np.ndarray, update: GraphUpdate) -> None:
        update.values.insert(X(i), to_state(pose))
        update.values.insert(V(i), np.asarray(twist, float))
        update.created.append(i)
        self._hint[i] = (pose, np.asarray(twist, float))

    def _landmark_priority(self, lm: LandmarkMeasurement) -> tuple[int, int, int, int]:
        """Sort key of a frame's landmarks (for `MeasurementConfig.max_orb_per_frame`): the
        anchor, then by kind (corners, components, ORB), the most sightings so far, track id."""
        seen = self._sightings.get(lm.track_id, int(lm.track_id in self._first_sightings))
        return (lm.track_id != self.anchor, KIND_PRIORITY[lm.kind], -seen, lm.track_id)

    def _disparity_bias(self, update: GraphUpdate) -> float | None:
        """``f b`` of the rig if the ring factors carry the common disparity bias (the
        variable and its prior enter with the first ring), else None."""
        sigma = self.config.ring_disparity_bias_px
        if sigma is None or self.rig.left_from_right is None:
            return None
        if not self._bias_in_graph:
            update.values.insert(DISPARITY_BIAS, np.zeros(1))
            update.factors.push_back(
                gtsam.PriorFactorVector(
                    DISPARITY_BIAS, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, sigma)
                )
            )
            self._bias_in_graph = True
        baseline = float(np.linalg.norm(self.rig.left_from_right.translation()))
        return float(self.rig.cal_left.fx()) * baseline

    def _rig_variable(self, update: GraphUpdate) -> None:
        """``RIG`` and its prior (the calibrated ``left_from_right``, its yaw free by
        ``landmark_disparity_bias_px / f``) before the first landmark factor that uses it."""
        sigma = self.config.landmark_disparity_bias_px
        if sigma is None or self._rig_in_graph or self.rig.left_from_right is None:
            return
        fixed = 1e-6  # [rad], [m]: the rest of the calibration as it is
        yaw = sigma / float(self.rig.cal_right.fx())
        update.values.insert(RIG, self.rig.left_from_right)
        update.factors.push_back(
            gtsam.PriorFactorPose3(
                RIG,
                self.rig.left_from_right,
                gtsam.noiseModel.Diagonal.Sigmas(np.array([fixed, yaw, fixed, *[fixed] * 3])),
            )
        )
        self._rig_in_graph = True

    def _circle(self, radius_m: float) -> int:
        """The circle of the ring a measured radius belongs to: the known circle whose median
        radius is nearest, if within ``ring_circle_gap`` (relative); else a new one
        (``len(self.circles)``). The rim's edges are concentric and coplanar (its front face),
        so only the radius tells them apart; the centre and normal are shared."""
        best, best_gap = len(self.circles), self.config.ring_circle_gap
        for k, radii in enumerate(self.circles):
            ref = float(np.median(radii))
            gap = abs(radius_m - ref) / ref
            if gap <= best_gap:
                best, best_gap = k, gap
        return best

    def _measurement_factors(self, i: int, m: FrameMeasurements, update: GraphUpdate) -> None:
        spin = m.spin
        if (
            self.config.spin_rate
            and spin is not None
            and spin.ok
            and spin.window_start_s > self._spin_until_s
        ):
            update.factors.push_back(spin_rate_factor(spin, i, self.config, self.clock))
            self._spin_until_s = spin.window_end_s
        if self.config.coupling == "loose":
            if m.pose is not None:
                update.factors.push_back(pose_factor(m.pose, i, self.config))
                self.full_frames += 1
            return
        observed = 0
        if m.ring is not None:
            fb = self._disparity_bias(update)
            update.factors.push_back(ring_factor(m.ring, i, self.config, self.clock, fb))
            if self.config.ring_radius:
                k = self._circle(m.ring.radius_m)
                if k == len(self.circles):
                    self.circles.append([])
                    update.values.insert(R(k), np.array([m.ring.radius_m]))
                    if k:
                        update.notes.append(
                            f"ring: another circle of the rim, radius {m.ring.radius_m:.4f} m"
                        )
                self.circles[k].append(float(m.ring.radius_m))
                update.factors.push_back(ring_radius_factor(m.ring, i, k, self.config, self.clock))
        orb_left = self.config.max_orb_per_frame
        for lm in sorted(m.landmarks, key=self._landmark_priority):
            if lm.kind not in self.config.landmark_kinds:
                continue
            known = lm.track_id in self.landmarks
            if not known and lm.track_id not in self._first_sightings:
                # a first sighting: kept aside (one stereo sighting says nothing about the
                # pose: the point's three coordinates absorb it), except for the anchor
                if lm.point_m is not None:
                    self._first_sightings[lm.track_id] = (i, lm)
                if lm.track_id != self.anchor or lm.point_m is None:
                    continue
            if lm.kind == LandmarkKind.ORB and lm.track_id != self.anchor and orb_left is not None:
                if orb_left <= 0:
                    continue
                orb_left -= 1
            self._rig_variable(update)
            if not known:
                # second sighting (or the anchor): the landmark enters the graph, with its
                # first sighting, initialised there from the current pose of that frame
                j, first = self._first_sightings.pop(lm.track_id)
                assert first.point_m is not None
                update.values.insert(
                    L(lm.track_id), self._hint[j][0].inverse().apply(first.point_m)
                )
                self.landmarks.add(lm.track_id)
                if j != i:
                    for factor in landmark_factors(first, j, self.rig, self.config):
                        update.factors.push_back(factor)
            for factor in landmark_factors(lm, i, self.rig, self.config):
                update.factors.push_back(factor)
            self._sightings[lm.track_id] = self._sightings.get(lm.track_id, 1) + 1
            observed += 1
        if (m.ring is not None and observed) or observed >= 3:
            self.full_frames += 1
