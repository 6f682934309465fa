"""Fitting a model to observations, judging its parameters, and holding conditions out.

The solver is scipy's bounded least squares with a Jacobian assembled from
the model's structure: the linear parameters' columns come from the model's
design and what each moves through every segment's slip and spring
(``jacobian.linear_jacobian``); the remaining parameters (nonlinear, and
friction's levels) and the per-condition load angles (which share one
column's work: each touches only its own condition's rows) enter only what
each segment's motion is made from, and those inputs are differenced and
carried through the rest by the chain rule (``jacobian.motion_columns``). A fit
of the full model then costs milliseconds per iteration instead of a second.
The columns must be the residuals' own derivatives: the solver stops where
they say the gradient vanishes.

A parameter that ends on one of its bounds is not a result. The bounds are
physical (a filter cannot answer before it is asked, a damping ratio is not
negative), so when the data pull a parameter past one, the model cannot
describe the recording, and ``bound_findings`` says so with how much the
data would gain; a parameter that merely rests on a bound the data do not
press against (an ideal sensor's zero delay) is reported as resting there.

Held-out residuals use the standard one-step approximation of leave-one-out
refits: from the full fit, one Gauss-Newton step on the data without the
condition, then the held-out condition's own load angle (a nuisance no other
condition can inform) refitted on its data alone. An exact refit without a condition
never fits that condition better than the fit with it did (the full fit minimised the
sum of both parts, the refit only the rest), and at an optimum the linear step agrees;
a step that predicts less than the fitted χ² comes from a fit short of its optimum or
from a direction the linearisation misjudges, so the fitted residuals stand instead.
Development control none@204 (a clean belt): a saturation group gained 20 in χ² and,
by such a step, 1283 held out, its held-out χ² 574 for 1905 values.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import OptimizeResult, least_squares, lsq_linear

from station.core import Mapper
from station.diagnosis.layout import BlockKind
from station.diagnosis.model import Model

_MAX_NFEV = 40
_FTOL = 1e-6
"""Relative change of χ² (and of the parameters) at which a fit stops: a millionth of a χ²
of thousands is far below anything a comparison of models resolves. A
hundred-thousandth made 14 % fewer Jacobians on 19 development trials (one per class) to
the same answers, but stopped a bent pair creeping along its valley at χ² 15,605, where a
millionth goes on below 2,882 (development detent_torque+flux_harmonics@821054, a test)."""
_STEP = 1e-6
_STEP_SPAN = 1e-2
"""A differenced parameter's step is ``_STEP`` of its value, of 1, or of this share of its
range, whichever is largest: a clock's drift (±5000 ppm) moved by 1e-6 ppm moved each
sample by 1e-12 of a period, and the rounding of its phases put its column 2.4e-4 off."""
HELD_RCOND = 1e-4
"""Singular values of the held-out step below this fraction of the largest are dropped."""
HELD_TRUST = 4.0
"""A one-step prediction this many times worse than the condition's fitted χ² (plus its
values) is checked on the model itself (``held_out``)."""
HELD_SHRINK = (1.0, 0.5, 0.25, 0.125, 0.0)
"""Fractions of the Gauss-Newton step tried when the linear prediction is not trusted."""
TOURNAMENT_NFEV = 8
"""Evaluations of the short polish that picks among many starts (``best_of``). Against
12, on 19 development trials (one per class), the diagnoses made 10 % fewer Jacobians to
the same answers, every final χ² within 1 %: the starts that win are ahead by then."""
HEAT_NFEV = 3
"""Evaluations of the first heat of a tournament of more than ``HEAT_FIELD`` starts: only
its better half goes on to the rest of the short polish (``best_of``)."""
HEAT_FIELD = 3
"""Starts a tournament polishes to ``TOURNAMENT_NFEV`` without a heat before."""
AT_BOUND = 1e-6
"""How near a bound, as a share of the range, a parameter the solver left free counts as
on it when judged (``judge_parameters``): rounding, not the solver's tolerance, which
``REJECT_MARGIN`` allows for where a group may not rest."""
PUSH_CHI2 = 9.0
"""A bound pressed this hard (χ² it would give back, 3σ) is a finding, not a rest."""
REJECT_MARGIN = 1e-3
"""How near a bound its group may not rest on (``Block.rejects``), as a share of the
range, a fit counts as resting there: the solver stops short of a bound it presses by its
own tolerances. Benchmark trial friction@1850757460 (a disk): beside friction a coupling
ended at a damping ratio of 1.9998 against the bound of 2, a damper and no mode, was not
taken as resting there, and was named."""


@dataclass(frozen=True)
class Fit:
    """A model at its best parameters, with what judging it needs."""

    model: Model
    params: NDArray[np.float64]
    residuals: NDArray[np.float64]  # weighted, unit variance per part
    jacobian: NDArray[np.float64]
    active: NDArray[np.int8]  # −1 at the lower bound, +1 at the upper, 0 inside
    converged: bool = True  # False: the polish ran out of evaluations first

    @property
    def chi2(self) -> float:
        return float(self.residuals @ self.residuals)

    @property
    def parameters(self) -> int:
        return self.model.layout.size

    @property
    def observations(self) -> int:
        return int(self.residuals.size)

    @property
    def dof(self) -> int:
        return max(1, self.observations - self.parameters)

    @property
    def bic(self) -> float:
        """Schwarz's criterion with known noise: χ² plus ln(n) per parameter."""
        return self.chi2 + self.parameters * math.log(self.observations)

    def value(self, name: str) -> NDArray[np.float64]:
        return self.params[self.model.layout.slices[name]]

    @property
    def rejected(self) -> tuple[str, ...]:
        """Blocks resting on a bound their group may not rest on (``Block.rejects``), or
        fitted where their group is the base model again (``Block.null_band``)."""
        slices = self.model.layout.slices
        return tuple(b.name for b in self.model.layout.blocks
                     if any(side in b.rejects for side in self.active[slices[b.name]])
                     or bool(np.any(np.abs(self.params[slices[b.name]]) < b.null_band)))

    def scalar(self, name: str) -> float:
        return float(self.value(name)[0])


def jacobian(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """d residuals / d parameters, from the model's structure (see the module note)."""
    out = np.empty((model.residuals(p).size, p.size))
    lin = model.linear_index()
    if lin.size:
        out[:, lin] = model.linear_jacobian(p).T
    rho = model.layout.slices["load_angle_rad"]
    # Every load angle moved at once: each touches only its own condition's rows.
    angles = p.copy()
    angles[rho] += _STEP
    moving = model.motion_index()
    low, high = model.layout.bounds()
    span = np.where(np.isfinite(high - low), high - low, 0.0)[moving]
    scale = np.maximum(np.maximum(1.0, np.abs(p[moving])), _STEP_SPAN * span)
    steps = np.concatenate([[_STEP], _STEP * scale])
    points = [angles]
    for i, step in zip(moving, steps[1:], strict=True):
        shifted = p.copy()
        shifted[i] += step
        points.append(shifted)
    columns = model.motion_columns(p, points, steps)
    cond = model.residual_conditions()
    out[:, rho] = 0.0
    inside = cond >= 0
    out[np.flatnonzero(inside), rho.start + cond[inside]] = columns[inside, 0]
    out[:, moving] = columns[:, 1:]
    return out


def solve_linear(model: Model, p: NDArray[np.float64], passes: int = 2,
                 held: tuple[str, ...] = (), split: tuple[str, ...] = ()
                 ) -> NDArray[np.float64]:
    """The linear parameters that best fit within their bounds, the others held (a couple
    of passes settle the small cross terms between them); blocks named in ``held`` keep
    their values too, and two-valued blocks named in ``split`` keep their mean and fit
    only their difference."""
    return _LinearSolve(model, held, split).run(p, passes)[0]


class _LinearSolve:
    """``solve_linear``'s passes, which also say the χ² their linearisation predicts."""

    def __init__(self, model: Model, held: tuple[str, ...], split: tuple[str, ...]) -> None:
        self.model = model
        idx = model.linear_index()
        keep = np.zeros(model.layout.size, dtype=bool)
        for name in (*held, *split):
            if model.layout.has(name):
                keep[model.layout.slices[name]] = True
        position = {int(i): j for j, i in enumerate(idx)}
        self.pairs: list[tuple[int, int]] = []
        for name in split:
            if model.layout.has(name):
                first, second = range(model.layout.size)[model.layout.slices[name]]
                self.pairs.append((position[first], position[second]))
        self.idx = idx
        self.free = ~keep[idx]
        low, high = model.layout.bounds()
        self.low, self.high = low[idx][self.free], high[idx][self.free]

    def run(self, p: NDArray[np.float64], passes: int,
            given: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
            ) -> tuple[NDArray[np.float64], float]:
        """``p`` after ``passes`` passes, and the χ² the last one predicts there (inf when
        there was nothing to solve or the design was not finite); the first pass on the
        linear design ``given`` (``first_passes_shared``) when there is one."""
        out = p.copy()
        predicted = math.inf
        if not self.free.any() and not self.pairs:
            return out, predicted
        for n in range(passes):
            step = self._pass(out, given if n == 0 else None)
            if step is None:
                break
            out, predicted = step
        return out, predicted

    def _pass(self, p: NDArray[np.float64],
              given: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
              ) -> tuple[NDArray[np.float64], float] | None:
        idx, free, pairs = self.idx, self.free, self.pairs
        at_zero, design = self.model.linear_design(p) if given is None else given
        a = design[free].T
        b = -at_zero - design[~free].T @ p[idx][~free]
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return None
        lower, upper = self.low, self.high
        if pairs:
            # Each split's difference is one more column, a step unbounded: the bounds it
            # must keep are far outside what a screening point asks of it.
            a = np.column_stack([a, *(design[i] - design[j] for i, j in pairs)])
            lower = np.concatenate([lower, np.full(len(pairs), -np.inf)])
            upper = np.concatenate([upper, np.full(len(pairs), np.inf)])
        solution = np.linalg.lstsq(a, b, rcond=None)[0]
        if np.any(solution < lower) or np.any(solution > upper):
            solution = lsq_linear(a, b, bounds=(lower, upper), method="bvls").x
        out = p.copy()
        out[idx[free]] = solution[:self.low.size]
        for (i, j), step in zip(pairs, solution[self.low.size:], strict=True):
            out[idx[i]] += step
            out[idx[j]] -= step
        r = a @ solution - b  # the residual the linearisation predicts at ``out``
        return out, float(r @ r)


def _inside(model: Model) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    low, high = model.layout.bounds()
    span = np.where(np.isfinite(low) & np.isfinite(high), high - low, 1.0)
    inside_low = np.where(np.isfinite(low), low + 1e-9 * span, -np.inf)
    inside_high = np.where(np.isfinite(high), high - 1e-9 * span, np.inf)
    return inside_low, inside_high


def chi2_at(model: Model, p: NDArray[np.float64]) -> float:
    r = model.residuals(p)
    value = float(r @ r)
    return value if math.isfinite(value) else math.inf


SCREEN_HELD = ("amp_gain_error",)
"""Held at their start while starts are ranked: gain errors would otherwise stand in for a
wrong chain (stiffness scales with the current as the rotor's frequency squared does).
Ranked a second way with their mean held and their difference fitted (``split``): the
split between the phases only sets the order-2 ripple, and held at zero it left a belt
whose phases differed by 18 % ranking its own chain 237th of 294."""


def screen(model: Model, starts: list[NDArray[np.float64]], *, split: bool = False,
           exact: int | None = None, run: Mapper = map
           ) -> list[tuple[float, NDArray[np.float64]]]:
    """Every start with its linear parameters solved, best first (cheap, and it ranks
    the starts well); ``split``: the gain errors' difference solved too.

    ``exact``: for a grid of many starts, each is first ranked by the χ² its first linear
    pass predicts, and only that many of the best are given the second pass and their
    true χ², which ranks them as before; the others follow in the first ranking, with
    the χ² it predicted. The second pass and the true χ² are most of a point's cost, and
    the first ranking already puts the best points on top (a flux-harmonics belt's six
    best of 294 regridded points sat at the pre-ranking's first seven).

    ``run`` maps over chunks of ``SCREEN_CHUNK`` starts (each start is independent)."""
    inside_low, inside_high = _inside(model)
    clipped = [np.clip(start, inside_low, inside_high) for start in starts]
    if exact is not None and len(starts) > exact:
        # The first pass of every point; the best go on from where it left them.
        passed = _chunked(run, _first_passes, (model, split), clipped)
        return rank_passed(model, passed, exact, split=split, run=run)
    screened = _chunked(run, _last_passes, (model, split), clipped, 2)
    screened.sort(key=lambda item: item[0])
    return screened


def rank_passed(model: Model, passed: list[tuple[NDArray[np.float64], float]], exact: int,
                *, split: bool = False, run: Mapper = map
                ) -> list[tuple[float, NDArray[np.float64]]]:
    """``screen``'s ranking of starts given after their first linear pass, each with the
    χ² that pass predicted: the ``exact`` best given the second pass and their true χ²,
    the others after them as the first pass ranked them."""
    inside_low, inside_high = _inside(model)
    quick = sorted(((chi2, x) for x, chi2 in passed), key=lambda item: item[0])
    rest = [(c, np.clip(x, inside_low, inside_high)) for c, x in quick[exact:]]
    screened = _chunked(run, _last_passes, (model, split), [x for _, x in quick[:exact]], 1)
    screened.sort(key=lambda item: item[0])
    return screened + rest


def first_passes_shared(union: Model, models: list[Model], starts: list[NDArray[np.float64]],
                        keep: int, *, split: list[bool] | None = None, run: Mapper = map
                        ) -> list[list[tuple[NDArray[np.float64], float]]]:
    """For each of ``models``, the ``keep`` best of ``starts`` (given in ``union``'s layout)
    after its first linear pass (``screen``, with its gain errors' difference solved
    where ``split`` says), each with the χ² that pass predicted, from one linear design
    per start.

    ``union`` must hold every block of every model, its groups' blocks zero at the starts
    and there leaving the motion as it is: each model's motion is then the union's, and so
    is each linear parameter's design row (the first pass moves no nonlinear one). Made
    with each group's own model, a belt's chain-grid first passes for every group tried
    alone on a bent nominal were a fifth of its diagnosis (development
    flux_harmonics@202, profiled): the same motions made again for each group (and for
    both rankings of the nominal's own grid).
    """
    inside_low, inside_high = _inside(union)
    clipped = [np.clip(start, inside_low, inside_high) for start in starts]
    splits = [False] * len(models) if split is None else split
    per_start = _chunked(run, _shared_passes, (union, models, splits), clipped)
    # Stable, as ``rank_passed`` sorts: the first of equals stays first.
    return [sorted((row[k] for row in per_start), key=lambda item: item[1])[:keep]
            for k in range(len(models))]


def _shared_passes(union: Model, models: list[Model], split: list[bool],
                   starts: list[NDArray[np.float64]]
                   ) -> list[list[tuple[NDArray[np.float64], float]]]:
    """Per start, each model's first pass (``first_passes_shared``)."""
    union_linear = {int(i): row for row, i in enumerate(union.linear_index())}
    picks, rows, solvers = [], [], []
    for model, gains_split in zip(models, split, strict=True):
        # Where each of the model's parameters sits in the union's layout.
        pick = np.concatenate([np.arange(union.layout.slices[b.name].start,
                                         union.layout.slices[b.name].stop)
                               for b in model.layout.blocks])
        picks.append(pick)
        rows.append(np.array([union_linear[int(pick[i])] for i in model.linear_index()],
                             dtype=np.intp))
        solvers.append(_solver(model, gains_split))
    out = []
    for x in starts:
        at_zero, design = union.linear_design(x)
        out.append([solver.run(x[pick], 1, (at_zero, design[row]))
                    for pick, row, solver in zip(picks, rows, solvers, strict=True)])
    return out


SCREEN_CHUNK = 16
"""Starts per task when a screen is spread over worker processes."""


def _chunked(run: Mapper, task: Callable[..., list[Any]], fixed: tuple[Any, ...],
             starts: list[NDArray[np.float64]], *extra: int) -> list[Any]:
    """``task(*fixed, chunk, *extra)`` over ``starts`` in chunks, its answers in the order
    of the starts."""
    chunks = [starts[i:i + SCREEN_CHUNK] for i in range(0, len(starts), SCREEN_CHUNK)]
    n = len(chunks)
    args = [*([value] * n for value in fixed), chunks, *([value] * n for value in extra)]
    return [item for part in run(task, *args) for item in part]


def _solver(model: Model, split: bool) -> _LinearSolve:
    held, split_held = ((), SCREEN_HELD) if split else (SCREEN_HELD, ())
    return _LinearSolve(model, held, split_held)


def _first_passes(model: Model, split: bool, starts: list[NDArray[np.float64]]
                  ) -> list[tuple[NDArray[np.float64], float]]:
    solver = _solver(model, split)
    return [solver.run(x, 1) for x in starts]


def _last_passes(model: Model, split: bool, starts: list[NDArray[np.float64]], passes: int
                 ) -> list[tuple[float, NDArray[np.float64]]]:
    solver = _solver(model, split)
    inside_low, inside_high = _inside(model)
    out = []
    for x in starts:
        x0 = np.clip(solver.run(x, passes)[0], inside_low, inside_high)
        out.append((chi2_at(model, x0), x0))
    return out


def polish(model: Model, x0: NDArray[np.float64], max_nfev: int = _MAX_NFEV, *,
           jac0: NDArray[np.float64] | None = None) -> Fit:
    """Bounded least squares from ``x0`` as it is (``fit`` first re-solves every start's
    linear parameters, which can move a start away from a point known to be good).

    ``jac0``: the Jacobian at ``x0`` when it is known (``polished_on``), used for the
    solver's first step instead of being made again.
    """
    low, high = model.layout.bounds()
    start = np.clip(x0, *_inside(model))
    known: list[NDArray[np.float64]] = []

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        # Only the very first request can be at the start; the solver asks at most once.
        if known and np.array_equal(p, start):
            return known.pop().copy()
        known.clear()
        return jacobian(model, p)

    def solve(**solver: str) -> OptimizeResult:
        # Each try (the SVD's fallback too) starts at the start, where jac0 is.
        known[:] = [] if jac0 is None else [jac0]
        return least_squares(
            model.residuals, start, jac=jac,
            bounds=(low, high), x_scale="jac", method="trf", max_nfev=max_nfev, ftol=_FTOL,
            xtol=_FTOL, **solver,
        )

    try:
        result = solve()
    except np.linalg.LinAlgError:
        # LAPACK's divide-and-conquer SVD, behind each step of the dense trust region, can
        # fail to converge on a finite Jacobian (benchmark trial detent_torque@76034821, a
        # belt, ended the whole diagnosis there): the iterative subproblem solver needs no
        # SVD, and the polish goes on from the same start.
        result = solve(tr_solver="lsmr")
    return Fit(model, result.x, result.fun, result.jac,
               resting(model, result.x, np.asarray(result.active_mask, dtype=np.int8)),
               converged=result.status > 0)


def resting(model: Model, x: NDArray[np.float64], active: NDArray[np.int8]
            ) -> NDArray[np.int8]:
    """The solver's ``active`` sides, with values within ``REJECT_MARGIN`` of a bound
    their group may not rest on counted as resting there."""
    out = active.copy()
    slices = model.layout.slices
    for block in model.layout.blocks:
        if not block.rejects:
            continue
        sl = slices[block.name]
        near = REJECT_MARGIN * (block.high - block.low)
        value, side = x[sl], out[sl]
        if -1 in block.rejects:
            side[(side == 0) & (value - block.low <= near)] = -1
        if 1 in block.rejects:
            side[(side == 0) & (block.high - value <= near)] = 1
    return out


def polish_all(model: Model, starts: list[NDArray[np.float64]], max_nfev: int = _MAX_NFEV,
               run: Mapper = map) -> Iterable[Fit]:
    """``polish`` from each start (side by side when ``run`` is an executor's), in order."""
    n = len(starts)
    return run(polish, [model] * n, starts, [max_nfev] * n)


def polished_on(stopped: Fit, max_nfev: int = _MAX_NFEV) -> Fit:
    """``stopped`` polished on from where it stopped, with the Jacobian it stopped with.

    Each stage of a tournament (``best_of``) and each finishing polish goes on from a fit
    whose Jacobian at its point was made already: the solver's first request is that one.
    A restarted solver otherwise makes it again, one Jacobian of the seven or so a polish
    makes, for nothing. Same answer to the last bit: the solver sees the same matrix.
    """
    # A fit no start of which evaluated (``_unevaluated``) has no Jacobian to give.
    known = stopped.jacobian if np.any(stopped.jacobian) else None
    return polish(stopped.model, stopped.params, max_nfev, jac0=known)


def polished_on_all(stopped: list[Fit], max_nfev: int = _MAX_NFEV,
                    run: Mapper = map) -> Iterable[Fit]:
    """``polished_on`` for each fit (side by side when ``run`` is an executor's), in order."""
    return run(polished_on, stopped, [max_nfev] * len(stopped))


def fit(model: Model, starts: list[NDArray[np.float64]], *, keep: int = 2,
        max_nfev: int = _MAX_NFEV, estimated: list[NDArray[np.float64]] | None = None,
        run: Mapper = map) -> Fit:
    """Bounded least squares from the ``keep`` most promising starts, and from every
    ``estimated`` one (a start the data themselves point to, which a ranking by χ² before
    the search could pass over); the best result (``best_of``)."""
    chosen = chosen_starts(model, starts, keep, estimated)
    if not chosen:
        return _unevaluated(model, starts)
    return best_of(model, chosen, max_nfev=max_nfev, run=run)


def chosen_starts(model: Model, starts: list[NDArray[np.float64]], keep: int,
                  estimated: list[NDArray[np.float64]] | None = None
                  ) -> list[NDArray[np.float64]]:
    """``fit``'s starts: the ``keep`` best of ``starts`` and every ``estimated`` one, each
    with its linear parameters solved (those that do not evaluate are dropped)."""
    ranked = screen(model, starts)[:keep] + screen(model, estimated or [])
    return [x for chi2, x in ranked if math.isfinite(chi2)]


def best_of(model: Model, chosen: list[NDArray[np.float64]], *, max_nfev: int = _MAX_NFEV,
            finalists: int | None = None, heat: bool = True, run: Mapper = map) -> Fit:
    """The best polish from ``chosen``; with ``finalists``, each is first polished for
    ``TOURNAMENT_NFEV`` evaluations and only that many of the best go on.

    A few evaluations sort the starts far better than their χ² before any polish (a
    chain a little off its modes then ranks below one with none in band), and most of a
    full polish is spent creeping along the valley of the start it began in: a model
    with many starts (a bent nominal's regridded chain, the group's own estimates, the
    unbent chain) spends its budget on the few that lead somewhere. ``heat``: whether a
    wide field has the first heat (``_short_polishes``).
    """
    best: Fit | None = None
    if finalists is not None and len(chosen) > finalists:
        short = _short_polishes(model, chosen, finalists, run, heat)
        best = short[0]
        # A finalist whose short polish already converged has nothing left to gain.
        going = [f for f in short[:finalists] if not f.converged]
        polished = polished_on_all(going, max_nfev, run)
    else:
        polished = polish_all(model, chosen, max_nfev, run)
    for candidate in polished:
        if best is None or candidate.chi2 < best.chi2:
            best = candidate
    if best is None:
        return _unevaluated(model, chosen)
    return best


def _short_polishes(model: Model, chosen: list[NDArray[np.float64]], finalists: int,
                    run: Mapper, heat: bool = True) -> list[Fit]:
    """``chosen`` polished for ``TOURNAMENT_NFEV`` evaluations, best first; of a field
    wider than ``HEAT_FIELD``, only the better half after ``HEAT_NFEV`` goes on.

    Most of a tournament's cost is starts that end where a better one does, or worse: on
    ten development trials (188 tournaments, 1,287 starts) the start that ended best
    after the whole short polish was in the better half after three evaluations in all
    but 4, each a group patching a bent nominal model (χ² in the millions, its gain
    deciding nothing), for a third fewer evaluations. A start that converged in the heat
    has nothing left to gain and keeps its place. Without ``heat`` every start has the
    whole short polish: a field of chains spread over a grid, whose χ² after three
    evaluations says how near the base a chain starts, not which basin it is in
    (``EffectTerms.tournament``).
    """
    if not heat or len(chosen) <= max(HEAT_FIELD, finalists):
        return sorted(polish_all(model, chosen, TOURNAMENT_NFEV, run), key=lambda f: f.chi2)
    heated = sorted(polish_all(model, chosen, HEAT_NFEV, run), key=lambda f: f.chi2)
    ahead = heated[:max(HEAT_FIELD, finalists + 1, (len(heated) + 1) // 2)]
    going = [f for f in ahead if not f.converged]
    later = polished_on_all(going, TOURNAMENT_NFEV - HEAT_NFEV, run)
    return sorted([*(f for f in ahead if f.converged), *later], key=lambda f: f.chi2)


def _unevaluated(model: Model, starts: list[NDArray[np.float64]]) -> Fit:
    """Every start failed to evaluate: the first (or the model's own start) as it is,
    so the caller sees its χ²."""
    x0 = np.clip(starts[0] if starts else model.layout.start(), *_inside(model))
    r = np.nan_to_num(model.residuals(x0), nan=1e6, posinf=1e6, neginf=-1e6)
    return Fit(model, x0, r, np.zeros((r.size, x0.size)), np.zeros(x0.size, np.int8),
               converged=False)


@dataclass(frozen=True)
class HeldOut:
    """Residuals of each condition predicted by a fit that did not see it."""

    chi2: NDArray[np.float64]  # (C,) per condition
    residuals: NDArray[np.float64]  # same layout as Fit.residuals

    @property
    def total(self) -> float:
        return float(self.chi2.sum())


def held_out(result: Fit) -> HeldOut:
    """Leave-one-condition-out residuals by the one-step approximation (module note)."""
    model = result.model
    r = result.residuals
    jac = result.jacobian
    cond = model.residual_conditions()
    rho = model.layout.slices["load_angle_rad"]
    conditions = len(model.obs.conditions)
    chi2 = np.zeros(conditions)
    out = np.zeros_like(r)  # the prior is never held out: it stays 0 here
    # Parameters resting on a bound stay there: a step would leave the physical range.
    free = result.active == 0
    for c in range(conditions):
        inside = cond == c
        others = [i for i in range(jac.shape[1]) if i != rho.start + c and free[i]]
        j_out = jac[~inside][:, others]
        # Directions the other conditions leave undetermined are not stepped along: a
        # linear step there is wild, where a refit would stay put.
        step = -np.linalg.lstsq(j_out, r[~inside], rcond=HELD_RCOND)[0]
        predicted = r[inside] + jac[inside][:, others] @ step
        fitted = float(r[inside] @ r[inside])
        if float(predicted @ predicted) > HELD_TRUST * fitted + np.count_nonzero(inside):
            predicted = _checked_step(result, inside, others, step)
        local = jac[inside][:, rho.start + c]
        norm = float(local @ local)
        if norm > 0:
            predicted = predicted - local * float(local @ predicted) / norm
        if float(predicted @ predicted) < fitted:
            # A refit without the condition cannot fit it better than the fit with it
            # did: a step that says so is not a refit (module note).
            predicted = r[inside]
        out[inside] = predicted
        chi2[c] = float(predicted @ predicted)
    return HeldOut(chi2, out)


def _checked_step(result: Fit, inside: NDArray[np.bool_], others: list[int],
                  step: NDArray[np.float64]) -> NDArray[np.float64]:
    """The held-out residual from the model itself, along the step as far as it helps.

    Where the model is far from linear over the step (a drifting clock's sawtooth of
    delays: its slope in ppm is large and wraps), the linear prediction can be wild
    although a refit would barely move. So the step is shortened until the other
    conditions' true χ² is least, and the held-out residual taken from the model there.
    """
    low, high = result.model.layout.bounds()
    best: tuple[float, NDArray[np.float64]] | None = None
    for t in HELD_SHRINK:
        p = result.params.copy()
        p[others] = np.clip(p[others] + t * step, low[others], high[others])
        r = result.model.residuals(p)
        rest = float(r[~inside] @ r[~inside])
        if best is None or rest < best[0]:
            best = (rest, r[inside])
    assert best is not None
    return best[1]


# --------------------------------------------------------------------------- judging
class ParameterState(StrEnum):
    FITTED = "fitted"
    AT_LIMIT = "at_limit"  # on a physical bound the data do not press against
    PUSHED = "pushed_past_limit"  # the data pull it past a physical bound: a finding
    UNRESOLVED = "unresolved"  # the data do not constrain it


@dataclass(frozen=True)
class ParameterJudgement:
    name: str
    index: int
    value: float
    sigma: float
    state: ParameterState
    bound: float | None = None
    chi2_gain: float = 0.0  # what a step past its bound, at most its range, gives back


def covariance(result: Fit) -> NDArray[np.float64]:
    """Parameter covariance from the Jacobian, inflated by the Birge ratio when the model
    does not reach the noise (its own misfit then dominates)."""
    jac = result.jacobian
    birge = max(1.0, result.chi2 / result.dof)
    with np.errstate(all="ignore"):
        cov = np.linalg.pinv(jac.T @ jac, rcond=1e-12) * birge
    return np.asarray(cov, dtype=np.float64)


def _gain_past_bound(gradient: float, variance: float, span: float) -> float:
    """The χ² a Gauss-Newton step past a bound gives back (the others refitted along),
    the step no longer than ``span``; ``variance``: the parameter's, unscaled."""
    step = abs(gradient) * variance
    if step <= span:
        return gradient * gradient * variance
    return 2.0 * abs(gradient) * span - span * span / variance


def sigmas(result: Fit) -> NDArray[np.float64]:
    return np.sqrt(np.maximum(np.diag(covariance(result)), 0.0))


def judge_parameters(result: Fit, *, unresolved_sigma: dict[str, float] | None = None
                     ) -> list[ParameterJudgement]:
    """Each nonlinear parameter's state: fitted, resting on or pushed past a bound, or
    unresolved (σ above ``unresolved_sigma[name]``, in the parameter's own units).

    The χ² a bound gives back is measured over a step no longer than the parameter's own
    range: the quadratic from the gradient is the model's linearisation, and far beyond
    the range it extrapolates along whatever direction the data barely constrain. On a
    clean benchmark belt (none@1428525103) the sensor's delay (0.29 ms in the plant)
    rested at 0 with σ 2.2 ms; the full step, "χ² would fall by 10", needed a delay of
    −6.8 ms, almost six times the whole range of 1.19 ms, and was a false alarm. A step
    of one range gives back 3.
    """
    model = result.model
    lay = model.layout
    low, high = lay.bounds()
    jac = result.jacobian
    gradient = jac.T @ result.residuals
    with np.errstate(all="ignore"):
        inverse = np.linalg.pinv(jac.T @ jac, rcond=1e-12)
    sig = sigmas(result)
    out: list[ParameterJudgement] = []
    for block in lay.blocks:
        if block.kind is BlockKind.LINEAR:
            continue
        sl = lay.slices[block.name]
        for offset, i in enumerate(range(sl.start, sl.stop)):
            name = block.name if block.size == 1 else f"{block.name}[{offset}]"
            value = float(result.params[i])
            side = int(result.active[i])
            span = float(high[i] - low[i])  # infinite for a one-sided bound
            if side == 0:
                near = AT_BOUND * (span if math.isfinite(span) else 1.0)
                side = -1 if value - low[i] <= near else 1 if high[i] - value <= near else 0
            if side != 0:
                gain = _gain_past_bound(float(gradient[i]), float(inverse[i, i]), span)
                pulls_out = gradient[i] * side < 0
                state = (ParameterState.PUSHED if pulls_out and gain > PUSH_CHI2
                         else ParameterState.AT_LIMIT)
                out.append(ParameterJudgement(name, i, value, float(sig[i]), state,
                                              float(low[i] if side < 0 else high[i]),
                                              gain if pulls_out else 0.0))
                continue
            limit = (unresolved_sigma or {}).get(block.name)
            state = (ParameterState.UNRESOLVED if limit is not None and sig[i] > limit
                     else ParameterState.FITTED)
            out.append(ParameterJudgement(name, i, value, float(sig[i]), state))
    return out
