"""The station's command line (contract: shared/spec/CLI.md).

Thin on purpose: parse, call one procedure, print. Data goes to stdout (one
JSON document with ``--json``), logs and progress to stderr. Exit codes:
0 success, 1 unit failed a limit, 2 usage/recipe/input error (nothing done),
3 station or device error, or aborted.

The commands that move a drive or record for long (``calibrate``,
``recalibrate``, ``characterize``, ``sim record``) run under
``station.signals.stop_on_signals``: SIGINT and SIGTERM stop them once,
cleanly (drive disabled, run recorded as ``aborted`` with the signal named),
and a second signal cannot cut that cleanup short.
"""

from __future__ import annotations

import csv
import json
import logging
import re
import sys
import time as time_module
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from datetime import UTC, datetime, time
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console, Group
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

# Only what every command's options need is imported here: ``station --help`` and a
# rejected serial answer in a fraction of a second. The analysis (scipy), the bus and
# log-format stacks (python-can, asammdf) and the simulator are imported by the
# commands that use them (``bench/run cli_start`` measures it).
from station import __version__
from station.bench_names import check_bench
from station.core import Effect, LoadKind, MethodChoice
from station.errors import ExitCode, InputError, StationError
from station.paths import database_path, default_operator
from station.recording import require_recording
from station.runs import Verdict
from station.schedules import ScheduleName
from station.serials import parse_serial
from station.signals import stop_on_signals
from station.steps import STEPS, Step
from station.storage import describe
from station.views import (
    diagnosis_view,
    path_line,
    run_view,
    runs_table,
    stats_view,
    trims_text,
    verify_view,
)

if TYPE_CHECKING:
    from station.rows import RunFilter
    from station.runs import Run
    from station.schedules import Hold
    from station.service import Calibration, Station

log = logging.getLogger("station")

stdout = Console(soft_wrap=True)
stderr = Console(stderr=True, soft_wrap=True)

app = typer.Typer(
    name="station",
    help="End-of-line calibration station for hybrid stepper motor drives.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
sim_app = typer.Typer(
    help="The simulated bench: recordings and units whose truth is known.",
    no_args_is_help=True,
)
app.add_typer(sim_app, name="sim")

FLAG = ""
"""A flag's help shows no type: it takes no value."""


def _help_without_python_types() -> None:
    """Help that names what a value is (SERIAL, FILE, URL), not its Python type.

    typer 0.29 prints ``<str>`` beside every argument and ``<bool>`` beside its own
    ``--help``, where options show their metavar. Arguments get the options' rule (the
    metavar, else nothing) and flags show nothing: they take no value. Guarded, so a
    typer that renders help otherwise is left as it is.
    """
    from typer import core  # noqa: PLC0415 - typer's internals, only to adjust help

    argument = getattr(core, "TyperArgument", None)
    option = getattr(core, "TyperOption", None)
    if argument is None or option is None or not hasattr(option, "display_type_rich"):
        return
    typed = option.display_type_rich

    def option_type(self: Any, ctx: Any) -> str | None:
        return None if getattr(self, "is_bool_flag", False) else typed(self, ctx)

    def argument_type(self: Any, ctx: Any) -> str | None:
        return None

    def usage_name(self: Any) -> str:
        # What the argument is, as man pages write it: required bare, optional in [].
        name = str(self.display_name_raw)
        return name if self.required else f"[{name}]"

    option.display_type_rich = option_type
    argument.display_type_rich = argument_type
    if hasattr(argument, "_usage_display_name"):
        argument._usage_display_name = usage_name


_help_without_python_types()
JsonOption = Annotated[bool, typer.Option("--json", help="Print one JSON document on stdout.",
                                          metavar=FLAG)]
NO_EFFECTS = "none"


class OutputFormat(StrEnum):
    TABLE = "table"
    JSON = "json"
    CSV = "csv"


FormatOption = Annotated[
    OutputFormat, typer.Option("--format", help="table for people, json or csv for machines.")
]


class DocumentFormat(StrEnum):
    """What a command that prints one document (not rows) can print it as."""

    TABLE = "table"
    JSON = "json"


DocFormatOption = Annotated[
    DocumentFormat, typer.Option("--format", help="table for people, json for machines "
                                 "(--json is its short form).")
]


def _wants_json(output: DocumentFormat, as_json: bool) -> bool:
    """One output option on every command: ``--json`` is ``--format json``."""
    return as_json or output is DocumentFormat.JSON



_TYPER_INTERRUPTED = 130
"""What typer returns (standalone_mode=False) when a KeyboardInterrupt leaves a command."""


class CommandAborted(StationError):
    """A stop (Ctrl-C, SIGTERM) that ended a command outside any run's own recording.

    Runs record their own abort and end with their verdict's exit code; this
    is the stop that came before a run began, or in a command that records no
    run. Raised as a ``StationError`` because typer would turn the
    ``KeyboardInterrupt`` into exit 130, and CLI.md promises 3 for aborted.
    """

    exit_code = ExitCode.STATION


@contextmanager
def _stoppable() -> Iterator[None]:
    """Run a long command under ``stop_on_signals``; a stop that escapes it exits 3.

    The block includes printing the result: once a stop has been delivered and
    the run recorded, further signals cannot cut the report of it short.
    """
    try:
        with stop_on_signals():
            yield
    except KeyboardInterrupt as exc:
        raise CommandAborted(f"aborted: {str(exc) or 'by the operator'}") from exc


def _print_version(wanted: bool) -> None:
    if wanted:
        stdout.print(__version__)
        raise typer.Exit


@app.callback()
def _configure(
    verbose: Annotated[
        int, typer.Option("--verbose", "-v", count=True, metavar=FLAG,
                         help="More log detail on stderr (twice: more).")
    ] = 0,
    _version: Annotated[bool, typer.Option(
        "--version", metavar=FLAG, callback=_print_version, is_eager=True,
        help="Print the station software version and exit.")] = False,
) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(
        level=level,
        format="%(message)s",
        handlers=[RichHandler(console=stderr, show_path=False, rich_tracebacks=False)],
        force=True,
    )
    # canopen logs every SDO at INFO; that is noise for an operator.
    logging.getLogger("canopen").setLevel(max(level, logging.WARNING))
    logging.getLogger("can").setLevel(max(level, logging.WARNING))


def _emit(doc: Any, as_json: bool, human: Any = None) -> None:
    if as_json:
        stdout.out(json.dumps(doc, indent=2), highlight=False)
    else:
        _show(human if human is not None else doc)


def _show(human: Any) -> None:
    """Text as it is (the terminal wraps it); tables and banners wrap to the terminal,
    with the paths in them (``views.path_line``) whole: nothing is cropped at its width."""
    if isinstance(human, str):
        stdout.print(human)
    else:
        stdout.print(human, soft_wrap=False, crop=False)


def _progress_display(enabled: bool) -> Progress:
    """Rich progress on stderr, so stdout stays clean for data."""
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.fields[phase]}"),
        TimeElapsedColumn(),
    )
    return Progress(*columns, console=stderr, transient=True, disable=not enabled)


@contextmanager
def _progress(description: str, enabled: bool = True) -> Iterator[Any]:
    with _progress_display(enabled) as progress:
        task = progress.add_task(description, total=None, phase="")

        def update(done: int, total: int, hold: Hold) -> None:
            progress.update(task, completed=done, total=total, phase=hold.phase.value)

        yield update


def _parse_effects(values: list[str]) -> frozenset[Effect] | None:
    """``--effect`` given: exactly those (``none`` for none); absent: the unit's own."""
    if not values:
        return None
    effects: set[Effect] = set()
    for value in values:
        if value == NO_EFFECTS:
            continue
        try:
            effects.add(Effect(value))
        except ValueError:
            known = ", ".join([e.value for e in Effect] + [NO_EFFECTS])
            raise InputError(f"unknown effect {value!r}; known effects: {known}") from None
    if NO_EFFECTS in values and effects:
        raise InputError(f"--effect {NO_EFFECTS} cannot be combined with other effects")
    return frozenset(effects)


@sim_app.command("record")
def sim_record(
    out: Annotated[
        Path, typer.Argument(metavar="OUT",
                             help="Recording to write (.asc, .blf, .log, .csv or .mf4).")
    ],
    serial: Annotated[
        str, typer.Option("--serial", metavar="SERIAL",
                          help="Serial label of the simulated unit, e.g. SN123.")
    ],
    schedule: Annotated[
        ScheduleName, typer.Option("--schedule", help="What the drive is made to do.")
    ],
    effect: Annotated[
        list[str] | None,
        typer.Option(
            "--effect", metavar="ID",
            help="Physics to switch on (repeatable; 'none' for none): "
            f"{', '.join(e.value for e in Effect)}. Default: the unit's own.",
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option("--seed", metavar="N", help="Seed of the sensor noise and frame losses.")
    ] = 0,
    load: Annotated[
        LoadKind, typer.Option("--load", help="Mechanical load on the motor.")
    ] = LoadKind.DISK,
    loss: Annotated[
        float, typer.Option("--loss", metavar="FRACTION", min=0.0, max=0.5,
                            help="Fraction of frames the logger drops.")
    ] = 0.0,
    noise_ug: Annotated[
        float | None,
        typer.Option(
            "--noise-ug", metavar="µg/√Hz", min=0.0,
            help="Sensor noise density in µg/√Hz (default: the unit's)."
        ),
    ] = None,
    range_g: Annotated[
        int | None,
        typer.Option(
            "--range-g", metavar="G",
            help="Sensor range in g: 2, 4, 8 or 16 (default: the schedule's)."
        ),
    ] = None,
    truth: Annotated[
        Path | None,
        typer.Option("--truth", metavar="FILE",
                     help="Where to write the truth file (never beside the recording)."),
    ] = None,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Record a run of the simulated bench, with its truth in a separate file."""
    as_json = _wants_json(output, as_json)
    unit, effects = parse_serial(serial), _parse_effects(effect or [])  # before the imports
    from station.sim.record import SimRecordRequest, record_simulation  # noqa: PLC0415 - the simulator

    request = SimRecordRequest(
        out=out,
        serial=unit,
        schedule=schedule,
        effects=effects,
        seed=seed,
        load=load,
        loss=loss,
        noise_density_ug=noise_ug,
        truth=truth,
        range_g=range_g,
    )
    with _stoppable():
        with _progress(f"recording {request.serial}", enabled=not as_json) as update:
            result = record_simulation(request, on_progress=update)
        doc = result.as_dict()
        _emit(doc, as_json, human=_table("simulated recording", doc))


@sim_app.command("unit")
def sim_unit(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the simulated unit, e.g. SN123.")],
    effect: Annotated[
        list[str] | None,
        typer.Option(
            "--effect", metavar="ID",
            help="Override the unit's concealed effects (repeatable; 'none' for "
            f"none): {', '.join(e.value for e in Effect)}."
        ),
    ] = None,
    load: Annotated[
        LoadKind, typer.Option("--load", help="Mechanical load on the motor.")
    ] = LoadKind.DISK,
    amplitude_mA: Annotated[
        float, typer.Option("--amplitude-mA", metavar="mA", help="Operating current I.", min=1.0)
    ] = 1000.0,
    electrical_hz: Annotated[
        float, typer.Option("--electrical-hz", metavar="Hz", help="Operating electrical frequency.")
    ] = 20.0,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Reveal a simulated unit: its concealed imperfections and its optimal trims."""
    as_json = _wants_json(output, as_json)
    unit, effects = parse_serial(serial), _parse_effects(effect or [])  # before the imports
    from station.sim.record import describe_unit  # noqa: PLC0415 - the simulator

    doc = describe_unit(
        unit,
        load=load,
        effects=effects,
        amplitude_mA=amplitude_mA,
        electrical_hz=electrical_hz,
    )
    _emit(doc, as_json, human=_unit_table(doc))


def _unit_table(doc: dict[str, Any]) -> Table:
    """What a technician asks of a simulated unit; the whole truth is in ``--json``."""
    point = doc["operating_point"]
    amp = doc["unit"]["amplifier"]
    table = Table(title=f"simulated unit {doc['serial']} ({doc['load']} load)", show_header=False)
    table.add_column("key", style="bold")
    table.add_column("value")
    table.add_row(
        f"optimal trims at {point['amplitude_mA']:.0f} mA, {point['electrical_hz']:g} Hz",
        trims_text(doc["optimal_trims"], decimals=1),
    )
    table.add_row(
        "amplifier",
        f"offsets {amp['offset_a_mA']:+.1f} / {amp['offset_b_mA']:+.1f} mA, "
        f"gain errors {100 * amp['gain_error_a']:+.2f} / {100 * amp['gain_error_b']:+.2f} %",
    )
    effects = [e["id"] for e in doc["effects"]]
    table.add_row("concealed effects", ", ".join(effects) if effects else "none")
    table.add_row("stored in its EEPROM", trims_text(doc["stored_trims"], absent="none stored"))
    return table


def _table(title: str, doc: dict[str, Any]) -> Table:
    table = Table(title=title, show_header=False)
    table.add_column("key", style="bold")
    table.add_column("value")
    for key, value in doc.items():
        text = json.dumps(value) if isinstance(value, dict | list) else str(value)
        table.add_row(key, text)
    return table


@app.command("analyze")
def analyze_command(
    recording: Annotated[
        Path, typer.Argument(metavar="RECORDING",
                             help="CAN log of a run (ICD.md §5), its .json metadata beside it.")
    ],
    method: Annotated[
        MethodChoice,
        typer.Option(
            "--method",
            help="auto: phase-coherent when the data allow, else the paper's parabolas.",
        ),
    ] = MethodChoice.AUTO,
    settle_periods: Annotated[
        float | None,
        typer.Option(
            "--settle-periods", metavar="PERIODS",
            help="Electrical periods dropped after each change (default: judged from the data).",
            min=0.0,
        ),
    ] = None,
    report: Annotated[bool, typer.Option(
        "--report", metavar=FLAG,
        help="Also write the HTML calibration report beside the recording.")] = False,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Estimate the trims from a recording, off the bench."""
    as_json = _wants_json(output, as_json)
    require_recording(recording)  # a typo answers before the analysis stack loads
    from station.analysis.pipeline import AnalysisOptions, analyze  # noqa: PLC0415 - scipy
    from station.analysis.reader import read_recording  # noqa: PLC0415 - python-can, asammdf
    from station.analysis.report import analysis_dict  # noqa: PLC0415 - scipy

    with _progress(f"analysing {recording.name}", enabled=not as_json):
        timeline = read_recording(recording)
        result = analyze(timeline, AnalysisOptions(method=method, settle_periods=settle_periods))
    doc = analysis_dict(result, str(recording))
    if report:
        from station.reports import report_recording  # noqa: PLC0415 - matplotlib

        with _step_display("writing the report", enabled=not as_json):
            doc["report"] = str(report_recording(recording, result).path)
    _emit(doc, as_json, human=_analysis_tables(doc))


def _analysis_tables(doc: dict[str, Any]) -> Group:
    """Trims with uncertainties, then one row per trim point, as a motion engineer reads them."""
    head = Table(
        title=f"{doc['serial']}: trims by the {doc['method']} method from {doc['segments']} "
        f"segments at {doc['condition']['amplitude_mA']} mA, "
        f"{doc['condition']['electrical_hz']:.2f} Hz"
    )
    head.add_column("trim")
    head.add_column("value", justify="right")
    head.add_column("± (1σ)", justify="right")
    for key, value in doc["trims"].items():
        head.add_row(key, f"{value:.1f}", f"{doc['uncertainty'][key]:.1f}")
    points = Table(title="trim points (offsets mA, |H| m/s², phase degrees)")
    for column in ("off A", "off B", "gain A", "gain B", "|H1|", "∠H1", "|H2|", "∠H2",
                   "lost", "clip"):
        points.add_column(column, justify="right", no_wrap=True)
    for p in doc["conditions"][0]["points"]:
        t = p["trims"]
        points.add_row(
            f"{t['offset_a_mA']:.0f}", f"{t['offset_b_mA']:.0f}", f"{t['gain_a']:.0f}",
            f"{t['gain_b']:.0f}", f"{p['h1']['magnitude']:.3f}", f"{p['h1']['phase_deg']:.0f}",
            f"{p['h2']['magnitude']:.3f}", f"{p['h2']['phase_deg']:.0f}",
            str(p["samples_missing"]), str(p["samples_saturated"]),
        )
    notes: list[Any] = [Text(f"warning: {w}", style="yellow") for w in doc["warnings"]]
    losses = doc["losses"]
    notes.append(
        Text(
            f"{doc['samples']} samples; {losses['syncs_missing']} SYNC and "
            f"{losses['sensor_samples_lost']} sensor samples missing, "
            f"{losses['saturated_samples']} clipped; {len(doc['rejected'])} stretches rejected"
        )
    )
    if doc.get("report"):
        notes.append(path_line("report", doc["report"]))
    return Group(head, points, *notes)


NoReportOption = Annotated[bool, typer.Option("--no-report", help="Write no HTML report.",
                                              metavar=FLAG)]


@app.command("diagnose")
def diagnose_command(
    recording: Annotated[
        Path, typer.Argument(metavar="RECORDING",
                             help="CAN log of a run (ICD.md §5), its .json metadata beside it.")
    ],
    report: Annotated[
        Path | None,
        typer.Option("--report", metavar="FILE",
                     help="HTML report (default: beside the recording)."),
    ] = None,
    no_report: NoReportOption = False,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Compare the nominal model with a recording: locate, name and model what is missing.

    Exit 0 whether or not a mismatch is found (it is a finding, not a failure);
    2 when the recording cannot be read or holds too few conditions.
    """
    as_json = _wants_json(output, as_json)
    require_recording(recording)
    from station.characterize import diagnose_recording  # noqa: PLC0415 - the diagnosis

    with _step_display(f"diagnosing {recording.name}", enabled=not as_json) as step:
        result = diagnose_recording(recording, report=report, write_report=not no_report,
                                    progress=step)
    doc = result.as_dict()
    _emit(doc, as_json, human=diagnosis_view(doc))


@app.command("characterize")
def characterize_command(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the unit on the fixture.")],
    db: DbOption = None,
    bench: BenchOption = None,
    operator: OperatorOption = None,
    recipe: RecipeOption = None,
    no_report: NoReportOption = False,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Run the characterization schedule (speeds both ways, three currents, small trim
    steps) around the unit's own trims, record it beside the database, and diagnose it."""
    as_json = _wants_json(output, as_json)
    _checked(serial, recipe)
    from station.characterize import characterize  # noqa: PLC0415 - the diagnosis

    station = _station(db, bench, operator)

    def on_step(text: str) -> None:
        if not as_json:
            stderr.print(f"[bold]characterize[/] {text}", highlight=False)

    with _stoppable():
        with _progress(f"characterizing {serial}", enabled=not as_json) as update:
            result = characterize(station, serial, recipe_name=recipe, on_step=on_step,
                                  on_progress=update, write_report=not no_report)
        doc = result.as_dict()
        _emit(doc, as_json, human=diagnosis_view(doc))


@contextmanager
def _step_display(description: str, enabled: bool) -> Iterator[Any]:
    with _progress_display(enabled) as progress:
        task = progress.add_task(description, total=None, phase="")

        def step(text: str) -> None:
            progress.update(task, phase=text)

        yield step


DbOption = Annotated[
    str | None,
    typer.Option(
        "--db", metavar="FILE|URL",
        help="Results database: a SQLite file, or a line's postgresql://user@host/db "
        "(default: $STATION_DB, else $STATION_HOME/station.db)."
    ),
]
BenchOption = Annotated[
    str | None,
    typer.Option("--bench", metavar="NAME|FILE",
                 help="'sim' (default, also $STATION_BENCH) or a bench file (TOML)."),
]
OperatorOption = Annotated[
    str | None,
    typer.Option("--operator", metavar="NAME",
                 help="Who runs the station (default: $STATION_OPERATOR or login)."),
]
RecipeOption = Annotated[
    str | None,
    typer.Option("--recipe", metavar="NAME|FILE",
                 help="Recipe name (recipes/NAME.toml) or path; default: 'default'."),
]


def _checked(serial: str, recipe: str | None = None) -> None:
    """Refuse a malformed serial or a bad recipe before the procedure's stack is imported:
    the service checks both again, but a typo should not wait for scipy to load."""
    parse_serial(serial)
    if recipe is not None:
        from station.recipes import load_recipe  # noqa: PLC0415 - recipe checks

        load_recipe(recipe)


def _station(db: str | None, bench: str | None, operator: str | None) -> Station:
    check_bench(bench)
    from station.benches import load_bench  # noqa: PLC0415 - python-can, canopen, drivers
    from station.service import Station  # noqa: PLC0415 - the procedure

    return Station(database_path(db), load_bench(bench), operator or default_operator())


class _OperatorDisplay:
    """Rich progress on stderr: each step as a line ("step n of 9" and the time the run
    has taken), the current hold batch as a bar."""

    def __init__(self, progress: Progress, enabled: bool) -> None:
        self._progress = progress
        self._task = progress.add_task("", total=None, phase="")
        self._enabled = enabled
        self._started = time_module.monotonic()

    def step(self, step: Step, detail: str) -> None:
        if self._enabled:
            elapsed = time_module.monotonic() - self._started
            where = f"step {step.number} of {STEPS}" if step.number else "done"
            self._progress.console.print(
                f"[dim]{where:>12} {elapsed:6.1f} s[/]  [bold]{escape(step.value)}[/] "
                f"{escape(detail)}", highlight=False)
        self._progress.update(self._task, description=step.value, completed=0, total=None,
                              phase=detail)

    def progress(self, done: int, total: int) -> None:
        self._progress.update(self._task, completed=done, total=total)


@contextmanager
def _operator_display(enabled: bool) -> Iterator[_OperatorDisplay]:
    with _progress_display(enabled) as progress:
        yield _OperatorDisplay(progress, enabled)


def _finish_run(station: Station, result: Calibration, as_json: bool, write_report: bool) -> int:
    from station.run_report import calibration_dict  # noqa: PLC0415 - the service

    doc = calibration_dict(result)
    if write_report:
        from station.reports import report_finished  # noqa: PLC0415 - matplotlib, scipy

        with _step_display("writing the calibration report", enabled=not as_json):
            written = report_finished(station.db_path, result.run)
        doc["report"] = str(written.path) if written is not None else None
    _emit(doc, as_json, human=run_view(doc))
    verdict = result.run.verdict or Verdict.ERROR
    return int(verdict.exit_code)


@app.command("calibrate")
def calibrate_command(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the unit on the bench: SN123.")],
    recipe: RecipeOption = None,
    bench: BenchOption = None,
    db: DbOption = None,
    operator: OperatorOption = None,
    no_report: NoReportOption = False,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> int:
    """Calibrate one unit: sweep, estimate, store, verify, record (exit 0 pass, 1 fail, 3 error).

    The run's HTML report goes beside its recording (``station report`` draws it again)."""
    as_json = _wants_json(output, as_json)
    _checked(serial, recipe)
    station = _station(db, bench, operator)
    from station.service import calibrate  # noqa: PLC0415 - the procedure

    with _stoppable():
        with _operator_display(not as_json) as display:
            result = calibrate(station, serial, recipe, observer=display)
        return _finish_run(station, result, as_json, not no_report)


@app.command("recalibrate")
def recalibrate_command(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the unit, e.g. SN123.")],
    reason: Annotated[
        str, typer.Option("--reason", metavar="TEXT",
                          help="Why the unit is recalibrated (recorded).")
    ],
    force: Annotated[
        bool, typer.Option("--force", metavar=FLAG,
                           help="Calibrate even though the unit has no record here.")
    ] = False,
    recipe: Annotated[
        str | None,
        typer.Option("--recipe", metavar="NAME|FILE",
                     help="Recipe name or path; default: the unit's last one."),
    ] = None,
    bench: BenchOption = None,
    db: DbOption = None,
    operator: OperatorOption = None,
    no_report: NoReportOption = False,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> int:
    """Field service: recalibrate a unit and show how far its trims drifted."""
    as_json = _wants_json(output, as_json)
    _checked(serial, recipe)
    station = _station(db, bench, operator)
    from station.service import recalibrate  # noqa: PLC0415 - the procedure

    with _stoppable():
        with _operator_display(not as_json) as display:
            result = recalibrate(station, serial, reason, recipe_name=recipe, force=force,
                                 observer=display)
        return _finish_run(station, result, as_json, not no_report)


@app.command("verify")
def verify_command(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the unit, e.g. SN123.")],
    bench: BenchOption = None,
    db: DbOption = None,
    operator: OperatorOption = None,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> int:
    """Compare the trims stored in the drive with the last ones recorded (exit 0 match, 1 not)."""
    as_json = _wants_json(output, as_json)
    _checked(serial)
    from station.run_report import verify_dict  # noqa: PLC0415 - the service
    from station.service import verify  # noqa: PLC0415 - the procedure

    result = verify(_station(db, bench, operator), serial)
    doc = verify_dict(result)
    _emit(doc, as_json, human=verify_view(doc))
    return int(ExitCode.OK if result.match else ExitCode.FAILED_LIMIT)


def _print_runs(runs: Sequence[Run], output: OutputFormat, title: str, *,
                one_unit: bool = False) -> None:
    from station.run_report import CSV_COLUMNS, run_csv_row, run_dict  # noqa: PLC0415 - the service

    docs = [run_dict(r) for r in runs]
    if output is OutputFormat.JSON:
        _emit(docs, True)
    elif output is OutputFormat.CSV:
        writer = csv.writer(sys.stdout, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        writer.writerows(run_csv_row(doc) for doc in docs)
    else:
        _show(runs_table(docs, title, one_unit=one_unit))


def _output(output: OutputFormat, as_json: bool) -> OutputFormat:
    """``--json`` is the short form of ``--format json``; asked for with another format it
    is refused rather than one of them silently winning."""
    if as_json and output not in (OutputFormat.TABLE, OutputFormat.JSON):
        raise InputError(f"--json is --format json: give --json or --format {output.value}, "
                         "not both")
    return OutputFormat.JSON if as_json else output


StationFilter = Annotated[int | None, typer.Option("--station", metavar="ID", help="Station ID.")]


@app.command("history")
def history_command(
    serial: Annotated[str, typer.Argument(metavar="SERIAL",
    help="Serial label of the unit, e.g. SN123.")],
    station: StationFilter = None,
    db: DbOption = None,
    output: FormatOption = OutputFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Every run of one unit, oldest first (on a line's database: at every station, or
    at one with --station)."""
    chosen = _output(output, as_json)
    target = database_path(db)
    from station.records import history  # noqa: PLC0415 - the stores

    runs = history(target, serial, station_id=station)
    if not runs and chosen is OutputFormat.TABLE:
        # An empty table reads like a display fault; machines still get [] or a header.
        at = f" at station {station}" if station is not None else ""
        stdout.print(f"no runs of {parse_serial(serial)}{at} are recorded in {describe(target)}")
        return
    _print_runs(runs, chosen, f"history of {parse_serial(serial)}", one_unit=True)


def _moment(text: str | None, *, end_of_day: bool) -> datetime | None:
    """ISO 8601 date or date-time; naive times are UTC; a bare 'until' date includes its day."""
    if text is None:
        return None
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        raise InputError(f"{text!r} is not an ISO 8601 date or date-time") from None
    if end_of_day and len(text) == 10:
        moment = datetime.combine(moment.date(), time.max)
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment.astimezone(UTC)


SinceOption = Annotated[
    str | None, typer.Option("--since", metavar="DATE",
                             help="Runs started at or after (ISO 8601, UTC if naive).")
]
UntilOption = Annotated[
    str | None, typer.Option("--until", metavar="DATE",
                             help="Runs started at or before (a date includes its day).")
]
RecipeFilter = Annotated[str | None, typer.Option("--recipe", metavar="NAME",
                                                  help="Recipe name.")]
VerdictFilter = Annotated[Verdict | None, typer.Option("--verdict", help="Verdict.")]
SerialFilter = Annotated[str | None, typer.Option("--serial", metavar="SERIAL", help="One unit.")]
LimitOption = Annotated[
    int | None, typer.Option("--limit", metavar="N", help="Only the newest N runs.", min=0)
]


def _filter(since: str | None, until: str | None, recipe: str | None, verdict: Verdict | None,
            station: int | None, serial: str | None, limit: int | None) -> RunFilter:
    from station.rows import RunFilter  # noqa: PLC0415 - the stores' rows

    return RunFilter(
        serial=parse_serial(serial).label if serial is not None else None,
        since=_moment(since, end_of_day=False),
        until=_moment(until, end_of_day=True),
        recipe=recipe,
        verdict=verdict,
        station_id=station,
        limit=limit,
    )


@app.command("query")
def query_command(
    since: SinceOption = None,
    until: UntilOption = None,
    recipe: RecipeFilter = None,
    verdict: VerdictFilter = None,
    station: StationFilter = None,
    serial: SerialFilter = None,
    limit: LimitOption = None,
    db: DbOption = None,
    output: FormatOption = OutputFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Runs across units, filtered by date, recipe, verdict, station; oldest first."""
    run_filter = _filter(since, until, recipe, verdict, station, serial, limit)
    from station.records import query  # noqa: PLC0415 - the stores

    _print_runs(query(database_path(db), run_filter), _output(output, as_json), "runs")


@app.command("stats")
def stats_command(
    since: SinceOption = None,
    until: UntilOption = None,
    recipe: RecipeFilter = None,
    station: StationFilter = None,
    db: DbOption = None,
    output: FormatOption = OutputFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Per recipe version: mean, standard deviation and Cpk of trims and residual ripple."""
    chosen = _output(output, as_json)
    run_filter = _filter(since, until, recipe, None, station, None, None)
    from station.records import statistics  # noqa: PLC0415 - the stores
    from station.run_report import STATS_CSV_COLUMNS, stats_csv_rows, stats_dict  # noqa: PLC0415 - the service

    docs = [stats_dict(s) for s in statistics(database_path(db), run_filter)]
    if chosen is OutputFormat.CSV:
        # One row per recipe version and quantity: what a spreadsheet pivots on.
        writer = csv.writer(sys.stdout, lineterminator="\n")
        writer.writerow(STATS_CSV_COLUMNS)
        writer.writerows(stats_csv_rows(docs))
        return
    _emit(docs, chosen is OutputFormat.JSON, human=stats_view(docs))


@app.command("sync")
def sync_command(
    db: DbOption = None,
    list_only: Annotated[bool, typer.Option(
        "--list", metavar=FLAG,
        help="Only show what waits in the spool; connect to nothing.")] = False,
    source: Annotated[Path | None, typer.Option(
        "--from", help="Forward this SQLite database's runs instead of the spool: a "
        "station's history from before it joined the line.", metavar="FILE")] = None,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Forward the runs this station spooled while its line's database was out of reach,
    oldest first, each once; show what was forwarded and what still waits."""
    as_json = _wants_json(output, as_json)
    from station.records import sync  # noqa: PLC0415 - the stores
    from station.run_report import run_dict  # noqa: PLC0415 - the service

    report = sync(database_path(db), list_only=list_only, source=source)
    waiting = [run_dict(r) for r in report.waiting]
    if as_json:
        _emit({"line": report.line,
               "forwarded": [{**run_dict(f.run), "line_run_id": f.line_run_id, "new": f.new}
                             for f in report.forwarded],
               "waiting": waiting}, True)
        return
    if report.forwarded:
        # Numbered as the line now numbers them: the spool's numbers mean nothing there.
        _show(runs_table([run_dict(replace(f.run, run_id=f.line_run_id))
                          for f in report.forwarded], f"forwarded to {report.line}"))
    where = str(source) if source is not None else "this station's spool"
    _show(runs_table(waiting, f"waiting in {where}") if waiting
                 else f"nothing waits in {where} for {report.line}")


@app.command("report")
def report_command(
    key: Annotated[str, typer.Argument(
        metavar="RUN_ID|SERIAL",
        help="A run's ID, or a unit's serial for its newest calibration.")],
    out: Annotated[Path | None, typer.Option(
        "--out", metavar="FILE",
        help="Where to write the page (default: beside the run's recording).")] = None,
    db: DbOption = None,
    output: DocFormatOption = DocumentFormat.TABLE,
    as_json: JsonOption = False,
) -> None:
    """Write one run's HTML calibration report: the paper's figures for the unit, its
    trims with σ, every limit, its history and what the recording lost."""
    as_json = _wants_json(output, as_json)
    from station.reports import report  # noqa: PLC0415 - matplotlib, scipy

    with _step_display(f"drawing the report of {key}", enabled=not as_json):
        written = report(database_path(db), key, out)
    doc = written.as_dict()
    if as_json:
        _emit(doc, True)
        return
    for note in written.notes:
        stderr.print(f"[yellow]note:[/] {escape(note)}", highlight=False)
    _show(str(written.path))


RECIPE_COLUMNS = ("name", "version", "method", "description", "electrical_hz", "amplitude_mA",
                  "sha256")


@app.command("recipes")
def recipes_command(output: FormatOption = OutputFormat.TABLE,
                    as_json: JsonOption = False) -> None:
    """The shipped recipes: name, version, method, operating point."""
    chosen = _output(output, as_json)
    from station.recipes import available_recipes, load_recipe  # noqa: PLC0415 - recipe checks

    docs: list[dict[str, Any]] = []
    for name in available_recipes():
        r = load_recipe(name)
        docs.append({"name": r.name, "version": r.version, "method": r.method,
                     "description": r.description, "electrical_hz": r.motion.electrical_hz,
                     "amplitude_mA": r.motion.amplitude_mA, "sha256": r.sha256})
    table = Table(title="recipes")
    for column in ("name", "version", "method", "operating point", "description"):
        table.add_column(column)
    for d in docs:
        table.add_row(d["name"], d["version"], d["method"],
                      f"{d['amplitude_mA']} mA, {d['electrical_hz']:g} Hz", d["description"])
    if chosen is OutputFormat.CSV:
        writer = csv.writer(sys.stdout, lineterminator="\n")
        writer.writerow(RECIPE_COLUMNS)
        writer.writerows([d[k] for k in RECIPE_COLUMNS] for d in docs)
        return
    _emit(docs, chosen is OutputFormat.JSON, human=table)


@app.command("version")
def version() -> None:
    """Print the station software version."""
    stdout.print(__version__)


_VERBOSE = re.compile(r"-v+|--verbose")
_FLAGS = frozenset({"--json", "--force", "--list", "--no-report", "--report", "--help",
                    "--version"})
"""Options that take no value: a ``-v`` after one of them is verbosity, not its value."""


def _verbosity_first(args: list[str]) -> list[str]:
    """``-v`` where an operator types it: ``station calibrate SN123 -v`` as well as
    ``station -v calibrate SN123`` (typer reads the group's options only before the
    command). A ``-v`` that is another option's value, or after ``--``, stays put."""
    moved: list[str] = []
    kept: list[str] = []
    for i, arg in enumerate(args):
        if arg == "--":
            kept.extend(args[i:])
            break
        previous = args[i - 1] if i else ""
        takes_value = previous.startswith("--") and "=" not in previous and (
            previous not in _FLAGS)
        if _VERBOSE.fullmatch(arg) and not takes_value:
            moved.append(arg)
        else:
            kept.append(arg)
    return moved + kept


def main() -> None:
    """Entry point: map every failure to CLI.md's exit codes."""
    try:
        result = app(args=_verbosity_first(sys.argv[1:]), prog_name="station",
                     standalone_mode=False)
    except typer.Abort:
        stderr.print("[bold red]aborted[/]")
        sys.exit(ExitCode.STATION)
    except typer.TyperException as exc:
        # Usage errors (bad option, bad value, missing argument), shown as click shows them.
        exc.show(file=sys.stderr)  # type: ignore[attr-defined]
        sys.exit(ExitCode.USAGE)
    except KeyboardInterrupt:
        stderr.print("[bold red]aborted[/]")
        sys.exit(ExitCode.STATION)
    except CommandAborted as exc:
        stderr.print(f"[bold red]{escape(str(exc))}[/]", highlight=False)
        sys.exit(exc.exit_code)
    except StationError as exc:
        stderr.print(f"[bold red]error:[/] {exc}", highlight=False)
        sys.exit(exc.exit_code)
    if result == _TYPER_INTERRUPTED:
        # Ctrl-C in a short command (QA, verify) that runs without stop_on_signals.
        stderr.print("[bold red]aborted[/]")
        sys.exit(ExitCode.STATION)
    sys.exit(result if isinstance(result, int) else ExitCode.OK)


if __name__ == "__main__":
    main()
