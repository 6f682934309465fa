"""Quality statistics over many runs, for QA rather than for one unit's verdict.

A unit passes or fails its limits one at a time; whether the line as a whole
is capable of meeting them is a property of the distribution. Cpk says how
many three-sigma widths fit between the process mean and the nearer recipe
limit, so a drift towards a limit shows up before units start to fail. Pure
functions: the store fetches the values, this only computes.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field

from station.runs import RecipeRef, Verdict


@dataclass(frozen=True)
class Capability:
    """Process capability of one quantity against its limits.

    ``cpk`` is None when it means nothing: no limit, fewer than two values
    (no spread to measure), or no spread at all (every value equal).
    """

    n: int
    mean: float  # NaN without values
    std: float  # sample standard deviation (ddof=1); NaN with fewer than two values
    low: float | None
    high: float | None
    cpk: float | None

    @property
    def cpk_sigma(self) -> float | None:
        """Standard error of ``cpk`` (Bissell's approximation, normal data):
        √(1/(9n) + Cpk²/(2(n−1))). Five runs at Cpk 1.33 give ±0.5: the figure alone
        would read as a capable process where the data cannot tell."""
        if self.cpk is None or self.n < 2:
            return None
        return math.sqrt(1.0 / (9.0 * self.n) + self.cpk ** 2 / (2.0 * (self.n - 1)))

    @property
    def cpk_rough(self) -> bool:
        """Too few values for Cpk to be more than a rough guide (``CPK_MIN_VALUES``)."""
        return self.cpk is not None and self.n < CPK_MIN_VALUES


CPK_MIN_VALUES = 30
"""Below this many values a Cpk is shown with a caution: its standard error is then
above 0.15 even for an incapable process, and above 0.2 at the usual target of 1.33."""


def capability(values: Sequence[float], low: float | None, high: float | None) -> Capability:
    """Cpk of ``values`` against ``low``..``high`` (either may be absent).

    The sample standard deviation (ddof=1) is used because QA looks at a
    sample of the line, not the whole population; with one-sided limits only
    that side counts. Non-finite values are refused: a NaN would silently make
    the whole figure NaN, hiding the run that produced it.
    """
    _check_limits(low, high)
    if not all(math.isfinite(value) for value in values):
        raise ValueError("capability needs finite values; filter out runs without a value first")
    n = len(values)
    mean = statistics.fmean(values) if n else math.nan
    std = statistics.stdev(values) if n >= 2 else math.nan
    return Capability(n, mean, std, low, high, _cpk(mean, std, low, high))


def _check_limits(low: float | None, high: float | None) -> None:
    if low is not None and high is not None and low > high:
        raise ValueError(f"low limit {low} is above high limit {high}")


def _cpk(mean: float, std: float, low: float | None, high: float | None) -> float | None:
    if not std > 0.0:  # also catches NaN, i.e. fewer than two values
        return None
    sides = []
    if high is not None:
        sides.append((high - mean) / (3.0 * std))
    if low is not None:
        sides.append((mean - low) / (3.0 * std))
    return min(sides) if sides else None


@dataclass(frozen=True)
class Moments:
    """Count, sum and sum of squares of one quantity, each value less a pivot.

    A database sums a million rows faster than it can send them, but the textbook
    ``sum(x**2) - n * mean**2`` loses every digit of a spread that is small against
    the mean (gains near 10000 units that differ by a few). Sums of ``x - pivot``,
    with the pivot one of the values, keep the cancellation to the spread's own scale.
    Moments of one pivot add, so groups summed apart (by verdict, say) combine here.
    """

    pivot: float
    n: int = 0
    shifted_sum: float = 0.0
    shifted_squares: float = 0.0

    def __add__(self, other: Moments) -> Moments:
        if other.pivot != self.pivot:
            raise ValueError("moments add only about the same pivot")
        return Moments(self.pivot, self.n + other.n, self.shifted_sum + other.shifted_sum,
                       self.shifted_squares + other.shifted_squares)

    def capability(self, low: float | None, high: float | None) -> Capability:
        """What ``capability`` gives for the values these moments were summed from."""
        _check_limits(low, high)
        n = self.n
        if not (math.isfinite(self.shifted_sum) and math.isfinite(self.shifted_squares)):
            raise ValueError("capability needs finite values; the sums were not finite")
        mean = self.pivot + self.shifted_sum / n if n else math.nan
        std = math.nan
        if n >= 2:
            # Rounding can leave a hair below zero when every value is equal.
            variance = (self.shifted_squares - self.shifted_sum**2 / n) / (n - 1)
            std = math.sqrt(max(variance, 0.0))
        return Capability(n, mean, std, low, high, _cpk(mean, std, low, high))


@dataclass(frozen=True)
class RecipeStatistics:
    """Process capability of one recipe version over the runs QA selected."""

    recipe: RecipeRef
    runs: int
    verdicts: dict[Verdict, int]
    quantities: dict[str, Capability] = field(default_factory=dict)
