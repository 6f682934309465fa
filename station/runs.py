"""What one calibration attempt is, as the station records it.

A run is the unit of traceability on the line: one row per attempt, whatever
happened. The procedure fills a ``Run`` as it goes, so that a run cut short by
a device error still carries everything learnt up to that moment (trims
before, the baseline, the recording); the store persists it and QA reads it
back. A failed unit is data (``Verdict.FAIL`` with the limits it missed); a
station problem is ``Verdict.ERROR`` with its reason.

Once finished and recorded a run is a record, and records outlive software: a run read
back from a store (or returned by a finished calibration) is frozen (``Run.freeze``),
so nothing downstream can change what was recorded, and it carries its limit checks
with their bounds and its recipe's name, version, hash and text. QA, reports and field
service read what the record holds and never need today's recipe parser.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any
from uuid import UUID, uuid4

from station.core import Trims
from station.errors import ExitCode


class Verdict(StrEnum):
    """Outcome of a run (CLI.md: ``pass``/``fail``/``error``/``aborted``)."""

    PASS = "pass"
    FAIL = "fail"
    ERROR = "error"
    ABORTED = "aborted"

    @property
    def exit_code(self) -> ExitCode:
        if self is Verdict.PASS:
            return ExitCode.OK
        if self is Verdict.FAIL:
            return ExitCode.FAILED_LIMIT
        return ExitCode.STATION


class RunKind(StrEnum):
    """Why the unit was on the station: production, or field service."""

    CALIBRATE = "calibrate"
    RECALIBRATE = "recalibrate"


class LimitName(StrEnum):
    """Every pass/fail limit a recipe can set, named as reports and QA name them."""

    ESTIMATE = "estimate"  # the data supported an estimate at all
    OFFSET_A = "offset_a_mA"  # trim within the recipe's bounds
    OFFSET_B = "offset_b_mA"
    GAIN_A = "gain_a"
    GAIN_B = "gain_b"
    OFFSET_SIGMA = "offset_sigma_mA"  # standard uncertainty of the offsets
    GAIN_SIGMA = "gain_sigma"
    FIT_R2 = "fit_r_squared"  # the worst share of the variation a fit explains
    H1_AFTER = "h1_after_mps2"
    H2_AFTER = "h2_after_mps2"
    H1_REDUCTION = "h1_reduction_db"  # |H1| before over |H1| after
    H2_REDUCTION = "h2_reduction_db"
    # Samples at the sensor's full scale during the measurements: left out of every fit,
    # and said (no recipe limit yet: the table shows the count, judged by nobody).
    CLIPPED = "clipped_samples"


def limit_name(text: str) -> LimitName | str:
    """A stored limit's name; one this software version does not know stays plain text.

    Records outlive software: a database written by a newer station (or by an
    older one, before a limit was renamed) must still read back for QA.
    """
    try:
        return LimitName(text)
    except ValueError:
        return text


@dataclass(frozen=True)
class LimitCheck:
    """One limit applied to one value; ``passed`` None means it did not apply."""

    name: LimitName | str
    value: float | None
    low: float | None
    high: float | None
    unit: str
    passed: bool | None
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": str(self.name),
            "value": _finite_or_none(self.value),
            "low": self.low,
            "high": self.high,
            "unit": self.unit,
            "passed": self.passed,
            "note": self.note,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LimitCheck:
        return cls(
            name=limit_name(str(data["name"])),
            value=data["value"],
            low=data["low"],
            high=data["high"],
            unit=str(data["unit"]),
            passed=data["passed"],
            note=str(data.get("note", "")),
        )


@dataclass(frozen=True)
class Ripple:
    """Magnitudes of the 1st and 2nd harmonic of the load's tangential acceleration."""

    h1: float  # m/s²
    h2: float  # m/s²

    @property
    def total(self) -> float:
        """What the unit shakes with at these two orders together (m/s² rms-like sum)."""
        return math.hypot(self.h1, self.h2)

    def as_dict(self) -> dict[str, float]:
        return {"h1": self.h1, "h2": self.h2}

    @classmethod
    def from_dict(cls, data: dict[str, float]) -> Ripple:
        return cls(float(data["h1"]), float(data["h2"]))


@dataclass(frozen=True)
class RecipeRef:
    """Which recipe a run followed: enough to find the exact text again, and on a run
    read back from a store the text itself (two references to one text are equal
    whether or not they carry it)."""

    name: str
    version: str
    sha256: str
    text: str | None = field(default=None, compare=False, repr=False)


class FrozenRecord(TypeError):
    """An attempt to change a finished run's record."""


class _FrozenList(list[Any]):
    """A list that refuses to change: a frozen record's warnings and fit arrays."""

    def _refuse(self, *_args: object, **_kwargs: object) -> Any:
        raise FrozenRecord("a finished run's record is not changed")

    append = extend = insert = remove = pop = clear = sort = reverse = _refuse
    __setitem__ = __delitem__ = __iadd__ = __imul__ = _refuse

    def __reduce__(self) -> tuple[Any, ...]:  # pickled and copied as a whole, not by append
        return (_FrozenList, (list(self),))


class _FrozenDict(dict[str, Any]):
    """A dict that refuses to change: a frozen record's fit summary."""

    def _refuse(self, *_args: object, **_kwargs: object) -> Any:
        raise FrozenRecord("a finished run's record is not changed")

    __setitem__ = __delitem__ = __ior__ = clear = pop = popitem = setdefault = update = _refuse

    def __reduce__(self) -> tuple[Any, ...]:
        return (_FrozenDict, (dict(self),))


def _frozen(value: Any) -> Any:
    """JSON-like data made unchangeable, all the way down."""
    if isinstance(value, dict):
        return _FrozenDict({k: _frozen(v) for k, v in value.items()})
    if isinstance(value, list):
        return _FrozenList(_frozen(v) for v in value)
    return value


@dataclass
class Run:
    """One attempt at one unit, filled in as the procedure learns things.

    Fields after ``bench`` are unknown at the start and stay ``None`` when the
    run never got that far.
    """

    serial: str
    kind: RunKind
    recipe: RecipeRef
    station_id: int
    operator: str
    software_version: str
    bench: str
    started_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    service_reason: str | None = None  # field service: why the unit came back
    previous_run_id: int | None = None  # field service: the run whose trims it had
    # Who the run is, wherever it is stored: a spooled run forwarded to a line's database
    # is the same run there, never a second one. None on runs recorded before it existed.
    run_uuid: UUID | None = field(default_factory=uuid4)
    run_id: int | None = None  # the database's own number, in the order runs began there
    finished_at: datetime | None = None
    verdict: Verdict | None = None  # None while running
    reason: str | None = None  # why ERROR/ABORTED, or a summary of a FAIL
    limits: tuple[LimitCheck, ...] = ()
    trims_before: Trims | None = None  # what the drive held when the run began
    trims_after: Trims | None = None  # what the drive holds (stored) when it ended
    trims_stored: bool = False  # the run wrote and stored trims in the drive
    trims_estimated: Trims | None = None  # the estimate, before rounding to the drive
    uncertainty: Trims | None = None  # 1σ of the estimate, same units as the trims
    before: Ripple | None = None
    after: Ripple | None = None
    method: str | None = None
    fit: dict[str, Any] | None = None  # fit quality, per fit (JSON-able)
    warnings: list[str] = field(default_factory=list)
    recording: str | None = None  # path of the ICD.md §5 recording
    recording_sha256: str | None = None
    motion_s: float | None = None  # simulated/bench time the SYNC clock ran

    def __setattr__(self, name: str, value: object) -> None:
        if self.__dict__.get("_frozen", False):
            raise FrozenRecord(f"run {self.run_id} of {self.serial} is a finished record: "
                               f"its {name} is not changed")
        object.__setattr__(self, name, value)

    def freeze(self) -> Run:
        """Make this run the record it is from now on; returns it.

        Only a finished run is frozen: one still going is the procedure's to fill."""
        if self.verdict is None or self.finished_at is None:
            raise ValueError(f"run {self.run_id} of {self.serial} is not finished")
        if not self.frozen:
            self.warnings = _frozen(list(self.warnings))
            self.fit = None if self.fit is None else _frozen(dict(self.fit))
            object.__setattr__(self, "_frozen", True)
        return self

    @property
    def frozen(self) -> bool:
        return bool(self.__dict__.get("_frozen", False))

    @property
    def failed_limits(self) -> tuple[LimitCheck, ...]:
        return tuple(check for check in self.limits if check.passed is False)


def utc_iso(moment: datetime) -> str:
    """ISO 8601 in UTC with a 'Z', to the microsecond: sorts as text, reads anywhere."""
    return moment.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def parse_utc_iso(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).astimezone(UTC)


def _finite_or_none(value: float | None) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(value)
