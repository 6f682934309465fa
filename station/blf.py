"""Binary Logging Files of plain CAN frames, written and read as arrays in one pass.

python-can's ``BLFWriter`` takes one message per call, about 10 µs each: a simulated
characterization's 243,000 frames spent 2.4 s there and 1.6 s more being copied into
messages for it, half the time of recording a trial in process. The frames of an
in-process run are arrays already, so here each becomes one fixed-size CAN_MESSAGE
object (an object header, its version-1 time header and the frame: 48 bytes, no
padding) in one numpy record array, cut into log containers of the size python-can
uses and compressed as it compresses them. The file is the one ``BLFWriter`` writes
for the same frames, byte for byte (``tests/test_blf.py``): readers see no difference.

Reading is the same in reverse: python-can's ``BLFReader`` makes a message per frame,
2.4 s of every diagnosis of a simulated characterization. A file whose every object is
a plain CAN_MESSAGE in compressed or stored containers (what python-can and this
station write) is read as arrays here, giving what that reader would give, down to the
timestamps' bits; any other file is left to it (``NotPlainCan``). A container at a time:
read whole, a ten-minute log's analysis peaked at 562 MB against its 400 MB target (333
MB frame by frame, 337 MB now).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from can.io.blf import systemtime_to_timestamp, timestamp_to_systemtime
from numpy.typing import NDArray

_FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQLL8H8H")
_FILE_HEADER_SIZE = 144
_CONTAINER_HEADER = struct.Struct("<4sHHLLH6xL4x")  # object header, then container's
_CONTAINER_BASE_SIZE = 16  # the object header alone, which a container's size field counts
_CONTAINER_SIZE = 128 * 1024  # uncompressed bytes per container, as python-can cuts them
_APPLICATION_ID = 5  # python-can's; a reader keys nothing on it
_CAN_MESSAGE = 1
_LOG_CONTAINER = 10
_NO_COMPRESSION = 0
_ZLIB_DEFLATE = 2
_TIME_TEN_MICS = 1
_TIME_ONE_NANS = 2
_EXTENDED = 0x80000000
_REMOTE = 0x80
_CHANNEL = 1  # one recording is one bus (RecordingWriter leaves the channel unset)

_OBJECT = np.dtype([
    ("signature", "S4"), ("header_size", "<u2"), ("header_version", "<u2"),
    ("object_size", "<u4"), ("object_type", "<u4"),
    ("time_flags", "<u4"), ("client", "<u2"), ("object_version", "<u2"),
    ("time_ns", "<u8"),
    ("channel", "<u2"), ("flags", "u1"), ("dlc", "u1"), ("can_id", "<u4"), ("data", "u1", 8),
])
_HEADERS = 32  # the object's two headers, before the frame


def write_can_frames(path: Path, timestamps: NDArray[np.float64], cob_ids: NDArray[np.integer],
                     lengths: NDArray[np.integer], payloads: NDArray[np.uint8]) -> None:
    """Write standard (11-bit), received data frames as a BLF file at ``path``.

    ``payloads`` is (K, 8); bytes beyond a frame's length are written as zero whatever
    they hold. Times are kept in nanoseconds from the first frame's, truncated to the
    millisecond as the file header keeps it.
    """
    count = len(timestamps)
    stamps = np.asarray(timestamps, dtype=np.float64)
    start = int(float(stamps[0]) * 1000) / 1000 if count else None
    objects = np.zeros(count, dtype=_OBJECT)
    objects["signature"] = b"LOBJ"
    objects["header_size"] = _HEADERS
    objects["header_version"] = 1
    objects["object_size"] = _OBJECT.itemsize
    objects["object_type"] = _CAN_MESSAGE
    objects["time_flags"] = _TIME_ONE_NANS
    if start is not None:
        objects["time_ns"] = np.maximum(np.trunc((stamps - start) * 1e9), 0.0).astype(np.uint64)
    objects["channel"] = _CHANNEL
    size = np.asarray(lengths, dtype=np.uint8)
    objects["dlc"] = size
    objects["can_id"] = np.asarray(cob_ids, dtype=np.uint32)
    objects["data"] = np.where(np.arange(8)[None, :] < size[:, None],
                               np.asarray(payloads, dtype=np.uint8).reshape(count, 8), 0)
    stream = objects.tobytes()
    with path.open("wb") as out:
        out.write(bytes(_FILE_HEADER_SIZE))  # rewritten once the sizes are known
        uncompressed = _FILE_HEADER_SIZE
        for at in range(0, len(stream), _CONTAINER_SIZE):
            chunk = stream[at:at + _CONTAINER_SIZE]
            packed = zlib.compress(chunk, -1)
            object_size = _CONTAINER_HEADER.size + len(packed)
            out.write(_CONTAINER_HEADER.pack(b"LOBJ", _CONTAINER_BASE_SIZE, 1, object_size,
                                             _LOG_CONTAINER, _ZLIB_DEFLATE, len(chunk)))
            out.write(packed)
            out.write(bytes(object_size % 4))
            uncompressed += _CONTAINER_HEADER.size + len(chunk)
        file_size = out.tell()
        out.seek(0)
        stop = float(stamps[-1]) if count else None
        out.write(_FILE_HEADER.pack(
            b"LOGG", _FILE_HEADER_SIZE, _APPLICATION_ID, 0, 0, 0, 2, 6, 8, 1,
            file_size, uncompressed, count, 0,
            *timestamp_to_systemtime(start), *timestamp_to_systemtime(stop)))


@dataclass(frozen=True)
class CanFrames:
    """A log's CAN frames in file order, as python-can's reader would give them."""

    timestamps: NDArray[np.float64]
    arbitration_ids: NDArray[np.uint32]  # without the extended-id flag
    extended: NDArray[np.bool_]
    remote: NDArray[np.bool_]
    lengths: NDArray[np.uint8]  # bytes of data (a DLC beyond 8 gives 8, a remote frame 0)
    data: NDArray[np.uint8]  # (K, 8); bytes beyond the length are zero


class NotPlainCan(Exception):
    """The file is not (only) plain CAN messages in containers: read it another way."""


def can_frame_chunks(path: Path) -> Iterator[CanFrames]:
    """The frames of the BLF file at ``path``, a container's worth at a time (so that a
    ten-minute log is never held whole), while every object is a plain CAN message.
    Raises ``NotPlainCan`` on the first header, container or object of any other kind,
    a container that does not decompress, or a cut object: what was given before it
    must then be dropped."""
    with path.open("rb") as log:
        head = log.read(_FILE_HEADER.size)
        if len(head) < _FILE_HEADER.size:
            raise NotPlainCan("no BLF file header")
        header = _FILE_HEADER.unpack(head)
        if header[0] != b"LOGG":
            raise NotPlainCan("no BLF signature")
        start = systemtime_to_timestamp(header[14:22])
        log.seek(header[1])
        tail = b""
        while base := log.read(_CONTAINER_HEADER.size):
            if len(base) < _CONTAINER_HEADER.size:
                raise NotPlainCan("a cut object header")
            signature, _, _, size, kind, method, _ = _CONTAINER_HEADER.unpack(base)
            if signature != b"LOBJ" or kind != _LOG_CONTAINER or size < len(base):
                raise NotPlainCan("an object that is not a log container")
            body = log.read(size - len(base))
            log.read(size % 4)
            stream = tail + _unpacked(method, body)
            whole = len(stream) - len(stream) % _OBJECT.itemsize
            tail = stream[whole:]
            yield _plain(np.frombuffer(stream, dtype=_OBJECT, count=whole // _OBJECT.itemsize),
                         start)
        if tail:
            raise NotPlainCan("a cut object at the end")


def _unpacked(method: int, body: bytes) -> bytes:
    if method == _NO_COMPRESSION:
        return body
    if method != _ZLIB_DEFLATE:
        raise NotPlainCan(f"compression method {method}")
    try:
        return zlib.decompressobj().decompress(body)
    except zlib.error as exc:
        raise NotPlainCan(str(exc)) from None


def _plain(objects: NDArray[np.void], start: float) -> CanFrames:
    """The frames of ``objects`` as python-can's reader gives them."""
    if not (np.all(objects["signature"] == b"LOBJ") and np.all(objects["header_size"] == _HEADERS)
            and np.all(objects["header_version"] == 1)
            and np.all(objects["object_size"] == _OBJECT.itemsize)
            and np.all(objects["object_type"] == _CAN_MESSAGE)):
        raise NotPlainCan("an object that is not a plain CAN message")
    # The reader's own arithmetic: ticks times an exact decimal factor, rounded once,
    # plus the start; a division by the exact power of ten rounds the same.
    ticks = objects["time_ns"].astype(np.float64)
    ticks /= np.where(objects["time_flags"] == _TIME_TEN_MICS, 1e5, 1e9)
    remote = (objects["flags"] & _REMOTE) != 0
    # A remote frame carries no data, whatever its DLC says (python-can's Message).
    lengths = np.where(remote, 0, np.minimum(objects["dlc"], 8)).astype(np.uint8)
    data = np.where(np.arange(8)[None, :] < lengths[:, None], objects["data"], 0)
    can_id = objects["can_id"]
    return CanFrames(
        timestamps=ticks + start,
        arbitration_ids=(can_id & 0x1FFFFFFF).astype(np.uint32),
        extended=(can_id & _EXTENDED) != 0,
        remote=remote,
        lengths=lengths,
        data=data.astype(np.uint8),
    )
