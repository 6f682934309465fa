"""The simulated drive over Modbus TCP and RTU (ICD.md §4), with pymodbus's own client."""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from canopen.sdo.exceptions import SdoCommunicationError
from pymodbus.exceptions import ModbusIOException

from drivers.base import DriveState, decode_statusword
from drivers.modbus_map import STORE_READS, STORE_WORDS, ModbusLink, Register
from station.sim.bench import SimBench
from station.sim.devices import Obj
from station.sim.modbus import SimModbusServer
from tests.sim import running, unique_config
from tests.sim.modbus_helpers import (
    SILENT_TIMEOUT_S,
    connect,
    exception_code,
    modbus_bench,
    read,
    sync,
    write,
)

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 0x01, 0x02, 0x03, 0x04
TRIMS = [(-12) & 0xFFFF, 34, 10100, 9900]  # offset A is an I16: two's complement on the wire
TRIM_KEYS = [Obj.OFFSET_A, Obj.OFFSET_B, Obj.GAIN_A, Obj.GAIN_B]

LINKS = pytest.mark.parametrize("link", [ModbusLink.TCP, ModbusLink.RTU])


def _words32(value: int) -> list[int]:
    raw = value & 0xFFFF_FFFF
    return [raw >> 16, raw & 0xFFFF]


def _energised(bench: SimBench) -> bool:
    """Whether the plant is given an enabled drive (the command in effect this period)."""
    return bench.drive.command.enabled


def _wait_for(condition: Callable[[], bool], timeout_s: float = 3.0) -> float:
    """Seconds until ``condition()`` held; fails the test if it never does."""
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < timeout_s, "condition never held"
        time.sleep(0.01)
    return time.monotonic() - start


@LINKS
def test_identity_ratings_and_power_on_state_read_as_the_drive_holds_them(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, _):
        unit = bench.unit
        assert read(client, Register.SERIAL_NUMBER, 2) == _words32(unit.serial_number)
        assert read(client, Register.MICROSTEPS) == [unit.microsteps]
        assert read(client, Register.RATED_CURRENT) == [unit.rated_current_mA]
        # 0x0040..0x0043 in one request, as a station reads its identity block.
        assert read(client, Register.SERIAL_NUMBER, 4) == [
            *_words32(unit.serial_number), unit.microsteps, unit.rated_current_mA,
        ]
        assert read(client, Register.STATUSWORD) == [0x0250]  # switch on disabled
        assert read(client, Register.AMPLITUDE) == [unit.rated_current_mA]  # as after a reset
        assert read(client, Register.OFFSET_A, 4) == [0, 0, 10000, 10000]
        assert read(client, Register.STORE, 2) == [0, STORE_READS]
        assert read(client, Register.POSITION_DEMAND, 2) == [0, 0]


@LINKS
def test_the_controlword_sequence_enables_the_drive_and_the_plant_follows_at_sync(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, station):
        for controlword, statusword in ((0x06, 0x0231), (0x07, 0x0233), (0x0F, 0x1637)):
            assert write(client, Register.CONTROLWORD, [controlword]) == 0
            assert read(client, Register.STATUSWORD) == [statusword]
        assert read(client, Register.CONTROLWORD) == [0x0F]
        assert bench.drive.state is DriveState.OPERATION_ENABLED
        assert not _energised(bench)  # held, not yet in effect
        sync(station)
        assert _energised(bench)
        assert write(client, Register.TARGET_VELOCITY, _words32(25_600)) == 0
        assert read(client, Register.TARGET_VELOCITY, 2) == _words32(25_600)
        sync(station, 20)
        assert bench.drive.command.velocity > 0  # what the plant is given
        position = read(client, Register.POSITION_DEMAND, 2)
        assert 0 < (position[0] << 16 | position[1]) == bench.drive.read_object(Obj.POSITION_DEMAND)


def test_a_negative_target_velocity_is_its_int32_high_word_first(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (bench, client, _):
        assert write(client, Register.TARGET_VELOCITY, [0xFFFF, 0x9C00]) == 0
        assert bench.drive.read_object(Obj.TARGET_VELOCITY) == -25_600


@LINKS
def test_trims_written_in_one_request_read_back_and_take_effect_at_the_next_sync(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, station):
        assert write(client, Register.OFFSET_A, TRIMS) == 0
        assert read(client, Register.OFFSET_A, 4) == TRIMS
        assert bench.drive.read_objects(TRIM_KEYS) == [-12, 34, 10100, 9900]
        assert bench.drive.effective_trims == (0, 0, 10000, 10000)
        sync(station)
        assert bench.drive.effective_trims == (-12, 34, 10100, 9900)


@LINKS
def test_an_out_of_range_trim_is_refused_with_0x03_and_no_trim_changes(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, _):
        assert bench.unit.rated_current_mA == 1000  # offsets up to ±500 mA
        assert write(client, Register.OFFSET_A, TRIMS) == 0
        for bad in ([10, 20, 4999, 10000], [501, 0, 10000, 10000], [0, (-501) & 0xFFFF, 10000,
                    10000], [0, 0, 10000, 15001]):
            assert write(client, Register.OFFSET_A, bad) == ILLEGAL_VALUE, bad
            assert read(client, Register.OFFSET_A, 4) == TRIMS
        assert write(client, Register.GAIN_B, [15001]) == ILLEGAL_VALUE
        assert write(client, Register.AMPLITUDE, [1001]) == ILLEGAL_VALUE  # above rated
        assert bench.drive.read_objects(TRIM_KEYS) == [-12, 34, 10100, 9900]


def test_a_write_of_several_values_is_all_or_nothing(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (bench, client, _):
        # Microsteps (valid, applied first) with a rated current below the amplitude held.
        assert write(client, Register.MICROSTEPS, [128, 900]) == ILLEGAL_VALUE
        assert read(client, Register.MICROSTEPS, 2) == [256, 1000]
        assert write(client, Register.MICROSTEPS, [128, 1200]) == 0
        assert read(client, Register.MICROSTEPS, 2) == [128, 1200]
        record = [*_words32(1_700_000_000), 7, 3]
        assert write(client, Register.CALIBRATED_AT, record) == 0
        assert read(client, Register.CALIBRATED_AT, 4) == record
        assert bench.drive.read_object(Obj.MICROSTEPS) == 128


def test_a_value_refused_in_the_present_state_is_answered_with_0x03(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (_, client, _station):
        for controlword in (0x06, 0x07, 0x0F):
            assert write(client, Register.CONTROLWORD, [controlword]) == 0
        # The electrical angle would jump under a running motor (SDO abort 0x08000022).
        assert write(client, Register.MICROSTEPS, [128]) == ILLEGAL_VALUE
        assert read(client, Register.MICROSTEPS) == [256]


@LINKS
def test_addresses_outside_the_map_are_refused_with_0x02(tmp_path: Path, link: ModbusLink) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, _):
        for address, count in ((0x0002, 1), (0x0000, 0x14), (0x0015, 1), (0x0024, 1),
                               (0x0054, 1), (0x0100, 2), (0x0042, 3)):
            answer = client.read_holding_registers(address, count=count, device_id=1)
            assert exception_code(answer) == ILLEGAL_ADDRESS, hex(address)
        assert write(client, Register.OFFSET_A, [*TRIMS, 0]) == ILLEGAL_ADDRESS  # 0x0024
        assert write(client, 0x0024, [1]) == ILLEGAL_ADDRESS
        assert write(client, 0x00FF, [1, 2]) == ILLEGAL_ADDRESS
        assert bench.drive.read_objects(TRIM_KEYS) == [0, 0, 10000, 10000]


@LINKS
def test_writing_a_read_only_register_is_refused_with_0x02(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link) as (bench, client, _):
        assert write(client, Register.STATUSWORD, [0x0F]) == ILLEGAL_ADDRESS
        assert write(client, Register.SERIAL_NUMBER, [0, 5]) == ILLEGAL_ADDRESS
        assert write(client, Register.POSITION_DEMAND, [0, 5]) == ILLEGAL_ADDRESS
        # Target velocity with the position demand after it: the valid part is not applied.
        assert write(client, Register.TARGET_VELOCITY, [0, 100, 0, 5]) == ILLEGAL_ADDRESS
        assert write(client, Register.CONTROLWORD, [0x06, 0]) == ILLEGAL_ADDRESS
        assert bench.drive.read_object(Obj.TARGET_VELOCITY) == 0
        assert bench.drive.state is DriveState.SWITCH_ON_DISABLED
        assert read(client, Register.SERIAL_NUMBER, 2) == _words32(bench.unit.serial_number)


def test_half_a_32_bit_value_may_be_read_but_not_written(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (bench, client, _):
        assert read(client, Register.SERIAL_NUMBER + 1) == [bench.unit.serial_number & 0xFFFF]
        assert write(client, Register.TARGET_VELOCITY, [1]) == ILLEGAL_ADDRESS
        assert write(client, Register.TARGET_VELOCITY + 1, [1]) == ILLEGAL_ADDRESS
        assert write(client, Register.CALIBRATED_AT + 1, [1, 42]) == ILLEGAL_ADDRESS
        assert read(client, Register.CALIBRATED_AT, 4) == [0, 0, 0, 0]


def test_only_function_codes_0x03_0x06_and_0x10_are_served(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (bench, client, _):
        refused = [
            client.read_coils(0, count=1, device_id=1),
            client.read_discrete_inputs(0, count=1, device_id=1),
            client.read_input_registers(Register.SERIAL_NUMBER, count=2, device_id=1),
            client.write_coil(0, True, device_id=1),
            client.mask_write_register(address=Register.OFFSET_A, and_mask=0, or_mask=7,
                                       device_id=1),
            client.readwrite_registers(read_address=0x40, read_count=2, write_address=0x20,
                                       values=[7], device_id=1),
            client.diag_read_diagnostic_register(device_id=1),
        ]
        assert [exception_code(answer) for answer in refused] == [ILLEGAL_FUNCTION] * 7
        assert bench.drive.read_object(Obj.OFFSET_A) == 0
        # A function pymodbus has no decoder for, refused under its own code.
        host, port = bench.modbus.tcp_address if bench.modbus else ("", 0)
        with socket.create_connection((host, port), timeout=2.0) as raw:
            raw.sendall(struct.pack(">HHHBB", 0x1234, 0, 2, 1, 0x41))
            assert raw.recv(64) == struct.pack(">HHHBBB", 0x1234, 0, 3, 1, 0xC1, ILLEGAL_FUNCTION)


def test_store_persists_over_modbus_into_a_new_bench_whatever_its_link(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP, serial="SN42") as (_, client, _station):
        assert write(client, Register.OFFSET_A, TRIMS) == 0
        assert write(client, Register.CALIBRATED_AT, [*_words32(1_700_000_000), 7, 3]) == 0
        assert write(client, Register.STORE, list(STORE_WORDS)) == 0
        assert write(client, Register.OFFSET_A, [99]) == 0  # after the store: lost
    with modbus_bench(tmp_path, ModbusLink.RTU, serial="SN42") as (bench, client, _station):
        assert read(client, Register.OFFSET_A, 4) == TRIMS
        assert read(client, Register.CALIBRATED_AT, 4) == [*_words32(1_700_000_000), 7, 3]
        assert bench.drive.effective_trims == (-12, 34, 10100, 9900)  # loaded at power-on
    with running(tmp_path, serial="SN42") as (_, station):  # the same unit on CANopen
        assert station.drive.sdo[0x2100][1].raw == -12


def test_store_takes_only_the_save_signature_written_whole(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP, serial="SN43") as (bench, client, _):
        assert write(client, Register.STORE, [STORE_WORDS[0], 0]) == ILLEGAL_VALUE
        assert write(client, Register.STORE, [0x6173, 0x7665]) == ILLEGAL_VALUE  # "asve"
        assert write(client, Register.STORE, [STORE_WORDS[0]]) == ILLEGAL_ADDRESS  # half
        assert not bench.drive.eeprom.path.exists()


def test_an_eeprom_failure_is_answered_with_0x04(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP, serial="SN44") as (bench, client, _):

        def failing_replace(src: str, dst: str) -> None:
            raise OSError("EEPROM write failed")

        monkeypatch.setattr(os, "replace", failing_replace)
        assert write(client, Register.STORE, list(STORE_WORDS)) == DEVICE_FAILURE
        assert not bench.drive.eeprom.path.exists()


@LINKS
def test_a_silenced_drive_answers_nothing_and_hears_nothing_until_it_speaks(
    tmp_path: Path, link: ModbusLink
) -> None:
    with modbus_bench(tmp_path, link, timeout_s=SILENT_TIMEOUT_S) as (bench, client, _):
        server = bench.modbus
        assert server is not None
        server.silence()
        assert server.silent
        with pytest.raises(ModbusIOException):
            client.read_holding_registers(Register.STATUSWORD, count=1, device_id=1)
        with pytest.raises(ModbusIOException):
            client.write_registers(Register.OFFSET_A, TRIMS, device_id=1)
        server.speak()
        assert read(client, Register.OFFSET_A, 4) == [0, 0, 10000, 10000]  # never heard


def test_requests_for_another_unit_go_unanswered(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.RTU, timeout_s=SILENT_TIMEOUT_S,
                      modbus_unit=7) as (bench, client, _):
        with pytest.raises(ModbusIOException):
            client.read_holding_registers(Register.STATUSWORD, count=1, device_id=1)
        assert read(client, Register.SERIAL_NUMBER, 2, unit=7) == _words32(
            bench.unit.serial_number)


def test_the_watchdog_disables_an_enabled_drive_whose_master_fell_silent(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    watchdog_s = 0.3
    with modbus_bench(tmp_path, ModbusLink.TCP, modbus_watchdog_s=watchdog_s) as (
        bench, client, station
    ):
        for controlword in (0x06, 0x07, 0x0F):
            assert write(client, Register.CONTROLWORD, [controlword]) == 0
        assert write(client, Register.TARGET_VELOCITY, _words32(1000)) == 0
        sync(station, 3)
        assert _energised(bench)
        assert bench.modbus is not None
        with caplog.at_level(logging.WARNING, logger="station.sim.modbus"):
            # The last request it hears; running (accelerating), so no "target reached".
            (statusword,) = read(client, Register.STATUSWORD)
            assert decode_statusword(statusword) is DriveState.OPERATION_ENABLED
            bench.modbus.silence()
            # No SYNC meanwhile: the watchdog runs on wall-clock time.
            waited = _wait_for(lambda: bench.drive.state is DriveState.SWITCH_ON_DISABLED)
        assert waited >= watchdog_s * 0.8
        assert "watchdog" in caplog.text
        bench.modbus.speak()
        assert read(client, Register.STATUSWORD) == [0x0250]
        assert read(client, Register.TARGET_VELOCITY, 2) == [0, 0]
        sync(station)
        assert not _energised(bench)  # and the plant stops being driven
        # The master enables it again explicitly.
        for controlword in (0x06, 0x07, 0x0F):
            assert write(client, Register.CONTROLWORD, [controlword]) == 0
        assert read(client, Register.STATUSWORD) == [0x1637]


def test_polling_keeps_the_watchdog_from_firing_and_zero_disables_it(tmp_path: Path) -> None:
    for watchdog_s, poll_s in ((0.3, 0.05), (0.0, 0.6)):
        with modbus_bench(tmp_path, ModbusLink.TCP, modbus_watchdog_s=watchdog_s) as (
            bench, client, _
        ):
            for controlword in (0x06, 0x07, 0x0F):
                assert write(client, Register.CONTROLWORD, [controlword]) == 0
            deadline = time.monotonic() + 0.6  # twice the watchdog time
            while time.monotonic() < deadline:
                assert read(client, Register.STATUSWORD) == [0x1637], watchdog_s
                time.sleep(poll_s)
            assert bench.drive.state is DriveState.OPERATION_ENABLED


def test_a_modbus_drive_is_not_on_the_can_bus_but_runs_at_each_sync(tmp_path: Path) -> None:
    with modbus_bench(tmp_path, ModbusLink.TCP) as (bench, _, station):
        drive_node = station.config.drive_node
        station.drive.sdo.RESPONSE_TIMEOUT = 0.1
        with pytest.raises(SdoCommunicationError):
            station.drive.sdo.upload(0x1000, 0)
        station.nmt(0x01)  # start all: only the sensor is there to start
        station.sensor.sdo.upload(0x1000, 0)
        since = len(station.keeper.frames)
        answers = [station.sync(expect=1) for _ in range(5)]
        assert [[frame.cob_id for frame in frames] for frames in answers] == [[0x190]] * 5
        time.sleep(0.25)  # more than a heartbeat period (100 ms)
        from_drive = [f for f in station.keeper.frames if f.cob_id & 0x7F == drive_node]
        assert from_drive == []
        assert 0x710 in {f.cob_id for f in station.keeper.frames[since:]}  # sensor heartbeat
        assert bench.sync_count == 5


@LINKS
def test_close_joins_its_threads_and_releases_every_descriptor_even_with_a_client_on(
    tmp_path: Path, link: ModbusLink
) -> None:
    bench = SimBench(unique_config(), state_dir=tmp_path)  # never started: only its drive
    bench.drive.boot_standalone()
    threads_before = set(threading.enumerate())
    fds_before = sorted(os.listdir("/proc/self/fd"))
    server = SimModbusServer(bench.drive, link, watchdog_s=0.5)
    server.start()
    client = connect(server)
    assert read(client, Register.STATUSWORD) == [0x0250]
    server.close()
    server.close()
    client.close()  # type: ignore[no-untyped-call]
    assert sorted(os.listdir("/proc/self/fd")) == fds_before
    assert [t.name for t in threading.enumerate() if t not in threads_before] == []
    with pytest.raises(RuntimeError, match="closed"):
        server.start()
    with pytest.raises(RuntimeError, match="closed"):
        _ = server.tcp_address if link is ModbusLink.TCP else server.serial_port


def test_a_unit_id_outside_1_to_247_or_a_negative_watchdog_is_refused(tmp_path: Path) -> None:
    bench = SimBench(unique_config(), state_dir=tmp_path)
    for unit in (0, 248):
        with pytest.raises(ValueError, match="unit ID"):
            SimModbusServer(bench.drive, ModbusLink.TCP, unit=unit)
    with pytest.raises(ValueError, match="negative"):
        SimModbusServer(bench.drive, ModbusLink.TCP, watchdog_s=-1.0)
