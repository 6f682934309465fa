"""Current-loop lag: each phase's current following its command late (a first-order loop
per phase), which turns the torque's phase with the electrical frequency."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms, Params, Starts
from station.diagnosis.effects.readings import sigmas
from station.diagnosis.hooks import Hooks, Phasors, Role
from station.diagnosis.layout import Block

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.observations import Observations

START_LAGS_MS = (0.2, 0.6, 1.5, 4.0)
"""Time constants a search starts from: from a fast loop to one slower than a SYNC."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    t_ms = obs.metadata.sync_period_s * 1e3
    return [Block("current_lag_ms", 2, 0.5 * t_ms, 0.0, 20.0 * t_ms, rejects=(1,))]


def starts(model: Model, p: Params) -> list[Starts]:
    # A lag looks like a negative sensor delay: start with the sensor's share moved over.
    a1 = float(p[model.layout.slices["sensor_a1_ms"]][0])
    return [{"current_lag_ms": [lag, lag], "sensor_a1_ms": [a1 + lag]} for lag in START_LAGS_MS]


def current_response(model: Model, p: Params, response_a: Phasors, response_b: Phasors
                     ) -> tuple[Phasors, Phasors]:
    # A first-order loop per phase at each of the waveform's harmonics.
    tau = model.block(p, "current_lag_ms") * 1e-3
    s = 1j * model.obs.omega[:, None] * model.current_orders[None, :]
    return response_a * (1.0 / (1.0 + s * tau[0])), response_b * (1.0 / (1.0 + s * tau[1]))


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["current_lag_ms"]
    v, s = fit.params[sl], sigmas(cov)[sl]
    return {
        "time_constant_a_ms": float(v[0]), "time_constant_a_ms_sigma": float(s[0]),
        "time_constant_b_ms": float(v[1]), "time_constant_b_ms_sigma": float(s[1]),
        "bandwidth_a_hz": 1e3 / (2 * math.pi * float(v[0])) if v[0] > 0 else None,
        "bandwidth_b_hz": 1e3 / (2 * math.pi * float(v[1])) if v[1] > 0 else None,
        "note": ("a current loop's lag and the sensor's own delay look alike at low "
                 "frequency; the time constants are what the sensor's delay cannot hide"),
    }


TERMS = EffectTerms(
    effect=Effect.CURRENT_LOOP_LAG,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Kept by the nominal model in part: a loop far faster than the recorded orders is a "
        "delay the sensor's own low-pass stands for. Named where the time constants show "
        "what no sensor delay can hide."),
    rivals={
        Effect.SENSOR_CLOCK_DRIFT: (
            "repeat with the sensor's sampling locked to SYNC (or a sensor whose clock is "
            "known): a lagging current loop keeps its phase shift, a drifting clock's "
            "changes along the recording"),
    },
    starts=starts,
    hooks=Hooks(reads={Role.CURRENTS: ("current_lag_ms",)},
                current_response=current_response),
)
