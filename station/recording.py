"""Recordings as ICD.md §5 defines them: a CAN log plus a metadata file.

A recording must outlive the station that wrote it and be readable by other
benches, so the writer never leaves a half-written log under the final name:
frames go to a hidden temporary file in the target directory, and only a
completed run is moved into place (``os.replace`` is atomic on one file
system), metadata last.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from types import TracebackType
from typing import Any, Final

import can
import numpy as np
from can.io.mf4 import STD_DTYPE, MF4Writer
from can.util import channel2int
from numpy.typing import NDArray

from drivers.cia301 import SYNC_COB_ID
from station.blf import write_can_frames
from station.core import Axis
from station.errors import InputError, RecordingError

RECORDING_FORMAT: Final = "hsm-recording/1"

FRAMES_RECORDED_KEY: Final = "frames_recorded"
"""Metadata key this writer adds: every frame it wrote, so that a reader catches a
cut log even where the format has no end marker. Other benches may omit it."""

# Time one 8-byte standard frame occupies at 1 Mbit/s with typical bit stuffing;
# used to space simulated timestamps the way a real bus would.
_FRAME_SPACING_S: Final = 130e-6


class LogFormat(StrEnum):
    """Log formats of ICD.md §5, by file suffix (all read by python-can's LogReader)."""

    ASC = ".asc"
    BLF = ".blf"
    CANDUMP = ".log"
    CSV = ".csv"
    MF4 = ".mf4"


def log_format_for(path: Path) -> LogFormat:
    """The format a recording path asks for; anything else is an input error."""
    try:
        return LogFormat(path.suffix.lower())
    except ValueError:
        known = ", ".join(f.value for f in LogFormat)
        raise InputError(
            f"{path}: unknown recording suffix {path.suffix!r}; use one of {known}"
        ) from None


def metadata_path_for(log_path: Path) -> Path:
    """ICD.md §5: the metadata file has the log's stem and the suffix ``.json``."""
    return log_path.with_suffix(".json")


_REQUIRED_KEYS: Final[dict[str, type | tuple[type, ...]]] = {
    "format": str,
    "serial": str,
    "drive_node": int,
    "sensor_node": int,
    "sync_period_s": (int, float),
    "microsteps_per_fullstep": int,
    "rotor_teeth": int,
    "rated_current_mA": (int, float),
    "sensor_lsb_mps2": (int, float),
    "tangential_axis": str,
    "sensor_radius_m": (int, float),
    "gear_ratio": (int, float),
}


@dataclass(frozen=True)
class RecordingMetadata:
    """The keys ICD.md §5 requires, plus whatever else a writer adds (``extra``)."""

    serial: str
    drive_node: int
    sensor_node: int
    sync_period_s: float
    microsteps_per_fullstep: int
    rotor_teeth: int
    rated_current_mA: float
    sensor_lsb_mps2: float
    tangential_axis: Axis
    sensor_radius_m: float
    gear_ratio: float
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def sensor_full_scale_mps2(self) -> float:
        """The acceleration the sensor's range ends at: its sensitivity is range·g/32768
        (ICD.md §3, 0x2001), so the range is read back from the sensitivity alone."""
        return self.sensor_lsb_mps2 * 32768.0

    def to_json_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": RECORDING_FORMAT,
            "serial": self.serial,
            "drive_node": self.drive_node,
            "sensor_node": self.sensor_node,
            "sync_period_s": self.sync_period_s,
            "microsteps_per_fullstep": self.microsteps_per_fullstep,
            "rotor_teeth": self.rotor_teeth,
            "rated_current_mA": self.rated_current_mA,
            "sensor_lsb_mps2": self.sensor_lsb_mps2,
            "tangential_axis": self.tangential_axis.value,
            "sensor_radius_m": self.sensor_radius_m,
            "gear_ratio": self.gear_ratio,
        }
        for key, value in self.extra.items():
            doc.setdefault(key, value)
        return doc

    @classmethod
    def from_json_dict(
        cls, doc: Mapping[str, Any], *, source: str = "metadata"
    ) -> RecordingMetadata:
        """Strict reading: every ICD key present, of the right type and in range."""
        for key, kinds in _REQUIRED_KEYS.items():
            if key not in doc:
                raise RecordingError(f"{source}: missing key {key!r}")
            value = doc[key]
            if isinstance(value, bool) or not isinstance(value, kinds):
                raise RecordingError(f"{source}: key {key!r} has a malformed value {value!r}")
        if doc["format"] != RECORDING_FORMAT:
            raise RecordingError(
                f"{source}: key 'format' is {doc['format']!r}, expected {RECORDING_FORMAT!r}"
            )
        positive = (
            "sync_period_s",
            "microsteps_per_fullstep",
            "rotor_teeth",
            "rated_current_mA",
            "sensor_lsb_mps2",
            "sensor_radius_m",
            "gear_ratio",
        )
        for key in positive:
            if not math.isfinite(float(doc[key])) or float(doc[key]) <= 0:
                raise RecordingError(f"{source}: key {key!r} must be positive, got {doc[key]!r}")
        for key in ("drive_node", "sensor_node"):
            if not 1 <= int(doc[key]) <= 127:
                raise RecordingError(f"{source}: key {key!r} must be a node-ID 1..127")
        try:
            axis = Axis(str(doc["tangential_axis"]).lower())
        except ValueError:
            raise RecordingError(
                f"{source}: key 'tangential_axis' must be x, y or z, got {doc['tangential_axis']!r}"
            ) from None
        extra = {k: v for k, v in doc.items() if k not in _REQUIRED_KEYS}
        return cls(
            serial=str(doc["serial"]),
            drive_node=int(doc["drive_node"]),
            sensor_node=int(doc["sensor_node"]),
            sync_period_s=float(doc["sync_period_s"]),
            microsteps_per_fullstep=int(doc["microsteps_per_fullstep"]),
            rotor_teeth=int(doc["rotor_teeth"]),
            rated_current_mA=float(doc["rated_current_mA"]),
            sensor_lsb_mps2=float(doc["sensor_lsb_mps2"]),
            tangential_axis=axis,
            sensor_radius_m=float(doc["sensor_radius_m"]),
            gear_ratio=float(doc["gear_ratio"]),
            extra=extra,
        )


def read_metadata(log_path: Path) -> RecordingMetadata:
    """Load and validate the metadata beside a log."""
    path = metadata_path_for(log_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecordingError(f"{log_path}: metadata file {path.name} is missing") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read metadata: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: metadata is not UTF-8 text") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RecordingError(
            f"{path}: metadata is not valid JSON ({exc.msg}, line {exc.lineno})"
        ) from None
    if not isinstance(doc, dict):
        raise RecordingError(f"{path}: metadata must be a JSON object")
    return RecordingMetadata.from_json_dict(doc, source=str(path))


def write_text_atomically(path: Path, text: str) -> None:
    """Write a text file so that readers see either the old file or the whole new one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json_atomically(path: Path, doc: Mapping[str, Any]) -> None:
    write_text_atomically(path, json.dumps(doc, indent=2, sort_keys=False) + "\n")


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
