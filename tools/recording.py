"""Rerun recording of a run: images with detections, the 3-D scene, trajectories, time series.

The pipeline calls `RunRecorder` as a hook; nothing in frontend/ or backend/ imports rerun.
One explicit `rr.RecordingStream` (no global recording), entity paths defined here once,
OpenCV view coordinates (x right, y down, z forward) for the world = left camera frame.

Layout (`blueprint`): left and right images with the detected ring ellipses, landmarks (by
kind, labelled with their track ids) and the estimated ring reprojected; the 3-D scene with
both cameras, the estimated and true target (ring, axes, landmark map), trajectories
(truth, per-frame, kalman, iSAM2 filtered, smoothed) and the position covariance ellipsoid;
time series of errors, spin rate and stage timings. Timeline: ``frame``.

Compact files: the SDK's default micro-batching flushes every few milliseconds, and a frame
takes far longer than that to process, so every ``log`` call used to become a one-row chunk
(1,894 chunks for a 40-frame stereo run). A recording written to a file is batched per entity
instead (`file_batcher`): an entity's rows accumulate until they reach the viewer's own chunk
target (384 KiB or 4096 rows) or the recording is closed; series known only at the end go in
with one ``send_columns`` call each. The content (entities, rows, blueprint) is unchanged;
benchmarks/rerun_size.py measures chunks and size (docs/results/rerun_size.md). Streaming to a
viewer (``spawn``) keeps short flushes so that the viewer follows the run frame by frame.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from satpose.datasets.geometry import Rigid3, matrix_to_quat_xyzw
from satpose.datasets.sequence import Calibration, TargetGeometry
from satpose.frontend.conics import Ellipse, circle_to_conic, conic_to_ellipse
from satpose.frontend.measurements import FrameMeasurements, LandmarkKind

log = logging.getLogger(__name__)

WORLD = "world"
CAMERA = {"left": "world/camera/left", "right": "world/camera/right"}
TARGET_ESTIMATE = "world/target/estimate"
TARGET_TRUTH = "world/target/truth"
TRAJECTORY = "world/trajectory"
COVARIANCE = "world/covariance"
PLOTS = "plots"
FAILURES = "log/failures"

TRAJECTORIES = ("truth", "per_frame", "kalman", "isam2", "smoothed", "isam2_smoothed")
"""Trajectory names: truth, the frontend's per-frame poses, the Kalman filter and iSAM2 as
they run (causal), the offline smoother and iSAM2's final smoothed estimate."""
COLORS = {
    "truth": (80, 220, 80),
    "per_frame": (200, 200, 200),
    "kalman": (240, 160, 40),
    "isam2": (60, 160, 255),
    "smoothed": (230, 60, 200),
    "isam2_smoothed": (140, 90, 255),
}
KIND_COLORS = {
    LandmarkKind.CORNER: (255, 200, 0),
    LandmarkKind.COMPONENT: (0, 220, 255),
    LandmarkKind.ORB: (255, 80, 80),
}


def file_batcher() -> rr.ChunkBatcherConfig:
    """The SDK batching of a recording written to a file: an entity's rows accumulate into one
    chunk until it holds 384 KiB or 4096 rows (the viewer's own compaction target, so that it
    has nothing left to merge) or the recording is flushed at `RunRecorder.close`; the time
    tick is effectively off. Rerun batches per entity, so a chunk never mixes entities."""
    return rr.ChunkBatcherConfig(
        flush_tick=timedelta(hours=24), flush_num_bytes=384 * 1024, flush_num_rows=4096
    )


def live_batcher() -> rr.ChunkBatcherConfig:
    """The SDK batching while streaming to a viewer (``spawn``): flush every 100 ms, so that
    the viewer shows each frame as it is processed (the file written alongside then has small
    chunks again)."""
    return rr.ChunkBatcherConfig(flush_tick=timedelta(milliseconds=100))


@dataclass(frozen=True, kw_only=True)
class RecordingConfig:
    """What goes into run.rrd.

    Attributes:
        images: log the camera images (JPEG) every frame.
        jpeg_quality: JPEG quality of the logged images.
        orb_points: log ORB landmarks too (hundreds per frame at close range).
        compact: batch each entity's rows into large chunks (`file_batcher`); False: the
            SDK's default micro-batching (about one chunk per entity and frame). Ignored while
            streaming to a viewer (``spawn``: `live_batcher`).
    """

    images: bool = True
    jpeg_quality: int = 80
    orb_points: bool = True
    compact: bool = True


def blueprint() -> rrb.Blueprint:
    """The default layout: images left, 3-D scene centre, time series right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin=CAMERA["left"], name="left camera"),
                rrb.Spatial2DView(origin=CAMERA["right"], name="right camera"),
            ),
            rrb.Spatial3DView(origin=WORLD, name="scene (left camera frame)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{PLOTS}/error", name="errors vs truth"),
                rrb.TimeSeriesView(origin=f"{PLOTS}/spin", name="spin rate [deg/frame]"),
                rrb.TimeSeriesView(origin=f"{PLOTS}/timing_ms", name="stage time [ms]"),
            ),
            column_shares=[1, 2, 1],
        ),
        collapse_panels=True,
    )


def _errors(T: Rigid3, truth: Rigid3) -> tuple[float, float]:
    """Position error [cm] and ring-normal error [deg] of one estimate (the normal, target z,
    does not depend on the estimator's choice of the body x axis)."""
    cos = float(np.clip(T.R[:, 2] @ truth.R[:, 2], -1.0, 1.0))
    return 100.0 * float(np.linalg.norm(T.t - truth.t)), float(np.degrees(np.arccos(cos)))


def _circle_points(T: Rigid3, radius: float, n: int = 96) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n)
    return T.apply(np.c_[radius * np.cos(a), radius * np.sin(a), np.zeros(n)])


def _ellipse_strip(e: Ellipse, n: int = 96) -> np.ndarray:
    p = e.points(n)
    return np.vstack([p, p[:1]])


def jpeg_image(img: np.ndarray, quality: int) -> rr.EncodedImage:
    """A camera image as stored (grey or BGR, 8 or 16 bit) as a JPEG for the recording.

    Encoded by OpenCV (libjpeg-turbo) from the BGR array as it is: 1.2 ms for a 1024x768
    colour image, against 5.1 ms for ``rr.Image(...).compress`` (which converts to RGB and
    encodes with Pillow) on the same machine, quiet (docs/live.md)."""
    img8 = img if img.dtype == np.uint8 else (img // 257).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img8, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"JPEG encoding failed for an image of shape {img.shape}")
    return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")


DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"
"""Where a viewer started by ``rerun`` (or ``--spawn``) listens by default."""


def viewer_url(address: str) -> str:
    """A Rerun viewer's gRPC URL from ``--connect``'s argument: a URL as is
    (``rerun+http://host:9876/proxy``), ``HOST:PORT`` or ``HOST`` completed to one, ``""``
    the local viewer's default (`DEFAULT_VIEWER`)."""
    if not address:
        return DEFAULT_VIEWER
    if "://" in address:
        return address
    host, _, port = address.partition(":")
    return f"rerun+http://{host or '127.0.0.1'}:{port or 9876}/proxy"


class RunRecorder:
    """Writes run.rrd while the pipeline runs (the pipeline calls `log_frame` per frame and
    `log_final` once), then `close`.

    Args:
        path: the recording file; always written, also while streaming to a viewer.
        spawn: start a Rerun viewer and stream to it as well.
        connect: also stream to the viewer at this gRPC URL (`viewer_url`).
    """

    def __init__(
        self,
        path: str | Path,
        calibration: Calibration,
        target: TargetGeometry | None = None,
        config: RecordingConfig | None = None,
        spawn: bool = False,
        connect: str | None = None,
    ) -> None:
        self.config = config or RecordingConfig()
        self.calibration = calibration
        self.target = target
        self.viewers = [u for u in ([DEFAULT_VIEWER] if spawn else []) + [connect] if u]
        if self.viewers:
            batcher = live_batcher()
        elif self.config.compact:
            batcher = file_batcher()
        else:
            batcher = rr.ChunkBatcherConfig()  # the SDK's defaults
        self.rec = rr.RecordingStream(
            application_id="satpose", recording_id=None, batcher_config=batcher
        )
        # one stream, several sinks: spawn()/connect_grpc() alone would replace the file sink
        sinks: list[rr.FileSink | rr.GrpcSink] = [rr.FileSink(str(path))]
        if spawn:
            self.rec.spawn(connect=False)
        sinks += [rr.GrpcSink(u) for u in dict.fromkeys(self.viewers)]
        self.rec.set_sinks(*sinks)
        self.rec.send_blueprint(blueprint())
        self._tracks: dict[str, list[np.ndarray]] = {name: [] for name in TRAJECTORIES}
        self._radius: float | None = None
        self._static()

    def _static(self) -> None:
        rec = self.rec
        rec.log(WORLD, rr.ViewCoordinates.RDF, static=True)
        for cam in ("left", "right") if self.calibration.is_stereo else ("left",):
            c = self.calibration.camera(cam)
            T = Rigid3.identity() if cam == "left" else self.calibration.right_from_left.inverse()
            rec.log(
                CAMERA[cam], rr.Transform3D(translation=T.t, quaternion=T.quat_xyzw), static=True
            )
            rec.log(
                CAMERA[cam],
                rr.Pinhole(
                    image_from_camera=c.K,
                    resolution=[c.width, c.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=0.5,
                ),
                static=True,
            )
        for name in TRAJECTORIES:
            rec.log(
                f"{PLOTS}/error/position_cm/{name}",
                rr.SeriesLines(colors=[COLORS[name]], names=name),
                static=True,
            )
            rec.log(
                f"{PLOTS}/error/normal_deg/{name}",
                rr.SeriesLines(colors=[COLORS[name]], names=name),
                static=True,
            )

    # -- per frame --------------------------------------------------------------------------

    def log_frame(
        self,
        index: int,
        images: Mapping[str, np.ndarray],
        m: FrameMeasurements,
        estimates: Mapping[str, Rigid3 | None],
        covariance: np.ndarray | None = None,
        truth: Rigid3 | None = None,
        spin_deg_per_frame: Mapping[str, float] | None = None,
        timings_ms: Mapping[str, float] | None = None,
    ) -> None:
        """One frame: images and detections, poses so far (``estimates`` keyed by trajectory
        name: ``per_frame``, ``kalman``, ``isam2``), the main estimate's 6x6 covariance, the
        truth, spin rates and stage timings."""
        rec = self.rec
        rec.set_time("frame", sequence=index)
        rec.set_time("time", duration=float(m.t_s))
        if self.config.images:
            for cam, img in images.items():
                rec.log(f"{CAMERA[cam]}/image", jpeg_image(img, self.config.jpeg_quality))
        self._log_detections(m)
        if m.ring is not None:
            self._radius = m.ring.radius_m
        main = next(
            (
                T
                for T in (
                    estimates.get("isam2"),
                    estimates.get("kalman"),
                    estimates.get("per_frame"),
                )
                if T is not None
            ),
            None,
        )
        for name, T in estimates.items():
            if T is not None:
                self._tracks[name].append(T.t)
        if truth is not None:
            self._tracks["truth"].append(truth.t)
            self._log_target(TARGET_TRUTH, truth, COLORS["truth"], truth_model=True)
        if main is not None:
            self._log_target(TARGET_ESTIMATE, main, COLORS["isam2"], truth_model=False)
            self._log_reprojected_ring(main)
            if covariance is not None:
                self._log_covariance(main, covariance)
        for name, pts in self._tracks.items():
            if len(pts) >= 2:
                rec.log(
                    f"{TRAJECTORY}/{name}", rr.LineStrips3D([np.array(pts)], colors=[COLORS[name]])
                )
        if truth is not None:
            for name, T in estimates.items():
                if T is not None:
                    self._log_errors(name, T, truth)
        for name, rate in (spin_deg_per_frame or {}).items():
            rec.log(f"{PLOTS}/spin/{name}", rr.Scalars(float(rate)))
        for stage, ms in (timings_ms or {}).items():
            rec.log(f"{PLOTS}/timing_ms/{stage}", rr.Scalars(float(ms)))
        if m.failures:
            rec.log(FAILURES, rr.TextLog("; ".join(m.failures), level=rr.TextLogLevel.WARN))

    def _log_errors(self, name: str, T: Rigid3, truth: Rigid3) -> None:
        """Position error [cm] and ring-normal error [deg] of one estimate (`_errors`)."""
        pos_cm, normal_deg = _errors(T, truth)
        self.rec.log(f"{PLOTS}/error/position_cm/{name}", rr.Scalars(pos_cm))
        self.rec.log(f"{PLOTS}/error/normal_deg/{name}", rr.Scalars(normal_deg))

    def _log_detections(self, m: FrameMeasurements) -> None:
        rec = self.rec
        for cam in CAMERA:
            ellipses = [e for e in (m.ring.ellipses if m.ring else ()) if e.camera.value == cam]
            rec.log(
                f"{CAMERA[cam]}/ring",
                rr.LineStrips2D(
                    [
                        _ellipse_strip(Ellipse.from_params([*e.center_px, *e.axes_px, e.angle_rad]))
                        for e in ellipses
                    ],
                    colors=[(0, 255, 0)],
                    radii=rr.Radius.ui_points(1.5),
                ),
            )
            for kind in LandmarkKind:
                if kind == LandmarkKind.ORB and not self.config.orb_points:
                    continue
                pts, labels = [], []
                for lm in m.landmarks:
                    if lm.kind != kind:
                        continue
                    px = lm.left_px if cam == "left" else lm.right_px
                    if px is not None:
                        pts.append(px)
                        labels.append(str(lm.track_id))
                rec.log(
                    f"{CAMERA[cam]}/landmarks/{kind.value}",
                    rr.Points2D(
                        np.array(pts).reshape(-1, 2),
                        colors=[KIND_COLORS[kind]],
                        radii=rr.Radius.ui_points(3.0),
                        labels=labels if kind != LandmarkKind.ORB else None,
                    ),
                )

    def _log_reprojected_ring(self, T: Rigid3) -> None:
        if self._radius is None:
            return
        for cam in ("left", "right") if self.calibration.is_stereo else ("left",):
            c = self.calibration.camera(cam)
            cam_from_target = T if cam == "left" else self.calibration.right_from_left @ T
            if cam_from_target.t[2] <= 0:
                continue
            try:
                e = conic_to_ellipse(circle_to_conic(c.K, cam_from_target, self._radius))
            except (ValueError, np.linalg.LinAlgError):
                continue
            self.rec.log(
                f"{CAMERA[cam]}/ring_estimate",
                rr.LineStrips2D(
                    [_ellipse_strip(e)], colors=[(60, 160, 255)], radii=rr.Radius.ui_points(1.0)
                ),
            )

    def _log_target(
        self, entity: str, T: Rigid3, color: tuple[int, int, int], truth_model: bool
    ) -> None:
        rec = self.rec
        rec.log(entity, rr.Transform3D(translation=T.t, quaternion=T.quat_xyzw))
        radius = self._radius or 0.3
        if truth_model and self.target is not None and self.target.ring is not None:
            radius = self.target.ring.radius_m
        a = np.linspace(0, 2 * np.pi, 96)
        strips = [np.c_[radius * np.cos(a), radius * np.sin(a), np.zeros(a.size)]]
        if truth_model and self.target is not None and self.target.panel_corners is not None:
            strips.append(np.vstack([self.target.panel_corners, self.target.panel_corners[:1]]))
        rec.log(f"{entity}/model", rr.LineStrips3D(strips, colors=[color]))
        s = 0.4 * radius / 0.3
        rec.log(
            f"{entity}/axes",
            rr.Arrows3D(
                origins=np.zeros((3, 3)),
                vectors=np.eye(3) * s,
                colors=[(255, 0, 0), (0, 255, 0), (0, 0, 255)],
            ),
        )

    def _log_covariance(self, T: Rigid3, covariance: np.ndarray) -> None:
        """3-sigma ellipsoid of the position (covariance in the target axes, rotated into the
        camera frame)."""
        C = T.R @ covariance[3:, 3:] @ T.R.T
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        if np.linalg.det(V) < 0:
            V[:, 0] = -V[:, 0]
        self.rec.log(
            COVARIANCE,
            rr.Ellipsoids3D(
                centers=[T.t],
                half_sizes=[3.0 * np.sqrt(np.clip(w, 0, None))],
                quaternions=[matrix_to_quat_xyzw(V)],
                colors=[(60, 160, 255)],
                fill_mode=rr.components.FillMode.MajorWireframe,
            ),
        )

    # -- end of run -------------------------------------------------------------------------

    def log_final(
        self,
        name: str,
        frames: Sequence[int],
        poses: Sequence[Rigid3],
        truth: Sequence[Rigid3 | None] | None = None,
        spin_deg_per_frame: Sequence[float] | None = None,
        t_s: Sequence[float] | None = None,
    ) -> None:
        """A whole trajectory known only at the end (the smoothed one): its line and its
        error and spin series at every frame (``t_s``: the frames' times, for the ``time``
        timeline), each series sent as one column."""
        frame_idx = np.asarray(frames, dtype=np.int64)
        times = None if t_s is None else np.asarray(t_s, dtype=float)

        def send(entity: str, rows: np.ndarray, values: Sequence[float]) -> None:
            if rows.size == 0:
                return
            indexes = [rr.TimeColumn("frame", sequence=frame_idx[rows])]
            if times is not None:
                indexes.append(rr.TimeColumn("time", duration=times[rows]))
            self.rec.send_columns(
                entity, indexes=indexes, columns=rr.Scalars.columns(scalars=np.asarray(values))
            )

        if truth is not None:
            rows = [k for k, tk in enumerate(truth) if tk is not None]
            errs = [_errors(poses[k], truth[k]) for k in rows]
            send(f"{PLOTS}/error/position_cm/{name}", np.array(rows, int), [e[0] for e in errs])
            send(f"{PLOTS}/error/normal_deg/{name}", np.array(rows, int), [e[1] for e in errs])
        if spin_deg_per_frame is not None:
            send(
                f"{PLOTS}/spin/{name}",
                np.arange(len(frame_idx)),
                [float(r) for r in spin_deg_per_frame],
            )
        self.rec.log(
            f"{TRAJECTORY}/{name}",
            rr.LineStrips3D(
                [np.array([T.t for T in poses])], colors=[COLORS.get(name, (255, 255, 255))]
            ),
            static=True,
        )

    def close(self) -> None:
        """Flush and close every sink. A viewer that cannot be reached is a warning (run.rrd
        is complete regardless), not an error."""
        try:
            self.rec.flush()
        except RuntimeError as exc:
            log.warning("Rerun viewer %s: %s", ", ".join(self.viewers), str(exc).splitlines()[0])
        self.rec.disconnect()
