"""Holding trim points on the bench and measuring what each did, for every step that
measures (the baseline, a method's sweeps, the verification).

A hold is the motor turning at the recipe's speed with one set of trims for a whole
number of electrical periods; its harmonics come from what the bus carried meanwhile,
matched to the plan by the trims the drive reported in effect. Holds that clip the
sensor are counted and said, and where the recipe allows measured again nearer their
design's centre or left out. What the holds saw of the sensor's clock is kept for the
run's later holds: one sensor, one clock.
"""

from __future__ import annotations

from collections.abc import Sequence

from station.analysis.phasor_clock import clock_from_phasors
from station.analysis.pipeline import AnalysisOptions, Measured, measure
from station.analysis.sampling import ClockPhase, RateObservation, pooled_clock
from station.analysis.timeline import Timeline
from station.benches import BenchSession
from station.capture import FrameCapture
from station.commands import CommandLog
from station.core import Trims
from station.designs import holds_for, within_drive_range
from station.errors import SensorFault
from station.methods import trims_text
from station.recipes import Clipping, Recipe
from station.runner import Motion
from station.runs import Run
from station.schedules import Phase
from station.selfcheck import sensor_in_motion_problems

_SAME_SPEED = 0.01
"""A segment within 1 % of the recipe's electrical frequency is one of its holds."""


class Holds:
    """The holds of one run: what they measured, clipped, left out and timed."""

    def __init__(self, recipe: Recipe, run: Run, session: BenchSession, capture: FrameCapture,
                 commands: CommandLog | None, *, velocity: int, electrical_hz: float,
                 sees_angle: bool) -> None:
        self.recipe = recipe
        self.run = run  # its warnings say what the holds met
        self.session = session
        self.capture = capture
        self.commands = commands
        self.velocity = velocity
        self.electrical_hz = electrical_hz
        self.period_s = session.spec.sync_period_s
        self.sees_angle = sees_angle
        self.clipped = 0  # measured samples at the sensor's full scale, and all of them
        self.received = 0
        self.remeasured = 0  # holds measured again nearer their centre because they clipped
        self.left_out: set[Trims] = set()  # points whose holds clipped beyond the recipe's share
        # What the holds saw of the sensor's clock, pooled over the run (one sensor, one
        # clock), the rate the latest holds were demodulated at, and the wraps found.
        self.clock_seen: list[RateObservation] = []
        self.clock_rate = 0.0
        self.wraps: list[int] = []  # where, in the run's samples
        self.clock_phasors: float | None = None  # the rate the phasors fitted best

    def measure(self, motion: Motion, points: list[Trims], phase: Phase, *,
                 centre: Trims | None = None, lead_periods: float = 0.0,
                 settle_periods: int | None = None,
                 dwell_periods: int | None = None) -> list[Measured]:
        """Hold each point and return what it measured, clipped holds dealt with.

        Where the recipe allows, a hold clipped beyond its share is measured
        again nearer ``centre`` (its design's centre, where the ripple is lower),
        and left out when it still clips or cannot move; ``centre`` None (a
        baseline, a verification) moves nothing.
        """
        found = self.hold(motion, points, phase, lead_periods=lead_periods,
                           settle_periods=settle_periods, dwell_periods=dwell_periods)
        policy = self.recipe.clipping
        if policy is None:
            return found
        used, clipped = _unclipped(found, policy)
        shrink = policy.step_shrink
        for _ in range(policy.retries):
            if centre is None or not clipped:
                break
            again = [p for p in dict.fromkeys(self._nearer(centre, p, shrink) for p in clipped)
                     if p != centre and p not in self.left_out]
            self._leave_out([p for p in clipped if self._nearer(centre, p, shrink) not in again],
                            phase, policy, "it cannot be moved nearer its design's centre")
            if not again:
                clipped = []
                break
            self.run.warnings.append(
                f"{phase.value}: {len(again)} point(s) clipped at the sensor's "
                f"±{self.recipe.motion.sensor_range_g} g in more than "
                f"{policy.max_share:.0%} of their samples: measured again at {shrink:g} of "
                f"their step from {trims_text(centre)}, where the ripple is lower")
            self.remeasured += len(again)
            kept, clipped = _unclipped(
                self.hold(motion, again, phase, settle_periods=settle_periods,
                           dwell_periods=dwell_periods), policy)
            used += kept
        self._leave_out(clipped, phase, policy,
                        f"still clipped after {policy.retries} smaller step(s)"
                        if centre is not None else "a point nothing can replace")
        return used

    def _nearer(self, centre: Trims, point: Trims, shrink: float) -> Trims:
        """``point`` moved towards ``centre``: ``shrink`` of its step remains."""
        def towards(c: float, p: float) -> float:
            return c + shrink * (p - c)

        moved = Trims(towards(centre.offset_a_mA, point.offset_a_mA),
                      towards(centre.offset_b_mA, point.offset_b_mA),
                      towards(centre.gain_a, point.gain_a), towards(centre.gain_b, point.gain_b))
        return within_drive_range(moved, self.recipe.product.rated_current_mA)

    def _leave_out(self, points: Sequence[Trims], phase: Phase, policy: Clipping,
                   why: str) -> None:
        """Points whose holds clipped beyond the recipe's share: not used, and said."""
        for point in points:
            if point in self.left_out:
                continue
            self.left_out.add(point)
            self.run.warnings.append(
                f"{phase.value}: point {trims_text(point)} left out: clipped at the sensor's "
                f"±{self.recipe.motion.sensor_range_g} g in more than {policy.max_share:.0%} "
                f"of its samples ({why})")

    def hold(self, motion: Motion, points: list[Trims], phase: Phase, *,
              lead_periods: float = 0.0, dwell_periods: int | None = None,
              settle_periods: int | None = None, halves: bool = False) -> list[Measured]:
        """Hold each point, then demodulate what the bus carried meanwhile.

        Segments are matched to the plan by the trims the drive reported in
        effect (TPDO2), never by when the station wrote them. A point that
        yields no segment is left out with a warning; the estimators say
        whether what remains suffices.
        """
        motion_spec = self.recipe.motion
        dwell = motion_spec.dwell_periods if dwell_periods is None else dwell_periods
        settle = motion_spec.settle_periods if settle_periods is None else settle_periods
        holds = holds_for(
            points,
            phase=phase,
            velocity=self.velocity,
            amplitude_mA=motion_spec.amplitude_mA,
            hold_periods=settle + dwell,
            electrical_hz=self.electrical_hz,
            sync_period_s=self.period_s,
            lead_periods=lead_periods,
        )
        assert self.capture is not None
        mark = self.capture.mark()
        # The timeline begins at the first SYNC after the mark: the run's sample index of
        # the next SYNC (one SYNC between the two calls moves u by a millionth of a period).
        first = self.capture.syncs_seen()
        motion.run(holds)
        timeline = self.capture.timeline(mark, self.commands)
        self._check_sensor(timeline)
        self._count_clipping(timeline, phase)
        measured, rejected = measure(timeline, AnalysisOptions(
            settle_periods=float(settle), clock_seen=tuple(self.clock_seen),
            first_sample=first, wraps_seen=tuple(self.wraps), halves=halves,
            find_ringing=phase is not Phase.VERIFY, taper=phase is Phase.VERIFY))
        self._follow_clock(measured)
        best: dict[Trims, Measured] = {}
        for m in measured:
            seg = m.segment
            hz = seg.electrical_hz(self.period_s)
            if seg.amplitude_mA != motion_spec.amplitude_mA or (
                abs(hz - self.electrical_hz) > _SAME_SPEED * self.electrical_hz
            ):
                continue
            if seg.trims not in best or seg.samples > best[seg.trims].segment.samples:
                best[seg.trims] = m
        found: list[Measured] = []
        for point in points:
            if point in best:
                found.append(best[point])
                continue
            reasons = "; ".join(sorted({r.reason for r in rejected})) or "no steady segment"
            self.run.warnings.append(
                f"{phase.value}: point {trims_text(point)} not measured ({reasons})"
            )
        return found

    def _follow_clock(self, measured: Sequence[Measured]) -> None:
        """Keep what these holds saw of the sensor's clock for the run's later holds."""
        self.clock_seen.extend(m.clock_observed for m in measured
                               if m.clock_observed is not None)
        if measured:
            self.clock_rate = measured[0].clock_rate
        self.wraps.extend(m.first_sample + m.wrap_at for m in measured
                          if m.wrap_at is not None)

    def clock_phase(self, held: Sequence[Measured]) -> ClockPhase | None:
        """The sensor's clock over the run so far, as the holds timed it and the phasors
        refine it; None where no phasor is used (without the drive's angle only
        magnitudes are)."""
        if not self.sees_angle:
            return None
        clock = clock_from_phasors(held, pooled_clock(self.clock_seen), self.wraps)
        self.clock_phasors = clock.rate
        return clock

    def _count_clipping(self, timeline: Timeline, phase: Phase) -> None:
        """Say when holds clipped: the analysis leaves those samples out of its fits, and
        an estimate must never come from clipped holds without a word: of 200 units of
        the population benchmark, 133 clipped at ±4 g and only the three that the sensor
        check stopped said so."""
        clipped = timeline.losses.saturated_samples
        received = int(timeline.sensor_valid.sum())
        self.clipped += clipped
        self.received += received
        if clipped:
            self.run.warnings.append(
                f"{phase.value}: {clipped} of {received} samples clipped at the sensor's "
                f"±{self.recipe.motion.sensor_range_g} g, left out of the fits")

    def _check_sensor(self, timeline: Timeline) -> None:
        """Refuse holds whose samples are not acceleration (saturated, unplugged, stuck)."""
        problems = sensor_in_motion_problems(
            timeline.accel_counts[timeline.sensor_valid],
            timeline.metadata.sensor_lsb_mps2,
            gravity_axis=self.session.fixture.gravity_axis,
            gravity_tolerance_mps2=self.recipe.self_check.gravity_tolerance_mps2,
        )
        if problems:
            raise SensorFault(self.session.sensor.name, "; ".join(problems))


def _unclipped(found: Sequence[Measured], policy: Clipping) -> tuple[list[Measured], list[Trims]]:
    """The holds within the recipe's share of clipped samples, and the points of the rest."""
    used: list[Measured] = []
    clipped: list[Trims] = []
    for m in found:
        if m.saturated > policy.max_share * max(1, m.segment.samples):
            clipped.append(m.segment.trims)
        else:
            used.append(m)
    return used, clipped
