"""A parameter resting on a physical bound: a finding when the data pull it past within
its own range, not when only a linear extrapolation far beyond the range would."""

from __future__ import annotations

from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest

from station.diagnosis.fit import PUSH_CHI2, Fit, ParameterState, judge_parameters
from station.diagnosis.layout import Block, Layout
from station.diagnosis.model import Model

ROWS = 100


def _at_lower_bound(curvature: float, pull: float) -> Fit:
    """A linear fit of one delay-like parameter (range 0 to 1) resting on 0, beside a free
    one; ``curvature`` is how sharply the data locate it (its column's norm), ``pull``
    the χ²'s square root that a step past the bound would give back."""
    layout = Layout()
    layout.add(Block("delay", 1, 0.5, 0.0, 1.0))
    layout.add(Block("free", 1, 0.0))
    u = np.zeros(ROWS)
    u[::2] = 1.0 / np.sqrt(ROWS / 2)
    v = np.zeros(ROWS)
    v[1::2] = 1.0 / np.sqrt(ROWS / 2)
    jacobian = np.column_stack([curvature * u, v])
    residuals = pull * u
    model = cast(Model, SimpleNamespace(layout=layout))
    return Fit(model, np.array([0.0, 0.0]), residuals, jacobian,
               np.array([-1, 0], dtype=np.int8))


def test_a_bound_the_data_pull_past_within_its_range_is_pushed() -> None:
    # χ² 16 given back by a step of 0.5 past the bound, half the range.
    judged = judge_parameters(_at_lower_bound(curvature=8.0, pull=4.0))[0]
    assert judged.state is ParameterState.PUSHED
    assert judged.chi2_gain == pytest.approx(16.0)
    assert judged.bound == 0.0


def test_a_pull_the_data_make_only_far_beyond_the_range_is_not_a_finding() -> None:
    # The full step would give back χ² 16 at 4 past the bound, four times the range; a step
    # of one range gives back 2·4·1 − 1² = 7.
    judged = judge_parameters(_at_lower_bound(curvature=1.0, pull=4.0))[0]
    assert judged.state is ParameterState.AT_LIMIT
    assert judged.chi2_gain == pytest.approx(7.0)
    assert judged.sigma == pytest.approx(1.0)


def test_a_strong_pull_beyond_the_range_is_still_a_finding() -> None:
    # Full step 2, twice the range; one range gives back 2·8·1 − 1²/0.25 = 12 of 16.
    judged = judge_parameters(_at_lower_bound(curvature=2.0, pull=4.0))[0]
    assert judged.state is ParameterState.PUSHED
    assert judged.chi2_gain == pytest.approx(12.0) and judged.chi2_gain > PUSH_CHI2


def test_a_weak_or_inward_pull_leaves_the_parameter_resting_at_its_limit() -> None:
    weak = judge_parameters(_at_lower_bound(curvature=8.0, pull=2.0))[0]
    inward = judge_parameters(_at_lower_bound(curvature=8.0, pull=-4.0))[0]
    assert weak.state is ParameterState.AT_LIMIT and weak.chi2_gain == pytest.approx(4.0)
    assert inward.state is ParameterState.AT_LIMIT and inward.chi2_gain == 0.0
