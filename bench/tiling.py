"""Long recordings made by repeating a short one, for benchmarks.

The lockstep bench records about three simulated seconds per wall second, so
a ten-minute recording would take minutes to make on every benchmark run. A
recording repeated end to end is as costly to analyse as a recorded one if it
reads as one continuous run: every counter and the position demand go on
where the previous copy stopped, and timestamps keep increasing. With
``tiles=1`` the same code copies a recording into another log format.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from station.analysis.reader import read_recording
from station.analysis.timeline import PAYLOAD_BYTES
from station.cia301 import SYNC_COB_ID, SYNC_COUNTER_OVERFLOW, TPDO1_COB_BASE
from station.core import SENSOR_COUNTER_MODULUS
from station.recording import (
    FRAMES_RECORDED_KEY,
    log_format_for,
    metadata_path_for,
    write_json_atomically,
)

_INT32_SPAN = 1 << 32


@dataclass(frozen=True)
class LogArrays:
    """Every frame of a log as columns, so a tile is rewritten with numpy."""

    stamps: NDArray[np.float64]
    ids: NDArray[np.int64]
    extended: NDArray[np.bool_]
    remote: NDArray[np.bool_]
    error: NDArray[np.bool_]
    rx: NDArray[np.bool_]
    dlc: NDArray[np.uint8]
    lengths: NDArray[np.uint8]  # payload bytes actually carried (a remote frame has none)
    data: NDArray[np.uint8]  # (K, 8), zero-padded

    @property
    def frames(self) -> int:
        return int(self.stamps.size)


@dataclass(frozen=True)
class FrameRoles:
    """Rows of the frames whose contents count samples or positions."""

    sync: NDArray[np.bool_]
    sensor: NDArray[np.bool_]
    drive_status: NDArray[np.bool_]
    first_sync: int  # row of the first SYNC: what precedes it is set-up traffic


@dataclass(frozen=True)
class TileResult:
    recording: Path
    tiles: int
    samples_per_tile: int
    position_per_tile: int
    frames_written: int


def read_log_arrays(path: Path) -> LogArrays:
    """The whole log in memory (a minute of bench traffic is ~250 000 frames)."""
    stamps: list[float] = []
    ids: list[int] = []
    flags: list[tuple[bool, bool, bool, bool]] = []
    dlc: list[int] = []
    payload = bytearray()
    lengths: list[int] = []
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            if len(msg.data) > PAYLOAD_BYTES:
                raise ValueError(f"{path}: frame 0x{msg.arbitration_id:X} is CAN FD, not ICD")
            stamps.append(msg.timestamp)
            ids.append(msg.arbitration_id)
            flags.append((msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.is_rx))
            dlc.append(msg.dlc)
            lengths.append(len(msg.data))
            payload += bytes(msg.data).ljust(PAYLOAD_BYTES, b"\0")
    flag_array = np.array(flags, dtype=np.bool_).reshape(-1, 4)
    return LogArrays(
        stamps=np.array(stamps, dtype=np.float64),
        ids=np.array(ids, dtype=np.int64),
        extended=flag_array[:, 0],
        remote=flag_array[:, 1],
        error=flag_array[:, 2],
        rx=flag_array[:, 3],
        dlc=np.array(dlc, dtype=np.uint8),
        lengths=np.array(lengths, dtype=np.uint8),
        data=np.frombuffer(bytes(payload), dtype=np.uint8).reshape(-1, PAYLOAD_BYTES).copy(),
    )


def frame_roles(log: LogArrays, *, drive_node: int, sensor_node: int) -> FrameRoles:
    """Which frames carry the SYNC counter, the sensor counter and the position demand."""
    plain = ~log.extended & ~log.remote & ~log.error
    sync = plain & (log.ids == SYNC_COB_ID) & (log.lengths == 1)
    full = plain & (log.lengths == PAYLOAD_BYTES)
    syncs = np.flatnonzero(sync)
    if syncs.size == 0:
        raise ValueError("the log holds no SYNC: it has no samples to tile")
    return FrameRoles(
        sync=sync,
        sensor=full & (log.ids == TPDO1_COB_BASE + sensor_node),
        drive_status=full & (log.ids == TPDO1_COB_BASE + drive_node),
        first_sync=int(syncs[0]),
    )


def shifted_payloads(
    data: NDArray[np.uint8], roles: FrameRoles, *, samples: int, position: int
) -> NDArray[np.uint8]:
    """Payloads as if recorded ``samples`` SYNCs later with the position demand
    ``position`` microsteps further on; every counter wraps as the ICD says."""
    out = data.copy()
    sync_counter = out[roles.sync, 0].astype(np.int64)
    out[roles.sync, 0] = (sync_counter - 1 + samples) % SYNC_COUNTER_OVERFLOW + 1
    sensor = out[roles.sensor]
    counter = sensor[:, 0:2].copy().view("<u2")[:, 0].astype(np.int64)
    sensor[:, 0:2] = (
        ((counter + samples) % SENSOR_COUNTER_MODULUS).astype("<u2").view(np.uint8).reshape(-1, 2)
    )
    out[roles.sensor] = sensor
    drive = out[roles.drive_status]
    demand = drive[:, 0:4].copy().view("<i4")[:, 0].astype(np.int64)
    wrapped = (demand + position + _INT32_SPAN // 2) % _INT32_SPAN - _INT32_SPAN // 2
    drive[:, 0:4] = wrapped.astype("<i4").view(np.uint8).reshape(-1, 4)
    out[roles.drive_status] = drive
    return out


def tile_recording(source: Path, out: Path, tiles: int) -> TileResult:
    """Write ``tiles`` copies of ``source`` end to end into ``out`` (any log suffix).

    A tile lasts the source's samples, counted from its first SYNC, so tile
    k+1's first SYNC follows tile k's last sample with no gap. Set-up traffic
    before the first SYNC is kept only once, at the start: a later copy of it
    would be stamped before the end of the previous tile. The source should
    start and end at standstill, as a schedule does, so that the position
    demand, continued from where the previous tile left it, does not jump.
    """
    if tiles < 1:
        raise ValueError(f"tiles must be at least 1, got {tiles}")
    log_format_for(out)  # refuse an unknown suffix before the long work
    timeline = read_recording(source)
    metadata = timeline.metadata
    samples = timeline.samples
    positions = timeline.position[timeline.drive_valid]
    position_step = int(positions[-1] - positions[0]) if positions.size else 0
    log = read_log_arrays(source)
    roles = frame_roles(log, drive_node=metadata.drive_node, sensor_node=metadata.sensor_node)
    duration = samples * metadata.sync_period_s
    written = 0
    writer = can.Logger(str(out))
    try:
        for k in range(tiles):
            first = 0 if k == 0 else roles.first_sync
            payloads = shifted_payloads(
                log.data, roles, samples=k * samples, position=k * position_step
            )
            written += _write_rows(writer, log, payloads, range(first, log.frames), k * duration)
    finally:
        writer.stop()
    doc: dict[str, Any] = json.loads(metadata_path_for(source).read_text(encoding="utf-8"))
    doc[FRAMES_RECORDED_KEY] = written
    write_json_atomically(metadata_path_for(out), doc)
    return TileResult(out, tiles, samples, position_step, written)


def _write_rows(
    writer: can.Listener,
    log: LogArrays,
    payloads: NDArray[np.uint8],
    rows: range,
    time_shift: float,
) -> int:
    """The per-frame loop; python lists index faster than numpy scalars here."""
    stamps = (log.stamps + time_shift).tolist()
    ids = log.ids.tolist()
    extended = log.extended.tolist()
    remote = log.remote.tolist()
    error = log.error.tolist()
    rx = log.rx.tolist()
    dlc = log.dlc.tolist()
    lengths = log.lengths.tolist()
    blob = payloads.tobytes()
    for i in rows:
        start = i * PAYLOAD_BYTES
        writer.on_message_received(
            can.Message(
                timestamp=stamps[i],
                arbitration_id=ids[i],
                is_extended_id=extended[i],
                is_remote_frame=remote[i],
                is_error_frame=error[i],
                is_rx=rx[i],
                dlc=dlc[i],
                data=blob[start : start + lengths[i]],
                check=False,
            )
        )
    return len(rows)
