"""Reading ICD.md §5 recordings into per-SYNC timelines (station.analysis.reader)."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import can
import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis.reader import read_recording
from station.analysis.timeline import Timeline
from station.core import NOMINAL_TRIMS, LoadKind, Trims
from station.errors import ExitCode, InputError, RecordingError
from station.recording import (
    LogFormat,
    metadata_path_for,
    read_metadata,
    write_json_atomically,
)
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule
from tests.metadata import icd_metadata

# Hand-written from ICD.md, independent of the reader and the devices.
SYNC = 0x080
SENSOR_TPDO1 = 0x180 + 16
DRIVE_TPDO1 = 0x180 + 1
DRIVE_TPDO2 = 0x280 + 1
SENSOR_LAYOUT = struct.Struct("<Hhhh")
DRIVE1_LAYOUT = struct.Struct("<iHH")
DRIVE2_LAYOUT = struct.Struct("<hhHH")
SWEPT = Trims(offset_a_mA=-120.0, offset_b_mA=55.0, gain_a=9500.0, gain_b=10500.0)


# ---------------------------------------------------------------- simulated bench


def _short_schedule() -> Schedule:
    v = velocity_for(20.0, 256)
    return Schedule(
        "short",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 100),
            Hold(Phase.BASELINE, v, 1000, NOMINAL_TRIMS, 300),
            Hold(Phase.SWEEP_OFFSET_A, v, 1000, SWEPT, 300),
            Hold(Phase.STOP, 0, 1000, SWEPT, 50),
        ),
    )


def _record(out: Path, truth_dir: Path, *, loss: float = 0.0) -> Path:
    request = SimRecordRequest(
        out=out,
        serial=parse_serial("SN123"),
        schedule=ScheduleName.CALIBRATION,  # only validated; the short schedule runs
        effects=frozenset(),
        seed=1,
        load=LoadKind.DISK,
        loss=loss,
        truth=truth_dir / f"{out.stem}.truth.json",
    )
    record_schedule(request, _short_schedule())
    return out


@dataclass(frozen=True)
class SimRecordings:
    lossless: dict[LogFormat, Path]
    lossy: Path  # BLF, same seed as lossless[BLF], 2 % of frames dropped


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimRecordings]:
    """One short run per format; recording is the slow part, so runs are shared."""
    root = tmp_path_factory.mktemp("sim")
    (root / "rec").mkdir()
    (root / "truth").mkdir()
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATION_HOME", str(root / "home"))
        lossless = {
            fmt: _record(root / "rec" / f"run-{fmt.name}{fmt.value}", root / "truth")
            for fmt in LogFormat
        }
        lossy = _record(root / "rec" / "lossy.blf", root / "truth", loss=0.02)
        yield SimRecordings(lossless, lossy)


@dataclass(frozen=True)
class BusView:
    """What the log holds per SYNC, decoded straight from the frames (lossless logs)."""

    accel: NDArray[np.int64]
    position: NDArray[np.int64]
    amplitude: NDArray[np.int64]
    trims: NDArray[np.int64]
    sensor_counter: NDArray[np.int64]


def _bus_view(path: Path) -> BusView:
    samples: list[dict[int, bytes]] = []
    for msg in can.LogReader(str(path)):
        if msg.arbitration_id == SYNC:
            samples.append({})
        elif samples and msg.arbitration_id in (SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2):
            samples[-1][msg.arbitration_id] = bytes(msg.data)
    sensor = [SENSOR_LAYOUT.unpack(s[SENSOR_TPDO1]) for s in samples]
    drive = [DRIVE1_LAYOUT.unpack(s[DRIVE_TPDO1]) for s in samples]
    return BusView(
        accel=np.array([s[1:] for s in sensor]),
        position=np.array([d[0] for d in drive]),
        amplitude=np.array([d[1] for d in drive]),
        trims=np.array([DRIVE2_LAYOUT.unpack(s[DRIVE_TPDO2]) for s in samples]),
        sensor_counter=np.array([s[0] for s in sensor]),
    )


def _icd_frames(path: Path) -> int:
    ids = {SYNC, SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2}
    return sum(1 for msg in can.LogReader(str(path)) if msg.arbitration_id in ids)


@pytest.mark.parametrize("fmt", list(LogFormat))
def test_every_format_reads_back_exactly_what_the_bench_sent(
    sim: SimRecordings, fmt: LogFormat
) -> None:
    path = sim.lossless[fmt]
    timeline = read_recording(path)
    bus = _bus_view(path)
    assert timeline.samples == _short_schedule().cycles == len(bus.position)
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    assert timeline.trims_valid.all()
    losses = timeline.losses
    assert (losses.syncs_missing, losses.sensor_samples_lost) == (0, 0)
    assert (losses.drive_status_lost, losses.drive_trims_lost, losses.frames_malformed) == (0, 0, 0)
    # SDO set-up traffic and heartbeats are on the bus too, and ignored.
    assert losses.frames_ignored > 0
    assert np.array_equal(timeline.accel_counts, bus.accel)
    assert np.array_equal(timeline.position, bus.position)
    assert np.array_equal(timeline.amplitude_mA, bus.amplitude)
    assert np.array_equal(timeline.trims, bus.trims)
    assert (np.mod(np.diff(bus.sensor_counter), 65536) == 1).all()
    assert set(timeline.amplitude_mA.tolist()) == {1000}
    assert timeline.trims[150].tolist() == [0, 0, 10000, 10000]
    assert timeline.trims[500].tolist() == [-120, 55, 9500, 10500]
    assert set(np.diff(timeline.position[250:390]).tolist()) <= {20, 21}
    assert timeline.metadata == read_metadata(path)
    assert timeline.sync_period_s == 0.001


def test_all_formats_of_one_run_give_the_same_timeline(sim: SimRecordings) -> None:
    timelines = [read_recording(path) for path in sim.lossless.values()]
    first = timelines[0]
    for other in timelines[1:]:
        assert np.array_equal(other.accel_counts, first.accel_counts)
        assert np.array_equal(other.position, first.position)
        assert np.array_equal(other.trims, first.trims)


def test_lost_frames_are_counted_and_every_kept_frame_keeps_its_sample(
    sim: SimRecordings,
) -> None:
    clean = read_recording(sim.lossless[LogFormat.BLF])
    lossy = read_recording(sim.lossy)
    assert lossy.samples == clean.samples
    losses = lossy.losses
    assert losses.syncs_missing > 0 and losses.sensor_samples_lost > 0
    assert losses.drive_status_lost > 0 and losses.drive_trims_lost > 0
    assert losses.syncs_seen + losses.syncs_missing == lossy.samples
    assert losses.sensor_samples_lost == np.count_nonzero(~lossy.sensor_valid)
    assert losses.drive_status_lost == np.count_nonzero(~lossy.drive_valid)
    assert losses.drive_trims_lost == np.count_nonzero(~lossy.trims_valid)
    # Every ICD frame missing from the log is accounted for once.
    missing = (
        losses.syncs_missing
        + losses.sensor_samples_lost
        + losses.drive_status_lost
        + losses.drive_trims_lost
    )
    assert missing == 4 * clean.samples - _icd_frames(sim.lossy)
    # Same seed, same plant: the frames that survived sit at the same samples;
    # sensor frames always (their counter says where), drive frames wherever
    # the rank rule is unambiguous.
    s = lossy.sensor_valid
    d = lossy.drive_valid & ~_rank_ambiguous(sim.lossy, DRIVE_TPDO1, lossy.samples)
    t = lossy.trims_valid & ~_rank_ambiguous(sim.lossy, DRIVE_TPDO2, lossy.samples)
    assert np.count_nonzero(d) > 0.95 * lossy.samples
    assert np.array_equal(lossy.accel_counts[s], clean.accel_counts[s])
    assert np.array_equal(lossy.position[d], clean.position[d])
    assert np.array_equal(lossy.trims[t], clean.trims[t])
    assert not lossy.accel_counts[~s].any() and not lossy.position[~lossy.drive_valid].any()


def _rank_ambiguous(path: Path, cob: int, samples: int) -> NDArray[np.bool_]:
    """Samples where a drive frame may sit one sample early: after a lost SYNC,
    the k-th frame is taken for the k-th sample, which is wrong once a frame of
    the same stretch was lost too (drive frames carry no counter)."""
    ambiguous = np.zeros(samples, dtype=np.bool_)
    start, count, previous = -1, 0, 0
    for msg in can.LogReader(str(path)):
        if msg.arbitration_id == SYNC:
            counter = msg.data[0]
            end = 0 if start < 0 else start + (counter - previous - 1) % 240 + 1
            if count < end - start:
                ambiguous[start:end] = end - start > 1
            start, count, previous = end, 0, counter
        elif msg.arbitration_id == cob:
            count += 1
    if count < samples - start:
        ambiguous[start:] = samples - start > 1
    return ambiguous


# ---------------------------------------------------------------- hand-made logs

T0 = 1_700_000_000.0
FRAME_GAP_S = 130e-6
METADATA = icd_metadata(serial="SN7", sensor_radius_m=0.05)


@dataclass(frozen=True)
class Plan:
    """What a well-behaved bench sends for ``samples`` SYNCs."""

    samples: int
    sync_start: int = 1  # SYNC counter of sample 0
    sensor_start: int = 500  # sensor counter of sample 0
    position_start: int = 0
    step: int = 20  # microsteps per SYNC

    def accel(self, n: int) -> tuple[int, int, int]:
        return (n * 37) % 2001 - 1000, n % 97, 16384

    def position(self, n: int) -> int:
        raw = self.position_start + self.step * n
        return (raw + 2**31) % 2**32 - 2**31  # as the int32 object carries it

    def trims(self, n: int) -> tuple[int, int, int, int]:
        return (-n % 50, n % 30, 10000 - n % 7, 10000 + n % 11)


def _frames(plan: Plan, drop: frozenset[tuple[int, int]] = frozenset()) -> list[can.Message]:
    """The bus in order; ``drop`` holds (COB-ID, sample) pairs the logger missed."""
    out: list[can.Message] = []
    for n in range(plan.samples):
        payloads = (
            (SYNC, bytes([(plan.sync_start - 1 + n) % 240 + 1])),
            (SENSOR_TPDO1, SENSOR_LAYOUT.pack((plan.sensor_start + n) % 65536, *plan.accel(n))),
            (DRIVE_TPDO1, DRIVE1_LAYOUT.pack(plan.position(n), 1000, 0x0627)),
            (DRIVE_TPDO2, DRIVE2_LAYOUT.pack(*plan.trims(n))),
        )
        for i, (cob, data) in enumerate(payloads):
            if (cob, n) not in drop:
                stamp = T0 + n * METADATA.sync_period_s + i * FRAME_GAP_S
                out.append(_message(cob, data, stamp))
    return out


def _message(cob: int, data: bytes, stamp: float, *, extended: bool = False) -> can.Message:
    return can.Message(timestamp=stamp, arbitration_id=cob, is_extended_id=extended, data=data)


def _write(path: Path, frames: list[can.Message], **extra: object) -> Path:
    with can.Logger(str(path)) as log:
        for msg in frames:
            log.on_message_received(msg)
    doc = METADATA.to_json_dict()
    doc.update(extra)
    write_json_atomically(metadata_path_for(path), doc)
    return path


def _assert_matches(timeline: Timeline, plan: Plan) -> None:
    """Every valid row holds exactly what the plan sent for that sample."""
    n = np.arange(plan.samples)
    s, d, t = timeline.sensor_valid, timeline.drive_valid, timeline.trims_valid
    expected_accel = np.array([plan.accel(i) for i in range(plan.samples)])
    expected_trims = np.array([plan.trims(i) for i in range(plan.samples)])
    assert np.array_equal(timeline.accel_counts[s], expected_accel[s])
    assert np.array_equal(timeline.position[d], plan.position_start + plan.step * n[d])
    assert np.array_equal(timeline.trims[t], expected_trims[t])
    assert (timeline.amplitude_mA[d] == 1000).all()
    assert (timeline.statusword[d] == 0x0627).all()


def test_hand_made_log_reads_back_across_sync_and_sensor_counter_wraps(tmp_path: Path) -> None:
    plan = Plan(samples=300, sync_start=235, sensor_start=65400)
    timeline = read_recording(_write(tmp_path / "run.asc", _frames(plan)))
    assert timeline.samples == 300
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    assert timeline.trims_valid.all()
    assert timeline.losses.syncs_missing == 0
    _assert_matches(timeline, plan)


def test_tpdos_after_a_lost_sync_land_on_that_syncs_sample(tmp_path: Path) -> None:
    plan = Plan(samples=20)
    timeline = read_recording(_write(tmp_path / "run.asc", _frames(plan, frozenset({(SYNC, 7)}))))
    assert timeline.samples == 20
    assert timeline.losses.syncs_missing == 1 and timeline.losses.syncs_seen == 19
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    assert timeline.trims_valid.all()
    _assert_matches(timeline, plan)


def test_drive_frames_after_consecutive_lost_syncs_take_one_sample_each(tmp_path: Path) -> None:
    plan = Plan(samples=30)
    drop = frozenset({(SYNC, 10), (SYNC, 11), (SYNC, 12), (SENSOR_TPDO1, 11)})
    timeline = read_recording(_write(tmp_path / "run.blf", _frames(plan, drop)))
    assert timeline.samples == 30
    assert timeline.losses.syncs_missing == 3
    assert timeline.losses.sensor_samples_lost == 1 and not timeline.sensor_valid[11]
    assert timeline.drive_valid.all()
    _assert_matches(timeline, plan)


def test_more_than_240_lost_syncs_are_resolved_by_the_sensor_counter(tmp_path: Path) -> None:
    plan = Plan(samples=700, sync_start=17)
    # The SYNC counter alone sees 300 lost SYNCs as 60.
    drop = frozenset((SYNC, n) for n in range(200, 500))
    timeline = read_recording(_write(tmp_path / "run.blf", _frames(plan, drop)))
    assert timeline.samples == 700
    assert timeline.losses.syncs_missing == 300
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    _assert_matches(timeline, plan)


def test_a_bus_outage_longer_than_240_syncs_keeps_later_samples_in_place(tmp_path: Path) -> None:
    plan = Plan(samples=800)
    cobs = (SYNC, SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2)
    drop = frozenset((cob, n) for n in range(300, 551) for cob in cobs)
    timeline = read_recording(_write(tmp_path / "run.csv", _frames(plan, drop)))
    assert timeline.samples == 800
    assert timeline.losses.syncs_missing == 251
    assert timeline.losses.sensor_samples_lost == 251
    assert not timeline.sensor_valid[300:551].any() and timeline.sensor_valid[551:].all()
    assert timeline.drive_valid[551:].all()
    _assert_matches(timeline, plan)


@pytest.mark.parametrize(("start", "step"), [(2**31 - 5000, 1000), (-(2**31) + 5000, -1000)])
def test_position_demand_is_unwrapped_past_the_int32_range(
    tmp_path: Path, start: int, step: int
) -> None:
    plan = Plan(samples=40, position_start=start, step=step)
    timeline = read_recording(_write(tmp_path / "run.log", _frames(plan)))
    assert np.array_equal(timeline.position, start + step * np.arange(40))
    assert abs(int(timeline.position[-1])) > 2**31
    assert (np.diff(timeline.position) == step).all()


def test_frames_outside_the_icd_are_ignored_and_counted(tmp_path: Path) -> None:
    plan = Plan(samples=30)
    frames = _frames(plan)
    stamp = T0 + 0.0105
    noise = [
        _message(0x601, bytes(8), stamp),  # SDO request
        _message(0x581, bytes(8), stamp),  # SDO response
        _message(0x701, b"\x05", stamp),  # heartbeat
        _message(0x081, bytes(8), stamp),  # EMCY
        _message(0x182, bytes(8), stamp),  # another node's TPDO1
        _message(0x190, bytes(8), stamp, extended=True),  # 29-bit 0x190
        can.Message(
            timestamp=stamp, arbitration_id=0x190, is_extended_id=False, is_remote_frame=True, dlc=8
        ),  # RTR on the sensor's COB-ID
        can.Message(timestamp=stamp, is_error_frame=True),
    ]
    clean = read_recording(_write(tmp_path / "clean.blf", frames))
    noisy = read_recording(_write(tmp_path / "noisy.blf", frames[:42] + noise + frames[42:]))
    assert noisy.losses.frames_ignored == len(noise)
    assert noisy.losses.frames_malformed == 0
    assert replace(noisy.losses, frames_ignored=0) == clean.losses
    assert np.array_equal(noisy.accel_counts, clean.accel_counts)
    assert np.array_equal(noisy.position, clean.position)
    _assert_matches(noisy, plan)


def test_an_icd_frame_with_a_wrong_length_is_counted_malformed_and_skipped(
    tmp_path: Path,
) -> None:
    plan = Plan(samples=20)
    frames = _frames(plan)
    sensor_5 = next(
        i
        for i, m in enumerate(frames)
        if m.arbitration_id == SENSOR_TPDO1 and m.timestamp > T0 + 0.005
    )
    frames[sensor_5] = _message(
        SENSOR_TPDO1, bytes(frames[sensor_5].data[:6]), frames[sensor_5].timestamp
    )
    timeline = read_recording(_write(tmp_path / "run.asc", frames))
    assert timeline.losses.frames_malformed == 1
    assert timeline.losses.sensor_samples_lost == 1 and not timeline.sensor_valid[5]
    _assert_matches(timeline, plan)


def test_device_frames_before_the_first_sync_are_counted_malformed(tmp_path: Path) -> None:
    plan = Plan(samples=10)
    early = _message(SENSOR_TPDO1, SENSOR_LAYOUT.pack(499, 1, 2, 3), T0 - 0.0005)
    timeline = read_recording(_write(tmp_path / "run.csv", [early, *_frames(plan)]))
    assert timeline.samples == 10
    assert timeline.losses.frames_malformed == 1
    _assert_matches(timeline, plan)


def test_frames_logged_out_of_order_are_sorted_by_timestamp(tmp_path: Path) -> None:
    plan = Plan(samples=20)
    frames = _frames(plan)
    # The frames of samples 5 and 6 reach the file swapped, stamps intact.
    shuffled = frames[:20] + frames[24:28] + frames[20:24] + frames[28:]
    assert [m.timestamp for m in shuffled] != sorted(m.timestamp for m in shuffled)
    timeline = read_recording(_write(tmp_path / "run.blf", shuffled))
    assert timeline.samples == 20 and timeline.losses.syncs_missing == 0
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    _assert_matches(timeline, plan)


@pytest.mark.parametrize("value", [32767, -32767, -32768])
def test_a_sample_at_full_scale_is_flagged_saturated(tmp_path: Path, value: int) -> None:
    plan = Plan(samples=10)
    frames = _frames(plan)
    index = next(
        i
        for i, m in enumerate(frames)
        if m.arbitration_id == SENSOR_TPDO1 and m.timestamp > T0 + 0.003
    )
    frames[index] = _message(
        SENSOR_TPDO1, SENSOR_LAYOUT.pack(503, 0, value, 100), frames[index].timestamp
    )
    timeline = read_recording(_write(tmp_path / "run.asc", frames))
    assert timeline.saturated.tolist() == [n == 3 for n in range(10)]
    assert timeline.losses.saturated_samples == 1


@pytest.mark.parametrize(
    ("missing", "message"),
    [
        (SYNC, "no SYNC"),
        (SENSOR_TPDO1, "no sensor TPDO1"),
        (DRIVE_TPDO1, "no drive TPDO1"),
    ],
)
def test_a_log_without_an_essential_frame_is_refused(
    tmp_path: Path, missing: int, message: str
) -> None:
    plan = Plan(samples=10)
    frames = [m for m in _frames(plan) if m.arbitration_id != missing]
    path = _write(tmp_path / "run.asc", frames)
    with pytest.raises(RecordingError, match=message) as error:
        read_recording(path)
    assert str(path) in str(error.value)
    assert error.value.exit_code == ExitCode.USAGE


def test_an_unknown_suffix_is_an_input_error(tmp_path: Path) -> None:
    path = tmp_path / "run.trc"
    path.write_text("")
    with pytest.raises(InputError, match="unknown recording suffix") as error:
        read_recording(path)
    assert error.value.exit_code == ExitCode.USAGE


def test_a_log_without_metadata_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "run.asc", _frames(Plan(samples=5)))
    metadata_path_for(path).unlink()
    with pytest.raises(RecordingError, match=r"run\.json is missing"):
        read_recording(path)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("sensor_node", None, "missing key 'sensor_node'"),
        ("sync_period_s", "fast", "key 'sync_period_s' has a malformed value"),
        ("frames_recorded", "many", "key 'frames_recorded' has a malformed value"),
    ],
)
def test_bad_metadata_names_the_key(tmp_path: Path, key: str, value: object, message: str) -> None:
    path = _write(tmp_path / "run.asc", _frames(Plan(samples=5)))
    doc = METADATA.to_json_dict()
    if value is None:
        del doc[key]
    else:
        doc[key] = value
    write_json_atomically(metadata_path_for(path), doc)
    with pytest.raises(RecordingError, match=message):
        read_recording(path)


def test_a_missing_log_beside_its_metadata_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "run.blf"
    write_json_atomically(metadata_path_for(path), METADATA.to_json_dict())
    with pytest.raises(RecordingError, match="log file is missing"):
        read_recording(path)


@pytest.mark.parametrize("fmt", [LogFormat.BLF, LogFormat.MF4])
def test_a_file_that_is_not_the_format_its_suffix_says_is_refused(
    tmp_path: Path, fmt: LogFormat
) -> None:
    path = tmp_path / f"run{fmt.value}"
    path.write_bytes(b"definitely not a CAN log\n" * 40)
    write_json_atomically(metadata_path_for(path), METADATA.to_json_dict())
    with pytest.raises(RecordingError, match="cannot be read as"):
        read_recording(path)


# ---------------------------------------------------------------- truncation

CUTS = {"half": 0.5, "ninety_percent": 0.9, "minus_3_bytes": None}


def _cut_copy(source: Path, target_dir: Path, cut: float | None, *, keep_count: bool) -> Path:
    """A copy cut short, with metadata that may omit ``frames_recorded``
    (other benches do), so the format's own end check must catch the cut."""
    data = source.read_bytes()
    size = len(data) - 3 if cut is None else int(len(data) * cut)
    if data[size - 1 : size] == b"\n":
        # A cut right after a line end leaves a shorter but well-formed line-based log
        # (CSV, candump), which only frames_recorded can tell (keep_count=True); about
        # one cut in forty landed there, depending on the recording's exact length.
        size -= 1
    target = target_dir / source.name
    target.write_bytes(data[:size])
    doc = read_metadata(source).to_json_dict()
    if not keep_count:
        doc.pop("frames_recorded", None)
    write_json_atomically(metadata_path_for(target), doc)
    return target


@pytest.mark.parametrize("cut", list(CUTS))
@pytest.mark.parametrize("fmt", list(LogFormat))
def test_a_truncated_log_of_any_format_is_refused(
    sim: SimRecordings, tmp_path: Path, fmt: LogFormat, cut: str
) -> None:
    source = sim.lossless[fmt]
    assert "frames_recorded" in read_metadata(source).extra
    path = _cut_copy(source, tmp_path, CUTS[cut], keep_count=False)
    with pytest.raises(RecordingError, match="truncated") as error:
        read_recording(path)
    assert str(path) in str(error.value)


def test_the_recorded_frame_count_catches_a_cut_on_a_line_boundary(
    sim: SimRecordings, tmp_path: Path
) -> None:
    source = sim.lossless[LogFormat.CANDUMP]
    text = source.read_bytes()
    whole_lines = text[: text.index(b"\n", len(text) // 2) + 1]
    for keep_count, name in ((True, "counted"), (False, "uncounted")):
        (tmp_path / name).mkdir()
        target = _cut_copy(source, tmp_path / name, 1.0, keep_count=keep_count)
        target.write_bytes(whole_lines)
    with pytest.raises(RecordingError, match=r"truncated.*metadata says"):
        read_recording(tmp_path / "counted" / source.name)
    # Without the count, a cut between lines looks like a shorter run.
    assert read_recording(tmp_path / "uncounted" / source.name).samples < 750


def test_a_blf_whose_writer_never_closed_it_is_refused(sim: SimRecordings, tmp_path: Path) -> None:
    source = sim.lossless[LogFormat.BLF]
    target = _cut_copy(source, tmp_path, 1.0, keep_count=False)
    data = bytearray(target.read_bytes())
    # python-can's placeholder header: its own size, no objects.
    struct.pack_into("<QQL", data, 16, 144, 144, 0)
    target.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="never completed"):
        read_recording(target)
