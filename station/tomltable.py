"""Strict reading of TOML files that people write: recipes, bench files.

A typo in a file that drives a production line must not silently become a
default, and whoever edits it should fix every problem in one pass. So a
``TomlTable`` reads field by field, records each problem with its dotted
path instead of raising, and reports at the end every key nobody read, with a
"did you mean" when one is close.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from collections.abc import Collection, Mapping
from enum import Enum
from typing import Final, TypeVar

E = TypeVar("E", bound=Enum)

# Python 3.11's TOMLDecodeError carries its position only in the message.
_TOML_POSITION = re.compile(r"\s*\(at line (\d+), column (\d+)\)$")


def toml_error(exc: tomllib.TOMLDecodeError) -> str:
    """A decoding error as 'line N, column M: invalid TOML: ...' for people."""
    message = str(exc)
    position = _TOML_POSITION.search(message)
    if position is None:
        return f"invalid TOML: {message}"
    line, column = position.groups()
    return f"line {line}, column {column}: invalid TOML: {message[: position.start()]}"


_TOML_TYPES: Final[Mapping[str, str]] = {
    "bool": "a boolean",
    "int": "an integer",
    "float": "a float",
    "str": "a string",
    "list": "an array",
    "dict": "a table",
    "datetime": "a date-time",
    "date": "a date",
    "time": "a time",
}


def toml_type(value: object) -> str:
    """Name a value's type as the recipe's author wrote it, not as Python holds it."""
    return _TOML_TYPES.get(type(value).__name__, type(value).__name__)


def _interval(low: float | None, low_open: bool, high: float | None, high_open: bool) -> str:
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low:g}"
    return f"{'<' if high_open else '<='} {high if high is not None else math.inf:g}"


class TomlTable:
    """Reads one TOML table field by field, recording each problem instead of
    raising, so that one pass over a recipe finds all of them.

    Readers return a placeholder when a value is unusable; the placeholder
    never escapes because any problem makes the parse fail. Cross-field rules
    ask ``valid`` first, so a bad value is reported once, not again by every
    rule that uses it.
    """

    def __init__(
        self, problems: list[str], path: str, data: Mapping[str, object], *, absent: bool = False
    ) -> None:
        self._problems = problems
        self._path = path
        self._data = data
        self._absent = absent  # the table itself is missing: its keys are not reported
        self._read: set[str] = set()
        self._bad: set[str] = set()

    def name(self, key: str) -> str:
        return f"{self._path}.{key}" if self._path else key

    def problem(self, key: str, message: str) -> None:
        self._bad.add(key)
        self._problems.append(f"{self.name(key)}: {message}")

    def valid(self, *keys: str) -> bool:
        return not self._bad.intersection(keys)

    def _raw(self, key: str) -> object | None:
        self._read.add(key)
        if key not in self._data:
            if self._absent:
                self._bad.add(key)
            else:
                self.problem(key, "missing")
            return None
        return self._data[key]

    def _wrong_type(self, key: str, expected: str, value: object) -> None:
        self.problem(key, f"expected {expected}, got {toml_type(value)} {value!r}")

    def string(
        self, key: str, *, pattern: re.Pattern[str] | None = None, nonempty: bool = False
    ) -> str:
        value = self._raw(key)
        if value is None:
            return ""
        if not isinstance(value, str):
            self._wrong_type(key, "a string", value)
            return ""
        if nonempty and not value:
            self.problem(key, "must not be empty")
        elif pattern is not None and not pattern.fullmatch(value):
            self.problem(key, f"{value!r} does not match {pattern.pattern}")
        return value

    def integer(
        self,
        key: str,
        low: int | None = None,
        high: int | None = None,
        *,
        choices: Collection[int] | None = None,
        note: str = "",
    ) -> int:
        value = self._raw(key)
        if value is None:
            return 0
        # bool is an int to Python, never to a recipe; a float is refused even when
        # integral, because 4.0 periods suggests the author meant something else.
        if isinstance(value, bool) or not isinstance(value, int):
            self._wrong_type(key, "an integer", value)
            return 0
        self.check_int(key, value, low, high, choices=choices, note=note)
        return value

    def check_int(
        self,
        key: str,
        value: int,
        low: int | None,
        high: int | None,
        *,
        choices: Collection[int] | None = None,
        note: str = "",
    ) -> None:
        suffix = f" ({note})" if note else ""
        if choices is not None and value not in choices:
            listed = ", ".join(str(c) for c in choices)
            self.problem(key, f"must be one of {listed}, got {value}{suffix}")
        elif (low is not None and value < low) or (high is not None and value > high):
            if low is not None and high is not None:
                bounds = f"in {low}..{high}"
            else:
                bounds = f">= {low}" if low is not None else f"<= {high}"
            self.problem(key, f"must be {bounds}, got {value}{suffix}")

    def real(
        self,
        key: str,
        *,
        gt: float | None = None,
        ge: float | None = None,
        lt: float | None = None,
        le: float | None = None,
        note: str = "",
    ) -> float:
        value = self._raw(key)
        if value is None:
            return 0.0
        if isinstance(value, bool) or not isinstance(value, int | float):
            self._wrong_type(key, "a number", value)
            return 0.0
        try:
            number = float(value)
        except OverflowError:  # TOML integers are unbounded
            number = math.inf
        if not math.isfinite(number):
            self.problem(key, f"must be finite, got {value!r}")
            return 0.0
        low, high = (gt if gt is not None else ge), (lt if lt is not None else le)
        if (
            (gt is not None and number <= gt)
            or (ge is not None and number < ge)
            or (lt is not None and number >= lt)
            or (le is not None and number > le)
        ):
            bounds = _interval(low, gt is not None, high, lt is not None)
            suffix = f" ({note})" if note else ""
            self.problem(key, f"must be {bounds}, got {value!r}{suffix}")
        return number

    def int_array(self, key: str) -> tuple[int, ...]:
        value = self._raw(key)
        if value is None:
            return ()
        if not isinstance(value, list):
            self._wrong_type(key, "an array of integers", value)
            return ()
        items: list[int] = []
        for i, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, int):
                self._wrong_type(f"{key}[{i}]", "an integer", item)
                self._bad.add(key)
            else:
                items.append(item)
        return tuple(items)

    def table(self, key: str) -> TomlTable:
        value = self._raw(key)
        if isinstance(value, dict):
            return TomlTable(self._problems, self.name(key), value)
        if value is not None:
            self._wrong_type(key, "a table", value)
        return TomlTable(self._problems, self.name(key), {}, absent=True)

    def table_array(self, key: str) -> list[TomlTable]:
        """An array of tables (``[[key]]``), each read strictly as ``key[i]``."""
        value = self._raw(key)
        if value is None:
            return []
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            self._wrong_type(key, "an array of tables", value)
            return []
        return [TomlTable(self._problems, f"{self.name(key)}[{i}]", item)
                for i, item in enumerate(value)]

    def choice(self, key: str, kind: type[E]) -> E | None:
        """One of an enum's values, or None (with the problem recorded)."""
        value = self.string(key)
        if not self.valid(key):
            return None
        try:
            return kind(value)
        except ValueError:
            listed = ", ".join(repr(m.value) for m in kind)
            self.problem(key, f"must be one of {listed}, got {value!r}")
            return None

    def one_of(self, key: str, names: Collection[str]) -> str | None:
        """One of ``names`` (a registry's), or None (with the problem recorded)."""
        value = self.string(key)
        if not self.valid(key):
            return None
        if value not in names:
            self.problem(key, f"must be one of {', '.join(map(repr, names))}, got {value!r}")
            return None
        return value

    def has(self, key: str) -> bool:
        """Whether an optional key is present (a file that may leave it to its default)."""
        return key in self._data

    def optional_table(self, key: str) -> TomlTable | None:
        """A table that may be absent; None then, and nothing is reported."""
        return self.table(key) if key in self._data else None

    def mapping(self, key: str) -> Mapping[str, object] | None:
        """A table passed through unread (another library's settings), or None."""
        value = self._raw(key) if key in self._data else None
        if value is None or isinstance(value, dict):
            return value
        self._wrong_type(key, "a table", value)
        return None

    def str_array(self, key: str) -> tuple[str, ...]:
        value = self._raw(key)
        if value is None:
            return ()
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self._wrong_type(key, "an array of strings", value)
            return ()
        return tuple(value)

    # Called after every reader of the table, so ``_read`` holds every known key.
    def finish(self, foreign: Mapping[str, str] | None = None) -> None:
        """Report every key nobody read: a typo must not silently become a default."""
        for key in self._data:
            if key in self._read:
                continue
            if foreign and key in foreign:
                self.problem(key, foreign[key])
                continue
            close = difflib.get_close_matches(key, self._read, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            self.problem(key, f"unknown key{hint}")
