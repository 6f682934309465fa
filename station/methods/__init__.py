"""Calibration methods as plug-ins: where to hold the trims next, given what the holds so
far measured, and the estimate at the end.

The procedure owns the bench: it moves the motor, holds each point, deals with clipped
holds and the sensor's clock, records everything. A method owns only the experiment's
design, as a generator (``Plan``): it yields the next ``Batch`` of points, is sent what
they measured, and returns its ``TrimEstimate``. So the sweep part of the procedure is
one loop whatever the method, and a method is one module here that reads its own recipe
table and plans its own rounds: the paper's three parabolas, phase-coherent star rounds,
or the paper's parabolas in rounds for drives whose electrical angle is unknown.

Modules are named in ``SWEEPS`` and imported when first asked for, as python-can's
backends are; the estimators and designs they use are imported when a plan starts, so
reading a recipe stays quick.
"""

from __future__ import annotations

import importlib
from collections.abc import Generator, Sequence, Set
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Protocol, TypeAlias, TypeVar

from station.core import Method, Trims

if TYPE_CHECKING:
    from station.analysis.estimate import TrimEstimate
    from station.analysis.pipeline import Measured
    from station.analysis.sampling import ClockPhase
    from station.recipes import Recipe
    from station.schedules import Phase
    from station.tomltable import TomlTable


@dataclass(frozen=True)
class Batch:
    """Points a method wants held next, and how."""

    points: tuple[Trims, ...]
    phase: Phase
    label: str  # what the operator reads while they are held
    centre: Trims | None = None  # where clipped holds are moved towards (None: nowhere)
    settle_periods: int | None = None  # None: the recipe's motion table's
    dwell_periods: int | None = None


R = TypeVar("R")
Steps: TypeAlias = Generator[Batch, "list[Measured]", R]
"""Yields what to hold next, is sent what those holds measured, returns an ``R``."""
Plan: TypeAlias = Steps["TrimEstimate"]
"""A whole method's steps: it returns the estimate."""


class SweepContext(Protocol):
    """What a method may know of the run: the recipe, where the sweeps begin, what the
    baseline measured, and the few services of the procedure a design needs."""

    @property
    def recipe(self) -> Recipe: ...

    @property
    def centre(self) -> Trims:
        """The drive's trims as the run found them, within the drive's range."""
        ...

    @property
    def baseline(self) -> Sequence[Measured]: ...

    @property
    def left_out(self) -> Set[Trims]:
        """Points the procedure left out because they clipped: asking again is futile."""
        ...

    def clock(self, held: Sequence[Measured]) -> ClockPhase | None:
        """The sensor's clock for these holds' phasors (None: only magnitudes count)."""
        ...

    def storable(self, trims: Trims) -> bool:
        """Whether the recipe's limits let the drive store these trims."""
        ...

    def warn(self, text: str) -> None:
        """A warning for the run's record."""
        ...

    def estimating(self, detail: str) -> None:
        """Tell the operator an estimate is being made."""
        ...


class SweepMethod(Protocol):
    """One method's plug-in: its recipe table, what it needs of the bench, its plan."""

    @property
    def name(self) -> str: ...

    @property
    def settings_type(self) -> type:
        """The dataclass its recipe table is read into."""
        ...

    @property
    def table(self) -> str:
        """The recipe table its settings are read from."""
        ...

    @property
    def needs_angle(self) -> bool:
        """Whether its phasors need the drive's electrical angle with every sample."""
        ...

    @property
    def estimates(self) -> Method:
        """The estimator its result is reported as."""
        ...

    def read(self, t: TomlTable, rated_mA: int | None) -> Any:
        """Its settings from its recipe table, every problem reported on ``t``."""
        ...

    def plan(self, settings: Any, ctx: SweepContext) -> Plan: ...


SWEEPS: Final[dict[str, str]] = {
    "paper": "station.methods.paper",
    "coherent": "station.methods.coherent",
    "magnitude": "station.methods.magnitude",
}
"""Every method by name, and the module that holds its ``METHOD``."""

ANGLE_FREE: Final = "magnitude"
"""What a recipe's ``magnitude_sweep`` table runs where its method needs the angle and
the drive does not report it (a Modbus drive)."""


def trims_text(t: Trims) -> str:
    """Trims as the operator reads them."""
    return (f"offsets {t.offset_a_mA:+.0f}/{t.offset_b_mA:+.0f} mA, "
            f"gains {t.gain_a:.0f}/{t.gain_b:.0f}")


S = TypeVar("S")


def settings_of(settings: object, kind: type[S]) -> S:
    """A method's own settings, as its recipe table was read into them."""
    if not isinstance(settings, kind):
        raise TypeError(f"expected {kind.__name__} settings, got {type(settings).__name__}")
    return settings


def sweep_method(name: str) -> SweepMethod:
    """The plug-in called ``name``, its module imported on first use."""
    try:
        module = SWEEPS[name]
    except KeyError:
        raise ValueError(f"no calibration method {name!r} (known: {', '.join(SWEEPS)})") \
            from None
    method: SweepMethod = importlib.import_module(module).METHOD
    return method


def for_run(recipe: Recipe, *, sees_angle: bool) -> tuple[SweepMethod, Any]:
    """The method a run uses on this bench, and its settings from the recipe."""
    chosen = sweep_method(recipe.method)
    if chosen.needs_angle and not sees_angle:
        if recipe.magnitude_sweep is None:  # refused with the request, before the bench
            raise ValueError(f"recipe {recipe.name} needs the drive's angle, which this "
                             "drive does not report, and has no magnitude_sweep table")
        return sweep_method(ANGLE_FREE), recipe.magnitude_sweep
    return chosen, recipe.sweep
