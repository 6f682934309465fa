"""One unit's calibration as a page an engineer can check: the paper's figures for it.

The run's record says what was decided (trims, σ, every limit and the
verdict); the recording says why. This page puts both side by side: the
ripple power of the holds against each trim with the fitted parabola and
its vertex ± σ (the paper's figures 7 and 8), the harmonics and the
time-domain ripple before and after, the limit table, the unit's trims over
its recalibrations, and what the recording lost or clipped.

The figures come from the recording analysed again (``station analyze``'s
arithmetic); the trims, limits and verdict are the run's own record, never
recomputed, so a page drawn years later by newer software shows the numbers
the unit was judged by. A recording analysed without a record (``analyze
--report``) gives the same page without the record's parts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from station.advice import next_step
from station.analysis.estimate import (
    AXES,
    ParabolaFit,
    TrimAxis,
    TrimEstimate,
    TrimSigma,
    trim_coordinate,
)
from station.analysis.pipeline import Analysis, Measured, tangential_signal
from station.core import Method, Trims
from station.htmlpage import cells, escape, figure, key_values, num, page, svg, table
from station.recording import write_text_atomically
from station.runs import LimitCheck, Run, utc_iso

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

RIPPLE_PERIODS = 3
"""Electrical periods of ripple drawn before and after: enough to see its shape repeat."""

_BEFORE = "#c0392b"
_AFTER = "#1e8449"
_FIT = "#1f4e79"
_ROUNDS = ("#7f8c8d", "#8e44ad", "#d35400", "#16a085", "#2c3e50", "#b7950b")

_AXIS_LABEL = {
    TrimAxis.OFFSET_A: "offset A (mA)",
    TrimAxis.OFFSET_B: "offset B (mA)",
    TrimAxis.GAIN_SPLIT: "gain split (gain A − gain B)/2, 1/10000",
}


@dataclass(frozen=True)
class BeforeAfter:
    """The holds the page compares: the first at the trims the unit came with, the last
    at the trims it leaves with (a calibration's baseline and verification)."""

    before: Measured
    after: Measured | None

    @classmethod
    def of(cls, measured: Sequence[Measured], run: Run | None) -> BeforeAfter:
        start = run.trims_before if run is not None else None
        end = run.trims_after if run is not None and run.trims_stored else None
        before = next((m for m in measured if start is not None and m.segment.trims == start),
                      measured[0])
        if run is not None and end is None:
            return cls(before, None)  # nothing was stored: there is no "after" to show
        after_candidates = [m for m in measured if end is None or m.segment.trims == end]
        after = after_candidates[-1] if after_candidates else None
        return cls(before, after if after is not before else None)


# --------------------------------------------------------------------------- figures
def _new_figure(width: float = 4.4, height: float = 3.3) -> tuple[Figure, Axes]:
    from matplotlib.figure import Figure  # noqa: PLC0415 - only pages draw

    fig = Figure(figsize=(width, height), layout="constrained")
    ax = fig.subplots()
    ax.tick_params(labelsize=10)
    ax.grid(True, alpha=0.3)
    return fig, ax


def _lines(measured: Sequence[Measured], axis: TrimAxis) -> list[list[Measured]]:
    """Holds grouped into sweeps along ``axis``: the other two trims equal, two or more
    positions along it. Holds off every such line say nothing about this axis alone."""
    groups: dict[tuple[float, ...], list[Measured]] = {}
    others = [a for a in AXES if a is not axis]
    for m in measured:
        groups.setdefault(tuple(trim_coordinate(m.segment.trims, a) for a in others),
                          []).append(m)
    return [g for g in groups.values()
            if len({trim_coordinate(m.segment.trims, axis) for m in g}) >= 2]


@dataclass(frozen=True)
class Band:
    """The trims a figure marks with their ±1σ: the run's own estimate where the page has
    a record (what the unit was judged by), else the recording analysed again."""

    label: str
    trims: Trims
    sigma: Trims | TrimSigma

    @classmethod
    def of(cls, run: Run | None, analysis: Analysis) -> Band | None:
        if run is not None and run.trims_estimated is not None and run.uncertainty is not None:
            return cls(f"{run.method or 'recorded'} estimate", run.trims_estimated,
                       run.uncertainty)
        estimate = analysis.primary.estimate
        if estimate is None:
            return None
        return cls(f"{estimate.method.value} estimate (analysed again)", estimate.trims,
                   estimate.sigma)

    def on(self, axis: TrimAxis) -> tuple[float, float]:
        s = self.sigma
        sigma = {TrimAxis.OFFSET_A: s.offset_a_mA, TrimAxis.OFFSET_B: s.offset_b_mA,
                 TrimAxis.GAIN_SPLIT: s.gain_a}[axis]
        return trim_coordinate(self.trims, axis), sigma


def _sweep_figure(measured: Sequence[Measured], axis: TrimAxis, band: Band | None,
                  parabola: ParabolaFit | None) -> str:
    order = axis.harmonic
    fig, ax = _new_figure(4.4, 4.0)
    lowest = math.inf
    for i, line in enumerate(sorted(_lines(measured, axis),
                                    key=lambda g: measured.index(g[0]))):
        x = np.array([trim_coordinate(m.segment.trims, axis) for m in line])
        y = np.array([abs(m.harmonics.h(order)) ** 2 for m in line])
        # σ of |H|² from the phasor's σ: 2|H|σ, and at least σ² where |H| is near 0.
        var = np.array([m.harmonics.var(order) for m in line])
        err = 2.0 * np.sqrt(y * var) + var
        ax.errorbar(x, y, yerr=err, fmt="o", ms=5, color=_ROUNDS[i % len(_ROUNDS)],
                    capsize=2, label=f"sweep {i + 1} ({len(line)} holds)", zorder=3)
        positive = y[y > 0]
        if positive.size:
            lowest = min(lowest, float(positive.min()))
    if parabola is not None:
        xs = np.linspace(parabola.swept[0], parabola.swept[1], 200)
        ys = parabola.floor + parabola.curvature * (xs - parabola.vertex) ** 2
        ax.plot(xs, np.maximum(ys, lowest / 10 if math.isfinite(lowest) else 1e-9), "-",
                color=_FIT, lw=1.4, label="paper's parabola", zorder=2)
    if band is not None:
        value, sigma = band.on(axis)
        ax.axvspan(value - sigma, value + sigma, color=_AFTER, alpha=0.25, lw=0)
        ax.axvline(value, color=_AFTER, lw=1.2,
                   label=f"{band.label} {num(value)} ± {num(sigma, 2)}")
    ax.set_yscale("log")
    if math.isfinite(lowest):
        ax.set_ylim(bottom=lowest / 3)
    ax.set_xlabel(_AXIS_LABEL[axis], fontsize=11)
    ax.set_ylabel(f"|H{order}|² ((m/s²)²)", fontsize=11)
    fig.legend(fontsize=9, loc="outside lower center", ncol=2, frameon=False)
    return svg(fig, f"sweep-{axis.value}")


def _harmonics_figure(holds: BeforeAfter) -> str:
    fig, ax = _new_figure()
    shown = [(holds.before, "before", _BEFORE)]
    if holds.after is not None:
        shown.append((holds.after, "after", _AFTER))
    orders = min(len(m.harmonics.phasors) for m, _, _ in shown)
    k = np.arange(1, orders + 1)
    width = 0.8 / len(shown)
    for i, (m, label, colour) in enumerate(shown):
        magnitude = np.abs(m.harmonics.phasors[:orders])
        sigma = np.sqrt(m.harmonics.variance[:orders])
        ax.bar(k + (i - (len(shown) - 1) / 2) * width, np.maximum(magnitude, 1e-6), width,
               yerr=sigma, color=colour, capsize=2, label=label, ecolor="#444")
    ax.set_yscale("log")
    ax.set_xticks(k)
    ax.set_xlabel("harmonic order (per electrical period)", fontsize=11)
    ax.set_ylabel("|H| (m/s²)", fontsize=11)
    ax.legend(fontsize=9)
    return svg(fig, "harmonics")


def _window(m: Measured, signal: NDArray[np.float64], sync_period_s: float
            ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The middle ``RIPPLE_PERIODS`` periods of a hold: time (ms) and ripple (mean off)."""
    seg = m.segment
    per_period = seg.samples / max(seg.periods, 1)
    length = round(min(RIPPLE_PERIODS, seg.periods) * per_period)
    start = seg.start + max(0, (seg.samples - length) // 2)
    y = signal[start:start + length]
    y = y - np.nanmean(y) if np.isfinite(y).any() else y
    t: NDArray[np.float64] = np.arange(y.size, dtype=np.float64) * (sync_period_s * 1e3)
    return t, y


def _ripple_figure(analysis: Analysis, holds: BeforeAfter) -> str:
    signal = tangential_signal(analysis.timeline)
    period = analysis.timeline.sync_period_s
    fig, ax = _new_figure()
    t, y = _window(holds.before, signal, period)
    ax.plot(t, y, "-", color=_BEFORE, lw=1.1, label="before")
    if holds.after is not None:
        t, y = _window(holds.after, signal, period)
        ax.plot(t, y, "-", color=_AFTER, lw=1.1, label="after")
    ax.set_xlabel("time in the hold (ms)", fontsize=11)
    ax.set_ylabel("tangential acceleration (m/s²)", fontsize=11)
    ax.legend(fontsize=9)
    return svg(fig, "ripple")


def _drift_figure(runs: Sequence[Run]) -> str:
    stored = [(r, r.trims_after) for r in runs if r.trims_stored and r.trims_after is not None]
    fig, ax = _new_figure()
    x = np.arange(1, len(stored) + 1)
    trims = [t for _, t in stored]
    ax.plot(x, [t.offset_a_mA for t in trims], "o-", color=_BEFORE, label="offset A (mA)")
    ax.plot(x, [t.offset_b_mA for t in trims], "s-", color=_FIT, label="offset B (mA)")
    ax.plot(x, [trim_coordinate(t, TrimAxis.GAIN_SPLIT) for t in trims], "^-", color=_AFTER,
            label="gain split (1/10000)")
    ax.set_xticks(x)
    ax.set_xticklabels([f"run {r.run_id}" for r, _ in stored], fontsize=8, rotation=30)
    ax.set_ylabel("trim stored", fontsize=11)
    ax.legend(fontsize=9)
    return svg(fig, "drift")


# --------------------------------------------------------------------------- sections
def _banner(run: Run) -> str:
    verdict = run.verdict.value if run.verdict is not None else "open"
    reason = escape(run.reason or "")
    advice = next_step(run)
    then = f"<br><b>Next:</b> {escape(advice)}" if advice else ""
    return (f"<div class='banner v-{escape(verdict)}'><b class='{escape(verdict)}'>"
            f"{escape(verdict.upper())}</b> — {reason}{then}</div>")


def _identity(run: Run | None, analysis: Analysis | None, source: str) -> str:
    rows = []
    if run is not None:
        rows += [
            ("run", f"{run.run_id} ({run.kind.value}), uuid {run.run_uuid}"),
            ("started / finished", f"{utc_iso(run.started_at)} / "
             f"{utc_iso(run.finished_at) if run.finished_at else '—'}"),
            ("station / operator / bench", f"{run.station_id} / {run.operator} / {run.bench}"),
            ("recipe", f"{run.recipe.name} version {run.recipe.version} "
             f"(sha256 {run.recipe.sha256[:12]}…)"),
            ("software", run.software_version),
        ]
        if run.service_reason:
            rows.append(("field service reason", run.service_reason))
    if analysis is not None:
        meta = analysis.timeline.metadata
        rows.append(("fixture", f"{meta.rotor_teeth} rotor teeth, sensor radius "
                     f"{meta.sensor_radius_m} m, gear ratio {meta.gear_ratio:g}, tangential "
                     f"axis {meta.tangential_axis.value}"))
    shown = [(k, escape(v)) for k, v in rows]
    shown.append(("recording", f"<span class='path'>{escape(source)}</span>"))
    return key_values(shown)


def _trims_section(run: Run | None, estimate: TrimEstimate | None) -> str:
    keys = ("offset_a_mA", "offset_b_mA", "gain_a", "gain_b")
    rows = []
    record_sigma = run.uncertainty.as_dict() if run is not None and run.uncertainty else None
    for key in keys:
        row = [escape(key)]
        if run is not None:
            before = run.trims_before.as_dict()[key] if run.trims_before else None
            est = run.trims_estimated.as_dict()[key] if run.trims_estimated else None
            stored = (run.trims_after.as_dict()[key]
                      if run.trims_stored and run.trims_after else None)
            sigma = record_sigma[key] if record_sigma else None
            row += [num(before), f"{num(est)} ± {num(sigma, 2)}" if est is not None else "—",
                    num(stored)]
        if estimate is not None:
            again = estimate.trims.as_dict()[key]
            row.append(f"{num(again)} ± {num(estimate.sigma.as_dict()[key], 2)}")
        rows.append(cells(*row, numeric=tuple(range(1, len(row)))))
    header: tuple[str, ...] = ("trim",)
    if run is not None:
        header += ("the unit came with", "estimated (record) ± 1σ", "stored in the drive")
    if estimate is not None:
        header += (f"recording analysed again ({estimate.method.value}) ± 1σ",)
    return table(header, rows)


def _limit_row(check: LimitCheck) -> str:
    state = ("pass" if check.passed else "fail") if check.passed is not None else "n/a"
    css = "failed" if check.passed is False else ""
    return cells(escape(str(check.name)), num(check.value), num(check.low), num(check.high),
                 escape(check.unit), f"<span class='{state}'>{escape(state)}</span>",
                 escape(check.note), numeric=(1, 2, 3), css=css)


def _limits_section(run: Run) -> str:
    if not run.limits:
        return "<p class='note'>No limit was checked: the run ended before its checks.</p>"
    return table(("check", "value", "low", "high", "unit", "result", "note"),
                 [_limit_row(c) for c in run.limits])


def _ripple_section(run: Run | None, holds: BeforeAfter) -> str:
    def hold(m: Measured | None) -> tuple[str, str]:
        if m is None:
            return "—", "—"
        h = m.harmonics
        return (f"{num(abs(h.h(1)))} ± {num(math.sqrt(h.var(1)), 2)}",
                f"{num(abs(h.h(2)))} ± {num(math.sqrt(h.var(2)), 2)}")

    rows = []
    for name, m, recorded in (("before", holds.before, run.before if run else None),
                              ("after", holds.after, run.after if run else None)):
        h1, h2 = hold(m)
        row = [escape(name), h1, h2]
        if run is not None:
            row += [num(recorded.h1) if recorded else "—", num(recorded.h2) if recorded else "—"]
        rows.append(cells(*row, numeric=tuple(range(1, len(row)))))
    header = ["", "|H1| in the recording (m/s²)", "|H2| in the recording (m/s²)"]
    if run is not None:
        header += ["|H1| recorded", "|H2| recorded"]
    return table(header, rows)


def _history_section(runs: Sequence[Run], this: Run) -> str:
    rows = []
    previous: Trims | None = None
    for r in runs:
        stored = r.trims_after if r.trims_stored else None
        delta = ""
        if stored is not None and previous is not None:
            delta = (f"{stored.offset_a_mA - previous.offset_a_mA:+.0f} / "
                     f"{stored.offset_b_mA - previous.offset_b_mA:+.0f} mA, "
                     f"{stored.gain_a - previous.gain_a:+.0f} / "
                     f"{stored.gain_b - previous.gain_b:+.0f}")
        trims = ("—" if stored is None else
                 f"{stored.offset_a_mA:+.0f} / {stored.offset_b_mA:+.0f} mA, "
                 f"{stored.gain_a:.0f} / {stored.gain_b:.0f}")
        verdict = r.verdict.value if r.verdict else "open"
        rows.append(cells(escape(r.run_id), escape(utc_iso(r.started_at)[:19]),
                          escape(r.kind.value), f"<span class='{verdict}'>{verdict}</span>",
                          escape(trims), escape(delta), escape(r.reason or ""),
                          numeric=(0,), css="chosen" if r.run_id == this.run_id else ""))
        if stored is not None:
            previous = stored
    parts = [table(("run", "started (UTC)", "kind", "verdict", "trims stored (A / B, gains)",
                    "change since the last stored", "reason"), rows)]
    if sum(1 for r in runs if r.trims_stored) >= 2:
        parts.insert(0, "<div class='figures'>" + figure(
            _drift_figure(runs), "Trims stored by each run of this unit that stored trims, "
            "oldest first: a drift across recalibrations shows as a slope.") + "</div>")
    return "".join(parts)


def _recording_section(analysis: Analysis) -> str:
    losses = analysis.timeline.losses
    measured = analysis.primary.condition.measured
    saturated = sum(m.saturated for m in measured)
    rows = [
        ("samples (SYNCs)", f"{analysis.timeline.samples}"),
        ("SYNCs missing", f"{losses.syncs_missing}"),
        ("sensor samples lost", f"{losses.sensor_samples_lost}"),
        ("drive status / trims frames lost",
         f"{losses.drive_status_lost} / {losses.drive_trims_lost}"),
        ("samples at the sensor's full scale (clipped)",
         f"{losses.saturated_samples} in the recording, {saturated} in the holds used"),
        ("malformed / ignored frames", f"{losses.frames_malformed} / {losses.frames_ignored}"),
        ("holds used", f"{len(measured)}"),
    ]
    parts = [key_values([(k, escape(v)) for k, v in rows])]
    if analysis.rejected:
        period = analysis.timeline.sync_period_s
        parts.append("<p>Stretches left out:</p>" + table(
            ("from (s)", "to (s)", "why"),
            [cells(num(r.start * period), num(r.stop * period), escape(r.reason),
                   numeric=(0, 1)) for r in analysis.rejected]))
    estimate = analysis.primary.estimate
    warnings = list(analysis.warnings) + (list(estimate.warnings) if estimate else [])
    if warnings:
        parts.append("<ul>" + "".join(f"<li class='caution'>{escape(w)}</li>"
                                      for w in warnings) + "</ul>")
    return "".join(parts)


def _holds_table(measured: Sequence[Measured], sync_period_s: float) -> str:
    rows = []
    for i, m in enumerate(measured, 1):
        t, h = m.segment.trims, m.harmonics
        rows.append(cells(
            str(i), num(m.segment.start * sync_period_s, 3), f"{t.offset_a_mA:.0f}",
            f"{t.offset_b_mA:.0f}", f"{t.gain_a:.0f}", f"{t.gain_b:.0f}",
            f"{num(abs(h.h(1)))} ± {num(math.sqrt(h.var(1)), 2)}",
            f"{num(abs(h.h(2)))} ± {num(math.sqrt(h.var(2)), 2)}",
            str(h.samples_missing), str(m.saturated), numeric=tuple(range(10))))
    return table(("hold", "at (s)", "offset A", "offset B", "gain A", "gain B",
                  "|H1| (m/s²)", "|H2| (m/s²)", "lost", "clipped"), rows)


def _paper_parabolas(analysis: Analysis) -> dict[TrimAxis, ParabolaFit]:
    paper = analysis.primary.estimates.get(Method.PAPER)
    return {p.axis: p for p in paper.parabolas} if paper is not None else {}


def _sweeps_section(analysis: Analysis, run: Run | None) -> str:
    measured = analysis.primary.condition.measured
    band = Band.of(run, analysis)
    parabolas = _paper_parabolas(analysis)
    marked = (f" The band: the {band.label}'s ±1σ." if band is not None else
              " No estimate is marked: the recording analysed again supports none.")
    figures = []
    for axis in AXES:
        if not _lines(measured, axis):
            figures.append(f"<p class='note'>No sweep along {_AXIS_LABEL[axis]} in the holds "
                           "this recording gives when analysed again.</p>")
            continue
        parabola = parabolas.get(axis)
        fit = (f" The paper's parabola: vertex {num(parabola.vertex)} ± "
               f"{num(parabola.vertex_sigma, 2)}, R² {parabola.quality.r_squared:.4f}."
               if parabola is not None else
               " The paper's parabola could not be fitted to these holds: "
               + analysis.primary.unsupported.get(Method.PAPER, "no sweep along this axis")
               + ".")
        figures.append(figure(
            _sweep_figure(measured, axis, band, parabola),
            f"|H{axis.harmonic}|² of every hold on a sweep along {_AXIS_LABEL[axis]} (log "
            "scale; error bars ±σ)." + marked + fit))
    return "<div class='figures'>" + "".join(figures) + "</div>"


def _figures_sections(analysis: Analysis, run: Run | None) -> list[str]:
    measured = analysis.primary.condition.measured
    holds = BeforeAfter.of(measured, run)
    after_caption = (" and the hold at the trims stored (after)" if holds.after is not None
                     else "; no hold at stored trims (nothing was stored)")
    return [
        "<h2>Ripple power against each trim</h2>", _sweeps_section(analysis, run),
        "<h2>Before and after</h2>", _ripple_section(run, holds),
        "<div class='figures'>",
        figure(_harmonics_figure(holds),
               "Harmonics of the tangential acceleration at the trims the unit came with "
               f"(before){after_caption} (log scale, error bars ±σ)."),
        figure(_ripple_figure(analysis, holds),
               f"{RIPPLE_PERIODS} electrical periods of the acceleration from the middle of "
               "each hold, mean removed."),
        "</div>",
    ]


def render_unit_report(*, source: str, analysis: Analysis | None = None, run: Run | None = None,
                       history: Sequence[Run] = (), notes: Sequence[str] = ()) -> str:
    """The page as text (``write_unit_report`` stores it).

    ``analysis`` None: the recording could not be analysed (a run stopped after two
    holds); the page then shows the record alone, with ``notes`` saying why.
    """
    if analysis is None and run is None:
        raise ValueError("a report needs a run's record, an analysed recording, or both")
    serial = run.serial if run is not None else analysis.timeline.metadata.serial  # type: ignore[union-attr]
    title = (f"Calibration of {serial}, run {run.run_id}" if run is not None
             else f"Calibration recording of {serial}")
    body = [f"<h1>{escape(title)}</h1>"]
    if run is not None:
        body.append(_banner(run))
    else:
        body.append("<p class='note'>No station record is shown: this page is the recording "
                    "alone, analysed off the bench.</p>")
    body += [f"<p class='caution'>{escape(n)}</p>" for n in notes]
    body.append(_identity(run, analysis, source))
    if analysis is not None:
        condition = analysis.primary.condition
        body.append(f"<p class='note'>Operating point {condition.amplitude_mA} mA, "
                    f"{abs(condition.electrical_hz):.2f} Hz electrical; "
                    f"{len(condition.measured)} holds.</p>")
    body += ["<h2>Trims</h2>",
             _trims_section(run, analysis.primary.estimate if analysis is not None else None)]
    if run is not None:
        body += ["<h2>Limits</h2>", _limits_section(run)]
    if analysis is not None:
        body += _figures_sections(analysis, run)
    if run is not None and history:
        body += ["<h2>This unit's history</h2>", _history_section(history, run)]
    if analysis is not None:
        body += ["<h2>The recording</h2>", _recording_section(analysis),
                 "<h2>Every hold</h2>",
                 _holds_table(analysis.primary.condition.measured,
                              analysis.timeline.sync_period_s)]
    return page(title, body)


def write_unit_report(path: Path, *, source: str, analysis: Analysis | None = None,
                      run: Run | None = None, history: Sequence[Run] = (),
                      notes: Sequence[str] = ()) -> Path:
    """Write the page; readers see the old file or the whole new one, never half."""
    write_text_atomically(Path(path), render_unit_report(
        source=source, analysis=analysis, run=run, history=history, notes=notes))
    return Path(path)
