"""What a diagnosis fits: every steady segment's harmonics 1..K, grouped by condition.

A condition is one operating point (current amplitude, signed speed). The
diagnosis compares models across conditions, so it keeps every segment, not
only those of the condition a calibration would use, and it keeps orders up
to 8: the effects it looks for live above the two orders the paper uses.

Besides the phasors, each segment carries what the slower physics needs:
where the rotor was mechanically (a once-per-revolution effect modulates the
harmonics with it), which samples it spans (a drifting sensor clock shifts
them by an amount that grows with the sample number) and how fast the load
turns (friction depends on the load's velocity, mean plus ripple).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Set
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from station.analysis.harmonics import JOINT_ORDERS, Harmonics, slow_variance
from station.analysis.pipeline import (
    AnalysisOptions,
    Measured,
    group_conditions,
    measure,
    tangential_signal,
)
from station.analysis.segments import (
    Rejected,
    Segment,
    SettleFallback,
    Settling,
    mechanical_angle,
    steady_segments,
)
from station.analysis.timeline import Timeline
from station.core import SENSOR_RANGES_G, STANDARD_GRAVITY, Axis, Mapper
from station.errors import InputError
from station.recording import RecordingMetadata

DIAGNOSIS_ORDERS = 8
"""Harmonic orders of the electrical frequency that a diagnosis models and maps."""

DEMODULATED_ORDERS = JOINT_ORDERS
"""Orders kept from each demodulation (as far as the sampling allows): a rough unit
swings far enough to put energy above order 8, and the swing is part of the motion."""

BEYOND_NYQUIST = 0.4
"""Orders above the modelled ones enter the motion only below this fraction of the
sample rate, where the sensor's harmonics are not aliases."""

MODEL_FLOOR = 0.003
"""Relative uncertainty of any model's torque balance: how far a model of a real chain
(or another simulator's integration of it) can be trusted. Applied to each phasor times
the chain's magnification of a torque error there (``Observations.with_floor``): far
from a mode an acceleration known to 1 %, near a lightly damped one much less. Without
it every high-SNR recording would be a mismatch."""

MIN_CONDITIONS = 3
"""Fewer conditions than this cannot hold one out and still fit the rest."""

NEEDED_SCHEDULE = (
    "a characterization recording is needed: several speeds in both directions, several "
    "currents and small trim steps at each (`station characterize SERIAL`, or "
    "`station sim record OUT --schedule characterization`)"
)

MAX_CLIPPED = 0.01
"""Fraction of a segment's samples that may sit at the sensor's full scale. Clipped
samples are left out of the fit, and a few at the peaks cost only precision; beyond
this the samples left are the quiet part of each period, and the phasors they give are
both biased and ill-conditioned."""

NOT_PERIODIC_NOISE = 30.0
"""What a segment's harmonics leave, as a multiple of the recording's noise variance, above
which its motion may not be periodic (see ``NOT_PERIODIC_SHARE``)."""
NOT_PERIODIC_SHARE = 0.2
"""...and as a share of the harmonics' own rms: both must be exceeded. Near its resonance a
swinging rotor can lose its periodic steady state (the chain's own mode keeps swinging,
beating with the harmonics, or the motion turns chaotic), and no model of a periodic
motion describes it: on a development disk 17 such segments of 127 left the nominal fit
at χ²/dof 50, against 0.25 without them. A large ripple with a small ringing tail (under
a tenth of it) or a small ripple at the noise (a trimmed unit) stays."""
NOT_PERIODIC_SLOW_SHARE = 0.01
"""Below ``NOT_PERIODIC_SHARE``, a segment is still not periodic when what its harmonics leave
is above this share of their rms and above ``NOT_PERIODIC_NOISE`` times the noise even with
its harmonics let change slowly through the hold (``slow_variance``: a modulation turning
with the rotor, a drifting clock, is periodic to the model). A rough unit at a low current
(offsets of 100 and 200 mA at 350 mA, Coulomb friction of 14 % of the holding torque)
nearly lost step in every hold of that current: its motion left 90 to 13,800 times the
noise at 2 to 15 % of the ripple, and kept it all with the harmonics let change (benchmark
trial friction@2082563418). Fitted with them, the nominal model left χ² 3.1 million and
no group could fit; without them friction was named at 14.3 and 13.3 % of the holding
torque (the plant's 14.3 and 13.2) and left 541 of 545 values. Under a hundredth of the
ripple the phasors err less than the model floor (``MODEL_FLOOR``) allows for anyway."""
SPEED_CHANGE_SHARE = 0.3
"""Share of the load's own speed by which its speed may change through a hold before the hold
is no steady motion. A periodic motion has no mean acceleration over whole periods; one whose
mean acceleration, times the hold's length, is a large part of the speed the load should turn
at stood still or caught up in the hold. Through a compliant belt, Coulomb friction holds the
load still after a reversal until the motor has wound the belt through the friction's two
levels (their sum over the belt's stiffness, at the load: 0.22 rad, 0.44 s at 14 Hz on
benchmark trial friction@416744003, 33 % of the holding torque through a 53 Hz belt): the
first hold of three operating points changed by 89 to 113 % of the load's speed (9 to 18
times what the noise gives), every other by at most 36 % (3 times), and the one at 89 % alone
left χ² 1,902 of the nominal fit's 4,285."""
SPEED_CHANGE_SIGMAS = 5.0
"""...and by this many standard deviations of the change the sensor's noise alone gives."""
NOISE_QUANTILE = 0.1
"""The recording's own noise variance: this low quantile of its segments' residual
variances, the quietest being those where nothing but the sensor's noise is left."""

_MECHANICAL_SAMPLES = 33
"""Points per segment over which the mechanical-angle average is taken (exact for a
line; the angle is a line within a segment)."""


class NotDiagnosable(InputError):
    """The recording does not hold the data a diagnosis needs; the message says which."""


@dataclass(frozen=True)
class ConditionKey:
    """One operating point as the drive reported it."""

    amplitude_mA: int
    electrical_hz: float  # signed: negative when the electrical angle decreases

    @property
    def direction(self) -> int:
        return 1 if self.electrical_hz > 0 else -1

    def label(self) -> str:
        return f"{self.amplitude_mA} mA, {self.electrical_hz:+.1f} Hz"

    def as_dict(self) -> dict[str, float | int | str]:
        return {
            "amplitude_mA": self.amplitude_mA,
            "electrical_hz": round(self.electrical_hz, 4),
            "direction": "forward" if self.direction > 0 else "reverse",
        }


@dataclass(frozen=True)
class Skipped:
    """A stretch of steady motion the diagnosis could not use, and why."""

    start_s: float
    stop_s: float
    reason: str

    def as_dict(self) -> dict[str, float | str]:
        return {"start_s": round(self.start_s, 3), "stop_s": round(self.stop_s, 3),
                "reason": self.reason}


@dataclass(frozen=True)
class OtherAxis:
    """One of the sensor's two axes besides the tangential one, demodulated like it.

    ICD.md names only the tangential axis; the others are radial and axial in some
    order, and a check of the element's alignment must not need to know which.
    """

    axis: Axis
    phasors: NDArray[np.complex128]  # (S, K) m/s², same reference as the tangential ones
    sigma: NDArray[np.float64]  # (S, K)


@dataclass(frozen=True)
class Observations:
    """Per-segment arrays (S segments, K orders) and the conditions they belong to.

    ``phasors`` are the measured tangential acceleration harmonics in m/s²,
    referenced to the drive's reported electrical angle (ICD.md §2), as
    ``station.analysis.harmonics`` defines them; ``sigma`` their standard
    uncertainty (|Ĥ − H|, both parts together).
    """

    metadata: RecordingMetadata
    conditions: tuple[ConditionKey, ...]
    condition: NDArray[np.intp]  # (S,) index into ``conditions``
    amplitude_A: NDArray[np.float64]  # (S,) reported current amplitude
    omega: NDArray[np.float64]  # (S,) signed electrical angular speed, rad/s
    trims: NDArray[np.float64]  # (S, 4) offset A, offset B (mA), gain A, gain B (1/10000)
    phasors: NDArray[np.complex128]  # (S, K)
    sigma: NDArray[np.float64]  # (S, K): the noise and the model floor, what fits weigh by
    noise: NDArray[np.float64]  # (S, K): the sensor's noise alone
    time_s: NDArray[np.float64]  # (S,) mid-segment instant from the first SYNC
    # (S, 2) first and one-past-last sample of each segment (SYNC numbers from the first)
    span: NDArray[np.int64]
    # (S,) mean of e^{jθ} over the segment, θ the rotor's mechanical angle from the
    # position demand (zero where the demand is zero: the phase is arbitrary, not the shape)
    mechanical: NDArray[np.complex128]
    segments: tuple[Segment, ...]
    skipped: tuple[Skipped, ...] = ()
    # (S, E) measured harmonics of orders K+1 … K+E: not modelled, but part of the motion
    # the torque is evaluated on (zero where an order lies beyond what the sampling shows)
    beyond: NDArray[np.complex128] | None = None
    other_axes: tuple[OtherAxis, ...] = ()
    dc: NDArray[np.float64] | None = None  # (S,) mean tangential acceleration, m/s²
    # The tangential axis also reads part of the radial ripple (a turned element, found
    # on the other axes): every model then carries that part (``Model.measured``).
    axis_mixed: bool = False

    @property
    def orders(self) -> int:
        return int(self.phasors.shape[1])

    @property
    def count(self) -> int:
        return int(self.phasors.shape[0])

    @property
    def load_speed(self) -> NDArray[np.float64]:
        """Mean angular speed of the load that carries the sensor (rad/s, signed)."""
        meta = self.metadata
        out: NDArray[np.float64] = self.omega / meta.rotor_teeth * meta.gear_ratio
        return out

    def turning(self, per_revolution: int) -> Observations:
        """The same observations with the rotor's mechanical angle taken ``per_revolution``
        times over: a once-per-revolution group fitted on them is tied to angles that are
        not the rotor's (``candidates.wrong_angle_chi2``)."""
        teeth = self.metadata.rotor_teeth
        return replace(self, mechanical=np.array(
            [mechanical_phasor(s, teeth, per_revolution) for s in self.segments]))

    def with_floor(self, floor: NDArray[np.float64]) -> Observations:
        """The same observations with a model's own floor (m/s² per phasor, ``floors.floor``)
        added to the noise."""
        return replace(self, sigma=np.sqrt(self.noise**2 + floor**2))

    @property
    def model_settled(self) -> int:
        """Segments whose settling came from the chain's model (too short to judge)."""
        return sum(1 for s in self.segments if s.settling is Settling.MODEL)

    @property
    def ringing(self) -> int:
        """Segments that start while the chain's slowest modes still ring (fitted out)."""
        return sum(1 for s in self.segments if s.settling is Settling.RINGING)

    def subset(self, keep: NDArray[np.bool_]) -> Observations:
        """The segments where ``keep`` is true, conditions renumbered."""
        used = sorted(set(self.condition[keep].tolist()))
        renumber = {old: new for new, old in enumerate(used)}
        return Observations(
            metadata=self.metadata,
            conditions=tuple(self.conditions[i] for i in used),
            condition=np.array([renumber[int(c)] for c in self.condition[keep]], dtype=np.intp),
            amplitude_A=self.amplitude_A[keep],
            omega=self.omega[keep],
            trims=self.trims[keep],
            phasors=self.phasors[keep],
            sigma=self.sigma[keep],
            noise=self.noise[keep],
            time_s=self.time_s[keep],
            span=self.span[keep],
            mechanical=self.mechanical[keep],
            segments=tuple(s for s, k in zip(self.segments, keep, strict=True) if k),
            skipped=self.skipped,
            beyond=None if self.beyond is None else self.beyond[keep],
            other_axes=tuple(replace(a, phasors=a.phasors[keep], sigma=a.sigma[keep])
                             for a in self.other_axes),
            dc=None if self.dc is None else self.dc[keep],
            axis_mixed=self.axis_mixed,
        )


def mechanical_phasor(segment: Segment, rotor_teeth: int, per_revolution: int = 1) -> complex:
    """Mean of e^{jnθ} over a segment, θ the mechanical angle of the position demand and
    n ``per_revolution``: within a segment the demand is a line, so the mean of the
    phasor is its value at mid-segment times a sinc.
    """
    n = np.linspace(0.0, segment.samples, _MECHANICAL_SAMPLES)
    theta = mechanical_angle(segment.position0 + segment.microsteps_per_sample * n,
                             segment.microsteps_per_fullstep, rotor_teeth)
    return complex(np.mean(np.exp(1j * per_revolution * theta)))


def clipping_advice(metadata: RecordingMetadata) -> str:
    """What to change when holds clip: the sensor's range while a wider one exists (ICD:
    2, 4, 8 or 16 g), else the operating point. Told to widen a range already at 16 g, an
    engineer records the same clipped schedule again (benchmark trial
    current_distortion+current_loop_lag@1124444116: a light disk past 16 g in nearly
    every hold at 38 Hz)."""
    range_g = metadata.sensor_full_scale_mps2 / STANDARD_GRAVITY
    widest = max(SENSOR_RANGES_G)
    if range_g < 0.99 * widest:
        return "record with a larger range"
    return (f"the sensor is at its widest range ({widest} g): record at lower speeds or "
            "currents")


def _refuse_unless_characterization(segments: list[Segment], sync_period_s: float,
                                    conditions: int, why: str) -> None:
    speeds = {round(abs(s.electrical_hz(sync_period_s)), 1) for s in segments}
    trims = {s.trims for s in segments}
    if conditions >= MIN_CONDITIONS and len(speeds) >= 2 and len(trims) >= 2:
        return
    found = (f"{conditions} operating condition(s) (speed, direction, current), "
             f"{len(speeds)} speed(s), {len(trims)} trim set(s)")
    if why:
        found += f"; {why}"
    raise NotDiagnosable(f"this recording is not a characterization ({found}): "
                         f"{NEEDED_SCHEDULE}")


def measure_options(orders: int, settle_fallback: SettleFallback | None) -> AnalysisOptions:
    return AnalysisOptions(
        orders=max(orders, DEMODULATED_ORDERS), settle_fallback=settle_fallback,
        settle_orders=tuple(range(1, orders + 1)), white_noise=True, sample_instants=False)


Holds = tuple[tuple[int, int, Settling], ...]
"""Which samples each steady segment holds and what settled it (``settled_holds``)."""


def settled_holds(timeline: Timeline, *, orders: int = DIAGNOSIS_ORDERS,
                  settle_fallback: SettleFallback | None = None) -> Holds:
    """The steady segments ``observe`` starts from, each as the samples it holds and what
    settled it, before their ringing is measured and they are demodulated (most of an
    observation's cost): whether another pass of the diagnosis's settling would keep
    other holds."""
    options = measure_options(orders, settle_fallback)
    segments, _ = steady_segments(
        timeline, tangential_signal(timeline), settle_periods=options.settle_periods,
        settle_fallback=settle_fallback, settle_orders=options.settle_orders)
    return holds_of(segments)


def holds_of(segments: Iterable[Segment]) -> Holds:
    """``segments`` as ``settled_holds`` gives them: the samples each holds and what
    settled it."""
    return tuple((s.start, s.stop, s.settling) for s in segments)


def observe(timeline: Timeline, *, orders: int = DIAGNOSIS_ORDERS,
            settle_fallback: SettleFallback | None = None, run: Mapper = map
            ) -> Observations:
    """Segment the run and demodulate every steady segment to ``orders`` harmonics.

    Holds too short to judge their own settling are used when ``settle_fallback``
    says how long the chain takes to settle (the diagnosis knows that once it has
    fitted the chain on the longer holds). Segments where an order could not be
    fitted (too few samples per period for it) are dropped rather than carried
    with a NaN, so every row is whole; every stretch left out is in ``skipped``.
    ``run`` measures the ringing of the operating points (side by side in workers).
    """
    measured, rejected = measure(timeline, measure_options(orders, settle_fallback), run)
    conditions = group_conditions(measured, timeline.sync_period_s)
    keys: list[ConditionKey] = []
    rows: list[tuple[int, Measured]] = []
    period = timeline.sync_period_s
    skipped = [_skipped(r, period) for r in rejected]
    clipped_n = sparse_n = erratic_n = unsteady_n = 0
    advice = clipping_advice(timeline.metadata)
    signal = tangential_signal(timeline)
    erratic = _why_not_periodic(not_periodic(measured, orders, signal))
    unsteady = speed_changed(measured, signal, timeline.metadata)
    for condition in conditions:
        key = ConditionKey(condition.amplitude_mA, condition.electrical_hz)
        usable = []
        # Only the rotor's irregular motion is a matter of the operating point; a load still
        # catching up after a reversal is a matter of the hold's place in the schedule.
        erratic.update(_why_not_periodic(_erratic_point(condition.measured, erratic.keys())))
        for m in condition.measured:
            where = (m.segment.start * period, m.segment.stop * period)
            clipped = m.saturated / max(m.segment.samples, 1)
            if not np.all(np.isfinite(m.harmonics.phasors[:orders])):
                sparse_n += 1
                skipped.append(Skipped(
                    *where, f"{key.label()}: too few samples per period for order {orders}"))
            elif id(m) in unsteady:
                unsteady_n += 1
                skipped.append(Skipped(*where, f"{key.label()}: {unsteady[id(m)]}"))
            elif id(m) in erratic:
                erratic_n += 1
                skipped.append(Skipped(*where, f"{key.label()}: {erratic[id(m)]}"))
            elif clipped > MAX_CLIPPED:
                clipped_n += 1
                skipped.append(Skipped(*where, (
                    f"{key.label()}: {100 * clipped:.0f} % of the samples clipped at the "
                    f"sensor's full scale (more than {100 * MAX_CLIPPED:.0f} %): {advice}")))
            else:
                usable.append(m)
        if not usable:
            continue
        keys.append(key)
        rows.extend((len(keys) - 1, m) for m in usable)
    segs_all = [m.segment for _, m in rows]
    reasons = sorted({r.reason for r in rejected})
    if clipped_n:
        # A recording clipped at every fast speed needs another range (at the widest, another
        # operating point), not another schedule.
        reasons.append(f"{clipped_n} settled segment(s) clipped at the sensor's full scale in "
                       f"more than {100 * MAX_CLIPPED:.0f} % of their samples: {advice}")
    if erratic_n:
        reasons.append(f"{erratic_n} settled segment(s) whose motion was not periodic: "
                       "record at speeds away from the chain's resonance, at currents well above "
                       "the load's torque, or with the unit trimmed")
    if unsteady_n:
        reasons.append(f"{unsteady_n} settled segment(s) through which the load's speed "
                       "changed: hold longer after each reversal, or record at currents well "
                       "above the load's friction")
    if sparse_n:
        reasons.append(f"{sparse_n} settled segment(s) with too few samples per period for "
                       f"order {orders}: record at lower speeds")
    why = "; ".join(reasons)
    _refuse_unless_characterization(segs_all, period, len(keys), why)
    rows.sort(key=lambda row: row[1].segment.start)
    segs = [m.segment for _, m in rows]
    harmonics = [m.harmonics for _, m in rows]
    index = np.array([c for c, _ in rows], dtype=np.intp)
    phasors = np.array([h.phasors[:orders] for h in harmonics])
    noise = noise_sigma(harmonics, index, orders)
    omega = np.array([2 * math.pi * s.electrical_hz(period) for s in segs])
    teeth = timeline.metadata.rotor_teeth
    skipped.sort(key=lambda s: s.start_s)
    return Observations(
        metadata=timeline.metadata,
        conditions=tuple(keys),
        condition=index,
        amplitude_A=np.array([s.amplitude_mA * 1e-3 for s in segs]),
        omega=omega,
        trims=np.array(
            [[s.trims.offset_a_mA, s.trims.offset_b_mA, s.trims.gain_a, s.trims.gain_b]
             for s in segs]
        ),
        phasors=phasors,
        sigma=np.sqrt(noise**2 + (MODEL_FLOOR * np.abs(phasors)) ** 2),
        noise=noise,
        time_s=np.array([0.5 * (s.start + s.stop) * period for s in segs]),
        span=np.array([[s.start, s.stop] for s in segs], dtype=np.int64),
        mechanical=np.array([mechanical_phasor(s, teeth) for s in segs]),
        segments=tuple(segs),
        skipped=tuple(skipped),
        beyond=_beyond(harmonics, orders, omega, period),
        other_axes=_other_axes(timeline, segs, orders),
        dc=np.array([h.dc for h in harmonics]),
    )


def not_periodic(measured: list[Measured], orders: int, signal: NDArray[np.float64]
                  ) -> dict[int, str]:
    """The segments whose harmonics leave too much unexplained (by ``id``), each with what
    was left, in words.

    Compared with the recording's own noise, so the rule needs no sensor datasheet, and
    with the segment's ripple, so a loud ripple's small ringing tail is kept (fitting the
    chain's ringing out is the settling's business). A smaller share counts when the
    harmonics let change slowly through the hold still leave it (``NOT_PERIODIC_SLOW_SHARE``);
    a hold still ringing is judged by the first rule alone, its decays being part of its fit.
    """
    if len(measured) < 2:
        return {}
    left = np.array([m.harmonics.noise_variance for m in measured])
    noise = float(np.quantile(left, NOISE_QUANTILE))
    out: dict[int, str] = {}
    for m, variance in zip(measured, left, strict=True):
        ripple = float(np.nansum(np.abs(m.harmonics.phasors[:orders]) ** 2) / 2.0)
        share = math.sqrt(variance / max(ripple, 1e-30))
        if not variance > NOT_PERIODIC_NOISE * noise or share <= NOT_PERIODIC_SLOW_SHARE:
            continue
        what = (f"what its harmonics leave is {variance / noise:.0f} times the noise and "
                f"{share:.0%} of the ripple")
        if share > NOT_PERIODIC_SHARE:
            out[id(m)] = what
            continue
        seg = m.segment
        if seg.ringing:
            continue
        slow = slow_variance(signal[seg.start:seg.stop], seg.electrical_angle(),
                             seg.samples_per_period, orders)
        if slow > NOT_PERIODIC_NOISE * noise:
            out[id(m)] = f"{what}, {slow / noise:.0f} times with its harmonics let change slowly"
    return out


def speed_changed(measured: list[Measured], signal: NDArray[np.float64],
                  metadata: RecordingMetadata) -> dict[int, str]:
    """The segments through which the load's speed changed (by ``id``), in words.

    The change is the hold's mean acceleration times its length, against the holds at the
    same speed: the sensor's bias and any centripetal part a turned element reads (which
    grows with the speed, not with its sign) are common to them. A hold through which the
    load stood still and then caught up is no steady motion at the commanded speed, however
    quiet it is: the harmonics of a load at rest are small, not wrong, so neither the fit's
    residual nor ``not_periodic`` sees it.
    """
    period = metadata.sync_period_s
    left = np.array([m.harmonics.noise_variance for m in measured])
    if left.size < 2 or not np.any(np.isfinite(left)):
        return {}
    noise = float(np.nanquantile(left, NOISE_QUANTILE))
    speeds: dict[float, list[Measured]] = {}
    for m in measured:
        if not m.segment.ringing:  # a ringing hold's decays are its fit's, speed and all
            speeds.setdefault(round(abs(m.segment.electrical_hz(period)), 1), []).append(m)
    out: dict[int, str] = {}
    for hz, same in speeds.items():
        if len(same) < 3 or hz <= 0.0:
            continue  # no bias to measure the change against
        bias = float(np.median([m.harmonics.dc for m in same]))
        # The load's tangential speed at the sensor: mechanical speed through the gear.
        load = 2.0 * math.pi * hz / metadata.rotor_teeth * metadata.gear_ratio
        speed = load * metadata.sensor_radius_m
        for m in same:
            seg = m.segment
            used = int(np.count_nonzero(np.isfinite(signal[seg.start:seg.stop])))
            if used < 2:
                continue
            length = seg.samples * period
            change = (m.harmonics.dc - bias) * length
            sigma = math.sqrt(noise / used) * length
            if (abs(change) > SPEED_CHANGE_SHARE * speed
                    and abs(change) > SPEED_CHANGE_SIGMAS * sigma):
                out[id(m)] = (f"the load's speed changed by {abs(change) / speed:.0%} of its "
                              f"own through the hold ({abs(change) / sigma:.0f} times what the "
                              "noise gives): it stood still or caught up")
    # A load that changed speed in a hold was not at its speed in the holds before it at the
    # same operating point either (friction@416744003: a 6.5 Hz load stood still through
    # the whole first hold after a reversal, quiet and so unchanged, and caught up in the
    # second). The run is assumed to end at the commanded speed.
    later: str | None = None
    run: tuple[int, float] | None = None
    for m in sorted(measured, key=lambda m: -m.segment.start):
        key = (m.segment.amplitude_mA, round(m.segment.electrical_hz(period), 1))
        if key != run:
            run, later = key, None
        if id(m) in out:
            later = later or ("the load's speed changed in a later hold at this operating "
                              "point: it had not reached its speed yet")
        elif later is not None:
            out[id(m)] = later
    return out


def _why_not_periodic(what: dict[int, str]) -> dict[int, str]:
    """``not_periodic``'s findings as the reasons a skipped segment is given."""
    return {key: (f"the motion was not periodic ({text}): the chain's own mode swung beside "
                  "the harmonics, as near a resonance, or the rotor nearly lost step")
            for key, text in what.items()}


def _erratic_point(measured: tuple[Measured, ...], erratic: Set[int]) -> dict[int, str]:
    """The other holds of an operating point at least half of whose holds were not periodic.

    Whether a rotor nearly loses step is a matter of its current and speed; trim steps of
    25 mA do not change it. A hold whose irregular part happens to fall a little below
    the threshold is no periodic motion either: on benchmark trial friction@2082563418
    one 350 mA hold of sixteen was kept at 34 times the noise, its neighbours at 39 to
    10,800, and it alone left the nominal fit at χ² 241,547 for 562 values."""
    bad = sum(id(m) in erratic for m in measured)
    if not bad or 2 * bad < len(measured):
        return {}
    why = (f"{bad} of the {len(measured)} holds at this operating point left more than "
           f"{NOT_PERIODIC_NOISE:.0f} times the noise unexplained")
    return {id(m): why for m in measured if id(m) not in erratic}


def _other_axes(timeline: Timeline, segments: list[Segment], orders: int
                ) -> tuple[OtherAxis, ...]:
    """The two non-tangential axes' harmonics over the same segments and samples.

    Each window is first rid of a slow quadratic: on a fixture whose shaft is not
    vertical an axis reads gravity turning once per revolution, a drift that would
    otherwise leak into every order.
    """
    meta = timeline.metadata
    ok = timeline.sensor_valid & ~timeline.saturated
    out = []
    for axis in Axis:
        if axis is meta.tangential_axis:
            continue
        signal = timeline.accel_counts[:, axis.column] * meta.sensor_lsb_mps2
        phasors = np.zeros((len(segments), orders), dtype=np.complex128)
        sigma = np.full((len(segments), orders), np.inf)
        for i, seg in enumerate(segments):
            window = signal[seg.start:seg.stop].astype(np.float64)
            present = ok[seg.start:seg.stop]
            t = np.linspace(-1.0, 1.0, window.size)
            trend = np.polynomial.polynomial.polyfit(t[present], window[present], 2)
            window = window - np.polynomial.polynomial.polyval(t, trend)
            window[~present] = np.nan
            h = seg.harmonics(window, orders)
            found = np.isfinite(h.phasors)
            phasors[i, found] = h.phasors[found]
            sigma[i, found] = np.sqrt(h.variance[found])
        out.append(OtherAxis(axis, phasors, sigma))
    return tuple(out)


def _beyond(harmonics: list[Harmonics], orders: int, omega: NDArray[np.float64],
            period: float) -> NDArray[np.complex128]:
    """The orders above those modelled, where the sampling resolves them.

    A strong ripple swings the rotor at its own higher orders too, and the torque of
    the modelled orders is evaluated on that swing: leaving those orders out of the
    motion mixes an error of a few per cent into the strongest cells.
    """
    out = np.array([h.phasors[orders:DEMODULATED_ORDERS] for h in harmonics],
                   dtype=np.complex128).reshape(len(harmonics), -1)
    k = np.arange(orders + 1, orders + 1 + out.shape[1])
    resolved = np.abs(omega)[:, None] * k[None, :] / (2 * math.pi) < BEYOND_NYQUIST / period
    return np.where(resolved & np.isfinite(out), out, 0.0)


def noise_sigma(harmonics: list[Harmonics], condition: NDArray[np.intp], orders: int
                ) -> NDArray[np.float64]:
    """Each phasor's standard uncertainty from the sensor's noise, pooled per condition,
    through the segment's own design.

    The sensor's noise is a property of the sensor, the same in every segment of an
    operating point; pooling it (a median, so one unsettled segment does not inflate
    the others) gives an estimate with thousands of degrees of freedom, where a
    segment's own is noisy and a per-period scatter noisier still: χ² against either
    would be biased and would hide what the model misses.
    """
    noise = np.array([h.noise_variance for h in harmonics])
    pooled = np.zeros(noise.size)
    for c in np.unique(condition):
        rows = condition == c
        pooled[rows] = float(np.median(noise[rows]))
    unit = np.array([np.asarray(h.unit_variance)[:orders] for h in harmonics])
    out: NDArray[np.float64] = np.sqrt(pooled[:, None] * unit)
    return out


def _skipped(rejected: Rejected, period: float) -> Skipped:
    return Skipped(rejected.start * period, rejected.stop * period, rejected.reason)


BEND_GRID = 128
"""Points per electrical period where the bend's products are formed: the cube of order
16 reaches order 48, which a grid of 128 resolves without folding."""


def radial_ripple(obs: Observations) -> NDArray[np.complex128]:
    """The centripetal ripple 2Ω·w at the sensor, orders 1..K then beyond, from the
    measured tangential ripple itself (w = a/(jkω), to first order)."""
    phasors = obs.phasors if obs.beyond is None else np.hstack([obs.phasors, obs.beyond])
    k = np.arange(1, phasors.shape[1] + 1, dtype=np.float64)
    out: NDArray[np.complex128] = (2.0 * obs.load_speed[:, None] * phasors
                                   / (1j * obs.omega[:, None] * k[None, :]))
    return out


def bend_bases(obs: Observations) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Harmonics of m²/FS and m³/FS² per segment, m the measured tangential waveform
    (its mean and every demodulated order), orders 1..K then the orders beyond.

    A sensor reading m = a + c2·a²/FS + c3·a³/FS² is undone to first order in c by
    a = m − c2·m²/FS − c3·m³/FS²: the products of the measurement itself, fixed by the
    data, so the bend enters the model linearly.
    """
    phasors = obs.phasors if obs.beyond is None else np.hstack([obs.phasors, obs.beyond])
    k = np.arange(1, phasors.shape[1] + 1, dtype=np.float64)
    x = 2.0 * np.pi * np.arange(BEND_GRID) / BEND_GRID
    synth = np.exp(1j * np.outer(k, x))
    dc = np.zeros(obs.count) if obs.dc is None else obs.dc
    wave = dc[:, None] + (phasors @ synth).real
    full_scale = obs.metadata.sensor_full_scale_mps2
    analyse = 2.0 / BEND_GRID * np.exp(-1j * np.outer(x, k))
    square = (wave**2 / full_scale) @ analyse
    cube = (wave**3 / full_scale**2) @ analyse
    return np.asarray(square, dtype=np.complex128), np.asarray(cube, dtype=np.complex128)
