"""A diagnosis as one HTML page a motion-control engineer can check, not just read.

The JSON document says *what* the diagnosis concluded; this page shows the
evidence behind it: the measured harmonics beside both models' predictions,
where (order, condition) the nominal model misses and whether the extended
one closes the gap, how the amplifier's "constants" move between conditions,
and every candidate the naming rounds tried with the numbers that decided.

The page is one self-contained file (inline SVG, no script, no external
resource) so it can be mailed, archived with the run and opened years later.
Figures are drawn on ``matplotlib.figure.Figure`` objects, never through
pyplot: pyplot keeps every figure in a global registry until it is closed and
picks a GUI backend, neither of which a station process wants.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import NDArray

from station.diagnosis.fit import Fit
from station.diagnosis.locate import SIGNIFICANT_CONFIDENCE, chi2_map, trim_constants
from station.diagnosis.name import MAX_EFFECTS, RIVAL_Z, UNEXPLAINED_RATIO
from station.diagnosis.observations import ConditionKey
from station.diagnosis.results import Diagnosis, LocatedKind
from station.htmlpage import cells as _cells
from station.htmlpage import escape as _e
from station.htmlpage import figure as _figure
from station.htmlpage import num as _num
from station.htmlpage import page
from station.htmlpage import svg as _svg
from station.htmlpage import table as _table
from station.recording import write_text_atomically

MAX_HARMONIC_ROWS = 40
"""Located harmonic entries listed; beyond this a table stops being read."""

_MEASURED = "#1f4e79"
_NOMINAL = "#c0392b"
_EXTENDED = "#27ae60"

# --------------------------------------------------------------------------- text
def _constant(value: float) -> str:
    """A threshold as the code states it (50, not 50.00)."""
    return f"{value:g}"


def _rms(value: float) -> str:
    """RMS in m/s²: three significant digits, the noise already blurs the fourth."""
    return f"{value:.3g}"


def _chi2(value: float) -> str:
    """χ² as the JSON document rounds it (0.1), so the page and the JSON read alike;
    past a million only the leading digits mean anything."""
    return f"{value:.1f}" if abs(value) < 1e6 else f"{value:.4e}"


def _confidence(value: float) -> str:
    """Confidence near 1 as its complement: 0.9999999 and 0.9999 must not both read 1.000."""
    p = 1.0 - float(value)
    if p <= 0.0:
        return "> 1 − 1e−16"
    if p < 1e-4:
        return f"1 − {p:.1e}"
    return f"{value:.4f}"


def _condition_of(item: Mapping[str, Any]) -> str | None:
    if "amplitude_mA" in item and "electrical_hz" in item:
        return ConditionKey(int(item["amplitude_mA"]), float(item["electrical_hz"])).label()
    return None


def _sigma_key(key: str, keys: Sequence[str]) -> str | None:
    """The key holding ``key``'s 1σ, by the two spellings the diagnosis uses: ``x`` with
    ``x_sigma``, and ``sigma_<unit>`` beside the one other key in that unit."""
    if f"{key}_sigma" in keys:
        return f"{key}_sigma"
    if key.startswith("sigma_") or "_sigma_" in key:
        return None
    # "coulomb_forward_sigma_percent" beside "coulomb_forward_percent_of_rated_…".
    for other in keys:
        stem, found, unit = other.partition("_sigma_")
        if found and key.startswith(stem + "_") and unit in key.split("_"):
            return other
    for other in keys:
        if other.startswith("sigma_"):
            unit = other.removeprefix("sigma_")
            same_unit = [k for k in keys if k != other and unit in k.split("_")]
            if same_unit == [key]:
                return other
    return None


def _flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, str]]:
    """Nested parameter documents as (path, "value ± σ") rows, σ beside its value."""
    if isinstance(value, Mapping):
        keys = [str(k) for k in value]
        sigmas = {k: s for k in keys if (s := _sigma_key(k, keys)) is not None}
        skip = set(sigmas.values())
        condition = _condition_of(value)
        if condition is not None:
            skip |= {"amplitude_mA", "electrical_hz", "direction"}
        for key in keys:
            if key in skip:
                continue
            path = f"{prefix}.{key}" if prefix else key
            item = value[key]
            if key in sigmas and not isinstance(item, Mapping | list | tuple):
                yield path, f"{_num(item)} ± {_num(value[sigmas[key]], 2)}{_flag(key, item)}"
            elif not isinstance(item, Mapping | list | tuple):
                yield path, f"{_num(item)}{_flag(key, item)}"
            else:
                yield from _flatten(item, path)
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            label = _condition_of(item) if isinstance(item, Mapping) else None
            yield from _flatten(item, f"{prefix}[{label if label is not None else i}]")
    else:
        yield prefix, _num(value)


FRICTION_PLAUSIBLE_PERCENT = 25.0
"""Drag above this share of the rated holding torque is flagged: a motor turning a disk or
a belt freely loses a few percent to friction; more says the model put something else
(a load, a misalignment, another effect) into its friction."""
LOAD_ANGLE_PLAUSIBLE_RAD = math.pi / 4
"""A load angle beyond 45° is flagged: pull-out is at 90°, and a unit at constant speed
that far round its torque curve is near losing step, not calibrating."""


def implausible(key: str, value: Any) -> str | None:
    """Why a fitted value cannot be taken at face value, by what the key says it is."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
            float(value)):
        return None
    x = abs(float(value))
    if "percent_of_rated_holding_torque" in key and x > FRICTION_PLAUSIBLE_PERCENT:
        return (f"implausible: more than {FRICTION_PLAUSIBLE_PERCENT:g} % of the holding "
                "torque lost to friction")
    if key == "load_angle_rad" and x > LOAD_ANGLE_PLAUSIBLE_RAD:
        return "implausible: beyond 45°, near pull-out (90°)"
    if key.endswith("damping_ratio") and not 0.0 <= float(value) <= 1.0:
        return "implausible: a damping ratio outside 0..1 is not a damped mode"
    return None


def _flag(key: str, value: Any) -> str:
    why = implausible(key, value)
    return f"  ⚠ {why}" if why else ""


def _parameter_table(parameters: Mapping[str, Any]) -> str:
    flagged = " class='implausible'"
    rows = "".join(
        f"<tr{flagged if '⚠' in text else ''}><td>{_e(path)}</td>"
        f"<td class='num'>{_e(text)}</td></tr>"
        for path, text in _flatten(parameters)
    )
    return f"<table class='inner'>{rows}</table>" if rows else "—"


# --------------------------------------------------------------------------- figures
def _condition_axis(ax: Axes, labels: Sequence[str], *, show: bool = True) -> None:
    ax.set_xticks(range(len(labels)))
    if show:
        ax.set_xticklabels(labels, rotation=45, ha="right", fontsize=9)
    else:
        ax.tick_params(axis="x", labelbottom=False)
    ax.set_xlim(-0.6, len(labels) - 0.4)


def _jitter(condition: NDArray[np.intp]) -> NDArray[np.float64]:
    """x position of every segment: its condition, spread by its rank within it."""
    x = condition.astype(float)
    for c in np.unique(condition):
        rows = np.flatnonzero(condition == c)
        n = rows.size
        if n > 1:
            x[rows] += (np.arange(n) - (n - 1) / 2.0) * (0.36 / (n - 1))
    return x


def _harmonics_figure(d: Diagnosis, labels: Sequence[str]) -> str:
    obs = d.observations
    measured = np.abs(obs.phasors)
    nominal = np.abs(d.nominal.fit.model.predicted(d.nominal.fit.params))
    extended = np.abs(d.extended.fit.model.predicted(d.extended.fit.params))
    x = _jitter(obs.condition)
    orders = obs.orders
    cols = 2 if orders > 1 else 1
    rows = math.ceil(orders / cols)
    fig = Figure(figsize=(10.0, 2.3 * rows + 1.6), layout="constrained")
    # Every panel sets the same condition ticks itself; only the bottom ones label them.
    axes = fig.subplots(rows, cols, squeeze=False)
    for k in range(rows * cols):
        ax: Axes = axes[k // cols, k % cols]
        if k >= orders:
            ax.set_visible(False)
            continue
        ax.errorbar(x, measured[:, k], yerr=obs.sigma[:, k], fmt="o", ms=3.5, color=_MEASURED,
                    ecolor=_MEASURED, elinewidth=0.8, capsize=1.5, zorder=3)
        ax.plot(x, nominal[:, k], "x", ms=5, color=_NOMINAL, zorder=4)
        ax.plot(x, extended[:, k], "_", ms=9, mew=1.8, color=_EXTENDED, zorder=5)
        ax.set_yscale("log")
        positive = np.concatenate([measured[:, k], nominal[:, k], extended[:, k]])
        positive = positive[np.isfinite(positive) & (positive > 0)]
        if positive.size:
            ax.set_ylim(bottom=0.4 * float(positive.min()))
        ax.set_title(f"order {k + 1}", fontsize=9, loc="left")
        ax.set_ylabel("|H| (m/s²)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="major", alpha=0.3)
        _condition_axis(ax, labels, show=k // cols == rows - 1 or k + cols >= orders)
    handles = [
        Line2D([], [], marker="o", ls="none", color=_MEASURED, label="measured, ±σ"),
        Line2D([], [], marker="x", ls="none", color=_NOMINAL, label="nominal model"),
        Line2D([], [], marker="_", ms=9, mew=1.8, ls="none", color=_EXTENDED,
               label="extended model"),
    ]
    fig.legend(handles=handles, loc="outside upper center", ncol=3, fontsize=9, frameon=False)
    return _svg(fig, "harmonics")


def _chi2_per_dof(result: Fit) -> NDArray[np.float64]:
    """χ² per degree of freedom, (orders, conditions): 1 where the model reaches the noise."""
    chi2, dof = chi2_map(result)
    out: NDArray[np.float64] = (chi2 / np.maximum(dof, 1)[:, None]).T
    return out


def _residual_map_figure(d: Diagnosis, labels: Sequence[str]) -> str:
    """Conditions down the side, orders across: condition labels read horizontally at a
    readable size however many conditions a schedule has."""
    obs = d.observations
    conditions = len(obs.conditions)
    maps = [_chi2_per_dof(d.nominal.fit).T, _chi2_per_dof(d.extended.fit).T]
    values = np.concatenate([m.ravel() for m in maps])
    values = values[np.isfinite(values) & (values > 0)]
    low = float(values.min()) if values.size else 0.1
    high = float(values.max()) if values.size else 10.0
    low = min(low, 0.5)  # keep the noise level (1) inside the scale
    high = max(high, 2.0 * low, 2.0)
    norm = LogNorm(vmin=low, vmax=high)
    fig = Figure(figsize=(max(7.0, 0.55 * obs.orders * 2 + 4.0), 0.34 * conditions + 1.8),
                 layout="constrained")
    axes = fig.subplots(1, 2, sharey=True, squeeze=False)[0]
    image = None
    for ax, grid, title in zip(axes, maps, ("nominal model", "extended model"), strict=True):
        shown = np.where(np.isfinite(grid) & (grid > 0), grid, low)
        image = ax.imshow(shown, norm=norm, cmap="viridis", aspect="auto", origin="upper")
        ax.set_title(title, fontsize=11)
        ax.set_xticks(range(obs.orders))
        ax.set_xticklabels([str(k + 1) for k in range(obs.orders)], fontsize=10)
        ax.set_xlabel("harmonic order", fontsize=10)
        ax.set_yticks(range(conditions))
        ax.set_yticklabels(labels, fontsize=10)
        for (c, k), v in np.ndenumerate(grid):
            if np.isfinite(v):
                bright = np.log(max(v, low) / low) > 0.6 * np.log(high / low)
                ax.text(k, c, f"{v:.2g}", ha="center", va="center", fontsize=8,
                        color="black" if bright else "white")
    assert image is not None
    bar = fig.colorbar(image, ax=list(axes), fraction=0.04)
    bar.set_label("χ² per degree of freedom (1 = noise)", fontsize=10)
    return _svg(fig, "residuals")


def _trims_figure(d: Diagnosis, labels: Sequence[str]) -> str:
    values, sigmas = d.constants
    overall = trim_constants(d.nominal.fit.value("amp_offset_mA"),
                             d.nominal.fit.value("amp_gain_error"))
    titles = ("optimal offset A (mA)", "optimal offset B (mA)", "optimal gain split (1/10000)")
    fig = Figure(figsize=(10.0, 6.2), layout="constrained")
    axes = fig.subplots(3, 1, squeeze=False)[:, 0]
    x = np.arange(len(labels))
    for i, ax in enumerate(axes):
        ax.errorbar(x, values[:, i], yerr=sigmas[:, i], fmt="o", ms=4, color=_MEASURED,
                    capsize=2, label="this condition alone, ±σ")
        ax.axhline(overall[i], color=_NOMINAL, ls="--", lw=1, label="nominal fit, all conditions")
        ax.set_ylabel(titles[i], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
        _condition_axis(ax, labels, show=i == 2)
    axes[0].legend(fontsize=8, loc="best")
    return _svg(fig, "trims")


def _held_out_figure(d: Diagnosis, labels: Sequence[str]) -> str:
    x = np.arange(len(labels))
    width = 0.38
    fig = Figure(figsize=(max(7.0, 0.7 * len(labels) + 2.0), 3.8), layout="constrained")
    ax = fig.subplots()
    nominal = np.maximum(d.nominal_held.chi2, 1e-3)
    extended = np.maximum(d.extended_held.chi2, 1e-3)
    ax.bar(x - width / 2, nominal, width, color=_NOMINAL, label="nominal model")
    ax.bar(x + width / 2, extended, width, color=_EXTENDED, label="extended model")
    ax.set_yscale("log")
    ax.set_ylabel("held-out χ²")
    ax.tick_params(labelsize=7)
    ax.grid(True, axis="y", alpha=0.3)
    _condition_axis(ax, labels)
    ax.legend(fontsize=8)
    return _svg(fig, "heldout")


# --------------------------------------------------------------------------- sections
def _verdict(d: Diagnosis, doc: Mapping[str, Any]) -> str:
    fit = doc["fit"]
    if doc["mismatch"]:
        verdict = ("<span class='mismatch'>Mismatch</span>: the paper's model does not "
                   "explain this recording within its noise.")
    elif doc["located"]:
        # Located cells without a mismatch: say both, or the headline contradicts the table.
        verdict = (f"<span class='caution'>No mismatch that matters</span>: "
                   f"{len(doc['located'])} disagreement(s) of the paper's model are located "
                   "below, but no effect explains them better than noise on held-out "
                   "conditions and what is left is noise: negligible for calibration.")
    else:
        verdict = ("<span class='match'>No mismatch</span>: the paper's model explains this "
                   "recording within its noise.")
    model = ", ".join(e["id"] for e in doc["effects"]) or "nominal only"
    left = d.unexplained
    if left.significant:
        residual = (
            "<p class='mismatch'>A significant residual is left: with the best model the "
            f"vocabulary allows, the held-out χ² is {_e(_chi2(left.chi2))} for "
            f"{_e(left.values)} values ({_e(_num(left.ratio, 3))} per value, noise is 1). "
            "No id describes what remains; where it is, is listed below as "
            "<i>unexplained</i>.</p>")
    elif left.lone is not None:
        lone = left.lone
        residual = (
            f"<p>What the {'extended' if d.effects else 'nominal'} model leaves on held-out "
            f"conditions is noise but for one hold: χ² {_e(_chi2(left.chi2))} for "
            f"{_e(left.values)} values, {_e(_chi2(lone.chi2))} of it in the hold at "
            f"{_e(lone.condition.label())}, {lone.start_s:.2f}–{lone.stop_s:.2f} s, which the "
            "other holds do not share: a transient the settling did not describe, not "
            "missing physics.</p>")
    else:
        residual = (
            f"<p>What the {'extended' if d.effects else 'nominal'} model leaves on held-out "
            f"conditions is noise: χ² {_e(_chi2(left.chi2))} for {_e(left.values)} values "
            f"({_e(_num(left.ratio, 3))} per value).</p>")
    lines = [
        f"<p class='verdict'>{verdict}</p>",
        residual,
        "<p>Held-out residual (inverse-variance weighted RMS, m/s²): "
        f"<b>{_e(_rms(fit['before']))}</b> with the nominal model → "
        f"<b>{_e(_rms(fit['after']))}</b> with the extended model "
        f"({_e(model)}). Held-out χ²: {_e(_chi2(fit['before_chi2']))} → "
        f"{_e(_chi2(fit['after_chi2']))} over {_e(fit['observations'])} observations "
        f"({_e(d.observations.count)} segments × {_e(d.observations.orders)} orders × "
        "2 parts, each condition held out in turn).</p>",
    ]
    if d.findings:
        items = "".join(f"<li>{_e(f.text)}</li>" for f in d.findings)
        lines.append("<p class='mismatch'>The nominal model cannot describe this recording:"
                     f"</p><ul>{items}</ul>")
    if d.warnings:
        items = "".join(f"<li>{_e(w)}</li>" for w in d.warnings)
        lines.append(f"<ul class='note'>{items}</ul>")
    return "".join(lines)


def _evidence_table(evidence: Sequence[Mapping[str, Any]]) -> str:
    """The located cells an effect explains: χ² of the held-out residual without it and
    with it, at each (condition, order)."""
    if not evidence:
        return "no single cell is significant on its own; the gain is spread thinly"
    rows = "".join(
        f"<tr><td>{_e(_condition_of(cell))}, order {_e(cell['order'])}</td>"
        f"<td class='num'>{_e(_chi2(cell['chi2_before']))} → "
        f"{_e(_chi2(cell['chi2_after']))}</td></tr>"
        for cell in evidence
    )
    return f"<table class='inner'>{rows}</table>"


def _effects_section(d: Diagnosis) -> str:
    if not d.effects:
        return ("<p>No effect beyond the nominal model wins on held-out conditions; see the "
                "naming rounds below for what was tried.</p>")
    rows = []
    for effect in d.effects:
        doc = effect.as_dict()
        rivals = ", ".join(doc.get("cannot_separate_from", [])) or "—"
        experiment = doc.get("separating_experiment") or "—"
        rows.append(_cells(
            f"<b>{_e(doc['id'])}</b>",
            _e(_chi2(doc["held_out_chi2_gain"])),
            _evidence_table(doc["evidence"]),
            _e(rivals),
            _e(experiment),
            _parameter_table(doc["parameters"]),
            numeric=(1,),
        ))
    return _table(("effect", "held-out χ² gain",
                   "evidence: located cells it explains (held-out χ² without → with it)",
                   "cannot separate from", "experiment that would separate them",
                   "fitted parameters (± 1σ)"), rows)


def _value_sigma(doc: Mapping[str, Any], key: str, sigma_key: str | None, unit: str,
                 digits: int = 4) -> tuple[str, str]:
    value = doc.get(key)
    sigma = doc.get(sigma_key) if sigma_key else None
    text = _num(value, digits) + (f" ± {_num(sigma, 2)}" if sigma is not None else "")
    return f"{text} {unit}".strip(), implausible(key, value) or ""


def _nominal_rows(doc: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """The chain, the sensor and the optimum as a motion engineer names them."""
    quantities = [
        ("rotor natural frequency at rated current", "rotor_natural_hz_at_rated_current",
         "rotor_natural_hz_sigma", "Hz"),
        ("rotor damping ratio", "rotor_damping_ratio", "rotor_damping_ratio_sigma", ""),
        ("sensor delay", "sensor_delay_ms", "sensor_delay_ms_sigma", "ms"),
        ("sensor bandwidth", "sensor_bandwidth_hz", None, "Hz"),
        ("belt natural frequency (motor held)", "belt_hz_motor_held", "belt_hz_sigma", "Hz"),
        ("belt damping ratio", "belt_damping_ratio", "belt_damping_ratio_sigma", ""),
        ("load damping ratio", "load_damping_ratio", "load_damping_ratio_sigma", ""),
        ("load / rotor inertia", "load_inertia_ratio", "load_inertia_ratio_sigma", ""),
        ("gear ratio (metadata)", "gear_ratio", None, ""),
    ]
    rows = [("chain", _e(doc.get("chain", "—")), "")]
    for label, key, sigma_key, unit in quantities:
        if key in doc:
            text, flag = _value_sigma(doc, key, sigma_key, unit)
            rows.append((label, _e(text), flag))
    modes = doc.get("chain_modes_at_rated_current") or []
    if modes:
        rows.append(("chain modes at rated current", _e("; ".join(
            f"{_num(m['frequency_hz'])} Hz, ζ {_num(m['damping_ratio'], 2)}" for m in modes)),
            ""))
    trims = doc.get("optimal_trims") or {}
    sig = doc.get("optimal_trims_sigma") or {}
    if trims:
        rows.append(("optimal trims", _e(
            f"offsets {_num(trims['offset_a_mA'])} ± {_num(sig.get('offset_a_mA'), 2)} / "
            f"{_num(trims['offset_b_mA'])} ± {_num(sig.get('offset_b_mA'), 2)} mA, gains "
            f"{_num(trims['gain_a'], 5)} / {_num(trims['gain_b'], 5)}"), ""))
    rows.append(("χ² per degree of freedom", _e(_num(doc.get("chi2_per_dof"), 3)), ""))
    return rows


def _nominal_section(doc: Mapping[str, Any]) -> str:
    nominal = doc["nominal"]
    rows = [_cells(_e(label), value, f"<span class='caution'>{_e(flag)}</span>" if flag else "",
                   css="implausible" if flag else "")
            for label, value, flag in _nominal_rows(nominal)]
    conditions = []
    for c in nominal.get("load_angles", []):
        label = _condition_of(c) or "—"
        angle = c.get("load_angle_rad")
        friction = c.get("friction_percent_of_rated_holding_torque")
        flags = [f for f in (implausible("load_angle_rad", angle),
                             implausible("percent_of_rated_holding_torque", friction)) if f]
        conditions.append(_cells(
            _e(label), _e(f"{_num(angle)} ± {_num(c.get('load_angle_sigma_rad'), 2)}"),
            _e(_num(friction, 3)),
            "<span class='caution'>" + _e("; ".join(flags)) + "</span>" if flags else "",
            numeric=(1, 2), css="implausible" if flags else ""))
    states = nominal.get("states") or {}
    state_rows = [_cells(f"<code>{_e(name)}</code>", _e(j["state"]), _e(_num(j["value"])),
                         _e(_num(j["bound"])), numeric=(2, 3))
                  for name, j in states.items()]
    parts = [
        "<p>What the nominal model found on all conditions, with 1σ. Values a motor on this "
        "fixture cannot physically have are flagged ⚠: the model fitted something else "
        "into them.</p>",
        _table(("quantity", "value ± 1σ", "plausibility"), rows),
        "<p>Per condition: the load angle the rotor sits at, and the drag it implies.</p>",
        _table(("condition", "load angle (rad) ± 1σ", "friction (% of rated holding torque)",
                "plausibility"), conditions),
    ]
    if state_rows:
        parts += ["<p>Parameters not simply fitted (at a bound, or fixed): not results.</p>",
                  _table(("parameter", "state", "value", "bound"), state_rows)]
    return "".join(parts)


def _skipped_section(d: Diagnosis) -> str:
    obs = d.observations
    settled = obs.model_settled
    head = (f"<p>{_e(obs.count)} segments used, {_e(settled)} of them from holds too short "
            "to judge their own settling (their start is the fitted chain's decay time and "
            "their σ is what the harmonics' own scatter says)")
    if obs.ringing:
        head += (f", {_e(obs.ringing)} from holds shorter than the chain's slowest decay (its "
                 "modes' ringing fitted out beside the harmonics, their σ including what that "
                 "costs)")
    head += ".</p>"
    if not obs.skipped:
        return head + "<p>No stretch of steady motion was skipped.</p>"
    rows = [_cells(_e(_num(s.start_s, 4)), _e(_num(s.stop_s, 4)), _e(s.reason),
                   numeric=(0, 1)) for s in obs.skipped]
    return head + _table(("from (s)", "to (s)", "why it was skipped"), rows)


def _located_section(d: Diagnosis) -> str:
    conditions = d.observations.conditions
    kinds = {LocatedKind.HARMONIC: "nominal residual",
             LocatedKind.UNEXPLAINED: "unexplained",
             LocatedKind.SENSOR_AXIS: "another sensor axis"}
    harmonic = [loc.as_dict(conditions) for loc in d.located if loc.kind in kinds]
    drift = [loc.as_dict(conditions) for loc in d.located
             if loc.kind is LocatedKind.PARAMETER_DRIFT]
    # What no id explains first: it is what the engineer must look at.
    harmonic.sort(key=lambda item: (item["kind"] == LocatedKind.HARMONIC.value,
                                    -float(item["chi2"])))
    shown = harmonic[:MAX_HARMONIC_ROWS]
    rows = []
    for item in shown:
        where = f"{_condition_of(item)}, order {item['order']}"
        if item["kind"] == LocatedKind.SENSOR_AXIS.value:
            where = f"{item['axis']} axis: {where}"
            detail = (f"{_num(item['residual_rms_mps2'], 3)} m/s² RMS beside "
                      f"{_num(item['measured_rms_mps2'], 3)} tangential")
        else:
            detail = (f"residual {_num(item['residual_rms_mps2'], 3)} of measured "
                      f"{_num(item['measured_rms_mps2'], 3)} m/s² RMS")
        rows.append(_located_row(kinds[LocatedKind(item["kind"])], where, item, detail))
    for item in drift:
        rows.append(_located_row("parameter drift", str(item["parameter"]), item,
                                 f"trend {item['trend']}"))
    note = (f"<p class='note'>{len(harmonic)} harmonic entries located, the "
            f"{len(shown)} strongest (by χ², what no id explains first) shown; {len(drift)} drift "
            "entries, all shown. Located: noise alone would give a χ² this large with "
            f"probability below {_constant(1.0 - SIGNIFICANT_CONFIDENCE)}.</p>")
    if not rows:
        return "<p>Nothing located: the nominal model's residual is noise everywhere.</p>" + note
    table = _table(("kind", "where", "χ² / dof", "ratio", "confidence", "detail"), rows)
    return table + note


def _located_row(kind: str, where: str, item: Mapping[str, Any], detail: str) -> str:
    chi2 = float(item["chi2"])
    dof = int(item["dof"])
    return _cells(
        _e(kind), _e(where), _e(f"{_chi2(chi2)} / {dof}"),
        _e(_num(chi2 / dof, 3) if dof else "—"), _e(_confidence(item["confidence"])),
        _e(detail), numeric=(2, 3, 4),
    )


def _rounds_section(d: Diagnosis) -> str:
    if not d.rounds:
        return "<p>No naming round was run.</p>"
    rows = []
    for rnd in d.rounds:
        chosen = rnd.chosen.label if rnd.chosen is not None else "none"
        rows.append(f"<tr class='round'><td colspan='7'>Models of {_e(rnd.size)} "
                    f"effect(s): chosen {_e(chosen)}</td></tr>")
        for test in sorted(rnd.tried, key=lambda t: t.larger.held.total):
            picked = rnd.chosen is not None and test.larger is rnd.chosen
            row = _cells(
                _e(test.larger.label), _e(test.smaller.label),
                _e(_chi2(test.chi2_gain)),
                _e(_chi2(max(test.f_threshold, test.bic_threshold))),
                _e(_chi2(test.held_gain)), _e(_chi2(test.added * test.noise)),
                "yes" if test.significant else "no",
                numeric=(2, 3, 4, 5),
            )
            rows.append(row.replace("<tr>", "<tr class='chosen'>", 1) if picked else row)
    return _table(("model", "against", "χ² gain", "needed (F, BIC)", "held-out gain",
                   "needed (noise × added)", "significant"), rows)


def _held_out_table(d: Diagnosis, labels: Sequence[str]) -> str:
    obs = d.observations
    rows = []
    for c, label in enumerate(labels):
        segments = int((obs.condition == c).sum())
        rows.append(_cells(
            _e(label), _e(segments), _e(2 * segments * obs.orders),
            _e(_chi2(d.nominal_held.chi2[c])), _e(_chi2(d.extended_held.chi2[c])),
            numeric=(1, 2, 3, 4),
        ))
    rows.append(_cells(
        "<b>total</b>", _e(obs.count), _e(2 * obs.count * obs.orders),
        f"<b>{_e(_chi2(d.nominal_held.total))}</b>",
        f"<b>{_e(_chi2(d.extended_held.total))}</b>", numeric=(1, 2, 3, 4),
    ))
    return _table(("condition held out", "segments", "dof", "nominal χ²", "extended χ²"), rows)


def _method() -> str:
    thresholds = (
        ("SIGNIFICANT_CONFIDENCE", SIGNIFICANT_CONFIDENCE,
         "a residual or drift is located, and a group's F test passes, when noise alone "
         "would reach its χ² with probability below 1 minus this"),
        ("MAX_EFFECTS", MAX_EFFECTS, "most effects combined in one model"),
        ("RIVAL_Z", RIVAL_Z,
         "a rival whose held-out χ² exceeds the winner's by less than this many standard "
         "errors (paired over the residuals) cannot be told apart from it"),
        ("UNEXPLAINED_RATIO", UNEXPLAINED_RATIO,
         "held-out χ² per value beyond this (plus four standard deviations of noise) is a "
         "significant residual left"),
    )
    rows = [_cells(f"<code>{_e(name)}</code>", _e(_constant(value)), _e(meaning), numeric=(1,))
            for name, value, meaning in thresholds]
    return (
        "<p>The <b>nominal model</b> is the paper's torque model (two phases with sinusoidal "
        "mutual inductance, the amplifier's offsets and gain errors on the commanded "
        "currents) driving the chain the fixture declares (a rigid disk on the shaft, or a "
        "belt to a load with the metadata's gear ratio and unknown stiffness, damping and "
        "inertia ratio), seen through the sensor's own low-pass, with one load angle per "
        "condition, from which each trim step's rotor slips along its magnetic spring until "
        "its mean torque meets the drag again. It is fitted as an <b>equation error</b> on "
        "the measured motion at every harmonic order, plus the mean torque balance of every "
        "segment, weighted by each harmonic's measured noise, so χ² counts the misfit in "
        "units of the noise.</p>"
        "<p>Every model is also judged on conditions <b>held out</b> of its fit (each "
        "condition in turn predicted by the model fitted to the others, by a one-step "
        "approximation of the refit). An effect's term group is added when it lowers χ² by "
        "more than noise explains for the parameters it adds (an F test against the larger "
        "model's own χ² per degree of freedom, and Schwarz's criterion) and lowers the "
        "held-out χ² by more than the noise per added parameter. Models of up to "
        f"{_e(MAX_EFFECTS)} effects are searched with a beam, then any group the others make "
        "unnecessary is dropped. When the best model still leaves a significant held-out "
        "residual, an id is kept only if it explains more of the mismatch than is left: "
        "physics no id describes is reported as unexplained, never as the nearest id.</p>"
        + _table(("threshold", "value", "meaning"), rows)
    )


def render_html(diagnosis: Diagnosis, *, source: str) -> str:
    """The report page as text (``write_report`` stores it)."""
    doc = diagnosis.to_dict()
    serial = diagnosis.observations.metadata.serial
    labels = [key.label() for key in diagnosis.observations.conditions]
    parts = [
        f"<h1>Diagnosis of drive {_e(serial)}</h1>",
        f"<p class='note'>Recording: <span class='path'>{_e(source)}</span></p>",
        _verdict(diagnosis, doc),
        "<h2>Named effects</h2>",
        _effects_section(diagnosis),
        "<h2>Nominal model</h2>",
        _nominal_section(doc),
        "<h2>Measured vs nominal vs extended</h2>",
        _figure(_harmonics_figure(diagnosis, labels),
                "Magnitude of each harmonic of the tangential acceleration, per segment "
                "(segments of one condition side by side, in recording order). Error bars: "
                "±σ, the measured phasor's standard uncertainty. Model points are each "
                "model's prediction for that segment, fitted to all conditions."),
        "<h2>Where the nominal model fails</h2>",
        _figure(_residual_map_figure(diagnosis, labels),
                "χ² per degree of freedom of each model's residual, per harmonic order and "
                "condition (summed over the condition's segments, both parts of each "
                "phasor). 1 is the noise; both maps share one colour scale."),
        "<h2>Trims re-estimated per condition</h2>",
        _figure(_trims_figure(diagnosis, labels),
                "The optimal trims (amplifier constants) solved again on each condition "
                "alone, the rest of the nominal model held. Constants that move with current "
                "or speed beyond their σ are something the nominal model lacks."),
        "<h2>Located disagreements</h2>",
        _located_section(diagnosis),
        "<h2>Holds used and skipped</h2>",
        _skipped_section(diagnosis),
        "<h2>Naming rounds</h2>",
        _rounds_section(diagnosis),
        "<h2>Held-out χ² per condition</h2>",
        _figure(_held_out_figure(diagnosis, labels),
                "χ² of each condition predicted by the model fitted without it."),
        _held_out_table(diagnosis, labels),
        "<h2>Method</h2>",
        _method(),
    ]
    return page(f"Diagnosis of {serial}", parts)


def write_report(diagnosis: Diagnosis, path: Path, *, source: str) -> Path:
    """Write the report page; readers see the old file or the whole new one, never half."""
    write_text_atomically(Path(path), render_html(diagnosis, source=source))
    return Path(path)
