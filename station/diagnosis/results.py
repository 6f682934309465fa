"""What a diagnosis finds, as records that carry their own meaning: where the recording and a
model disagree (``Located``), the models tried and the tests between them, the ids named
with their readouts, findings said in words, what is left unexplained, and the whole
``Diagnosis`` with its JSON; and how the chosen model's nominal parameters read, each
beside its state (a reading resting on a limit is null, never a value)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.core import GAIN_UNITY, Effect
from station.diagnosis import chain
from station.diagnosis.axes import AxisCoupling
from station.diagnosis.effects.friction import HEALTHY_COULOMB
from station.diagnosis.fit import Fit, HeldOut, ParameterJudgement, ParameterState, covariance
from station.diagnosis.layout import ChainKind, ModelSpec
from station.diagnosis.observations import ConditionKey, Observations

HELD_SHARE = 0.5
"""Of the threshold a fitted gain must clear, what its held-out gain must reach: a group
whose gain does not carry over to the conditions it was not fitted on is fitting those
conditions, not physics (friction beside a strong current distortion gained 807 fitted
and 7 held out)."""


class LocatedKind(StrEnum):
    HARMONIC = "harmonic"  # the nominal model's residual at one order and condition
    PARAMETER_DRIFT = "parameter_drift"  # a "constant" of the nominal model moves
    UNEXPLAINED = "unexplained"  # what the best model still leaves, with no id for it
    SENSOR_AXIS = "sensor_axis"  # tangential ripple on another sensor axis (axes.py)


@dataclass(frozen=True)
class Located:
    """One place where the recording and a model disagree."""

    kind: LocatedKind
    chi2: float
    dof: int
    confidence: float
    condition: ConditionKey | None = None
    order: int | None = None
    residual_rms_mps2: float | None = None
    measured_rms_mps2: float | None = None
    parameter: str | None = None
    values: tuple[float, ...] = ()
    sigmas: tuple[float, ...] = ()
    trend: str | None = None

    def as_dict(self, conditions: tuple[ConditionKey, ...]) -> dict[str, Any]:
        out: dict[str, Any] = {
            "kind": self.kind.value,
            "chi2": round(self.chi2, 2),
            "dof": self.dof,
            "confidence": self.confidence,
        }
        if self.kind is LocatedKind.PARAMETER_DRIFT:
            out.update(
                parameter=self.parameter,
                per_condition=[
                    {**c.as_dict(), "value": v, "sigma": s}
                    for c, v, s in zip(conditions, self.values, self.sigmas, strict=True)
                ],
                trend=self.trend,
            )
        else:
            assert self.condition is not None
            out.update(
                order=self.order,
                **self.condition.as_dict(),
                residual_rms_mps2=self.residual_rms_mps2,
                measured_rms_mps2=self.measured_rms_mps2,
            )
            if self.kind is LocatedKind.SENSOR_AXIS:
                out["axis"] = self.parameter
        return out


@dataclass(frozen=True)
class Candidate:
    """One model tried: its fit and its residuals on held-out conditions."""

    spec: ModelSpec
    fit: Fit
    held: HeldOut
    explained: float = 0.0  # χ² its groups took from the nominal model's
    # With a once-per-revolution group beside others: the χ² of the same model with that
    # group tied to angles that are not the rotor's (``wrong_angle_chi2``).
    wrong_angle: float | None = None

    @property
    def effects(self) -> frozenset[Effect]:
        return self.spec.effects

    @property
    def label(self) -> str:
        return self.spec.label()


@dataclass(frozen=True)
class Test:
    """Whether ``larger`` beats ``smaller`` by more than noise (the module note's rule)."""

    smaller: Candidate
    larger: Candidate
    added: int  # parameters added
    chi2_gain: float
    held_gain: float
    f_threshold: float
    bic_threshold: float
    noise: float  # the larger model's χ² per dof, floored at 1
    elsewhere: float = 0.0  # χ² the best of a scan gains on noise alone (``compare``)
    model_error: float = 0.0  # χ² a group may gain on the smaller's groups' errors
    # The gains again, each cell's in units of what the larger model leaves there
    # (``cell_gain``), and the thresholds they must clear: those above at unit noise.
    cell_chi2_gain: float = math.inf
    cell_held_gain: float = math.inf
    cell_threshold: float = 0.0
    cell_held_threshold: float = 0.0

    @property
    def significant(self) -> bool:
        """Gains beyond noise, by a model whose added groups stay the physics they name
        (none resting on a bound that makes it something else: ``Block.rejects``), and
        beyond what the larger model itself leaves in the cells where it gains."""
        threshold = max(self.f_threshold, self.bic_threshold)
        return (self.chi2_gain > threshold
                and self.held_gain > max(
                    self.added * self.noise + self.elsewhere + self.model_error,
                    HELD_SHARE * threshold)
                and self.cell_chi2_gain > self.cell_threshold
                and self.cell_held_gain > self.cell_held_threshold
                and not self.larger.fit.rejected)


@dataclass(frozen=True)
class Round:
    """One size of the search: the models tried, the best, and the verdict."""

    size: int
    tried: tuple[Test, ...]
    chosen: Candidate | None


@dataclass(frozen=True)
class NamedEffect:
    """An effect the data support, with what the data cannot tell it from."""

    effect: Effect
    parameters: dict[str, Any]
    held_out_gain_chi2: float
    explains: tuple[tuple[ConditionKey, int, float, float], ...] = ()  # cells: χ² before/after
    alternatives: tuple[Effect, ...] = ()
    experiment: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.effect.value,
            "parameters": self.parameters,
            "held_out_chi2_gain": round(self.held_out_gain_chi2, 1),
            "evidence": [
                {**c.as_dict(), "order": k, "chi2_before": round(b, 1),
                 "chi2_after": round(a, 1)}
                for c, k, b, a in self.explains
            ],
        }
        if self.alternatives:
            out["cannot_separate_from"] = [e.value for e in self.alternatives]
            out["separating_experiment"] = self.experiment
        return out


@dataclass(frozen=True)
class Finding:
    """Something the nominal model cannot describe, said in words (and why)."""

    text: str
    parameter: str | None = None
    chi2_gain: float = 0.0
    values: dict[str, float] = field(default_factory=dict)  # what the text quotes

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"finding": self.text, "parameter": self.parameter,
                               "chi2_gain": round(self.chi2_gain, 1)}
        if self.values:
            out["values"] = {k: round(v, 6) for k, v in self.values.items()}
        return out


@dataclass(frozen=True)
class LoneHold:
    """The one hold that carries a held-out residual the others do not (``Unexplained``)."""

    condition: ConditionKey
    start_s: float
    stop_s: float
    chi2: float
    values: int

    def as_dict(self) -> dict[str, Any]:
        return {**self.condition.as_dict(), "start_s": round(self.start_s, 3),
                "stop_s": round(self.stop_s, 3), "held_out_chi2": round(self.chi2, 1),
                "values": self.values}


@dataclass(frozen=True)
class Unexplained:
    """What the chosen model leaves on held-out conditions beyond the noise; ``lone``: the
    hold without which it would not be beyond it (then it is not ``significant``)."""

    chi2: float
    values: int  # held-out residual values (both parts of every phasor)
    significant: bool
    lone: LoneHold | None = None

    @property
    def ratio(self) -> float:
        return self.chi2 / max(self.values, 1)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"held_out_chi2": round(self.chi2, 1), "values": self.values,
                               "chi2_per_value": round(self.ratio, 3),
                               "significant": self.significant}
        if self.lone is not None:
            out["carried_by_one_hold"] = self.lone.as_dict()
        return out


@dataclass(frozen=True)
class Diagnosis:
    observations: Observations
    nominal: Candidate
    extended: Candidate
    located: tuple[Located, ...]
    # The optimal trims re-estimated per condition and their σ (per_condition_constants).
    constants: tuple[NDArray[np.float64], NDArray[np.float64]]
    effects: tuple[NamedEffect, ...]
    rounds: tuple[Round, ...]
    findings: tuple[Finding, ...]
    unexplained: Unexplained
    judgements: tuple[ParameterJudgement, ...]
    warnings: tuple[str, ...] = field(default_factory=tuple)
    sensor_axes: tuple[AxisCoupling, ...] = ()

    @property
    def nominal_held(self) -> HeldOut:
        return self.nominal.held

    @property
    def extended_held(self) -> HeldOut:
        return self.extended.held

    @property
    def mismatch(self) -> bool:
        return bool(self.effects) or bool(self.findings) or self.unexplained.significant

    def held_out_rms(self, held: HeldOut) -> float:
        """Noise-weighted RMS in m/s² of a held-out residual: χ² over the sum of weights,
        so it falls exactly when χ² does."""
        weight = self.nominal.fit.model.weight
        total = float(np.sum(weight**2)) * 2.0
        return float(math.sqrt(held.total / total)) if total > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        obs = self.observations
        return {
            "mismatch": self.mismatch,
            "located": [loc.as_dict(obs.conditions) for loc in self.located],
            "effects": [e.as_dict() for e in self.effects],
            "fit": {
                "before": self.held_out_rms(self.nominal.held),
                "after": self.held_out_rms(self.extended.held),
                "before_chi2": round(self.nominal.held.total, 1),
                "after_chi2": round(self.extended.held.total, 1),
                "observations": int(self.nominal.held.residuals.size),
                "held_out": "each condition in turn",
                "rms": "inverse-variance weighted, m/s²",
            },
            "unexplained": self.unexplained.as_dict(),
            "findings": [f.as_dict() for f in self.findings],
            "sensor_axes": [a.as_dict() for a in self.sensor_axes],
            # The chain, trims and sensor as the chosen model found them (the nominal
            # model's own when nothing is named).
            "nominal": nominal_parameters(self.extended.fit, self.judgements),
            "conditions": [c.as_dict() for c in obs.conditions],
            "segments": obs.count,
            "segments_settled_by_model": obs.model_settled,
            "segments_ringing": obs.ringing,
            "skipped": [s.as_dict() for s in obs.skipped],
            "orders": obs.orders,
            "warnings": list(self.warnings),
        }


LIMITED_READINGS = {
    "sensor_delay_ms": ("sensor_a1_ms",),
    "sensor_bandwidth_hz": ("sensor_a1_ms", "sensor_a2_ms2"),
    "rotor_damping_ratio": ("rotor_damping_ratio",),
    "rotor_natural_hz_at_rated_current": ("log_rotor_hz",),
}
"""The nominal readings and the parameters they rest on: one resting on a limit (or pushed
past it) is reported as null beside its state, never as a number (a dead-time recording's
sensor read 82,401,615 Hz, another's 400.0000002 Hz, ICD's floor)."""


def sensor_bandwidth_hz(a1_ms: float, a2_ms2: float) -> float | None:
    """Where |1/(1 + a1·s + a2·s²)|² falls to one half, Hz (None for no low-pass at all).

    With a2 at zero the low-pass is first order and its bandwidth is 1/(2π·a1): the old
    reading, 1/(2π·√a2), ran to 82 MHz there. In ω² = u: a2²u² + (a1² − 2a2)u − 1 = 0."""
    if a1_ms <= 0.0 and a2_ms2 <= 0.0:
        return None
    b = a1_ms * a1_ms - 2.0 * a2_ms2
    if a2_ms2 <= 0.0:
        u = 1.0 / b
    else:
        u = (-b + math.sqrt(b * b + 4.0 * a2_ms2 * a2_ms2)) / (2.0 * a2_ms2 * a2_ms2)
    return 1e3 * math.sqrt(u) / (2.0 * math.pi)


def bearing_friction(result: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    """The friction every motor has, as the fitted model holds it (CLI.md's healthy unit):
    Coulomb forward and reverse and the viscous drag, in % of the rated holding torque at
    the motor shaft, each with its 1σ; and whether a level is beyond a healthy unit's.

    The drag is the chain's damping seen as a mean torque (``chain.drag_coefficient``),
    its σ propagated from the fit's covariance through a central difference of it."""
    model = result.model
    rated_A = model.rated_A
    sl = model.layout.slices["friction_coulomb"]
    scale = 100.0 * model.gear_ratio / rated_A  # load torque in Kt units → % at the motor
    levels = result.params[sl] * scale
    level_sigma = np.sqrt(np.maximum(np.diag(cov)[sl], 0.0)) * scale

    def drag(p: NDArray[np.float64]) -> float:
        return 100.0 * chain.drag_coefficient(chain.stages_at(model, p)) / rated_A

    p = result.params
    gradient = np.zeros(p.size)
    for i in model.chain_index():
        step = 1e-6 * max(1.0, abs(float(p[i])))
        up, down = p.copy(), p.copy()
        up[i] += step
        down[i] -= step
        gradient[i] = (drag(up) - drag(down)) / (2.0 * step)
    fastest = float(np.max(np.abs(model.obs.omega))) / model.rotor_teeth
    viscous = drag(p)
    viscous_sigma = math.sqrt(max(float(gradient @ cov @ gradient), 0.0))
    limit = 100.0 * HEALTHY_COULOMB
    return {
        "coulomb_forward_percent_of_rated_holding_torque": float(levels[0]),
        "coulomb_forward_sigma_percent": float(level_sigma[0]),
        "coulomb_reverse_percent_of_rated_holding_torque": float(levels[1]),
        "coulomb_reverse_sigma_percent": float(level_sigma[1]),
        "viscous_percent_per_rad_s": viscous,
        "viscous_sigma_percent_per_rad_s": viscous_sigma,
        "viscous_percent_at_fastest_speed": viscous * fastest,
        "healthy_coulomb_limit_percent": limit,
        "beyond_healthy": bool(np.any(levels > limit)),
    }


def nominal_parameters(result: Fit, judgements: Iterable[ParameterJudgement] = ()
                       ) -> dict[str, Any]:
    """What the nominal model found, in the units a motion engineer uses, each with its
    1σ, and the state of any that is not simply fitted."""
    obs = result.model.obs
    model = result.model
    rated_A = obs.metadata.rated_current_mA / 1000.0
    cov = covariance(result)
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sl = model.layout.slices
    offsets = result.value("amp_offset_mA")
    gains = result.value("amp_gain_error")
    rho = result.value("load_angle_rad")
    rho_sig = sig[sl["load_angle_rad"]]
    f1 = math.exp(result.scalar("log_rotor_hz"))
    f1_sig = f1 * float(sig[sl["log_rotor_hz"]][0])
    friction = [
        {**c.as_dict(), "load_angle_rad": float(r), "load_angle_sigma_rad": float(s),
         "friction_percent_of_rated_holding_torque":
             100.0 * math.sin(abs(float(r))) * c.amplitude_mA / 1000.0 / rated_A}
        for c, r, s in zip(obs.conditions, rho, rho_sig, strict=True)
    ]
    states = {j.name: j for j in judgements if j.state is not ParameterState.FITTED}
    a1 = result.scalar("sensor_a1_ms")
    a2 = result.scalar("sensor_a2_ms2")
    out: dict[str, Any] = {
        "chain": model.spec.chain.value,
        "rotor_natural_hz_at_rated_current": f1 * math.sqrt(rated_A),
        "rotor_natural_hz_sigma": f1_sig * math.sqrt(rated_A),
        "rotor_damping_ratio": result.scalar("rotor_damping_ratio"),
        "rotor_damping_ratio_sigma": float(sig[sl["rotor_damping_ratio"]][0]),
        "sensor_delay_ms": a1,
        "sensor_delay_ms_sigma": float(sig[sl["sensor_a1_ms"]][0]),
        "sensor_bandwidth_hz": sensor_bandwidth_hz(a1, a2),
        "optimal_trims": {
            "offset_a_mA": -float(offsets[0]),
            "offset_b_mA": -float(offsets[1]),
            # Equal effective gains (1 + e)·g on both phases, their mean at unity.
            "gain_a": 2 * GAIN_UNITY * (1 + float(gains[1])) / (2 + float(gains[0] + gains[1])),
            "gain_b": 2 * GAIN_UNITY * (1 + float(gains[0])) / (2 + float(gains[0] + gains[1])),
        },
        "optimal_trims_sigma": {
            "offset_a_mA": float(sig[sl["amp_offset_mA"]][0]),
            "offset_b_mA": float(sig[sl["amp_offset_mA"]][1]),
        },
        "load_angles": friction,
        "friction": bearing_friction(result, cov),
        "chi2_per_dof": result.chi2 / result.dof,
        "states": {name: {"state": j.state.value, "value": j.value, "sigma": j.sigma,
                          "bound": j.bound, "chi2_gain": j.chi2_gain}
                   for name, j in states.items()},
    }
    # A value resting on its limit is the limit, not a measurement: said in ``states``.
    for key, names in LIMITED_READINGS.items():
        if key in out and any(n in states for n in names):
            out[key] = None
    if model.spec.chain is ChainKind.BELT:
        hz = math.exp(result.scalar("log_belt_hz"))
        ratio = math.exp(result.scalar("log_load_ratio"))
        out["belt_hz_motor_held"] = hz
        out["belt_hz_sigma"] = hz * float(sig[sl["log_belt_hz"]][0])
        out["belt_damping_ratio"] = result.scalar("belt_damping_ratio")
        out["belt_damping_ratio_sigma"] = float(sig[sl["belt_damping_ratio"]][0])
        out["load_damping_ratio"] = result.scalar("load_damping_ratio")
        out["load_damping_ratio_sigma"] = float(sig[sl["load_damping_ratio"]][0])
        out["load_inertia_ratio"] = ratio
        out["load_inertia_ratio_sigma"] = ratio * float(sig[sl["log_load_ratio"]][0])
        out["gear_ratio"] = obs.metadata.gear_ratio
    modes = chain.modes(model, result.params, rated_A)
    out["chain_modes_at_rated_current"] = [{"frequency_hz": f, "damping_ratio": z}
                                           for f, z in modes]
    return out
