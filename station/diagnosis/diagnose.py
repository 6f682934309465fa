"""Locate, name and model what the paper's model leaves out of a recording.

1. Fit the nominal model (the paper's torque model on the fixture's chain,
   amplifier offsets and gains, load angles, sensor timing).
2. Locate: where its residual is significant, per harmonic order and
   condition, with a confidence level; and where its "constants" (the
   amplifier offsets and gain imbalance, i.e. the optimal trims) drift from
   one condition to another.
3. Name: add each candidate effect's term group in turn, keep the best one
   only when it wins on conditions held out of the fit *and* by Schwarz's
   criterion, and repeat. A rival whose held-out residual is about as small
   is reported with it: the data cannot tell them apart, and the report
   names the experiment that would.
4. Model: the extended model's held-out residual against the nominal's.

Thresholds are stated in units of the measurement's own noise (χ²), so they
carry over to recordings from other benches and simulators.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from threadpoolctl import threadpool_limits

from station.analysis.timeline import Timeline
from station.core import GAIN_UNITY, Effect
from station.diagnosis.fit import Fit, HeldOut, fit, held_out, solve_linear, starts_from
from station.diagnosis.model import (
    CANDIDATES,
    DETENT_ORDERS,
    DISTORTION_ORDERS,
    FLUX_ORDERS,
    ChainKind,
    Model,
    ModelSpec,
    chain_for,
)
from station.diagnosis.observations import ConditionKey, Observations, observe

SIGNIFICANT_CONFIDENCE = 0.999
"""A residual or drift is reported as located when noise alone explains it less than
once in a thousand."""

MIN_GAIN_CHI2 = 50.0
"""A term group must cut the held-out χ² by at least this much (several σ of a χ²
difference for the few dozen parameters a group adds)."""

MIN_GAIN_FRACTION = 0.5
"""...and by at least this fraction of what is left: below it, what remains is the
model's fine detail, not a missing physical effect."""

SEPARABLE_RATIO = 2.0
"""A rival group that leaves less than this times the best one's held-out χ² cannot
be told apart from it on these data."""

MAX_EFFECTS = 3

SEPARATING_EXPERIMENTS: dict[frozenset[Effect], str] = {
    frozenset({Effect.FLUX_HARMONICS, Effect.CURRENT_DISTORTION}): (
        "record the phase currents (drive current sense or a current probe) while running: "
        "distortion shows in the current waveform, flux harmonics do not; or back-drive the "
        "motor with the drive disabled and record the back-EMF, whose harmonics are the flux's"
    ),
    frozenset({Effect.FLUX_HARMONICS, Effect.DETENT_TORQUE}): (
        "repeat the characterization at more currents including a low one: cogging torque "
        "does not change with current, flux-harmonic torque grows with it"
    ),
    frozenset({Effect.DETENT_TORQUE, Effect.CURRENT_DISTORTION}): (
        "record the drive's phase currents, or run at more currents: cogging does not change "
        "with current, distortion torque grows with it"
    ),
    frozenset({Effect.LOAD_RESONANCE, Effect.RELUCTANCE_TORQUE}): (
        "tap test or speed sweep with the rotor held: a compliant coupling keeps its frequency "
        "whatever the current, the magnetic spring's frequency moves with it"
    ),
}
_DEFAULT_EXPERIMENT = (
    "repeat the characterization with more speeds and currents, and trim steps of both signs, "
    "so that the two term groups' signatures (order, current scaling, load angle) part"
)


class LocatedKind(StrEnum):
    HARMONIC = "harmonic"  # the nominal model's residual at one order and condition
    PARAMETER_DRIFT = "parameter_drift"  # a "constant" of the nominal model moves


@dataclass(frozen=True)
class Located:
    """One place where the recording and the nominal model disagree."""

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
        if self.kind is LocatedKind.HARMONIC:
            assert self.condition is not None
            out.update(
                order=self.order,
                **self.condition.as_dict(),
                residual_rms_mps2=self.residual_rms_mps2,
                measured_rms_mps2=self.measured_rms_mps2,
            )
        else:
            out.update(
                parameter=self.parameter,
                per_condition=[
                    {**c.as_dict(), "value": v, "sigma": s}
                    for c, v, s in zip(conditions, self.values, self.sigmas, strict=True)
                ],
                trend=self.trend,
            )
        return out


@dataclass(frozen=True)
class Trial:
    """One candidate term group tried in one round of naming."""

    effect: Effect
    fit: Fit
    held: HeldOut

    @property
    def bic(self) -> float:
        return self.fit.bic


@dataclass(frozen=True)
class Round:
    base_held_chi2: float
    base_bic: float
    trials: tuple[Trial, ...]
    chosen: Effect | None


@dataclass(frozen=True)
class NamedEffect:
    """An effect the data support, with what the data cannot tell it from."""

    effect: Effect
    parameters: dict[str, Any]
    held_out_gain_chi2: float
    alternatives: tuple[Effect, ...] = ()
    experiment: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.effect.value,
            "parameters": self.parameters,
            "held_out_chi2_gain": round(self.held_out_gain_chi2, 1),
        }
        if self.alternatives:
            out["cannot_separate_from"] = [e.value for e in self.alternatives]
            out["separating_experiment"] = self.experiment
        return out


@dataclass(frozen=True)
class Diagnosis:
    observations: Observations
    nominal: Fit
    nominal_held: HeldOut
    extended: Fit
    extended_held: HeldOut
    located: tuple[Located, ...]
    # The optimal trims re-estimated per condition and their σ (per_condition_constants).
    constants: tuple[NDArray[np.float64], NDArray[np.float64]]
    effects: tuple[NamedEffect, ...]
    rounds: tuple[Round, ...]
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def mismatch(self) -> bool:
        return bool(self.effects) or any(loc.kind is LocatedKind.HARMONIC for loc in self.located)

    def held_out_rms(self, held: HeldOut) -> float:
        """RMS in m/s² of the held-out residual (each harmonic's both parts)."""
        physical = self.nominal.model.in_mps2(held.residuals)
        return float(math.sqrt(np.mean(physical**2) * 2.0))

    def to_dict(self) -> dict[str, Any]:
        obs = self.observations
        return {
            "mismatch": self.mismatch,
            "located": [loc.as_dict(obs.conditions) for loc in self.located],
            "effects": [e.as_dict() for e in self.effects],
            "fit": {
                "before": self.held_out_rms(self.nominal_held),
                "after": self.held_out_rms(self.extended_held),
                "before_chi2": round(self.nominal_held.total, 1),
                "after_chi2": round(self.extended_held.total, 1),
                "observations": self.nominal.observations,
                "held_out": "each condition in turn",
            },
            "nominal": nominal_parameters(self.nominal),
            "model": sorted(e.value for e in self.extended.model.spec.effects),
            "conditions": [c.as_dict() for c in obs.conditions],
            "segments": obs.count,
            "orders": obs.orders,
            "warnings": list(self.warnings),
        }


# --------------------------------------------------------------------------- fitting
def _extra_starts(spec: ModelSpec, effect: Effect | None) -> dict[str, list[float]]:
    extra: dict[str, list[float]] = {}
    if effect is None:
        extra["rotor_hz_at_1A"] = [40.0, 80.0, 250.0]
        if spec.chain is ChainKind.BELT:
            extra["belt_hz"] = [3.0, 8.0, 20.0, 60.0]
    if effect is Effect.LOAD_RESONANCE:
        extra["coupling_hz"] = [40.0, 80.0, 160.0, 320.0, 640.0]
    return extra


def fit_nominal(obs: Observations) -> Fit:
    model = Model(ModelSpec(chain_for(obs.metadata.gear_ratio)), obs)
    return fit(model, starts_from(model, None, _extra_starts(model.spec, None)), keep=2)


def fit_with(obs: Observations, base: Fit, effect: Effect) -> Fit:
    model = Model(base.model.spec.with_effect(effect), obs)
    return fit(model, starts_from(model, base, _extra_starts(model.spec, effect)))


# --------------------------------------------------------------------------- locating
def _confidence(chi2: float, dof: int) -> float:
    return float(stats.chi2.cdf(chi2, dof)) if dof > 0 else 0.0


def chi2_map(result: Fit) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """A fit's χ² per condition and order, (C, K), and the degrees of freedom per
    condition, (C,): both parts of every segment's phasor."""
    obs = result.model.obs
    res = result.residuals.reshape(2, obs.count, obs.orders)
    per_segment = (res**2).sum(axis=0)  # (S, K)
    conditions = len(obs.conditions)
    chi2 = np.zeros((conditions, obs.orders))
    np.add.at(chi2, obs.condition, per_segment)
    dof = 2 * np.bincount(obs.condition, minlength=conditions)
    return chi2, dof


def locate_harmonics(nominal: Fit) -> list[Located]:
    """Per condition and order: χ² of the nominal residual against the noise."""
    obs = nominal.model.obs
    chi2, dofs = chi2_map(nominal)
    in_mps2 = nominal.model.in_mps2(nominal.residuals)
    out: list[Located] = []
    for c, key in enumerate(obs.conditions):
        rows = obs.condition == c
        dof = int(dofs[c])
        for k in range(obs.orders):
            value = float(chi2[c, k])
            conf = _confidence(value, dof)
            if conf < SIGNIFICANT_CONFIDENCE:
                continue
            physical = in_mps2[:, rows, k]
            out.append(
                Located(
                    kind=LocatedKind.HARMONIC,
                    chi2=value,
                    dof=dof,
                    confidence=conf,
                    condition=key,
                    order=k + 1,
                    residual_rms_mps2=float(np.sqrt(np.mean((physical**2).sum(axis=0)))),
                    measured_rms_mps2=float(np.sqrt(np.mean(np.abs(obs.phasors[rows, k]) ** 2))),
                )
            )
    out.sort(key=lambda loc: loc.chi2, reverse=True)
    return out


def trim_constants(offsets_mA: NDArray[np.float64], gain_errors: NDArray[np.float64]
                   ) -> tuple[float, float, float]:
    """The amplifier's constants as the trims that null them: offsets A and B (mA)
    and the gain split (1/10000, half the A−B gain difference)."""
    return (-float(offsets_mA[0]), -float(offsets_mA[1]),
            -float(gain_errors[0] - gain_errors[1]) / 2.0 * GAIN_UNITY)


def per_condition_constants(nominal: Fit) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The optimal trims re-estimated at each condition alone, and their σ, (C, 3).

    Columns: offset A, offset B (mA, the negated amplifier offsets) and the gain
    split (1/10000, half the A−B gain difference that nulls the imbalance). The
    chain, timing and load angles stay at the nominal fit; only the amplifier's
    constants are solved again on each condition's segments.
    """
    obs = nominal.model.obs
    conditions = len(obs.conditions)
    values = np.full((conditions, 3), np.nan)
    sigmas = np.full((conditions, 3), np.nan)
    for c in range(conditions):
        sub = obs.subset(obs.condition == c)
        model = Model(nominal.model.spec, sub)
        p = model.layout.start()
        for block in nominal.model.layout.blocks:
            if block.name == "load_angle_rad":
                p[model.layout.slices[block.name]] = nominal.value(block.name)[c]
            else:
                p[model.layout.slices[block.name]] = nominal.value(block.name)
        p = solve_linear(model, p, passes=3)
        _, design = model.linear_design(p)
        flat = design.reshape(design.shape[0], -1)
        jac = np.concatenate([flat.real, flat.imag], axis=1).T
        try:
            cov = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            continue
        sl = model.layout.slices
        idx = model.linear_index().tolist()
        ia = idx.index(sl["amp_offset_mA"].start)
        ib = ia + 1
        ga = idx.index(sl["amp_gain_error"].start)
        gb = ga + 1
        values[c] = trim_constants(p[sl["amp_offset_mA"]], p[sl["amp_gain_error"]])
        split_var = (cov[ga, ga] + cov[gb, gb] - 2 * cov[ga, gb]) / 4.0 * GAIN_UNITY**2
        sigmas[c] = np.sqrt([cov[ia, ia], cov[ib, ib], max(split_var, 0.0)])
    return values, sigmas


def locate_drift(values: NDArray[np.float64], sigmas: NDArray[np.float64],
                 conditions: tuple[ConditionKey, ...]) -> list[Located]:
    """Constants of the nominal model that differ between conditions beyond their σ
    (``values``/``sigmas`` from ``per_condition_constants``)."""
    amps = np.array([c.amplitude_mA for c in conditions], dtype=float)
    out: list[Located] = []
    for column, name in enumerate(("optimal_offset_a_mA", "optimal_offset_b_mA",
                                   "optimal_gain_split")):
        v, s = values[:, column], sigmas[:, column]
        ok = np.isfinite(v) & np.isfinite(s) & (s > 0)
        if ok.sum() < 2:
            continue
        w = 1.0 / s[ok] ** 2
        mean = float(np.sum(w * v[ok]) / np.sum(w))
        chi2 = float(np.sum(w * (v[ok] - mean) ** 2))
        dof = int(ok.sum()) - 1
        conf = _confidence(chi2, dof)
        if conf < SIGNIFICANT_CONFIDENCE:
            continue
        slope = np.polyfit(amps[ok], v[ok], 1, w=np.sqrt(w))[0]
        out.append(
            Located(
                kind=LocatedKind.PARAMETER_DRIFT,
                chi2=chi2,
                dof=dof,
                confidence=conf,
                parameter=name,
                values=tuple(float(x) for x in v),
                sigmas=tuple(float(x) for x in s),
                trend=f"{slope * 1000:+.2f} per A of current amplitude",
            )
        )
    return out


# --------------------------------------------------------------------------- naming
def _supported(trial: Trial, base_held: float, base_bic: float) -> bool:
    gain = base_held - trial.held.total
    return gain > max(MIN_GAIN_CHI2, MIN_GAIN_FRACTION * base_held) and trial.bic < base_bic


def name_effects(obs: Observations, nominal: Fit, nominal_held: HeldOut,
                 progress: Callable[[str], None] | None = None
                 ) -> tuple[Fit, HeldOut, list[NamedEffect], list[Round]]:
    """Forward selection of term groups on held-out conditions (module note)."""
    current, current_held = nominal, nominal_held
    named: list[NamedEffect] = []
    rounds: list[Round] = []
    excluded: set[Effect] = set()
    while len(named) < MAX_EFFECTS:
        trials: list[Trial] = []
        for effect in CANDIDATES:
            if effect in current.model.spec.effects or effect in excluded:
                continue
            if progress is not None:
                progress(f"fitting {effect.value}")
            candidate = fit_with(obs, current, effect)
            trials.append(Trial(effect, candidate, held_out(candidate)))
        supported = [t for t in trials if _supported(t, current_held.total, current.bic)]
        supported.sort(key=lambda t: t.held.total)
        chosen = supported[0] if supported else None
        rounds.append(Round(current_held.total, current.bic, tuple(trials),
                            chosen.effect if chosen else None))
        if chosen is None:
            break
        rivals = tuple(
            t.effect for t in supported[1:]
            if t.held.total < SEPARABLE_RATIO * chosen.held.total + MIN_GAIN_CHI2
        )
        excluded.update(rivals)
        experiment = None
        if rivals:
            experiment = SEPARATING_EXPERIMENTS.get(
                frozenset({chosen.effect, rivals[0]}), _DEFAULT_EXPERIMENT
            )
        named.append(
            NamedEffect(
                effect=chosen.effect,
                parameters=effect_parameters(chosen.fit, chosen.effect),
                held_out_gain_chi2=current_held.total - chosen.held.total,
                alternatives=rivals,
                experiment=experiment,
            )
        )
        current, current_held = chosen.fit, chosen.held
    return current, current_held, named, rounds


def diagnose_observations(obs: Observations,
                          progress: Callable[[str], None] | None = None) -> Diagnosis:
    with threadpool_limits(limits=1, user_api="blas"):
        if progress is not None:
            progress("fitting the nominal model")
        nominal = fit_nominal(obs)
        nominal_held = held_out(nominal)
        constants = per_condition_constants(nominal)
        located = locate_harmonics(nominal) + locate_drift(*constants, obs.conditions)
        extended, extended_held, named, rounds = name_effects(obs, nominal, nominal_held, progress)
    warnings: list[str] = []
    if any(e.alternatives for e in named):
        warnings.append("some effects cannot be separated on these data; see each effect's "
                        "separating_experiment")
    return Diagnosis(
        observations=obs,
        nominal=nominal,
        nominal_held=nominal_held,
        extended=extended,
        extended_held=extended_held,
        located=tuple(located),
        constants=constants,
        effects=tuple(named),
        rounds=tuple(rounds),
        warnings=tuple(warnings),
    )


def diagnose(timeline: Timeline, progress: Callable[[str], None] | None = None) -> Diagnosis:
    """The whole diagnosis of one recording's timeline."""
    return diagnose_observations(observe(timeline), progress)


# --------------------------------------------------------------------------- reporting
def _sigmas(result: Fit) -> NDArray[np.float64]:
    """1σ of every parameter from the Jacobian, inflated by the Birge ratio when the
    model does not reach the noise (its own misfit then dominates)."""
    jac = result.jacobian
    dof = max(1, result.observations - result.parameters)
    birge = max(1.0, result.chi2 / dof)
    try:
        cov = np.linalg.pinv(jac.T @ jac) * birge
    except np.linalg.LinAlgError:
        return np.full(result.parameters, np.nan)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _complex_terms(values: NDArray[np.float64], sigma: NDArray[np.float64], scale: float
                   ) -> tuple[float, float, float]:
    """(magnitude, phase, σ of magnitude) of a (sin, cos) coefficient pair."""
    mag = math.hypot(values[0], values[1])
    phase = math.atan2(values[1], values[0])
    return mag * scale, phase, math.hypot(sigma[0], sigma[1]) * scale


def effect_parameters(result: Fit, effect: Effect) -> dict[str, Any]:
    """The effect's fitted parameters in physical (or dimensionless, where only a ratio
    is identifiable from acceleration) units, each with its 1σ."""
    sig = _sigmas(result)
    sl = result.model.layout.slices
    rated_A = result.model.obs.metadata.rated_current_mA / 1000.0
    out: dict[str, Any] = {}
    if effect is Effect.FLUX_HARMONICS:
        v, s = result.value("flux"), sig[sl["flux"]]
        for i, j in enumerate(FLUX_ORDERS):
            for p, phase in enumerate(("a", "b")):
                mag, ph, err = _complex_terms(v[4 * i + 2 * p:4 * i + 2 * p + 2],
                                              s[4 * i + 2 * p:4 * i + 2 * p + 2], 100.0)
                out[f"order_{j}_phase_{phase}"] = {"relative_to_Lm1_percent": mag,
                                                   "sigma_percent": err, "phase_rad": ph}
    elif effect is Effect.CURRENT_DISTORTION:
        v, s = result.value("distortion"), sig[sl["distortion"]]
        for i, h in enumerate(DISTORTION_ORDERS):
            for p, phase in enumerate(("a", "b")):
                pair = v[4 * i + 2 * p:4 * i + 2 * p + 2]
                mag = math.hypot(pair[0], pair[1]) * 100.0
                err = math.hypot(*s[4 * i + 2 * p:4 * i + 2 * p + 2]) * 100.0
                out[f"order_{h}_phase_{phase}"] = {
                    "relative_to_fundamental_percent": mag, "sigma_percent": err,
                    "phase_rad": math.atan2(-pair[1], pair[0]),
                }
    elif effect is Effect.DETENT_TORQUE:
        v, s = result.value("detent"), sig[sl["detent"]]
        for i, d in enumerate(DETENT_ORDERS):
            mag, ph, err = _complex_terms(v[2 * i:2 * i + 2], s[2 * i:2 * i + 2],
                                          100.0 / rated_A)
            out[f"order_{d}"] = {"peak_percent_of_rated_holding_torque": mag,
                                 "sigma_percent": err, "phase_rad": ph}
    elif effect is Effect.LOAD_RESONANCE:
        for name, key in (("coupling_hz", "coupling_resonance_hz"),
                          ("coupling_damping_ratio", "damping_ratio"),
                          ("coupling_inertia_fraction", "inertia_fraction_beyond_coupling")):
            out[key] = float(result.value(name)[0])
            out[f"{key}_sigma"] = float(sig[sl[name]][0])
    elif effect is Effect.RELUCTANCE_TORQUE:
        lam = float(result.value("reluctance")[0])
        out["peak_percent_of_holding_torque_at_rated"] = lam * rated_A * 100.0
        out["sigma_percent"] = float(sig[sl["reluctance"]][0]) * rated_A * 100.0
    return out


def nominal_parameters(result: Fit) -> dict[str, Any]:
    """What the nominal model found, in the units a motion engineer uses."""
    obs = result.model.obs
    rated_A = obs.metadata.rated_current_mA / 1000.0
    f1 = float(result.value("rotor_hz_at_1A")[0])
    damping = float(result.value("rotor_damping_per_s")[0])
    w_rated = 2 * math.pi * f1 * math.sqrt(rated_A)
    offsets = result.value("amp_offset_mA")
    gains = result.value("amp_gain_error")
    rho = result.value("load_angle_rad")
    friction = [
        {**c.as_dict(), "load_angle_rad": float(r),
         "friction_percent_of_rated_holding_torque":
             100.0 * math.sin(abs(float(r))) * c.amplitude_mA / 1000.0 / rated_A}
        for c, r in zip(obs.conditions, rho, strict=True)
    ]
    out: dict[str, Any] = {
        "rotor_natural_hz_at_rated_current": w_rated / (2 * math.pi),
        "rotor_damping_ratio": damping / (2 * w_rated),
        "sensor_delay_ms": float(result.value("delay_ms")[0]),
        "angle_offset_rad": float(result.value("angle_offset_rad")[0]),
        "optimal_trims": {
            "offset_a_mA": -float(offsets[0]),
            "offset_b_mA": -float(offsets[1]),
            # Equal effective gains (1 + e)·g on both phases, their mean at unity.
            "gain_a": 2 * GAIN_UNITY * (1 + float(gains[1])) / (2 + float(gains[0] + gains[1])),
            "gain_b": 2 * GAIN_UNITY * (1 + float(gains[0])) / (2 + float(gains[0] + gains[1])),
        },
        "load_angles": friction,
    }
    if result.model.spec.chain is ChainKind.BELT:
        out["belt_hz"] = float(result.value("belt_hz")[0])
        out["belt_damping_ratio"] = float(result.value("belt_damping_ratio")[0])
        out["load_inertia_ratio"] = float(result.value("load_inertia_ratio")[0])
    return out
