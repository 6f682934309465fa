"""Read an ICD.md §5 recording into a timeline: the only I/O of the analysis.

The log is iterated once with python-can's own ``LogReader``, so every format
it reads is read the same way. A ten-minute log is millions of frames: the
loop keeps no ``can.Message``, only a tag, a timestamp and the payload bytes
of the ICD frames in compact buffers, decoded afterwards with numpy.

A recording that stops early must not pass for a short run, and some readers
stop silently at a cut, so each format's own end marker is checked too.
"""

from __future__ import annotations

import gc
import struct
import sys
from array import array
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import can
import numpy as np
from numpy.typing import NDArray

from station.analysis.commanded import (
    DRIVE_COMMANDS_KEY,
    commanded_timeline,
    commands_from_metadata,
)
from station.analysis.timeline import (
    PAYLOAD_BYTES,
    FrameKind,
    Timeline,
    build_timeline,
    icd_frames,
)
from station.blf import CanFrames, NotPlainCan, can_frame_chunks
from station.cia301 import SYNC_COB_ID
from station.errors import RecordingError
from station.recording import (
    FRAMES_RECORDED_KEY,
    LogFormat,
    RecordingMetadata,
    read_metadata,
    require_recording,
)

ASC_END_MARKER: Final = "end triggerblock"
"""Last line of a complete Vector ASC log (case as Vector and python-can vary)."""

_TAIL_BYTES = 4096

# python-can's BLF writer puts a placeholder header (its own size, no objects)
# first and fills it in only when it closes the file.
_BLF_PLACEHOLDER_SIZE = 144

_NAMES: Final = {
    FrameKind.SYNC: f"SYNC (COB-ID 0x{SYNC_COB_ID:03X})",
    FrameKind.SENSOR: "sensor TPDO1",
    FrameKind.DRIVE_STATUS: "drive TPDO1",
}


@dataclass(frozen=True)
class LogFrames:
    """The ICD frames of one log in bus order, with what was left out."""

    kinds: NDArray[np.uint8]  # FrameKind per frame
    payloads: NDArray[np.uint8]  # (K, 8); a SYNC's counter in column 0
    frames_total: int  # every frame the log holds
    frames_ignored: int
    frames_malformed: int


def read_recording(log_path: Path) -> Timeline:
    """The sample timeline of a recording (log plus metadata beside it)."""
    log_format = require_recording(log_path)
    metadata = read_metadata(log_path)
    frames = read_log_frames(log_path, log_format, metadata)
    timeline = build_timeline(
        metadata,
        frames.kinds,
        frames.payloads,
        frames_ignored=frames.frames_ignored,
        frames_malformed=frames.frames_malformed,
    )
    if DRIVE_COMMANDS_KEY in metadata.extra:
        # A drive that sent nothing on the bus (Modbus): the station's log stands in for it.
        commands, timing = commands_from_metadata(metadata.extra)
        timeline = commanded_timeline(timeline, commands, timing)
    return timeline


def read_log_frames(
    log_path: Path, log_format: LogFormat, metadata: RecordingMetadata
) -> LogFrames:
    """Stream the log once, keeping the ICD frames and checking the log is whole."""
    if not log_path.is_file():
        raise RecordingError(f"{log_path}: log file is missing")
    if metadata.drive_node == metadata.sensor_node:
        raise RecordingError(
            f"{log_path}: drive and sensor share node-ID {metadata.drive_node}; "
            "their TPDO1 frames cannot be told apart"
        )
    expected = _expected_frames(log_path, metadata)
    reader = _open_reader(log_path, log_format)
    with reader:
        _check_complete_before(log_path, log_format, reader)
        scan = _scan_blf(log_path, metadata) if log_format is LogFormat.BLF else None
        if scan is None:
            scan = _scan(log_path, reader, metadata)
    if expected is not None and scan.frames_total < expected:
        raise RecordingError(
            f"{log_path}: the log is truncated: it holds {scan.frames_total} frames, "
            f"the metadata says {expected} were recorded"
        )
    counts = np.bincount(scan.kinds, minlength=len(FrameKind))
    # A drive reached over Modbus sends nothing on the bus; the station's write log
    # in the metadata stands in for its frames.
    drive_on_bus = DRIVE_COMMANDS_KEY not in metadata.extra
    for kind, name in _NAMES.items():
        if counts[kind] == 0 and (drive_on_bus or kind is not FrameKind.DRIVE_STATUS):
            raise RecordingError(f"{log_path}: the log holds no {name} frame")
    return scan


def _expected_frames(log_path: Path, metadata: RecordingMetadata) -> int | None:
    if FRAMES_RECORDED_KEY not in metadata.extra:
        return None
    value = metadata.extra[FRAMES_RECORDED_KEY]
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise RecordingError(
            f"{log_path}: metadata key {FRAMES_RECORDED_KEY!r} has a malformed value {value!r}"
        )
    return value


@contextmanager
def _quiet_asammdf_finaliser() -> Iterator[None]:
    """asammdf's ``MDF4.__del__`` raises on an object whose constructor failed
    (a cut MF4 file), which Python reports as an unraisable exception at some
    later, unrelated moment. Those reports, and only those, are dropped while
    a reader is opened."""
    previous = sys.unraisablehook

    def hook(report: Any) -> None:
        if getattr(report.object, "__qualname__", "") != "MDF4.__del__":
            previous(report)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _open_reader(log_path: Path, log_format: LogFormat) -> can.io.generic.MessageReader:
    failure = ""
    with _quiet_asammdf_finaliser():
        try:
            reader: can.io.generic.MessageReader = can.LogReader(str(log_path))
        except Exception as exc:  # each reader fails its own way on a bad file
            failure = _describe(exc)
        else:
            return reader
        # The half-built reader dies here, inside the quiet window.
        gc.collect()
    what = f"cannot be read as {log_format.name} (truncated or not that format)"
    raise RecordingError(f"{log_path}: {what}: {failure}")


def _describe(exc: BaseException) -> str:
    if isinstance(exc, struct.error):
        # A reader unpacking a header longer than the file: python's words for it
        # ("unpack requires a buffer of 72 bytes") say nothing to whoever holds the file.
        return "its header is cut short"
    if isinstance(exc, ValueError) and "values to unpack" in str(exc):
        return "a line does not have the format's fields"
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _check_complete_before(
    log_path: Path, log_format: LogFormat, reader: can.io.generic.MessageReader
) -> None:
    """Truncation a reader would not notice, judged before the long read."""
    checks: dict[LogFormat, Callable[[Path, can.io.generic.MessageReader], str | None]] = {
        LogFormat.BLF: _blf_incomplete,
        LogFormat.ASC: _asc_incomplete,
        LogFormat.CANDUMP: _last_line_incomplete,
        LogFormat.CSV: _last_line_incomplete,
        # asammdf refuses a cut MF4 file itself (its blocks point past the end).
    }
    check = checks.get(log_format)
    problem = check(log_path, reader) if check is not None else None
    if problem is not None:
        raise RecordingError(f"{log_path}: the log is truncated: {problem}")


def _blf_incomplete(log_path: Path, reader: can.io.generic.MessageReader) -> str | None:
    """python-can's BLFReader stops quietly at a cut (a partial zlib container
    decompresses to fewer objects), but the file header says how big the file is."""
    promised = int(getattr(reader, "file_size", 0))
    objects = int(getattr(reader, "object_count", 0))
    actual = log_path.stat().st_size
    if actual < promised:
        return f"the BLF header promises {promised} bytes, the file has {actual}"
    if promised == _BLF_PLACEHOLDER_SIZE and objects == 0 and actual > promised:
        return "the BLF header was never completed (the writer did not close the file)"
    return None


def _tail(log_path: Path) -> bytes:
    with log_path.open("rb") as stream:
        size = stream.seek(0, 2)
        stream.seek(max(0, size - _TAIL_BYTES))
        return stream.read()


def _asc_incomplete(log_path: Path, _reader: can.io.generic.MessageReader) -> str | None:
    lines = _tail(log_path).rstrip().splitlines()
    last = lines[-1].decode("ascii", "replace").strip() if lines else ""
    if " ".join(last.lower().split()) != ASC_END_MARKER:
        if not last.isprintable():
            return "an ASC log is text ending with 'End TriggerBlock'; this one is not text"
        return f"an ASC log ends with 'End TriggerBlock', this one with {last[:60]!r}"
    return None


def _last_line_incomplete(log_path: Path, _reader: can.io.generic.MessageReader) -> str | None:
    """Line-per-frame formats: a writer ends every line, so a cut one shows."""
    if not _tail(log_path).endswith(b"\n"):
        return "the last line is incomplete (no line end)"
    return None


def _scan(
    log_path: Path, reader: can.io.generic.MessageReader, metadata: RecordingMetadata
) -> LogFrames:
    """The hot loop: one dict lookup and three appends per kept frame."""
    kinds = bytearray()
    stamps = array("d")
    sync_bytes = bytearray()
    tpdo_bytes = bytearray()
    buffers = {FrameKind.SYNC: sync_bytes}
    wanted: dict[int, tuple[int, int, bytearray]] = {
        cob_id: (kind, size, buffers.get(kind, tpdo_bytes))
        for cob_id, (kind, size) in icd_frames(metadata.drive_node, metadata.sensor_node).items()
    }
    lookup = wanted.get
    add_kind = kinds.append
    add_stamp = stamps.append
    total = 0
    malformed = 0
    try:
        for total, msg in enumerate(reader, 1):  # noqa: B007 - read after the loop
            spec = lookup(msg.arbitration_id)
            if spec is None:
                continue
            if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
                continue  # an ICD number, but not an ICD frame: ignored
            kind, size, buffer = spec
            data = msg.data
            if len(data) != size:
                malformed += 1
                continue
            add_kind(kind)
            add_stamp(msg.timestamp)
            buffer += data
    except Exception as exc:  # each reader fails its own way on a bad file
        raise RecordingError(
            f"{log_path}: cannot be parsed after frame {total} "
            f"(truncated or corrupt): {_describe(exc)}"
        ) from None
    kind_array = np.frombuffer(kinds, dtype=np.uint8)
    payloads = np.zeros((kind_array.size, PAYLOAD_BYTES), dtype=np.uint8)
    is_sync = kind_array == FrameKind.SYNC
    payloads[is_sync, 0] = np.frombuffer(sync_bytes, dtype=np.uint8)
    payloads[~is_sync] = np.frombuffer(tpdo_bytes, dtype=np.uint8).reshape(-1, PAYLOAD_BYTES)
    del is_sync
    return _in_time_order(kind_array, payloads, np.frombuffer(stamps, dtype=np.float64),
                          total, malformed)


def _scan_blf(log_path: Path, metadata: RecordingMetadata) -> LogFrames | None:
    """A BLF log of plain CAN messages read as arrays; None for any other, which
    python-can's reader reads its own way (``_scan``)."""
    try:
        return _scan_chunks(can_frame_chunks(log_path), metadata)
    except NotPlainCan:
        return None


def _scan_chunks(chunks: Iterable[CanFrames], metadata: RecordingMetadata) -> LogFrames:
    """``_scan`` of a log read as arrays a container at a time (``station.blf``), only
    the ICD frames of each kept, as the frame loop keeps them."""
    wanted = icd_frames(metadata.drive_node, metadata.sensor_node)
    kinds, payloads, stamps = [], [], []
    total = malformed = 0
    for frames in chunks:
        count = frames.timestamps.size
        kind = np.full(count, len(FrameKind), dtype=np.uint8)  # not an ICD frame
        size = np.zeros(count, dtype=np.uint8)
        for cob_id, (frame_kind, length) in wanted.items():
            ours = frames.arbitration_ids == cob_id
            kind[ours], size[ours] = frame_kind, length
        icd = (kind < len(FrameKind)) & ~frames.extended & ~frames.remote
        kept = icd & (frames.lengths == size)
        # A SYNC's one byte stays in column 0, the rest zero, as ``_scan`` lays it out.
        kinds.append(kind[kept])
        payloads.append(frames.data[kept])
        stamps.append(frames.timestamps[kept])
        total += count
        malformed += int(np.count_nonzero(icd & ~kept))
    return _in_time_order(
        np.concatenate(kinds) if kinds else np.zeros(0, np.uint8),
        np.concatenate(payloads) if payloads else np.zeros((0, PAYLOAD_BYTES), np.uint8),
        np.concatenate(stamps) if stamps else np.zeros(0), total, malformed)


def _in_time_order(kind_array: NDArray[np.uint8], payloads: NDArray[np.uint8],
                   times: NDArray[np.float64], total: int, malformed: int) -> LogFrames:
    if times.size > 1 and bool((np.diff(times) < 0).any()):
        # ICD.md §5: timestamps only order frames; a stable sort keeps bus
        # order among frames stamped alike.
        order = np.argsort(times, kind="stable")
        kind_array, payloads = kind_array[order], payloads[order]
    return LogFrames(
        kinds=kind_array,
        payloads=payloads,
        frames_total=total,
        frames_ignored=total - kind_array.size - malformed,
        frames_malformed=malformed,
    )
