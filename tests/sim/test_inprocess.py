"""In-process recordings: the same samples as the bus bench, for a fraction of the cost.

The reference is ``station sim record``'s path (devices on the virtual bus, the
station's drivers and lockstep SYNC, ``RecordingWriter``); the in-process
replay must give the same timeline sample for sample. It does, with no shift:
the lockstep clock sends no SYNC before the first hold nor between two writes,
so there is nothing to mirror. The one difference is documented in
``test_only_the_non_icd_traffic_differs``.
"""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from station.analysis.reader import read_log_frames, read_recording
from station.analysis.timeline import Timeline
from station.core import NOMINAL_TRIMS, Effect, LoadKind, Trims
from station.errors import InputError
from station.physics.params import UnitParams, derive_unit
from station.recorder import SimulatedClock
from station.recording import FRAMES_RECORDED_KEY, LogFormat, log_format_for, read_metadata
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.inprocess import (
    BENCH_NAME,
    record_in_process,
    simulate_frames,
    simulate_timeline,
)
from station.sim.record import SimRecordRequest, record_schedule

_SAMPLE_FIELDS = (
    "accel_counts", "sensor_valid", "saturated", "position", "amplitude_mA", "statusword",
    "drive_valid", "trims", "trims_valid",
)

BELT_EFFECTS = frozenset({
    Effect.CURRENT_LOOP_LAG, Effect.CURRENT_DISTORTION, Effect.FRICTION,
    Effect.SENSOR_CLOCK_DRIFT, Effect.DETENT_TORQUE,
})


def _short_schedule(range_g: int = 8) -> Schedule:
    """A few seconds with every kind of change a characterization makes: energising at
    standstill, a ramp up, trim and amplitude steps, a reversal through zero, a stop."""
    v8, v12 = velocity_for(8.0, 256), velocity_for(12.0, 256)
    step_a = Trims(40.0, 0.0, 10000.0, 10000.0)
    gain = Trims(0.0, 0.0, 10400.0, 9600.0)
    step_b = Trims(-10.4, 25.6, 10000.0, 10000.0)  # rounded by the drive, as on the bus
    holds = (
        Hold(Phase.STANDSTILL, 0, 900, NOMINAL_TRIMS, 120),
        Hold(Phase.CONDITION, v8, 900, NOMINAL_TRIMS, 500),
        Hold(Phase.STEP_OFFSET_A, v8, 900, step_a, 250),
        Hold(Phase.STEP_GAIN, v8, 600, gain, 250),
        Hold(Phase.CONDITION, -v12, 1000, NOMINAL_TRIMS, 600),
        Hold(Phase.STEP_OFFSET_B, -v12, 1000, step_b, 250),
        Hold(Phase.STOP, 0, 1000, NOMINAL_TRIMS, 200),
    )
    return Schedule("short", holds, 256, range_g)


def _tiny_schedule() -> Schedule:
    v = velocity_for(10.0, 256)
    return Schedule("tiny", (
        Hold(Phase.STANDSTILL, 0, 800, NOMINAL_TRIMS, 50),
        Hold(Phase.CONDITION, v, 800, NOMINAL_TRIMS, 300),
        Hold(Phase.STOP, 0, 800, NOMINAL_TRIMS, 100),
    ), 256, 4)


def assert_same_samples(actual: Timeline, expected: Timeline) -> None:
    assert actual.samples == expected.samples
    for name in _SAMPLE_FIELDS:
        a, b = getattr(actual, name), getattr(expected, name)
        assert a.dtype == b.dtype, name
        mismatched = np.flatnonzero((a != b).reshape(a.shape[0], -1).any(axis=1))
        assert mismatched.size == 0, f"{name} differs at samples {mismatched[:10]}"


def _bus_recording(out: Path, serial: str, load: LoadKind,
                   effects: frozenset[Effect] | None, seed: int) -> Path:
    # The named schedule is only validated: record_schedule runs the one it is given.
    request = SimRecordRequest(out=out, serial=parse_serial(serial),
                               schedule=ScheduleName.CHARACTERIZATION, effects=effects,
                               seed=seed, load=load)
    return record_schedule(request, _short_schedule()).recording


@pytest.mark.parametrize(
    ("serial", "load", "effects", "seed"),
    [
        ("SN7101", LoadKind.DISK, None, 0),  # the unit's own concealed effects
        ("SN7102", LoadKind.BELT, BELT_EFFECTS, 5),
    ],
    ids=["disk", "belt"],
)
def test_in_process_timeline_is_the_bus_timeline(
    tmp_path: Path, serial: str, load: LoadKind, effects: frozenset[Effect] | None, seed: int
) -> None:
    (tmp_path / "bus").mkdir()
    (tmp_path / "inprocess").mkdir()
    unit = derive_unit(serial, load=load, effects=effects)
    bus_log = _bus_recording(tmp_path / "bus" / "run.blf", serial, load, effects, seed)
    made = record_in_process(tmp_path / "inprocess" / "run.blf", unit, _short_schedule(),
                             seed=seed)
    bus = read_recording(bus_log)
    in_process = read_recording(made.recording)

    # Sample 0 is the first SYNC on both paths: no shift to allow for.
    assert_same_samples(in_process, bus)
    assert_same_samples(simulate_timeline(unit, _short_schedule(), seed=seed), bus)
    # And below the timeline: the ICD frames, byte for byte and in bus order.
    bus_frames = read_log_frames(bus_log, LogFormat.BLF, bus.metadata)
    ours = read_log_frames(made.recording, LogFormat.BLF, in_process.metadata)
    assert np.array_equal(ours.kinds, bus_frames.kinds)
    assert np.array_equal(ours.payloads, bus_frames.payloads)
    # Every ICD.md §5 key as the bus bench writes it (the LSB read back as REAL32 included).
    ours_doc, bus_doc = in_process.metadata.to_json_dict(), bus.metadata.to_json_dict()
    different = {k for k in bus_doc if ours_doc.get(k) != bus_doc[k]}
    # The clock time differs unless both runs fell within the same second.
    assert different - {"recorded_at"} == {"bench", FRAMES_RECORDED_KEY}
    assert set(ours_doc) == set(bus_doc)
    assert ours_doc["bench"] == BENCH_NAME


def test_only_the_non_icd_traffic_differs(tmp_path: Path) -> None:
    """What a bus recording has beyond the ICD frames: the SDOs that set the sensor
    range, enable the drive and write each hold, NMT, and heartbeats from canopen's
    wall-clock thread (100 ms of real time, so their number depends on the host's
    speed). The reader ignores them but counts them, so ``frames_ignored`` is the one
    loss figure that differs, and it is not reproducible on the bus itself; frame
    timestamps differ for the same reason (a heartbeat between a SYNC and its TPDOs
    pushes them one frame time later)."""
    unit = derive_unit("SN7101")
    (tmp_path / "bus").mkdir()
    bus = read_recording(_bus_recording(tmp_path / "bus" / "run.blf", "SN7101",
                                        LoadKind.DISK, None, 0))
    ours = simulate_timeline(unit, _short_schedule())
    assert bus.losses.frames_ignored > 0
    assert ours.losses.frames_ignored == 0
    fields = ("syncs_seen", "syncs_missing", "sensor_samples_lost", "drive_status_lost",
              "drive_trims_lost", "saturated_samples", "frames_malformed")
    assert {f: getattr(ours.losses, f) for f in fields} == {
        f: getattr(bus.losses, f) for f in fields}


def test_timestamps_are_the_simulated_clocks(tmp_path: Path) -> None:
    frames = simulate_frames(derive_unit("SN7101"), _tiny_schedule(), start_s=1.7e9)
    clock = SimulatedClock(0.001, start=1.7e9)
    stamps = [clock.stamp(message) for message in frames.messages()]
    assert np.array_equal(frames.timestamps, np.array(stamps))
    assert list(frames.cob_ids[:5]) == [0x080, 0x190, 0x181, 0x281, 0x080]
    assert list(frames.payloads[:241 * 4:4, 0][-2:]) == [240, 1]  # SYNC counter wraps


@pytest.mark.parametrize("log_format", list(LogFormat), ids=lambda f: f.name)
def test_every_icd_suffix_reads_back_as_simulated(tmp_path: Path, log_format: LogFormat) -> None:
    unit = derive_unit("SN7103")
    out = tmp_path / f"run{log_format.value}"
    assert log_format_for(out) is log_format
    made = record_in_process(out, unit, _tiny_schedule(), seed=2, extra_metadata={"trial": 7})
    read = read_recording(made.recording)
    expected = simulate_timeline(unit, _tiny_schedule(), seed=2)
    assert_same_samples(read, expected)
    assert read.losses == expected.losses
    assert read.metadata.extra["trial"] == 7
    assert made.frames == made.frames_recorded == 4 * made.cycles == 4 * 450
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, "run.json"])


def test_loss_drops_frames_that_the_reader_counts(tmp_path: Path) -> None:
    unit = derive_unit("SN7101")
    schedule = _tiny_schedule()
    made = record_in_process(tmp_path / "lossy.blf", unit, schedule, seed=3, loss=0.05)
    read = read_recording(made.recording)
    assert made.frames == 4 * made.cycles
    assert 0 < made.frames - made.frames_recorded < 0.1 * made.frames
    assert read_metadata(made.recording).extra[FRAMES_RECORDED_KEY] == made.frames_recorded
    losses = read.losses
    assert losses.sensor_samples_lost > 0
    assert losses.drive_status_lost > 0
    assert losses.drive_trims_lost > 0
    assert read.samples == made.cycles  # sensor counters place every sample, lost or not
    # Exactly the frames the writer dropped: the frame-free timeline loses the same ones.
    expected = simulate_timeline(unit, schedule, seed=3, loss=0.05)
    assert_same_samples(read, expected)
    assert losses == expected.losses
    kept = simulate_frames(unit, schedule, seed=3).kept(0.05, 3)
    sensor_rows = np.arange(1, kept.size, 4)
    assert losses.sensor_samples_lost == int(np.count_nonzero(~kept[sensor_rows]))


def test_sensor_range_sets_the_lsb_and_the_counts() -> None:
    unit = derive_unit("SN7101")
    at_4 = simulate_timeline(unit, _tiny_schedule(), sensor_range_g=4)
    at_16 = simulate_timeline(unit, _tiny_schedule(), sensor_range_g=16)
    assert at_16.metadata.sensor_lsb_mps2 == pytest.approx(4 * at_4.metadata.sensor_lsb_mps2)
    gravity_4 = at_4.accel_counts[:, 2].mean()
    assert at_16.accel_counts[:, 2].mean() == pytest.approx(gravity_4 / 4, rel=0.01)


def _refused(unit: UnitParams) -> list[Schedule]:
    base = _tiny_schedule()
    hold = base.holds[1]
    over = unit.rated_current_mA + 1
    return [
        Schedule("amp", (Hold(hold.phase, hold.velocity, over, hold.trims, 10),), 256, 4),
        Schedule("off", (Hold(hold.phase, hold.velocity, 800,
                              Trims(unit.rated_current_mA / 2 + 1, 0, 10000, 10000), 10),),
                 256, 4),
        Schedule("gain", (Hold(hold.phase, hold.velocity, 800,
                               Trims(0, 0, 4000, 16000), 10),), 256, 4),
        Schedule("microsteps", base.holds, 128, 4),
    ]


def test_what_the_drive_would_refuse_writes_nothing(tmp_path: Path) -> None:
    unit = derive_unit("SN7101")
    for schedule in _refused(unit):
        with pytest.raises(InputError):
            record_in_process(tmp_path / "refused.blf", unit, schedule)
    with pytest.raises(InputError):
        record_in_process(tmp_path / "refused.txt", unit, _tiny_schedule())
    with pytest.raises(InputError):
        record_in_process(tmp_path / "refused.blf", unit, _tiny_schedule(), loss=1.0)
    assert list(tmp_path.iterdir()) == []


def test_messages_are_plain_can_frames() -> None:
    frames = simulate_frames(derive_unit("SN7101"), _tiny_schedule())
    messages = list(frames.messages())
    assert len(messages) == len(frames) == 4 * frames.cycles
    assert all(isinstance(m, can.Message) and not m.is_extended_id for m in messages[:8])
    assert [m.dlc for m in messages[:4]] == [1, 8, 8, 8]
