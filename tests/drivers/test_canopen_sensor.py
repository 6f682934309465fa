"""The CANopen sensor driver and the lockstep SYNC clock against the simulated bench."""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterator

import can
import canopen
import numpy as np
import pytest

from drivers.base import DriveState
from drivers.canbus import SteppedSync, bench_tpdo_cob_ids
from drivers.canopen_drive import CanopenDrive
from drivers.canopen_sensor import (
    CanopenSensor,
    SampleBuffer,
    count_lost_samples,
    decode_samples,
)
from station.errors import DeviceStateError, DeviceTimeout, InputError
from station.sim.bench import SimBench

STANDARD_GRAVITY = 9.80665
SENSOR_TPDO1 = 0x190
END_MARKER_COB = 0x7FF


@pytest.fixture
def sensor(network: canopen.Network) -> Iterator[CanopenSensor]:
    with CanopenSensor(network) as opened:
        assert isinstance(opened, CanopenSensor)
        yield opened


def _frame(counter: int, x: int, y: int, z: int) -> bytes:
    return struct.pack("<Hhhh", counter, x, y, z)


# -- pure decoding --------------------------------------------------------------------------


def test_decode_samples_follows_the_tpdo1_layout() -> None:
    counter, counts = decode_samples(_frame(65535, -32767, 1, 32767) + _frame(0, 2, -3, 4))
    assert counter.dtype == np.uint16 and counts.dtype == np.int16
    assert counter.tolist() == [65535, 0]
    assert counts.tolist() == [[-32767, 1, 32767], [2, -3, 4]]


def test_count_lost_samples_reads_gaps_in_the_counter_across_the_wrap() -> None:
    assert count_lost_samples(np.array([65533, 65534, 65535, 0, 1], dtype=np.uint16)) == 0
    assert count_lost_samples(np.array([65534, 1, 2, 5], dtype=np.uint16)) == 2 + 2
    assert count_lost_samples(np.array([7, 7, 8], dtype=np.uint16)) == 0  # duplicate, not loss
    assert count_lost_samples(np.array([], dtype=np.uint16)) == 0


def test_sample_buffer_grows_past_its_initial_capacity_without_losing_order() -> None:
    buffer = SampleBuffer(initial_capacity=4)
    for k in range(11):
        buffer.append(_frame(k, k, -k, 2 * k))
    counter, counts = buffer.decode()
    assert counter.tolist() == list(range(11))
    assert counts[:, 2].tolist() == [2 * k for k in range(11)]
    buffer.clear()
    assert len(buffer) == 0


# -- against the simulated bench -----------------------------------------------------------


def test_identity_of_the_sensor_is_read_from_0x1018(sensor: CanopenSensor) -> None:
    identity = sensor.identity()
    assert identity.vendor_id > 0


def test_range_change_changes_the_sensitivity(sensor: CanopenSensor) -> None:
    assert sensor.range_g() == 2
    assert sensor.lsb_mps2() == pytest.approx(2 * STANDARD_GRAVITY / 32768, rel=1e-6)
    sensor.set_range_g(8)
    assert sensor.range_g() == 8
    assert sensor.lsb_mps2() == pytest.approx(8 * STANDARD_GRAVITY / 32768, rel=1e-6)


def test_invalid_range_is_refused_before_any_bus_traffic(
    bench: SimBench, sensor: CanopenSensor
) -> None:
    bench.close()  # no device left: any bus traffic would end in a timeout, not InputError
    with pytest.raises(InputError, match="range 3 g"):
        sensor.set_range_g(3)


def test_capture_at_standstill_sees_gravity_on_z_one_sample_per_sync_and_no_loss(
    network: canopen.Network, sensor: CanopenSensor
) -> None:
    with (
        CanopenDrive(network) as drive,
        SteppedSync(network, expected_cob_ids=bench_tpdo_cob_ids(1, 16)) as clock,
    ):
        drive.enable()
        drive.set_velocity(0)
        assert drive.state() is DriveState.OPERATION_ENABLED
        clock.advance(10)
        sensor.start_capture()
        clock.advance(600)
        capture = sensor.stop_capture()
        clock.advance(5)  # samples after stop are not kept
    assert capture.counter.size == 600
    assert capture.lost == 0
    assert np.all(np.diff(capture.counter.astype(np.int64)) == 1)
    acceleration = capture.acceleration
    assert acceleration.shape == (600, 3)
    assert capture.lsb_mps2 == pytest.approx(2 * STANDARD_GRAVITY / 32768, rel=1e-6)
    assert np.mean(acceleration[:, 2]) == pytest.approx(STANDARD_GRAVITY, abs=0.2)
    assert abs(np.mean(acceleration[:, 0])) < 0.2


def test_dropped_frames_are_counted_from_counter_gaps(
    channel: str, network: canopen.Network, sensor: CanopenSensor
) -> None:
    # No SYNC runs, so the only TPDO1 frames are these: 3 + 1 samples are missing.
    counters = [100, 101, 105, 106, 108]
    end_marker = threading.Event()
    network.subscribe(END_MARKER_COB, lambda can_id, data, timestamp: end_marker.set())
    sensor.start_capture()
    with can.Bus(interface="virtual", channel=channel) as injector:
        for counter in counters:
            injector.send(can.Message(arbitration_id=SENSOR_TPDO1, data=_frame(counter, 1, 2, 3)))
        injector.send(can.Message(arbitration_id=SENSOR_TPDO1, data=b"\x00\x01"))  # malformed
        # One notifier thread delivers in bus order: the marker comes after every sample.
        injector.send(can.Message(arbitration_id=END_MARKER_COB, data=b""))
        assert end_marker.wait(2.0)
    capture = sensor.stop_capture()
    assert capture.counter.tolist() == counters
    assert capture.lost == 4
    assert capture.counts.tolist() == [[1, 2, 3]] * 5


def test_stop_capture_without_start_is_a_state_error(sensor: CanopenSensor) -> None:
    with pytest.raises(DeviceStateError):
        sensor.stop_capture()


def test_range_cannot_change_during_a_capture(sensor: CanopenSensor) -> None:
    sensor.start_capture()
    with pytest.raises(DeviceStateError):
        sensor.set_range_g(4)
    sensor.stop_capture()


def test_lockstep_clock_times_out_naming_the_device_when_the_bench_is_closed(
    bench: SimBench, network: canopen.Network
) -> None:
    sensor = CanopenSensor(network, sdo_timeout_s=0.05)
    drive = CanopenDrive(network, sdo_timeout_s=0.05)
    try:
        with SteppedSync(
            network,
            expected_cob_ids=bench_tpdo_cob_ids(1, 16),
            timeout_s=0.02,
            max_missing_cycles=3,
        ) as clock:
            clock.advance(20)
            bench.close()
            with pytest.raises(DeviceTimeout) as raised:
                clock.advance(100)
            assert raised.value.device == "sensor"
            assert clock.cycles == 23
    finally:
        drive.close()
        sensor.close()


def test_close_twice_is_harmless_and_stops_listening(network: canopen.Network) -> None:
    sensor = CanopenSensor(network)
    sensor.close()
    sensor.close()
    assert 16 not in network.nodes
    assert SENSOR_TPDO1 not in network.subscribers
