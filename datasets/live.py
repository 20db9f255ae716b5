"""Frames as they arrive: a sequence folder still being written, and a recorder that writes one.

A *frame source* (`FrameSource`) hands over frames as they become complete; the live tracker
(`satpose.tools.live`, ``satpose track --live``) polls it and decides which frames it
processes. `FolderSource` watches a sequence folder (format v1, docs/sequence_format.md) that a
recorder is writing; `replay_sequence` is such a recorder, copying a finished sequence frame by
frame at a given rate (``satpose record-replay``). `BagReplay` is a ROS 1/ROS 2 bag replayed at
its recorded rate, read as ``satpose import`` reads it (docs/live.md, "A ROS bag replayed at
its recorded rate").

**When a frame of a folder is complete.** Frame ``k`` is complete when

1. its row in frames.csv is complete: the line ends with a newline, and the header line before
   it is the format's (``frame,t_s,left,right``; a row that cannot be parsed is named in a
   warning and skipped);
2. each of its image files exists and is whole: it starts with the PNG signature and an IHDR
   chunk and ends with the IEND chunk (``00 00 00 00 'IEND' ae 42 60 82``), which a PNG
   writer writes last. A file that is still being written (shorter, or without its IEND yet)
   is looked at again at the next poll: a partially written PNG is retried, never a failure.
   A file that starts with something other than a PNG signature, or whose IHDR disagrees with
   calib.yaml, is complete but bad: the tracker reads it, and the frame is a bad frame named
   on the console, like in ``satpose run``.

Decoding is left to the tracker (``ArrivedFrame.read``), which retries a whole-looking file that
does not decode a few times (`READ_RETRIES`, `READ_RETRY_S`) before it calls the frame bad.
The row may come before or after the images (a recorder that appends the row first is fine);
frames.csv may be appended to or replaced as a whole (write and rename): rows already seen are
recognised by their frame index.

**Arrival time** of a frame: the moment it became complete, from the file system: the latest
modification time of its image files and of frames.csv when its row was first read (the
tracker measures its latency from this; a frame already complete when the source was opened
arrives at the opening). ``seen_s``: when the source found it complete.

**End of the recording.** A recorder says it is done by creating the file `RECORDING_DONE`
(``recording.done``, empty) after the last frame's images and row. The source reports `ended`
once it has seen that file and handed over every complete frame; rows whose images never
became whole are then given up (`Skipped`). A recorder that crashes writes no marker: the
tracker's idle timeout (``--until-idle``) or Ctrl-C ends the run then.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml

from satpose.datasets.errors import SatposeError, SequenceError
from satpose.datasets.importers.bag import BagSource
from satpose.datasets.importers.calib import read_calibration_file
from satpose.datasets.importers.common import RecordingError
from satpose.datasets.importers.recording import (
    ImportOptions,
    first_frame_calibration,
    open_source,
    prepare_images,
    recording_calibration,
    source_kind,
)
from satpose.datasets.sequence import (
    FORMAT_VERSION,
    FRAMES_COLUMNS,
    SequenceHeader,
    atomic_write,
    calibration_to_yaml,
    load_header,
    load_sequence,
    read_image,
    target_to_yaml,
)

log = logging.getLogger(__name__)

RECORDING_DONE = "recording.done"
"""The marker file a recorder creates in the sequence folder when it has written its last
frame."""

POLL_S = 0.02
"""How often the tracker polls a folder when it has nothing to do [s]: a new frame is picked
up within this (plus the poll's own cost) after it became complete."""

READ_RETRIES = 5
"""Times a whole-looking image that does not decode is read again before its frame is bad."""
READ_RETRY_S = 0.02
"""Pause between those reads [s]."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"


@dataclass(frozen=True, kw_only=True)
class ArrivedFrame:
    """A frame that became complete.

    Attributes:
        index: the frame index (frames.csv ``frame``).
        t_s: the frame's time as recorded [s].
        arrival_s: when it became complete, Unix time [s] (see the module doc).
        seen_s: when the source found it complete, Unix time [s].
        files: its image files (named in warnings); empty for a source without files.
        read: returns the raw ``(left, right)`` images as stored; may raise `SatposeError`.
    """

    index: int
    t_s: float
    arrival_s: float
    seen_s: float
    files: tuple[Path, ...]
    read: Callable[[], tuple[np.ndarray, np.ndarray]] = field(repr=False)


@dataclass(frozen=True, kw_only=True)
class Skipped:
    """A frame announced by the recording but never complete, given up.

    Attributes:
        index, t_s: frames.csv's row.
        reason: why, e.g. ``"incomplete: left/000004.png not whole"``.
    """

    index: int
    t_s: float
    reason: str


class FrameSource(Protocol):
    """Frames of one recording as they arrive (stereo: left and right).

    The tracker calls `poll` in a loop (every `POLL_S` while idle, right after each frame it
    processed while busy) and never blocks in it: a source returns at once what became
    complete since the previous call, oldest first.
    """

    @property
    def header(self) -> SequenceHeader:
        """Name, kind, nominal rate and calibration of the recording."""
        ...

    def poll(self) -> tuple[list[ArrivedFrame], list[Skipped]]:
        """Frames complete since the last call (increasing index), and frames given up."""
        ...

    def ended(self) -> bool:
        """True once the recording has ended and every frame was handed over or given up."""
        ...

    def incomplete(self) -> list[Skipped]:
        """Announced frames that are not complete yet (the tracker gives them up at a stop)."""
        ...

    def notes(self) -> list[str]:
        """Facts about the recording worth reporting at the end, one line each."""
        ...


@dataclass
class _Row:
    index: int
    t_s: float
    files: tuple[Path, ...]
    row_s: float  # when frames.csv held the row (its mtime at the read), Unix time


class FolderSource:
    """A sequence folder that a recorder is still writing (see the module doc for when a frame
    counts as complete).

    Args:
        root: the sequence folder; sequence.yaml and calib.yaml must be readable
            (`wait_for_header`).
        header: the header if already read.
    """

    def __init__(self, root: str | Path, header: SequenceHeader | None = None) -> None:
        self.root = Path(root)
        self._header = header or load_header(self.root)
        if self._header.kind != "stereo":
            raise SequenceError(
                self.root / "sequence.yaml",
                "kind",
                f"live tracking needs a stereo sequence (this one is {self._header.kind})",
            )
        self.opened_s = time.time()
        self.csv_path = self.root / "frames.csv"
        self._columns = FRAMES_COLUMNS[self._header.kind]
        self._inode: int | None = None
        self._offset = 0
        self._tail = b""
        self._header_seen = False
        self._line = 0  # lines of frames.csv read (the header is line 1)
        self._last: tuple[int, float] | None = None  # index and t_s of the newest row
        self._pending: list[_Row] = []
        self._done = False
        self.bad_rows = 0

    @property
    def header(self) -> SequenceHeader:
        return self._header

    def ended(self) -> bool:
        return self._done and not self._pending

    def incomplete(self) -> list[Skipped]:
        return [Skipped(index=r.index, t_s=r.t_s, reason=self._why(r)) for r in self._pending]

    def notes(self) -> list[str]:
        if not self.bad_rows:
            return []
        return [f"{self.csv_path}: {self.bad_rows} rows could not be read and were skipped"]

    def poll(self) -> tuple[list[ArrivedFrame], list[Skipped]]:
        # the marker is looked at before frames.csv: every row written before it is read below
        marker = (self.root / RECORDING_DONE).exists()
        self._read_rows()
        now = time.time()
        ready: list[ArrivedFrame] = []
        last_ready = -1
        for k, row in enumerate(self._pending):
            mtimes = [_whole(p) for p in row.files]
            if any(t is None for t in mtimes):
                continue
            arrival = max([row.row_s, *(t for t in mtimes if t is not None)])
            ready.append(
                ArrivedFrame(
                    index=row.index,
                    t_s=row.t_s,
                    arrival_s=min(max(arrival, self.opened_s), now),
                    seen_s=now,
                    files=row.files,
                    read=_Reader(row.files, self._header),
                )
            )
            last_ready = k
        skipped = []
        keep = []
        for k, row in enumerate(self._pending):
            if any(f.index == row.index for f in ready):
                continue
            if k < last_ready:  # a later frame is complete: this one can no longer be used
                skipped.append(Skipped(index=row.index, t_s=row.t_s, reason=self._why(row)))
            else:
                keep.append(row)
        self._pending = keep
        if marker:
            self._done = True
            skipped += [
                Skipped(index=r.index, t_s=r.t_s, reason=f"{self._why(r)} at the end")
                for r in self._pending
            ]
            self._pending = []
        return ready, skipped

    def _why(self, row: _Row) -> str:
        for p in row.files:
            if _whole(p) is None:
                state = "missing" if not p.exists() else "not whole"
                return f"incomplete: {_relative(p, self.root)} {state}"
        return "incomplete"

    def _read_rows(self) -> None:
        """Read the complete lines frames.csv gained since the last poll."""
        try:
            st = os.stat(self.csv_path)
        except FileNotFoundError:
            return
        except OSError as exc:
            raise SequenceError(
                self.csv_path, None, f"cannot read ({exc.strerror or exc})"
            ) from None
        if st.st_ino != self._inode or st.st_size < self._offset:
            # a new file (replaced by rename) or truncated: read it again from the start;
            # rows already seen are recognised by their frame index
            self._inode, self._offset, self._tail = st.st_ino, 0, b""
            self._header_seen, self._line = False, 0
        if st.st_size == self._offset:
            return
        try:
            with open(self.csv_path, "rb") as fh:
                fh.seek(self._offset)
                data = fh.read()
                row_s = os.fstat(fh.fileno()).st_mtime
        except OSError as exc:
            raise SequenceError(
                self.csv_path, None, f"cannot read ({exc.strerror or exc})"
            ) from None
        self._offset += len(data)
        lines = (self._tail + data).split(b"\n")
        self._tail = lines.pop()  # no newline yet: not complete
        for raw in lines:
            self._line += 1
            self._parse(raw, row_s)

    def _parse(self, raw: bytes, row_s: float) -> None:
        try:
            text = raw.decode("utf-8").strip()
        except UnicodeDecodeError:
            self._bad_row("not UTF-8 text")
            return
        if not self._header_seen:
            columns = [c.strip() for c in text.split(",")]
            if columns != self._columns:
                raise SequenceError(
                    self.csv_path,
                    ",".join(columns),
                    f"header must be {','.join(self._columns)} (a live sequence's columns "
                    "in this order)",
                )
            self._header_seen = True
            return
        if not text:
            return
        values = [v.strip() for v in next(csv.reader([text]))]
        if len(values) != len(self._columns):
            self._bad_row(f"expected {len(self._columns)} values, got {len(values)}")
            return
        try:
            index_f = float(values[0])
            t_s = float(values[1])
        except ValueError:
            self._bad_row("frame and t_s must be numbers")
            return
        if not (math.isfinite(index_f) and index_f == round(index_f) and math.isfinite(t_s)):
            self._bad_row("frame must be an integer and t_s finite")
            return
        index = int(index_f)
        if self._last is not None and index <= self._last[0]:
            return  # seen before (the file was replaced or rewritten)
        if self._last is not None and t_s <= self._last[1]:
            self._bad_row(f"t_s {t_s} is not after the previous row's {self._last[1]}")
            return
        if not all(values[2:]):
            self._bad_row("image path is empty")
            return
        self._last = (index, t_s)
        files = tuple(self.root / v for v in values[2:])
        self._pending.append(_Row(index=index, t_s=t_s, files=files, row_s=row_s))

    def _bad_row(self, problem: str) -> None:
        self.bad_rows += 1
        log.warning("%s: row %d: %s; row skipped", self.csv_path, self._line - 1, problem)


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _whole(path: Path) -> float | None:
    """The file's modification time if it is a whole PNG or cannot become one (then the reader
    names the problem), None while it may still be being written."""
    try:
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())
            head = fh.read(33)
            if len(head) < len(_PNG_SIGNATURE):
                return None
            if head[:8] != _PNG_SIGNATURE:
                return st.st_mtime  # not a PNG: complete, and bad
            if len(head) < 33 or st.st_size < 33 + len(_PNG_IEND):
                return None
            fh.seek(st.st_size - len(_PNG_IEND))
            if fh.read(len(_PNG_IEND)) != _PNG_IEND:
                return None
            return st.st_mtime
    except FileNotFoundError:
        return None
    except OSError:
        return None


class _Reader:
    """``ArrivedFrame.read`` of a folder frame: both images, a whole-looking file that does not
    decode read again up to `READ_RETRIES` times."""

    def __init__(self, files: tuple[Path, ...], header: SequenceHeader) -> None:
        self.files = files
        self.cameras = [header.calibration.left, header.calibration.right]

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        images = []
        for path, camera in zip(self.files, self.cameras, strict=True):
            assert camera is not None
            for attempt in range(READ_RETRIES + 1):
                try:
                    images.append(read_image(path, camera))
                    break
                except SequenceError as exc:
                    if "not a readable PNG" not in str(exc) or attempt == READ_RETRIES:
                        raise
                    time.sleep(READ_RETRY_S)
        return images[0], images[1]


def wait_for_header(
    root: str | Path,
    timeout_s: float | None,
    poll_s: float = POLL_S,
    stop: Callable[[], bool] | None = None,
) -> SequenceHeader | None:
    """Wait until a recorder has written sequence.yaml and calib.yaml, and read them.

    A file that exists but does not parse yet is read again until ``timeout_s`` (a recorder
    that writes them in place may be half-way); after that its error is raised.

    Args:
        timeout_s: give up after this long [s]; None: wait until ``stop()``.
        stop: returns True to give up (Ctrl-C).

    Returns:
        the header, or None if ``stop()`` said so first.

    Raises:
        SequenceError: the files are missing or invalid after ``timeout_s``.
    """
    start = time.monotonic()
    root = Path(root)
    while True:
        try:
            return load_header(root)
        except SequenceError as exc:
            if timeout_s is not None and time.monotonic() - start >= timeout_s:
                raise SequenceError(
                    exc.path, exc.field, f"{exc.problem} (waited {timeout_s:g} s for the recorder)"
                ) from None
        if stop is not None and stop():
            return None
        time.sleep(poll_s)


# --------------------------------------------------------------------------------------------
# A ROS bag replayed at its recorded rate
# --------------------------------------------------------------------------------------------


class BagReplay:
    """A ROS 1 or ROS 2 bag replayed at its recorded rate (times ``rate``): frames arrive
    when a camera would have delivered them.

    Everything that decides *what* the frames are is `satpose import`'s
    (`satpose.datasets.importers`): the image topics (``options.left``/``right``, else picked,
    also by a calibration file's ``rostopic``), stereo pairing by header stamp
    (``options.pair_tolerance_s``), the calibration (``options.calib``/``calib_right``,
    else the bag's CameraInfo), lens resampling, ``options.grey``, the image size check. So
    a live run on a bag sees the frames that ``satpose import`` would write.

    **When a frame arrives.** The replay starts at the first `poll` (the tracker is ready then;
    a camera started earlier would only make the first frames "before start" drops); pair
    ``k`` with header stamp ``t_k`` arrives at ``start + (t_k - t_0) / rate`` (Unix time,
    ``arrival_s``), whatever the tracker is doing: a poll after a long step returns every pair
    that arrived meanwhile, with its own arrival time, and the tracker keeps the newest. The
    messages are read from the bag when they arrive and decoded only by ``read()``, i.e. for
    the frames the tracker processes (as `FolderSource` leaves a dropped PNG undecoded).

    Frame indices count the pairs from 0 (as an import numbers them); ``t_s`` is the stamp [s].
    The first pair is read and decoded when the replay is opened: its sizes check the
    calibration, so a wrong calibration, a mono bag or an unsupported encoding fails here, in
    one line naming the bag (or calibration file) and the field. A bag that turns out to be
    corrupt or truncated later ends the replay there with a warning naming the bag. The
    pairing's counts (unpaired images) are in `notes` once the replay has ended.

    Args:
        path: ``.bag`` (ROS 1), a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.
        options: topics, calibration, pairing (`satpose.datasets.importers.ImportOptions`;
            the fields about writing a sequence are not used).
        rate: replay speed, a multiple of the recorded rate (``rosbag play --rate``).
        clock: the wall clock, Unix time [s].

    Raises:
        RecordingError: as `satpose import` for the same bag and options, or a mono bag.
    """

    def __init__(
        self,
        path: str | Path,
        options: ImportOptions | None = None,
        *,
        rate: float = 1.0,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise SatposeError(f"replay rate must be a positive multiple, got {rate}")
        self.path = Path(path)
        self.options = opts = options or ImportOptions()
        self.rate = float(rate)
        self.clock = clock
        kind = source_kind(self.path)
        if kind not in ("rosbag1", "rosbag2"):
            raise RecordingError(
                self.path, None, "not a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder)"
            )
        override = (
            read_calibration_file(opts.calib, opts.calib_right) if opts.calib is not None else None
        )
        src, _ = open_source([self.path], opts, override)
        assert isinstance(src, BagSource)
        self.src = src
        try:
            if src.kind != "stereo":
                raise RecordingError(
                    self.path,
                    "topics",
                    f"live tracking needs a stereo pair of image topics; {src.choice}: "
                    f"{src.left_topic} alone (name both with --left and --right)",
                )
            calib, note = recording_calibration(src, override)
            self._pairs = src.pairs()
            first = next(self._pairs, None)
            if first is None:
                src.check()
                raise RecordingError(self.path, None, "holds no stereo pairs")
            t0, ml, mr = first
            images = (src.decode(ml, "left"), src.decode(mr, "right"))
            calibration, self._maps, self._sizes, lens = first_frame_calibration(
                src, calib, (t0, *images), opts.grey
            )
            self._notes = [*src.notes()[:1], note, *lens]
            second = next(self._pairs, None)
        except BaseException:
            src.close()
            raise
        self._next: list[tuple[float, Any, Any]] = [first] + ([second] if second else [])
        self._t0 = t0
        rate_hz = 1.0 / (second[0] - t0) if second is not None else 1.0
        self._header = SequenceHeader(
            root=self.path,
            name=opts.name or self.path.name.removesuffix(".bag") or "bag",
            kind="stereo",
            rate_hz=rate_hz,
            calibration=calibration,
            generator={"tool": "satpose-track", "source": src.provenance()},
        )
        self.start_s: float | None = None
        self._index = 0
        self._done = False

    @property
    def header(self) -> SequenceHeader:
        """The bag's name, calibration and the rate of its first two pairs."""
        return self._header

    def arrival(self, t_s: float) -> float:
        """When the pair stamped ``t_s`` arrives, Unix time [s] (after the first `poll`)."""
        assert self.start_s is not None
        return self.start_s + (t_s - self._t0) / self.rate

    def poll(self) -> tuple[list[ArrivedFrame], list[Skipped]]:
        now = self.clock()
        if self.start_s is None:
            self.start_s = now
        ready: list[ArrivedFrame] = []
        while self._next and self.arrival(self._next[0][0]) <= now:
            t_s, ml, mr = self._next.pop(0)
            ready.append(
                ArrivedFrame(
                    index=self._index,
                    t_s=t_s,
                    arrival_s=self.arrival(t_s),
                    seen_s=now,
                    files=(),
                    read=_BagReader(self, t_s, ml, mr),
                )
            )
            self._index += 1
            if not self._next and not self._done:
                self._read_next()
        return ready, []

    def _read_next(self) -> None:
        try:
            item = next(self._pairs, None)
        except RecordingError as exc:  # corrupt or truncated after the start
            log.warning("%s; the replay ends here", exc)
            item = None
        if item is None:
            self._done = True
            self.src.close()
            return
        self._next.append(item)

    def ended(self) -> bool:
        """True once the last pair has been handed over."""
        return self._done and not self._next

    def incomplete(self) -> list[Skipped]:
        """Nothing: a bag's pair is there whole or not at all."""
        return []

    def notes(self) -> list[str]:
        """One line per fact, as `satpose import` prints them: topics, calibration, lenses
        resampled, and (once the replay has ended) the pairing's counts and dropped stamps."""
        if not self._done:
            return self._notes
        out = [*self._notes, *self.src.notes()[1:]]
        try:
            self.src.check()
        except RecordingError as exc:  # `satpose import` would refuse the bag
            out.append(f"warning: {exc}")
        return out

    def close(self) -> None:
        """Stop reading the bag."""
        self._done = True
        self._next = []
        self._pairs.close()
        self.src.close()


class _BagReader:
    """``ArrivedFrame.read`` of a bag pair: both messages decoded and prepared as `satpose
    import` writes them (`prepare_images`)."""

    def __init__(self, replay: BagReplay, t_s: float, left: Any, right: Any) -> None:
        self.replay, self.t_s, self.left, self.right = replay, t_s, left, right

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.replay
        images = [r.src.decode(self.left, "left"), r.src.decode(self.right, "right")]
        left, right = prepare_images(r.src, self.t_s, images, r._sizes, r._maps, r.options.grey)
        return left, right


# --------------------------------------------------------------------------------------------
# A recorder: replay a finished sequence into a folder frame by frame
# --------------------------------------------------------------------------------------------


class Recorder:
    """Writes a finished sequence into a new folder one frame at a time, as a recorder would
    (`replay_sequence` paces it; tests call `write` themselves).

    `start` writes sequence.yaml, calib.yaml and target.yaml (each to a temporary name, then
    renamed) and frames.csv's header; `write` frame ``k``'s images (byte copies, each to a
    hidden temporary name, then renamed) and then its row, appended to frames.csv in one write;
    `finish` groundtruth.csv's rows of the written frames (if the source has truth, for
    ``satpose eval`` afterwards) and the marker `RECORDING_DONE`. Timestamps stay as recorded
    (``t_s``, ``rate_hz``). Masks are not copied.

    Args:
        source: a finished sequence folder.
        out: the new folder (must not exist, or be empty).

    Raises:
        SequenceError: the source is not a valid sequence, or ``out`` is not empty.
    """

    def __init__(self, source: str | Path, out: str | Path) -> None:
        self.seq = load_sequence(source)
        self.out = Path(out)
        if self.out.exists() and (not self.out.is_dir() or any(self.out.iterdir())):
            raise SequenceError(self.out, None, "output folder already exists and is not empty")
        self.written = 0

    def __len__(self) -> int:
        return len(self.seq)

    def start(self) -> None:
        """The header files and frames.csv's header line."""
        seq, out = self.seq, self.out
        out.mkdir(parents=True, exist_ok=True)
        head = {
            "format": FORMAT_VERSION,
            "name": seq.name,
            "kind": seq.kind,
            "rate_hz": seq.rate_hz,
            "generator": dict(seq.generator),
        }
        _write_yaml(out / "sequence.yaml", head)
        _write_yaml(out / "calib.yaml", calibration_to_yaml(seq.calibration))
        if seq.target is not None:
            _write_yaml(out / "target.yaml", target_to_yaml(seq.target))
        with open(out / "frames.csv", "w", encoding="utf-8") as fh:
            fh.write(",".join(FRAMES_COLUMNS[seq.kind]) + "\n")

    def write(self, k: int) -> None:
        """Frame ``k`` of the source (the next one: frames are written in order)."""
        fr = self.seq.frames[k]
        rels = []
        for path in (fr.left_path, fr.right_path):
            if path is None:
                continue
            rel = path.relative_to(self.seq.root)
            copy_file(path, self.out / rel)
            rels.append(rel.as_posix())
        with open(self.out / "frames.csv", "a", encoding="utf-8") as fh:
            fh.write(",".join([str(fr.index), repr(fr.t_s), *rels]) + "\n")
        self.written = k + 1

    def finish(self) -> None:
        """groundtruth.csv (the written frames' rows) and the end marker."""
        if self.seq.truth is not None:
            lines = (self.seq.root / "groundtruth.csv").read_text(encoding="utf-8").splitlines()
            text = "\n".join(lines[: self.written + 1]) + "\n"
            atomic_write(self.out / "groundtruth.csv", lambda tmp: Path(tmp).write_text(text))
        (self.out / RECORDING_DONE).touch()


def replay_sequence(
    source: str | Path,
    out: str | Path,
    rate_hz: float,
    *,
    frames: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> int:
    """Copy a finished sequence into a new folder frame by frame at ``rate_hz`` frames per
    second of wall time, as a recorder would (`Recorder`): frame ``k`` at ``k / rate_hz``
    seconds after the start (a late frame is written at once; the schedule is not shifted).

    Args:
        source: a finished sequence folder.
        out: the new folder (must not exist, or be empty).
        rate_hz: frames written per second of wall time.
        frames: copy only the first this many frames.
        progress: called with ``(frames written, frames to write)`` after each frame.
        stop: polled before each frame; True stops the copy without the end marker (like a
            recorder that died).

    Returns:
        the number of frames written.

    Raises:
        SequenceError: the source is not a valid sequence, or ``out`` cannot be written.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise SatposeError(f"replay rate must be a positive number of Hz, got {rate_hz}")
    rec = Recorder(source, out)
    n = len(rec) if frames is None else min(frames, len(rec))
    try:
        rec.start()
        start = time.monotonic()
        for k in range(n):
            if stop is not None and stop():
                return k
            delay = start + k / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            rec.write(k)
            if progress is not None:
                progress(k + 1, n)
        rec.finish()
    except OSError as exc:
        raise SequenceError(out, None, f"cannot write ({exc.strerror or exc})") from None
    return n


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to a hidden temporary name beside ``dst`` and rename it into place (a
    reader sees no file or the whole file)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(dst, lambda tmp: shutil.copyfile(src, tmp))


def _write_yaml(path: Path, data: dict[str, object]) -> None:
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
