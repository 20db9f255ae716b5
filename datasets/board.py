"""A ChArUco calibration board shown to the stereo rig at varied poses (the ``calibration``
preset).

Board frame (the sequence's target frame for a board): OpenCV's ChArUco object frame. Origin
at the outer corner of the square grid that is the top-left corner of the printed image, x
along the ``squares_x`` direction (image columns), y along ``squares_y`` (image rows, down), z
= x × y, pointing *into* the board: the printed face looks along -z. Chessboard corner ``i``
(OpenCV's ChArUco id) lies at ``((c + 1) s, (r + 1) s, 0)`` with ``c = i mod (squares_x - 1)``,
``r = i div (squares_x - 1)``, ``s`` the square size. A white margin surrounds the grid.

The board is evenly lit (like a light box): it is rendered as an emitter whose radiance is the
printed image (white 1, black ``black_level``), so the only things between truth and pixels
are the renderer's camera model, lens distortion and the sensor noise.

Poses (`board_poses`): deterministic from a seed; the board centre is placed on a jittered grid
of viewing directions spread over the left image, at a random distance, tilted about a random
in-plane axis and rolled, always showing its printed face to the cameras.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from satpose.datasets.errors import ConfigError
from satpose.datasets.geometry import Rigid3, rotvec_to_matrix
from satpose.datasets.sequence import Calibration, TargetGeometry

if TYPE_CHECKING:
    from types import ModuleType

    from satpose.datasets.scenarios import Scenario

log = logging.getLogger(__name__)

BOARD_FRAME = (
    "ChArUco board frame (OpenCV): origin at the grid's outer corner at the top-left of the "
    "printed image; x along squares_x (image columns), y along squares_y (image rows); "
    "z = x cross y, into the board (the printed face looks along -z); corner i at "
    "((i mod (squares_x-1)) + 1, (i div (squares_x-1)) + 1) times square_size_m"
)


@dataclass(frozen=True, kw_only=True)
class BoardConfig:
    """A ChArUco board and the range of poses it is shown at.

    Attributes:
        squares_x, squares_y: squares along x and y (chessboard corners: (sx-1)(sy-1)).
        square_size_m: side of a chessboard square [m].
        marker_size_m: side of an ArUco marker inside a white square [m].
        dictionary: OpenCV ArUco dictionary name (``cv2.aruco.DICT_*`` without the prefix).
        margin_squares: white margin around the grid, in squares.
        texels_per_square: texture resolution of the printed image.
        black_level: radiance of black print relative to white paper.
        distance_m: (min, max) distance of the board centre from the left camera [m].
        tilt_deg: (min, max) angle between the board normal and the line of sight [deg].
        roll_deg: the board is rolled uniformly in ±roll_deg about its normal [deg].
        spread: board centres are spread over this fraction of the left image's half-size
            (0: always in the centre, 1: up to the image border).
    """

    squares_x: int = 14
    squares_y: int = 10
    square_size_m: float = 0.045
    marker_size_m: float = 0.034
    dictionary: str = "DICT_5X5_100"
    margin_squares: float = 0.5
    texels_per_square: int = 64
    black_level: float = 0.04
    distance_m: tuple[float, float] = (0.5, 1.2)
    tilt_deg: tuple[float, float] = (20.0, 55.0)
    roll_deg: float = 30.0
    spread: float = 0.5

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise ConfigError("board: squares_x and squares_y must be >= 3")
        if not 0 < self.marker_size_m < self.square_size_m:
            raise ConfigError("board: need 0 < marker_size_m < square_size_m")
        if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
            raise ConfigError(f"board.dictionary: unknown ArUco dictionary {self.dictionary!r}")
        markers = (self.squares_x * self.squares_y) // 2
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList
        if markers > size.shape[0]:
            raise ConfigError(
                f"board: {markers} markers needed but {self.dictionary} has {size.shape[0]}"
            )
        if self.margin_squares < 0 or self.texels_per_square < 8:
            raise ConfigError("board: margin_squares >= 0 and texels_per_square >= 8 required")
        if not 0 <= self.black_level < 1:
            raise ConfigError("board.black_level must be in [0, 1)")
        lo, hi = self.distance_m
        if not 0 < lo <= hi:
            raise ConfigError("board.distance_m must be (min, max) with 0 < min <= max")
        tlo, thi = self.tilt_deg
        if not 0 <= tlo <= thi < 80:
            raise ConfigError("board.tilt_deg must be (min, max) with 0 <= min <= max < 80")
        if not 0 <= self.spread <= 1:
            raise ConfigError("board.spread must be in [0, 1]")

    @property
    def grid_size_m(self) -> tuple[float, float]:
        """Width and height of the square grid [m]."""
        return self.squares_x * self.square_size_m, self.squares_y * self.square_size_m

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the printed board including the margin [m]."""
        m = 2 * self.margin_squares * self.square_size_m
        w, h = self.grid_size_m
        return w + m, h + m


def charuco_board(cfg: BoardConfig) -> Any:
    """The ``cv2.aruco.CharucoBoard`` of a config (object points in metres, board frame)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cfg.dictionary))
    return cv2.aruco.CharucoBoard(
        (cfg.squares_x, cfg.squares_y), cfg.square_size_m, cfg.marker_size_m, dictionary
    )


def board_corners(cfg: BoardConfig) -> np.ndarray:
    """Chessboard corners in the board frame, (N, 3) [m], row ``i`` = ChArUco corner id ``i``."""
    n = cfg.squares_x - 1
    ids = np.arange(n * (cfg.squares_y - 1))
    s = cfg.square_size_m
    return np.stack([(ids % n + 1) * s, (ids // n + 1) * s, np.zeros(ids.size)], axis=1)


def board_image(cfg: BoardConfig) -> np.ndarray:
    """The printed board, (H, W) float32 in [black_level, 1], grid plus white margin.

    Texel ``(r, c)`` covers board coordinates ``[c, c+1) x [r, r+1)`` times the texel size,
    measured from the margin's outer corner (at ``-margin`` in board x and y).
    """
    t = cfg.texels_per_square
    grid = charuco_board(cfg).generateImage((cfg.squares_x * t, cfg.squares_y * t), marginSize=0)
    pad = round(cfg.margin_squares * t)
    img = cv2.copyMakeBorder(grid, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    out = img.astype(np.float32) / 255.0
    return cfg.black_level + (1.0 - cfg.black_level) * out


def board_geometry(cfg: BoardConfig) -> TargetGeometry:
    """target.yaml of a board sequence: the board description and its corners (board frame)."""
    return TargetGeometry(
        extras={
            "frame": BOARD_FRAME,
            "board": {
                "kind": "charuco",
                "dictionary": cfg.dictionary,
                "squares_x": cfg.squares_x,
                "squares_y": cfg.squares_y,
                "square_size_m": cfg.square_size_m,
                "marker_size_m": cfg.marker_size_m,
                "margin_m": cfg.margin_squares * cfg.square_size_m,
                "legacy_pattern": False,
            },
            "board_corners": board_corners(cfg).tolist(),
        }
    )


def board_poses(cfg: BoardConfig, calib: Calibration, frames: int, seed: int) -> list[Rigid3]:
    """``left_cam_from_board`` for ``frames`` views, deterministic in ``seed``.

    The board centre is placed along a direction taken from a jittered grid over ``spread``
    of the left image, at a distance drawn from ``distance_m``, measured from the midpoint
    between the two cameras (so that both see it); the board normal is tilted from the line
    of sight by an angle drawn from ``tilt_deg`` about a random axis and rolled within
    ±``roll_deg``.
    """
    rng = np.random.default_rng([seed, 0xB0A4D])
    cam = calib.left
    cols = max(1, round(math.sqrt(frames * cam.width / cam.height)))
    rows = max(1, math.ceil(frames / cols))
    cells = rng.permutation(rows * cols)[:frames]
    gw, gh = cfg.grid_size_m
    centre_board = np.array([gw / 2, gh / 2, 0.0])
    # Midpoint of the camera centres in the left frame (the left centre for a mono rig).
    mid = np.zeros(3) if calib.right_from_left is None else calib.right_from_left.inverse().t / 2
    poses = []
    for cell in cells:
        r, c = divmod(int(cell), cols)
        # Jittered grid in [-spread, spread]^2 of the half image, in pixels of the left camera.
        fx = (c + rng.uniform(0.2, 0.8)) / cols * 2 - 1
        fy = (r + rng.uniform(0.2, 0.8)) / rows * 2 - 1
        u = cam.cx + fx * cfg.spread * cam.width / 2
        v = cam.cy + fy * cfg.spread * cam.height / 2
        ray = cam.undistort_points(np.array([[u, v]]))[0]
        ray = np.array([ray[0], ray[1], 1.0])
        ray /= np.linalg.norm(ray)
        dist = rng.uniform(*cfg.distance_m)
        # Board facing the camera: board z along the line of sight (printed face toward it).
        z = ray
        x0 = np.cross([0.0, 1.0, 0.0], z)
        x0 /= np.linalg.norm(x0)
        facing = np.column_stack([x0, np.cross(z, x0), z])
        tilt = math.radians(rng.uniform(*cfg.tilt_deg))
        axis_angle = rng.uniform(0, 2 * math.pi)
        tilt_axis = facing @ np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0])
        roll = math.radians(rng.uniform(-cfg.roll_deg, cfg.roll_deg))
        R = rotvec_to_matrix(tilt_axis * tilt) @ facing @ rotvec_to_matrix([0.0, 0.0, roll])
        t = mid + ray * dist - R @ centre_board
        poses.append(Rigid3(R=R, t=t))
    return poses


def board_shape(mi: ModuleType, cfg: BoardConfig) -> dict[str, Any]:
    """Mitsuba rectangle of the printed board (board frame), emitting its image as radiance.

    The rectangle's local frame maps to the board frame with local x -> board x, local y ->
    board -y, normal -> board -z (the printed face emits toward -z, the side cameras see).
    Mitsuba's rectangle texture coordinate is (u, v) = ((x + 1) / 2, (y + 1) / 2) of its
    local square [-1, 1]^2, and a bitmap's first row is looked up at v = 0. The printed
    image's row 0 (board y = -margin) is at local y = +1, v = 1, so the rows are flipped.
    The rendered test board proves the convention: its detected corners land on the
    projected truth with no offset (tests/tools/test_calibcheck.py).
    """
    img = board_image(cfg)
    w, h = cfg.size_m
    margin = cfg.margin_squares * cfg.square_size_m
    M = np.eye(4)
    M[:3, 0] = [w / 2, 0.0, 0.0]
    M[:3, 1] = [0.0, -h / 2, 0.0]
    M[:3, 2] = [0.0, 0.0, -1.0]
    M[:3, 3] = [w / 2 - margin, h / 2 - margin, 0.0]
    texture = {
        "type": "bitmap",
        # Row 0 of the printed image must be looked up at v = 1 (see the docstring).
        "bitmap": mi.Bitmap(np.ascontiguousarray(img[::-1, :, None].repeat(3, axis=2))),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(M.tolist()),
        "bsdf": black,
        "emitter": {"type": "area", "radiance": texture},
    }


def render_board_sequence(
    scenario: Scenario,
    out: str | Path,
    *,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Render a board scenario (``scenario.board`` set) into a sequence folder (format v1).

    groundtruth.csv holds ``left_cam_from_board`` (no velocities: the poses are independent
    views); target.yaml describes the board (`board_geometry`). No masks.
    """
    from satpose.datasets.config import to_plain
    from satpose.datasets.render import StereoRenderer, _version
    from satpose.datasets.scene import load_mitsuba
    from satpose.datasets.sequence import SequenceWriter

    cfg = scenario.board
    if cfg is None:
        raise ConfigError(f"scenario {scenario.name!r} has no board")
    calib = scenario.rig.calibration()
    poses = board_poses(cfg, calib, scenario.frames, scenario.seed)
    writer = SequenceWriter(
        out,
        name=scenario.name,
        kind="stereo" if calib.is_stereo else "mono",
        rate_hz=scenario.rate_hz,
        calibration=calib,
        target=board_geometry(cfg),
        overwrite=overwrite,
    )
    with writer:
        mi, _ = load_mitsuba(scenario.render.variant)
        # parts={} keeps none of the satellite's parts and no light: only the emissive board.
        renderer = StereoRenderer(scenario, parts={}, extra_shapes={"board": board_shape(mi, cfg)})
        writer.generator = {
            "tool": "satpose-render",
            "version": _version(),
            "variant": renderer.variant,
            "scenario": to_plain(scenario),
        }
        # White paper has radiance 1: auto exposure makes it read `white_level`.
        sensor = scenario.sensor
        scale = sensor.gain if sensor.exposure == "fixed" else sensor.white_level
        for k, pose in enumerate(poses):
            rad = renderer.radiance(k, pose)
            images = {
                v.name: renderer.expose(k, i, rad[v.name], scale)
                for i, v in enumerate(renderer.views)
            }
            writer.add_frame(
                k, k / scenario.rate_hz, images["left"], images.get("right"), truth=pose
            )
            if progress is not None:
                progress(k)
    return Path(out)
