"""Current-loop lag: each phase's current following its command late, which turns the
torque's phase with the electrical frequency, and, for a PI loop on the phase's R and L,
the current the loop lets the motor's back-EMF make.

A PI loop tuned as drives tune it (its zero on the phase's pole) follows its command as a
first-order lag of its bandwidth ωb; against the back-EMF e = ω·∂τ/∂i it leaves
−e·s/(L(s + ωb)(s + R/L)), a current that grows with speed and damps the rotor's swing.
Without that path, an independent simulator's PI loops were hidden in the nominal model's
rotor damping (0.379 against 0.073 on its twin) and the lag was never named; on the
bench's own PI trials the back-EMF's share went to saturation, reluctance or a coupling."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms, Params, Starts
from station.diagnosis.effects.readings import sigmas, value
from station.diagnosis.hooks import Grid, Hooks, Phasors, Role
from station.diagnosis.layout import Block

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations

START_LAGS_MS = (0.2, 0.6, 1.5, 4.0)
"""Time constants a search starts from: from a fast loop to one slower than a SYNC."""


EMF_MAX = 3000.0
"""Kt/L (A per rad), the back-EMF's current scale, at most: 0.5 N·m/A over 0.17 mH."""
START_EMF = (0.0, 150.0)
"""Kt/L a search starts from: none (a first-order loop), and a NEMA 17 motor's
(0.3 N·m/A over 2 mH)."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    t_ms = obs.metadata.sync_period_s * 1e3
    return [Block("current_lag_ms", 2, 0.5 * t_ms, 0.0, 20.0 * t_ms, rejects=(1,)),
            # Kt/L, from none; R/L, the phase's own pole (100-2,700 rad/s on datasheets).
            Block("emf_per_inductance", 1, 0.0, 0.0, EMF_MAX, rejects=(1,)),
            Block("log_phase_pole", 1, math.log(500.0), math.log(30.0), math.log(1e4))]


def starts(model: Model, p: Params) -> list[Starts]:
    # A lag looks like a negative sensor delay: start with the sensor's share moved over.
    a1 = float(p[model.layout.slices["sensor_a1_ms"]][0])
    return [{"current_lag_ms": [lag, lag], "sensor_a1_ms": [a1 + lag],
             "emf_per_inductance": [emf]} for emf in START_EMF for lag in START_LAGS_MS]


def current_response(model: Model, p: Params, response_a: Phasors, response_b: Phasors
                     ) -> tuple[Phasors, Phasors]:
    # A first-order loop per phase at each of the waveform's harmonics.
    tau = model.block(p, "current_lag_ms") * 1e-3
    s = 1j * model.obs.omega[:, None] * model.current_orders[None, :]
    return response_a * (1.0 / (1.0 + s * tau[0])), response_b * (1.0 / (1.0 + s * tau[1]))


def _rejected(model: Model, emf: Grid, lag: float, pole: float) -> Grid:
    """The current a PI loop of time constant ``lag`` lets a back-EMF (per Kt, on the grid,
    (…, S, N)) make, per unit of Kt/L: −s/((s + 1/lag)(s + pole)) at every order the grid
    holds. Orders above the modelled ones count: the swing's top order beats with the
    currents' fundamental into the one above it, and cut there, the slowest holds near
    the rotor's mode kept most of a fit's χ² at that top order."""
    n = emf.shape[-1]
    s = 1j * model.obs.omega[:, None] * np.arange(n // 2 + 1)
    admittance = s * lag / ((1.0 + s * lag) * (s + pole))
    out: Grid = -np.fft.irfft(np.fft.rfft(emf, axis=-1) * admittance, n=n, axis=-1)
    return out


def current_motion(model: Model, p: Params, m: Motion, speed: Grid) -> tuple[Grid, Grid]:
    g = model.scalar(p, "emf_per_inductance")
    if g == 0.0:
        return m.i_a, m.i_b
    tau = model.block(p, "current_lag_ms") * 1e-3
    pole = math.exp(model.scalar(p, "log_phase_pole"))
    pa, pb = model.magnet_weights(p, m)
    # e/Kt = ω·∂τ/∂i on the grid; the loop's current against it, times Kt/L.
    return (m.i_a + g * _rejected(model, speed * pa, float(tau[0]), pole),
            m.i_b + g * _rejected(model, speed * pb, float(tau[1]), pole))


def current_motion_response(model: Model, p: Params, m: Motion, d_theta: Phasors
                            ) -> Phasors:
    g = model.scalar(p, "emf_per_inductance")
    if g == 0.0:
        return np.zeros(d_theta.shape, dtype=np.complex128)
    tau = model.block(p, "current_lag_ms") * 1e-3
    pole = math.exp(model.scalar(p, "log_phase_pole"))
    pa, pb = model.magnet_weights(p, m)
    scale = model.kt_factor(p, m.i_a, m.i_b) * m.modulation
    d_speed = ((model.jw * d_theta) @ model.synth).real  # (…, S, N)
    moved = np.zeros(d_speed.shape)
    for weight, lag in ((pa, float(tau[0])), (pb, float(tau[1]))):
        moved = moved + g * scale * weight * _rejected(model, d_speed * weight, lag, pole)
    return model.analysed(moved)


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
        **_back_emf(fit, cov),
    }


def _back_emf(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    """The loop's current against the back-EMF, where the fit found one."""
    g, g_sigma = value(fit, sigmas(cov), "emf_per_inductance")
    if g <= 0.0:
        return {"back_emf": None}
    pole, pole_sigma = value(fit, sigmas(cov), "log_phase_pole")
    return {"back_emf": {
        "kt_over_inductance_A_per_rad": g, "kt_over_inductance_sigma": g_sigma,
        "phase_pole_rad_s": math.exp(pole), "phase_pole_relative_sigma": pole_sigma,
        "law": "PI loop tuned to its bandwidth: i = lag·i* − (Kt/L)·s/((s + ωb)(s + R/L))·"
               "ω·∂τ/∂i"}}


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
    hooks=Hooks(reads={Role.CURRENTS: ("current_lag_ms",),
                       Role.TORQUE: ("emf_per_inductance", "log_phase_pole")},
                current_response=current_response, current_motion=current_motion,
                current_motion_response=current_motion_response),
)
