"""Reading the methods' recipe tables: checks several methods (and the recipe's limits)
share, each problem reported on the table with the key's full name."""

from __future__ import annotations

from typing import Final

from station.tomltable import TomlTable

MAX_ROUNDS: Final = 5
MAX_SIGMA_ROUNDS: Final = 3
MAX_GAIN_STEP: Final = 5000
HALF_RATED_NOTE: Final = "at most half of product.rated_current_mA"


def negated(value: int | None) -> int | None:
    return None if value is None else -value


def span(t: TomlTable, keys: tuple[str, str], values: tuple[int, int], through: int) -> None:
    """A [min, max] pair must be ordered and contain ``through`` (nominal): the
    paper's parabolas need the untrimmed unit's own ripple, and gain limits
    that exclude 10000 would fail every unit that needs no gain trim."""
    low_key, high_key = keys
    low, high = values
    if not t.valid(low_key, high_key):
        return
    if low >= high:
        t.problem(low_key, f"must be less than {t.name(high_key)} ({high}), got {low}")
    elif low > through:
        t.problem(low_key, f"must be <= {through}: the range {low}..{high} must contain {through}")
    elif high < through:
        t.problem(high_key, f"must be >= {through}: the range {low}..{high} must contain {through}")


def rounds(t: TomlTable, key: str, high: int | None, note: str) -> tuple[int, ...]:
    """One positive step (or span) per round, at most ``MAX_ROUNDS`` of them."""
    steps = t.int_array(key)
    if not t.valid(key):
        return steps  # a mistyped element was reported already
    if not steps:
        t.problem(key, "must not be empty: one entry per round")
    elif len(steps) > MAX_ROUNDS:
        t.problem(key, f"must have at most {MAX_ROUNDS} rounds, got {len(steps)}")
    for i, step in enumerate(steps):
        t.check_int(f"{key}[{i}]", step, 1, high, note=note if high is not None else "")
    return steps


def same_rounds(t: TomlTable, first: str, second: str, got: tuple[int, int]) -> None:
    """Two per-round arrays must have as many rounds each."""
    rounds_a, rounds_b = got
    if t.valid(first, second) and rounds_a and rounds_b and rounds_a != rounds_b:
        t.problem(second, f"must have as many rounds as {t.name(first)} ({rounds_a}), "
                  f"got {rounds_b}")
