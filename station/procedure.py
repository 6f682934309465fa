"""The calibration of one unit on one bench, step by step, as the recipe says.

Orchestration only. The maths is in ``station.analysis`` (segmenting, demodulation,
estimators), ``station.designs`` (where to measure), ``station.selfcheck`` and
``station.limits`` (judging), all pure; the calibration methods' plans are in
``station.methods``; holding points and measuring them is ``station.holding``; the
verification is ``station.verifying``; the devices are behind ``drivers.base``;
storage is someone else's job. The procedure fills the caller's ``Run`` as it learns
things, so when it stops on a device error the record still holds everything up to that
point, and the whole run is always published as an ICD.md §5 recording, whatever
happened.

Steps (``station.steps.Step``): identify the unit (its electronic serial must match the
label, its ratings the recipe's product), self-check the sensor at standstill, measure
a baseline at the trims the drive holds, run the method's sweeps closed loop (each
batch of points depends on what the last measured), estimate, judge the estimate,
write and store the trims, reset the drive and read them back, verify by measuring
again, judge the result, and on a pass write the calibration record (0x2101) and store
it. The drive is disabled on the way out, always.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence, Set
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from drivers.base import CalibrationRecord, Drive
from station import __version__
from station.analysis.estimate import (
    CLIPPED_NOTE,
    TrimEstimate,
    Unsupported,
)
from station.analysis.pipeline import Measured
from station.analysis.report import fit_summary
from station.analysis.sampling import ClockPhase
from station.benches import BenchSession, BenchSpec, open_bench
from station.capture import FrameCapture
from station.commands import CommandLog, LoggedDrive
from station.core import Trims
from station.designs import (
    within_drive_range,
)
from station.errors import (
    DeviceError,
    DeviceTimeout,
    IdentityMismatch,
    ProductMismatch,
    RecordingError,
    SelfCheckFailed,
    StationError,
)
from station.holding import Holds
from station.limits import (
    clipping_check,
    estimate_checks,
    ripple_checks,
    summary,
    trims_within,
    unsupported,
    verdict_for,
)
from station.methods import Plan, for_run, trims_text
from station.recipes import Recipe
from station.recorder import RecordingWriter
from station.recording import RecordingMetadata, sha256_of
from station.runner import Motion
from station.runs import LimitCheck, LimitName, Ripple, Run, Verdict
from station.schedules import Phase, velocity_for
from station.selfcheck import sensor_self_check
from station.serials import Serial, label_for
from station.steps import Observer, Silent, Step
from station.verifying import Verifier

log = logging.getLogger(__name__)

_U16_MAX = 0xFFFF


@dataclass(frozen=True)
class CalibrationRequest:
    serial: Serial
    recipe: Recipe
    bench: BenchSpec
    recording: Path


@contextmanager
def unit_on_bench(bench: BenchSpec, serial: Serial,
                  observer: Observer | None = None) -> Iterator[BenchSession]:
    """The bench, open, with the named unit on it: checked by reading only.

    The wrong unit on the fixture is the operator's mistake, not the unit's:
    it is refused (``IdentityMismatch``, exit code 2) before the station
    records a run or writes anything to the drive.
    """
    shown = observer if observer is not None else Silent()
    shown.step(Step.CONNECT, f"bench {bench.name}")
    with open_bench(bench, serial) as session:
        shown.step(Step.IDENTIFY, str(serial))
        check_identity(session.drive, serial)
        yield session


def calibrate_unit(request: CalibrationRequest, run: Run, session: BenchSession,
                   observer: Observer | None = None) -> None:
    """Calibrate the unit on ``session``, filling ``run``; raises a station error when the
    bench fails.

    On return ``run.verdict`` is PASS or FAIL and ``run.limits`` says why; on
    an exception the caller records ERROR (or ABORTED) with what ``run``
    already holds, and the drive holds the trims it was found with.
    """
    _Calibration(request, run, session, observer if observer is not None else Silent()).run()


def check_identity(drive: Drive, serial: Serial) -> None:
    """The unit on the fixture must be the one the operator named (0x1018:4)."""
    reported = drive.identity().serial_number
    if reported != serial.number:
        raise IdentityMismatch(
            drive.name,
            f"the unit on the bench reports serial {label_for(reported)} (0x1018:4 = "
            f"{reported}), not {serial}: wrong unit on the fixture?",
        )


class _Context:
    """What a calibration method sees of the run (``station.methods.SweepContext``)."""

    def __init__(self, calibration: _Calibration, centre: Trims,
                 baseline: Sequence[Measured]) -> None:
        self._run = calibration
        self._centre = centre
        self._baseline = tuple(baseline)

    @property
    def recipe(self) -> Recipe:
        return self._run.recipe

    @property
    def centre(self) -> Trims:
        return self._centre

    @property
    def baseline(self) -> Sequence[Measured]:
        return self._baseline

    @property
    def left_out(self) -> Set[Trims]:
        return self._run.held.left_out

    def clock(self, held: Sequence[Measured]) -> ClockPhase | None:
        # The clock the latest estimate's phasors used: the verification's correction
        # and the record's fit summary follow it.
        self._run.clock_used = self._run.held.clock_phase(held)
        return self._run.clock_used

    def storable(self, trims: Trims) -> bool:
        return trims_within(self._run.recipe.limits, trims)

    def warn(self, text: str) -> None:
        self._run.run_record.warnings.append(text)

    def estimating(self, detail: str) -> None:
        self._run.observer.step(Step.ESTIMATE, detail)


class _Calibration:
    """One run's state: the session, the recipe's operating point, what was measured."""

    def __init__(self, request: CalibrationRequest, run: Run, session: BenchSession,
                 observer: Observer) -> None:
        self.request = request
        self.recipe = request.recipe
        self.run_record = run
        self.session = session
        self.observer = observer
        self.drive: Drive = session.drive
        # Asked of the drive once: whether its electrical angle comes with every sample
        # (the phasors then share one reference), or only magnitudes mean anything.
        self.sees_angle = session.drive.reports_state
        self.commands: CommandLog | None = None  # a drive that reports nothing on the bus
        self.period_s = session.spec.sync_period_s
        self.capture: FrameCapture | None = None
        self.holds: Holds | None = None  # once the unit is identified: its speed is known
        self.record_before: CalibrationRecord | None = None
        self.eeprom_touched = False  # a store was sent: the EEPROM may differ from before
        self.clock_used: ClockPhase | None = None  # the clock the last estimate's phasors used

    @property
    def held(self) -> Holds:
        """The run's holds (the unit identified: its speed is known)."""
        assert self.holds is not None
        return self.holds

    # -- the whole run ------------------------------------------------------------------------

    def run(self) -> None:
        metadata = self._metadata()
        capture = FrameCapture(metadata)
        self.capture = capture
        timing = self.session.command_timing
        if timing is not None:
            # Only the station knows when this drive changed: it logs its own writes
            # against the SYNCs the recording holds.
            self.commands = CommandLog(timing, capture.syncs_seen)
            self.drive = LoggedDrive(self.session.drive, self.commands)
        writer = RecordingWriter(self.request.recording, metadata,
                                 clock=self.session.recording_clock())
        start_cycles = self.session.clock.cycles
        try:
            # Recorded from the identity check on: a refused unit leaves its traces too.
            with self.session.listening(writer, capture):
                self._identify(metadata)
                self._calibrate()
                if not self.run_record.trims_stored:
                    # A unit failed before its trims were written keeps its own: the
                    # sweep's last point must not stay in its RAM.
                    self._restore()
        except BaseException:
            self._restore()
            raise
        finally:
            self.run_record.motion_s = (self.session.clock.cycles - start_cycles) * self.period_s
            errors = self.session.bus_monitor.error_frames
            if errors:
                # Harmless by themselves (CAN resends), but a bus going bad shows here first.
                self.run_record.warnings.append(f"{errors} CAN error frames during the run")
            self._publish(writer)

    def _restore(self) -> None:
        """Give the drive back its trims as found, after a run that did not finish.

        Trims under test must not stay in its RAM, and a half-done calibration
        must not stay in its EEPROM: if a store was sent, the previous trims and
        calibration record are stored again. Best effort (the drive may be the
        fault); what could not be restored is said in the run's warnings, and
        ``trims_stored`` keeps saying what the EEPROM holds as far as known.
        """
        run, drive = self.run_record, self.session.drive
        before = run.trims_before
        if before is None:
            return  # nothing was touched before the trims were even read
        where = "RAM"
        try:
            drive.write_trims(before)
            if self.eeprom_touched:
                where = "EEPROM"
                if self.record_before is not None:
                    drive.write_calibration_record(self.record_before)
                drive.store()
                run.trims_stored, run.trims_after = False, None
                run.warnings.append(f"{drive.name}: previous trims {trims_text(before)} and "
                                    "calibration record stored again (rolled back)")
        except StationError as exc:
            log.error("%s: could not restore the trims it was found with: %s", drive.name, exc)
            run.warnings.append(
                f"{drive.name}: could not restore its previous trims {trims_text(before)} "
                f"in its {where} ({exc}): verify the unit before it ships"
            )

    def _publish(self, writer: RecordingWriter) -> None:
        """The recording is kept whatever happened: an error is exactly when it is needed."""
        if self.commands is not None:
            meta = writer.metadata
            writer.metadata = replace(meta, extra={**meta.extra, **self.commands.metadata()})
        try:
            path = writer.commit()
        except RecordingError as exc:
            log.error("the run's recording could not be written: %s", exc)
            self.run_record.warnings.append(f"recording lost: {exc}")
            return
        self.run_record.recording = str(path)
        self.run_record.recording_sha256 = sha256_of(path)

    def _metadata(self) -> RecordingMetadata:
        """What the recording's metadata needs, read from the devices (ICD.md §5)."""
        drive, sensor, product = self.drive, self.session.sensor, self.recipe.product
        microsteps = drive.microsteps_per_fullstep()
        sensor.set_range_g(self.recipe.motion.sensor_range_g)
        run = self.run_record
        return self.session.recording_metadata(
            self.request.serial.label,
            microsteps=microsteps,
            rotor_teeth=product.rotor_teeth,
            rated_current_mA=drive.rated_current_mA(),
            extra={
                "schedule": run.kind.value,
                "run_id": run.run_id,
                "recipe": self.recipe.name,
                "recipe_version": self.recipe.version,
                "recipe_sha256": self.recipe.sha256,
                "bench": self.session.spec.name,
                "station_id": run.station_id,
                "station_software": __version__,
                "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            },
        )

    def _identify(self, metadata: RecordingMetadata) -> None:
        """Refuse the wrong unit or the wrong product before anything moves."""
        drive, product = self.drive, self.recipe.product
        check_identity(drive, self.request.serial)
        microsteps = metadata.microsteps_per_fullstep
        rated = round(metadata.rated_current_mA)
        if microsteps != product.microsteps or rated != product.rated_current_mA:
            raise ProductMismatch(
                drive.name,
                f"runs {microsteps} microsteps per full step at {rated} mA rated; recipe "
                f"{self.recipe.name} is for {product.name} ({product.microsteps} microsteps, "
                f"{product.rated_current_mA} mA)",
            )
        self.run_record.trims_before = drive.read_trims()
        self.record_before = drive.read_calibration_record()
        velocity = velocity_for(self.recipe.motion.electrical_hz, microsteps)
        assert self.capture is not None  # listening since before the identity check
        self.holds = Holds(self.recipe, self.run_record, self.session, self.capture,
                           self.commands, velocity=velocity,
                           electrical_hz=velocity / (4.0 * microsteps),
                           sees_angle=self.sees_angle)

    def _calibrate(self) -> None:
        self._self_check()
        run = self.run_record
        with Motion(self.drive, self.session.clock,
                    on_progress=lambda done, total, _h: self.observer.progress(done, total)
                    ) as motion:
            estimate = self._sweeps(motion)
        if estimate is None:
            return
        stored = estimate.trims.rounded()
        checks = estimate_checks(self.recipe.limits, estimate, stored)
        if verdict_for(checks) is Verdict.FAIL:
            # Trims out of bounds or a doubtful fit are not written: the drive keeps its own.
            self._judge(checks)
            return
        self._write_and_store(stored)
        verifier = Verifier(self.recipe, run, self.session, drive=self.drive,
                            observer=self.observer, holds=self.held, store=self._write_and_store)
        after = verifier.verify(stored)
        checks = (*checks, *ripple_checks(self.recipe.limits, run.before, after,
                                          verifier.hidden()))
        for _ in range(self.recipe.verification.max_corrections):
            corrected = verifier.correct(estimate, stored, checks, self.clock_used)
            if corrected is None:
                break
            stored, checks = corrected
        self._judge(checks)
        if run.verdict is Verdict.PASS:
            self._write_calibration_record()
        self.observer.step(Step.DONE, run.verdict.value if run.verdict else "")

    def _judge(self, checks: Sequence[LimitCheck]) -> None:
        held = self.held
        checks = (*checks, clipping_check(held.clipped, held.received, remeasured=held.remeasured,
                                          left_out=len(held.left_out)))
        run = self.run_record
        run.limits = checks
        run.verdict = verdict_for(checks)
        run.reason = summary(checks)
        if run.verdict is Verdict.FAIL and self.held.left_out:
            # The likely cause, in words the operator can act on.
            run.reason += (f"; {len(self.held.left_out)} point(s) left out because the ripple "
                           f"clipped the sensor's ±{self.recipe.motion.sensor_range_g} g")
        sigma = {LimitName.OFFSET_SIGMA, LimitName.GAIN_SIGMA}
        if (any(c.name in sigma and c.passed is False for c in checks)
                and any(f"{CLIPPED_NOTE}: " in w for w in run.warnings)):
            run.reason += (f"; the ripple over the sensor's ±{self.recipe.motion.sensor_range_g}"
                           " g hides part of each harmonic in every hold")

    # -- steps --------------------------------------------------------------------------------

    def _self_check(self) -> None:
        spec = self.recipe.self_check
        self.observer.step(Step.SELF_CHECK, f"{spec.standstill_s:g} s at standstill")
        sensor = self.session.sensor
        cycles = max(1, round(spec.standstill_s / self.period_s))
        sensor.start_capture()
        try:
            self.session.clock.advance(cycles)
        finally:
            capture = sensor.stop_capture()
        result = sensor_self_check(
            capture.counts,
            capture.lsb_mps2,
            samples_expected=cycles,
            gravity_axis=self.session.fixture.gravity_axis,
            gravity_tolerance_mps2=spec.gravity_tolerance_mps2,
            max_noise_mps2=spec.max_noise_mps2,
        )
        if not result.ok:
            raise SelfCheckFailed(sensor.name, "; ".join(result.problems))

    def _sweeps(self, motion: Motion) -> TrimEstimate | None:
        """Baseline, then the recipe's sweeps; the estimate, or None after a FAIL."""
        run = self.run_record
        assert run.trims_before is not None
        rated = self.recipe.product.rated_current_mA
        centre = within_drive_range(run.trims_before, rated)
        self.observer.step(Step.BASELINE, trims_text(centre))
        baseline = self.held.measure(motion, [centre], Phase.BASELINE,
                                 lead_periods=self.recipe.motion.spin_up_periods)
        if baseline:
            h = baseline[0].harmonics
            run.before = Ripple(abs(h.h(1)), abs(h.h(2)))
        else:
            run.warnings.append("no baseline: the reduction cannot be judged")
        method, settings = for_run(self.recipe, sees_angle=self.sees_angle)
        try:
            estimate = self._follow(motion, method.plan(settings, _Context(self, centre,
                                                                           baseline)))
        except Unsupported as exc:
            self._judge((unsupported(str(exc)),))
            return None
        run.method = estimate.method.value
        run.trims_estimated = estimate.trims
        s = estimate.sigma
        run.uncertainty = Trims(s.offset_a_mA, s.offset_b_mA, s.gain_a, s.gain_b)
        run.fit = fit_summary(estimate)
        # The sensor's clock against SYNC as the holds were demodulated (0: on the SYNC).
        run.fit["sensor_clock"] = {
            "ppm": round(self.held.clock_rate * 1e6, 1), "wraps": len(self.held.wraps),
            **({} if self.held.clock_phasors is None
               else {"phasors_ppm": round(self.held.clock_phasors * 1e6, 1)})}
        run.warnings.extend(estimate.warnings)
        return estimate

    def _follow(self, motion: Motion, plan: Plan) -> TrimEstimate:
        """Hold what the method asks for, batch after batch, until it has its estimate:
        the one sweep loop, whatever the method."""
        try:
            batch = next(plan)
            while True:
                self.observer.step(Step.SWEEP, batch.label)
                measured = self.held.measure(motion, list(batch.points), batch.phase,
                                         centre=batch.centre,
                                         settle_periods=batch.settle_periods,
                                         dwell_periods=batch.dwell_periods)
                batch = plan.send(measured)
        except StopIteration as done:
            estimate: TrimEstimate = done.value
            return estimate
        finally:
            plan.close()

    def _write_and_store(self, trims: Trims) -> None:
        drive, run = self.drive, self.run_record
        self.observer.step(Step.WRITE, trims_text(trims))
        drive.write_trims(trims)
        self.observer.step(Step.STORE, "0x1010:01 save")
        self._store(drive)
        run.trims_stored = True
        run.trims_after = trims
        if drive.resettable:
            self.observer.step(Step.RESET, "NMT reset node")
            drive.reset()
        else:
            run.warnings.append(
                f"{drive.name}: read back without a reset (the transport has none), so the "
                "trims were confirmed in the drive's RAM, not reloaded from its EEPROM"
            )
        self.observer.step(Step.READ_BACK, "trims")
        back = drive.read_trims()
        run.trims_after = back
        if back != trims:
            raise DeviceError(
                drive.name,
                f"read back, the drive holds {trims_text(back)}, but "
                f"{trims_text(trims)} were written and stored: the EEPROM did not keep them",
            )

    def _store(self, drive: Drive) -> None:
        """Store, noting whether the EEPROM may now differ from how the unit came.

        A refused store (an abort, a Modbus exception: the drive's own answer)
        left the EEPROM as it was; an unanswered one may have acted.
        """
        touched = self.eeprom_touched
        self.eeprom_touched = True
        try:
            drive.store()
        except DeviceTimeout:
            raise
        except StationError:
            self.eeprom_touched = touched
            raise

    def _write_calibration_record(self) -> None:
        """0x2101: when, where and how often; stored, so the unit carries its own history."""
        drive, run = self.drive, self.run_record
        self.observer.step(Step.RECORD, "0x2101 and store")
        previous = self.record_before
        assert previous is not None  # read when the unit was identified
        drive.write_calibration_record(
            CalibrationRecord(
                calibrated_at=int(time.time()),
                station_id=run.station_id,
                count=min(previous.count + 1, _U16_MAX),
            )
        )
        self._store(drive)
