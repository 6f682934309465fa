"""Larger models fitted for the naming: a model with more term groups started from its base,
from the unbent nominal and from each group's own starts (``effects``), kept never worse
than the model it extends, and each made a ``Candidate`` with its held-out residuals."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import terms
from station.diagnosis.fit import (
    Fit,
    best_of,
    chosen_starts,
    fit,
    held_out,
    polish,
    polished_on,
    rank_passed,
    screen,
)
from station.diagnosis.layout import ChainKind, ModelSpec
from station.diagnosis.model import Model
from station.diagnosis.nominal import GRID_EXACT, nominal_starts, transplanted
from station.diagnosis.observations import Observations
from station.diagnosis.results import Candidate

REGRID_CHI2 = 3.0
"""A base fitting worse than this χ²/dof has likely bent its chain: new groups are also
started from the chain grid."""
REGRID_KEEP = 2
"""Best chain-grid points (with the new groups solved) searched from when regridding."""


REFINE_TOLERANCE = 1.0
"""How much a smaller model must gain, in units of its noise's χ² per value, when polished
again from a larger model's point (``Search.refined``) to be taken instead: less changes
no test."""


FINALISTS = 2
"""A larger model's starts polished in full after the short tournament (``best_of``)."""
SWAPPED_FINALISTS = 1
"""Chains far from the base (``EffectTerms.far_starts``: a coupling's from its base's belt)
polished in full after their own short tournament."""


def fit_spec(obs: Observations, spec: ModelSpec, base: Fit, free: Fit | None = None,
             grid: tuple[tuple[NDArray[np.float64], float], ...] | None = None,
             *, others: Sequence[Fit] = ()) -> Fit:
    """A model with more term groups than ``base``, started from it, from the unbent
    nominal fit ``free`` and from each new group's own starting points; and, when the base
    fits badly (it has bent its chain to hide what it lacks), from the chains of the
    ``others`` one group smaller (each bent its own way), and from the chain grid again
    (``grid``: its best points after their first linear pass, made already, each with
    the χ² that pass predicted: ``Search.shared_grid``)."""
    model = Model(spec, obs)
    start = transplanted(model, base)
    starts = [start]
    zeroed = start.copy()
    zeroed[model.layout.slices["load_angle_rad"]] = 0.0
    starts.append(zeroed)
    estimated = []
    added = spec.effects - base.model.spec.effects
    bent = is_bent(base)
    for effect in added:
        declared = terms(effect)
        if declared.starts is not None:
            made = [model.with_values(start, values)
                    for values in declared.starts(model, start)]
            if declared.tournament:
                estimated += made
            else:
                starts += made
        if declared.estimates is not None:
            estimated += [model.with_values(start, values)
                          for values in declared.estimates(model, start, screen)]
    if bent and not base.model.spec.effects:
        # The nominal bent its chain to hide what it lacks: the chain grid again, with the
        # new groups' linear parts solved at every point, finds the chain they leave
        # behind. Larger models start from the chain their best subset found.
        ranked = (screen(model, nominal_starts(model), exact=GRID_EXACT) if grid is None
                  else rank_passed(model, list(grid), GRID_EXACT))
        estimated += [x for _, x in ranked[:REGRID_KEEP]]
    if bent:
        # A bent base's chain is where its own groups were best hidden, and another subset
        # may have bent it elsewhere, nearer the chain the larger model needs.
        estimated += [transplanted(model, other) for other in others]
    chosen = chosen_starts(model, starts, 2, estimated)
    if bent and free is not None:
        # The unbent chain and load angles, with the new groups' linear parts solved: these
        # start worse than the bent ones, so they are ranked among themselves.
        unbent = transplanted(model, free)
        made = [model.with_values(unbent, v) for e in added
                if (maker := terms(e).starts) is not None for v in maker(model, unbent)]
        chosen += chosen_starts(model, [unbent, *made], 2)
    # Starts spread over a grid (a coupling's chains) have no first heat (``tournament``).
    heat = not any(terms(e).tournament for e in added)
    result = best_of(model, chosen, finalists=FINALISTS, heat=heat)
    for effect in added:
        far = terms(effect).far_starts
        if far is None:
            continue
        # Chains far from the base (its belt as the coupling): ranked apart.
        chains = [model.with_values(start, v) for v in far(model, start)]
        swapped = chosen_starts(model, chains, len(chains))
        if swapped:
            other = best_of(model, swapped, finalists=SWAPPED_FINALISTS, heat=False)
            result = min(result, other, key=lambda f: f.chi2)
    return never_worse(model, result, base, start)


def is_bent(base: Fit) -> bool:
    """Whether ``base`` fits so badly that a larger model searches the chain grid again
    (``REGRID_CHI2``)."""
    return base.chi2 > REGRID_CHI2 * base.dof


def never_worse(model: Model, result: Fit, base: Fit, start: NDArray[np.float64]) -> Fit:
    """``result``, or when it fits worse than ``base`` a polish from ``start`` (the base's
    own point in ``model``) if that does better.

    Every start had its linear parameters solved again, which can lose the base's own
    point; a larger model must never fit worse than the one it extends.
    """
    if result.chi2 <= base.chi2:
        return result
    kept = polish(model, start)
    return kept if kept.chi2 < result.chi2 else result


Key = tuple[frozenset[Effect], bool]
"""A model of the search: its term groups, and whether the sensor's bend is in it."""


@dataclass(frozen=True)
class Job:
    """One model to fit, with everything its fit starts from: what a worker process needs."""

    spec: ModelSpec
    base: Fit  # the best fitted model one group smaller (or the same without bend)
    free: Fit  # the nominal model with free load angles
    earlier: Fit | None  # the same model fitted with the first pass's weights
    # The chain grid's best points after their first pass, when made for many jobs at once.
    grid: tuple[tuple[NDArray[np.float64], float], ...] | None = None
    others: tuple[Fit, ...] = ()  # the other fitted models one group smaller


def fit_job(obs: Observations, nominal_chi2: float, job: Job) -> Candidate:
    """A model fitted and judged on held-out conditions (in a worker or in process)."""
    if job.earlier is not None:
        # Fitted by the first pass: again with these weights, from where that pass
        # left it and from its base here. Only the floor near the chain's modes
        # moved, so the earlier optimum is a start beside the new one: searching the
        # chain grid again (most of a bent model's cost) finds the same basin. Its
        # sensor clock keeps the form that pass chose.
        model = Model(job.earlier.model.spec, obs)
        start = transplanted(model, job.base)
        result = fit(model, [job.earlier.params.copy(), start], keep=2)
        result = never_worse(model, kept_physics(model, result, job.earlier), job.base, start)
    else:
        result = fit_spec(obs, job.spec, job.base, job.free, job.grid, others=job.others)
        if (Effect.SENSOR_CLOCK_DRIFT in job.spec.effects
                and Effect.SENSOR_CLOCK_DRIFT not in job.base.model.spec.effects):
            # A sensor may hold its latest sample per SYNC (a sawtooth of delays) or
            # stamp its own: both forms are tried where the clock first enters, the
            # better one kept, and a model grown from it keeps that form (``Search._job``).
            # The form is the sensor's, not the other groups': fitted again in every
            # larger model it doubled the cost of each, most of a drifting clock's
            # diagnosis.
            other = fit_spec(obs, replace(job.spec, clock_wraps=not job.spec.clock_wraps),
                             job.base, job.free)
            if other.chi2 < result.chi2:
                result = other
    return candidate_of(obs, nominal_chi2, result)


def kept_physics(model: Model, result: Fit, earlier: Fit) -> Fit:
    """``result``, unless it rests where its groups are something else (``Block.rejects``)
    and the first pass's fit of the same model (``earlier``) did not: then a polish from
    that fit, if it does not either.

    With the second pass's weights a group can find a second basin of equal χ² that is
    no longer its physics, and the model was then judged as if the group had failed. On
    benchmark trial detent_torque+load_resonance@213179117 (a belt, the coupling at
    136 Hz and ζ 0.035) the coupling's damping went to its bound of 2 at χ² 2,041; from
    the first pass's point it fitted the same χ² inside its range, and took the held-out
    χ² from 5,862 to 2,145 for 1,633 values: named (tried there by ``local_groups``),
    where detent torque had been named alone beside a significant residual.
    """
    if not result.rejected or earlier.rejected:
        return result
    kept = polish(model, earlier.params.copy())
    return result if kept.rejected else kept


def candidate_of(obs: Observations, nominal_chi2: float, result: Fit) -> Candidate:
    """``result`` judged on held-out conditions, and against wrong angles where it has a
    once-per-revolution group beside others."""
    effects = result.model.spec.effects
    wrong = (wrong_angle_chi2(obs, result)
             if Effect.ROTOR_ECCENTRICITY in effects and len(effects) > 1 else None)
    return Candidate(result.model.spec, result, held_out(result),
                     max(0.0, nominal_chi2 - result.chi2), wrong)


WRONG_TURNS = (2, 3)
"""Times per revolution at which a once-per-revolution group is fitted for its null."""


def wrong_angle_chi2(obs: Observations, result: Fit) -> float:
    """χ² of ``result``'s model with its once-per-revolution group fitted at twice and
    three times the rotor's angle instead (the better of the two), from ``result``'s
    point with that group emptied.

    An eccentric rotor modulates the strongest torque by a few percent, so beside a
    strong flux harmonic its gain is a small share of what the flux took, and the share
    a strong group's own errors may leave (``MODEL_ERROR_SHARE``) hid it: on a
    development belt (flux_harmonics+rotor_eccentricity@204) it gained 447 against a
    threshold of 1848, and fitted an eccentricity of 3.6 % where the plant had 3.4 %.
    But a strong group's errors belong to its conditions and electrical angles, not to
    where the rotor stands in its revolution: the same group at angles that are not the
    rotor's gained 6 and 23 there, and 1 or less at every multiple on its twin with the
    flux alone. What it gains at those angles is what it may gain on errors.
    """
    best = math.inf
    for turns in WRONG_TURNS:
        model = Model(result.model.spec, obs.turning(turns))
        start = model.with_values(result.params, {"eccentricity": [0.0, 0.0],
                                                  "unbalance": [0.0, 0.0]})
        best = min(best, polish(model, start).chi2)
    return best


def refit_job(obs: Observations, nominal_chi2: float, smaller: Fit, larger: Fit
               ) -> Candidate | None:
    """``smaller`` polished again from ``larger``'s point (``polished_from``), as a
    candidate; None when that is no better."""
    result = polished_from(smaller, larger)
    return None if result is None else candidate_of(obs, nominal_chi2, result)


def polished_from(smaller: Fit, larger: Fit) -> Fit | None:
    """``smaller``'s model polished again from ``larger``'s point with the added groups
    taken out (``Search.refined``), when that fits better than ``smaller`` by more than
    ``REFINE_TOLERANCE``; else None."""
    model = smaller.model
    # The nominal was fitted from a grid of chains: only a belt a coupling found is new.
    starts = [transplanted(model, larger)] if model.spec.effects else []
    as_belt = coupling_as_belt(model, larger)
    if as_belt is not None:
        starts.append(as_belt)
    if not starts:
        return None
    result = min((polish(model, x) for x in starts), key=lambda f: f.chi2)
    if not result.chi2 < smaller.chi2 - REFINE_TOLERANCE * max(1.0, smaller.chi2 / smaller.dof):
        return None
    return result


def finish_job(obs: Observations, nominal_chi2: float, unfinished: Fit) -> Candidate | None:
    """``unfinished`` polished on from its point (``Search.finished``); the candidate when
    that fits better, else None."""
    result = polished_on(unfinished)
    return candidate_of(obs, nominal_chi2, result) if result.chi2 < unfinished.chi2 else None


def coupling_as_belt(model: Model, larger: Fit) -> NDArray[np.float64] | None:
    """``model``'s point (a belt without the coupling group) with the coupling ``larger``
    fitted moved into the declared belt, or None when there is none to move.

    On a belt the nominal fit can settle where its belt does nothing (a load of a few
    percent of the rotor on a belt damped at its ceiling), and a coupling group then
    fits the belt itself: development trial detent_torque@1981511873 (belt mode 143 Hz
    at ζ 0.12) was named detent_torque and load_resonance, the coupling at 152 Hz, ζ 0.15,
    with 83 % of the inertia beyond it, while the model's belt was unresolved. CLI.md makes
    a declared belt's mode nominal physics, so before the coupling's gain counts, the
    model without it is polished from that mode put where the fixture declares it: the
    inertia beyond the coupling becomes the load (its ratio to what stays at the rotor),
    the coupling's spring and damping the belt's, the rotor's own frequency and damping
    kept as they act on the lighter rotor. A second mode beside a belt the data resolve
    loses that belt's own mode this way and stays significant.
    """
    if not moves_into_belt(model.spec, larger):
        return None
    frac = float(larger.value("coupling_fraction")[0])
    rest = 1.0 - frac
    # The rotor keeps its own inertia only: its frequency on the field's spring rises, and
    # the damping ratio of the same drag with it.
    values = {
        "log_rotor_hz": [float(larger.value("log_rotor_hz")[0]) - 0.5 * math.log(rest)],
        "rotor_damping_ratio": [float(larger.value("rotor_damping_ratio")[0])
                                / math.sqrt(rest)],
        "log_load_ratio": [math.log(frac / rest)],
        "log_belt_hz": [float(larger.value("log_coupling_hz")[0])],
        "belt_damping_ratio": [float(larger.value("coupling_damping_ratio")[0])],
        "load_damping_ratio": [float(model.layout.start()[model.layout.slices[
            "load_damping_ratio"]][0])],
    }
    return model.with_values(transplanted(model, larger), values)


def moves_into_belt(smaller: ModelSpec, larger: Fit) -> bool:
    """Whether ``larger``'s coupling can be moved into the belt ``smaller`` declares
    (``coupling_as_belt``): a belt without a coupling of its own, beside a coupling with
    inertia on both sides of it."""
    if (smaller.chain is not ChainKind.BELT or Effect.LOAD_RESONANCE in smaller.effects
            or Effect.LOAD_RESONANCE not in larger.model.spec.effects):
        return False
    return 0.0 < float(larger.value("coupling_fraction")[0]) < 1.0
