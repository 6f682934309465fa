"""The simulated drive reached over Modbus TCP or RTU (ICD.md §4) instead of CANopen.

The registers are a facade over the very ``SimDrive`` the CANopen bench uses:
every read is an object read and every write goes through ``write_objects``,
so the range checks, the CiA 402 state machine, the EEPROM and the plant are the
drive's own, and a write takes effect at the next SYNC exactly as an SDO write
does. Nothing is cached between requests.

pymodbus's server does the framing, in an event loop on a thread of its own.
Its hooks decide what the drive hears: ``trace_pdu`` drops requests for other
units and every request while the drive is silenced (the client times out, as
with a cut cable), and answers function codes other than 0x03, 0x06 and 0x10
with exception 0x01 before they reach the registers. A watchdog thread disables
a drive left in OPERATION ENABLED by a master that stopped polling, in wall-clock
time, whether or not anyone sends SYNC.

RTU runs over two pseudo-terminals joined by an in-process relay (as ``socat``
would), so that a client opens an ordinary serial-port path; TCP listens on an
ephemeral loopback port. No frame leaves the machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from functools import cache
from types import TracebackType
from typing import Final, cast

from canopen.sdo.exceptions import SdoAbortedError
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.framer import FramerType
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.modbus_map import (
    DEFAULT_UNIT_ID,
    FIELDS,
    PTY_PARITY,
    RTU_BAUDRATE,
    Field,
    ModbusExceptionCode,
    ModbusFunction,
    ModbusLink,
    Register,
    field_at,
    store_value,
)
from station.cia301 import AbortCode, Signature
from station.sim.devices import SimDrive

_log = logging.getLogger(__name__)

DEFAULT_WATCHDOG_S: Final = 2.0
"""How long an enabled drive runs without hearing its master (0 disables the watchdog)."""

LOOPBACK: Final = "127.0.0.1"

_UNITS: Final = range(1, 248)
"""Modbus serial line: 0 is broadcast, 248..255 are reserved."""

_REGISTER_SPAN: Final = max(field.stop for field in FIELDS.values())
_FUNCTIONS: Final = frozenset(int(function) for function in ModbusFunction)
_FUNCTION_CODES: Final = range(1, 0x80)  # 0x80 and up mark exception responses
_START_TIMEOUT_S: Final = 10.0
_JOIN_TIMEOUT_S: Final = 10.0
_WATCHDOG_TICK_S: Final = 0.05
_RELAY_CHUNK: Final = 4096
_SERIAL_BITS: Final = 8
_STOP_BITS: Final = 1

_EXCEPTION_FOR_ABORT: Final[Mapping[int, ModbusExceptionCode]] = {
    AbortCode.VALUE_RANGE: ModbusExceptionCode.ILLEGAL_DATA_VALUE,
    # Allowed values, not allowed now (microsteps under a running motor): still a value
    # the drive refuses, and ICD.md §4 names one exception for refused values.
    AbortCode.DEVICE_STATE: ModbusExceptionCode.ILLEGAL_DATA_VALUE,
    AbortCode.READ_ONLY: ModbusExceptionCode.ILLEGAL_DATA_ADDRESS,
    # The signature is checked before the drive sees it: what is left is the EEPROM.
    AbortCode.CANNOT_STORE: ModbusExceptionCode.SERVER_DEVICE_FAILURE,
}


def _exception_for(abort: SdoAbortedError) -> ModbusExceptionCode:
    return _EXCEPTION_FOR_ABORT.get(int(abort.code), ModbusExceptionCode.SERVER_DEVICE_FAILURE)


# --- The register map over the drive's objects ---------------------------------------------

@dataclass(frozen=True)
class _Span:
    """The part of one value a request touches."""

    field: Field
    first: int  # first word of the value touched
    count: int  # words of it touched

    @property
    def whole(self) -> bool:
        return self.first == 0 and self.count == self.field.words


def _spans(address: int, count: int) -> list[_Span] | None:
    """The values registers ``address``.. ``address + count - 1`` belong to; None if
    any of them is not in the map."""
    spans: list[_Span] = []
    at, end = address, address + count
    while at < end:
        found = field_at(at)
        if found is None:
            return None
        field, word = found
        touched = min(field.words - word, end - at)
        spans.append(_Span(field, word, touched))
        at += touched
    return spans


class DriveRegisters:
    """ICD.md §4's holding registers, read from and written to a drive's objects.

    Independent of pymodbus, so the map's semantics can be tested and read in one
    place: each access answers words, None (written) or the exception code.
    """

    def __init__(self, drive: SimDrive) -> None:
        self._drive = drive

    def read(self, address: int, count: int) -> list[int] | ModbusExceptionCode:
        """Registers from one instant of the drive; part of a 32-bit value may be read."""
        spans = _spans(address, count)
        if spans is None:
            return ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
        try:
            values = self._drive.read_objects([span.field.canopen for span in spans])
        except SdoAbortedError as exc:
            return _exception_for(exc)
        words: list[int] = []
        for span, value in zip(spans, values, strict=True):
            try:
                encoded = span.field.encode(value)
            except ValueError as exc:
                # The object holds more than its register can carry (a U32 in a U16).
                _log.error("Modbus register 0x%04X: %s", span.field.register, exc)
                return ModbusExceptionCode.SERVER_DEVICE_FAILURE
            words += encoded[span.first : span.first + span.count]
        return words

    def write(self, address: int, words: Sequence[int]) -> ModbusExceptionCode | None:
        """All the values the words make up, or none of them.

        Every register must be in the map, writable, and 32-bit values written
        whole (half of one would be a value nobody meant); then the drive checks
        each value as an SDO write and refuses the lot if it refuses one.
        """
        spans = _spans(address, len(words))
        if spans is None or not all(span.whole and span.field.writable for span in spans):
            return ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
        writes: list[tuple[tuple[int, int], int]] = []
        at = 0
        for span in spans:
            field = span.field
            value = field.decode(list(words[at : at + field.words]))
            at += field.words
            if field.register is Register.STORE:
                # "save" in Modbus's byte order; the drive's object takes CiA 301's.
                if value != store_value():
                    return ModbusExceptionCode.ILLEGAL_DATA_VALUE
                value = Signature.SAVE
            writes.append((field.canopen, value))
        try:
            self._drive.write_objects(writes)
        except SdoAbortedError as exc:
            _log.debug("Modbus write at 0x%04X refused: %s", address, exc)
            return _exception_for(exc)
        return None


# --- pymodbus hooks --------------------------------------------------------------------------

class _Unanswered(ModbusPDU):
    """A request the drive does not hear: pymodbus answers nothing for a missing device."""

    def __init__(self, request: ModbusPDU) -> None:
        super().__init__(dev_id=request.dev_id, transaction_id=request.transaction_id)
        self.function_code = request.function_code

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        raise NoSuchIdException(f"unit {device_id} does not hear this request")


class _Refused(ModbusPDU):
    """A request answered with an exception before it reaches the registers."""

    def __init__(self, request: ModbusPDU, code: ExcCodes) -> None:
        super().__init__(dev_id=request.dev_id, transaction_id=request.transaction_id)
        self.function_code = request.function_code
        self._code = code

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        return ExceptionResponse(self.function_code, self._code)


class _OtherRequest(ModbusPDU):
    """A function pymodbus does not know, so that it is refused with 0x01 under its own code
    (pymodbus would answer function 0x00). TCP only: the MBAP header gives its length,
    whereas an RTU frame of an unknown function has no length to find its end by."""

    def decode(self, data: bytes) -> None:
        """Nothing to decode: the request is refused whatever it carries."""


@cache
def _other_requests() -> tuple[type[ModbusPDU], ...]:
    known = set(DecodePDU.pdu_table)
    return tuple(
        cast(type[ModbusPDU],
             type(f"_Function{code:02X}", (_OtherRequest,), {"function_code": code}))
        for code in _FUNCTION_CODES
        if code not in known
    )


# --- RTU over pseudo-terminals -------------------------------------------------------------

class _PtyRelay:
    """A null-modem cable between two pseudo-terminals (what ``socat pty pty`` makes).

    The server opens one pty, a client the other; a thread copies bytes between
    their masters. The relay keeps both slave ends open itself, so that a client
    may come and go without the master hanging up (EIO), and makes them raw at
    once: an echoing line discipline would bounce every frame straight back.
    """

    def __init__(self) -> None:
        self._fds: list[int] = []
        try:
            server_master, server_slave = self._open_pty()
            client_master, client_slave = self._open_pty()
            self._wake_read, self._wake_write = os.pipe()
            self._fds += [self._wake_read, self._wake_write]
        except BaseException:
            self._close_fds()
            raise
        self.server_port = os.ttyname(server_slave)
        self.client_port = os.ttyname(client_slave)
        self._peer = {server_master: client_master, client_master: server_master}
        self._thread = threading.Thread(target=self._run, name="modbus-sim-pty-relay")

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        if self._thread.is_alive():
            os.write(self._wake_write, b"\0")
            self._thread.join(_JOIN_TIMEOUT_S)
        self._close_fds()

    def _open_pty(self) -> tuple[int, int]:
        master, slave = os.openpty()
        self._fds += [master, slave]
        tty.setraw(slave)
        os.set_blocking(master, False)
        return master, slave

    def _close_fds(self) -> None:
        fds, self._fds = self._fds, []
        for fd in fds:
            os.close(fd)

    def _run(self) -> None:
        watched = [*self._peer, self._wake_read]
        while True:
            ready, _, _ = select.select(watched, [], [])
            if self._wake_read in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, _RELAY_CHUNK)
                except BlockingIOError:
                    continue
                self._forward(self._peer[fd], data)

    @staticmethod
    def _forward(fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(fd, view)
            except BlockingIOError:
                # Nobody reads that end: the bytes are lost, as on an unplugged line.
                return
            view = view[written:]


# --- The server ------------------------------------------------------------------------------

class _Lifecycle(Enum):
    NEW = "new"
    RUNNING = "running"
    CLOSED = "closed"


class SimModbusServer:
    """One simulated drive answering Modbus requests as unit ``unit``.

    ``start`` (or entering the context) opens the link; ``close`` stops every
    thread it started and releases every socket and file descriptor, and may be
    called twice. ``silence``/``speak`` cut and restore the cable.
    """

    def __init__(
        self,
        drive: SimDrive,
        link: ModbusLink,
        *,
        unit: int = DEFAULT_UNIT_ID,
        watchdog_s: float = DEFAULT_WATCHDOG_S,
    ) -> None:
        if unit not in _UNITS:
            raise ValueError(f"Modbus unit ID {unit} is not a device address (1..247)")
        if watchdog_s < 0:
            raise ValueError(f"watchdog time {watchdog_s} s is negative")
        self.drive = drive
        self.link = link
        self.unit = unit
        self.watchdog_s = watchdog_s
        self._registers = DriveRegisters(drive)
        self._lifecycle = _Lifecycle.NEW
        self._silent = threading.Event()
        self._drop_lock = threading.Lock()
        self._requests_to_drop = 0
        self._on_dropped: Callable[[], None] | None = None
        self._closing = threading.Event()
        self._ready = threading.Event()
        self._last_heard = time.monotonic()
        self._threads: list[threading.Thread] = []
        self._relay: _PtyRelay | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._failure: BaseException | None = None
        self._tcp_address: tuple[str, int] | None = None

    # Public ---------------------------------------------------------------------------------

    @property
    def tcp_address(self) -> tuple[str, int]:
        """Where a Modbus TCP client connects (the port is chosen by the system)."""
        if self._tcp_address is None or self._lifecycle is not _Lifecycle.RUNNING:
            raise RuntimeError(f"no TCP address: the link is {self.link.value}, "
                               f"the server {self._lifecycle.value}")
        return self._tcp_address

    @property
    def serial_port(self) -> str:
        """The serial-port path a Modbus RTU client opens (a pseudo-terminal)."""
        if self._relay is None or self._lifecycle is not _Lifecycle.RUNNING:
            raise RuntimeError(f"no serial port: the link is {self.link.value}, "
                               f"the server {self._lifecycle.value}")
        return self._relay.client_port

    @property
    def silent(self) -> bool:
        return self._silent.is_set()

    def silence(self) -> None:
        """The drive stops hearing requests and answers none (a cut cable)."""
        self._silent.set()

    def speak(self) -> None:
        """Undo ``silence``."""
        self._silent.clear()

    def drop_requests(self, count: int, on_dropped: Callable[[], None] | None = None) -> None:
        """Leave the next ``count`` requests unanswered (noise on the line, a busy drive)."""
        with self._drop_lock:
            self._requests_to_drop += count
            self._on_dropped = on_dropped

    def start(self) -> None:
        """Open the link and serve; returns once clients can connect. No-op when running."""
        if self._lifecycle is _Lifecycle.CLOSED:
            raise RuntimeError("a closed Modbus server cannot be started again")
        if self._lifecycle is _Lifecycle.RUNNING:
            return
        self._lifecycle = _Lifecycle.RUNNING
        try:
            if self.link is ModbusLink.RTU:
                self._relay = _PtyRelay()
                self._relay.start()
            self._last_heard = time.monotonic()
            self._spawn(self._run_loop, "server")
            if not self._ready.wait(_START_TIMEOUT_S):
                raise RuntimeError(f"the Modbus {self.link.value} server did not start "
                                   f"within {_START_TIMEOUT_S} s")
            if self._failure is not None:
                raise RuntimeError(f"the Modbus {self.link.value} server did not start: "
                                   f"{self._failure}") from self._failure
            if self.watchdog_s > 0:
                self._spawn(self._watch, "watchdog")
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop serving, join every thread, release the link; harmless when closed."""
        if self._lifecycle is _Lifecycle.CLOSED:
            return
        self._lifecycle = _Lifecycle.CLOSED
        self._closing.set()
        # The loop publishes _stop before _loop, and checks _closing after both.
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # the loop has already ended
                loop.call_soon_threadsafe(stop.set)
        stuck = []
        for thread in self._threads:
            thread.join(_JOIN_TIMEOUT_S)
            if thread.is_alive():
                stuck.append(thread.name)
        if self._relay is not None:
            self._relay.close()
        if stuck:
            raise RuntimeError(f"Modbus simulator threads did not stop: {stuck}")

    def __enter__(self) -> SimModbusServer:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # The event loop -------------------------------------------------------------------------

    def _spawn(self, target: Callable[[], None], role: str) -> None:
        thread = threading.Thread(target=target, name=f"modbus-sim-{self.link.value}-{role}")
        self._threads.append(thread)
        thread.start()

    def _run_loop(self) -> None:
        # asyncio.run also cancels leftover request tasks and closes the loop's own fds.
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        self._stop = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        server: ModbusTcpServer | ModbusSerialServer | None = None
        try:
            server = self._make_server()
            await server.serve_forever(background=True)
            if self.link is ModbusLink.TCP:
                listener = cast(asyncio.Server, server.transport)
                host, port = listener.sockets[0].getsockname()[:2]
                self._tcp_address = (str(host), int(port))
        except Exception as exc:
            self._failure = exc
            if server is not None:
                await server.shutdown()  # type: ignore[no-untyped-call]
            self._ready.set()
            return
        self._ready.set()
        try:
            if not self._closing.is_set():
                await self._stop.wait()
        finally:
            await server.shutdown()  # type: ignore[no-untyped-call]
            # Closed transports release their sockets in callbacks: let those run.
            for _ in range(3):
                await asyncio.sleep(0)

    def _make_server(self) -> ModbusTcpServer | ModbusSerialServer:
        device = SimDevice(
            self.unit,
            simdata=[SimData(0, count=_REGISTER_SPAN, datatype=DataType.REGISTERS)],
            action=self._access,
        )
        if self.link is ModbusLink.TCP:
            return ModbusTcpServer(
                device,
                address=(LOOPBACK, 0),
                ignore_missing_devices=True,
                trace_packet=self._on_packet,
                trace_pdu=self._on_request,
                custom_pdu=list(_other_requests()),
            )
        assert self._relay is not None
        return ModbusSerialServer(
            device,
            framer=FramerType.RTU,
            port=self._relay.server_port,
            baudrate=RTU_BAUDRATE,
            bytesize=_SERIAL_BITS,
            parity=PTY_PARITY,  # 8E1 has no meaning on a pty (see drivers.modbus_map)
            stopbits=_STOP_BITS,
            ignore_missing_devices=True,
            trace_packet=self._on_packet,
            trace_pdu=self._on_request,
        )

    def _on_request(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        """What the drive makes of a decoded request (responses pass unchanged)."""
        if sending:
            return pdu
        if self._silent.is_set() or pdu.dev_id != self.unit:
            return _Unanswered(pdu)
        with self._drop_lock:
            dropped = self._requests_to_drop > 0
            if dropped:
                self._requests_to_drop -= 1
            on_dropped = self._on_dropped
        if dropped:
            if on_dropped is not None:
                on_dropped()
            return _Unanswered(pdu)
        self._last_heard = time.monotonic()
        if pdu.function_code not in _FUNCTIONS:
            return _Refused(pdu, ExcCodes.ILLEGAL_FUNCTION)
        return pdu

    def _on_packet(self, sending: bool, data: bytes) -> bytes:
        # Also silences what pymodbus answers on its own (a frame it could not decode).
        return b"" if sending and self._silent.is_set() else data

    async def _access(  # noqa: PLR0917 - the signature of pymodbus's SimAction
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus's datastore hook: the drive answers, its block is only a buffer."""
        if function_code not in _FUNCTIONS:
            return ExcCodes.ILLEGAL_FUNCTION
        if values:
            refused = self._registers.write(address, [int(value) for value in values])
            return None if refused is None else ExcCodes(refused)
        # A read, or 0x06's echo of the register it wrote.
        words = self._registers.read(address, count)
        if isinstance(words, ModbusExceptionCode):
            return ExcCodes(words)
        offset = address - start_address
        registers[offset : offset + count] = words
        return None

    # The watchdog ---------------------------------------------------------------------------

    def _watch(self) -> None:
        tick = min(self.watchdog_s / 10, _WATCHDOG_TICK_S)
        while not self._closing.wait(tick):
            quiet_s = time.monotonic() - self._last_heard
            if quiet_s >= self.watchdog_s and self.drive.communication_lost():
                _log.warning(
                    "Modbus unit %d: no request for %.2f s (watchdog %.2f s): drive disabled, "
                    "target velocity 0, switch on disabled", self.unit, quiet_s, self.watchdog_s,
                )
