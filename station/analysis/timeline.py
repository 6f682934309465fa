"""The sample timeline of a recording: one row per SYNC, rebuilt from counters.

ICD.md §5 makes the SYNC counter and period the clock of a recording; log
timestamps only order frames. Lost frames leave holes that are flagged, never
filled, so every estimate downstream knows which samples are real.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from station.cia301 import SYNC_COB_ID, SYNC_COUNTER_OVERFLOW, TPDO1_COB_BASE, TPDO2_COB_BASE
from station.core import SATURATED_COUNTS, SENSOR_COUNTER_MODULUS
from station.errors import RecordingError
from station.recording import RecordingMetadata


@dataclass(frozen=True)
class LossReport:
    """What the recording lacks or carries beyond the ICD frames, for people and QA."""

    syncs_seen: int
    syncs_missing: int  # inferred from counter gaps (SYNC counter and sensor counter)
    sensor_samples_lost: int  # samples without a sensor TPDO1
    drive_status_lost: int  # samples without a drive TPDO1
    drive_trims_lost: int  # samples without a drive TPDO2
    saturated_samples: int  # samples with any axis at ±32767
    frames_ignored: int  # SDO, heartbeat, EMCY, other nodes, error and remote frames
    # ICD COB-IDs with a wrong length, device frames before any SYNC, SYNCs with a
    # counter outside 1..240, and TPDOs that no sample has room for (duplicates)
    frames_malformed: int


@dataclass(frozen=True)
class Timeline:
    """Per-sample arrays, index n = SYNC n counted from the log's first SYNC.

    Sample n's instant is ``n * sync_period_s`` (ICD.md §5). Every array has
    length ``samples``; ``*_valid`` says whether the frame for that sample was
    in the log. Values of invalid rows are zero and mean nothing.
    """

    metadata: RecordingMetadata
    accel_counts: NDArray[np.int16]  # (N, 3): X, Y, Z sensor counts
    sensor_valid: NDArray[np.bool_]  # (N,)
    saturated: NDArray[np.bool_]  # (N,) any axis at ±32767 (only where sensor_valid)
    position: NDArray[np.int64]  # (N,) 0x6062, unwrapped from int32 (continuous)
    amplitude_mA: NDArray[np.int32]  # (N,) 0x2103
    statusword: NDArray[np.uint16]  # (N,) 0x6041
    drive_valid: NDArray[np.bool_]  # (N,) drive TPDO1 present
    trims: NDArray[np.int32]  # (N, 4): offset A, offset B (I16), gain A, gain B (U16)
    trims_valid: NDArray[np.bool_]  # (N,) drive TPDO2 present
    losses: LossReport
    # False when the drive columns are the station's own commands (a Modbus drive sends
    # no TPDOs): the position demand's phase is then arbitrary, its magnitudes are not.
    drive_reported: bool = True

    @property
    def samples(self) -> int:
        return int(self.sensor_valid.shape[0])

    @property
    def sync_period_s(self) -> float:
        return self.metadata.sync_period_s


class FrameKind(IntEnum):
    """The ICD frames a timeline is built from, as the reader tags them."""

    SYNC = 0
    SENSOR = 1  # sensor TPDO1: counter, X, Y, Z
    DRIVE_STATUS = 2  # drive TPDO1: position demand, amplitude, statusword
    DRIVE_TRIMS = 3  # drive TPDO2: the trims in effect


PAYLOAD_BYTES: Final = 8
"""Every ICD TPDO is 8 bytes; a SYNC's one counter byte sits in column 0."""

SYNC_BYTES: Final = 1
"""A SYNC carries one byte: its counter (ICD.md §1, overflow 240)."""


def icd_frames(drive_node: int, sensor_node: int) -> dict[int, tuple[FrameKind, int]]:
    """COB-ID to (kind, payload length) of every frame a timeline is built from.

    One table for the offline reader and the live capture, so a calibration on
    the bench and ``station analyze`` of its recording classify frames alike.
    """
    return {
        SYNC_COB_ID: (FrameKind.SYNC, SYNC_BYTES),
        TPDO1_COB_BASE + sensor_node: (FrameKind.SENSOR, PAYLOAD_BYTES),
        TPDO1_COB_BASE + drive_node: (FrameKind.DRIVE_STATUS, PAYLOAD_BYTES),
        TPDO2_COB_BASE + drive_node: (FrameKind.DRIVE_TRIMS, PAYLOAD_BYTES),
    }

_OFFSET_VOTERS = 64
"""Sensor frames that vote on the sensor-counter offset: enough to outvote a
few frames misplaced by losses, few enough to stay near the first SYNC."""

_INT32_SPAN = 1 << 32
_SATURATION_LEVELS = (SATURATED_COUNTS, -SATURATED_COUNTS, -SATURATED_COUNTS - 1)


@dataclass(frozen=True)
class _Placed:
    """Frames of one kind placed on samples: each sample once, in sample order."""

    samples: NDArray[np.int64]
    rows: NDArray[np.intp]  # row of each placed frame in the payload array
    rejected: int


def build_timeline(
    metadata: RecordingMetadata,
    kinds: NDArray[np.uint8],
    payloads: NDArray[np.uint8],
    *,
    frames_ignored: int = 0,
    frames_malformed: int = 0,
) -> Timeline:
    """Rebuild the per-SYNC timeline from the ICD frames in bus order.

    ``kinds`` holds a ``FrameKind`` per frame and ``payloads`` its bytes as a
    (K, 8) array (a SYNC's counter in column 0). Counters, not timestamps,
    place frames, because a logger may lose frames but cannot invent
    counters: the SYNC counter gives each SYNC its sample modulo 240, and the
    sensor's 16-bit counter settles what 240 cannot (long runs of lost SYNCs).
    ``frames_ignored``/``frames_malformed`` are what the reader already
    discarded; frames rejected here are added to the latter.
    """
    kinds = np.asarray(kinds, dtype=np.uint8)
    payloads = np.ascontiguousarray(payloads, dtype=np.uint8)
    if payloads.shape != (kinds.shape[0], PAYLOAD_BYTES):
        raise ValueError(f"payloads must be ({kinds.shape[0]}, {PAYLOAD_BYTES}) bytes")
    sync_rows = np.flatnonzero(kinds == FrameKind.SYNC)
    counters = payloads[sync_rows, 0].astype(np.int64)
    valid_counter = (counters >= 1) & (counters <= SYNC_COUNTER_OVERFLOW)
    malformed = frames_malformed + int(np.count_nonzero(~valid_counter))
    if not valid_counter.all():
        # A SYNC with an impossible counter is dropped; its TPDOs then read as
        # those of a lost SYNC and are placed by the rule for those.
        sync_rows, counters = sync_rows[valid_counter], counters[valid_counter]
    if counters.size == 0:
        raise RecordingError("no SYNC frame with a valid counter: there is no sample clock")

    # Samples between SYNCs seen, 1..240 from the counter alone; the sensor
    # counter then adds the whole turns of 240 the SYNC counter cannot show.
    periods = (np.diff(counters) - 1) % SYNC_COUNTER_OVERFLOW + 1
    sync_samples = np.concatenate(([0], np.cumsum(periods)))
    del periods
    sensor_rows, sensor_group, sensor_rank, early = _ranked(kinds, sync_rows, FrameKind.SENSOR)
    sensor_samples = _sensor_samples(
        payloads[sensor_rows, :2].view("<u2")[:, 0], sync_samples[sensor_group] + sensor_rank
    )
    first = sensor_rank == 0
    sync_samples += _gap_corrections(sync_samples, sensor_samples[first], sensor_group[first])
    del first, sensor_group, sensor_rank

    sensor = _unique_placement(sensor_samples, sensor_rows)
    del sensor_samples, sensor_rows
    status = _place_by_rank(kinds, sync_rows, sync_samples, FrameKind.DRIVE_STATUS)
    trims_placed = _place_by_rank(kinds, sync_rows, sync_samples, FrameKind.DRIVE_TRIMS)
    malformed += early + sensor.rejected + status.rejected + trims_placed.rejected

    last = int(sync_samples[-1])
    for placed in (sensor, status, trims_placed):
        if placed.samples.size:
            last = max(last, int(placed.samples[-1]))
    n = last + 1

    accel = np.zeros((n, 3), dtype=np.int16)
    sensor_valid = np.zeros(n, dtype=np.bool_)
    accel[sensor.samples] = payloads[sensor.rows].view("<i2")[:, 1:4]
    sensor_valid[sensor.samples] = True
    # -32768 cannot come from a sensor that saturates at ±32767; if it does, it is no better.
    at_limit = (accel >= SATURATED_COUNTS) | (accel <= -SATURATED_COUNTS)
    saturated = np.asarray(at_limit.any(axis=1), dtype=np.bool_)

    position = np.zeros(n, dtype=np.int64)
    amplitude = np.zeros(n, dtype=np.int32)
    statusword = np.zeros(n, dtype=np.uint16)
    drive_valid = np.zeros(n, dtype=np.bool_)
    status_rows = payloads[status.rows]
    position[status.samples] = unwrap_int32(status_rows.view("<i4")[:, 0])
    amplitude[status.samples] = status_rows.view("<u2")[:, 2]
    statusword[status.samples] = status_rows.view("<u2")[:, 3]
    drive_valid[status.samples] = True
    del status_rows

    trims = np.zeros((n, 4), dtype=np.int32)
    trims_valid = np.zeros(n, dtype=np.bool_)
    trim_words = payloads[trims_placed.rows]
    trims[trims_placed.samples, 0:2] = trim_words.view("<i2")[:, 0:2]
    trims[trims_placed.samples, 2:4] = trim_words.view("<u2")[:, 2:4]
    trims_valid[trims_placed.samples] = True
    del trim_words

    syncs_seen = int(counters.size)
    losses = LossReport(
        syncs_seen=syncs_seen,
        syncs_missing=n - syncs_seen,
        sensor_samples_lost=n - int(np.count_nonzero(sensor_valid)),
        drive_status_lost=n - int(np.count_nonzero(drive_valid)),
        drive_trims_lost=n - int(np.count_nonzero(trims_valid)),
        saturated_samples=int(np.count_nonzero(saturated)),
        frames_ignored=frames_ignored,
        frames_malformed=malformed,
    )
    return Timeline(
        metadata=metadata,
        accel_counts=accel,
        sensor_valid=sensor_valid,
        saturated=saturated,
        position=position,
        amplitude_mA=amplitude,
        statusword=statusword,
        drive_valid=drive_valid,
        trims=trims,
        trims_valid=trims_valid,
        losses=losses,
    )


def unwrap_int32(values: NDArray[np.integer[Any]]) -> NDArray[np.int64]:
    """Undo int32 wrap-around: steps between neighbours are read as signed
    32-bit, so a position demand that wraps stays continuous."""
    wide = np.asarray(values, dtype=np.int64)
    if wide.size == 0:
        return wide
    out = np.empty_like(wide)
    out[0] = wide[0]
    steps = np.diff(wide)
    steps += _INT32_SPAN // 2
    steps %= _INT32_SPAN
    steps -= _INT32_SPAN // 2
    np.cumsum(steps, out=out[1:])
    out[1:] += wide[0]
    return out


def _ranked(
    kinds: NDArray[np.uint8], sync_rows: NDArray[np.intp], kind: FrameKind
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], int]:
    """Frames of one kind after the first SYNC: their rows, their group (the
    SYNC seen last before them) and their rank in it (0 = first after that
    SYNC); also how many came before any SYNC."""
    rows = np.flatnonzero(kinds == kind)
    groups = np.searchsorted(sync_rows, rows, side="right")
    groups -= 1
    early = int(np.searchsorted(groups, 0))  # groups never decrease along the log
    rows, groups = rows[early:], groups[early:]
    ranks = np.arange(groups.size, dtype=np.intp)
    ranks -= np.searchsorted(groups, groups)
    return rows, groups, ranks, early


def _sensor_samples(counter: NDArray[np.uint16], tentative: NDArray[np.int64]) -> NDArray[np.int64]:
    """Place sensor frames by their own counter, the one clock the logger cannot lose.

    The counter-to-sample offset is the most common one among the first frames;
    each frame then lands on the sample nearest its tentative place that its
    counter allows (tentative places err by whole 240-sample turns only).
    """
    if counter.size == 0:
        return np.zeros(0, dtype=np.int64)
    votes = (counter[:_OFFSET_VOTERS].astype(np.int64) - tentative[:_OFFSET_VOTERS]) % (
        SENSOR_COUNTER_MODULUS
    )
    values, counts = np.unique(votes, return_counts=True)
    offset = int(values[np.argmax(counts)])
    half = SENSOR_COUNTER_MODULUS // 2
    shift = counter.astype(np.int64)
    shift -= tentative
    shift += half - offset
    shift %= SENSOR_COUNTER_MODULUS
    shift -= half
    shift += tentative
    return shift


def _gap_corrections(
    tentative: NDArray[np.int64], first_sensor: NDArray[np.int64], first_group: NDArray[np.intp]
) -> NDArray[np.int64]:
    """Whole 240-sample turns the SYNC counter could not see, per SYNC.

    The first sensor frame after SYNC j is for that SYNC's sample, or a later
    one when frames right after it were lost too, but fewer than 240 later in
    any plausible log; so flooring to whole turns recovers the turns missed
    before SYNC j. Turns only accumulate, so the estimate is a running maximum.
    """
    evidence = np.zeros(tentative.size, dtype=np.int64)
    turns = (first_sensor - tentative[first_group]) // SYNC_COUNTER_OVERFLOW
    evidence[first_group] = np.maximum(turns, 0) * SYNC_COUNTER_OVERFLOW
    evidence[0] = 0  # sample 0 is the first SYNC by definition
    return np.maximum.accumulate(evidence, out=evidence)


def _unique_placement(samples: NDArray[np.int64], rows: NDArray[np.intp]) -> _Placed:
    """One frame per sample (the first in bus order), none before sample 0."""
    if samples.size == 0 or (samples[0] >= 0 and bool((samples[1:] > samples[:-1]).all())):
        return _Placed(samples, rows, 0)  # the usual case: already one per sample, in order
    inside = samples >= 0
    unique, first = np.unique(samples[inside], return_index=True)
    return _Placed(unique, rows[inside][first], int(samples.size - unique.size))


def _place_by_rank(
    kinds: NDArray[np.uint8],
    sync_rows: NDArray[np.intp],
    sync_samples: NDArray[np.int64],
    kind: FrameKind,
) -> _Placed:
    """Drive frames carry no counter: the k-th after a SYNC is for k-1 samples
    later (ICD.md §1, one TPDO per SYNC even when the logger lost the SYNC).
    More frames than samples before the next SYNC seen cannot be placed."""
    rows, groups, ranks, early = _ranked(kinds, sync_rows, kind)
    room = np.append(np.diff(sync_samples), np.iinfo(np.int64).max)
    surplus = 0
    if (np.bincount(groups, minlength=room.size) > room).any():
        fits = ranks < room[groups]
        surplus = int(np.count_nonzero(~fits))
        rows, groups, ranks = rows[fits], groups[fits], ranks[fits]
    del room
    samples = sync_samples[groups]
    samples += ranks
    placed = _unique_placement(samples, rows)
    return _Placed(placed.samples, placed.rows, placed.rejected + early + surplus)
