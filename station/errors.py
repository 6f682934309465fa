"""One exception family for the whole station.

Every failure the station can meet is a ``StationError``; its ``exit_code``
is what the CLI returns (CLI.md: 2 for usage, recipe or input errors where
nothing was done, 3 for station or device errors). Device errors keep the
device's own code (SDO abort code, Modbus exception code) so that a technician
can look it up in the device manual.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any


class ExitCode(IntEnum):
    """Process exit codes promised by CLI.md."""

    OK = 0
    FAILED_LIMIT = 1
    USAGE = 2
    STATION = 3


class StationError(Exception):
    """Root of every error the station raises on purpose."""

    exit_code: ExitCode = ExitCode.STATION

    def __reduce__(self) -> tuple[Any, ...]:
        # Errors cross process boundaries (worker pools of the diagnosis and the
        # benchmarks), and pickle would call a subclass's own constructor with the
        # message alone: rebuilt instead from the message, with every attribute kept.
        return _rebuilt, (type(self), self.args, self.__dict__)


def _rebuilt(cls: type[StationError], args: tuple[Any, ...],
             state: dict[str, Any]) -> StationError:
    error = cls.__new__(cls)
    Exception.__init__(error, *args)
    error.__dict__.update(state)
    return error


class InputError(StationError):
    """Bad input from the operator or a file: nothing was done."""

    exit_code = ExitCode.USAGE


class RecordingError(InputError):
    """A recording or its metadata cannot be read as ICD.md §5 describes."""


class DeviceError(StationError):
    """A device misbehaved or could not be reached."""

    def __init__(self, device: str, message: str) -> None:
        super().__init__(f"{device}: {message}")
        self.device = device


class DeviceTimeout(DeviceError):
    """A device did not answer within its deadline."""


class SdoAbort(DeviceError):
    """The device refused an SDO transfer; ``code`` is the CiA 301 abort code."""

    def __init__(self, device: str, index: int, subindex: int, code: int,
                 meaning: str = "") -> None:
        said = f" ({meaning})" if meaning else ""
        super().__init__(device,
                         f"SDO 0x{index:04X}:{subindex:02X} aborted with 0x{code:08X}{said}")
        self.index = index
        self.subindex = subindex
        self.code = code


class DeviceStateError(DeviceError):
    """The device is not in the state the procedure needs (e.g. CiA 402 fault)."""


class DeviceRebooted(DeviceStateError):
    """The device booted again mid-run (power cycle, watchdog): what it held in RAM is gone."""


class BusFault(DeviceError):
    """The CAN interface reported bus-off, or so many errors that no frame can be trusted."""


class SensorFault(DeviceError):
    """The sensor answers, but what it reports is not acceleration (clipped, stuck, unplugged)."""


class IdentityMismatch(DeviceError):
    """The unit on the bench is not the unit the operator named.

    An operator's mistake, found by reading the drive only: nothing is recorded
    and nothing written to the drive, so it is an input error (exit code 2).
    """

    exit_code = ExitCode.USAGE


class ProductMismatch(DeviceError):
    """The unit is not the product the recipe was written for (rating, microstepping)."""


class SelfCheckFailed(DeviceError):
    """The acceleration sensor failed its standstill self-check: nothing it says can be trusted."""


class DatabaseError(StationError):
    """The results database could not be opened, migrated, read or written.

    A station that cannot record its runs must stop: the message names the file
    so the technician knows which database (and which disk) to look at.
    """

    exit_code = ExitCode.STATION

    def __init__(self, database: str, message: str) -> None:
        super().__init__(f"database {database}: {message}")
        self.database = database
        self.detail = message


class DatabaseUnreachable(DatabaseError):
    """A line's database server did not answer: the station records into its spool."""


class DatabaseRefused(DatabaseError):
    """A line's database that cannot be the one meant: its server refused the station
    (credentials, role, database name), or nothing answers at a URL this station has
    never reached (a mistyped host or port). Refused before anything runs, so it is an
    input error (exit code 2); only a line that was reached before and went away is an
    outage, spooled for."""

    exit_code = ExitCode.USAGE


class DatabasePathError(DatabaseError):
    """The database path given cannot hold a database (unwritable, not a directory, ...).

    The operator named it (``--db``, ``STATION_DB``), and it is refused before
    anything runs, so it is an input error (exit code 2).
    """

    exit_code = ExitCode.USAGE


class ModbusException(DeviceError):
    """The drive answered a Modbus request with an exception; ``code`` is its exception code.

    Kept as the device sent it (0x02 unknown address, 0x03 value out of range,
    0x04 device failure, ...) so a technician can look it up in the manual.
    """

    def __init__(self, device: str, function: int, address: int, code: int,
                 meaning: str) -> None:
        super().__init__(
            device,
            f"Modbus function 0x{function:02X} at register 0x{address:04X} answered "
            f"exception 0x{code:02X} ({meaning})",
        )
        self.function = function
        self.address = address
        self.code = code
