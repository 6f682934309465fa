"""Which bench a command names, decided before any bench code is imported.

Opening a bench needs python-can, canopen, the drivers and (for the simulated
bench) the physics: a second of imports. A name that is neither a built-in
bench nor a readable file is refused here first, so a typo answers at once.
"""

from __future__ import annotations

import os
from pathlib import Path

from station.errors import InputError

SIM_BENCH = "sim"
"""The bench name meaning the simulated bench in this process (CLI.md)."""
SIM_MODBUS_BENCH = "sim-modbus"
"""The simulated bench with its drive reached over Modbus TCP on loopback (ICD.md §4)."""
BUILT_IN_NAMES = (SIM_BENCH, SIM_MODBUS_BENCH)
BENCH_ENV = "STATION_BENCH"


class BenchFileError(InputError):
    """A bench file that cannot be used; nothing was done (exit code 2)."""


def chosen_bench(name_or_path: str | None = None) -> str:
    """``--bench``, else ``STATION_BENCH``, else the simulated bench."""
    return name_or_path or os.environ.get(BENCH_ENV) or SIM_BENCH


def read_bench_file(chosen: str) -> tuple[Path, str]:
    """A bench file's path and text, or why it cannot be one."""
    path = Path(chosen).expanduser()
    try:
        return path, path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BenchFileError(
            f"bench {chosen!r} is neither a built-in bench ({', '.join(BUILT_IN_NAMES)}) "
            "nor an existing bench file"
        ) from None
    except OSError as exc:
        raise BenchFileError(f"bench file {path}: cannot be read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise BenchFileError(f"bench file {path}: not UTF-8 text (byte {exc.start})") from None


def check_bench(name_or_path: str | None = None) -> None:
    """Refuse a bench that is neither built in nor a readable text file."""
    chosen = chosen_bench(name_or_path)
    if chosen not in BUILT_IN_NAMES:
        read_bench_file(chosen)
