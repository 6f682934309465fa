"""The station's Modbus drive driver against the simulated drive's server (TCP and RTU)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.base import CalibrationRecord, DriveState
from drivers.modbus_drive import ModbusDrive, ModbusEndpoint
from drivers.modbus_map import PTY_PARITY, ModbusExceptionCode, ModbusLink
from station.core import NOMINAL_TRIMS, Trims
from station.errors import DeviceStateError, DeviceTimeout, InputError, ModbusException
from station.sim.bench import SimBench, SimBenchConfig
from station.sim.devices import FaultCode


def _bench(tmp_path: Path, link: ModbusLink, watchdog_s: float = 2.0) -> SimBench:
    return SimBench(SimBenchConfig(serial="SN123", channel=f"test-modbus-{uuid.uuid4().hex}",
                                   drive_link=link, modbus_watchdog_s=watchdog_s),
                    state_dir=tmp_path / "eeprom")


def _endpoint(bench: SimBench) -> ModbusEndpoint:
    server = bench.modbus
    assert server is not None
    if bench.config.drive_link is ModbusLink.TCP:
        host, port = server.tcp_address
        return ModbusEndpoint(ModbusLink.TCP, host=host, port=port, timeout_s=0.3)
    return ModbusEndpoint(ModbusLink.RTU, device=server.serial_port, parity=PTY_PARITY,
                          timeout_s=0.3)


@pytest.fixture(params=[ModbusLink.TCP, ModbusLink.RTU])
def bench(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SimBench]:
    with _bench(tmp_path, request.param) as sim:
        yield sim


def _sync(bench: SimBench, cycles: int = 2) -> None:
    """Let the drive latch what it holds (it applies writes at its next cycle)."""
    for _ in range(cycles):
        with bench._lock:
            bench.plant.advance(bench.drive.command)
            bench.drive.sync()


def test_the_drive_identifies_itself_with_the_units_serial_and_ratings(bench: SimBench) -> None:
    with ModbusDrive(_endpoint(bench)) as drive:
        assert drive.identity().serial_number == 123
        assert drive.rated_current_mA() == 1000
        assert drive.microsteps_per_fullstep() == 256
        assert not drive.reports_state and not drive.resettable


def test_trims_are_written_in_one_request_and_read_back(bench: SimBench) -> None:
    wanted = Trims(12.0, -7.0, 9950.0, 10050.0)
    with ModbusDrive(_endpoint(bench)) as drive:
        drive.write_trims(Trims(12.4, -6.6, 9950.2, 10049.6))  # rounded as the drive stores
        assert drive.read_trims() == wanted
        _sync(bench)
        assert bench.drive.effective_trims == (12, -7, 9950, 10050)


def test_an_out_of_range_trim_is_refused_with_exception_3_and_changes_nothing(
    bench: SimBench,
) -> None:
    with ModbusDrive(_endpoint(bench)) as drive:
        drive.write_trims(Trims(5.0, 5.0, 10000.0, 10000.0))
        with pytest.raises(ModbusException) as refused:
            drive.write_trims(Trims(5.0, 600.0, 10000.0, 10000.0))  # beyond rated/2
        assert refused.value.code == ModbusExceptionCode.ILLEGAL_DATA_VALUE
        assert "0x03" in str(refused.value) and "illegal data value" in str(refused.value)
        assert drive.read_trims() == Trims(5.0, 5.0, 10000.0, 10000.0)


def test_a_value_that_cannot_fit_its_register_is_an_input_error_before_any_request(
    bench: SimBench,
) -> None:
    with ModbusDrive(_endpoint(bench)) as drive, pytest.raises(InputError):
        drive.write_trims(Trims(5.0, 5.0, 70000.0, 10000.0))


def test_enable_walks_cia402_and_close_leaves_the_drive_disabled(bench: SimBench) -> None:
    drive = ModbusDrive(_endpoint(bench))
    try:
        drive.set_amplitude(800)
        drive.enable()
        assert drive.state() is DriveState.OPERATION_ENABLED
        drive.set_velocity(5120)
        drive.check()  # running as told
    finally:
        drive.close()
        drive.close()  # twice is harmless
    assert bench.drive.state is DriveState.SWITCH_ON_DISABLED


def test_stored_trims_and_calibration_record_survive_a_power_cycle(tmp_path: Path) -> None:
    record = CalibrationRecord(calibrated_at=1_790_000_000, station_id=7, count=3)
    with _bench(tmp_path, ModbusLink.TCP) as sim, ModbusDrive(_endpoint(sim)) as drive:
        drive.write_trims(Trims(21.0, -4.0, 9900.0, 10100.0))
        drive.write_calibration_record(record)
        drive.store()
        drive.write_trims(NOMINAL_TRIMS)  # held in RAM only
    with _bench(tmp_path, ModbusLink.TCP) as sim, ModbusDrive(_endpoint(sim)) as drive:
        assert drive.read_trims() == Trims(21.0, -4.0, 9900.0, 10100.0)
        assert drive.read_calibration_record() == record


def test_a_silent_drive_is_a_timeout_naming_the_endpoint(tmp_path: Path) -> None:
    with _bench(tmp_path, ModbusLink.TCP) as sim:
        drive = ModbusDrive(_endpoint(sim))
        try:
            assert sim.modbus is not None
            sim.modbus.silence()
            with pytest.raises(DeviceTimeout) as silent:
                drive.read_trims()
            assert "Modbus TCP 127.0.0.1:" in str(silent.value) and "0x0020" in str(silent.value)
        finally:
            drive.close()  # cannot disable a silent drive: logged, not raised


def test_a_drive_that_stopped_by_itself_is_noticed_by_the_keep_alive(tmp_path: Path) -> None:
    with _bench(tmp_path, ModbusLink.TCP) as sim, ModbusDrive(_endpoint(sim)) as drive:
        drive.set_amplitude(1000)
        drive.enable()
        sim.drive.trip(FaultCode.OVERCURRENT)
        deadline = time.monotonic() + 2.0
        with pytest.raises(DeviceStateError, match="left operation enabled"):
            while time.monotonic() < deadline:
                drive.check()
                time.sleep(0.05)
