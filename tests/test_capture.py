"""The live capture of ICD frames (station.capture), fed hand-made frames."""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import can
import numpy as np
import pytest

from station.analysis.reader import read_recording
from station.analysis.timeline import Timeline
from station.capture import FrameCapture
from station.errors import DeviceError
from station.recorder import RecordingWriter
from tests.metadata import icd_metadata

# Hand-written from ICD.md §1-3 (drive node 1, sensor node 16), independent of the module.
SYNC = 0x080
SENSOR_TPDO1 = 0x180 + 16
DRIVE_TPDO1 = 0x180 + 1
DRIVE_TPDO2 = 0x280 + 1
SENSOR_LAYOUT = struct.Struct("<Hhhh")  # counter, X, Y, Z
DRIVE1_LAYOUT = struct.Struct("<iHH")  # position demand, amplitude, statusword
DRIVE2_LAYOUT = struct.Struct("<hhHH")  # offset A, offset B, gain A, gain B
OPERATION_ENABLED = 0x1637
FRAME_S = 130e-6


@dataclass(frozen=True)
class Sample:
    """What the bus says about SYNC n."""

    n: int
    sensor_counter: int
    accel: tuple[int, int, int]
    position: int
    amplitude: int
    status: int
    trims: tuple[int, int, int, int]


def sample(n: int, *, counter_start: int = 65500) -> Sample:
    return Sample(
        n=n,
        sensor_counter=(counter_start + n) % 65536,
        accel=(100 + n, -200 - n, 16384 - n % 7),
        position=2_147_483_647 - 1024 * 50 + 1024 * n,  # past int32 from sample 50 on
        amplitude=1000,
        status=OPERATION_ENABLED,
        trims=(-12 + n % 3, 40, 10150, 9850 + n % 2),
    )


def msg(cob_id: int, data: bytes, t: float, **kwargs: bool) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=cob_id, data=data, is_extended_id=False,
                       **kwargs)


def frames_for(s: Sample, *, period_s: float = 0.001) -> list[can.Message]:
    t = s.n * period_s
    return [
        msg(SYNC, bytes([s.n % 240 + 1]), t),
        msg(SENSOR_TPDO1, SENSOR_LAYOUT.pack(s.sensor_counter, *s.accel), t + FRAME_S),
        msg(DRIVE_TPDO1, DRIVE1_LAYOUT.pack(s.position - (1 << 32) * (s.position >= 1 << 31),
                                            s.amplitude, s.status), t + 2 * FRAME_S),
        msg(DRIVE_TPDO2, DRIVE2_LAYOUT.pack(*s.trims), t + 3 * FRAME_S),
    ]


def feed(capture: FrameCapture, messages: Iterable[can.Message]) -> None:
    for m in messages:
        capture.on_message_received(m)


def bus(samples: Iterable[Sample]) -> list[can.Message]:
    return [m for s in samples for m in frames_for(s)]


def assert_matches(timeline: Timeline, samples: list[Sample]) -> None:
    assert timeline.samples == len(samples)
    assert timeline.sensor_valid.all() and timeline.drive_valid.all()
    assert timeline.trims_valid.all()
    np.testing.assert_array_equal(timeline.accel_counts, [s.accel for s in samples])
    np.testing.assert_array_equal(timeline.position, [s.position for s in samples])
    np.testing.assert_array_equal(timeline.amplitude_mA, [s.amplitude for s in samples])
    np.testing.assert_array_equal(timeline.statusword, [s.status for s in samples])
    np.testing.assert_array_equal(timeline.trims, [s.trims for s in samples])


def test_timeline_gives_every_sample_across_sync_and_sensor_counter_wraps() -> None:
    samples = [sample(n) for n in range(300)]  # SYNC counter wraps at 240, sensor at 65536
    capture = FrameCapture(icd_metadata())
    feed(capture, bus(samples))
    timeline = capture.timeline()
    assert_matches(timeline, samples)
    losses = timeline.losses
    assert (losses.syncs_seen, losses.syncs_missing, losses.sensor_samples_lost) == (300, 0, 0)
    assert (losses.frames_malformed, losses.saturated_samples) == (0, 0)


def test_timeline_since_a_mark_starts_at_the_first_sync_after_the_mark() -> None:
    samples = [sample(n) for n in range(20)]
    capture = FrameCapture(icd_metadata())
    first, second = bus(samples[:8]), bus(samples[8:])
    # The mark falls after sample 7's SYNC and sensor frame, before its drive frames.
    feed(capture, first[:-2])
    mark = capture.mark()
    feed(capture, first[-2:])
    feed(capture, second)
    timeline = capture.timeline(since=mark)
    assert_matches(timeline, samples[8:])
    assert timeline.losses.frames_malformed == 0  # the stragglers before the SYNC are not data
    assert_matches(capture.timeline(), samples)  # the whole capture is still there


def test_frames_the_icd_does_not_define_are_ignored() -> None:
    samples = [sample(n) for n in range(10)]
    noise: list[can.Message] = [
        msg(0x701, b"\x05", 0.0),  # drive heartbeat
        msg(0x581, bytes(8), 0.0),  # SDO response
        msg(0x182, bytes(8), 0.0),  # TPDO1 of another node
        msg(0x291, bytes(8), 0.0),  # sensor TPDO2: not in the ICD
        can.Message(timestamp=0.0, arbitration_id=SYNC, data=b"\x07", is_extended_id=True),
        can.Message(timestamp=0.0, arbitration_id=SENSOR_TPDO1, is_extended_id=False,
                    is_remote_frame=True, dlc=8),
        can.Message(timestamp=0.0, arbitration_id=DRIVE_TPDO1, is_extended_id=False,
                    is_error_frame=True),
    ]
    capture = FrameCapture(icd_metadata())
    for i, frames in enumerate(frames_for(s) for s in samples):
        feed(capture, [*frames[:2], noise[i % len(noise)], *frames[2:]])
    feed(capture, noise)
    timeline = capture.timeline()
    assert_matches(timeline, samples)
    assert timeline.losses.frames_malformed == 0


def test_a_wrong_length_icd_frame_is_counted_malformed_and_leaves_its_sample_empty() -> None:
    samples = [sample(n) for n in range(10)]
    messages = bus(samples)
    sensor_5 = 5 * 4 + 1
    assert messages[sensor_5].arbitration_id == SENSOR_TPDO1
    messages[sensor_5] = msg(SENSOR_TPDO1, bytes(messages[sensor_5].data[:6]), 0.0)
    capture = FrameCapture(icd_metadata())
    feed(capture, messages)
    timeline = capture.timeline()
    assert timeline.losses.frames_malformed == 1
    assert timeline.losses.sensor_samples_lost == 1
    assert not timeline.sensor_valid[5]
    assert timeline.sensor_valid.sum() == 9
    assert timeline.drive_valid.all()


def test_a_sync_without_its_counter_byte_is_malformed() -> None:
    messages = bus(sample(n) for n in range(4))
    capture = FrameCapture(icd_metadata())
    feed(capture, messages)
    feed(capture, [msg(SYNC, b"", 0.004)])
    assert capture.timeline().losses.frames_malformed == 1


def test_saturated_samples_are_flagged() -> None:
    samples = [sample(n) for n in range(6)]
    samples[3] = replace(samples[3], accel=(32767, 0, 16384))
    capture = FrameCapture(icd_metadata())
    feed(capture, bus(samples))
    timeline = capture.timeline()
    assert timeline.saturated.tolist() == [False, False, False, True, False, False]


def test_a_capture_without_sync_raises_a_device_error() -> None:
    capture = FrameCapture(icd_metadata())
    with pytest.raises(DeviceError, match="no SYNC"):
        capture.timeline()
    feed(capture, [m for m in bus([sample(0)]) if m.arbitration_id != SYNC])
    with pytest.raises(DeviceError):
        capture.timeline()


def test_a_mark_after_the_last_sync_has_no_samples_yet() -> None:
    capture = FrameCapture(icd_metadata())
    feed(capture, bus(sample(n) for n in range(5)))
    mark = capture.mark()
    assert mark == 20
    with pytest.raises(DeviceError):
        capture.timeline(since=mark)


def test_capture_follows_the_node_ids_of_the_metadata() -> None:
    capture = FrameCapture(icd_metadata(drive_node=2, sensor_node=17))
    feed(capture, bus(sample(n) for n in range(5)))  # frames of nodes 1 and 16
    timeline = capture.timeline()
    assert timeline.samples == 5
    assert not timeline.sensor_valid.any() and not timeline.drive_valid.any()


def test_the_live_capture_and_the_offline_reader_agree(tmp_path: Path) -> None:
    metadata = icd_metadata()
    samples = [sample(n) for n in range(260)]
    samples[100] = replace(samples[100], accel=(-32767, 0, 16384))
    messages = bus(samples)
    del messages[50 * 4 + 2]  # a drive TPDO1 lost
    messages.insert(10, msg(0x701, b"\x05", messages[9].timestamp))  # ignored by both
    messages.insert(30, msg(DRIVE_TPDO2, b"\x01\x02", messages[29].timestamp))  # malformed
    path = tmp_path / "x.blf"
    capture = FrameCapture(metadata)
    with RecordingWriter(path, metadata) as writer:
        for m in messages:
            capture.on_message_received(m)
            writer.on_message_received(m)
        writer.commit()
    live, offline = capture.timeline(), read_recording(path)
    assert live.samples == offline.samples == 260
    for name in ("accel_counts", "sensor_valid", "saturated", "position", "amplitude_mA",
                 "statusword", "drive_valid", "trims", "trims_valid"):
        np.testing.assert_array_equal(getattr(live, name), getattr(offline, name), err_msg=name)
    assert live.losses.frames_malformed == offline.losses.frames_malformed == 1
    assert live.losses.drive_status_lost == offline.losses.drive_status_lost == 1
    assert live.losses.saturated_samples == offline.losses.saturated_samples == 1
    assert offline.losses.frames_ignored == 1
