"""The bench's stepper drive over Modbus TCP or RTU (ICD.md §4), as a ``drivers.base.Drive``.

The same drive as over CANopen, through holding registers. What Modbus does
not give shapes this driver:

- no SYNC and no PDOs: the drive's state is only what the station reads or
  commands, so ``reports_state`` is False and the station logs its own writes;
- no reset: a stored calibration is read back without a reboot;
- no heartbeat: drives disable themselves when their master falls silent
  (a communication watchdog), so a keep-alive thread reads the statusword
  every ``keep_alive_s`` and notices a drive that left operation enabled.

Every request goes through one lock (pymodbus's synchronous clients are not
thread-safe). Modbus exceptions keep their code (``ModbusException``); a
request without answer is a ``DeviceTimeout`` naming the endpoint.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException as PymodbusError
from pymodbus.pdu import ModbusPDU

from drivers.base import (
    LIVENESS_TIMEOUT_S,
    CalibrationRecord,
    DeviceIdentity,
    Drive,
    DriveState,
    retried,
)
from drivers.cia402 import StateMachine
from drivers.modbus_map import (
    CALIBRATION_REGISTERS,
    DEFAULT_UNIT_ID,
    FIELDS,
    RTU_BAUDRATE,
    RTU_PARITY,
    STORE_WORDS,
    TRIM_REGISTERS,
    ModbusExceptionCode,
    ModbusFunction,
    ModbusLink,
    Register,
)
from drivers.transports import DriveTraits
from station.core import Trims
from station.errors import (
    DeviceError,
    DeviceStateError,
    DeviceTimeout,
    InputError,
    ModbusException,
    StationError,
)

log = logging.getLogger(__name__)

DEFAULT_TCP_PORT = 502


@dataclass(frozen=True)
class ModbusEndpoint:
    """Where the drive answers: a TCP host and port, or a serial device, and its unit ID."""

    link: ModbusLink
    host: str = "127.0.0.1"
    port: int = DEFAULT_TCP_PORT
    device: str = ""
    baudrate: int = RTU_BAUDRATE
    parity: str = RTU_PARITY
    unit: int = DEFAULT_UNIT_ID
    timeout_s: float = 0.5

    def describe(self) -> str:
        where = (f"{self.host}:{self.port}" if self.link is ModbusLink.TCP
                 else f"{self.device} {self.baudrate} 8{self.parity}1")
        return f"Modbus {self.link.value.upper()} {where} unit {self.unit}"


def _exception_meaning(code: int) -> str:
    try:
        return ModbusExceptionCode(code).meaning
    except ValueError:
        return "unknown exception code"


class ModbusDrive(Drive):
    """A CiA 402 stepper drive with current trims behind ICD.md §4's holding registers."""

    # Nothing on the CAN bus (the station logs its own writes), and no reset register.
    TRAITS = DriveTraits(reports_state=False, resettable=False)

    def __init__(self, endpoint: ModbusEndpoint, *, name: str = "drive",
                 state_timeout_s: float = 0.5, keep_alive_s: float = 0.2) -> None:
        self.name = name
        self.endpoint = endpoint
        self._lock = threading.Lock()
        self._closed = False
        self._expect_enabled = False
        self._left_enabled: str | None = None
        self._last_answer = time.monotonic()
        client: ModbusTcpClient | ModbusSerialClient
        if endpoint.link is ModbusLink.TCP:
            client = ModbusTcpClient(endpoint.host, port=endpoint.port,
                                     timeout=endpoint.timeout_s, retries=0)
        else:
            client = ModbusSerialClient(endpoint.device, baudrate=endpoint.baudrate,
                                        parity=endpoint.parity, bytesize=8, stopbits=1,
                                        timeout=endpoint.timeout_s, retries=0)
        self._client = client
        self._machine = StateMachine(name, self.statusword, self._write_controlword,
                                     timeout_s=state_timeout_s)
        if not client.connect():
            client.close()  # type: ignore[no-untyped-call]
            raise DeviceError(name, f"cannot connect to {endpoint.describe()}")
        try:
            # A drive that does not answer its identity is not worth going on with.
            self.identity()
        except BaseException:
            client.close()  # type: ignore[no-untyped-call]
            raise
        self._stop = threading.Event()
        self._keep_alive_s = keep_alive_s
        self._keeper = threading.Thread(target=self._keep_alive, name=f"{name}-keep-alive",
                                        daemon=True)
        self._keeper.start()

    # -- requests --------------------------------------------------------------

    def _where(self, function: ModbusFunction, address: int) -> str:
        return (f"{self.endpoint.describe()}: function 0x{function:02X} at register "
                f"0x{address:04X}")

    def _request(self, function: ModbusFunction, address: int, *,
                 count: int = 0, values: list[int] | None = None) -> list[int]:
        """One request under the lock; the answer's registers, or a station error.

        An unanswered request is sent again (``drivers.base.retried``, logged), for
        the reason SDOs are: every register the station writes holds an absolute
        value, so repeating a request the drive did act on changes nothing.
        """
        with self._lock:
            if self._closed:
                raise DeviceError(self.name, "the Modbus connection is closed")
            unit = self.endpoint.unit

            def once() -> ModbusPDU:
                if function is ModbusFunction.READ_HOLDING_REGISTERS:
                    return self._client.read_holding_registers(address, count=count,
                                                                device_id=unit)
                assert values is not None
                if function is ModbusFunction.WRITE_SINGLE_REGISTER:
                    return self._client.write_register(address, values[0], device_id=unit)
                return self._client.write_registers(address, values, device_id=unit)

            response = retried(
                once, device=self.name,
                what=f"{self._where(function, address)} (timeout {self.endpoint.timeout_s} s)",
                unanswered=PymodbusError,
            )
            self._last_answer = time.monotonic()
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            if code == 0:
                raise DeviceError(self.name, f"{self._where(function, address)}: {response}")
            raise ModbusException(self.name, int(function), address, code,
                                  _exception_meaning(code))
        return list(getattr(response, "registers", []) or [])

    def _read(self, register: Register) -> int:
        field = FIELDS[register]
        words = self._request(ModbusFunction.READ_HOLDING_REGISTERS, register,
                              count=field.words)
        return field.decode(words)

    def _read_block(self, registers: tuple[Register, ...]) -> dict[Register, int]:
        """Consecutive values in one request: they come from one instant of the drive."""
        first, last = FIELDS[registers[0]], FIELDS[registers[-1]]
        words = self._request(ModbusFunction.READ_HOLDING_REGISTERS, first.register,
                              count=last.stop - first.register)
        out: dict[Register, int] = {}
        for register in registers:
            f = FIELDS[register]
            offset = f.register - first.register
            out[register] = f.decode(words[offset: offset + f.words])
        return out

    def _encode(self, values: dict[Register, int]) -> list[int]:
        words: list[int] = []
        for register, value in values.items():
            try:
                words += FIELDS[register].encode(value)
            except ValueError as exc:
                raise InputError(f"{self.name}: {exc}") from None
        return words

    def _write(self, values: dict[Register, int]) -> None:
        """Consecutive values in one request, which the drive applies all or none."""
        first = next(iter(values))
        words = self._encode(values)
        if len(words) == 1:
            self._request(ModbusFunction.WRITE_SINGLE_REGISTER, first, values=words)
        else:
            self._request(ModbusFunction.WRITE_MULTIPLE_REGISTERS, first, values=words)

    # -- identity and ratings -------------------------------------------------

    def identity(self) -> DeviceIdentity:
        # ICD.md §4 maps only the serial number of CiA 301's identity object.
        return DeviceIdentity(0, 0, 0, self._read(Register.SERIAL_NUMBER))

    def rated_current_mA(self) -> int:
        return self._read(Register.RATED_CURRENT)

    def microsteps_per_fullstep(self) -> int:
        return self._read(Register.MICROSTEPS)

    # -- CiA 402 power state machine ------------------------------------------

    def statusword(self) -> int:
        return self._read(Register.STATUSWORD)

    def _write_controlword(self, controlword: int) -> None:
        self._write({Register.CONTROLWORD: int(controlword)})

    def state(self) -> DriveState:
        return self._machine.state()

    def enable(self) -> None:
        # A stale target velocity would start the motor the moment it is enabled.
        self._raise_if_dropped()
        self.set_velocity(0)
        self._machine.enable()
        self._left_enabled = None
        self._expect_enabled = True

    def disable(self) -> None:
        self._expect_enabled = False
        self.set_velocity(0)
        self._machine.disable()

    def check(self) -> None:
        self._raise_if_dropped()
        if self._expect_enabled:
            state = self.state()
            if state is not DriveState.OPERATION_ENABLED:
                self._expect_enabled = False
                raise DeviceStateError(self.name, f"left operation enabled by itself: now "
                                       f"{state.value} (power cycle, watchdog or fault)")

    def check_alive(self) -> None:
        """What the keep-alive thread found: a drive that stopped, or stopped answering."""
        self._raise_if_dropped()
        quiet_s = time.monotonic() - self._last_answer  # no lock: a request may hang it
        if quiet_s > max(LIVENESS_TIMEOUT_S, 5 * self._keep_alive_s):
            raise DeviceTimeout(self.name, f"silent: no answer to the keep-alive for "
                                f"{quiet_s:.2f} s ({self.endpoint.describe()})")

    def _raise_if_dropped(self) -> None:
        dropped, self._left_enabled = self._left_enabled, None
        if dropped is not None:
            self._expect_enabled = False
            raise DeviceStateError(self.name, dropped)

    def _keep_alive(self) -> None:
        """Feed the drive's watchdog, and notice when it stops running as commanded."""
        while not self._stop.wait(self._keep_alive_s):
            try:
                state = self.state()
            except StationError as exc:
                log.debug("%s: keep-alive read failed: %s", self.name, exc)
                continue
            if self._expect_enabled and state is not DriveState.OPERATION_ENABLED:
                self._left_enabled = (f"left operation enabled by itself: now {state.value} "
                                     "(power cycle, watchdog or fault)")
                log.warning("%s: %s", self.name, self._left_enabled)

    # -- set-points ------------------------------------------------------------

    def set_velocity(self, microsteps_per_s: int) -> None:
        self._write({Register.TARGET_VELOCITY: microsteps_per_s})

    def set_amplitude(self, amplitude_mA: int) -> None:
        self._write({Register.AMPLITUDE: amplitude_mA})

    # -- trims -----------------------------------------------------------------

    def write_trims(self, trims: Trims) -> None:
        """All four trims in one request: the drive takes all of them or none."""
        values = self._stored_form(trims)
        self._raise_if_dropped()
        self._write(dict(zip(TRIM_REGISTERS, values, strict=True)))

    def read_trims(self) -> Trims:
        values = self._read_block(TRIM_REGISTERS)
        return Trims(*(float(values[r]) for r in TRIM_REGISTERS))

    # -- persistence -----------------------------------------------------------

    def store(self) -> None:
        self._request(ModbusFunction.WRITE_MULTIPLE_REGISTERS, Register.STORE,
                      values=list(STORE_WORDS))

    def reset(self) -> None:
        raise DeviceError(self.name, "ICD.md §4 gives a Modbus drive no reset command")

    def read_calibration_record(self) -> CalibrationRecord:
        values = self._read_block(CALIBRATION_REGISTERS)
        return CalibrationRecord(values[Register.CALIBRATED_AT], values[Register.STATION_ID],
                                 values[Register.CALIBRATION_COUNT])

    def write_calibration_record(self, record: CalibrationRecord) -> None:
        self._write({Register.CALIBRATED_AT: record.calibrated_at,
                     Register.STATION_ID: record.station_id,
                     Register.CALIBRATION_COUNT: record.count})

    # -- teardown --------------------------------------------------------------

    def close(self) -> None:
        if self._closed:
            return
        self._stop.set()
        self._keeper.join()
        try:
            self.disable()
        except StationError as exc:
            log.warning("%s: could not disable on close: %s", self.name, exc)
        finally:
            self._closed = True
            with self._lock:
                self._client.close()  # type: ignore[no-untyped-call]
