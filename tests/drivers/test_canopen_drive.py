"""The CANopen drive driver against the simulated bench on the virtual bus."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import canopen
import pytest

from drivers.base import CalibrationRecord, DriveState
from drivers.canbus import BusConfig, open_network
from drivers.canopen_drive import CanopenDrive
from drivers.eds import DeviceKind, load_od
from station.core import NOMINAL_TRIMS, Trims
from station.errors import (
    DeviceError,
    DeviceStateError,
    DeviceTimeout,
    InputError,
    SdoAbort,
)
from station.serials import label_for
from station.sim.bench import SimBench
from station.sim.devices import FaultCode

VALUE_RANGE_EXCEEDED = 0x06090030


@pytest.fixture
def drive(network: canopen.Network) -> Iterator[CanopenDrive]:
    with CanopenDrive(network) as opened:
        assert isinstance(opened, CanopenDrive)
        yield opened


def test_identity_reports_the_serial_number_printed_on_the_unit(drive: CanopenDrive) -> None:
    identity = drive.identity()
    assert identity.serial_number == 123
    assert label_for(identity.serial_number) == "SN123"


def test_ratings_follow_the_icd_defaults(drive: CanopenDrive) -> None:
    assert drive.rated_current_mA() == 1000
    assert drive.microsteps_per_fullstep() == 256


def test_enable_reaches_operation_enabled_and_disable_switch_on_disabled(
    drive: CanopenDrive,
) -> None:
    assert drive.state() is DriveState.SWITCH_ON_DISABLED
    drive.enable()
    assert drive.state() is DriveState.OPERATION_ENABLED
    drive.enable()  # already enabled: nothing to do, nothing breaks
    assert drive.state() is DriveState.OPERATION_ENABLED
    drive.disable()
    assert drive.state() is DriveState.SWITCH_ON_DISABLED
    drive.disable()
    assert drive.state() is DriveState.SWITCH_ON_DISABLED


def test_context_exit_leaves_the_drive_disabled_even_after_an_exception(
    network: canopen.Network,
) -> None:
    with pytest.raises(RuntimeError, match="procedure failed"), CanopenDrive(network) as drive:
        drive.enable()
        drive.set_velocity(2000)
        raise RuntimeError("procedure failed")
    # The node was detached on close, so a fresh driver can look at the unit.
    with CanopenDrive(network) as again:
        assert again.state() is DriveState.SWITCH_ON_DISABLED


def test_close_twice_is_harmless_and_detaches_the_node(network: canopen.Network) -> None:
    drive = CanopenDrive(network)
    drive.close()
    drive.close()
    assert 1 not in network.nodes


def test_a_second_driver_for_the_same_node_is_refused(
    drive: CanopenDrive, network: canopen.Network
) -> None:
    with pytest.raises(DeviceError, match="already attached"):
        CanopenDrive(network)


def test_trims_written_are_read_back_rounded(drive: CanopenDrive) -> None:
    drive.write_trims(Trims(12.4, -7.6, 10123.5, 9876.2))
    assert drive.read_trims() == Trims(12.0, -8.0, 10124.0, 9876.0)


def test_out_of_range_offset_is_refused_with_abort_0x06090030(drive: CanopenDrive) -> None:
    before = drive.read_trims()
    with pytest.raises(SdoAbort) as raised:
        drive.write_trims(Trims(501.0, 0.0, 10000.0, 10000.0))
    assert raised.value.code == VALUE_RANGE_EXCEEDED
    assert (raised.value.index, raised.value.subindex) == (0x2100, 1)
    assert raised.value.device == "drive"
    assert drive.read_trims() == before


def test_refused_last_trim_rolls_back_the_ones_already_written(drive: CanopenDrive) -> None:
    drive.write_trims(Trims(5.0, 6.0, 10100.0, 10200.0))
    with pytest.raises(SdoAbort) as raised:
        drive.write_trims(Trims(-20.0, 30.0, 9000.0, 15001.0))
    assert (raised.value.subindex, raised.value.code) == (4, VALUE_RANGE_EXCEEDED)
    assert drive.read_trims() == Trims(5.0, 6.0, 10100.0, 10200.0)


def test_trims_the_data_type_cannot_hold_are_refused_before_bus_traffic(
    drive: CanopenDrive,
) -> None:
    before = drive.read_trims()
    with pytest.raises(InputError):
        drive.write_trims(Trims(40000.0, 0.0, 10000.0, 10000.0))
    with pytest.raises(InputError):
        drive.write_trims(Trims(float("nan"), 0.0, 10000.0, 10000.0))
    assert drive.read_trims() == before


def test_store_and_reset_keep_stored_trims_and_drop_unstored_ones(drive: CanopenDrive) -> None:
    stored = Trims(15.0, -25.0, 10250.0, 9800.0)
    drive.write_trims(stored)
    drive.store()
    drive.write_trims(Trims(-3.0, 4.0, 9500.0, 10500.0))
    drive.reset()
    assert drive.read_trims() == stored
    assert drive.state() is DriveState.SWITCH_ON_DISABLED
    drive.enable()  # back in OPERATIONAL and usable after the reset
    assert drive.state() is DriveState.OPERATION_ENABLED


def test_reset_without_store_restores_the_factory_trims(drive: CanopenDrive) -> None:
    drive.write_trims(Trims(40.0, 40.0, 11000.0, 11000.0))
    drive.reset()
    assert drive.read_trims() == NOMINAL_TRIMS


def test_calibration_record_round_trip(drive: CanopenDrive) -> None:
    assert drive.read_calibration_record() == CalibrationRecord(0, 0, 0)
    record = CalibrationRecord(calibrated_at=1_763_726_400, station_id=7, count=3)
    drive.write_calibration_record(record)
    assert drive.read_calibration_record() == record
    with pytest.raises(InputError):
        drive.write_calibration_record(CalibrationRecord(-1, 7, 3))
    assert drive.read_calibration_record() == record


def test_heartbeat_shows_the_drive_alive(drive: CanopenDrive) -> None:
    age = drive.heartbeat_age_s()
    assert age is not None and age < 0.5
    drive.check_alive(max_age_s=0.5)


def test_amplitude_above_rated_current_is_refused_by_the_drive(drive: CanopenDrive) -> None:
    drive.set_amplitude(800)
    with pytest.raises(SdoAbort) as raised:
        drive.set_amplitude(1001)
    assert raised.value.code == VALUE_RANGE_EXCEEDED


def test_missing_device_times_out_and_close_does_not_raise(
    bench: SimBench, network: canopen.Network
) -> None:
    drive = CanopenDrive(network, sdo_timeout_s=0.05)
    bench.close()
    with pytest.raises(DeviceTimeout) as raised:
        drive.identity()
    assert raised.value.device == "drive"
    with pytest.raises(DeviceTimeout):
        drive.check_alive(max_age_s=0.0)
    drive.close()
    drive.close()


def test_no_device_at_the_node_id_fails_construction_and_leaves_nothing_attached(
    network: canopen.Network,
) -> None:
    with pytest.raises(DeviceTimeout):
        CanopenDrive(network, node_id=5, sdo_timeout_s=0.05)
    assert 5 not in network.nodes


def test_node_id_outside_cia301_range_is_refused(network: canopen.Network) -> None:
    with pytest.raises(InputError):
        CanopenDrive(network, node_id=128)


def test_enable_resets_a_fault_and_disable_accepts_a_faulted_drive(
    bench: SimBench, drive: CanopenDrive
) -> None:
    drive.enable()
    bench.drive.trip(FaultCode.OVERCURRENT)
    assert drive.state() is DriveState.FAULT
    drive.disable()  # a faulted drive is already de-energised
    assert drive.state() is DriveState.FAULT
    drive.enable()
    assert drive.state() is DriveState.OPERATION_ENABLED


def test_a_transition_that_does_not_happen_raises_device_state_error() -> None:
    # A bare LocalNode from the drive EDS answers SDOs but its statusword never moves.
    channel = f"test-stuck-{uuid.uuid4().hex}"
    with (
        open_network(BusConfig(channel=channel)) as device_side,
        open_network(BusConfig(channel=channel)) as network,
    ):
        stuck = device_side.create_node(1, load_od(DeviceKind.DRIVE, 1))
        stuck.nmt.send_command(0x80)  # boot into PRE-OPERATIONAL: heartbeats start
        # (closing its bus stops the heartbeat task)
        with CanopenDrive(network, state_timeout_s=0.05) as drive:
            with pytest.raises(DeviceStateError, match="shutdown from switch on disabled"):
                drive.enable()
            controlword = stuck.sdo.get_variable(0x6040)
            assert controlword is not None and controlword.raw == 0x0006
