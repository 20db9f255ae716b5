"""Bad frames made visible: the console names each one, the summary counts them by reason.

A frame is *bad* when its input was unusable (an image missing, unreadable, of the wrong
size, black, saturated or with NaN/inf pixels) or when a stage raised an unexpected exception
(``"<stage>: internal error: <type>: <message>"``, `satpose.frontend.measurements.
exception_failure`). Ordinary degradation (no ring found, too few landmarks) is not: it stays
in each frame's failure notes (measurements.parquet) as before.

`BadFrames` is fed one frame at a time by the per-frame loops of the CLIs (`run`,
`frontend`, `spin`, `bracket`, `stars track`, `rings`). It logs a warning naming the frame's
file(s) and reason once per frame, the first `BAD_FRAME_LIMIT` frames one by one and then
only a note that more follow; `summary` gives the end-of-run count by reason.
`guarded` runs one frame's step and turns an unexpected exception into such a failure.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import TypeVar

from satpose.datasets.sequence import Frame
from satpose.datasets.sequence import Sequence as FrameSequence
from satpose.frontend.measurements import INTERNAL_ERROR, FrameMeasurements, exception_failure

log = logging.getLogger(__name__)

BAD_FRAME_LIMIT = 10
"""Bad frames named one by one on the console; later ones are only counted."""

# (pattern in an image failure note, reason); first match wins. The notes come from
# datasets.sequence.read_image (file problems) and frontend.preprocess (image checks).
_IMAGE_REASONS: tuple[tuple[str, str], ...] = (
    ("image file is missing", "missing image"),
    ("not a readable PNG", "unreadable image"),
    ("cannot read image", "unreadable image"),
    ("not 8- or 16-bit", "unsupported pixel type"),
    ("calib.yaml says", "wrong image size"),
    ("does not match the camera", "wrong image size"),
    ("non-finite pixel", "NaN/inf pixels"),
    ("too dark", "black image"),
    ("saturated", "saturated image"),
)
_IMAGE_WORD = re.compile(r"\bimage\b")

T = TypeVar("T")


def bad_frame_reason(failure: str) -> str | None:
    """The reason a failure note makes its frame bad (``"unreadable image"``, ``"internal
    error in ring"``, ...), or None for ordinary degradation."""
    marker = f": {INTERNAL_ERROR}: "
    if marker in failure:
        return f"{INTERNAL_ERROR} in {failure.split(marker, 1)[0]}"
    if _IMAGE_WORD.search(failure):
        for pattern, reason in _IMAGE_REASONS:
            if pattern in failure:
                return reason
    return None


def guarded(stage: str, frame: int, step: Callable[[], T]) -> tuple[T | None, str | None]:
    """Run one frame's ``step``: ``(result, None)``, or ``(None, failure note)`` if it raised
    an unexpected exception (type and message kept in the note; traceback at DEBUG level).
    KeyboardInterrupt and other non-``Exception`` exits pass through."""
    try:
        return step(), None
    except Exception as exc:
        log.debug("frame %d: %s raised", frame, stage, exc_info=True)
        return None, exception_failure(stage, exc)


def measure_frame(
    stage: str, frame: Frame, process: Callable[[Frame], FrameMeasurements]
) -> FrameMeasurements:
    """``process(frame)``, or a frame whose one failure note is the exception it raised
    (`guarded`, named ``stage``)."""
    m, why = guarded(stage, frame.index, partial(process, frame))
    if m is None:
        m = FrameMeasurements(frame=frame.index, t_s=frame.t_s, failures=(str(why),))
    return m


def measure_frames(
    seq: FrameSequence,
    stage: str,
    process: Callable[[Frame], FrameMeasurements],
    bad: BadFrames,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameMeasurements]:
    """Every frame of ``seq`` through ``process`` (a frontend's ``process_frame``) with a
    progress bar: an exception is that frame's failure note (`guarded`, named ``stage``), and
    each bad frame is named on the console with its image files (``bad``).
    ``progress(done, total)`` is called after each frame, outside the guard (so it may stop
    the loop by raising)."""
    import sys

    from tqdm import tqdm

    results = []
    for frame in tqdm(
        seq,
        desc=f"{stage} {seq.name}",
        unit="frame",
        file=sys.stderr,
        dynamic_ncols=True,
        delay=0.5,
    ):
        m = measure_frame(stage, frame, process)
        files = tuple(p for p in (frame.left_path, frame.right_path) if p is not None)
        bad.note(frame.index, m.failures, files)
        results.append(m)
        if progress is not None:
            progress(len(results), len(seq))
    return results


class BadFrames:
    """Names bad frames on the console (logging warnings) and counts them by reason.

    Args:
        root: the sequence folder; files under it are named relative to it.
        limit: frames named one by one; after that only the count grows.
        logger: where the warnings go (the CLI configures its handler).
    """

    def __init__(
        self,
        root: Path | None = None,
        limit: int = BAD_FRAME_LIMIT,
        logger: logging.Logger | None = None,
    ) -> None:
        self.root = root
        self.limit = limit
        self.log = logger or log
        self.frames: list[int] = []
        self.by_reason: Counter[str] = Counter()

    def _name(self, path: Path) -> str:
        if self.root is not None:
            try:
                return str(path.relative_to(self.root))
            except ValueError:
                pass
        return str(path)

    def note(self, frame: int, failures: Iterable[str], files: Sequence[Path | None] = ()) -> bool:
        """Look at one frame's failure notes; warn and count if the frame is bad.

        Args:
            frame: the frame index.
            failures: its failure notes.
            files: its image files (named in the warning).

        Returns:
            True if the frame is bad.
        """
        bad: list[tuple[str, str]] = []
        for f in failures:
            r = bad_frame_reason(f)
            # a stage's echo of an image problem ("ring (left): image too dark") adds nothing
            # to the image's own note ("image (left): too dark")
            if r is not None and (f.startswith("image") or r not in {x for _, x in bad}):
                bad.append((f, r))
        if not bad:
            return False
        self.frames.append(frame)
        for reason in dict.fromkeys(r for _, r in bad):
            self.by_reason[reason] += 1
        n = len(self.frames)
        if n <= self.limit:
            names = ", ".join(self._name(p) for p in files if p is not None)
            where = f"frame {frame} ({names})" if names else f"frame {frame}"
            self.log.warning("%s: %s", where, "; ".join(f for f, _ in bad))
        elif n == self.limit + 1:
            self.log.warning(
                "more than %d bad frames: the rest are only counted (summary at the end; "
                "every reason is in the frames' failure notes)",
                self.limit,
            )
        return True

    @property
    def count(self) -> int:
        """Number of bad frames so far."""
        return len(self.frames)

    def summary(self, total: int | None = None) -> str:
        """``"2 bad frames (of 20): unreadable image 1, wrong image size 1"``; empty if none."""
        if not self.frames:
            return ""
        of = f" (of {total})" if total is not None else ""
        reasons = ", ".join(f"{r} {k}" for r, k in self.by_reason.most_common())
        noun = "frame" if self.count == 1 else "frames"
        return f"{self.count} bad {noun}{of}: {reasons}"

    def as_dict(self) -> dict[str, int]:
        """Counts by reason (plain ints, for YAML/JSON)."""
        return {r: int(k) for r, k in self.by_reason.most_common()}
