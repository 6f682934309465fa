"""The drivers' watch over the bus: retries, heartbeats, reboots, error frames, bus-off."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator

import can
import canopen
import pytest

from drivers.canbus import BusMonitor, SteppedSync, bench_tpdo_cob_ids
from drivers.canopen_drive import CanopenDrive
from drivers.canopen_sensor import CanopenSensor
from station.errors import BusFault, DeviceRebooted, DeviceTimeout
from station.sim.bench import SimBench
from station.sim.faults import bus_error_frame, bus_off_frame


@pytest.fixture
def drive(network: canopen.Network) -> Iterator[CanopenDrive]:
    d = CanopenDrive(network, sdo_timeout_s=0.1)
    with d:
        yield d


def test_two_unanswered_sdo_requests_are_sent_again_and_logged(
    bench: SimBench, drive: CanopenDrive, caplog: pytest.LogCaptureFixture,
) -> None:
    bench.drive.sdo_requests_to_drop = 2
    with caplog.at_level(logging.WARNING):
        assert drive.identity().serial_number == bench.unit.serial_number
    assert "retry 1 of 2" in caplog.text
    assert bench.drive.sdo_requests_to_drop == 0


def test_a_request_unanswered_three_times_is_a_timeout_naming_the_object(
    bench: SimBench, drive: CanopenDrive,
) -> None:
    bench.drive.sdo_requests_to_drop = 100
    with pytest.raises(DeviceTimeout, match=r"drive: SDO 0x2100:01: no answer to 3 attempts"):
        drive.read_trims()


def test_an_sdo_abort_is_not_retried_and_keeps_its_meaning(
    bench: SimBench, drive: CanopenDrive, caplog: pytest.LogCaptureFixture,
) -> None:
    bench.drive.eeprom_fails = True
    with caplog.at_level(logging.WARNING, logger="drivers.canbus"), pytest.raises(
        Exception, match=r"0x08000020 \(data cannot be transferred or stored\)"
    ):
        drive.store()
    assert "retry" not in caplog.text


def test_a_silent_drive_is_noticed_by_its_missing_heartbeat(
    bench: SimBench, drive: CanopenDrive,
) -> None:
    drive.check_alive()
    bench.drive.fall_silent()
    time.sleep(0.35)
    with pytest.raises(DeviceTimeout, match="drive: silent: last heartbeat"):
        drive.check_alive(max_age_s=0.3)


def test_a_drive_that_reboots_by_itself_is_noticed_but_its_own_reset_is_not(
    bench: SimBench, drive: CanopenDrive,
) -> None:
    drive.reset()  # the station's own: expected
    drive.check_alive()
    bench.drive.power_cycle()
    deadline = time.monotonic() + 10.0  # generous: a wait for the boot-up, not a speed limit
    while time.monotonic() < deadline:
        try:
            drive.check_alive()
        except DeviceRebooted as exc:
            assert "boot-up" in str(exc)
            return
        time.sleep(0.01)
    pytest.fail("the power cycle went unnoticed")


def _bus_monitor(network: canopen.Network) -> BusMonitor:
    monitor = BusMonitor("test bus")
    assert network.notifier is not None
    network.notifier.add_listener(monitor)
    return monitor


def _send_from_bench(bench: SimBench, message: can.Message) -> None:
    bus = bench._bus
    assert bus is not None
    bus.send(message)


def _wait_for(condition: Callable[[], bool], timeout_s: float = 10.0) -> None:
    """Until ``condition`` holds; generous, since it returns as soon as it does."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)


def test_error_frames_are_counted_and_bus_off_stops_the_run(
    bench: SimBench, network: canopen.Network,
) -> None:
    monitor = _bus_monitor(network)
    for _ in range(3):
        _send_from_bench(bench, bus_error_frame())
    _wait_for(lambda: monitor.error_frames == 3)
    assert monitor.error_frames == 3
    monitor.check()  # error frames alone: CAN resends, nothing to stop for
    _send_from_bench(bench, bus_off_frame())
    _wait_for(lambda: monitor.error_frames == 4)
    assert monitor.passive
    with pytest.raises(BusFault, match="bus-off after 4 error frames"):
        monitor.check()


def test_the_clock_calls_its_supervisor_and_stops_when_it_raises(
    bench: SimBench, network: canopen.Network,
) -> None:
    sensor = CanopenSensor(network, sdo_timeout_s=0.1)
    with CanopenDrive(network) as drive, sensor:
        cob_ids = bench_tpdo_cob_ids(1, 16, drive_name=drive.name, sensor_name=sensor.name)
        calls: list[int] = []
        with SteppedSync(network, expected_cob_ids=cob_ids, timeout_s=0.5) as clock:
            clock.supervise(lambda: calls.append(clock.cycles))
            clock.advance(50)
            assert calls and calls[-1] == 50

            def dead() -> None:
                sensor.check_alive(max_age_s=0.05)

            clock.supervise(dead)
            bench.sensor.fall_silent()
            time.sleep(0.1)  # past max_age_s: the heartbeat is stale however fast this runs
            before = clock.cycles
            with pytest.raises(DeviceTimeout, match="sensor: silent"):
                clock.advance(50)
            # Stopped at the first stall, not after 20 missed frames: counted in cycles,
            # not in seconds, which a loaded machine stretches.
            assert clock.cycles - before <= 2
            assert max(clock.missed.values()) <= 1
