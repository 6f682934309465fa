"""The drive's Modbus register map (ICD.md §4), shared by the client and the simulator.

ICD.md §4 puts the CANopen drive's objects (§2) behind holding registers:
16-bit values in one register, 32-bit values in two with the high word first.
Keeping the map as data, one ``Field`` per value with the CANopen object it
stands for, lets the station's client and the simulated drive agree by
construction, while an independent client (``mbpoll`` in the tests) checks
that both agree with the document.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum
from typing import Final

DEFAULT_UNIT_ID: Final = 1
"""ICD.md §4: the drive answers as unit 1 unless configured otherwise."""

STORE_WORDS: Final = (0x7361, 0x7665)
"""ICD.md §4: "sa", "ve" written to 0x0030-0x0031 persist the parameters to EEPROM."""

STORE_READS: Final = 1
"""Reading the store registers gives 1, as 0x1010:01 does over CANopen (saves on command)."""

RTU_BAUDRATE: Final = 19200
"""Modbus over serial line: 19200 baud, 8 data bits, even parity, 1 stop bit by default."""
RTU_PARITY: Final = "E"

PTY_PARITY: Final = "N"
"""What pyserial must be told on a pseudo-terminal (the simulated RTU line).

A pty carries bytes, not bits, and Linux's pty driver drops PARENB; glibc's
tcsetattr then reports EINVAL whenever that was the only change asked for, which
is every reconfiguration after pyserial's first (pymodbus sets a timeout right
after opening). The bytes on a pty are the same whatever the parity, so a
pyserial client of the simulated drive opens it with no parity; libmodbus (mbpoll)
configures the port once and may keep 8E1.
"""


class ModbusLink(StrEnum):
    """How the Modbus frames travel: TCP (MBAP header) or a serial line (RTU framing)."""

    TCP = "tcp"
    RTU = "rtu"


class ModbusFunction(IntEnum):
    """The function codes ICD.md §4 allows."""

    READ_HOLDING_REGISTERS = 0x03
    WRITE_SINGLE_REGISTER = 0x06
    WRITE_MULTIPLE_REGISTERS = 0x10


class ModbusExceptionCode(IntEnum):
    """Modbus application protocol exception codes (the ones a drive answers with)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06

    @property
    def meaning(self) -> str:
        return self.name.lower().replace("_", " ")


class Register(IntEnum):
    """First register of each value in ICD.md §4."""

    CONTROLWORD = 0x0000
    STATUSWORD = 0x0001
    TARGET_VELOCITY = 0x0010
    POSITION_DEMAND = 0x0012
    AMPLITUDE = 0x0014
    OFFSET_A = 0x0020
    OFFSET_B = 0x0021
    GAIN_A = 0x0022
    GAIN_B = 0x0023
    STORE = 0x0030
    SERIAL_NUMBER = 0x0040
    MICROSTEPS = 0x0042
    RATED_CURRENT = 0x0043
    CALIBRATED_AT = 0x0050
    STATION_ID = 0x0052
    CALIBRATION_COUNT = 0x0053


@dataclass(frozen=True)
class Field:
    """One value of the map: where it sits, how wide, and what it means on CANopen."""

    register: Register
    words: int  # 1 (16 bits) or 2 (32 bits, high word first)
    signed: bool
    writable: bool
    canopen: tuple[int, int]  # (index, subindex) of the ICD.md §2 object it mirrors

    @property
    def stop(self) -> int:
        """One past the last register of the value."""
        return int(self.register) + self.words

    @property
    def bits(self) -> int:
        return 16 * self.words

    @property
    def low(self) -> int:
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def high(self) -> int:
        return (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1

    def encode(self, value: int) -> list[int]:
        """The registers carrying ``value``; raises ValueError outside the type's range."""
        if not self.low <= value <= self.high:
            raise ValueError(f"{value} does not fit {self.register.name} "
                             f"({self.low}..{self.high})")
        raw = value % (1 << self.bits)
        return [(raw >> (16 * (self.words - 1 - i))) & 0xFFFF for i in range(self.words)]

    def decode(self, words: list[int]) -> int:
        if len(words) != self.words:
            raise ValueError(f"{self.register.name} takes {self.words} registers, "
                             f"got {len(words)}")
        raw = 0
        for word in words:
            raw = (raw << 16) | (word & 0xFFFF)
        if self.signed and raw >= 1 << (self.bits - 1):
            raw -= 1 << self.bits
        return raw


def _field(register: Register, words: int, signed: bool, writable: bool,
           canopen: tuple[int, int]) -> Field:
    return Field(register, words, signed, writable, canopen)


FIELDS: Final[dict[Register, Field]] = {
    f.register: f
    for f in (
        _field(Register.CONTROLWORD, 1, False, True, (0x6040, 0)),
        _field(Register.STATUSWORD, 1, False, False, (0x6041, 0)),
        _field(Register.TARGET_VELOCITY, 2, True, True, (0x60FF, 0)),
        _field(Register.POSITION_DEMAND, 2, True, False, (0x6062, 0)),
        _field(Register.AMPLITUDE, 1, False, True, (0x2103, 0)),
        _field(Register.OFFSET_A, 1, True, True, (0x2100, 1)),
        _field(Register.OFFSET_B, 1, True, True, (0x2100, 2)),
        _field(Register.GAIN_A, 1, False, True, (0x2100, 3)),
        _field(Register.GAIN_B, 1, False, True, (0x2100, 4)),
        _field(Register.STORE, 2, False, True, (0x1010, 1)),
        _field(Register.SERIAL_NUMBER, 2, False, False, (0x1018, 4)),
        _field(Register.MICROSTEPS, 1, False, True, (0x2102, 0)),
        _field(Register.RATED_CURRENT, 1, False, True, (0x6075, 0)),
        _field(Register.CALIBRATED_AT, 2, False, True, (0x2101, 1)),
        _field(Register.STATION_ID, 1, False, True, (0x2101, 2)),
        _field(Register.CALIBRATION_COUNT, 1, False, True, (0x2101, 3)),
    )
}

TRIM_REGISTERS: Final = (Register.OFFSET_A, Register.OFFSET_B, Register.GAIN_A, Register.GAIN_B)
"""Consecutive, so one write of four registers sets all trims at once."""

CALIBRATION_REGISTERS: Final = (Register.CALIBRATED_AT, Register.STATION_ID,
                                Register.CALIBRATION_COUNT)


def field_at(address: int) -> tuple[Field, int] | None:
    """The value a register belongs to and the register's word within it, or None."""
    for f in FIELDS.values():
        if f.register <= address < f.stop:
            return f, address - int(f.register)
    return None


def store_value() -> int:
    """The U32 the store registers take ("save", high word first)."""
    return (STORE_WORDS[0] << 16) | STORE_WORDS[1]
