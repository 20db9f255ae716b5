"""The final-approach simulation of seed 002 (Wu et al. 2017, sec. 4): camera, bracket, truth.

Exact numbers from the paper: focal length 10 mm, 1280 x 1024 pixels of 12 um (so
``f = 833.33 px``); bracket vertices ``P1 = [500, 500, 500]``, ``P2 = [1500, 500, 500]``,
``P5 = [1000, 1480, 500]`` mm in the target frame; relative attitude ``gamma = pi/18 (t - 10)``
rad about Z with small X/Y wobble, 3-2-1 order; relative position ``r(t) = r0 - v t`` with
``r0 = [0.1, 0.2, 2.0]`` m and ``v = [0.005, 0.010, 0.100]`` m/s (toward the target: ``r``
reaches zero at ``t = 20`` s, and ``|r| < 1 m`` after ``t = 10`` s, as the paper says).

Choices where the paper is silent (docs/bracket.md): the wobble is ``phi(t) = A sin(2 pi t /
8 s)`` about X and ``theta(t) = A sin(2 pi t / 12 s + 1)`` about Y with ``A = 1 deg``; frames
every 0.1 s from 0 to 20 s; ``left_cam_from_target = [Rz(gamma) Ry(theta) Rx(phi), r(t)]``
(the paper's ``P_c = R P_t + T``); principal point at the image centre (OpenCV convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from satpose.datasets.camera import PinholeCamera
from satpose.datasets.geometry import Rigid3

PAPER_VERTICES_M = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [1.0, 1.48, 0.5]])
"""Bracket vertices P1, P2, P5 in the target frame [m] (paper sec. 4)."""

PAPER_VISIBLE_FRACTION = 0.2
"""Visible part of the struts P1P5 and P2P5, from P1 and P2 (the paper's 1/5)."""

PAPER_R0_M = np.array([0.1, 0.2, 2.0])
PAPER_V_M_S = np.array([0.005, 0.010, 0.100])


def paper_camera() -> PinholeCamera:
    """The paper's camera: f = 10 mm, 12 um pixels, 1280 x 1024, no distortion."""
    f_px = 10e-3 / 12e-6
    K = np.array([[f_px, 0.0, (1280 - 1) / 2], [0.0, f_px, (1024 - 1) / 2], [0.0, 0.0, 1.0]])
    return PinholeCamera(width=1280, height=1024, K=K)


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, kw_only=True)
class PaperMotion:
    """The relative motion of sec. 4 (defaults: the paper's numbers and our wobble choice).

    Attributes:
        r0_m: initial position of the target origin in the camera frame [m].
        v_m_s: approach velocity; ``r(t) = r0 - v t`` [m/s].
        spin_rad_s: rate of ``gamma = spin (t - t_zero)`` about Z [rad/s] (paper: pi/18).
        t_zero_s: time at which ``gamma = 0`` [s] (paper: 10).
        wobble_rad: amplitude of the X and Y wobble [rad].
        wobble_periods_s: periods of the X and Y wobble [s].
    """

    r0_m: tuple[float, float, float] = (0.1, 0.2, 2.0)
    v_m_s: tuple[float, float, float] = (0.005, 0.010, 0.100)
    spin_rad_s: float = math.pi / 18
    t_zero_s: float = 10.0
    wobble_rad: float = math.radians(1.0)
    wobble_periods_s: tuple[float, float] = (8.0, 12.0)

    def euler_321(self, t_s: float) -> tuple[float, float, float]:
        """``(gamma, theta, phi)``: rotations about Z, Y, X [rad] at time ``t_s``."""
        gamma = self.spin_rad_s * (t_s - self.t_zero_s)
        phi = self.wobble_rad * math.sin(2 * math.pi * t_s / self.wobble_periods_s[0])
        theta = self.wobble_rad * math.sin(2 * math.pi * t_s / self.wobble_periods_s[1] + 1.0)
        return gamma, theta, phi

    def cam_from_target(self, t_s: float) -> Rigid3:
        """``left_cam_from_target`` at ``t_s``: ``P_c = R P_t + T`` (paper eq. 2)."""
        gamma, theta, phi = self.euler_321(t_s)
        R = _rz(gamma) @ _ry(theta) @ _rx(phi)
        return Rigid3(R=R, t=np.asarray(self.r0_m) - np.asarray(self.v_m_s) * t_s)


def paper_times(dt_s: float = 0.1, duration_s: float = 20.0) -> np.ndarray:
    """Frame times ``0, dt, ..., duration`` [s]."""
    n = round(duration_s / dt_s)
    return np.arange(n + 1) * dt_s


def paper_truth(t_s: np.ndarray, motion: PaperMotion | None = None) -> list[Rigid3]:
    """``left_cam_from_target`` at each time of ``t_s``."""
    m = PaperMotion() if motion is None else motion
    return [m.cam_from_target(float(t)) for t in t_s]
