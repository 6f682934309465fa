"""Locate, name and model what the paper's model leaves out of a recording.

1. Fit the nominal model: the paper's torque model on the chain the fixture
   declares (a rigid disk, or a belt with the metadata's gear ratio and
   unknown stiffness, damping and inertia ratio), the amplifier's offsets and
   gains, a load angle per condition (each trim step's rotor slipping from it
   along its spring until the mean torque meets the drag again) and the
   sensor's own low-pass. Chains are started from a grid over their natural
   frequencies and inertia ratio, with the linear parameters solved at every
   grid point, so a fit starts in the right basin whatever the belt. A
   parameter the data pull past a physical limit is a finding ("the nominal
   model cannot describe this recording"), never a result.
2. Use every hold: holds too short to judge their own settling are settled
   by the fitted chain's slowest decay and added, when that chain describes
   the recording (``SETTLE_TRUST_CHI2``); what is skipped says why.
3. Locate: where the nominal residual is significant, per harmonic order and
   condition, with a confidence level; and where its "constants" (the
   amplifier offsets and gain imbalance, i.e. the optimal trims) drift from
   one condition to another.
4. Name: every term group of the vocabulary is tried; a group counts when it
   lowers χ² by more than the noise explains for the parameters it adds (an F
   test against the larger model's own residual, and Schwarz's criterion) and
   lowers it on conditions held out of the fit by at least half as much; a
   group whose parameter was the best of a scan (the clock's rate) must also
   beat the best that scan finds in noise, and a group added beside others
   must also gain more than the share of their explained χ² that their own
   errors leave (no group reproduces an effect exactly, and a strong effect's
   few-percent miss would otherwise be named as a second effect), except a
   group tied to the rotor's mechanical angle, which must instead beat itself
   fitted at angles that are not the rotor's (``wrong_angle_chi2``); and both
   gains must hold counted cell by cell in units of what the larger model
   leaves there (``cell_gain``): a misfit in a few cells is not noise.
   Combinations of up to three are searched with a beam. A
   rival that fits held-out data about as well (a paired test on the held-out
   residuals) is reported with the experiment that would separate them.
5. Be honest about the unknown: when the best model still leaves held-out
   residual well beyond the noise, that is said, with where it is, and an id
   is kept only if it explains more of the mismatch than is left unexplained:
   physics that no id describes is never given the nearest id. What the named
   groups' own errors may leave (the share of step 4) is not such physics.

Thresholds are stated in units of the measurement's own noise (χ²), so they
carry over to recordings from other benches and simulators.

Each step has its module: ``nominal`` (1 and 2), ``locate`` (3), ``candidates`` and
``name`` (4 and 5), ``results`` (what they find, as records); every id's own knowledge is
in ``effects``. This module runs the steps in order, in worker processes when asked.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, ProcessPoolExecutor

import numpy as np
from threadpoolctl import threadpool_limits

from station.analysis.timeline import Timeline
from station.core import Effect, Mapper
from station.diagnosis import floors
from station.diagnosis.axes import ElementTurn, axis_couplings, with_axes_checked
from station.diagnosis.fit import fit, held_out, judge_parameters
from station.diagnosis.locate import (
    bend_finding,
    bound_findings,
    locate_axis,
    locate_drift,
    locate_harmonics,
    per_condition_constants,
)
from station.diagnosis.model import Model
from station.diagnosis.name import Search, name_effects
from station.diagnosis.nominal import (
    Nominal,
    aligned,
    balanced_fit,
    fit_nominal,
    nominal_of,
    settling_warnings,
    transplanted,
)
from station.diagnosis.observations import Observations
from station.diagnosis.results import Candidate, Diagnosis, Finding, LocatedKind

REWEIGHT_CHANGE = math.log(1.3)
"""Weights that moved by more than 30 % (at the 99th percentile) call for a second pass."""


UNRESOLVED_SIGMA = {
    "log_rotor_hz": 0.5, "log_load_ratio": 1.0, "log_belt_hz": 0.5,
    "rotor_damping_ratio": 1.0, "belt_damping_ratio": 1.0, "load_damping_ratio": 2.0,
}
"""Nominal parameters whose σ exceeds this (in their own units; logs: a factor e^σ) are
reported as not resolved by the recording rather than as values."""


def diagnose(timeline: Timeline, progress: Callable[[str], None] | None = None,
             workers: int = 1) -> Diagnosis:
    """The whole diagnosis of one recording's timeline; with ``workers`` above 1, the
    search's models are fitted side by side in that many processes (the same answer).
    A recording the diagnosis refuses is refused before any worker starts."""
    with threadpool_limits(limits=1, user_api="blas"):
        read = aligned(timeline)
    with _search_pool(workers) as pool:
        obs, fits = nominal_of(read.timeline, progress, map if pool is None else pool.map,
                               read)
        return diagnose_observations(obs, progress, nominal=fits, pool=pool, turn=read.turn)


@contextlib.contextmanager
def _search_pool(workers: int) -> Iterator[Executor | None]:
    """Worker processes for the search, started at once: each imports the diagnosis
    (about a second) while this process fits the nominal model."""
    if workers <= 1:
        yield None
        return
    # Spawned, not forked: a caller's threads (a progress display) may hold locks.
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_one_blas_thread) as pool:
        for _ in range(workers):
            pool.submit(_ready)
        yield pool


def _one_blas_thread() -> None:
    """A worker's linear algebra on one thread, as in the diagnosing process: the
    matrices are small, and threads of several workers on few cores fight (a nominal fit
    measured 2.6 times slower)."""
    threadpool_limits(limits=1, user_api="blas")


def _ready() -> None:
    """Nothing: the task that makes a worker start (and import this module)."""


def _reweighted(nominal: Nominal, chosen: Candidate, run: Mapper = map) -> Nominal | None:
    """The nominal model refitted with the floor magnified where the chosen model's chain
    has its modes, when that moves the weights materially; else None.

    A strong effect bends the nominal chain to hide it, so its modes, and the floor
    placed on them, can be far from where the explaining model puts them; every model
    of the recording must then be judged again with the better weights.
    """
    obs = nominal.balanced.model.obs
    floored = obs.with_floor(floors.floor(chosen.fit.model, chosen.fit.params))
    change = np.abs(np.log(floored.sigma / obs.sigma))
    if float(np.quantile(change, 0.99)) < REWEIGHT_CHANGE:
        return None
    model = Model(nominal.free.model.spec, floored)
    free = fit(model, [transplanted(model, nominal.free), transplanted(model, chosen.fit)],
               keep=2, max_nfev=80, run=run)
    return Nominal(balanced_fit(free, floored, run=run), free)


def diagnose_observations(obs: Observations, progress: Callable[[str], None] | None = None,
                          *, nominal: Nominal | None = None,
                          pool: Executor | None = None,
                          turn: ElementTurn | None = None) -> Diagnosis:
    with threadpool_limits(limits=1, user_api="blas"):
        if nominal is None:
            obs = with_axes_checked(obs)
        run: Mapper = map if pool is None else pool.map
        fits = nominal if nominal is not None else fit_nominal(obs, run=run)
        untrusted = fits.untrusted
        around: tuple[frozenset[Effect], tuple[Effect, ...]] | None = None
        previous: Search | None = None  # the first pass, whose fits start the second's
        for _ in range(2):
            # Every model is judged with the weights the nominal fit settled (its floor).
            nominal_fit = fits.balanced
            base = Candidate(nominal_fit.model.spec, nominal_fit, held_out(nominal_fit))
            search = Search(nominal_fit.model.obs, base, fits.free, progress, previous,
                            pool=pool)
            previous = search
            extended, named, rounds, left, candidates = name_effects(search, progress, around)
            if not extended.effects or around is not None:
                break
            around = (extended.effects, candidates)
            again = _reweighted(fits, extended, run)
            if again is None:
                break
            if progress is not None:
                progress("judging again with the chosen model's modes weighted")
            fits = again
        obs = nominal_fit.model.obs
        # Judged on the chosen model: a nominal fit bent by an effect it lacks presses its
        # bounds, and that is the effect's doing, not the chain's.
        judgements = judge_parameters(extended.fit, unresolved_sigma=UNRESOLVED_SIGMA)
        findings = bound_findings(judgements)
        constants = per_condition_constants(nominal_fit)
        located = locate_harmonics(nominal_fit) + locate_drift(*constants, obs.conditions)
        if left.significant:
            located += locate_harmonics(extended.fit, extended.held.residuals,
                                        LocatedKind.UNEXPLAINED)
        if extended.spec.sensor_bend:
            findings.append(bend_finding(extended, search.get(extended.effects)))
        axes = axis_couplings(obs)
        # The turn undone before the fits (measured on the recording as it came), then any
        # coupling the models still carry.
        shown = [(turn.finding(), turn.coupling, turn.conditions,
                  {"turn_deg": turn.coupling.turn_deg})] if turn is not None else []
        shown += [(a.finding(), a, obs.conditions, {}) for a in axes if a.significant]
        for text, coupled, conditions, extra in shown:
            findings.append(Finding(text, f"sensor_{coupled.axis.value}_axis",
                                    values={**extra, "in_phase_share": coupled.coupling,
                                            "in_phase_share_sigma": coupled.sigma}))
            located += locate_axis(coupled, conditions)
    warnings: list[str] = []
    if any(e.alternatives for e in named):
        warnings.append("some effects cannot be separated on these data; see each effect's "
                        "separating_experiment")
    if left.significant:
        warnings.append(
            f"a significant residual is left that no effect of the vocabulary explains "
            f"(held-out χ² {left.chi2:.0f} for {left.values} values); see the located cells "
            "of kind 'unexplained'")
    elif left.lone is not None:
        lone = left.lone
        warnings.append(
            f"one hold ({lone.condition.label()}, {lone.start_s:.2f}-{lone.stop_s:.2f} s) "
            f"leaves held-out χ² {lone.chi2:.0f} for {lone.values} values that the other "
            "holds do not: taken for a transient the settling did not describe, not for "
            "missing physics (repeat the hold to be sure)")
    warnings += settling_warnings(obs, untrusted)
    return Diagnosis(
        observations=obs,
        nominal=base,
        extended=extended,
        located=tuple(located),
        constants=constants,
        effects=tuple(named),
        rounds=tuple(rounds),
        findings=tuple(findings),
        unexplained=left,
        judgements=tuple(judgements),
        warnings=tuple(warnings),
        sensor_axes=axes,
    )
