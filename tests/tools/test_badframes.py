"""Bad frames: which failure notes make a frame bad, warnings once per frame, the summary."""

from __future__ import annotations

import logging

import pytest

from satpose.frontend.measurements import exception_failure
from satpose.tools.badframes import BadFrames, bad_frame_reason, guarded


@pytest.mark.parametrize(
    ("note", "reason"),
    [
        ("image: /s/left/000001.png: not a readable PNG file", "unreadable image"),
        ("image: /s/left/000001.png: image file is missing", "missing image"),
        (
            "image: /s/right/000003.png: width/height: image is 320x240 but calib.yaml says "
            "640x480",
            "wrong image size",
        ),
        ("image (left): too dark", "black image"),
        ("image (right): saturated", "saturated image"),
        ("image (left): non-finite pixel values (NaN/inf) in 100 pixels", "NaN/inf pixels"),
        ("spin: image too dark", "black image"),
        ("ring: internal error: OverflowError: math range error", "internal error in ring"),
        ("ring (left): no ring-like ellipse found", None),
        ("panel: no corners", None),
        ("ring: the ring circle fit diverged (ring seen nearly edge-on)", None),
    ],
)
def test_bad_frame_reasons(note: str, reason: str | None) -> None:
    assert bad_frame_reason(note) == reason


def test_exception_failure_keeps_type_and_message() -> None:
    assert (
        exception_failure("ring", OverflowError("math range error\nmore"))
        == "ring: internal error: OverflowError: math range error"
    )
    assert exception_failure("pose", KeyError()) == "pose: internal error: KeyError"


def test_guarded_turns_an_exception_into_a_note() -> None:
    assert guarded("x", 0, lambda: 3) == (3, None)

    def boom() -> int:
        raise ZeroDivisionError("division by zero")

    assert guarded("backend_online", 7, boom) == (
        None,
        "backend_online: internal error: ZeroDivisionError: division by zero",
    )
    with pytest.raises(KeyboardInterrupt):
        guarded("x", 0, lambda: (_ for _ in ()).throw(KeyboardInterrupt()))


def test_warnings_once_per_frame_then_a_count(caplog: pytest.LogCaptureFixture) -> None:
    logger = logging.getLogger("test.badframes")
    bad = BadFrames(limit=3, logger=logger)
    with caplog.at_level(logging.WARNING, logger="test.badframes"):
        assert not bad.note(0, ["panel: no corners"])
        for k in range(1, 8):
            # one frame, two notes of the same image problem: one warning
            assert bad.note(k, ["image (left): too dark", "ring (left): image too dark"])
        assert bad.note(8, ["ring: internal error: ValueError: x"])
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3 + 1  # three named, then one note that more follow
    assert messages[0] == "frame 1: image (left): too dark"
    assert "more than 3 bad frames" in messages[3]
    assert bad.count == 8
    assert bad.summary(9) == "8 bad frames (of 9): black image 7, internal error in ring 1"
    assert bad.as_dict() == {"black image": 7, "internal error in ring": 1}
