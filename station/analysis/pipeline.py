"""From a timeline to trims: segment, demodulate, estimate, per operating condition.

This is the calibration's arithmetic, shared by ``station analyze`` and the
live procedure. It is pure: it takes the per-SYNC arrays a reader (or a live
capture) produced and returns numbers, so every step can be tested on arrays.
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from station.analysis.clipping import hidden_by_clipping
from station.analysis.estimate import (
    ESTIMATORS,
    TrimEstimate,
    TrimPoint,
    Unsupported,
)
from station.analysis.harmonics import (
    DEFAULT_ORDERS,
    Harmonics,
    hann,
    period_phasors,
    phase_drift,
)
from station.analysis.ringing import find_ringing, refine_ringing
from station.analysis.sampling import (
    ClockPhase,
    RateObservation,
    observe_rate,
    pooled_rate,
    sample_delays,
    wrap_sign,
)
from station.analysis.segments import (
    SETTLE_ORDERS,
    Rejected,
    Segment,
    SettleFallback,
    halves_shift,
    mechanical_angle,
    steady_segments,
)
from station.analysis.timeline import Timeline
from station.core import SATURATED_COUNTS, Mapper, Method, MethodChoice
from station.errors import InputError


@dataclass(frozen=True)
class AnalysisOptions:
    method: MethodChoice = MethodChoice.AUTO
    settle_periods: float | None = None  # None: judged from the data
    orders: int = DEFAULT_ORDERS
    # Settling of holds too short to judge from their own data (None: they are skipped).
    settle_fallback: SettleFallback | None = None
    settle_orders: tuple[int, ...] = SETTLE_ORDERS  # whose per-period phasors must settle
    white_noise: bool = False  # each segment's noise beyond every order (``demodulate``)
    # Each sample demodulated at the instant the sensor's own clock took it
    # (``station.analysis.sampling``). Off for the diagnosis, whose model names a drifting
    # clock (``sensor_clock_drift``) where calibration takes it out.
    sample_instants: bool = True
    # What earlier holds of the same run saw of the clock, pooled with this timeline's
    # own holds: one sensor, one clock, and a round's few holds time it less surely.
    clock_seen: tuple[RateObservation, ...] = ()
    # Where the timeline's first sample lies in the whole run (SYNCs before it), and the
    # wraps earlier holds of the run placed (run indices): every hold's phasors are put on
    # the run's one clock (``ClockPhase``), not left at wherever u stood in each hold.
    first_sample: int = 0
    wraps_seen: tuple[int, ...] = ()
    # Each hold's harmonics over its first and its second half as well: whether it was
    # still settling (``still_settling``).
    halves: bool = False
    # Holds still settling over their window have their ring found and fitted out
    # (``find_ringing``): for holds whose settle was given, without a model of the chain.
    find_ringing: bool = False
    # Phasors fitted under a Hann taper (``demodulate``): a verification's, judged against
    # limits a few hundredths of a m/s² high while a transient may still ring far from
    # orders 1 and 2 (development seed 1552235132: a disk's 99 Hz mode, rung by the
    # start after the reset, read 0.08 m/s² into H1 through a flat window's sidelobes,
    # and 0.03 under the taper, where the unit's steady H1 was 0.032).
    taper: bool = False


class EstimateUnsupported(InputError):
    """The recording holds no data from which trims can be estimated."""


@dataclass(frozen=True)
class Measured:
    """One steady segment and its harmonics."""

    segment: Segment
    harmonics: Harmonics
    saturated: int  # samples clipped at ±32767 (left out of the fit)
    # The sensor's clock as this hold saw it (its own rate, σ infinite where it could not
    # time one), the rate its samples were demodulated at (without the drive's angle, with
    # the speed error measured against the station's command, which holds it too), and a
    # wrap found in it.
    clock_observed: RateObservation | None = None
    clock_rate: float = 0.0
    wrap_at: int | None = None
    wrap_searched: bool = False  # a wrap was looked for in the hold (none found: none there)
    # Where the timeline lay in the run, and the mean delay (samples) the harmonics were
    # demodulated at: what ``point`` needs to put them on a clock known better later.
    first_sample: int = 0
    reference_delay: float = 0.0
    rotor: complex | None = None  # e^{jθ} of the rotor's angle at the hold's middle
    halves: tuple[Harmonics, Harmonics] | None = None  # ``AnalysisOptions.halves``
    # The most the samples over the sensor's rail could move any phasor (m/s²,
    # ``hidden_by_clipping``): an uncertainty no period-to-period scatter shows, because
    # the same phases are missing in every period.
    hidden: float = 0.0

    def point(self, clock: ClockPhase | None = None) -> TrimPoint:
        """The hold's phasors, on ``clock`` where given: a run's first holds are measured
        before the holds after them have timed the clock, and each phasor of order k
        turns by k·dθ/dn per sample of delay (a constant delay is a turn, which a hold
        cannot tell from its own phase: only the run's clock can). What clipping may
        hide adds to each phasor's variance as a bias of unknown sign would."""
        h = self.harmonics
        h1, h2 = h.h(1), h.h(2)
        if clock is not None and clock.rate:
            seg = self.segment
            late = float(_on_clock(clock, seg, self.first_sample, self.wrap_at,
                                   self.wrap_searched).mean())
            turn = -seg.angle_per_sample * (late - self.reference_delay)
            h1, h2 = h1 * cmath.exp(1j * turn), h2 * cmath.exp(2j * turn)
        hidden = self.hidden ** 2
        return TrimPoint(self.segment.trims, h1, h.var(1) + hidden, h2, h.var(2) + hidden,
                         self.rotor, self.hidden)


def _on_clock(clock: ClockPhase, seg: Segment, first_sample: int, wrap_at: int | None,
              searched: bool) -> NDArray[np.float64]:
    """Each sample's delay in a segment of a timeline that began at the run's sample
    ``first_sample``, on the run's ``clock``; ``wrap_at`` the wrap the hold placed itself
    (timeline index)."""
    index = first_sample + seg.start + np.arange(seg.samples, dtype=np.float64)
    return clock.delays(index, None if wrap_at is None else first_sample + wrap_at,
                        searched=searched)


@dataclass(frozen=True)
class Condition:
    """One operating point: amplitude and signed electrical frequency."""

    amplitude_mA: int
    electrical_hz: float
    measured: tuple[Measured, ...]

    @property
    def trim_points(self) -> int:
        return len({m.segment.trims for m in self.measured})


@dataclass(frozen=True)
class ConditionResult:
    condition: Condition
    estimate: TrimEstimate | None
    estimates: dict[Method, TrimEstimate]
    unsupported: dict[Method, str]


@dataclass(frozen=True)
class Analysis:
    """Everything ``station analyze`` reports; ``primary`` holds the trims."""

    timeline: Timeline
    conditions: tuple[ConditionResult, ...]
    rejected: tuple[Rejected, ...]
    primary: ConditionResult
    options: AnalysisOptions
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def estimate(self) -> TrimEstimate:
        assert self.primary.estimate is not None  # guaranteed by analyze()
        return self.primary.estimate

    @property
    def segments_used(self) -> int:
        return len(self.primary.condition.measured)


def tangential_signal(timeline: Timeline) -> NDArray[np.float64]:
    """Load tangential acceleration in m/s², NaN where lost or clipped."""
    meta = timeline.metadata
    counts = timeline.accel_counts[:, meta.tangential_axis.column].astype(np.float64)
    signal = counts * meta.sensor_lsb_mps2
    signal[~timeline.sensor_valid | timeline.saturated] = np.nan
    return signal


def measure(
    timeline: Timeline, options: AnalysisOptions, run: Mapper = map
) -> tuple[list[Measured], list[Rejected]]:
    """Harmonics of every steady segment of the run; ringing holds measured by ``run``."""
    signal = tangential_signal(timeline)
    segments, rejected = steady_segments(
        timeline, signal, settle_periods=options.settle_periods,
        settle_fallback=options.settle_fallback, settle_orders=options.settle_orders,
    )
    # Without the drive's angle the sensor's clock is part of the speed error measured from
    # the data (both turn every order alike), from orders 1 and 2; what that leaves, the
    # holds time from every order below (``observe_rate``).
    errors = [0.0] * len(segments)
    if not timeline.drive_reported:
        errors = speed_errors(segments, signal)
        segments = [replace(seg, microsteps_per_sample=seg.microsteps_per_sample * (1 + d))
                    for seg, d in zip(segments, errors, strict=True)]
    if any(seg.ringing for seg in segments):
        segments = refine_ringing(signal, segments, run)
    if options.find_ringing:
        segments = find_ringing(signal, segments, timeline.sync_period_s)
    clipped = [bool(timeline.saturated[seg.start : seg.stop].any()) for seg in segments]
    observed: list[RateObservation | None] = [None] * len(segments)
    rate = 0.0
    if options.sample_instants and segments:
        # A hold still ringing is not timed (its transient would pass for a drift), nor
        # one that clipped (``observe_rate``).
        observed = [None if seg.ringing or clipped[i] else observe_rate(
            signal[seg.start : seg.stop], seg.electrical_angle(), seg.samples_per_period)
            for i, seg in enumerate(segments)]
        rate = pooled_rate([*options.clock_seen, *(o for o in observed if o is not None)])
    # The wrap the clock makes, looked for the way the whole rate says (a drive's own
    # clock, part of a Modbus drive's speed error, makes none, and none is found), but
    # not in a clipped hold (``observe_rate``).
    timings = [sample_delays(signal[seg.start : seg.stop], seg.electrical_angle(),
                             seg.samples_per_period, rate,
                             wrap=0.0 if cut else wrap_sign(rate + error))
               if rate or (error and not cut) else None
               for seg, cut, error in zip(segments, clipped, errors, strict=True)]
    wraps = [seg.start + t.wrap_at for seg, t in zip(segments, timings, strict=True)
             if t is not None and t.wrap_at is not None]
    # With the drive's angle every hold's phasors share one reference: the run's clock.
    # Without it only magnitudes are used (each hold's own speed error turns its phasors
    # anyway), and the hold-centred delays do.
    phase = (ClockPhase.of(rate, [*options.wraps_seen,
                                  *(options.first_sample + w for w in wraps)])
             if rate and timeline.drive_reported else None)
    meta = timeline.metadata
    out: list[Measured] = []
    for seg, seen, timing, error, cut in zip(segments, observed, timings, errors, clipped,
                                             strict=True):
        window = signal[seg.start : seg.stop]
        delays = None if timing is None else timing.delays
        own = None if timing is None or timing.wrap_at is None else seg.start + timing.wrap_at
        searched = timing is not None and not cut and wrap_sign(rate + error) != 0.0
        if phase is not None:
            delays = _on_clock(phase, seg, options.first_sample, own, searched)
        valid = window[np.isfinite(window)]
        if valid.size and np.ptp(valid) == 0.0:
            # No live sensor reads one value for a whole hold: a stuck or unplugged one
            # does, and its "harmonics" of zero variance would outweigh every other hold.
            rejected.append(Rejected(seg.start, seg.stop, "the sensor read one constant value "
                                     "throughout the hold (stuck or unplugged)"))
            continue
        try:
            h = seg.harmonics(window, options.orders, white_noise=options.white_noise,
                              delays=delays, taper=options.taper)
        except ValueError as exc:
            rejected.append(Rejected(seg.start, seg.stop, f"cannot demodulate: {exc}"))
            continue
        halves = (seg.halves(window, options.orders, white_noise=options.white_noise,
                             delays=delays, taper=options.taper) if options.halves else None)
        saturated = int(np.count_nonzero(timeline.saturated[seg.start : seg.stop]))
        counts = timeline.accel_counts[seg.start : seg.stop, meta.tangential_axis.column]
        at_rail = ((np.abs(counts) >= SATURATED_COUNTS)
                   & timeline.sensor_valid[seg.start : seg.stop])
        model = np.full(window.size, np.nan)
        if h.imputed is not None:
            model[np.isnan(window)] = h.imputed
        hidden = hidden_by_clipping(window, counts.astype(np.int64), at_rail,
                                    SATURATED_COUNTS * meta.sensor_lsb_mps2, imputed=model,
                                    weights=hann(window.size) if options.taper else None)
        rotor = None
        if timeline.drive_reported:
            middle = seg.position0 + seg.microsteps_per_sample * (seg.samples - 1) / 2.0
            rotor = cmath.exp(1j * float(mechanical_angle(
                np.array([middle]), meta.microsteps_per_fullstep, meta.rotor_teeth)[0]))
        out.append(Measured(seg, h, saturated, seen, rate + error, own, searched,
                            options.first_sample,
                            0.0 if delays is None else float(delays.mean()), rotor, halves,
                            hidden))
    return out, rejected


def still_settling(m: Measured, limits: Sequence[float]) -> tuple[int, ...]:
    """The orders (1, 2, … for each of ``limits``) at which the hold was still settling
    (``halves_shift``) by enough to decide a verdict against that limit: where the level
    measured lies within twice what is still moving of it. A detent disk started from
    standstill after its reset (development seed 100830014) rang down from several m/s²
    across its hold and read 0.11 m/s² of H1 against a limit of 0.08, where its steady
    state is 0.015; a unit ringing at 0.01 under the same limit can only pass. Holds
    measured without halves never count as settling.
    """
    if m.halves is None:
        return ()
    early, late = m.halves
    return tuple(order for order, limit in enumerate(limits, start=1)
                 if abs(abs(m.harmonics.h(order)) - limit)
                 < 2.0 * halves_shift(early, late, order))


_DRIFT_ORDERS = (1, 2)
_DRIFT_SIGNIFICANCE = 3.0
"""Standard errors a pooled speed error must exceed before the command is corrected."""


def speed_errors(segments: Sequence[Segment], signal: NDArray[np.float64]) -> list[float]:
    """Per segment, the drive's relative speed error against the station's command.

    Without the drive's position demand the electrical frequency is the
    commanded one, and a drive whose clock runs off by δ smears every phasor
    by 2πkδ per period. δ is measured from the phase drift of orders 1 and 2
    over each segment and pooled over all segments at one commanded speed
    (one drive clock), so short or quiet segments borrow from the others.
    """
    drifts: list[tuple[float, float]] = []
    for seg in segments:
        window = signal[seg.start : seg.stop]
        present = ~np.isnan(window)
        if not present.any():
            drifts.append((0.0, math.inf))
            continue
        centred = np.where(present, window - np.mean(window[present]), 0.0)
        spp = seg.samples_per_period
        z = period_phasors(centred, present, seg.electrical_angle(), spp, _DRIFT_ORDERS)
        drifts.append(phase_drift(z, _DRIFT_ORDERS))
    out: list[float] = []
    for seg in segments:
        same = [(d, sigma) for other, (d, sigma) in zip(segments, drifts, strict=True)
                if abs(other.microsteps_per_sample - seg.microsteps_per_sample)
                <= SAME_SPEED * abs(seg.microsteps_per_sample) and math.isfinite(sigma)]
        information = sum(1.0 / sigma**2 for _, sigma in same)
        if information == 0.0:
            out.append(0.0)
            continue
        pooled = sum(d / sigma**2 for d, sigma in same) / information
        # A drift the data cannot tell from zero leaves the command as it is: near the
        # null the phasors are mostly noise, and "correcting" by noise moves the speed.
        if abs(pooled) <= _DRIFT_SIGNIFICANCE / math.sqrt(information):
            out.append(0.0)
            continue
        # The drift is measured against the segment's own direction of rotation.
        out.append(pooled if seg.microsteps_per_sample > 0 else -pooled)
    return out


SAME_SPEED = 1e-3
"""Relative difference below which two segments ran at one commanded speed."""


def group_conditions(measured: Sequence[Measured], sync_period_s: float) -> list[Condition]:
    """Segments grouped by amplitude and speed, the condition with most trim points first.

    Fitted slopes of one commanded velocity differ in their last digits, so
    speeds are clustered (sorted, split where consecutive ones differ by more
    than ``SAME_SPEED``) rather than compared exactly.
    """
    by_key: dict[tuple[int, bool], list[Measured]] = {}
    for m in measured:
        forward = m.segment.microsteps_per_sample > 0
        by_key.setdefault((m.segment.amplitude_mA, forward), []).append(m)
    conditions: list[Condition] = []
    for (amplitude, _), members in by_key.items():
        members.sort(key=lambda m: abs(m.segment.microsteps_per_sample))
        cluster: list[Measured] = []
        for m in members:
            speed = abs(m.segment.microsteps_per_sample)
            last = abs(cluster[-1].segment.microsteps_per_sample) if cluster else speed
            if speed > last * (1 + SAME_SPEED):
                conditions.append(_condition(amplitude, cluster, sync_period_s))
                cluster = []
            cluster.append(m)
        conditions.append(_condition(amplitude, cluster, sync_period_s))
    conditions.sort(key=lambda c: (c.trim_points, len(c.measured), c.amplitude_mA), reverse=True)
    return conditions


def _condition(amplitude: int, members: Sequence[Measured], sync_period_s: float) -> Condition:
    # Keep the run's order: people read trim points in the order they were measured.
    ordered = sorted(members, key=lambda m: m.segment.start)
    hz = float(np.median([m.segment.electrical_hz(sync_period_s) for m in ordered]))
    return Condition(amplitude_mA=amplitude, electrical_hz=hz, measured=tuple(ordered))


def estimate_condition(condition: Condition, choice: MethodChoice, *,
                       drive_reported: bool = True) -> ConditionResult:
    """Both estimators where the data allow; the chosen one's result, or why not."""
    points = [m.point() for m in condition.measured]
    estimates: dict[Method, TrimEstimate] = {}
    unsupported: dict[Method, str] = {}
    for method, estimator in ESTIMATORS.items():
        if method.needs_angle and not drive_reported:
            unsupported[method] = ("the drive reported no electrical angle (no TPDOs: a Modbus "
                                   "drive); only magnitudes are meaningful")
            continue
        try:
            estimates[method] = estimator(points)
        except Unsupported as exc:
            unsupported[method] = str(exc)
    if choice is MethodChoice.AUTO:
        chosen = next((estimates[m] for m in ESTIMATORS if m in estimates), None)
    else:
        chosen = estimates.get(Method(choice.value))
    return ConditionResult(condition, chosen, estimates, unsupported)


def analyze(timeline: Timeline, options: AnalysisOptions | None = None, *,
            estimate_required: bool = True) -> Analysis:
    """Trims from a timeline; raises EstimateUnsupported with every reason when none,
    unless ``estimate_required`` is False: a report draws the holds of a recording no
    estimator here supports (a magnitude sweep, a run stopped after its baseline), its
    primary condition then the one with the most trim points and no estimate.

    BLAS runs single-threaded here: the fits are small (thousands of rows, a
    few dozen columns), and on a loaded 2-core machine OpenBLAS's threads made
    them 5-30 times slower.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _analyze(timeline, options or AnalysisOptions(), estimate_required)


def _analyze(timeline: Timeline, opts: AnalysisOptions, estimate_required: bool) -> Analysis:
    measured, rejected = measure(timeline, opts)
    if not measured:
        reasons = sorted({r.reason for r in rejected}) or ["the drive never ran at constant speed"]
        raise EstimateUnsupported(f"no steady segment to analyse: {'; '.join(reasons)}")
    results = [
        estimate_condition(c, opts.method, drive_reported=timeline.drive_reported)
        for c in group_conditions(measured, timeline.sync_period_s)
    ]
    primary = next((r for r in results if r.estimate is not None), None)
    if primary is None and not estimate_required:
        primary = results[0]
    if primary is None:
        top = results[0]
        why = "; ".join(f"{m.value}: {reason}" for m, reason in top.unsupported.items())
        raise EstimateUnsupported(
            f"the data cannot support an estimate at {top.condition.amplitude_mA} mA, "
            f"{top.condition.electrical_hz:.2f} Hz ({why})"
        )
    warnings: list[str] = []
    if primary.estimate is not None and primary is not results[0]:
        warnings.append(
            "the condition with the most trim points supports no estimate; "
            "trims come from the next one"
        )
    if timeline.losses.saturated_samples:
        warnings.append(
            f"{timeline.losses.saturated_samples} samples clipped at the sensor's full scale "
            "were left out"
        )
    return Analysis(
        timeline=timeline,
        conditions=tuple(results),
        rejected=tuple(rejected),
        primary=primary,
        options=opts,
        warnings=tuple(warnings),
    )
