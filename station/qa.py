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
from dataclasses import dataclass


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


def capability(values: Sequence[float], low: float | None, high: float | None) -> Capability:
    """Cpk of ``values`` against ``low``..``high`` (either may be absent).

    The sample standard deviation (ddof=1) is used because QA looks at a
    sample of the line, not the whole population; with one-sided limits only
    that side counts. Non-finite values are refused: a NaN would silently make
    the whole figure NaN, hiding the run that produced it.
    """
    if low is not None and high is not None and low > high:
        raise ValueError(f"low limit {low} is above high limit {high}")
    if not all(math.isfinite(value) for value in values):
        raise ValueError("capability needs finite values; filter out runs without a value first")
    n = len(values)
    mean = statistics.fmean(values) if n else math.nan
    std = statistics.stdev(values) if n >= 2 else math.nan
    return Capability(n, mean, std, low, high, _cpk(mean, std, low, high))


def _cpk(mean: float, std: float, low: float | None, high: float | None) -> float | None:
    if not std > 0.0:  # also catches NaN, i.e. fewer than two values
        return None
    sides = []
    if high is not None:
        sides.append((high - mean) / (3.0 * std))
    if low is not None:
        sides.append((mean - low) / (3.0 * std))
    return min(sides) if sides else None
