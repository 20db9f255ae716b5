"""iSAM2 recovering from an indeterminate system on a live run's measurements.

The fixture (tests/data/live_gaps): the frontend's measurements of `paper-docking` frames 0,
7, 9-45 as `satpose track --live` processed them at 5 Hz (frames 1-6 and 8 dropped), with
the sequence's calib.yaml. With the relinearisation window, the panel corner l1 runs away
along its viewing ray until it is behind every camera that saw it; at frame 41 iSAM2 then
raises "Indeterminate linear system" and its Bayes tree is unusable (every later frame failed
and the run ended without an estimate). `OnlineEstimator._restart` drops the dead landmark and
restarts iSAM2 from a batch solve of the rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from satpose.backend import BackendConfig, StepReport, make_estimator
from satpose.datasets.sequence import load_calibration
from satpose.tools.files import read_measurements

DATA = Path(__file__).resolve().parents[1] / "data" / "live_gaps"


def test_dead_landmark_is_dropped_and_the_run_agrees_with_the_batch_smoother() -> None:
    calib = load_calibration(DATA / "calib.yaml", kind="stereo")
    frames = read_measurements(DATA / "measurements.parquet")
    assert [m.frame for m in frames][:3] == [0, 7, 9]
    reports: list[StepReport] = []
    online = make_estimator("online", calib, BackendConfig(), reports.append)
    offline = make_estimator("offline", calib, BackendConfig())
    for m in frames:
        online.add(m)  # raised at frame 41 before the restart existed
        offline.add(m)
    restarts = [(r.frame, n) for r in reports for n in r.notes if n.startswith("iSAM2:")]
    assert len(restarts) == 1 and restarts[0][0] == 41, restarts
    assert "l1" in restarts[0][1] and "dropped" in restarts[0][1]
    a, b = online.estimate(), offline.estimate()
    assert list(a.frame) == list(b.frame) == [m.frame for m in frames]
    pairs = zip(a.left_cam_from_target, b.left_cam_from_target, strict=True)
    diff = [np.linalg.norm(p.t - q.t) for p, q in pairs]
    # The batch smoother keeps l1 (it converges); the restarted iSAM2 lost l1's sightings
    # up to frame 41 and still agrees to a few mm (measured 2.0 mm); 2 cm would be another
    # answer.
    assert max(diff) < 0.02, max(diff)
