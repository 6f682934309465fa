"""The station side for testing the simulated Modbus drive: pymodbus's own client.

Deliberately not the station's driver (drivers.modbus_drive): the simulator is
checked against a client neither side wrote, plus mbpoll in the interop tests.
SYNCs still come from the CAN station of tests.sim, since the drive's cycle runs
at each SYNC whatever the transport.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.pdu import ModbusPDU

from drivers.modbus_map import PTY_PARITY, RTU_BAUDRATE, ModbusLink
from station.sim.bench import SimBench
from station.sim.modbus import SimModbusServer
from tests.sim import Station, unique_config

Client = ModbusTcpClient | ModbusSerialClient

TIMEOUT_S = 1.0
SILENT_TIMEOUT_S = 0.3
"""How long a test waits for an answer that must not come."""


def connect(server: SimModbusServer, *, timeout_s: float = TIMEOUT_S) -> Client:
    """A connected pymodbus client for ``server``'s link, without retries."""
    client: Client
    if server.link is ModbusLink.TCP:
        host, port = server.tcp_address
        client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
    else:
        client = ModbusSerialClient(
            server.serial_port,
            baudrate=RTU_BAUDRATE,
            parity=PTY_PARITY,
            bytesize=8,
            stopbits=1,
            timeout=timeout_s,
            retries=0,
        )
    assert client.connect(), f"cannot connect to the simulated drive over {server.link}"
    return client


@contextmanager
def modbus_bench(
    state_dir: Path, link: ModbusLink, *, timeout_s: float = TIMEOUT_S, **changes: object
) -> Iterator[tuple[SimBench, Client, Station]]:
    """A started bench whose drive speaks Modbus, a client of it, and a SYNC producer."""
    with SimBench(unique_config(drive_link=link, **changes), state_dir=state_dir) as bench:
        assert bench.modbus is not None
        station = Station(bench)
        try:
            client = connect(bench.modbus, timeout_s=timeout_s)
            try:
                yield bench, client, station
            finally:
                client.close()  # type: ignore[no-untyped-call]
        finally:
            station.close()


def exception_code(response: ModbusPDU) -> int:
    """The Modbus exception code of an answer (0 when it is not an exception)."""
    return int(response.exception_code) if response.isError() else 0


def read(client: Client, address: int, count: int = 1, *, unit: int = 1) -> list[int]:
    response = client.read_holding_registers(address, count=count, device_id=unit)
    assert not response.isError(), f"read 0x{address:04X}+{count}: {response}"
    return list(response.registers)


def write(client: Client, address: int, words: list[int], *, unit: int = 1) -> int:
    """Write ``words`` as a station would (0x06 for one, 0x10 for more); the exception
    code of the answer, 0 if it was accepted."""
    if len(words) == 1:
        return exception_code(client.write_register(address, words[0], device_id=unit))
    return exception_code(client.write_registers(address, words, device_id=unit))


def sync(station: Station, cycles: int = 1) -> None:
    """SYNCs on the virtual bus; only the sensor answers, and only once started."""
    for _ in range(cycles):
        station.sync(expect=0)
