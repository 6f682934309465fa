"""What people see: rich tables and the operator's banner, built from plain data.

The CLI prints these on stdout when ``--json`` is not given. They read the
same documents the JSON carries (``run_report.run_dict``), so what a person
sees and what a script reads cannot disagree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from rich import box
from rich.align import Align
from rich.console import Group, RenderableType
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from station.qa import CPK_MIN_VALUES

_VERDICT_STYLE = {"pass": "bold white on green", "fail": "bold white on red",
                  "error": "bold white on dark_orange3", "aborted": "bold white on grey30"}


def trims_text(trims: dict[str, float] | None, *, decimals: int = 0, absent: str = "—") -> str:
    """Trims for people; stored trims are whole units, estimates and optima are not."""
    if trims is None:
        return absent
    d = decimals
    return (f"A {trims['offset_a_mA']:+.{d}f} mA, B {trims['offset_b_mA']:+.{d}f} mA, "
            f"gains {trims['gain_a']:.{d}f}/{trims['gain_b']:.{d}f}")


def _ripple_text(ripple: dict[str, float] | None) -> str:
    if ripple is None:
        return "—"
    return f"H1 {ripple['h1']:.4f}, H2 {ripple['h2']:.4f} m/s²"


def _limit_text(check: dict[str, Any]) -> str:
    value = check["value"]
    note = f" ({check['note']})" if check["note"] else ""
    if value is None:
        return (check["note"] or "—") if check["passed"] is not False else f"no{note}"
    bound = " .. ".join(
        "" if b is None else f"{b:g}" for b in (check["low"], check["high"])
    ).strip(" .")
    unit = f" {check['unit']}" if check["unit"] and check["unit"] != "1/10000" else ""
    if abs(value) >= 1000:
        shown = f"{value:.0f}"
    elif 0.99 <= abs(value) < 1:  # R²: "1" would hide what the limit judges
        shown = f"{value:.6f}"
    else:
        shown = f"{value:.4g}"
    return f"{shown}{unit}, limit {bound or 'none'}{note}"


def path_line(label: str, path: str | None) -> Text:
    """A path on a line of its own, whole: never cut with "…" nor broken by a newline,
    so an operator can copy it (the terminal wraps it; printed with ``crop=False``)."""
    return Text.assemble((f"{label}: ", "bold"), path or "—", no_wrap=True, overflow="ignore")


def banner(verdict: str | None, serial: str, reason: str | None,
           next_step: str | None = None) -> Panel:
    """The one thing an operator must not misread: big, coloured, with the whole reason
    (wrapped, never cut) and what to do next."""
    word = (verdict or "unknown").upper()
    text = Text(f"  {serial}: {word}  ", style=_VERDICT_STYLE.get(verdict or "", "bold"))
    body: list[RenderableType] = [Align.center(text)]
    if reason and verdict != "pass":
        body.append(Text(reason, justify="center", overflow="fold"))
    if next_step:
        body.append(Text.assemble(("next: ", "bold"), next_step, overflow="fold"))
    return Panel(Group(*body), expand=True)


def run_view(doc: dict[str, Any]) -> Group:
    """A run's result for the operator: what changed, how quiet it got, and the verdict."""
    table = Table(title=f"run {doc['run_id']}: {doc['serial']} ({doc['kind']}, recipe "
                        f"{doc['recipe']} {doc['recipe_version']})", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value", overflow="fold")
    table.add_row("trims before", trims_text(doc["trims_before"]))
    if "previous_trims" in doc:
        table.add_row("previous calibration", trims_text(doc["previous_trims"]))
    sigma = doc["uncertainty"]
    stored = trims_text(doc["trims"]) if doc["trims"] is not None else "not stored"
    if sigma is not None:
        stored += (f"  (1σ {sigma['offset_a_mA']:.2f}/{sigma['offset_b_mA']:.2f} mA, "
                   f"{sigma['gain_a']:.1f})")
    table.add_row("trims stored", stored)
    if doc.get("drift") is not None:
        table.add_row("drift since previous", trims_text(doc["drift"]))
    table.add_row("ripple before", _ripple_text(doc["before"]))
    table.add_row("ripple after", _ripple_text(doc["after"]))
    for check in doc["limits"]:
        mark = {True: "[green]ok[/]", False: "[red]FAILED[/]", None: "[dim]n/a[/]"}[check["passed"]]
        table.add_row(check["name"], f"{mark} {_limit_text(check)}")
    if doc["motion_s"] is not None:
        table.add_row("motion time", f"{doc['motion_s']:.1f} s")
    parts: list[RenderableType] = [table, path_line("recording", doc["recording"])]
    if doc.get("report"):
        parts.append(path_line("report", doc["report"]))
    parts.extend(Text(f"warning: {w}", style="yellow", overflow="fold") for w in doc["warnings"])
    parts.append(banner(doc["verdict"], doc["serial"], doc["reason"], doc.get("next_step")))
    return Group(*parts)


def _compact_trims(trims: dict[str, float] | None) -> str:
    """Two short lines (offsets, then gains): a table of runs must fit a terminal."""
    if trims is None:
        return "—"
    return (f"{trims['offset_a_mA']:+.0f}/{trims['offset_b_mA']:+.0f}\n"
            f"{trims['gain_a']:.0f}/{trims['gain_b']:.0f}")


def runs_table(docs: Sequence[dict[str, Any]], title: str, *, one_unit: bool = False) -> Table:
    """History and query results, one line per run, as QA scans them (80 columns): what
    kind of run it was and why it ended as it did, in the run's own words."""
    table = Table(title=title, box=box.SIMPLE_HEAD, padding=(0, 1, 0, 0), pad_edge=False,
                  caption="verdict over cal (production) or recal (field service); trims: "
                  "offsets A/B (mA) over gains A/B; H1 over H2 after (m/s²)")
    columns = ["run", "started UTC", "verdict", "recipe", "stn", "trims", "H after", "reason"]
    for column in columns:
        # Reasons and limit names are folded, never cut: the reason is what QA reads.
        table.add_column(column, no_wrap=column != "reason", overflow="fold",
                         ratio=1 if column == "reason" else None,
                         min_width=12 if column == "reason" else None)
    for d in docs:
        after = d["after"]
        cells = {
            # Across units, each run's serial under its number.
            "run": str(d["run_id"]) if one_unit else f"{d['run_id']}\n{d['serial']}",
            "started UTC": d["started_at"][:16].replace("T", "\n"),
            # Over the verdict, the run's kind: production or field service.
            "verdict": f"{d['verdict'] or 'running'}\n"
                       f"{'recal' if d['kind'] == 'recalibrate' else 'cal'}",
            "recipe": f"{d['recipe']}\n{d['recipe_version']}",
            "stn": str(d["station"]),
            "trims": _compact_trims(d["trims"]),
            "H after": "—" if after is None else f"{after['h1']:.4f}\n{after['h2']:.4f}",
            "reason": d["reason"] or "—",
        }
        table.add_row(*(cells[c] for c in columns))
    return table


def verify_view(doc: dict[str, Any]) -> Group:
    table = Table(title=f"verify {doc['serial']}", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("trims in the drive", trims_text(doc["drive_trims"]))
    recorded = doc["recorded_trims"]
    source = f" (run {doc['recorded_run_id']}, {doc['recorded_verdict']})" if recorded else ""
    table.add_row("trims recorded", trims_text(recorded) + source)
    record = doc["calibration_record"]
    table.add_row("0x2101 in the drive", f"calibrated at {record['calibrated_at'] or 'never'}, "
                  f"station {record['station_id']}, count {record['count']}")
    # A unit never calibrated has nothing to mismatch: it says so, and what to do.
    word = "match" if doc["match"] else "mismatch" if recorded else "no record"
    style = "bold white on green" if doc["match"] else "bold white on red"
    if recorded is None:
        table.add_row("next", f"no calibration of {doc['serial']} is recorded in this "
                      f"database: run `station calibrate {doc['serial']}`")
    return Group(table, Panel(Align.center(Text(f"  {doc['serial']}: {word.upper()}  ",
                                                style=style))))


def _number(value: float | None, digits: int = 2) -> str:
    if value is None or not math.isfinite(value):
        return "—"
    return f"{value:.{digits}f}"


def stats_view(docs: Sequence[dict[str, Any]]) -> Group:
    """Per recipe version: counts by verdict, then capability of each quantity."""
    tables: list[RenderableType] = []
    for d in docs:
        counts = ", ".join(f"{k} {v}" for k, v in d["verdicts"].items() if v)
        table = Table(title=f"recipe {d['recipe']} {d['recipe_version']} "
                            f"({d['recipe_sha256'][:12]}): {d['runs']} runs: {counts}")
        for column in ("quantity", "n", "mean", "std", "low", "high", "Cpk"):
            table.add_column(column, justify="left" if column == "quantity" else "right",
                             no_wrap=column != "quantity")
        rough = False
        for name, c in d["quantities"].items():
            cpk = _number(c["cpk"])
            if c.get("cpk_sigma") is not None:
                cpk += f" ± {c['cpk_sigma']:.2f}"
            if c.get("cpk_rough"):
                cpk, rough = cpk + " *", True
            table.add_row(name, str(c["n"]), _number(c["mean"], 4), _number(c["std"], 4),
                          _number(c["low"], 1), _number(c["high"], 3), cpk)
        if rough:
            table.caption = (f"* Cpk from fewer than {CPK_MIN_VALUES} runs: a rough guide, "
                             "not evidence of capability (± its standard error)")
        tables.append(table)
    if not tables:
        tables.append(Text("no runs match"))
    return Group(*tables)


def _flat(value: Any, prefix: str = "") -> list[str]:
    """Nested parameter documents as ``path=value`` lines, never a Python repr."""
    if isinstance(value, dict):
        return [line for k, v in value.items()
                for line in _flat(v, f"{prefix}.{k}" if prefix else str(k))]
    if isinstance(value, list | tuple):
        return [line for i, v in enumerate(value) for line in _flat(v, f"{prefix}[{i}]")]
    if isinstance(value, float):
        return [f"{prefix}={value:.4g}"]
    return [f"{prefix}={value}"]


def _parameter_text(parameters: dict[str, Any]) -> str:
    """Effect parameters one per line, nested entries by their path."""
    return "\n".join(_flat(parameters))


def diagnosis_view(doc: dict[str, Any]) -> Group:
    """What a motion engineer reads first: the verdict, the effects, the fit, where it fails."""
    fit = doc["fit"]
    if doc["mismatch"]:
        said = "mismatch with the nominal model"
    elif doc["located"]:
        said = (f"no mismatch that matters: {len(doc['located'])} disagreement(s) located, "
                "none explained better than noise on held-out conditions")
    else:
        said = "no mismatch with the nominal model"
    head = Text(
        f"{doc['serial']}: {said}; held-out residual {fit['before']:.4f} → "
        f"{fit['after']:.4f} m/s² RMS "
        f"(χ² {fit['before_chi2']:.0f} → {fit['after_chi2']:.0f}, "
        f"{len(doc['conditions'])} conditions, {doc['segments']} segments)",
        style="bold",
    )
    effects = Table(title="effects named (strongest first)", box=box.SIMPLE)
    for column in ("effect", "held-out χ² gain", "parameters"):
        effects.add_column(column, overflow="fold")
    for e in doc["effects"]:
        name = e["id"]
        if e.get("cannot_separate_from"):
            name += "\nor " + ", ".join(e["cannot_separate_from"]) + " (cannot separate)"
        effects.add_row(name, f"{e['held_out_chi2_gain']:.0f}", _parameter_text(e["parameters"]))
    located = Table(title="where the nominal model fails (strongest 10)", box=box.SIMPLE)
    for column in ("where", "χ²/dof", "confidence"):
        located.add_column(column, overflow="fold")
    # What no id explains comes first: it is what the engineer must look at.
    for loc in sorted(doc["located"], key=lambda item: item["kind"] == "harmonic")[:10]:
        if "order" in loc:
            where = (f"order {loc['order']} at {loc['amplitude_mA']} mA, "
                     f"{loc['electrical_hz']:+.1f} Hz")
            if loc["kind"] == "unexplained":
                where += " (left unexplained)"
            elif loc["kind"] == "sensor_axis":
                where += f" (on the sensor's {loc['axis']} axis)"
        else:
            where = f"{loc['parameter']} drifts ({loc['trend']})"
        located.add_row(where, f"{loc['chi2'] / max(loc['dof'], 1):.1f}",
                        f"{loc['confidence']:.4f}")
    notes: list[RenderableType] = [Text(f["finding"], style="red") for f in doc["findings"]]
    notes += [Text(f"warning: {w}", style="yellow", overflow="fold") for w in doc["warnings"]]
    for e in doc["effects"]:
        if e.get("separating_experiment"):
            notes.append(Text(f"to separate {e['id']}: {e['separating_experiment']}"))
    if doc.get("report"):
        notes.append(path_line("report", doc["report"]))
    notes.append(path_line("recording", doc["recording"]))
    body: list[RenderableType] = [head]
    if doc["effects"]:
        body.append(effects)
    if doc["located"]:
        body.append(located)
    return Group(*body, *notes)
