"""Writing recordings (ICD.md §5): the CAN log, then its metadata.

A recording must outlive the station that wrote it and be readable by other
benches, so the writer never leaves a half-written log under the final name:
frames go to a hidden temporary file in the target directory, and only a
completed run is moved into place (``os.replace`` is atomic on one file
system), metadata last.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import Final

import can
import numpy as np
from can.io.mf4 import STD_DTYPE, MF4Writer
from can.util import channel2int
from numpy.typing import NDArray

from station.blf import write_can_frames
from station.cia301 import SYNC_COB_ID
from station.errors import InputError, RecordingError
from station.recording import (
    FRAMES_RECORDED_KEY,
    LogFormat,
    RecordingMetadata,
    log_format_for,
    metadata_path_for,
    write_json_atomically,
)

# Time one 8-byte standard frame occupies at 1 Mbit/s with typical bit stuffing;
# used to space simulated timestamps the way a real bus would.
_FRAME_SPACING_S: Final = 130e-6


class _BatchedMF4Writer(MF4Writer):
    """python-can's MF4 writer extends the file once per frame (~0.5 ms each);
    batching the data frames into the same channel group keeps the file
    identical in layout and makes a one-minute run take seconds, not minutes."""

    _BATCH: Final = 8192

    def __init__(self, file: str) -> None:
        super().__init__(file)
        self._pending: list[tuple[float, int, int, int, int, bytes]] = []

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            self._flush()
            super().on_message_received(msg)
            return
        timestamp = self.last_timestamp if msg.timestamp is None else msg.timestamp
        self.last_timestamp = max(self.last_timestamp, timestamp)
        channel = channel2int(msg.channel)
        self._pending.append(
            (
                timestamp - self._start_time,
                msg.arbitration_id,
                int(msg.is_extended_id),
                0 if msg.is_rx else 1,
                channel if channel is not None else 0,
                bytes(msg.data),
            )
        )
        if len(self._pending) >= self._BATCH:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        rows = self._pending
        self._pending = []
        block = np.zeros(len(rows), dtype=STD_DTYPE)
        stamps = np.fromiter((r[0] for r in rows), dtype="<f8", count=len(rows))
        block["CAN_DataFrame.ID"] = [r[1] for r in rows]
        block["CAN_DataFrame.IDE"] = [r[2] for r in rows]
        block["CAN_DataFrame.Dir"] = [r[3] for r in rows]
        block["CAN_DataFrame.BusChannel"] = [r[4] for r in rows]
        lengths = [len(r[5]) for r in rows]
        block["CAN_DataFrame.DataLength"] = lengths
        block["CAN_DataFrame.DLC"] = lengths
        payload = block["CAN_DataFrame.DataBytes"]
        for i, row in enumerate(rows):
            if row[5]:
                payload[i, : len(row[5])] = np.frombuffer(row[5], dtype=np.uint8)
        self._mdf.extend(0, [(stamps, None), (block, None)])

    def stop(self) -> None:
        self._flush()
        super().stop()


def _open_log_writer(path: Path, log_format: LogFormat) -> can.Listener:
    if log_format is LogFormat.MF4:
        return _BatchedMF4Writer(str(path))
    return can.Logger(str(path))


class SimulatedClock:
    """Timestamps in simulated time, for benches that run faster than real time.

    A simulated bench advances only on SYNC, so wall-clock receive times would
    compress a one-minute run into seconds. Frames are stamped at SYNC n's
    instant plus one frame time per frame that followed it, as a bus analyser
    on a real 1 Mbit/s bench would show them. Frames before the first SYNC
    (set-up SDO traffic) come one frame time apart, and the first SYNC after
    them: stamps never go backwards, so ordering by time is ordering by bus.
    """

    def __init__(self, sync_period_s: float, start: float | None = None) -> None:
        self._period = sync_period_s
        self._start = time.time() if start is None else start
        self._first_sync: float | None = None
        self._syncs = 0
        self._frames_since_sync = 0
        self._last: float | None = None

    def stamp(self, msg: can.Message) -> float:
        self._frames_since_sync += 1
        if msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id:
            if self._first_sync is None:
                self._first_sync = self._start + (self._frames_since_sync - 1) * _FRAME_SPACING_S
            else:
                self._syncs += 1
            self._frames_since_sync = 0
            stamp = self._first_sync + self._syncs * self._period
        elif self._first_sync is None:
            stamp = self._start + (self._frames_since_sync - 1) * _FRAME_SPACING_S
        else:
            offset = min(self._frames_since_sync * _FRAME_SPACING_S, 0.95 * self._period)
            stamp = self._first_sync + self._syncs * self._period + offset
        if self._last is not None:
            stamp = max(stamp, self._last)
        self._last = stamp
        return stamp


class FrameLoss:
    """Which frames a logger that drops ``probability`` of them drops, one seeded draw per
    frame in bus order: a simulated recording with losses is reproducible, and the frames
    it lost can be told apart from outside (``SimulatedFrames.kept``)."""

    _BLOCK: Final = 65536  # draws made at a time

    def __init__(self, probability: float, seed: int) -> None:
        self.probability = probability
        self._rng = np.random.default_rng(np.random.SeedSequence([seed, 0x10557]))
        self._draws = np.empty(0)
        self._next = 0

    def dropped(self) -> bool:
        """Whether the next frame is dropped (on the bus thread, per frame: no arrays)."""
        if self.probability <= 0.0:
            return False
        self._refill()
        draw = self._draws[self._next]
        self._next += 1
        return bool(draw < self.probability)

    def dropped_block(self, count: int) -> NDArray[np.bool_]:
        """Whether each of the next ``count`` frames is dropped."""
        out = np.zeros(count, dtype=np.bool_)
        done = 0
        while self.probability > 0.0 and done < count:
            self._refill()
            take = min(count - done, len(self._draws) - self._next)
            out[done:done + take] = self._draws[self._next:self._next + take] < self.probability
            self._next += take
            done += take
        return out

    def _refill(self) -> None:
        if self._next >= len(self._draws):
            self._draws = self._rng.random(self._BLOCK)
            self._next = 0


class RecordingWriter(can.Listener):
    """Records every frame it is given into an ICD.md §5 recording.

    ``loss_probability`` models a logger that drops frames (USB adapters under
    load do): dropped frames are chosen by a seeded generator, so a simulated
    recording with losses is reproducible. ``commit`` publishes the log and its
    metadata; leaving the context without committing deletes everything.
    """

    def __init__(
        self,
        path: Path,
        metadata: RecordingMetadata,
        *,
        clock: SimulatedClock | None = None,
        loss_probability: float = 0.0,
        seed: int = 0,
    ) -> None:
        log_format = log_format_for(path)
        if not 0.0 <= loss_probability < 1.0:
            raise InputError(f"frame loss probability must be in [0, 1), got {loss_probability}")
        self.path = path
        self._format = log_format
        self.metadata = metadata
        self._clock = clock
        self._loss = FrameLoss(loss_probability, seed)
        self._tmp = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
        self._lock = threading.Lock()
        self._writer: can.Listener | None = _open_log_writer(self._tmp, log_format)
        self.frames_seen = 0
        self.frames_written = 0
        self._failure: Exception | None = None
        self._closed = False

    def on_message_received(self, msg: can.Message) -> None:
        """Called on the bus reader's thread: it must never raise there, or the
        station's notifier dies and every later SDO times out. A writer failure
        is kept and reported by ``commit``."""
        with self._lock:
            if self._writer is None or self._failure is not None:
                return
            self.frames_seen += 1
            stamp = msg.timestamp if self._clock is None else self._clock.stamp(msg)
            if self._loss.dropped():
                return
            # One recording is one bus: the channel is left to the writer's
            # default, since interface channel names ("can0", a virtual channel's
            # name) map to log channel numbers differently per format.
            copy = can.Message(
                timestamp=stamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                is_rx=msg.is_rx,
                dlc=msg.dlc,
                data=msg.data,
            )
            try:
                self._writer.on_message_received(copy)
            except Exception as exc:
                self._failure = exc
                return
            self.frames_written += 1

    def write_frames(self, timestamps: NDArray[np.float64], cob_ids: NDArray[np.integer],
                     lengths: NDArray[np.integer], payloads: NDArray[np.uint8]) -> None:
        """Record standard data frames known all at once (an in-process simulation's, in
        bus order): the same recording as ``on_message_received`` for each, losses
        drawn the same, and for a BLF log in one pass (``station.blf``). Only into a
        recording given nothing yet; nothing may be given after."""
        if self.frames_seen or self._writer is None or self._failure is not None:
            raise RecordingError(f"{self.path}: frames at once only into an empty recording")
        count = len(timestamps)
        stamps = np.asarray(timestamps, dtype=np.float64)
        if self._clock is not None or self._format is not LogFormat.BLF:
            for stamp, cob_id, length, payload in zip(
                    stamps.tolist(), np.asarray(cob_ids).tolist(), np.asarray(lengths).tolist(),
                    np.asarray(payloads).tolist(), strict=True):
                self.on_message_received(can.Message(
                    timestamp=stamp, arbitration_id=cob_id, is_extended_id=False, dlc=length,
                    data=payload[:length]))
            return
        kept = ~self._loss.dropped_block(count)
        self._stop_writer()  # its empty file is replaced whole
        try:
            write_can_frames(self._tmp, stamps[kept], np.asarray(cob_ids)[kept],
                             np.asarray(lengths)[kept], np.asarray(payloads)[kept])
        except OSError as exc:
            self._failure = exc
            return
        self.frames_seen = count
        self.frames_written = int(np.count_nonzero(kept))

    def _stop_writer(self) -> None:
        with self._lock:
            writer, self._writer = self._writer, None
        if writer is not None:
            writer.stop()

    def commit(self) -> Path:
        """Publish the recording: the log under its name, then its metadata."""
        if self._closed:
            raise RecordingError(f"{self.path}: recording already closed")
        self._closed = True
        if self._failure is not None:
            self.discard()
            raise RecordingError(
                f"{self.path}: the log writer failed during the run: {self._failure}"
            ) from self._failure
        try:
            self._stop_writer()
            os.replace(self._tmp, self.path)
            doc = self.metadata.to_json_dict()
            doc.setdefault(FRAMES_RECORDED_KEY, self.frames_written)
            write_json_atomically(metadata_path_for(self.path), doc)
        except OSError as exc:
            self._tmp.unlink(missing_ok=True)
            raise RecordingError(f"{self.path}: cannot write recording: {exc.strerror}") from None
        return self.path

    def discard(self) -> None:
        """Drop everything written so far; nothing is left behind. Safe twice."""
        self._closed = True
        try:
            self._stop_writer()
        finally:
            self._tmp.unlink(missing_ok=True)

    def stop(self) -> None:
        """can.Listener protocol: a notifier stopping us is not a commit."""

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if not self._closed:
            self.discard()
