"""Step 7 of a calibration: the stored trims measured as the unit runs them after its
reset, and, where only the ripple failed, one correction from that very hold.

The verification is the only measurement taken exactly as the unit ships (its trims
stored, the drive reset and read back), so the verdict is judged on it; it is also the
hold nearest the null, so its phasors say where the null is more closely than the
sweep's far points did.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from drivers.base import Drive
from station.analysis.estimate import TrimEstimate, correction_from
from station.analysis.pipeline import Measured, still_settling
from station.analysis.sampling import ClockPhase
from station.benches import BenchSession
from station.core import Trims
from station.errors import DeviceError
from station.holding import Holds
from station.limits import RIPPLE_LIMITS, estimate_checks, ripple_checks, verdict_for
from station.methods import trims_text
from station.recipes import Recipe
from station.runner import Motion
from station.runs import LimitCheck, Ripple, Run, Verdict
from station.schedules import Phase
from station.steps import Observer, Step


class NoMeasurement(DeviceError):
    """A hold produced no usable steady segment: the bench, not the unit, let us down."""


class Verifier:
    """The verification of one run, and what its judged hold measured."""

    def __init__(self, recipe: Recipe, run: Run, session: BenchSession, *, drive: Drive,
                 observer: Observer, holds: Holds, store: Callable[[Trims], None]) -> None:
        self.recipe = recipe
        self.run = run
        self.session = session
        self.drive = drive
        self.observer = observer
        self.holds = holds
        self.store = store  # writes and stores trims in the drive, reset and read back
        self.verified: Measured | None = None  # the hold the verdict was judged on

    def verify(self, trims: Trims) -> Ripple:
        """Measure the stored trims as the drive runs them after its reset.

        The drive starts from standstill after its reset, and some units ring down from
        that start for longer than any fixed settle that suits the rest: a detent disk
        (development seed 100830014) still read 0.082 m/s² of H1 after 4 + 4 periods,
        against 0.015 at its steady state. So the hold goes on, in holds of the same
        length at the same trims (the motor keeps turning between them), while its two
        halves still differ where that could decide the verdict, up to the recipe's
        ``max_dwell_periods``; the unit is judged on the last hold.
        """
        spec = self.recipe.verification
        self.observer.step(Step.VERIFY, trims_text(trims))
        longest = spec.max_dwell_periods or spec.dwell_periods
        with Motion(self.drive, self.session.clock,
                    on_progress=lambda done, total, _h: self.observer.progress(done, total)
                    ) as motion:
            # The unit as it ships: measured whatever it clips (counted and said).
            measured = self.holds.hold(motion, [trims], Phase.VERIFY,
                                  lead_periods=self.recipe.motion.spin_up_periods,
                                  dwell_periods=spec.dwell_periods,
                                  settle_periods=spec.settle_periods, halves=True)
            dwelt = spec.dwell_periods
            moving = self._settling(measured)
            while moving and dwelt + spec.dwell_periods <= longest:
                # Nothing changes at the drive: the new hold needs no settle of its own.
                again = self.holds.hold(motion, [trims], Phase.VERIFY,
                                   dwell_periods=spec.dwell_periods, settle_periods=0,
                                   halves=True)
                dwelt += spec.dwell_periods
                if not again:
                    break  # the warning says why; the last hold measured stands
                measured, moving = again, self._settling(again)
        if not measured:
            raise NoMeasurement(
                self.session.sensor.name,
                "the verification run gave no steady segment: " + "; ".join(
                    w for w in self.run.warnings if w.startswith(Phase.VERIFY.value)),
            )
        period_s = 1.0 / self.holds.electrical_hz
        if dwelt > spec.dwell_periods:
            self.run.warnings.append(
                f"{Phase.VERIFY.value}: the unit was still settling after its reset; "
                f"measured for {dwelt * period_s:.2f} s instead of "
                f"{spec.dwell_periods * period_s:.2f} s and judged on the last "
                f"{spec.dwell_periods * period_s:.2f} s"
            )
        if moving:
            orders = " and ".join(f"H{k}" for k in moving)
            self.run.warnings.append(
                f"{Phase.VERIFY.value}: {orders} still moved at the end of "
                f"{dwelt * period_s:.2f} s of verification (the recipe's longest); the "
                "ripple after is what the last hold measured"
            )
        self.verified = measured[0]
        h = measured[0].harmonics
        after = Ripple(abs(h.h(1)), abs(h.h(2)))
        self.run.after = after
        return after

    def correct(self, estimate: TrimEstimate, stored: Trims, checks: Sequence[LimitCheck],
                clock: ClockPhase | None) -> tuple[Trims, tuple[LimitCheck, ...]] | None:
        """Trims corrected from a verification that failed only on its ripple, stored and
        verified again; None where no correction can help.

        The verification is one more hold, at the trims the unit ships with and near
        the null, so its phasors say where the null is more closely than the sweep's
        far points did (``correction_from``). A unit whose maps predict a ripple over a
        limit even at the corrected trims (an irreducible H2, say) is not moved: it
        fails as measured, and its failing costs no further motion.
        """
        failed = {c.name for c in checks if c.passed is False}
        if not failed or not failed <= RIPPLE_LIMITS or self.verified is None:
            return None
        run = self.run
        assert run.after is not None
        if verdict_for(ripple_checks(self.recipe.limits, run.before, run.after)) is Verdict.PASS:
            return None  # failed on what clipping may hide, which no trim moves
        correction = correction_from(estimate, self.verified.point(clock))
        limits = self.recipe.limits
        if (correction is None or correction.trims == stored
                or correction.h1_mps2 > limits.max_h1_after_mps2
                or correction.h2_mps2 > limits.max_h2_after_mps2):
            return None
        checks = estimate_checks(limits, estimate, correction.trims)
        if verdict_for(checks) is Verdict.FAIL:
            return None  # out of the recipe's bounds: the unit keeps what was verified
        was = run.after
        run.warnings.append(
            f"{Phase.VERIFY.value}: {' and '.join(sorted(failed))} over the limit at "
            f"{trims_text(stored)} (H1 {was.h1:.3g}, H2 {was.h2:.3g} m/s²); the sweep's maps "
            f"anchored on that hold put the offsets' null at {correction.null.offset_a_mA:+.1f}/"
            f"{correction.null.offset_b_mA:+.1f} mA: stored "
            f"{trims_text(correction.trims)} (predicted H1 {correction.h1_mps2:.3g}, "
            f"H2 {correction.h2_mps2:.3g} m/s²) and verified again")
        self.store(correction.trims)
        after = self.verify(correction.trims)
        return correction.trims, (*checks, *ripple_checks(limits, run.before, after,
                                                          self.hidden()))

    def hidden(self) -> float:
        """What the judged verification hold's clipping may hide, said where it is any."""
        judged = self.verified
        if judged is None or not judged.hidden:
            return 0.0
        self.run.warnings.append(
            f"{Phase.VERIFY.value}: {judged.saturated} samples over the sensor's "
            f"±{self.recipe.motion.sensor_range_g} g may hide up to {judged.hidden:.3g} m/s² of "
            "each harmonic; the unit is judged on the most it could have")
        return judged.hidden

    def _settling(self, measured: Sequence[Measured]) -> tuple[int, ...]:
        limits = self.recipe.limits
        return still_settling(measured[0], (limits.max_h1_after_mps2, limits.max_h2_after_mps2)
                              ) if measured else ()
