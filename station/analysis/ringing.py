"""The chain's ringing measured on the holds that still ring, not taken from its model.

A hold shorter than the chain's slowest decay has that mode fitted out beside the
harmonics, at the poles the chain's model gives (``segments.ChainDecay``). The model is
fitted to steady harmonics, which pin the chain's transfer at the harmonics' frequencies
rather than its mode's own frequency and decay. Near a lightly damped mode that small
difference is all that matters: on the clean twin of benchmark trial
rotor_eccentricity@1926034785 (a disk whose rotor mode sits on order 6 at 570 mA, holds
of 0.57 s) the model's pole rang 1.4 % fast and decayed 39 % too fast; ringing fitted
out there left the phasors of the order nearest the mode 5 to 28 σ off the same holds
held 4 s, and the nominal fit at 12 times its noise. The ringing measures its own pole,
and the holds of one operating point share it: fitted jointly on them, every phasor came
within 0.6 σ of the long holds'.

Each hold then measures its own, started from its operating point's: its trims set the
rotor's stiffness a little apart from its neighbours', and its ringing's amplitude, on a
spring that softens as it swings, its frequency. A shift of 0.1 % is nothing to the model
but, with a mode this lightly damped beside a harmonic, several σ of that harmonic: on
the same twin the shared poles left the phasors 2,810 (z² against the long holds, 84
holds of 8 orders), each hold's own 965.

A hold's ring is also a chirp: the rotor turns through the hold, and an eccentric rotor's
spring is stiffer on one side of its revolution. On benchmark trial
rotor_eccentricity@1926034785 (4.6 %, holds of 0.57 s turning through 29° of the
revolution, some 2.5 % of the spring), rings of one frequency left the nominal model with
eccentricity at 7,171 for 1,361 values; each hold's frequency measured moving linearly over
the hold (its sidebands ride on it), 1,531 for 1,429.

The poles are measured by variable projection (each trial pole's harmonics and ringing
amplitudes are the linear least-squares fit, only the poles are searched, along the
projection's exact slopes: ``harmonics.DecayFit.slopes``), within a
factor of the model's decay and a share of its frequency, and kept only where they
explain more than the parameters they cost: a hold whose ringing is too weak to
measure keeps the model's, which then also biases nothing.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from station.analysis.harmonics import DecayFit, SteadyProjection
from station.analysis.segments import SETTLE_ORDERS, Segment, Settling, halves_shift
from station.core import Mapper

RATE_RANGE = 3.0
"""How far a measured decay rate may lie from the model's, as a factor either way."""
FREQUENCY_RANGE = 0.1
"""...and a measured ringing frequency, as a share of the model's."""
HOLD_RATE_RANGE = 1.5
HOLD_FREQUENCY_RANGE = 0.06
"""How far one hold's poles may lie from those its operating point shares: an eccentric
rotor's spring is stiffer on one side of its revolution by twice its eccentricity (the
bench draws up to 10 %), and each hold stands on its own part of the revolution, so its
mode lies up to 5 % from their mean (benchmark trial rotor_eccentricity@1926034785, 4.6 %:
within 2 % the nominal model with eccentricity left 9,083 for 1,259 values, within 6 %
7,171 for 1,361)."""
HOLD_DRIFT_RANGE = 0.06
"""How far one hold's ringing frequency may move over the hold, as a share: the same
spring changes as the rotor turns through the hold (on that trial 29° of the revolution
in 0.57 s, some 2.5 % of its stiffness), and the ring is a chirp."""
PARAMETER_COST = 2.0
"""Noise variances of residual a measured pole's parameter must remove to be kept (the
Akaike criterion's price of a parameter)."""


def refine_ringing(signal: NDArray[np.float64], segments: list[Segment],
                   run: Mapper = map) -> list[Segment]:
    """``segments`` with each operating point's ringing poles measured on its holds
    (``signal`` the tangential acceleration, NaN where missing); the operating points
    one by one, or side by side by ``run``.

    An operating point's search reads only its own holds, and it is most of the time a
    diagnosis spends observing a belt: benchmark trial current_loop_lag@1703429826 spent
    30 s of its 58 here, in two observations of 16 and 17 operating points.
    """
    groups: dict[tuple[int, tuple[complex, ...]], list[int]] = {}
    for i, seg in enumerate(segments):
        if seg.ringing:
            groups.setdefault((seg.amplitude_mA, seg.ringing), []).append(i)
    members = list(groups.values())
    # Each job carries its holds' samples, not the whole recording.
    refined = run(_refined_point, [[segments[i] for i in group] for group in members],
                  [[signal[segments[i].start:segments[i].stop] for i in group]
                   for group in members])
    out = list(segments)
    for group, point in zip(members, refined, strict=True):
        for i, seg in zip(group, point, strict=True):
            out[i] = seg
    return out


def _refined_point(holds: list[Segment], samples: list[NDArray[np.float64]]
                   ) -> list[Segment]:
    """The holds of one operating point (``samples`` each one's signal) with their
    ringing poles measured: shared by all, then each hold's own near them."""
    model = holds[0].ringing
    # Factored once per hold: the shared search and the hold's own both use it.
    windows = [_projection(y, seg) for y, seg in zip(samples, holds, strict=True)]
    shared = measured_poles(holds, windows, model, RATE_RANGE, FREQUENCY_RANGE)
    if shared is None:
        return holds  # rings too weakly to measure together, and so each hold alone
    out = []
    for seg, window in zip(holds, windows, strict=True):
        # Within a step of the shared poles' grid: searched from them alone.
        own = measured_poles([seg], [window], shared.poles, HOLD_RATE_RANGE,
                             HOLD_FREQUENCY_RANGE, grid=False, drift_range=HOLD_DRIFT_RANGE,
                             rate_prior=True)
        ring = own or shared
        out.append(replace(seg, ringing=ring.poles, drift=ring.drift))
    return out


@dataclass(frozen=True)
class Ring:
    """Poles measured on holds (per sample), and how fast their frequencies move as a
    share of each per sample (``Segment.drift``); where they move, a pole's frequency is
    the one at its window's middle."""

    poles: tuple[complex, ...]
    drift: float = 0.0


def _projection(samples: NDArray[np.float64], seg: Segment) -> SteadyProjection:
    return SteadyProjection.of(samples, seg.electrical_angle(),
                               seg.samples_per_period, seg.start - seg.held_from)


def _layout(model: tuple[complex, ...]) -> list[tuple[int, int | None]]:
    """Where each pole of ``model`` sits among the searched parameters: the index of the
    log of its rate's factor on the model's and, for a ringing pole, of its frequency's
    (None for a pole that does not ring). The pole search, its bounds and its grid all
    read it, so they cannot disagree on the order."""
    out: list[tuple[int, int | None]] = []
    j = 0
    for pole in model:
        rings = pole.imag != 0.0
        out.append((j, j + 1 if rings else None))
        j += 1 + rings
    return out


def _poles(model: tuple[complex, ...], x: NDArray[np.float64]) -> tuple[complex, ...]:
    """The poles ``x`` describes (``_layout``)."""
    return tuple(complex(pole.real * math.exp(float(x[r])),
                         0.0 if f is None else pole.imag * math.exp(float(x[f])))
                 for pole, (r, f) in zip(model, _layout(model), strict=True))


SEARCH_TOLERANCE = 1e-5
"""Relative change of the residual, or of a pole, at which a search stops: a pole to a
hundred-thousandth, and what is left to gain far below the noise's variance that decides
whether the pole is kept (the defaults, 1e-8, took 160 evaluations a search)."""
SEARCH_EVALUATIONS = 40
"""Evaluations of the residual one search may make."""

STARTS = 1
"""Searches made besides the one from the model's poles: from the points of the frequency
grid (``_starts``) that fit best."""


def _starts(model: tuple[complex, ...], low: NDArray[np.float64], samples: int
            ) -> list[NDArray[np.float64]]:
    """Where the search for the poles starts: the model's poles, and each ringing pole
    moved along a grid of its frequency a quarter of the window's resolution apart.

    The residual is not convex in a pole's frequency: a ring beside a harmonic cannot
    cross it (there the two are one column), so a search started on the wrong side of it
    stays there. Benchmark belt magnetic_saturation@1628227624 rings at 34.4 Hz beside
    order 2 at 35 Hz (17.5 Hz electrical): started from the model, a hold's pole settled
    at 34.3 Hz, and the phasor of order 2 came out 86 σ off; the other holds' at 35.5 Hz,
    within 3 σ.
    """
    starts = [np.zeros(low.size)]
    for pole, (_, f) in zip(model, _layout(model), strict=True):
        if f is None:
            continue
        step = 0.25 * (2 * math.pi / samples) / abs(pole.imag)
        for offset in np.arange(low[f], -low[f], step)[1:]:
            x = np.zeros(low.size)
            x[f] = offset
            starts.append(x)
    return starts


TANGENT_STEP = 1e-6
"""Step of the central differences of the pole map (``measured_poles``)."""
DIFFERENCE_STEP = 1e-5
"""Relative step of a residual's forward differences where its decays' columns are not
independent (``measured_poles``)."""


def _differenced(residual: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                 x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Forward differences of ``residual`` at ``x``, each step ``DIFFERENCE_STEP`` of
    the parameter's size or of 1."""
    base = residual(x)
    out = np.empty((base.size, x.size))
    for j in range(x.size):
        y = x.copy()
        y[j] += DIFFERENCE_STEP * max(1.0, abs(float(x[j])))
        out[:, j] = (residual(y) - base) / (y[j] - x[j])
    return out


def _window_residual(ring: Callable[[NDArray[np.float64]], Ring], s: Segment,
                     w: SteadyProjection, x: NDArray[np.float64]) -> NDArray[np.float64]:
    r = ring(x)
    return w.residual(*s.decays(r.poles, r.drift))


def measured_poles(members: list[Segment], windows: list[SteadyProjection],
                   model: tuple[complex, ...], rate_range: float, frequency_range: float,
                   *, grid: bool = True, drift_range: float = 0.0,
                   rate_prior: bool = False) -> Ring | None:
    """The ringing poles that ``members`` (holds of one operating point, ``windows`` their
    samples with the harmonics projected out) share, searched
    within ``rate_range`` (a factor) and ``frequency_range`` (a share) of ``model``, from
    ``model`` and, with ``grid``, from the best of a grid of frequencies; with
    ``drift_range``, also how fast their frequencies move, up to that share over the
    longest window; None where the data cannot tell them from ``model``.

    A search that ends on a bound of a frequency or of the drift found another mode than
    the model's, and is refused. With ``rate_prior`` the decay rate's range is what the
    model's neighbours allow rather than a test, and the search may end on it: over a
    window of a fifth of the decay time the rate and the drift trade for each other (a
    test's chirp of 4 % fitted as well with 6 % and half the decay)."""
    if any(p.real >= 0.0 for p in model):
        return None  # a mode that does not decay has no rate to scale
    drifts = drift_range > 0.0
    # The drift is searched as the share its frequencies move by the last sample.
    span = max(float(w.times[-1]) for w in windows if w.times.size) if drifts else 1.0

    def ring(x: NDArray[np.float64]) -> Ring:
        return Ring(_poles(model, x), float(x[-1]) / span if drifts else 0.0)

    fitted: dict[bytes, list[DecayFit]] = {}  # the latest point's fits, for its slopes

    def fitted_at(x: NDArray[np.float64]) -> list[DecayFit]:
        key = x.tobytes()
        if key not in fitted:
            r = ring(x)
            fitted.clear()
            fitted[key] = [w.fit(*s.decays(r.poles, r.drift))
                           for s, w in zip(members, windows, strict=True)]
        return fitted[key]

    def residual(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.concatenate([f.residual for f in fitted_at(x)])

    def tangents(x: NDArray[np.float64]) -> NDArray[np.float64]:
        """(P, decays, 3): how each decay's rate, frequency and sweep moves with each
        parameter; central differences of the pole map, exact to rounding (it scales).
        The same for every member: their sidebands differ by a constant turn."""
        out = np.empty((x.size, len(members[0].decays(model)[0]), 3))
        for j in range(x.size):
            step = np.zeros(x.size)
            step[j] = TANGENT_STEP
            ends = []
            for sign in (1.0, -1.0):
                r = ring(x + sign * step)
                poles, sweeps = members[0].decays(r.poles, r.drift)
                ends.append(np.array([[p.real, p.imag, c] for p, c in itertools.zip_longest(
                    poles, sweeps, fillvalue=0.0)]))
            out[j] = (ends[0] - ends[1]) / (2.0 * TANGENT_STEP)
        return out

    def slopes(x: NDArray[np.float64]) -> NDArray[np.float64]:
        moves = tangents(x)
        blocks = []
        for s, w, f in zip(members, windows, fitted_at(x), strict=True):
            block = f.slopes(moves)
            if block is None:
                # Columns the window cannot tell apart: the residual's own differences.
                block = _differenced(functools.partial(_window_residual, ring, s, w), x)
            blocks.append(block)
        return np.concatenate(blocks)

    layout = _layout(model)
    low = np.zeros(sum(1 + (f is not None) for _, f in layout) + drifts)
    for r, f in layout:
        low[r] = -math.log(rate_range)
        if f is not None:
            low[f] = math.log1p(-frequency_range)
    if drifts:
        low[-1] = -drift_range
    size = low.size
    before = residual(np.zeros(size))
    fits = []
    starts = _starts(model, low, max(w.times.size for w in windows)) if grid else [
        np.zeros(size)]
    # Grid points are searched from only where they fit better than the model's poles.
    scored = sorted((float(np.sum(residual(x) ** 2)), j) for j, x in enumerate(starts[1:]))
    better = [starts[1 + j] for cost, j in scored[:STARTS] if cost < float(before @ before)]
    for start in [starts[0], *better]:
        try:
            fits.append(least_squares(residual, start, jac=slopes, bounds=(low, -low),
                                      x_scale=0.01, ftol=SEARCH_TOLERANCE,
                                      xtol=SEARCH_TOLERANCE, max_nfev=SEARCH_EVALUATIONS))
        except (ValueError, np.linalg.LinAlgError):
            continue
    if not fits:
        return None
    fit = min(fits, key=lambda f: float(f.cost))
    after = fit.fun
    # Each hold fits its harmonics and both parts of every decay.
    columns = sum(w.columns + 2 * len(s.decays(model)[0])
                  for s, w in zip(members, windows, strict=True))
    dof = sum(w.left.size for w in windows) - columns - size
    bounds = fit.active_mask != 0
    if rate_prior:
        bounds[[r for r, _ in layout]] = False
    if dof <= 0 or fit.status < 0 or np.any(bounds):
        # At a bound the data want another mode than the model's: not this one's pole.
        return None
    noise = float(after @ after) / dof
    if float(before @ before - after @ after) <= PARAMETER_COST * size * noise:
        return None
    return ring(fit.x)


# --------------------------------------------------------------------------- without a model
FOUND_RATES_PER_S = np.geomspace(2.0, 80.0, 7)
"""Decay rates (1/s) a ring is looked for at where no model gives one: slower rings are
steady over a hold, faster ones are over within a calibration's settle."""
FOUND_FREQUENCIES = 36
"""...and frequencies, log-spaced from a tenth of the electrical frequency to 0.4 of
the sampling rate."""
FOUND_COST = 4.0
"""Noise variances of residual each parameter of a ring found without a model (its pole,
and each hold's amplitudes at the pole and its sidebands) must remove for the ring to be
kept: twice the Akaike price, because the grid tries some 250 poles and keeps the best."""


def settling_holds(signal: NDArray[np.float64], segments: list[Segment],
                   orders: tuple[int, ...] = SETTLE_ORDERS) -> list[int]:
    """Which holds, not already known to ring, were still settling over their window at
    any of ``orders`` (``halves_shift``)."""
    out = []
    for i, seg in enumerate(segments):
        halves = None if seg.ringing else seg.halves(signal[seg.start:seg.stop], max(orders))
        if halves is not None and any(halves_shift(*halves, k) > 0.0 for k in orders):
            out.append(i)
    return out


def find_ringing(signal: NDArray[np.float64], segments: list[Segment], sync_period_s: float
                 ) -> list[Segment]:
    """``segments`` with the holds still settling given the ring they share, where no
    model of the chain says where to look (a calibration knows none): a belt's load mode
    excited by every trim step rings through a calibration's short holds, and its phasors
    moved by 11-22 standard errors between the two halves of every hold (development seed
    2046250336: 9.8 mA from its optimum). The ring is looked for on a grid of decay rates
    and frequencies jointly over the settling holds (one load, one mode), and from the
    best of it ``refine_ringing`` measures it as it would a model's (and each hold's own
    near it). A ring that does not remove ``FOUND_COST`` noise variances per parameter
    is not fitted at all; one that does, but that the refinement cannot measure more
    closely, is fitted out where the grid found it, at a cost in variance but no bias.
    Only the holds found settling are refined: holds already ringing at a model's poles
    were measured before."""
    settling = settling_holds(signal, segments)
    if not settling:
        return segments
    members = [segments[i] for i in settling]
    windows = [_projection(signal[s.start:s.stop], s) for s in members]
    electrical = abs(members[0].angle_per_sample) / (2.0 * math.pi) / sync_period_s
    frequencies = np.geomspace(0.1 * electrical, 0.4 / sync_period_s, FOUND_FREQUENCIES)
    best, least, slowest = None, math.inf, False
    for rate in FOUND_RATES_PER_S:
        for hz in frequencies:
            pole = complex(-rate, 2.0 * math.pi * hz) * sync_period_s
            total = sum(float(np.sum(w.fit(*s.decays((pole,))).residual ** 2))
                        for s, w in zip(members, windows, strict=True))
            if total < least:
                best, least, slowest = pole, total, rate == FOUND_RATES_PER_S[0]
    # A ring as slow as the slowest tried is steady over a hold: what it fits is the
    # hold's own content (near a harmonic, the harmonic itself), not a transient.
    if best is None or slowest:
        return segments
    before = sum(float(np.sum(w.left**2)) for w in windows)
    columns = sum(2 * len(s.decays((best,))[0]) for s in members) + 2
    left = sum(w.left.size for w in windows) - sum(w.columns for w in windows) - columns
    if left <= 0 or before - least < FOUND_COST * columns * least / left:
        return segments
    refined = refine_ringing(signal, [replace(s, ringing=(best,), settling=Settling.RINGING)
                                      for s in members])
    out = list(segments)
    for i, seg in zip(settling, refined, strict=True):
        out[i] = seg
    return out
