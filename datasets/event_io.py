"""Event files: HDF5 as in DSEC and the text format of the Event Camera Dataset.

- HDF5 (``.h5``): datasets ``events/t`` (int64, microseconds), ``events/x``, ``events/y``
  (uint16), ``events/p`` (uint8, 1 = ON), plus the attribute ``t_offset_us`` on ``events``
  (DSEC stores times relative to ``t_offset``; satpose writes 0). Read with h5py.
- Text (``.txt``): one event per line ``t x y p`` with ``t`` in seconds and ``p`` in {0, 1}
  (Event Camera Dataset, Mueggler et al. 2017).
- AEDAT4 (``.aedat4``, iniVation DV recordings): read and written with ``faery`` (its event
  dtype: ``t`` microseconds, ``x``, ``y``, ``on``); the first event stream of the file.
- Prophesee / Metavision RAW (``.raw``: EVT 2.0, 2.1 and 3.0 encodings, told apart by the
  file's header): read with ``evlib`` (its Rust decoders; checked against a real Prophesee
  EVT3 recording, docs/stars.md). Not written (evlib writes HDF5 and text only).
- Prophesee DAT (``.dat``, the older Metavision/ATIS CD layout: ``%`` header lines, one byte
  event type and one byte event size, then little-endian records of ``uint32 t`` [us] and
  ``uint32`` with x in bits 0-13, y in bits 14-27 and the polarity in bits 28-31): read
  with numpy (no maintained reader on PyPI reads it; evlib does not).

A recording folder holds one of them as ``events.h5`` (what satpose writes), ``events.hdf5``,
``events.txt``, ``events.aedat4``, ``events.raw`` or ``events.dat`` (`find_events_file`).

Writers go to a temporary name and rename into place.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from satpose.datasets.errors import SequenceError
from satpose.datasets.events import EventError, Events
from satpose.datasets.sequence import atomic_write


def write_events_h5(events: Events, path: str | Path) -> Path:
    """Write ``events`` to an HDF5 file in DSEC's layout (gzip-compressed)."""
    import h5py

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            g = f.create_group("events")
            g.attrs["t_offset_us"] = 0
            for name, arr, dt in (
                ("t", events.t_us, np.int64),
                ("x", events.x, np.uint16),
                ("y", events.y, np.uint16),
                ("p", events.p, np.uint8),
            ):
                g.create_dataset(name, data=np.asarray(arr, dtype=dt), compression="gzip")

    return atomic_write(path, write)


def read_events_h5(path: str | Path) -> Events:
    """Read ``events/t,x,y,p`` (DSEC layout; ``t_offset_us`` or DSEC's ``t_offset`` is added)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, None, "event file not found")
    try:
        with h5py.File(path, "r") as f:
            if "events" not in f:
                raise SequenceError(path, "events", "missing group (expected events/t,x,y,p)")
            g = f["events"]
            cols = {}
            for name in ("t", "x", "y", "p"):
                if name not in g:
                    raise SequenceError(path, f"events/{name}", "missing dataset")
                cols[name] = g[name][()]
            off = int(g.attrs.get("t_offset_us", 0)) + int(
                f["t_offset"][()] if "t_offset" in f else 0
            )
    except OSError as exc:
        raise SequenceError(path, None, f"not a readable HDF5 file ({exc})") from None
    t = np.asarray(cols["t"], dtype=np.int64) + off
    try:
        return Events(
            t_us=t,
            x=np.asarray(cols["x"], dtype=np.uint16),
            y=np.asarray(cols["y"], dtype=np.uint16),
            p=(np.asarray(cols["p"]) > 0).astype(np.uint8),
        )
    except EventError as exc:
        raise SequenceError(path, "events", str(exc)) from None


def write_events_txt(events: Events, path: str | Path) -> Path:
    """Write ``t x y p`` lines (t in seconds with microsecond resolution)."""
    data = np.column_stack(
        [events.t_us // 1_000_000, events.t_us % 1_000_000, events.x, events.y, events.p]
    )

    def write(tmp: Path) -> None:
        with open(tmp, "w", encoding="ascii") as f:
            np.savetxt(f, data, fmt="%d.%06d %d %d %d")

    return atomic_write(path, write)


def read_events_txt(path: str | Path) -> Events:
    """Read an Event Camera Dataset ``events.txt`` (``t x y p`` per line, t in seconds)."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, None, "event file not found")
    import pandas as pd

    try:
        df = pd.read_csv(path, sep=r"\s+", header=None, names=["t", "x", "y", "p"], comment="#")
    except (ValueError, OSError) as exc:
        raise SequenceError(path, None, f"cannot parse 't x y p' lines ({exc})") from None
    if df.isna().any().any() or (df.shape[0] and not np.isfinite(df["t"].to_numpy()).all()):
        raise SequenceError(path, "t x y p", "a line has missing or non-numeric fields")
    try:
        return Events(
            t_us=np.rint(df["t"].to_numpy(dtype=float) * 1e6).astype(np.int64),
            x=df["x"].to_numpy(dtype=np.uint16),
            y=df["y"].to_numpy(dtype=np.uint16),
            p=(df["p"].to_numpy() > 0).astype(np.uint8),
        )
    except EventError as exc:
        raise SequenceError(path, "t", str(exc)) from None


def write_events_aedat4(events: Events, path: str | Path, width: int, height: int) -> Path:
    """Write an AEDAT4 file (faery) with sensor size ``width`` x ``height``."""
    import faery

    arr = np.zeros(len(events), dtype=faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = events.t_us, events.x, events.y, events.p > 0
    return atomic_write(
        path,
        lambda tmp: faery.events_stream_from_array(arr, dimensions=(width, height)).to_file(
            str(tmp)
        ),
    )


def read_events_aedat4(path: str | Path) -> Events:
    """Read the first event stream of an AEDAT4 file (faery)."""
    import faery

    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, None, "event file not found")
    try:
        arr = faery.events_stream_from_file(str(path)).to_array()
    except Exception as exc:  # faery raises its own (Rust) error types
        raise SequenceError(path, None, f"not a readable AEDAT4 file ({exc})") from None
    try:
        return Events(
            t_us=arr["t"].astype(np.int64),
            x=arr["x"].astype(np.uint16),
            y=arr["y"].astype(np.uint16),
            p=arr["on"].astype(np.uint8),
        )
    except EventError as exc:
        raise SequenceError(path, "events", str(exc)) from None


def read_events_raw(path: str | Path) -> Events:
    """Read a Prophesee / Metavision ``.raw`` file (EVT 2.0, 2.1 or 3.0) with evlib."""
    import logging

    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, None, "event file not found")
    logging.getLogger("evlib").setLevel(logging.ERROR)  # its import warns about PyTorch
    import evlib

    try:
        fmt = evlib.detect_format(str(path))
        if not str(fmt[0]).upper().startswith("EVT"):
            raise SequenceError(
                path, None, f"not a Prophesee RAW file (its header reads as {fmt[0]})"
            )
        df = evlib.load_events(str(path)).collect()
    except SequenceError:
        raise
    except Exception as exc:  # evlib raises OSError, ValueError and its own errors
        raise SequenceError(path, None, f"not a readable Prophesee RAW file ({exc})") from None
    try:
        return Events(
            t_us=df["t"].cast(int).to_numpy().astype(np.int64),
            x=df["x"].to_numpy().astype(np.uint16),
            y=df["y"].to_numpy().astype(np.uint16),
            p=(df["polarity"].to_numpy() > 0).astype(np.uint8),
        )
    except EventError as exc:
        raise SequenceError(path, "events", str(exc)) from None


def write_events_dat(events: Events, path: str | Path, width: int, height: int) -> Path:
    """Write a Prophesee DAT file (CD events; the layout in the module docstring)."""
    header = f"% Data file containing CD events.\n% Version 2\n% Width {width}\n% Height {height}\n"
    rec = np.zeros(len(events), dtype=[("t", "<u4"), ("d", "<u4")])
    rec["t"] = events.t_us
    rec["d"] = (
        events.x.astype(np.uint32)
        | (events.y.astype(np.uint32) << 14)
        | (events.p.astype(np.uint32) << 28)
    )

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(bytes([0x0C, 8]))  # event type: CD; event size: 8 bytes
            f.write(rec.tobytes())

    return atomic_write(path, write)


def read_events_dat(path: str | Path) -> Events:
    """Read a Prophesee DAT file of CD events (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, None, "event file not found")
    data = path.read_bytes()
    i = 0
    while i < len(data) and data[i : i + 1] == b"%":
        j = data.find(b"\n", i)
        if j < 0:
            raise SequenceError(path, None, "header line without an end")
        i = j + 1
    if len(data) < i + 2:
        raise SequenceError(path, None, "no event type and size after the header")
    size = data[i + 1]
    if size != 8:
        raise SequenceError(path, "event size", f"expected 8 bytes per event, got {size}")
    body = data[i + 2 :]
    if len(body) % 8:
        raise SequenceError(
            path, None, f"truncated: {len(body)} bytes is not a whole number of events"
        )
    rec = np.frombuffer(body, dtype=[("t", "<u4"), ("d", "<u4")])
    d = rec["d"]
    try:
        return Events(
            t_us=rec["t"].astype(np.int64),
            x=(d & 0x3FFF).astype(np.uint16),
            y=((d >> 14) & 0x3FFF).astype(np.uint16),
            p=((d >> 28) > 0).astype(np.uint8),
        )
    except EventError as exc:
        raise SequenceError(path, "events", str(exc)) from None


def read_events(path: str | Path) -> Events:
    """Read ``.h5``/``.hdf5``, ``.txt``, ``.aedat4``, ``.raw`` or ``.dat`` events by
    extension."""
    path = Path(path)
    if path.suffix in (".h5", ".hdf5"):
        return read_events_h5(path)
    if path.suffix == ".txt":
        return read_events_txt(path)
    if path.suffix == ".aedat4":
        return read_events_aedat4(path)
    if path.suffix == ".raw":
        return read_events_raw(path)
    if path.suffix == ".dat":
        return read_events_dat(path)
    raise SequenceError(
        path, None, "unknown event file type (expected .h5, .txt, .aedat4, .raw or .dat)"
    )


EVENT_FILE_NAMES = (
    "events.h5",
    "events.hdf5",
    "events.txt",
    "events.aedat4",
    "events.raw",
    "events.dat",
)
"""The event file names a recording folder may hold, in the order they are looked for."""


def find_events_file(folder: str | Path) -> Path | None:
    """The recording's event file: the first of `EVENT_FILE_NAMES` in ``folder``, or None."""
    for name in EVENT_FILE_NAMES:
        if (Path(folder) / name).is_file():
            return Path(folder) / name
    return None
