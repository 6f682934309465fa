"""What the diagnosis's shared work saves, measured side by side on a fresh belt trial.

A belt's chain grid (294 points) is searched again for every term group tried alone on
a bent nominal fit. The groups whose blocks are all linear and start at zero leave the
nominal's motion as it is at every grid point, so their first linear passes are made
from one design per point (``fit.first_passes_shared``) instead of one per group and
point; the figure is how many times faster that is than screening the grid with each
group's own model, best of a few alternating rounds (the machine is shared). What is
not shared bounds it near 2: each group's own solve at every point (a bounded one
wherever saturation's non-negative weights are pressed) and the exact second pass of
its best ``GRID_EXACT`` points; the target guards the sharing itself. The rankings must
agree: the same best points, their χ² to 1e-7.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from bench.record import BenchRecord, Goal
from station.diagnosis.candidates import REGRID_KEEP
from station.diagnosis.effects import grid_shared
from station.diagnosis.fit import first_passes_shared, rank_passed, screen
from station.diagnosis.layout import ChainKind, ModelSpec
from station.diagnosis.model import Model
from station.diagnosis.nominal import GRID_EXACT, nominal_starts
from station.diagnosis.observations import NotDiagnosable, Observations, observe
from station.sim.concealed import PLANT_SUBSTEPS, Case, TrialClass, fresh_seeds, plan_trial
from station.sim.inprocess import simulate_timeline

SPEEDUP_TARGET = 1.5
ROUNDS = 3


def _belt_observations() -> Observations:
    """A clean belt unit on a fresh seed, recorded in process; one whose recording the
    diagnosis refuses (a drawn schedule whose holds are too short to judge) is passed
    over, as the diagnosis benchmark counts it apart."""
    for seed in fresh_seeds(64):
        plan = plan_trial(Case(TrialClass(), seed))
        if plan.unit.mechanics.disk is None:
            timeline = simulate_timeline(plan.unit, plan.schedule, seed=seed, loss=plan.loss,
                                         substeps=PLANT_SUBSTEPS)
            try:
                return observe(timeline)
            except NotDiagnosable:
                continue
    raise RuntimeError("no diagnosable belt unit among 64 fresh seeds")


def measure() -> list[BenchRecord]:
    obs = _belt_observations()
    spec = ModelSpec(ChainKind.BELT)
    sharing = grid_shared()
    effects = sorted(sharing)
    union = Model(replace(spec, effects=sharing), obs)
    models = [Model(spec.with_effect(e), obs) for e in effects]
    own_s, shared_s = [], []
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(ROUNDS):
            started = time.perf_counter()
            own = [screen(m, nominal_starts(m), exact=GRID_EXACT)[:REGRID_KEEP] for m in models]
            own_s.append(time.perf_counter() - started)
            started = time.perf_counter()
            passed = first_passes_shared(union, models, nominal_starts(union), GRID_EXACT)
            shared = [rank_passed(m, p, GRID_EXACT)[:REGRID_KEEP]
                      for m, p in zip(models, passed, strict=True)]
            shared_s.append(time.perf_counter() - started)
    agree = all(np.isclose(a, b, rtol=1e-7)
                for mine, theirs in zip(own, shared, strict=True)
                for (a, _), (b, _) in zip(mine, theirs, strict=True))
    return [
        BenchRecord("diagnosis_grid_shared_speedup", min(own_s) / min(shared_s), "x",
                    SPEEDUP_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_grid_shared_same_ranking", 1.0 if agree else 0.0, "fraction",
                    1.0, Goal.AT_LEAST),
    ]
