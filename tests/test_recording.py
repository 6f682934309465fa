"""The recording writer: ICD.md §5 logs, atomic publication, strict metadata."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import can
import pytest

from station.core import Axis
from station.errors import InputError, RecordingError
from station.recorder import RecordingWriter, SimulatedClock
from station.recording import LogFormat, RecordingMetadata, metadata_path_for, read_metadata
from tests.metadata import icd_metadata


def _metadata() -> RecordingMetadata:
    return icd_metadata(gear_ratio=0.142857, extra={"schedule": "calibration"})


def _frames(cycles: int) -> list[can.Message]:
    frames = []
    for n in range(cycles):
        frames.append(can.Message(arbitration_id=0x080, data=[n % 240 + 1], is_extended_id=False))
        frames.append(
            can.Message(
                arbitration_id=0x190,
                data=struct.pack("<Hhhh", n, 1, -2, 1638),
                is_extended_id=False,
            )
        )
        frames.append(
            can.Message(
                arbitration_id=0x181,
                data=struct.pack("<iHH", 80 * n, 1000, 0x0237),
                is_extended_id=False,
            )
        )
        frames.append(
            can.Message(
                arbitration_id=0x281,
                data=struct.pack("<hhHH", -5, 7, 9900, 10100),
                is_extended_id=False,
            )
        )
    return frames


@pytest.mark.parametrize("fmt", list(LogFormat))
def test_every_icd_log_format_reads_back_byte_for_byte(tmp_path: Path, fmt: LogFormat) -> None:
    path = tmp_path / f"run{fmt.value}"
    frames = _frames(50)
    with RecordingWriter(path, _metadata(), clock=SimulatedClock(0.001, start=1000.0)) as rec:
        for msg in frames:
            rec.on_message_received(msg)
        rec.commit()
    back = list(can.LogReader(str(path)))
    assert [(m.arbitration_id, bytes(m.data)) for m in back] == [
        (m.arbitration_id, bytes(m.data)) for m in frames
    ]
    assert not any(m.is_extended_id for m in back)
    stamps = [m.timestamp for m in back]
    assert stamps == sorted(stamps)
    # Four frames per SYNC period: simulated time advances one period per SYNC.
    assert stamps[4] - stamps[0] == pytest.approx(0.001, abs=1e-6)
    assert json.loads(metadata_path_for(path).read_text())["format"] == "hsm-recording/1"


def test_uncommitted_recording_leaves_no_file_behind(tmp_path: Path) -> None:
    path = tmp_path / "run.blf"
    with pytest.raises(RuntimeError), RecordingWriter(path, _metadata()) as rec:
        for msg in _frames(10):
            rec.on_message_received(msg)
        raise RuntimeError("bench fell over")
    assert list(tmp_path.iterdir()) == []


def test_frame_loss_is_reproducible_and_near_the_asked_rate(tmp_path: Path) -> None:
    kept = []
    for name in ("a", "b"):
        path = tmp_path / f"{name}.csv"
        with RecordingWriter(path, _metadata(), loss_probability=0.05, seed=7) as rec:
            for msg in _frames(2000):
                rec.on_message_received(msg)
            rec.commit()
        kept.append([(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(path))])
    assert kept[0] == kept[1]
    assert 0.04 < 1 - len(kept[0]) / 8000 < 0.06


def test_unknown_suffix_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown recording suffix"):
        RecordingWriter(tmp_path / "run.trc", _metadata())


def test_metadata_round_trips_and_keeps_extra_keys(tmp_path: Path) -> None:
    path = tmp_path / "run.log"
    with RecordingWriter(path, _metadata()) as rec:
        rec.commit()
    back = read_metadata(path)
    assert back.serial == "SN123"
    assert back.tangential_axis is Axis.X
    assert back.extra["schedule"] == "calibration"


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("sync_period_s"), "missing key 'sync_period_s'"),
        (lambda d: d.update(rotor_teeth="fifty"), "key 'rotor_teeth' has a malformed value"),
        (lambda d: d.update(sensor_lsb_mps2=0), "key 'sensor_lsb_mps2' must be positive"),
        (lambda d: d.update(tangential_axis="w"), "key 'tangential_axis' must be x, y or z"),
        (lambda d: d.update(format="other/2"), "key 'format'"),
        (lambda d: d.update(drive_node=200), "key 'drive_node' must be a node-ID"),
    ],
)
def test_malformed_metadata_names_the_key(tmp_path: Path, mutate: object, message: str) -> None:
    doc = _metadata().to_json_dict()
    mutate(doc)  # type: ignore[operator]
    (tmp_path / "run.json").write_text(json.dumps(doc))
    with pytest.raises(RecordingError, match=message):
        read_metadata(tmp_path / "run.asc")


def test_missing_or_broken_metadata_is_a_recording_error(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"metadata file run\.json is missing"):
        read_metadata(tmp_path / "run.asc")
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(RecordingError, match="not valid JSON"):
        read_metadata(tmp_path / "run.asc")


@pytest.mark.parametrize("fmt", list(LogFormat))
def test_bus_channel_names_ending_in_digits_do_not_break_any_format(
    tmp_path: Path, fmt: LogFormat
) -> None:
    # python-can turns a channel name's trailing digits into a channel number;
    # a virtual channel named after a uuid once overflowed BLF's 16-bit field.
    path = tmp_path / f"run{fmt.value}"
    frames = _frames(5)
    for msg in frames:
        msg.channel = "station-sim-5f0c8a4477123456789"
    with RecordingWriter(path, _metadata()) as rec:
        for msg in frames:
            rec.on_message_received(msg)
        rec.commit()
    assert len(list(can.LogReader(str(path)))) == len(frames)


class _BrokenWriter(can.Listener):
    def on_message_received(self, msg: can.Message) -> None:
        raise OSError(28, "No space left on device")

    def stop(self) -> None:
        pass


def test_a_failing_log_writer_is_reported_at_commit_not_on_the_bus_thread(tmp_path: Path) -> None:
    path = tmp_path / "run.asc"
    with RecordingWriter(path, _metadata()) as rec:
        rec._writer.stop()  # type: ignore[union-attr]
        rec._writer = _BrokenWriter()
        for msg in _frames(3):
            rec.on_message_received(msg)  # must not raise: it runs on the notifier thread
        with pytest.raises(RecordingError, match="log writer failed"):
            rec.commit()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt", list(LogFormat))
def test_set_up_traffic_before_the_first_sync_keeps_time_order(
    tmp_path: Path, fmt: LogFormat
) -> None:
    path = tmp_path / f"run{fmt.value}"
    sdo = [
        can.Message(
            arbitration_id=0x601,
            data=bytes([0x40, 0x18, 0x10, 4, 0, 0, 0, 0]),
            is_extended_id=False,
        ),
        can.Message(
            arbitration_id=0x581,
            data=bytes([0x43, 0x18, 0x10, 4, 123, 0, 0, 0]),
            is_extended_id=False,
        ),
    ]
    frames = sdo + _frames(20)
    with RecordingWriter(path, _metadata(), clock=SimulatedClock(0.001, start=5000.0)) as rec:
        for msg in frames:
            rec.on_message_received(msg)
        rec.commit()
    back = list(can.LogReader(str(path)))
    stamps = [m.timestamp for m in back]
    assert stamps == sorted(stamps)
    # Ordering by time must give the bus order back, SYNC 1 after the set-up frames.
    by_time = sorted(back, key=lambda m: m.timestamp)
    assert [m.arbitration_id for m in by_time] == [m.arbitration_id for m in frames]
    assert max(stamps) - min(stamps) < 0.1
