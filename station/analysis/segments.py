"""Steady segments: stretches where the drive held one trim set, amplitude and speed.

Everything here is judged from what the drive itself reported (TPDO2 trims in
effect, TPDO1 amplitude and position demand), never from a schedule, so a
recording from any bench segments the same way. A segment keeps only samples
that are (1) at constant commanded velocity, with a margin of one detection
window around every ramp, (2) past the rotor's settling after the last change,
judged from the data, and (3) a whole number of electrical periods, ending at
the end of the hold where the rotor has settled longest.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from station.analysis.harmonics import Harmonics, demodulate, period_phasors
from station.analysis.timeline import Timeline
from station.core import Trims

RAMP_WINDOW = 32
"""Samples each side over which a change of velocity is looked for.

Integer position demand on a constant-velocity line satisfies
|p[n+W] − 2p[n] + p[n−W]| ≤ 1; any acceleration a (microsteps/sample²) adds
a·W², so W = 32 catches ramps down to 0.002 microsteps/sample² (2000
microsteps/s² at 1 kHz), far gentler than any drive's profile.
"""

_CURVATURE_TOLERANCE = 2
"""Microsteps: the rounding of two integer position differences, plus one for jitter."""

_LINE_TOLERANCE = 2.5
"""Microsteps a steady position demand may stray from its fitted line."""

MIN_PERIODS = 3
"""A segment shorter than this many electrical periods carries no usable phasor."""

_SETTLE_BLOCK = 3
"""Periods averaged when deciding that the rotor has settled."""

SETTLE_ORDERS = (1, 2)
"""Orders whose per-period phasors decide settling unless the caller names others."""

_SETTLE_SIGMAS = 3.0
_OUTLIER_SIGMAS = 5.0
"""A single period this many robust spreads from the end level is still in its transient."""


_OPERATION_ENABLED_MASK = 0x006F
_OPERATION_ENABLED = 0x0027


class Settling(StrEnum):
    """How a segment's start was chosen: judged on its own data, or given from outside."""

    DATA = "data"  # per-period phasors reached their final level (needs 6 periods)
    GIVEN = "given"  # a settling time given by the caller (``settle_periods``)
    MODEL = "model"  # too short to judge: a time from a model of the chain's decay
    RINGING = "ringing"  # the chain's slowest modes still ring: fitted out as decays


@dataclass(frozen=True)
class ChainDecay:
    """How a model of the chain forgets a change: its modes' poles, and how many of their
    e-foldings make a transient negligible.

    A hold shorter than its slowest mode's decay still carries the harmonics: the
    transient is a sum of decaying exponentials at the chain's poles, so a segment can
    start before they have died out if those poles are fitted beside the harmonics
    (a free amplitude and phase each). The harmonics then cost the precision they share
    with the decays, and their variance says so.
    """

    poles: tuple[complex, ...]
    """Poles λ (1/s) of the modes the recording resolves, one of each conjugate pair."""
    e_foldings: float
    floor_s: float
    """Seconds every change needs whatever the modes (the faster physics around them)."""
    resolution_mps2: float = 0.0
    """The smallest transient worth waiting out (m/s² at the sensor, the noise of a
    segment's harmonics); 0: ``e_foldings`` whatever the change."""

    def seconds(self, pole: complex) -> float:
        """Seconds until ``pole``'s mode has decayed by ``e_foldings``."""
        return self.e_foldings / -pole.real

    def kicked(self, kick_mps2: float, since_s: float = 0.0) -> ChainDecay:
        """The decay of a change whose modes still ring at ``kick_mps2`` ``since_s`` after
        it (at the change itself by default).

        A fixed number of e-foldings leaves a fixed share of the transient: on a rough
        disk a trim step rings the mode at some 3 m/s², and its 1/300 is still ten times
        the noise of the harmonics (development disk none@208: the first hold alone left
        40 % of the recording's χ²). So the decay is waited out down to the harmonics'
        resolution, and never less than ``e_foldings``. A ring seen later is referred back
        to the change at the slowest mode's rate, counted in e-foldings: a well damped mode
        seen long after its change would be e^{rate·t} beyond any float (a benchmark belt
        overflowed there).
        """
        if self.resolution_mps2 <= 0.0 or kick_mps2 <= 0.0:
            return self
        folds = (math.log(kick_mps2 / self.resolution_mps2)
                 + self.slowest_decay_per_s() * since_s)
        if folds <= self.e_foldings:
            return self
        return replace(self, e_foldings=folds)

    def slowest_decay_per_s(self) -> float:
        """The decay rate of the slowest mode (1/s; 0 with none)."""
        return min((-p.real for p in self.poles), default=0.0)

    def settle_s(self) -> float:
        """Seconds until every mode has decayed."""
        return max([self.floor_s, *(self.seconds(p) for p in self.poles)])

    def plan(self, available_s: float, needed_s: float) -> tuple[float, tuple[complex, ...]]:
        """Seconds to wait after the change, and the poles to fit out as still ringing.

        Waiting for every mode is preferred; when that would leave less than
        ``needed_s`` of the ``available_s``, the slowest modes are fitted out, as few as
        leave enough (all of them at the worst, after ``floor_s``).
        """
        slowest_first = sorted(self.poles, key=self.seconds, reverse=True)
        for n in range(len(slowest_first) + 1):
            wait = max([self.floor_s, *(self.seconds(p) for p in slowest_first[n:])])
            if available_s - wait >= needed_s or n == len(slowest_first):
                return wait, tuple(slowest_first[:n])
        raise AssertionError("unreachable: the last plan fits every pole")


SIDEBANDS = (1, -1, 2, -2)
"""Orders of the electrical frequency beside each ringing pole that are fitted out with it.
The rotor's spring is not constant along a period: offsets make it swing at the electrical
frequency, an imbalance at twice it, so a transient rings at the mode and at the mode
shifted by those orders (a time-periodic system's modes). Fitted at the mode alone, a
development disk's ringing near order 4 left χ² of 50-220 at orders 3 and 5."""

SettleFallback = Callable[[int, float], ChainDecay | None]
"""For a hold too short to judge its own settling, or one whose data never settle:
(amplitude mA, signed electrical Hz) to how the chain decays, or None when it cannot
(a mode that does not decay)."""


def _electrical_angle(position0: float, slope: float, samples: int, microsteps_per_fullstep: int
                      ) -> NDArray[np.float64]:
    """ICD.md §2: x_u = 2π·(position mod 4m)/(4m) along a fitted line of the demand."""
    cycle = 4 * microsteps_per_fullstep
    position = position0 + slope * np.arange(samples, dtype=np.float64)
    out: NDArray[np.float64] = (2 * math.pi / cycle) * np.mod(position, cycle)
    return out


def mechanical_angle(position: NDArray[np.float64], microsteps_per_fullstep: int,
                     rotor_teeth: int) -> NDArray[np.float64]:
    """The rotor's angle at a position demand: one revolution is 4·m·Nr microsteps (a full
    electrical cycle is four full steps, and a hybrid rotor turns once per Nr cycles)."""
    revolution = 4 * microsteps_per_fullstep * rotor_teeth
    out: NDArray[np.float64] = (2 * math.pi / revolution) * position
    return out


@dataclass(frozen=True)
class Segment:
    """Samples [start, stop) of one steady condition, a whole number of periods long.

    ``position_at(n)`` is the line fitted through the position demand, so the
    electrical angle is defined at lost drive samples too. ``held_from`` is the
    first sample of the hold and ``steady_from`` the first at constant
    velocity, so the settling time dropped can be reported.
    """

    start: int
    stop: int
    held_from: int
    steady_from: int
    trims: Trims
    amplitude_mA: int
    position0: float  # fitted position demand at sample ``start`` (microsteps)
    microsteps_per_sample: float  # fitted slope
    periods: int
    microsteps_per_fullstep: int
    settling: Settling = Settling.DATA
    ringing: tuple[complex, ...] = ()
    """Poles still ringing at ``start``, per sample (λ·T): decays from ``held_from`` to fit
    out beside the harmonics."""
    drift: float = 0.0
    """How fast the ringing's frequencies move over the hold, as a share of each per
    sample (measured: ``station.analysis.ringing``)."""

    @property
    def samples(self) -> int:
        return self.stop - self.start

    def velocity(self, sync_period_s: float) -> float:
        """Microsteps/s."""
        return self.microsteps_per_sample / sync_period_s

    def electrical_hz(self, sync_period_s: float) -> float:
        """Signed: negative when the electrical angle decreases."""
        return self.microsteps_per_sample / (4 * self.microsteps_per_fullstep) / sync_period_s

    @property
    def samples_per_period(self) -> float:
        """Samples per electrical period: one period is 4·m microsteps (ICD.md §2)."""
        return 4 * self.microsteps_per_fullstep / abs(self.microsteps_per_sample)

    @property
    def angle_per_sample(self) -> float:
        """dθ/dn in radians, signed with the direction of rotation."""
        return 2 * math.pi * self.microsteps_per_sample / (4 * self.microsteps_per_fullstep)

    def part(self, first_period: int, periods: int) -> Segment:
        """Whole periods ``first_period`` … of this segment, on the same fitted line and
        the same ringing (its decays still run from the hold's change)."""
        spp = self.samples_per_period
        start = self.start + round(first_period * spp)
        return replace(self, start=start, stop=start + round(periods * spp), periods=periods,
                       position0=self.position0 + self.microsteps_per_sample * (start - self.start))

    def halves(self, window: NDArray[np.float64], orders: int, *, white_noise: bool = False,
               delays: NDArray[np.float64] | None = None, taper: bool = False
               ) -> tuple[Harmonics, Harmonics] | None:
        """``harmonics`` of the segment's first and second half (``window`` its samples,
        ``delays`` theirs): whether it was still settling (``halves_shift``). None for a
        segment shorter than two periods or a half too lossy to demodulate."""
        if self.periods < 2:
            return None
        first = self.periods // 2
        out = []
        for part in (self.part(0, first), self.part(first, self.periods - first)):
            lo, hi = part.start - self.start, part.stop - self.start
            try:
                out.append(part.harmonics(window[lo:hi], orders, white_noise=white_noise,
                                          delays=None if delays is None else delays[lo:hi],
                                          taper=taper))
            except ValueError:
                return None
        return out[0], out[1]

    def electrical_angle(self) -> NDArray[np.float64]:
        return _electrical_angle(self.position0, self.microsteps_per_sample, self.samples,
                                 self.microsteps_per_fullstep)

    def harmonics(self, window: NDArray[np.float64], orders: int, *,
                  white_noise: bool = False,
                  delays: NDArray[np.float64] | None = None, taper: bool = False) -> Harmonics:
        """``demodulate`` of the segment's samples ``window`` on its own angle, with the
        chain's ringing fitted out from the hold's change where it still rings; each
        sample at its own instant where ``delays`` (in samples) says the sensor's clock
        put it (``station.analysis.sampling``)."""
        poles, sweeps = self.decays(self.ringing, self.drift)
        angle = self.electrical_angle()
        if delays is not None:
            angle = angle + self.angle_per_sample * delays
        return demodulate(window, angle, self.samples_per_period,
                          orders=orders, decays=poles,
                          decay_from=self.start - self.held_from, white_noise=white_noise,
                          uncertain=self.ringing, sweeps=sweeps, taper=taper)

    def decays(self, ringing: tuple[complex, ...], drift: float = 0.0
               ) -> tuple[tuple[complex, ...], tuple[float, ...]]:
        """The poles fitted out for ``ringing`` (per sample): each, and each shifted by the
        ``SIDEBANDS`` orders of this segment's electrical frequency; and, when each mode's
        frequency moves by ``drift`` of itself per sample, how fast each pole's moves
        (rad/sample², empty when none does). A sideband rides on its mode and moves with it,
        so both lists are built together and stay in step."""
        turn = 2j * math.pi / self.samples_per_period
        pairs = [(p, drift * p.imag) for p in ringing] + [
            (p + k * turn, drift * p.imag) for p in ringing for k in SIDEBANDS]
        return (tuple(p for p, _ in pairs),
                tuple(c for _, c in pairs) if drift else ())


@dataclass(frozen=True)
class Hold:
    """A maximal run of samples with one reported trim set, amplitude and enable state."""

    start: int
    stop: int
    trims: tuple[int, int, int, int]
    amplitude_mA: int
    enabled: bool


def _forward_fill(values: NDArray[np.int64], valid: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Carry the last reported value over lost frames (the first one backwards)."""
    if not valid.any():
        raise ValueError("no valid rows to fill from")
    index = np.where(valid, np.arange(valid.size), 0)
    np.maximum.accumulate(index, out=index)
    first = int(np.argmax(valid))
    index[:first] = first
    return values[index]


def holds(timeline: Timeline) -> list[Hold]:
    """Split the run wherever the reported trims, amplitude or enable state change.

    A lost TPDO2 or TPDO1 repeats the last reported value: the boundary may
    then sit one sample late, which the settling margin absorbs.
    """
    trims = _forward_fill(timeline.trims.astype(np.int64), timeline.trims_valid)
    amplitude = _forward_fill(timeline.amplitude_mA.astype(np.int64), timeline.drive_valid)
    status = _forward_fill(timeline.statusword.astype(np.int64), timeline.drive_valid)
    enabled = (status & _OPERATION_ENABLED_MASK) == _OPERATION_ENABLED
    key = np.column_stack([trims, amplitude, enabled.astype(np.int64)])
    change = np.flatnonzero(np.any(key[1:] != key[:-1], axis=1)) + 1
    bounds = [0, *change.tolist(), timeline.samples]
    out: list[Hold] = []
    for a, b in itertools.pairwise(bounds):
        t = trims[a]
        out.append(
            Hold(
                start=a,
                stop=b,
                trims=(int(t[0]), int(t[1]), int(t[2]), int(t[3])),
                amplitude_mA=int(amplitude[a]),
                enabled=bool(enabled[a]),
            )
        )
    return out


_GLITCH_MICROSTEPS = 3.0
"""A reported position this far off the line through its neighbours is misplaced."""


def position_glitches(position: NDArray[np.int64], valid: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Valid-looking position samples that cannot be where the timeline put them.

    When a SYNC and the drive frame before it are both lost, a reader may place
    the next frame one sample early: it then sits a whole sample's travel off
    the line through its neighbours. Steady motion and any real ramp stay
    within a microstep or two of that line, so the sample whose deviation is
    large and larger than both neighbours' is the culprit.
    """
    idx = np.flatnonzero(valid)
    out = np.zeros(valid.shape, dtype=bool)
    if idx.size < 3:
        return out
    p = position[idx].astype(np.float64)
    n = idx.astype(np.float64)
    frac = (n[1:-1] - n[:-2]) / (n[2:] - n[:-2])
    err = np.zeros(idx.size)
    err[1:-1] = np.abs(p[1:-1] - (p[:-2] + (p[2:] - p[:-2]) * frac))
    peak = np.zeros(idx.size, dtype=bool)
    peak[1:-1] = (err[1:-1] > _GLITCH_MICROSTEPS) & (err[1:-1] >= err[:-2]) & (
        err[1:-1] >= err[2:]
    )
    out[idx[peak]] = True
    return out


def constant_velocity_runs(
    position: NDArray[np.int64], valid: NDArray[np.bool_], start: int, stop: int
) -> list[tuple[int, int]]:
    """Maximal runs of samples in [start, stop) whose position demand is on one line.

    Lost samples are bridged by interpolation for this test only; the line
    itself is fitted later through the real samples.
    """
    n = np.arange(start, stop)
    ok = valid[start:stop]
    if ok.sum() < 2 * RAMP_WINDOW + 1:
        return []
    p = np.interp(n, n[ok], position[start:stop][ok].astype(np.float64))
    w = RAMP_WINDOW
    curvature = np.abs(p[2 * w :] - 2 * p[w:-w] + p[: -2 * w])
    # Centre i is steady when its whole window [i−w, i+w] lies on one line. A run of
    # such centres is widened by w only where it meets the hold's own edge (a trim or
    # amplitude change, not a ramp); on a ramp's side the window is the margin. Runs
    # shorter than a window are the test flickering at a ramp's end, not motion.
    steady = np.zeros(n.size, dtype=np.int8)
    steady[w:-w] = curvature <= _CURVATURE_TOLERANCE
    edges = np.flatnonzero(np.diff(np.concatenate([[0], steady, [0]])))
    runs: list[tuple[int, int]] = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a < w:
            continue
        lo = 0 if a == w else int(a)
        hi = n.size if b == n.size - w else int(b)
        runs.append((start + lo, start + hi))
    return runs


def _fit_line(
    position: NDArray[np.int64], valid: NDArray[np.bool_], start: int, stop: int
) -> tuple[float, float] | None:
    """(position at ``start``, slope) through the valid samples, or None if not a line."""
    n = np.flatnonzero(valid[start:stop])
    if n.size < 2:
        return None
    p = position[start:stop][n].astype(np.float64)
    ref = p[0]
    slope, intercept = np.polyfit(n.astype(np.float64), p - ref, 1)
    if np.max(np.abs(p - ref - (intercept + slope * n))) > _LINE_TOLERANCE:
        return None
    return float(ref + intercept), float(slope)


def _complex_median(z: NDArray[np.complex128], axis: int = 0) -> NDArray[np.complex128]:
    out: NDArray[np.complex128] = np.median(z.real, axis=axis) + 1j * np.median(z.imag,
                                                                                axis=axis)
    return out


def _period_spread(per_period: NDArray[np.complex128]) -> NDArray[np.float64]:
    """Each order's robust spread of one period's phasor, from period-to-period differences,
    which a slow trend barely touches: 1.4826·median|z[k+1] − z[k]|/√2 is about 1.74 σ for
    circular Gaussian scatter."""
    steps = np.abs(np.diff(per_period, axis=0))
    out: NDArray[np.float64] = 1.4826 * np.median(steps, axis=0) / math.sqrt(2.0) + 1e-12
    return out


def settled_period(per_period: NDArray[np.complex128]) -> int | None:
    """Index of the first period from which the phasors stay at their final level.

    The reference is the last half of the hold, assumed settled; a block of
    periods has settled when its median is within a few robust spreads of the
    reference for every order. Medians, because a period that lost samples
    or clipped gives a wild crude phasor that must not decide anything. None
    when even the reference is not steady (the hold is too short for the
    rotor to settle).
    """
    periods = per_period.shape[0]
    if periods < 2 * _SETTLE_BLOCK:
        return None
    tail = per_period[periods // 2 :]
    reference = _complex_median(tail)
    spread = _period_spread(per_period)
    quarter = tail.shape[0] // 2
    if quarter >= _SETTLE_BLOCK:
        drift = np.abs(_complex_median(tail[:quarter]) - _complex_median(tail[quarter:]))
        if np.any(drift > _SETTLE_SIGMAS * spread * math.sqrt(2.0 / quarter)):
            return None
    for j in range(periods - _SETTLE_BLOCK + 1):
        block = _complex_median(per_period[j : j + _SETTLE_BLOCK])
        if np.all(np.abs(block - reference) <= _SETTLE_SIGMAS * spread / 2):
            # The median outvotes a transient in the block's first period as it outvotes a
            # period that lost samples; the first period kept must itself be near the end
            # level (loosely: a lossy period then costs one period, not a biased phasor).
            first = j
            while first < periods - _SETTLE_BLOCK and np.any(
                np.abs(per_period[first] - reference) > _OUTLIER_SIGMAS * spread
            ):
                first += 1
            return first
    return None


_TURNING_SIGMAS = 2.0
"""Robust spreads of one period's phasor that what the common turn leaves of a hold may
reach (its RMS; scatter alone leaves about 0.8) for the hold to count as turning with
the rotor."""

_TURN_SHARE = 0.75
"""Share of what the holds' own levels leave that the common turn must explain, at one
order at least, to be a turn at all."""


def _local(z: NDArray[np.complex128]) -> NDArray[np.bool_]:
    """Periods within ``_OUTLIER_SIGMAS`` of the median of the five around them, ``z`` in
    units of its spread: the median follows a steady trend, not a single wild period."""
    near = np.array([_complex_median(z[max(0, j - 2):j + 3]) for j in range(z.size)])
    out: NDArray[np.bool_] = np.abs(z - near) <= _OUTLIER_SIGMAS
    return out


def turning_with_rotor(holds: Sequence[tuple[NDArray[np.complex128], NDArray[np.float64]]]
                       ) -> list[bool]:
    """For the holds of one operating point, each given as its per-period phasors after the
    chain has forgotten the hold's change and each period's mechanical angle (rad):
    whether that hold's phasors are its own level times one change once per mechanical
    revolution that all the holds share, within the scatter of one period.

    An eccentric rotor's spring, or a load heavier on one side, moves the operating point
    with the rotor's angle; near a mode this turns the ripple's phasors by far more than
    their scatter over a hold, so the hold never looks settled although nothing rings (a
    development disk, rotor_eccentricity@520972, lost 24 of its 56 holds, and with them
    what named it). Such a hold is steady in the sense that matters: its mean is the
    response at its mean mechanical angle, which the model computes. The change is the
    chain's response at that angle, so it scales with each hold's level and repeats
    from hold to hold as the rotor turns on; a slow transient restarts at every change,
    towards each hold's own level, and fits no common turn (one hold alone could not
    tell the two apart over part of a revolution), so most holds must share the turn.
    Periods a few spreads off the fit (lost samples) are set aside, but never most of a
    hold's.
    """
    usable = [i for i, (z, _) in enumerate(holds) if z.shape[0] >= 3 * _SETTLE_BLOCK]
    verdict = [False] * len(holds)
    if len(usable) < 2:
        return verdict
    orders = min(holds[i][0].shape[1] for i in usable)
    ok = dict.fromkeys(usable, True)
    turned = False
    for k in range(orders):
        blocks, sizes, values, owner = [], [], [], []
        for m, i in enumerate(usable):
            z, angle = holds[i][0][:, k], holds[i][1]
            spread = float(_period_spread(z[:, None])[0])
            level = complex(_complex_median(z))
            blocks.append(np.column_stack([
                np.eye(len(usable))[np.full(z.size, m)],
                level * np.exp(1j * angle), level * np.exp(-1j * angle)]) / spread)
            values.append(z / spread)
            owner.append(np.full(z.size, m))
            sizes.append(z.size)
        design, target = np.vstack(blocks), np.concatenate(values)
        who = np.concatenate(owner)
        # A lost period is a spike against its neighbours, which a smooth turn is not.
        kept = np.concatenate([_local(z) for z in values])
        for _ in range(4):
            coef = np.linalg.lstsq(design[kept], target[kept], rcond=None)[0]
            residual = np.abs(target - design @ coef)  # in spreads
            within = residual <= _OUTLIER_SIGMAS
            if np.array_equal(within, kept) or any(
                    2 * int(within[who == m].sum()) < n for m, n in enumerate(sizes)):
                break
            kept = within
        for m, i in enumerate(usable):
            mine = (who == m) & kept
            rms = math.sqrt(float(np.mean(residual[mine] ** 2))) if mine.any() else math.inf
            ok[i] = ok[i] and 2 * int(mine.sum()) >= sizes[m] and rms <= _TURNING_SIGMAS
        # The levels alone, over the same periods: what the turn must explain.
        levels = design[kept][:, :len(usable)]
        alone = target[kept] - levels @ np.linalg.lstsq(levels, target[kept], rcond=None)[0]
        turned = turned or (float(np.sum(residual[kept] ** 2))
                            <= (1.0 - _TURN_SHARE) * float(np.sum(np.abs(alone) ** 2)))
    # A turn most holds do not share is no common turn: a hold that fits it alone does
    # so by chance. Nor is one that leaves the levels as they were: holds at the level of
    # their scatter fit any turn, and there the data's own verdict stands.
    if turned and 2 * sum(ok.values()) > len(usable):
        for i in usable:
            verdict[i] = ok[i]
    return verdict


CLOCK_SIGMAS = 5.0
"""Standard errors a recording's common phase turn must exceed to be taken as a clock."""
_CLOCK_STRONG = 10.0
"""Robust spreads of one period's phasor an order must stand above to time a turn: a
weaker order's angle is mostly noise."""
_CLOCK_BLOCKS = 32
"""Blocks of periods a tail is reduced to before its slope is taken (pairs grow as n²)."""


def _tail_turn(per_period: NDArray[np.complex128], orders: tuple[int, ...]
               ) -> tuple[float, float]:
    """The steady turn of the last half of a run's per-period phasors, as a relative rate
    (order k turns by 2πk times it per period), and its standard error; σ infinite when no
    order is strong enough or the tail too short.

    Each order's slope is Theil and Sen's, the median over pairs of periods: a period that
    lost samples gives a wild phasor, and on a plain least-squares line those made the
    holds of a 303 ppm clock disagree from −900 to +2,000 ppm (this way, 244 to 357).
    """
    tail = per_period[per_period.shape[0] // 2:]
    if tail.shape[0] < 2 * _SETTLE_BLOCK:
        return 0.0, math.inf
    reference = _complex_median(tail)
    spread = _period_spread(per_period)
    width = max(1, tail.shape[0] // _CLOCK_BLOCKS)
    blocks = tail.shape[0] // width
    periods = (np.arange(blocks) + 0.5) * width
    centred = periods - periods.mean()
    first, second = np.triu_indices(blocks, 1)
    estimate = information = 0.0
    for j, k in enumerate(orders):
        if abs(reference[j]) < _CLOCK_STRONG * spread[j]:
            continue
        z = _complex_median(tail[:blocks * width, j].reshape(blocks, width), axis=1)
        angle = np.angle(z / reference[j])
        slope = float(np.median((angle[second] - angle[first])
                                / (periods[second] - periods[first])))
        # One period's angle scatters by spread/|z|; a block's by that over √width.
        sigma = (spread[j] / abs(reference[j]) / math.sqrt(width)
                 / math.sqrt(float(centred @ centred)))
        scale = 2.0 * math.pi * k
        estimate += (slope / scale) * (scale / sigma) ** 2
        information += (scale / sigma) ** 2
    if information == 0.0:
        return 0.0, math.inf
    return estimate / information, 1.0 / math.sqrt(information)


def clock_rate(turns: list[tuple[float, float]]) -> float:
    """How much faster than SYNC the samples' own time runs (relative), from the steady
    turns of every run (each times its direction of rotation); 0 unless the runs
    agree on one beyond ``CLOCK_SIGMAS``.

    A sensor stamping its samples by its own clock, off by δ, samples ever later (or
    earlier) within each hold, and every order's phasor turns by 2πkδ per period whatever
    the speed: as a rotor still settling does, which is why it must be told apart. A
    transient turns one hold its own way; a clock turns them all alike. So the runs are
    pooled about their weighted median, each kept within four of its σ of the pool, and
    the clock is taken only when at least three runs and half of those that could time a
    turn agree on it (a clean unit's 31 runs: −216 ± 116 ppm; clocks of 303, 384 and
    −346 ppm: 308 ± 9, 362 ± 27, −337 ± 36).
    """
    timed = [(d, s) for d, s in turns if math.isfinite(s)]
    if len(timed) < 3:
        return 0.0
    rates = np.array([d for d, _ in timed])
    sigmas = np.array([s for _, s in timed])
    weights = sigmas ** -2.0
    order = np.argsort(rates)
    cumulative = np.cumsum(weights[order])
    pooled = float(rates[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    kept = np.abs(rates - pooled) <= 4.0 * sigmas
    for _ in range(3):
        if not kept.any():
            return 0.0
        pooled = float(np.sum(weights[kept] * rates[kept]) / np.sum(weights[kept]))
        kept = np.abs(rates - pooled) <= 4.0 * sigmas
    count = int(np.count_nonzero(kept))
    if count < max(3, len(timed) / 2):
        return 0.0
    sigma = 1.0 / math.sqrt(float(np.sum(weights[kept])))
    return pooled if abs(pooled) > CLOCK_SIGMAS * sigma else 0.0


def without_clock(per_period: NDArray[np.complex128], orders: tuple[int, ...],
                  turn: float) -> NDArray[np.complex128]:
    """``per_period`` with a steady turn of ``turn`` per period (relative, ``clock_rate``
    signed to the run's direction) taken out of each order."""
    if turn == 0.0:
        return per_period
    periods = np.arange(per_period.shape[0], dtype=np.float64)[:, None]
    k = np.asarray(orders, dtype=np.float64)[None, :]
    out: NDArray[np.complex128] = per_period * np.exp(-2j * math.pi * turn * k * periods)
    return out


def _rung_by_change(per_period: NDArray[np.complex128], since_change_s: float,
                    period_s: float, decay: ChainDecay) -> ChainDecay:
    """``decay`` kicked as hard as the hold's change rang the chain, seen in the stretch's
    own first period against its last; as it is where nothing rings clearly.

    The first period's phasors less the last ones are the transient there (the last
    carries the least of it); their largest is seen at the middle of the first period.
    Below ``KICK_VISIBLE`` times the harmonics' resolution it may be the noise of one
    period's phasors, and says nothing.
    """
    if per_period.shape[0] < 2 or per_period.shape[1] == 0 or decay.slowest_decay_per_s() <= 0:
        return decay
    seen = float(np.max(np.abs(per_period[0] - per_period[-1])))
    if seen <= KICK_VISIBLE * decay.resolution_mps2:
        return decay
    return decay.kicked(seen, since_change_s + 0.5 * period_s)


KICK_VISIBLE = 10.0
"""A first period's departure from the last, in units of the harmonics' resolution,
that is taken as ringing rather than the scatter of single periods."""


@dataclass(frozen=True)
class Rejected:
    """A steady stretch that could not be used, and why (for the report)."""

    start: int
    stop: int
    reason: str


@dataclass(frozen=True)
class _Run:
    """Samples [start, stop) of one hold at constant velocity, its demand's line fitted."""

    hold: Hold
    start: int
    stop: int
    position0: float
    slope: float  # microsteps per sample, signed
    hz: float  # electrical, unsigned
    samples_per_period: float
    microsteps_per_fullstep: int
    rotor_teeth: int

    @property
    def direction(self) -> float:
        """+1 where the electrical angle grows, -1 where it falls."""
        return 1.0 if self.slope > 0 else -1.0

    def orders(self, wanted: tuple[int, ...]) -> tuple[int, ...]:
        """Those of ``wanted`` the run's sampling resolves."""
        return tuple(k for k in wanted if 2 * k < self.samples_per_period)

    def phasors(self, signal: NDArray[np.float64], ok: NDArray[np.bool_],
                orders: tuple[int, ...]) -> NDArray[np.complex128]:
        """Per-period phasors of ``orders`` (``period_phasors``)."""
        window, present = signal[self.start:self.stop], ok[self.start:self.stop]
        centred = np.where(present, window - np.mean(window[present]), 0.0)
        angle = _electrical_angle(self.position0, self.slope, self.stop - self.start,
                                  self.microsteps_per_fullstep)
        return period_phasors(centred, present, angle, self.samples_per_period, orders)


def _runs(timeline: Timeline, drive_ok: NDArray[np.bool_], min_speed_hz: float
          ) -> Iterator[_Run | Rejected]:
    """Every enabled hold's stretches at constant velocity, in order, or why one is not."""
    cycle = 4 * timeline.metadata.microsteps_per_fullstep
    for hold in holds(timeline):
        if not hold.enabled:
            continue
        for a, b in constant_velocity_runs(timeline.position, drive_ok, hold.start, hold.stop):
            line = _fit_line(timeline.position, drive_ok, a, b)
            if line is None:
                yield Rejected(a, b, "position demand is not a straight line")
                continue
            p0, slope = line
            hz = abs(slope) / cycle / timeline.sync_period_s
            if hz < min_speed_hz:
                continue  # standstill or creeping: no electrical frequency to lock to
            yield _Run(hold, a, b, p0, slope, hz, cycle / abs(slope),
                       timeline.metadata.microsteps_per_fullstep, timeline.metadata.rotor_teeth)


@dataclass(frozen=True)
class _Observed:
    """Every steady run of a recording with its per-period phasors (by index into
    ``runs``) and the sample clock they agree on: computed once, for the clock and then
    for each run's settling."""

    runs: list[_Run | Rejected]
    phasors: dict[int, NDArray[np.complex128]]
    clock: float


def _observe(timeline: Timeline, signal: NDArray[np.float64], drive_ok: NDArray[np.bool_],
             *, orders: tuple[int, ...], min_speed_hz: float) -> _Observed:
    ok = ~np.isnan(signal)
    runs = list(_runs(timeline, drive_ok, min_speed_hz))
    phasors = {i: run.phasors(signal, ok, run.orders(orders))
               for i, run in enumerate(runs) if isinstance(run, _Run)}
    turns = []
    for i, z in phasors.items():
        run = runs[i]
        assert isinstance(run, _Run)
        turn, sigma = _tail_turn(z, run.orders(orders))
        # A turn ahead of the angle is the samples' time running fast, either way round.
        turns.append((turn * run.direction, sigma))
    return _Observed(runs, phasors, clock_rate(turns))


def _operating_point(run: _Run | Rejected) -> tuple[int, float] | None:
    """(amplitude mA, signed electrical Hz to 0.1) of a steady run; None for a rejection."""
    if isinstance(run, Rejected):
        return None
    return run.hold.amplitude_mA, round(math.copysign(run.hz, run.slope), 1)


def _after_change(seen: _Observed, index: int, orders: tuple[int, ...], settle_s: float,
                  period_s: float) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Run ``index``'s per-period phasors (the clock taken out) from ``settle_s`` after its
    hold's change, with each period's mechanical angle at its middle."""
    run = seen.runs[index]
    assert isinstance(run, _Run)
    z = without_clock(seen.phasors[index], run.orders(orders), seen.clock * run.direction)
    spp = run.samples_per_period
    waited = math.ceil(max(0.0, settle_s / period_s - (run.start - run.hold.start)) / spp)
    middle = (np.arange(waited, z.shape[0], dtype=np.float64) + 0.5) * spp
    angle = mechanical_angle(run.position0 + run.slope * middle, run.microsteps_per_fullstep,
                             run.rotor_teeth)
    return z[waited:], angle


def _drive_ok(timeline: Timeline) -> NDArray[np.bool_]:
    """Drive samples to trust: valid, and not a lone glitch of the position demand."""
    ok: NDArray[np.bool_] = timeline.drive_valid & ~position_glitches(timeline.position,
                                                                     timeline.drive_valid)
    return ok


def sensor_clock(timeline: Timeline, signal: NDArray[np.float64],
                 orders: tuple[int, ...] = SETTLE_ORDERS, min_speed_hz: float = 1.0) -> float:
    """How much faster than SYNC the samples of ``signal`` (the tangential acceleration,
    NaN where missing) keep their own time, relative; 0 where the holds do not agree on
    it (``clock_rate``): what ``steady_segments`` takes out before judging settling."""
    return _observe(timeline, signal, _drive_ok(timeline), orders=orders,
                    min_speed_hz=min_speed_hz).clock


def steady_segments(
    timeline: Timeline,
    signal: NDArray[np.float64],
    *,
    settle_periods: float | None = None,
    min_speed_hz: float = 1.0,
    settle_fallback: SettleFallback | None = None,
    settle_orders: tuple[int, ...] = SETTLE_ORDERS,
) -> tuple[list[Segment], list[Rejected]]:
    """Steady, settled, whole-period segments of the run, and the stretches rejected.

    ``signal`` is the tangential acceleration (NaN where lost or saturated).
    With ``settle_periods`` None the settling is judged from the data (per
    period phasors of orders 1 and 2); a number drops exactly that many
    electrical periods after the start of each steady stretch.
    ``settle_fallback`` rescues stretches too short for the data to judge
    (fewer than six periods): it gives the settling time from a model of the
    chain, and the segment may then be as short as one period; its phasors are
    noisier, and their variance says so. On longer stretches it is a floor under
    the data's judgement. ``settle_orders`` are the orders whose
    per-period phasors must have settled: the calibration's two by default; a caller
    that uses higher orders should watch them too, since a mode's ringing shows at
    the orders near its frequency long after orders 1 and 2 look steady. Settling is
    judged with the recording's sample clock taken out (``sensor_clock``), which turns
    every hold alike. Where the chain says its ringing is over but the data never settle,
    the holds of that operating point are kept if they change together as the rotor turns
    (``turning_with_rotor``: an eccentric rotor near a mode), else rejected.
    """
    m = timeline.metadata.microsteps_per_fullstep
    period_s = timeline.sync_period_s
    drive_ok = _drive_ok(timeline)
    segments: list[Segment] = []
    rejected: list[Rejected] = []
    if settle_periods is None:
        seen = _observe(timeline, signal, drive_ok, orders=settle_orders,
                        min_speed_hz=min_speed_hz)
    else:  # settling is given: no phasors to judge it by
        seen = _Observed(list(_runs(timeline, drive_ok, min_speed_hz)), {}, 0.0)
    turning: dict[tuple[int, float], dict[int, bool]] = {}

    def turns(index: int, decay: ChainDecay) -> bool:
        """Whether run ``index`` turns with the rotor together with its operating point's
        other holds (``turning_with_rotor``), judged once per operating point."""
        point = _operating_point(seen.runs[index])
        assert point is not None  # a steady run's
        if point not in turning:
            members = [j for j, r in enumerate(seen.runs) if _operating_point(r) == point]
            given = [_after_change(seen, j, settle_orders, decay.settle_s(), period_s)
                     for j in members]
            turning[point] = dict(zip(members, turning_with_rotor(given), strict=True))
        return turning[point][index]

    for i, run in enumerate(seen.runs):
        if isinstance(run, Rejected):
            rejected.append(run)
            continue
        hold, a, b, p0, slope = run.hold, run.start, run.stop, run.position0, run.slope
        hz, spp = run.hz, run.samples_per_period
        settling = Settling.GIVEN
        shortest = MIN_PERIODS
        ringing: tuple[complex, ...] = ()
        if settle_periods is None:
            settling = Settling.DATA
            usable = run.orders(settle_orders)
            # Judged with the recording's clock taken out: it turns every hold alike.
            phasors = without_clock(seen.phasors[i], usable, seen.clock * run.direction)
            first = settled_period(phasors)
            held = (b - a) / spp
            too_short = held < 2 * _SETTLE_BLOCK
            signed_hz = math.copysign(hz, slope)
            decay = (None if settle_fallback is None
                     else settle_fallback(hold.amplitude_mA, signed_hz))
            # Seconds from the change until this hold's own ringing is down to what
            # the harmonics resolve: waited for as far as the hold allows, never at
            # the cost of fitting a mode out that the plain decay would not.
            longest = 0.0 if decay is None else _rung_by_change(
                phasors, (a - hold.start) * period_s, spp * period_s, decay).settle_s()
            if first is None and settle_fallback is not None and decay is None:
                rejected.append(Rejected(a, b, (
                    f"a hold of {held:.1f} periods at {signed_hz:+.1f} Hz ends before the "
                    "chain's slowest mode has decayed")))
                continue
            if first is None and decay is not None:
                # A short hold, or one whose data never settle: the chain's model says
                # how long to wait, and which of its modes must be fitted out instead.
                shortest = 1 if too_short else MIN_PERIODS
                available_s = (b - hold.start) * period_s
                needed_s = shortest * spp * period_s
                wait_s, ringing = decay.plan(available_s, needed_s)
                if not too_short and not ringing and not turns(i, decay):
                    # The model sees nothing slow where the data do, and the data do not
                    # change with the rotor's angle alone: trust the data.
                    rejected.append(Rejected(a, b, "the rotor did not settle within the hold"))
                    continue
                if not ringing:
                    wait_s = max(wait_s, min(longest, available_s - needed_s))
                # The transient runs from the hold's change, not from the steady stretch.
                skip = max(0.0, wait_s / period_s - (a - hold.start))
                settling = Settling.RINGING if ringing else Settling.MODEL
                ringing = tuple(p * period_s for p in ringing)
            elif first is None:
                reason = (
                    f"a steady stretch of {held:.1f} periods is too short to judge settling "
                    f"(needs {2 * _SETTLE_BLOCK}); give the settling time explicitly"
                    if too_short
                    else "the rotor did not settle within the hold"
                )
                rejected.append(Rejected(a, b, reason))
                continue
            else:
                skip = first * spp
                if decay is not None:
                    # A lightly damped mode rings on at orders the data test cannot
                    # watch closely enough; where the model says it needs longer, wait,
                    # and for a hard ring as long as the hold leaves three periods. Not
                    # at the cost of the hold (cut to three periods, a rough clean
                    # disk, seed 2018362960, went from χ²/dof 1.4 to 5.7): where the
                    # model wants longer than the hold leaves, the modes still ringing
                    # at the data's start are fitted out from there, at poles the
                    # holds then measure (``station.analysis.ringing``; at the model's
                    # own poles, a development disk had kept a coupling's trace).
                    floor = decay.settle_s() / period_s - (a - hold.start)
                    room = b - a - MIN_PERIODS * spp
                    if floor <= room:
                        floor = min(max(floor, longest / period_s - (a - hold.start)), room)
                        if skip < floor:
                            skip, settling = floor, Settling.MODEL
                    elif skip < floor:
                        since_s = (a - hold.start + skip) * period_s
                        ringing = tuple(p * period_s for p in decay.poles
                                        if decay.seconds(p) > since_s)
                        if ringing:
                            settling = Settling.RINGING
        else:
            skip = settle_periods * spp
        # Half a sample of slack: the fitted speed is off in its last digits, and a hold
        # of exactly N periods must not come out as N − ε.
        periods = math.floor((b - a - skip + 0.5) / spp)
        if periods < shortest:
            rejected.append(
                Rejected(a, b, f"fewer than {shortest} settled electrical periods")
            )
            continue
        start = b - round(periods * spp)
        t = hold.trims
        segments.append(
            Segment(
                start=start,
                stop=b,
                held_from=hold.start,
                steady_from=a,
                trims=Trims(float(t[0]), float(t[1]), float(t[2]), float(t[3])),
                amplitude_mA=hold.amplitude_mA,
                position0=p0 + slope * (start - a),
                microsteps_per_sample=slope,
                periods=periods,
                microsteps_per_fullstep=m,
                settling=settling,
                ringing=ringing,
            )
        )
    return segments, rejected


HALVES_SIGMAS = 3.0
"""Standard errors (the quieter half's noise) a segment's two halves' phasors must lie
apart for it to count as still settling."""
HALVES_CHANCE = 1e-4
"""...or how rarely noise alone would leave its first half's residual variance that much
above its second's (the F test of the two): a half of two periods at 1 kHz keeps about 67
degrees of freedom beside the orders fitted, and the ratio must then exceed 2.6."""


def halves_shift(early: Harmonics, late: Harmonics, order: int) -> float:
    """How far a segment was still moving at ``order`` (m/s²), judged from its two halves;
    0 where they agree within the noise.

    A transient that outlasts the settle shows two ways: the halves' phasors lie apart
    beyond the noise (a ring near that order), or the first half leaves much more
    unexplained than the second (a ring elsewhere, which a half of a few periods
    partly averages out of its phasors but not out of its residual; its size is the part
    of the first half's residual the second no longer has). The noise is the quieter
    half's, because a ring inflates the other's.
    """
    apart = abs(late.h(order) - early.h(order))
    noise = math.sqrt(2.0 * min(late.var(order), early.var(order)))
    moved = apart if apart > HALVES_SIGMAS * noise else 0.0
    if _louder(early, late):
        moved = max(moved, math.sqrt(early.residual_rms**2 - late.residual_rms**2))
    return moved


def _louder(early: Harmonics, late: Harmonics) -> bool:
    """Whether the first half's noise variance exceeds the second's beyond chance."""
    dof = [h.samples_used * h.residual_rms**2 / h.noise_variance
           if h.noise_variance > 0.0 else 0.0 for h in (early, late)]
    if min(dof) < 1.0:
        return False
    ratio = early.noise_variance / late.noise_variance
    return bool(ratio > stats.f.isf(HALVES_CHANCE, dof[0], dof[1]))
