"""The diagnosis's first steps: the recording read and aligned, the nominal model fitted
(chains started from a grid, friction's floor, a belt's modes matched), and holds too short
to judge their own settling settled by the fitted chain (``diagnose`` steps 1 and 2)."""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from station.analysis.segments import ChainDecay, SettleFallback
from station.analysis.timeline import Timeline
from station.core import Mapper
from station.diagnosis import chain, floors
from station.diagnosis.axes import ElementTurn, element_turn, turned_back, with_axes_checked
from station.diagnosis.fit import (
    SCREEN_HELD,
    Fit,
    first_passes_shared,
    fit,
    polish_all,
    rank_passed,
    screen,
    solve_linear,
)
from station.diagnosis.layout import ChainKind, ModelSpec, chain_for
from station.diagnosis.model import Model
from station.diagnosis.observations import (
    NotDiagnosable,
    Observations,
    holds_of,
    observe,
    settled_holds,
)

SETTLE_PASSES = 3
"""Times at most the segments are taken again on the chain the last fit found. The first
fit sees only the holds that judge their own settling; the chain fitted on the segments it
settled can settle them better in turn (development disk none@22660216, a mode on orders 4
and 5 of holds too short to wait for: held-out χ² 1.94 per value after one pass, 1.24
after two, measured with waits cut to three periods that were later reverted)."""

SETTLE_TRUST_CHI2 = 50.0
"""χ² per dof of the nominal fit above which its chain settles no hold. A strong effect
the nominal model lacks bends the chain to hide it, and the modes it then has are where
the bend put them, not the recording's; fitted out of short holds as ringing they take
part of the harmonics with them. Benchmark belt detent_torque@1981511873 (plant belt
143 Hz): first fits 2,000 per dof, their low mode at 11 Hz damped 0.34 with one machine's
BLAS kernels and 0.05 with another's (the data differ by 4e-13); the lighter one rang out
16 holds at 10 Hz, moved their phasors by up to 44 σ and their noise by up to 35 times,
and the diagnosis named current_distortion there and detent_torque on the other machine.
Left with the holds that judge their own settling, both name detent_torque (held-out χ²
474.4 and 474.5). On the 95 development trials every first nominal fit lay below 29 or
above 109 per dof (weak effects and clean units below, strong ones above), so the limit
sits between: the score went from 84.0 to 84.5 (detent_torque+flux_harmonics@173386,
whose holds the bent chain had rung out in alternate passes, named), and the answers
that differ between Zen and SkylakeX kernels from 1 to 0; the 39 recordings above the
limit took 30 % less time (side by side, one core each). The short holds they lose are
listed in ``skipped`` and said in a warning."""

SETTLE_E_FOLDINGS = math.log(300.0)
"""A transient is taken as gone when it has decayed to 1/300 of its start."""

PRIOR_SETTLE_S = 0.12
"""Before any chain is known (no hold was long enough to judge its own settling), a
short hold is trusted after this long: the rotor's own mode on its magnetic spring
decays within tens of milliseconds on every unit the station has seen."""

RINGING_FLOOR_S = 0.02
"""Seconds a hold is waited for even when the chain's modes are fitted out as ringing:
what the chain's model leaves out (the current loop, the sensor's filter, hundreds of
hertz and well damped) has decayed by then."""

# The starting grid of the nominal chain (Hz, ratio): wide enough for any fixture.
ROTOR_HZ_GRID = (25.0, 45.0, 80.0, 140.0, 250.0, 450.0, 800.0)
LOAD_RATIO_GRID = (0.1, 0.5, 2.0, 8.0, 30.0, 120.0)
BELT_HZ_GRID = (12.0, 25.0, 50.0, 100.0, 200.0, 400.0, 800.0)

GRID_DAMPING = 0.3
MATCHED_DAMPING = (0.05, 0.3)
"""Belt and load damping ratios of the starts that keep a fitted belt's lowest mode."""
MATCHED_KEEP = 2
"""Of those, how many are polished (the best by their screened χ²)."""
GRID_EXACT = 24
"""Grid points ranked by their true χ² after the first linear pass has ranked them all
(``fit.screen``): four times the most any caller takes from the top."""

NOMINAL_KEEP = 4
"""Grid points the nominal fit starts from, as ranked with the gain errors held (the best
three of them, and of those below, are polished)."""
SPLIT_KEEP = 2
"""...and as ranked with the gain errors' difference fitted (``fit.SCREEN_HELD``)."""
NOMINAL_SHORT_NFEV = 12
"""Evaluations of the short polish that ranks the nominal fit's diverse grid points: the
one fit every gain is reported against, made once or twice per diagnosis, keeps the
longer look that ``fit.TOURNAMENT_NFEV`` gave up for the search's many models."""


DIVERSE_MIN_RATIO = 0.5
"""A belt's grid points at load-to-rotor inertia ratios from this one up are each tried
at least once (``_diverse``)."""


def transplanted(model: Model, base: Fit | None) -> NDArray[np.float64]:
    """The model's start, with every block a base fit shares taken from it."""
    p = model.layout.start()
    if base is not None:
        for block in base.model.layout.blocks:
            if model.layout.has(block.name) and block.size == model.layout.block(block.name).size:
                p[model.layout.slices[block.name]] = base.value(block.name)
    return p


def nominal_starts(model: Model) -> list[NDArray[np.float64]]:
    """A grid over the chain's natural frequencies (and, for a belt, its inertia ratio),
    each point with the linear parameters solved: the chain's response across speeds and
    orders picks the basin."""
    p0 = model.layout.start()
    grid: Iterable[tuple[float, ...]]
    if model.spec.chain is ChainKind.RIGID:
        grid = ((f,) for f in ROTOR_HZ_GRID)
        names: tuple[str, ...] = ("log_rotor_hz",)
    else:
        grid = itertools.product(ROTOR_HZ_GRID, LOAD_RATIO_GRID, BELT_HZ_GRID)
        names = ("log_rotor_hz", "log_load_ratio", "log_belt_hz")
    # Well damped at first: a resonance a little misplaced then costs a little, where a
    # sharp one would rank a good grid point below every chain without a mode in band.
    damped = model.with_values(p0, {n: [GRID_DAMPING] for n in
                               ("rotor_damping_ratio", "belt_damping_ratio", "load_damping_ratio")})
    out = []
    for point in grid:
        out.append(model.with_values(damped, {n: [math.log(v)] for n, v in zip(names, point,
                                                                            strict=True)}))
    return out


ANGLE_GRID = np.linspace(-1.2, 1.2, 17)
"""Load angles scanned per condition before Newton steps: large friction puts the right
angle a radian from zero, past other minima."""


def _refine_angles(model: Model, p: NDArray[np.float64], rounds: int = 3
                   ) -> NDArray[np.float64]:
    """Load angles per condition: a scan over ``ANGLE_GRID`` (each angle touches only its
    own condition's rows, so one evaluation tries a value for all of them), then a few
    Newton steps each, alternating with the linear solve."""
    rho = model.layout.slices["load_angle_rad"]
    cond = model.residual_conditions()
    conditions = len(model.obs.conditions)
    out = p.copy()
    low, high = model.layout.bounds()
    for _ in range(2):
        out = solve_linear(model, out, passes=1, held=SCREEN_HELD)
        best = np.full(conditions, np.inf)
        chosen = out[rho].copy()
        for value in (*ANGLE_GRID, None):
            trial = out.copy()
            if value is not None:
                trial[rho] = value
            r = np.nan_to_num(model.residuals(trial), nan=1e6)[cond >= 0]
            per = np.bincount(cond[cond >= 0], weights=r**2, minlength=conditions)
            better = per < best
            best[better] = per[better]
            chosen[better] = trial[rho][better]
        out[rho] = chosen
    for _ in range(rounds):
        out = solve_linear(model, out, passes=1)
        base = model.residuals(out)
        shifted = out.copy()
        shifted[rho] += 1e-4
        d = (model.residuals(shifted) - base) / 1e-4
        num = np.bincount(cond[cond >= 0], weights=(d * base)[cond >= 0], minlength=conditions)
        den = np.bincount(cond[cond >= 0], weights=(d * d)[cond >= 0], minlength=conditions)
        step = -num / np.maximum(den, 1e-12)
        out[rho] = np.clip(out[rho] + np.clip(step, -0.5, 0.5), low[rho] + 1e-6,
                           high[rho] - 1e-6)
    return out


@dataclass(frozen=True)
class Nominal:
    """The nominal model twice: with each segment's torque balance (the one judged) and
    without it (load angles free), which nothing unmodelled can bend and which every
    other model is also started from."""

    balanced: Fit
    free: Fit
    untrusted: float | None = None
    """χ²/dof of the fit whose chain was too far from the recording to settle its short
    holds (``SETTLE_TRUST_CHI2``), when that left them out; else None."""


def fit_nominal(obs: Observations, *, previous: Nominal | None = None,
                run: Mapper = map) -> Nominal:
    """The nominal model from the best few grid points (module note), or from the chain
    ``previous`` found on fewer holds of the same recording; first with free load angles,
    then with the model floor magnified where that chain has its modes, then with the
    torque balance; that weighting is the one every model of this recording is then
    judged by."""
    chain = chain_for(obs.metadata.gear_ratio)
    model = Model(ModelSpec(chain, dc_balance=False), obs)
    first = _from_grid(model, run) if previous is None else _from_previous(model, previous, run)
    matched = _mode_matched(model, first, run)
    if matched is not None and matched.chi2 < first.chi2:
        first = matched
    free, balanced = _floored(model, first, run)
    if balanced.chi2 < free.chi2:
        # The torque balance, harmonics and all, beats the harmonics alone: the grid missed
        # the chain's basin and the balance found it (a violent disk's twin, development
        # clock_drift@362477267: free χ² 1.5 million at 58 Hz with its load angles on their
        # bounds, balanced 3217 at 74 Hz). Everything is started again from there, the
        # floor's magnification included, which the wrong chain had put at the wrong orders.
        again = fit(model, [transplanted(model, balanced)], keep=1, max_nfev=80)
        if again.chi2 < first.chi2:
            free, balanced = _floored(model, again, run)
    return Nominal(balanced, free)


def _from_grid(model: Model, run: Mapper) -> Fit:
    """The free nominal fit from the chain grid's best points."""
    starts = nominal_starts(model)
    # Both rankings from one linear design per point.
    passed = first_passes_shared(model, [model, model], starts, len(starts),
                                 split=[False, True], run=run)
    ranked = rank_passed(model, passed[0], GRID_EXACT, run=run)
    split = rank_passed(model, passed[1], GRID_EXACT, split=True, run=run)
    chosen = [x for _, x in ranked[:NOMINAL_KEEP]] + [x for _, x in split[:SPLIT_KEEP]]
    diverse = _diverse(model, split, chosen)
    starts = chosen + diverse
    refined = list(run(_refine_angles, [model] * len(starts), starts))
    if diverse:
        # A short polish of each, then the full one from the best: ranked before any
        # polish, a chain whose modes sit a little off loses to one with none in band.
        tried = sorted(polish_all(model, refined, NOMINAL_SHORT_NFEV, run),
                       key=lambda f: f.chi2)
        refined = [f.params for f in tried[:NOMINAL_KEEP - 1]]
    return fit(model, refined, keep=NOMINAL_KEEP - 1, max_nfev=80, run=run)


def _from_previous(model: Model, previous: Nominal, run: Mapper) -> Fit:
    """The free nominal fit from ``previous``'s chain, its load angles refined for the
    holds added since.

    A settling pass adds short holds to the same recording, and the chain's basin does
    not move with them: on 42 development recordings of every class, 36 later passes
    refitted from the grid and from the previous chain alone ended within 0.04 % of
    each other (χ² 138,325 against 138,372 on a drifting clock with friction; within 1
    on 32, the previous chain better on two), for 84 s of grid work against 26 s.
    """
    start = transplanted(model, previous.free)
    return fit(model, [start, _refine_angles(model, start)], keep=2, max_nfev=80, run=run)


def _floored(model: Model, first: Fit, run: Mapper) -> tuple[Fit, Fit]:
    """The free and the balanced fit, weighted with the model floor magnified where
    ``first``'s chain has its modes."""
    # The floor's friction needs its levels, which only the torque balance gives: solved
    # at the free fit's point with the balance on.
    balanced = Model(replace(model.spec, dc_balance=True), model.obs)
    floored = model.obs.with_floor(floors.floor(balanced, solve_linear(balanced, first.params)))
    free = fit(Model(model.spec, floored), [first.params], keep=1, max_nfev=80)
    return free, balanced_fit(free, floored, run=run)


def _mode_matched(model: Model, found: Fit, run: Mapper = map) -> Fit | None:
    """A belt whose fit found a light load, fitted again from starts that keep the
    chain's lowest mode where ``found`` has it, at every inertia ratio and belt frequency
    of the grid (None for a disk, or a load of at least ``DIVERSE_MIN_RATIO``).

    What a recording pins first is the mode the whole chain swings on; how the inertia
    splits across the belt shows only in the few percent the belt's compliance bends the
    response below its own mode, far above the band. A grid point with that mode
    misplaced polishes downhill into a load too light to matter (ratio 0.001) with a
    heavily damped belt in band, which fits nothing well: a clean development belt
    (none@72, truth: ratio 5.9, belt 230 Hz) ended at χ² 1224 for 525 dof and was given
    a load resonance; from starts with its 69 Hz mode kept, 474, as from its truth. With
    the belt stiff, that mode is the rotor's own frequency over √(1 + ratio).
    """
    if (model.spec.chain is not ChainKind.BELT
            or math.exp(found.scalar("log_load_ratio")) >= DIVERSE_MIN_RATIO):
        return None
    modes = chain.modes(model, found.params, 1.0)
    if not modes:
        return None
    low = modes[0][0]
    damping = [found.scalar("rotor_damping_ratio")]
    starts = [model.with_values(found.params, {
        "log_rotor_hz": [math.log(low * math.sqrt(1.0 + ratio))],
        "log_load_ratio": [math.log(ratio)], "log_belt_hz": [math.log(belt)],
        "rotor_damping_ratio": damping, "belt_damping_ratio": [zeta],
        "load_damping_ratio": [zeta]})
        for ratio in LOAD_RATIO_GRID for belt in BELT_HZ_GRID for zeta in MATCHED_DAMPING]
    ranked = screen(model, starts, split=True, exact=GRID_EXACT, run=run)
    starts = [x for _, x in ranked[:MATCHED_KEEP]]
    refined = list(run(_refine_angles, [model] * len(starts), starts))
    return fit(model, refined, keep=MATCHED_KEEP, max_nfev=80, run=run)


def _diverse(model: Model, ranked: list[tuple[float, NDArray[np.float64]]],
             chosen: list[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    """For a belt, the best-ranked grid point at each load-to-rotor inertia ratio that
    ``chosen`` lacks.

    The top of the ranking is often a load too light to matter (ratio 0.1) with the
    rotor at the chain's combined frequency: it describes the low mode and nothing
    else, and fitted from there the load's inertia runs to its bound (development belt
    15, a load four times the rotor's: χ²/dof 39, against 0.86 from its truth).
    """
    if model.spec.chain is not ChainKind.BELT:
        return []
    ratio = model.layout.slices["log_load_ratio"]
    seen = {round(float(x[ratio][0]), 3) for x in chosen}
    out = []
    for _, x in ranked:
        key = round(float(x[ratio][0]), 3)
        if key not in seen and math.exp(key) >= DIVERSE_MIN_RATIO:
            seen.add(key)
            out.append(x)
    return out


def balanced_fit(free: Fit, obs: Observations, spec: ModelSpec | None = None, *,
              run: Mapper = map) -> Fit:
    model = Model(spec or ModelSpec(free.model.spec.chain), obs)
    start = transplanted(model, free)
    return fit(model, [start, _refine_angles(model, start)], keep=2, max_nfev=80, run=run)


def settle_fallback(nominal: Fit) -> SettleFallback:
    """How the fitted chain forgets a change, per condition (None: a mode that does not
    decay).

    Only modes the recording can resolve count: below twice the highest harmonic it
    analyses. A mode far above (a stiff belt the data barely see) has a damping the fit
    cannot know, and its ringing sits between the harmonics anyway.
    """
    model = nominal.model
    rho = nominal.value("load_angle_rad")
    # Each condition's load angle, and the spring its swing rides (a rough unit's is softer
    # than at rest).
    conditions = {(c.amplitude_mA, round(c.electrical_hz, 1)): (float(r), float(k))
                  for c, r, k in zip(model.obs.conditions, rho,
                                     floors.swing_springs(model, nominal.params), strict=True)}
    top = 2.0 * model.obs.orders * float(np.max(np.abs(model.obs.omega))) / (2 * math.pi)
    # What a segment's harmonics resolve: a transient below it is not worth waiting out.
    resolution = float(np.median(model.obs.noise))

    @functools.cache
    def by_condition(amplitude_mA: int, electrical_hz: float) -> ChainDecay | None:
        # Every hold of a condition asks: its chain's modes are found once.
        angle, spring = conditions.get((amplitude_mA, electrical_hz), (0.0, None))
        modes = [(f, z) for f, z in chain.modes(model, nominal.params, amplitude_mA / 1000.0,
                                                angle, spring)
                 if 0 < f <= top]
        if not modes:
            return _prior_settle(amplitude_mA, electrical_hz)
        if any(z <= 0 for _, z in modes):
            return None
        poles = tuple(_pole(f, z) for f, z in modes)
        return ChainDecay(poles, SETTLE_E_FOLDINGS, RINGING_FLOOR_S, resolution)

    def settle(amplitude_mA: int, electrical_hz: float) -> ChainDecay | None:
        return by_condition(amplitude_mA, round(electrical_hz, 1))

    return settle


def _pole(hz: float, damping: float) -> complex:
    """The upper pole of an underdamped mode (``chain.modes`` lists no other kind)."""
    wn = 2 * math.pi * hz
    return complex(-damping * wn, wn * math.sqrt(1.0 - damping * damping))


def _prior_settle(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
    return ChainDecay((), SETTLE_E_FOLDINGS, PRIOR_SETTLE_S)


def _observe(timeline: Timeline) -> Observations:
    """Holds that judge their own settling; if too few do, short holds on a prior."""
    try:
        return observe(timeline)
    except NotDiagnosable:
        return observe(timeline, settle_fallback=_prior_settle)


def nominal_of(timeline: Timeline, progress: Callable[[str], None] | None = None,
               run: Mapper = map, read: Aligned | None = None
               ) -> tuple[Observations, Nominal]:
    """The recording's observations and its nominal fit, as the diagnosis first takes them
    (``fit.before`` unless a chosen model's modes weight it again): fitted to a unit's
    clean twin, what an effect adds to. ``read``: the recording as ``aligned`` read it,
    when already read (then ``timeline`` is not read again)."""
    with threadpool_limits(limits=1, user_api="blas"):
        if progress is not None:
            progress("fitting the nominal model")
        if read is None:
            read = aligned(timeline)
        timeline, first = read.timeline, read.first
        fits = fit_nominal(first, run=run)
        obs, seen, kept = first, [settled_holds(timeline)], [holds_of(first.segments)]
        for _ in range(SETTLE_PASSES):
            per_dof = fits.free.chi2 / max(fits.free.dof, 1)
            if per_dof > SETTLE_TRUST_CHI2:
                # A chain bent to hide an effect has its modes where the bend put them.
                if obs is first:
                    fits = replace(fits, untrusted=per_dof)
                    if progress is not None:
                        progress(f"short holds left unsettled: the nominal chain leaves "
                                 f"χ²/dof {per_dof:.0f}")
                break
            # A pass that keeps the holds an earlier one kept, each settled the same way,
            # changes only the ringing poles they start from (their prior, which moves a
            # little with every nominal fit): the chain agrees with the segments it
            # settled, and the settling ends. Asked first of the steady segments alone
            # (the cheap part of an observation), then of those the observation keeps.
            # Development trial detent_torque+flux_harmonics@101, a belt: 111 holds
            # twice, each pole a few percent off the pass before, observed and fitted
            # again for 6 s of its 62.
            fallback = settle_fallback(fits.free)
            holds = settled_holds(timeline, settle_fallback=fallback)
            if holds in seen:
                break
            seen.append(holds)
            settled = with_axes_checked(observe(timeline, settle_fallback=fallback, run=run))
            if holds_of(settled.segments) in kept:
                break
            obs = settled
            kept.append(holds_of(obs.segments))
            if progress is not None:
                progress(f"segments settled by the fitted chain: {obs.model_settled}, "
                         f"with its ringing fitted out: {obs.ringing}")
            fits = fit_nominal(obs, previous=fits, run=run)
        return obs, fits


@dataclass(frozen=True)
class Aligned:
    """A recording as the diagnosis reads it: turned back when its sensing element was
    turned on its mount (``turn``, measured on the recording as it came), and its
    observations before the fitted chain settles any segment (``first``)."""

    timeline: Timeline
    first: Observations
    turn: ElementTurn | None


def aligned(timeline: Timeline, *, turn_back: bool = True) -> Aligned:
    """The recording read, its element turned back if it shows a turn (unless not to
    ``turn_back``: the recording as it came); where a recording that is not a
    characterization is refused."""
    obs = _observe(timeline)
    turn = element_turn(obs) if turn_back else None
    if turn is not None:
        timeline = turned_back(timeline, turn)
        obs = _observe(timeline)
    return Aligned(timeline, with_axes_checked(obs), turn)


def settling_warnings(obs: Observations, untrusted: float | None) -> list[str]:
    """What the settling did to the holds, and what it could not do (``untrusted``: the
    χ²/dof of a nominal chain not trusted to settle them, ``Nominal.untrusted``)."""
    out: list[str] = []
    if untrusted is not None and obs.skipped:
        out.append(
            f"holds too short to judge their own settling are left out (see skipped): the "
            f"nominal model leaves χ²/dof {untrusted:.0f}, more than "
            f"{SETTLE_TRUST_CHI2:.0f}, so its chain's modes are not trusted to settle them")
    if obs.model_settled:
        out.append(f"{obs.model_settled} segments come from holds too short to judge "
                   "their own settling; their start is the fitted chain's decay time")
    if obs.ringing:
        out.append(f"{obs.ringing} segments come from holds shorter than the chain's "
                   "slowest decay; its modes' ringing was fitted out beside the harmonics, "
                   "whose σ includes what that costs")
    return out
