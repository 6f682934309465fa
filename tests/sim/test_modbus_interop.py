"""The simulated Modbus drive against mbpoll, a Modbus master this project did not write.

pymodbus is on both sides of the other tests, so a framing or word-order mistake
shared by its client and server would go unseen there; mbpoll (libmodbus) reads
ICD.md §4 with its own code. These tests fail, not skip, without it: CI installs
it (.ci/run), and so must a developer.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.modbus_map import RTU_BAUDRATE, ModbusLink, Register
from station.sim.bench import SimBench
from station.sim.devices import Obj
from tests.sim import unique_config

_VALUE_LINE = re.compile(r"^\[(\d+)\]:\s+(-?\d+)\s*$", re.MULTILINE)
_RUN_TIMEOUT_S = 20.0
TRIM_KEYS = [Obj.OFFSET_A, Obj.OFFSET_B, Obj.GAIN_A, Obj.GAIN_B]


@pytest.fixture(scope="module")
def mbpoll() -> str:
    path = shutil.which("mbpoll")
    if path is None:
        pytest.fail("mbpoll is not installed; the Modbus interoperability tests need it: "
                    "apt-get install -y mbpoll")
    return path


@pytest.fixture
def tcp_bench(tmp_path: Path) -> Iterator[SimBench]:
    with SimBench(unique_config(drive_link=ModbusLink.TCP), state_dir=tmp_path) as bench:
        yield bench


def _run(mbpoll: str, *args: str) -> subprocess.CompletedProcess[str]:
    # -0: addresses are PDU addresses (as ICD.md §4 writes them); -1: one poll, then exit.
    return subprocess.run([mbpoll, "-a", "1", "-0", "-1", *args], capture_output=True,
                          text=True, timeout=_RUN_TIMEOUT_S, check=False)


def _tcp(
    mbpoll: str, bench: SimBench, *options: str, write: tuple[int, ...] = ()
) -> subprocess.CompletedProcess[str]:
    """mbpoll over TCP: options, then the host, then the values to write if any."""
    assert bench.modbus is not None
    host, port = bench.modbus.tcp_address
    # "--" lets a negative value through as a value rather than an option.
    values = ["--", *map(str, write)] if write else []
    return _run(mbpoll, "-m", "tcp", "-p", str(port), *options, host, *values)


def _values(result: subprocess.CompletedProcess[str]) -> dict[int, int]:
    """What mbpoll printed, by reference: ``[64]:  123``."""
    assert result.returncode == 0, result.stderr
    return {int(ref): int(value) for ref, value in _VALUE_LINE.findall(result.stdout)}


def test_mbpoll_reads_the_serial_number_high_word_first_and_the_trims(
    mbpoll: str, tcp_bench: SimBench
) -> None:
    serial = _tcp(mbpoll, tcp_bench, "-r", str(Register.SERIAL_NUMBER), "-c", "1",
                  "-t", "4:int", "-B")
    assert _values(serial) == {Register.SERIAL_NUMBER: tcp_bench.unit.serial_number}
    trims = _tcp(mbpoll, tcp_bench, "-r", str(Register.OFFSET_A), "-c", "4", "-t", "4")
    assert _values(trims) == {0x20: 0, 0x21: 0, 0x22: 10000, 0x23: 10000}


def test_mbpoll_writes_trims_and_32_bit_values_that_the_drive_then_holds(
    mbpoll: str, tcp_bench: SimBench
) -> None:
    # mbpoll's 16-bit registers are unsigned: -12 goes as its two's complement.
    trims = _tcp(mbpoll, tcp_bench, "-r", str(Register.OFFSET_A), "-t", "4",
                 write=(65524, 34, 10100, 9900))
    assert trims.returncode == 0, trims.stderr
    assert tcp_bench.drive.read_objects(TRIM_KEYS) == [-12, 34, 10100, 9900]
    velocity = _tcp(mbpoll, tcp_bench, "-r", str(Register.TARGET_VELOCITY), "-t", "4:int",
                    "-B", write=(-25600,))
    assert velocity.returncode == 0, velocity.stderr
    assert tcp_bench.drive.read_object(Obj.TARGET_VELOCITY) == -25600
    read_back = _tcp(mbpoll, tcp_bench, "-r", str(Register.TARGET_VELOCITY), "-c", "1",
                     "-t", "4:int", "-B")
    assert _values(read_back) == {Register.TARGET_VELOCITY: -25600}


def test_mbpoll_reports_the_exception_for_an_out_of_range_value_and_nothing_changes(
    mbpoll: str, tcp_bench: SimBench
) -> None:
    refused = _tcp(mbpoll, tcp_bench, "-r", str(Register.GAIN_A), "-t", "4", write=(4999,))
    assert refused.returncode != 0
    assert "illegal data value" in refused.stderr.lower()
    block = _tcp(mbpoll, tcp_bench, "-r", str(Register.OFFSET_A), "-t", "4",
                 write=(10, 20, 10100, 15001))
    assert block.returncode != 0
    assert "illegal data value" in block.stderr.lower()
    unknown = _tcp(mbpoll, tcp_bench, "-r", "2", "-c", "1", "-t", "4")
    assert "illegal data address" in (unknown.stdout + unknown.stderr).lower()
    assert tcp_bench.drive.read_objects(TRIM_KEYS) == [0, 0, 10000, 10000]


def test_mbpoll_reads_the_serial_number_over_rtu(mbpoll: str, tmp_path: Path) -> None:
    config = unique_config(drive_link=ModbusLink.RTU)
    with SimBench(config, state_dir=tmp_path) as bench:
        assert bench.modbus is not None
        # libmodbus sets up the port once, so it may ask for 8E1 even on a pty.
        result = _run(mbpoll, "-m", "rtu", "-b", str(RTU_BAUDRATE), "-P", "even",
                      "-r", str(Register.SERIAL_NUMBER), "-c", "1", "-t", "4:int", "-B",
                      bench.modbus.serial_port)
        assert _values(result) == {Register.SERIAL_NUMBER: bench.unit.serial_number}
