"""Simulated recordings made in process: the plant and the ICD frames, without the bus.

``station sim record`` makes a recording the way a real bench does (devices on
python-can's virtual bus, the station's drivers and SYNC clock, a logger), and
pays for it: a 50 s characterization takes ~12 s of threads, SDO round trips
and canopen dispatch, while the plant alone runs ~35x real time. A diagnosis
benchmark needs hundreds of recordings, so this module replays, SYNC by SYNC,
what the simulated bench does when ``run_schedule`` drives it, and produces
the frames the bus would have carried, or the timeline a reader would rebuild
from them.

Why the replay is exact rather than approximate: the simulated bench is
lock-stepped (``SteppedSync`` sends SYNCs only inside ``clock.advance``), and
the runner sends every SDO of a hold (amplitude, trims, target velocity; before
the first hold also the mode and the CiA 402 walk to operation enabled) before
it advances the clock. No SYNC ever falls between two writes, none precedes the
first hold, and the drive is disabled after the last SYNC, so each hold's
values take effect at its own first SYNC (ICD.md §2: "at the next SYNC"). The
drive's cycle below is ``SimDrive.sync`` for exactly that sequence of writes,
on the same trajectory generator and the same plant, fed the same commands in
the same order, so the sensor counts, position demands, statuswords and trims
come out bit for bit as on the bus (``tests/sim/test_inprocess.py`` holds the
two paths to that).

What a bus recording has beyond these frames: SDO, NMT and heartbeat traffic.
The reader ignores it, but counts it (``LossReport.frames_ignored``), and the
heartbeats come from canopen's wall-clock thread, so neither that count nor the
timestamps after the first SYNC are reproducible on the bus; here both are
deterministic (no ignored frames, timestamps as ``SimulatedClock`` gives them
with nothing before the first SYNC).

What is not replayed: injected faults (``SimBenchConfig.faults``), a drive
reached over Modbus, and the station's closed-loop runs (a calibration decides
its next holds from its last ones; a schedule is given up front). The bench's
EEPROM does not matter: the first hold writes all four trims before the first
SYNC, so what a unit had stored never takes effect.

The TPDO layouts are compiled from the EDS mapping objects, as the simulated
devices do, so the bytes agree with the bench by construction.
"""

from __future__ import annotations

import functools
import json
import struct
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Final

import can
import numpy as np
from canopen.objectdictionary import ODVariable, datatypes
from numpy.typing import NDArray

from drivers.base import DriveState
from drivers.canbus import check_node_id
from drivers.cia402 import ENABLE_STEPS
from drivers.eds import DeviceKind, load_od
from drivers.transports import Transport
from station import __version__
from station.analysis.timeline import (
    PAYLOAD_BYTES,
    SYNC_BYTES,
    Timeline,
    build_timeline,
    icd_frames,
)
from station.cia301 import SYNC_COB_ID, SYNC_COUNTER_OVERFLOW
from station.core import GAIN_LIMITS, SENSOR_COUNTER_MODULUS, SENSOR_RANGES_G, Trims
from station.errors import InputError
from station.physics.params import UnitParams
from station.physics.plant import DriveCommand, Plant
from station.recorder import FrameLoss, RecordingWriter, SimulatedClock
from station.recording import (
    FRAMES_RECORDED_KEY,
    RecordingMetadata,
    log_format_for,
    metadata_path_for,
)
from station.schedules import Schedule
from station.sim import trajectory as traj
from station.sim.devices import (
    COB_ID_INVALID,
    STATE_BITS,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
    Obj,
    Sw,
    decode_controlword,
    next_state,
)
from station.sim.eeprom import ObjectKey, key_text

BENCH_NAME: Final = "sim-inprocess"
"""The ``bench`` a recording made here names, so it is never taken for a bus recording."""

_CAN_ID_MASK = 0x7FF
_INT32 = (-(1 << 31), (1 << 31) - 1)
_U16_MAX = 0xFFFF

_NUMPY_CODES: Final = {
    datatypes.INTEGER8: "<i1",
    datatypes.INTEGER16: "<i2",
    datatypes.INTEGER32: "<i4",
    datatypes.UNSIGNED8: "<u1",
    datatypes.UNSIGNED16: "<u2",
    datatypes.UNSIGNED32: "<u4",
    datatypes.REAL32: "<f4",
}

_REAL32 = struct.Struct("<f")

# --- TPDO layouts from the EDS -------------------------------------------------------------


@dataclass(frozen=True)
class _Tpdo:
    cob_id: int
    mapped: tuple[ObjectKey, ...]
    layout: np.dtype[np.void]  # one field per mapped object, packed, little-endian


@dataclass(frozen=True)
class _Device:
    """What the replay needs from one device's EDS: its enabled TPDOs and power-on values."""

    tpdos: tuple[_Tpdo, ...]
    power_on: Mapping[ObjectKey, int]


@functools.cache
def _device(kind: DeviceKind, node_id: int) -> _Device:
    """Compiled once per process: the EDS does not change under a running benchmark."""
    od = load_od(kind, node_id)
    variables: dict[ObjectKey, ODVariable] = {}
    for obj in od.values():
        for var in [obj] if isinstance(obj, ODVariable) else list(obj.values()):
            variables[(var.index, var.subindex)] = var

    def default(key: ObjectKey) -> int:
        value = variables[key].default
        if not isinstance(value, int):
            raise ValueError(f"{kind} EDS: {key_text(key)} has no integer default")
        return value

    tpdos: list[_Tpdo] = []
    number = 0
    while (TPDO_COMM_BASE + number, 1) in variables:
        cob_id = default((TPDO_COMM_BASE + number, 1))
        count = default((TPDO_MAP_BASE + number, 0))
        mapped: list[ObjectKey] = []
        fields: list[tuple[str, str]] = []
        for sub in range(1, count + 1):
            entry = default((TPDO_MAP_BASE + number, sub))
            key = (entry >> 16, (entry >> 8) & 0xFF)
            var = variables.get(key)
            if var is None or len(var) != entry & 0xFF or var.data_type not in _NUMPY_CODES:
                raise ValueError(f"{kind} TPDO{number + 1} maps {entry:#010x}, not an object "
                                 "of that size")
            mapped.append(key)
            fields.append((f"f{sub}", _NUMPY_CODES[int(var.data_type)]))
        if not cob_id & COB_ID_INVALID:
            layout = np.dtype(fields)
            if layout.itemsize > PAYLOAD_BYTES:
                raise ValueError(f"{kind} TPDO{number + 1} maps {layout.itemsize} bytes")
            tpdos.append(_Tpdo(cob_id & _CAN_ID_MASK, tuple(mapped), layout))
        number += 1
    wanted = (Obj.PROFILE_ACCELERATION, Obj.PROFILE_DECELERATION, Obj.SAMPLE_COUNTER)
    power_on = {key: default(key) for key in wanted if key in variables}
    return _Device(tuple(tpdos), power_on)


# --- The frames ------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimulatedFrames:
    """The bus traffic of a run, one row per frame in bus order.

    Per SYNC: the SYNC (counter 1..240), then sensor TPDO1, drive TPDO1 and drive
    TPDO2, which is the order in which ``SimBench._on_sync`` sends them. Timestamps
    are those ``SimulatedClock`` gives (SYNC n at ``start_s + n·period``, each
    following frame one frame time later), with no frame before the first SYNC.
    """

    cob_ids: NDArray[np.uint16]  # (K,)
    lengths: NDArray[np.uint8]  # (K,) data length code
    payloads: NDArray[np.uint8]  # (K, 8); bytes beyond the length are zero
    timestamps: NDArray[np.float64]  # (K,)
    cycles: int  # SYNCs sent
    sync_period_s: float
    sensor_lsb_mps2: float  # 0x2001 as the sensor reports it (REAL32) during the run
    drive_node: int
    sensor_node: int

    def __len__(self) -> int:
        return int(self.cob_ids.shape[0])

    def messages(self) -> Iterator[can.Message]:
        """The frames as python-can messages, each a new object."""
        for cob_id, length, payload, stamp in zip(
            self.cob_ids.tolist(), self.lengths.tolist(), self.payloads.tolist(),
            self.timestamps.tolist(), strict=True,
        ):
            yield can.Message(timestamp=stamp, arbitration_id=cob_id, is_extended_id=False,
                              dlc=length, data=payload[:length])

    def kept(self, loss: float, seed: int) -> NDArray[np.bool_]:
        """Which frames a logger losing ``loss`` of them keeps: the very frames
        ``RecordingWriter(loss_probability=loss, seed=seed)`` keeps of this traffic."""
        _check_loss(loss)
        count = len(self)
        kept: NDArray[np.bool_] = ~FrameLoss(loss, seed).dropped_block(count)
        return kept


def simulate_frames(
    unit: UnitParams,
    schedule: Schedule,
    *,
    seed: int = 0,
    sync_period_s: float = 0.001,
    drive_node: int = 1,
    sensor_node: int = 16,
    substeps: int = 8,
    start_s: float = 0.0,
) -> SimulatedFrames:
    """The frames the simulated bench puts on the bus while ``run_schedule`` drives
    ``unit`` through ``schedule`` (``seed``: the plant's sensor noise, as the bench's)."""
    for node, name in ((drive_node, "drive"), (sensor_node, "sensor")):
        check_node_id(node, name)
    if drive_node == sensor_node:
        raise InputError(f"drive and sensor cannot share node-ID {drive_node}")
    _check_schedule(unit, schedule)
    drive = _device(DeviceKind.DRIVE, drive_node)
    sensor = _device(DeviceKind.SENSOR, sensor_node)
    plant = Plant(unit, sync_period_s=sync_period_s, substeps=substeps, seed=seed)
    plant.set_sensor_range(schedule.sensor_range_g)
    columns = _run(plant, unit, schedule, drive=drive, sensor=sensor,
                   period=traj.period_us(sync_period_s))
    return _assemble(columns, (*sensor.tpdos, *drive.tpdos), sync_period_s, start_s,
                     lsb=_REAL32.unpack(_REAL32.pack(plant.sensor_lsb_mps2()))[0],
                     drive_node=drive_node, sensor_node=sensor_node)


def _check_schedule(unit: UnitParams, schedule: Schedule) -> None:
    """Refuse what the drive would refuse (an SDO abort on the bus), before simulating."""
    if schedule.microsteps != unit.microsteps:
        raise InputError(f"{unit.serial} runs {unit.microsteps} microsteps per full step, the "
                         f"schedule was planned for {schedule.microsteps}")
    rated = unit.rated_current_mA
    for number, hold in enumerate(schedule.holds, 1):
        where = f"schedule {schedule.name!r}, hold {number} ({hold.phase.value})"
        raw = (hold.trims.offset_a_mA, hold.trims.offset_b_mA, hold.trims.gain_a,
               hold.trims.gain_b)
        if not all(np.isfinite(raw)):
            raise InputError(f"{where}: trims must be finite, not {hold.trims}")
        offset_a, offset_b, gain_a, gain_b = hold.trims.integers()
        if not 0 <= hold.amplitude_mA <= min(rated, _U16_MAX):
            raise InputError(f"{where}: amplitude {hold.amplitude_mA} mA outside 0..{rated}")
        if 2 * max(abs(offset_a), abs(offset_b)) > rated:
            raise InputError(f"{where}: offsets {offset_a}, {offset_b} mA exceed ±{rated // 2}")
        if not all(GAIN_LIMITS[0] <= g <= GAIN_LIMITS[1] for g in (gain_a, gain_b)):
            raise InputError(f"{where}: gains {gain_a}, {gain_b} outside {GAIN_LIMITS}")
        if not _INT32[0] <= hold.velocity <= _INT32[1]:
            raise InputError(f"{where}: velocity {hold.velocity} does not fit 0x60FF (I32)")
        if hold.cycles < 0:
            raise InputError(f"{where}: {hold.cycles} cycles")


def _enabled_state() -> DriveState:
    """Where the station's CiA 402 walk (``drivers.cia402``) takes the drive from power-on.

    Walked through the simulated drive's own transition function, so that a change to
    either side shows here instead of a statusword that only looks right.
    """
    state = DriveState.SWITCH_ON_DISABLED  # SimDrive after power-on
    while state in ENABLE_STEPS:
        command, expected = ENABLE_STEPS[state]
        state = next_state(state, decode_controlword(command))
        if state is not expected:
            raise AssertionError(f"CiA 402 walk reached {state.value}, expected {expected.value}")
    if state is not DriveState.OPERATION_ENABLED:
        raise AssertionError(f"CiA 402 walk ended in {state.value}")
    return state


@dataclass(frozen=True)
class _Columns:
    """Per-SYNC values of every object a TPDO maps."""

    values: dict[ObjectKey, NDArray[Any]]
    cycles: int


def _run(plant: Plant, unit: UnitParams, schedule: Schedule, *, drive: _Device,
         sensor: _Device, period: int) -> _Columns:
    """``SimBench._on_sync`` per SYNC for the writes ``run_schedule`` makes: the plant over
    the period that ended with the inputs in effect, then ``SimDrive.sync``, then the samples.
    """
    acceleration = drive.power_on[Obj.PROFILE_ACCELERATION]
    deceleration = drive.power_on[Obj.PROFILE_DECELERATION]
    microsteps = unit.microsteps
    enabled_word = STATE_BITS[_enabled_state()]
    reached, still = int(Sw.TARGET_REACHED), int(Sw.SPEED_ZERO)
    # Before the first SYNC the drive holds its power-on idle command: de-energised, so
    # the plant ignores its amplitude and trims.
    ramp, change = traj.STANDSTILL, 0
    idle = traj.kinematics(ramp, 0, period)
    command = DriveCommand(enabled=False, amplitude_mA=float(unit.rated_current_mA),
                           trims=Trims(), position_start=idle.position_start, velocity=0.0,
                           acceleration=0.0, microsteps_per_fullstep=microsteps)
    counts: list[tuple[int, int, int]] = []
    positions: list[int] = []
    words: list[int] = []
    advance, step, plan = plant.advance, traj.advance, traj.velocity_change
    kinematics, demand = traj.kinematics, traj.position_demand
    for hold in schedule.holds:
        # Latched at the hold's first SYNC: the values in effect for all of it.
        trims = Trims(*(float(t) for t in hold.trims.integers()))
        amplitude = float(hold.amplitude_mA)
        target = hold.velocity
        target_scaled = target * traj.VELOCITY_SCALE
        for _ in range(hold.cycles):
            counts.append(advance(command))
            ramp = step(ramp, change, period)
            change = plan(ramp.velocity, target, acceleration, deceleration, period)
            motion = kinematics(ramp, change, period)
            command = DriveCommand(True, amplitude, trims, motion.position_start,
                                   motion.velocity, motion.acceleration, microsteps)
            positions.append(demand(ramp))
            velocity = ramp.velocity
            words.append(enabled_word | (reached if velocity == target_scaled else 0)
                         | (still if velocity == 0 else 0))
    cycles = len(counts)
    lengths = [hold.cycles for hold in schedule.holds]
    held = np.array([hold.trims.integers() for hold in schedule.holds], dtype=np.int64)
    per_sample_trims = np.repeat(held.reshape(-1, 4), lengths, axis=0)
    accel = np.array(counts, dtype=np.int64).reshape(-1, 3)
    counter0 = sensor.power_on.get(Obj.SAMPLE_COUNTER, 0)
    values: dict[ObjectKey, NDArray[Any]] = {
        Obj.SAMPLE_COUNTER: (np.arange(1, cycles + 1) + counter0) % SENSOR_COUNTER_MODULUS,
        Obj.ACCEL_X: accel[:, 0],
        Obj.ACCEL_Y: accel[:, 1],
        Obj.ACCEL_Z: accel[:, 2],
        Obj.POSITION_DEMAND: np.array(positions, dtype=np.int64),
        Obj.AMPLITUDE: np.repeat([hold.amplitude_mA for hold in schedule.holds], lengths),
        Obj.STATUSWORD: np.array(words, dtype=np.int64),
        Obj.OFFSET_A: per_sample_trims[:, 0],
        Obj.OFFSET_B: per_sample_trims[:, 1],
        Obj.GAIN_A: per_sample_trims[:, 2],
        Obj.GAIN_B: per_sample_trims[:, 3],
    }
    return _Columns(values, cycles)


def _assemble(columns: _Columns, tpdos: Sequence[_Tpdo], sync_period_s: float, start_s: float,
              *, lsb: float, drive_node: int, sensor_node: int) -> SimulatedFrames:
    """Pack every frame at once: SYNC, then the TPDOs in bench order, per SYNC."""
    n = columns.cycles
    per_sync = 1 + len(tpdos)
    payloads = np.zeros((n, per_sync, PAYLOAD_BYTES), dtype=np.uint8)
    payloads[:, 0, 0] = np.arange(n) % SYNC_COUNTER_OVERFLOW + 1
    for slot, tpdo in enumerate(tpdos, 1):
        packed = np.zeros(n, dtype=tpdo.layout)
        for name, key in zip(tpdo.layout.names or (), tpdo.mapped, strict=True):
            source = columns.values.get(key)
            if source is None:
                raise NotImplementedError(
                    f"the in-process bench does not produce {key_text(key)}, which a TPDO "
                    "of the EDS maps; the bus bench does (station sim record)")
            packed[name] = source
        size = tpdo.layout.itemsize
        payloads[:, slot, :size] = packed.view(np.uint8).reshape(n, size)
    slot_ids = np.array([SYNC_COB_ID, *(t.cob_id for t in tpdos)], dtype=np.uint16)
    slot_lengths = np.array([SYNC_BYTES, *(t.layout.itemsize for t in tpdos)], dtype=np.uint8)
    return SimulatedFrames(
        cob_ids=np.tile(slot_ids, n),
        lengths=np.tile(slot_lengths, n),
        payloads=payloads.reshape(n * per_sync, PAYLOAD_BYTES),
        timestamps=_timestamps(n, slot_ids, sync_period_s, start_s),
        cycles=n,
        sync_period_s=sync_period_s,
        sensor_lsb_mps2=lsb,
        drive_node=drive_node,
        sensor_node=sensor_node,
    )


def _timestamps(n: int, slot_ids: NDArray[np.uint16], period: float,
                start_s: float) -> NDArray[np.float64]:
    """``SimulatedClock``'s stamps, computed for all SYNCs at once.

    The offsets of a SYNC's frames are read off the clock itself (one SYNC's worth of
    frames from time zero), and the clock's own sum ``first + n·period + offset`` is
    repeated in the same order, so the stamps are the clock's to the last bit.
    """
    probe = SimulatedClock(period, start=0.0)
    offsets = np.array([probe.stamp(can.Message(arbitration_id=int(cob), is_extended_id=False))
                        for cob in slot_ids], dtype=np.float64)
    sync_times = start_s + np.arange(n, dtype=np.int64) * period
    stamps = (sync_times[:, None] + offsets[None, :]).reshape(-1)
    return np.maximum.accumulate(stamps)


# --- Timeline and recording ------------------------------------------------------------------


def recording_metadata(unit: UnitParams, schedule: Schedule, frames: SimulatedFrames, *,
                       extra: Mapping[str, Any] | None = None) -> RecordingMetadata:
    """ICD.md §5 metadata of an in-process recording, key for key as a simulated bench's.

    As ``BenchSession.recording_metadata`` and ``station sim record`` fill them: the
    fixture as the simulator mounts the sensor, the LSB as the sensor reports it
    (REAL32, so float32-rounded), the drive's microsteps and rating.
    """
    sensor = unit.sensor
    doc: dict[str, Any] = {
        "drive_transport": Transport.CANOPEN.value,
        "schedule": schedule.name,
        "bench": BENCH_NAME,
        "load": unit.load.value,
        "station_software": __version__,
        "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    doc.update(extra or {})
    return RecordingMetadata(
        serial=unit.serial,
        drive_node=frames.drive_node,
        sensor_node=frames.sensor_node,
        sync_period_s=frames.sync_period_s,
        microsteps_per_fullstep=unit.microsteps,
        rotor_teeth=unit.rotor_teeth,
        rated_current_mA=unit.rated_current_mA,
        sensor_lsb_mps2=frames.sensor_lsb_mps2,
        tangential_axis=sensor.tangential_axis,
        sensor_radius_m=sensor.radius_m,
        gear_ratio=unit.gear_ratio,
        extra=doc,
    )


def timeline_of(frames: SimulatedFrames, metadata: RecordingMetadata, *, loss: float = 0.0,
                seed: int = 0) -> Timeline:
    """The timeline ``read_recording`` rebuilds from a log of ``frames`` (lost as the writer
    loses them), classified as the reader classifies frames: by COB-ID, then length."""
    _check_loss(loss)
    kept = frames.kept(loss, seed)
    cob_ids, lengths = frames.cob_ids[kept], frames.lengths[kept]
    kind_of = np.full(_CAN_ID_MASK + 1, np.iinfo(np.uint8).max, dtype=np.uint8)
    size_of = np.zeros(_CAN_ID_MASK + 1, dtype=np.int64)
    for cob_id, (kind, size) in icd_frames(metadata.drive_node, metadata.sensor_node).items():
        kind_of[cob_id], size_of[cob_id] = kind, size
    kinds = kind_of[cob_ids]
    icd = kinds != np.iinfo(np.uint8).max
    wellformed = icd & (lengths == size_of[cob_ids])
    doc = metadata.to_json_dict()
    doc.setdefault(FRAMES_RECORDED_KEY, int(np.count_nonzero(kept)))
    # Through JSON, as the reader gets it (tuples become lists, and so on).
    read_back = RecordingMetadata.from_json_dict(json.loads(json.dumps(doc)))
    return build_timeline(
        read_back,
        kinds[wellformed],
        frames.payloads[kept][wellformed],
        frames_ignored=int(np.count_nonzero(~icd)),
        frames_malformed=int(np.count_nonzero(icd & ~wellformed)),
    )


def simulate_timeline(
    unit: UnitParams,
    schedule: Schedule,
    *,
    seed: int = 0,
    loss: float = 0.0,
    extra_metadata: Mapping[str, Any] | None = None,
    sensor_range_g: int | None = None,
    sync_period_s: float = 0.001,
    drive_node: int = 1,
    sensor_node: int = 16,
    substeps: int = 8,
) -> Timeline:
    """What ``read_recording`` returns for ``record_in_process`` with the same arguments,
    without writing the file (``seed``: sensor noise and which frames a lossy logger drops).
    """
    _check_loss(loss)
    chosen = _with_range(schedule, sensor_range_g)
    frames = simulate_frames(unit, chosen, seed=seed, sync_period_s=sync_period_s,
                             drive_node=drive_node, sensor_node=sensor_node, substeps=substeps)
    metadata = recording_metadata(unit, chosen, frames, extra=extra_metadata)
    return timeline_of(frames, metadata, loss=loss, seed=seed)


@dataclass(frozen=True)
class InProcessRecording:
    recording: Path
    metadata: Path
    cycles: int
    frames: int  # put on the bus
    frames_recorded: int  # kept by the logger (fewer with loss)


def record_in_process(
    out: Path,
    unit: UnitParams,
    schedule: Schedule,
    *,
    seed: int = 0,
    loss: float = 0.0,
    extra_metadata: Mapping[str, Any] | None = None,
    sensor_range_g: int | None = None,
    sync_period_s: float = 0.001,
    drive_node: int = 1,
    sensor_node: int = 16,
    substeps: int = 8,
) -> InProcessRecording:
    """An ICD.md §5 recording (any suffix) of ``unit`` running ``schedule``, made in process.

    Written through ``RecordingWriter`` as the bus path writes: hidden until complete,
    the log moved into place, its metadata last; a failure leaves nothing behind. The
    whole run is simulated before the file is opened, so a refused schedule writes
    nothing either.
    """
    log_format_for(out)
    _check_loss(loss)
    if out.is_dir():
        raise InputError(f"output {out} is a directory")
    if not out.parent.is_dir():
        raise InputError(f"output directory {out.parent} does not exist")
    chosen = _with_range(schedule, sensor_range_g)
    frames = simulate_frames(unit, chosen, seed=seed, sync_period_s=sync_period_s,
                             drive_node=drive_node, sensor_node=sensor_node, substeps=substeps,
                             start_s=time.time())
    metadata = recording_metadata(unit, chosen, frames, extra=extra_metadata)
    with RecordingWriter(out, metadata, loss_probability=loss, seed=seed) as recorder:
        recorder.write_frames(frames.timestamps, frames.cob_ids, frames.lengths,
                              frames.payloads)
        recorder.commit()
    return InProcessRecording(
        recording=out,
        metadata=metadata_path_for(out),
        cycles=frames.cycles,
        frames=recorder.frames_seen,
        frames_recorded=recorder.frames_written,
    )


def _check_loss(loss: float) -> None:
    if not 0.0 <= loss < 1.0:
        raise InputError(f"frame loss probability must be in [0, 1), got {loss}")


def _with_range(schedule: Schedule, range_g: int | None) -> Schedule:
    if range_g is None:
        return schedule
    if range_g not in SENSOR_RANGES_G:
        raise InputError(f"sensor range must be one of {SENSOR_RANGES_G}, got {range_g}")
    return replace(schedule, sensor_range_g=range_g)

