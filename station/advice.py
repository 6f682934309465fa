"""What the operator does next, for every run that did not pass.

A FAIL banner that only says which limit broke leaves the operator to guess
whether the unit is trimmed, whether to try again, and whom to call. The
advice here is read from the run's own record (verdict, failed limits,
reason, whether trims were stored), so the screen, the JSON and the HTML
report give the same words, and a record read back years later gives them too.
"""

from __future__ import annotations

import shlex

from station.runs import LimitName, Run, RunKind, Verdict, limit_name

_OUT_OF_BOUNDS = frozenset({LimitName.OFFSET_A, LimitName.OFFSET_B, LimitName.GAIN_A,
                            LimitName.GAIN_B})
_UNCERTAIN = frozenset({LimitName.ESTIMATE, LimitName.OFFSET_SIGMA, LimitName.GAIN_SIGMA,
                        LimitName.FIT_R2})
_RESIDUAL = frozenset({LimitName.H1_AFTER, LimitName.H2_AFTER, LimitName.H1_REDUCTION,
                       LimitName.H2_REDUCTION})


def _command(run: Run) -> str:
    """The command that runs this unit again as this run ran it."""
    if run.kind is RunKind.RECALIBRATE:
        reason = shlex.quote(run.service_reason or "field service")
        return f"`station recalibrate {run.serial} --reason {reason}`"
    return f"`station calibrate {run.serial}`"


def _kept(run: Run) -> str:
    if run.trims_stored:
        return "the new trims are stored in the drive"
    return "not trimmed; the unit keeps its trims"


def _failed(run: Run) -> str:
    names = {limit_name(str(c.name)) for c in run.failed_limits}
    serial = run.serial
    if names & _OUT_OF_BOUNDS:
        # Beyond what a trim may correct: the amplifier itself is off, no retry fixes it.
        return (f"{_kept(run)}; the drive needs more correction than the recipe allows: "
                f"set the unit aside for repair, or run `station characterize {serial}` to "
                "see why")
    if names & _UNCERTAIN:
        return (f"{_kept(run)}; the measurement was not certain enough: check that the "
                f"sensor is screwed down and the coupling tight, then run {_command(run)} "
                "again; if it fails again, run "
                f"`station characterize {serial}`")
    if names & _RESIDUAL:
        return (f"{_kept(run)}; the ripple left after trimming is above the limit, which "
                "trims cannot remove: check the fixture's coupling and load, then run "
                f"`station characterize {serial}`")
    return f"{_kept(run)}; see the report for the limits that failed"


def _errored(run: Run) -> str:
    reason = (run.reason or "").lower()
    serial = run.serial
    again = f"then run {_command(run)} again"
    if reason.startswith("sensor"):
        return (f"{_kept(run)}; check the sensor's cable and connector and that its node is "
                f"powered, {again}")
    if reason.startswith("drive"):
        return (f"{_kept(run)}; check the drive's CAN cable, power and node ID, and that the "
                f"unit on the fixture is {serial}, {again}")
    if "database" in reason or "spool" in reason:
        return f"{_kept(run)}; check the connection to the results database, {again}"
    if reason.startswith("internal error"):
        return (f"{_kept(run)}; this is a defect of the station: keep the log (rerun with "
                "-v) and call the station's engineers")
    return f"{_kept(run)}; read the reason above, fix its cause, {again}"


def next_step(run: Run) -> str | None:
    """The operator's next step; None for a pass, which needs none."""
    if run.verdict is Verdict.PASS:
        return None
    if run.verdict is Verdict.FAIL:
        return _failed(run)
    if run.verdict is Verdict.ABORTED:
        return (f"{_kept(run)}; the run was stopped and the drive is disabled: run "
                f"{_command(run)} again when the unit is ready")
    if run.verdict is Verdict.ERROR:
        return _errored(run)
    return (f"the run of {run.serial} never finished (the station stopped during it): run "
            f"{_command(run)} again")
