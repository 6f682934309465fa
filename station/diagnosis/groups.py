"""What the diagnosis knows about each term group besides its equations.

The equations are in ``station.diagnosis.model`` (one model, every group a
switch on it). Here, per vocabulary id: where a fit of the group should start
(the nonlinear parameters are multimodal: a drifting clock's rate, a coupling's
frequency), how its fitted parameters read in physical or relative units with
their 1σ, and which experiment would separate it from a rival the data cannot
tell it from.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.fit import Fit, covariance, screen
from station.diagnosis.model import (
    DETENT_ORDERS,
    DISTORTION_ORDERS,
    FLUX_ORDERS,
    HEALTHY_COULOMB,
    MIN_CLOCK_PPM,
    ChainKind,
    Model,
    saturation_shapes,
)

Starts = dict[str, list[float]]


def _starts_resonance(model: Model, p: NDArray[np.float64]) -> list[Starts]:
    hz = [30.0, 60.0, 120.0, 240.0, 480.0, 960.0, 1900.0]
    return [{"log_coupling_hz": [math.log(f)], "coupling_fraction": [frac]}
            for f in hz for frac in (0.2, 0.6)]


SPLIT_GRID = (0.25, 0.6)
"""Shares of what lay beyond a belt that fitted a coupling that stay at the pulley
(``belt_as_coupling``); the rest is the load behind the belt."""
STIFF_BELT_GRID = (2.5, 6.0)
"""The belt's frequency where a coupling took its place, in multiples of the highest
mode below it (``belt_as_coupling``)."""


def belt_as_coupling(model: Model, p: NDArray[np.float64]) -> list[Starts]:
    """Chains for a coupling group on a belt whose model without it (``p``) let its belt
    be the coupling: the belt's spring becomes the coupling's, what lay beyond it is
    split between the pulley and the load, and a stiffer belt is put between them.

    A belt model without the coupling fits the chain's lowest mode whichever spring it
    is on: on benchmark trial detent_torque+load_resonance@1898614460 (rotor, coupling at
    64 Hz, pulley, belt at 405 Hz, load) every model without the coupling had its belt at
    43.7 Hz with the rotor alone at 307 Hz and all else beyond, the plant's lowest mode on
    its coupling. From there no coupling start found the plant's chain (χ² 1,310, where the
    plant's own chain polished to 1,029), and current-loop lag was named in its place.
    The inverse of ``diagnose.coupling_as_belt``: the same mechanics, with the springs
    swapped. These chains start far from the base, so they are ranked among themselves
    (``diagnose.fit_spec``): after a short polish beside the spread starts, the one that
    polished to the plant's chain stood eighth of twenty and was cut.
    """
    if model.spec.chain is not ChainKind.BELT:
        return []
    sl = model.layout.slices

    def value(name: str) -> float:
        return float(p[sl[name]][0])

    beyond = math.exp(value("log_load_ratio"))  # in units of the inertia before the belt
    belt_hz = math.exp(value("log_belt_hz"))
    rotor_hz = math.exp(value("log_rotor_hz"))
    out: list[Starts] = []
    for share in SPLIT_GRID:
        grows = 1.0 + share * beyond  # the inertia before the new belt, as before the old
        coupling_hz = belt_hz / math.sqrt(share)
        below = max(coupling_hz, rotor_hz / math.sqrt(grows))
        for stiff in STIFF_BELT_GRID:
            out.append({
                "log_rotor_hz": [math.log(rotor_hz) - 0.5 * math.log(grows)],
                "rotor_damping_ratio": [value("rotor_damping_ratio") / math.sqrt(grows)],
                "coupling_fraction": [share * beyond / grows],
                "log_coupling_hz": [math.log(coupling_hz)],
                "coupling_damping_ratio": [value("belt_damping_ratio") / math.sqrt(share)],
                "log_load_ratio": [math.log((1.0 - share) * beyond / grows)],
                "log_belt_hz": [math.log(stiff * below)],
            })
    return out


def _starts_lag(model: Model, p: NDArray[np.float64]) -> list[Starts]:
    # A lag looks like a negative sensor delay: start with the sensor's share moved over.
    a1 = float(p[model.layout.slices["sensor_a1_ms"]][0])
    return [{"current_lag_ms": [lag, lag], "sensor_a1_ms": [a1 + lag]}
            for lag in (0.2, 0.6, 1.5, 4.0)]


def _starts_friction(model: Model, p: NDArray[np.float64]) -> list[Starts]:
    return [{"log_friction_smoothing": [math.log(eps)]} for eps in (0.005, 0.02, 0.08)]


DELAY_PROBE_S = 1e-5
"""The extra delay a segment's data are shifted by to difference the model's error: far
below a SYNC period and below a radian at every order."""


def _shifted(model: Model, delay: NDArray[np.float64]) -> Model:
    """The model on data advanced by ``delay`` (s, per segment): each order k turned by
    e^{jkωd}, which undoes a sensor that sampled that much late."""
    obs = model.obs
    beyond = obs.beyond
    if model.beyond is not None:
        beyond = model.beyond * np.exp(model.jw_beyond * delay[:, None])
    return Model(model.spec, replace(obs, phasors=obs.phasors * np.exp(model.jw * delay[:, None]),
                                     beyond=beyond))


def segment_delays(model: Model, p: NDArray[np.float64], steps: int = 2
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each segment's extra delay (s) against the model at ``p``, and its weight (the
    information the segment carries about it): Gauss-Newton steps on the model's own
    weighted error, the segment's data shifted in time.

    The phase of measured over predicted phasors is no measure of it: the model's
    prediction is an equation error evaluated on the measured motion, so below the
    rotor's mode it follows the data, and a drifting clock's sawtooth came out at half
    its size (0.10 of a period per hold against the plant's 0.22 on a development
    trial), too little for its rate to stand out of the periodogram.
    """
    delay = np.zeros(model.obs.count)
    weight = np.zeros(model.obs.count)
    for _ in range(steps):
        here = _shifted(model, delay)
        base = here.weighted_error(p)
        slope = (_shifted(model, delay + DELAY_PROBE_S).weighted_error(p) - base) / DELAY_PROBE_S
        weight = np.sum(np.abs(slope) ** 2, axis=1)
        delay = delay - np.sum((np.conj(slope) * base).real, axis=1) / np.maximum(weight, 1e-300)
    return delay, weight


CLOCK_RATES_PPM = np.arange(-3000.0, 3000.5, 1.0)
"""Drift rates scanned by the periodogram (a sawtooth of N samples resolves 1/N)."""
CLOCK_REFINE_PPM = np.linspace(-1.0, 1.0, 81)
"""Offsets about a peak of the scan where it is refined."""


@dataclass(frozen=True)
class ClockScan:
    """The segments' own delays against a model (s) with their weights, and the
    periodogram over drift rates they make (``_starts_clock``). ``centre``: each
    segment's middle sample; ``middle``: the sample the model counts the clock's phase
    from (``clock_middle``)."""

    delay: NDArray[np.float64]
    weight: NDArray[np.float64]
    centre: NDArray[np.float64]
    period: float
    middle: float

    @classmethod
    def of(cls, model: Model, p: NDArray[np.float64]) -> ClockScan:
        delay, weight = segment_delays(model, p)
        return cls(delay, weight, model.obs.span.mean(axis=1),
                   model.obs.metadata.sync_period_s, model.clock_middle)

    def sums(self, rates: NDArray[np.float64]) -> NDArray[np.complex128]:
        z = self.weight[:, None] * np.exp(2j * np.pi * (
            self.delay[:, None] / self.period + self.centre[:, None] * rates[None, :] * 1e-6))
        return np.asarray(z.sum(axis=0), dtype=np.complex128)

    def window(self, rates: NDArray[np.float64]) -> NDArray[np.float64]:
        """How alike two rates ``rates`` apart look at the segments' centres (1: the same
        delays there): the schedule's rhythm makes a rate's aliases."""
        z = self.weight[:, None] * np.exp(2j * np.pi * self.centre[:, None] * rates[None, :] * 1e-6)
        out: NDArray[np.float64] = np.abs(z.sum(axis=0)) / max(float(self.weight.sum()), 1e-300)
        return out

    def peaks(self, count: int) -> list[Starts]:
        """The ``count`` strongest rates of the periodogram, strongest first, each refined
        and with the sawtooth's phase its sum says."""
        power = np.abs(self.sums(CLOCK_RATES_PPM))
        out: list[Starts] = []
        for index in np.argsort(power)[::-1][:2000]:
            rate = float(CLOCK_RATES_PPM[index])
            if any(abs(rate - s["clock_drift_ppm"][0]) < 20.0 for s in out):
                continue
            # The scan's step is about the basin's width for a long recording (the last
            # sample moves by N·δ periods): the peak is refined before it is a start.
            fine = rate + CLOCK_REFINE_PPM
            total = self.sums(fine)
            best = int(np.argmax(np.abs(total)))
            # The sum's angle is the phase at the first SYNC; the model counts it from the
            # recording's middle.
            phase = float(np.angle(total[best]) / (2 * np.pi)
                          - self.middle * fine[best] * 1e-6) % 1.0
            out.append({"clock_drift_ppm": [float(fine[best])], "clock_phase": [phase]})
            if len(out) == count:
                break
        return out

    def line(self) -> list[Starts]:
        slope = np.polyfit(self.centre, self.delay, 1, w=np.sqrt(self.weight))[0]
        return [{"clock_drift_ppm": [float(-slope / self.period * 1e6)]}]

    def family(self, rates: list[float]) -> list[float]:
        """The strongest of ``rates`` (strongest first) that is no alias of a clock
        without drift, and its own aliases among them: rates the segments' centres cannot
        tell apart, which only the fit, sample by sample, can."""
        window = self.window(np.asarray(rates))
        lead = next((r for r, w in zip(rates, window, strict=True) if w < ALIAS_WINDOW), None)
        if lead is None:
            return []
        apart = self.window(np.asarray(rates) - lead)
        # One rate per alias: the periodogram's side lobes (a lobe is about 10⁶ over the
        # recording's length in samples, in ppm) are the same basin again.
        lobe = 1e6 / max(float(np.ptp(self.centre)), 1.0)
        out: list[float] = []
        for rate, w in zip(rates, apart, strict=True):
            if w >= ALIAS_WINDOW and all(abs(rate - r) > lobe for r in out):
                out.append(rate)
        return out


def _starts_clock(model: Model, p: NDArray[np.float64], peaks: int = 3) -> list[Starts]:
    """Where the segments' own delays say the clock drifts.

    A clock off by δ that holds its latest sample delays sample n by T·frac(c − nδ): the
    phasor e^{2πi·d/T} then turns by 2πδ per sample, so the rate that best lines the
    segments' delays up is the peak of a periodogram over δ. A clock that stamps its own
    samples drifts as a line instead: a regression.
    """
    scan = ClockScan.of(model, p)
    return scan.peaks(peaks) if model.layout.has("clock_phase") else scan.line()


def scan_trials(model: Model) -> float:
    """How many independent models the groups of ``model`` were chosen among by a scan.

    The clock's rate is the best of a periodogram over thousands of rates: on noise alone
    its gain is the largest of that many chances, not one (the look-elsewhere effect).
    A sawtooth over N samples resolves rates 10⁶/N ppm apart, so the scan holds about
    (range · N / 10⁶) independent rates. A clock that stamps its own samples (a line) is
    a regression, and no group but the clock is scanned.
    """
    if not model.layout.has("clock_phase"):
        return 1.0
    span = float(model.obs.span[-1, 1] - model.obs.span[0, 0])
    scanned = float(CLOCK_RATES_PPM[-1] - CLOCK_RATES_PPM[0])
    return max(1.0, scanned * 1e-6 * span)


CLOCK_PEAKS = 12
"""Periodogram peaks screened: segments spaced alike alias the true rate, and their
delays are noisy, so the true rate need not be the highest peak (a development trial
had it ninth, behind the schedule's own rhythm at ±1390 and ±2780 ppm)."""

CLOCK_PHASES = 8
"""Sawtooth phases tried at the periodogram's rate: the phase sets where the delays wrap,
and a fit started half a period off settles in a wrong basin (from the true rate, starts
within about ±0.15 of a period converged)."""


CLOCK_KEEP = 4
"""Screened clock starts that are fitted, each the best phase of its rate and delay: the
basin of the true sawtooth is narrow in phase and sensor delay together."""

ALIAS_WINDOW = 0.5
"""Two rates whose sums over the segments' centres agree at least this well (1: the same
phase at every centre) are aliases: holds of equal length repeat every 1/length."""


def _estimate_clock(model: Model, p: NDArray[np.float64]) -> list[Starts]:
    """At each of the periodogram's peaks: the sawtooth's phase over a grid, with the
    sensor's delay as it is and less the sawtooth's mean (half a period, which the base
    model had folded into it); the ``CLOCK_KEEP`` that fit best once the linear
    parameters are solved, and the best of each rate in the strongest peak's family
    (``ClockScan.family``). A peak at no drift is the base model again and is passed
    over.

    The screen alone ranks the rates from a base that bent its chain to hide the clock:
    on a belt whose mode sat at the fourth order (sensor_clock_drift@572933410), the
    true rate (−169.6 ppm, the periodogram's strongest) screened at 266,197 against the
    base's 200,578 and was dropped for its alias 2160 ppm (one sawtooth more per hold),
    which polished to 156,125; from the true rate the polish ended at 865.
    """
    scan = ClockScan.of(model, p)
    if not model.layout.has("clock_phase"):
        return scan.line()
    peaks = [peak for peak in scan.peaks(CLOCK_PEAKS)
             if abs(peak["clock_drift_ppm"][0]) >= MIN_CLOCK_PPM]
    a1 = float(p[model.layout.slices["sensor_a1_ms"]][0])
    half = 0.5e3 * model.obs.metadata.sync_period_s
    tried: list[Starts] = [
        {**peak, "clock_phase": [phase], "sensor_a1_ms": [delay]}
        for peak in peaks
        for phase in (peak["clock_phase"][0] + np.arange(CLOCK_PHASES) / CLOCK_PHASES) % 1.0
        for delay in (a1, max(0.0, a1 - half))
    ]
    family = scan.family([peak["clock_drift_ppm"][0] for peak in peaks])
    starts = [model.with_values(p, values) for values in tried]
    out: dict[tuple[float, float], Starts] = {}
    kin: dict[float, Starts] = {}
    for _, x in screen(model, starts):
        values = {name: [float(v) for v in x[model.layout.slices[name]]]
                  for name in ("clock_drift_ppm", "clock_phase", "sensor_a1_ms")}
        rate = values["clock_drift_ppm"][0]
        # The best phase of each rate and delay: the delay and the phase trade against
        # each other, and the better basin is often the one the screen ranks second.
        if len(out) < CLOCK_KEEP:
            out.setdefault((rate, values["sensor_a1_ms"][0]), values)
        if any(abs(rate - r) < 1e-6 for r in family):
            kin.setdefault(rate, values)
    chosen = list(out.values())
    chosen += [v for rate, v in kin.items()
               if not any(abs(c["clock_drift_ppm"][0] - rate) < 1e-6 for c in chosen)]
    return chosen


GROUP_ESTIMATES: dict[Effect, Callable[[Model, NDArray[np.float64]], list[Starts]]] = {
    Effect.SENSOR_CLOCK_DRIFT: _estimate_clock,
}
"""Groups whose nonlinear parameters the data can estimate before any search: that start
is always searched from, whatever its χ² before the search."""

GROUP_STARTS: dict[Effect, Callable[[Model, NDArray[np.float64]], list[Starts]]] = {
    Effect.LOAD_RESONANCE: _starts_resonance,
    Effect.CURRENT_LOOP_LAG: _starts_lag,
    Effect.FRICTION: _starts_friction,
    Effect.SENSOR_CLOCK_DRIFT: _starts_clock,
}
"""Groups whose nonlinear parameters need more than one start; the linear ones start at
zero (absent) and are solved."""

GROUP_TOURNAMENT = frozenset({Effect.LOAD_RESONANCE})
"""Groups whose every start goes to the short polish (``fit.best_of``) instead of the
best two by their χ² before any polish: a coupling's χ² there says little about its
basin. Solving a strong detent's linear parts at each start favours any frequency where
the ripple it leaves is large; on development belt @1838253693 (detent torque and a
second compliance at 285 Hz) the two best-ranked starts settled at χ² 690, one ranked
lower at 512 with the coupling at 296 Hz, and the coupling was named only then.

Nor does their tournament have a first heat (``fit.best_of``): on development belt
load_resonance@202 (rotor, coupling and pulley, belt, load) the start that polished to the
plant's chain (χ² 1,206) stood at 1.2 million after three evaluations, 15th of 20 (seven of
the ten kept had not left the base), and was cut; its short polish would have been the best."""


# --------------------------------------------------------------------------- parameters
def _pair(values: NDArray[np.float64], sigma: NDArray[np.float64], scale: float
          ) -> dict[str, float]:
    """A (sin, cos) or (re, im) coefficient pair as magnitude ± σ and phase."""
    mag = math.hypot(values[0], values[1])
    err = math.hypot(sigma[0], sigma[1]) / math.sqrt(2.0)
    return {"magnitude": mag * scale, "sigma": err * scale,
            "phase_rad": math.atan2(values[1], values[0])}


def _value(fit: Fit, sig: NDArray[np.float64], name: str, scale: float = 1.0
           ) -> tuple[float, float]:
    sl = fit.model.layout.slices[name]
    return float(fit.params[sl][0]) * scale, float(sig[sl][0]) * scale


def _log_value(fit: Fit, sig: NDArray[np.float64], name: str) -> tuple[float, float]:
    value, err = _value(fit, sig, name)
    return math.exp(value), math.exp(value) * err


def _flux(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["flux"]
    v, s = fit.params[sl], sig[sl]
    out: dict[str, Any] = {}
    for i, j in enumerate(FLUX_ORDERS):
        for p, phase in enumerate(("a", "b")):
            k = 4 * i + 2 * p
            pair = _pair(v[k:k + 2], s[k:k + 2], 100.0)
            out[f"order_{j}_phase_{phase}"] = {
                "relative_to_Lm1_percent": pair["magnitude"],
                "sigma_percent": pair["sigma"], "phase_rad": pair["phase_rad"]}
    return out


def _distortion(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["distortion"]
    v, s = fit.params[sl], sig[sl]
    out: dict[str, Any] = {}
    for i, h in enumerate(DISTORTION_ORDERS):
        for p, phase in enumerate(("a", "b")):
            k = 4 * i + 2 * p
            pair = _pair(np.array([v[k], -v[k + 1]]), s[k:k + 2], 100.0)
            out[f"order_{h}_phase_{phase}"] = {
                "relative_to_fundamental_percent": pair["magnitude"],
                "sigma_percent": pair["sigma"], "phase_rad": pair["phase_rad"]}
    return out


def _detent(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["detent"]
    v, s = fit.params[sl], sig[sl]
    rated = fit.model.rated_A
    out: dict[str, Any] = {}
    for i, d in enumerate(DETENT_ORDERS):
        pair = _pair(v[2 * i:2 * i + 2], s[2 * i:2 * i + 2], 100.0 / rated)
        out[f"order_{d}"] = {"peak_percent_of_rated_holding_torque": pair["magnitude"],
                             "sigma_percent": pair["sigma"], "phase_rad": pair["phase_rad"]}
    return out


def _reluctance(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    rated = fit.model.rated_A
    value, err = _value(fit, sig, "reluctance", 100.0 * rated)
    # τ_vr peaks at Nr·L1·I²; in Kt units per A² the coefficient is Nr·L1/Kt.
    return {"peak_percent_of_holding_torque_at_rated": value, "sigma_percent": err}


def _resonance(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    hz, hz_err = _log_value(fit, sig, "log_coupling_hz")
    zeta, zeta_err = _value(fit, sig, "coupling_damping_ratio")
    frac, frac_err = _value(fit, sig, "coupling_fraction")
    where = "rotor and disk" if fit.model.spec.chain is ChainKind.RIGID else "rotor and pulley"
    return {"coupling_resonance_hz": hz, "coupling_resonance_hz_sigma": hz_err,
            "damping_ratio": zeta, "damping_ratio_sigma": zeta_err,
            "inertia_fraction_beyond_coupling": frac,
            "inertia_fraction_beyond_coupling_sigma": frac_err,
            "between": where}


def _lag(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["current_lag_ms"]
    v, s = fit.params[sl], sig[sl]
    return {
        "time_constant_a_ms": float(v[0]), "time_constant_a_ms_sigma": float(s[0]),
        "time_constant_b_ms": float(v[1]), "time_constant_b_ms_sigma": float(s[1]),
        "bandwidth_a_hz": 1e3 / (2 * math.pi * float(v[0])) if v[0] > 0 else None,
        "bandwidth_b_hz": 1e3 / (2 * math.pi * float(v[1])) if v[1] > 0 else None,
        "note": ("a current loop's lag and the sensor's own delay look alike at low "
                 "frequency; the time constants are what the sensor's delay cannot hide"),
    }


def _friction(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["friction_coulomb"]
    v, s = fit.params[sl], sig[sl]
    rated = fit.model.rated_A
    ratio = fit.model.gear_ratio
    # Coulomb levels are load torques in Kt units; seen at the motor they are ·n.
    scale = 100.0 * ratio / rated
    out: dict[str, Any] = {
        "coulomb_forward_percent_of_rated_holding_torque": float(v[0]) * scale,
        "coulomb_forward_sigma_percent": float(s[0]) * scale,
        "coulomb_reverse_percent_of_rated_holding_torque": float(v[1]) * scale,
        "coulomb_reverse_sigma_percent": float(s[1]) * scale,
        "smoothing_relative_to_slowest_speed": math.exp(fit.scalar("log_friction_smoothing")),
        "healthy_coulomb_limit_percent": 100.0 * HEALTHY_COULOMB,
        "note": ("the whole Coulomb levels, the bearings' healthy share among them; viscous "
                 "friction is in the chain's damping (nominal)"),
    }
    return out


def _clock(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    value, err = _value(fit, sig, "clock_drift_ppm")
    out: dict[str, Any] = {"clock_drift_ppm": value, "clock_drift_ppm_sigma": err,
                           "sample_timing": ("latest sample held for each SYNC"
                                             if fit.model.spec.clock_wraps
                                             else "sample times drift without wrapping")}
    if fit.model.layout.has("clock_phase"):
        # Reported at the first SYNC, where a reader of the recording would count it from.
        at_start = fit.scalar("clock_phase") + fit.model.clock_middle * value * 1e-6
        out["sample_phase"] = float(at_start) % 1.0
    return out


def _saturation(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    model = fit.model
    sl = model.layout.slices["saturation"]
    w = fit.params[sl]
    cov = covariance(fit)[sl, sl]

    def drop(current_A: float) -> tuple[float, float]:
        # The fall is linear in the two weights, so its σ is exact through their covariance.
        shapes = np.array(saturation_shapes(np.array((current_A / model.largest_A) ** 2)))
        return float(shapes @ w), math.sqrt(max(float(shapes @ cov @ shapes), 0.0))

    largest, largest_sig = drop(model.largest_A)
    half, half_sig = drop(0.5 * model.largest_A)
    return {"kt_drop_at_largest_current_percent": 100.0 * largest,
            "sigma_percent": 100.0 * largest_sig,
            "largest_current_mA": 1000.0 * model.largest_A,
            "kt_drop_at_half_that_percent": 100.0 * half,
            "kt_drop_at_half_that_sigma_percent": 100.0 * half_sig,
            "law": "Kt(|i|)/Kt(0) = 1 − w1·(2u² − u⁴) − w2·u⁴, u = |i|/I_max, w1, w2 ≥ 0",
            "w1": float(w[0]), "w1_sigma": float(sig[sl][0]),
            "w2": float(w[1]), "w2_sigma": float(sig[sl][1])}


def _eccentricity(fit: Fit, sig: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["eccentricity"]
    pair = _pair(fit.params[sl], sig[sl], 100.0)
    out = {"torque_modulation_percent": pair["magnitude"], "sigma_percent": pair["sigma"],
           "phase_rad": pair["phase_rad"],
           "note": "once per mechanical revolution of the rotor, on the magnet's torque"}
    if fit.model.layout.has("unbalance"):
        sl = fit.model.layout.slices["unbalance"]
        # (U·cos φ, U·sin φ) of the load U·sin(θ + φ): φ is the pair's own phase.
        load = _pair(fit.params[sl], sig[sl], 100.0)
        out.update({
            "unbalance_load_percent": load["magnitude"],
            "unbalance_sigma_percent": load["sigma"],
            "unbalance_phase_rad": load["phase_rad"],
            "unbalance_note": ("load U·sin(θ + φ) on the rotor, θ its mechanical angle, U in "
                               "percent of the holding torque at the largest current"),
        })
    return out


GROUP_PARAMETERS: dict[Effect, Callable[[Fit, NDArray[np.float64]], dict[str, Any]]] = {
    Effect.FLUX_HARMONICS: _flux,
    Effect.CURRENT_DISTORTION: _distortion,
    Effect.DETENT_TORQUE: _detent,
    Effect.RELUCTANCE_TORQUE: _reluctance,
    Effect.LOAD_RESONANCE: _resonance,
    Effect.CURRENT_LOOP_LAG: _lag,
    Effect.FRICTION: _friction,
    Effect.SENSOR_CLOCK_DRIFT: _clock,
    Effect.MAGNETIC_SATURATION: _saturation,
    Effect.ROTOR_ECCENTRICITY: _eccentricity,
}


# --------------------------------------------------------------------------- separating
HEALTHY_PART: dict[Effect, str] = {
    Effect.FRICTION: (
        "Kept by the nominal model: every motor's bearings have Coulomb friction (CLI.md: up "
        "to 10 % of the rated holding torque, either direction) and viscous drag, fitted "
        "and reported with σ under nominal.friction. Named only past a guarded ceiling "
        "(model.HEALTHY_COULOMB_GUARD) or as another form."),
    Effect.LOAD_RESONANCE: (
        "Kept by the nominal model: a belt the metadata declares is nominal physics, its "
        "mode fitted and reported. Named for a compliance the fixture does not declare."),
    Effect.SENSOR_CLOCK_DRIFT: (
        "Kept by the nominal model: a clock within a few ppm of SYNC's is the sensor's "
        "constant delay (model.MIN_CLOCK_PPM, the group's null band); every crystal drifts "
        "that much. Named beyond it."),
    Effect.CURRENT_LOOP_LAG: (
        "Kept by the nominal model in part: a loop far faster than the recorded orders is a "
        "delay the sensor's own low-pass stands for. Named where the time constants show "
        "what no sensor delay can hide."),
    Effect.FLUX_HARMONICS: (
        "Nothing kept: a real motor has some, but what a 1 A characterization resolves is "
        "ripple the customer feels and the compensation table removes, so it is named."),
    Effect.DETENT_TORQUE: (
        "Nothing kept: every hybrid stepper cogs a little, but cogging the recording "
        "resolves is ripple no trim removes, so it is named with its size for QA to judge."),
    Effect.RELUCTANCE_TORQUE: (
        "Nothing kept: named when the torque's growth with I² is resolved."),
    Effect.CURRENT_DISTORTION: (
        "Nothing kept: every drive's waveform is a little off, but what the recording "
        "resolves moves the optimal trims and the ripple, so it is named."),
    Effect.MAGNETIC_SATURATION: (
        "Nothing kept: every motor saturates somewhat near rated current, but named only "
        "when Kt's fall over the recorded currents is resolved."),
    Effect.ROTOR_ECCENTRICITY: (
        "Nothing kept: some runout is in every rotor, but named only when the "
        "once-per-revolution terms beat themselves fitted at wrong angles."),
}
"""What a healthy unit always has some of, for each id, and what was decided: kept by the
nominal model (fitted, reported, never named) or named whenever the data resolve it."""


SEPARATING_EXPERIMENTS: dict[frozenset[Effect], str] = {
    frozenset({Effect.FLUX_HARMONICS, Effect.CURRENT_DISTORTION}): (
        "record the phase currents (drive current sense or a current probe) while running: "
        "distortion shows in the current waveform, flux harmonics do not; or back-drive the "
        "motor with the drive disabled and record the back-EMF, whose harmonics are the flux's"
    ),
    frozenset({Effect.FLUX_HARMONICS, Effect.DETENT_TORQUE}): (
        "repeat the characterization at more currents including a low one: cogging torque "
        "does not change with current, flux-harmonic torque grows with it"
    ),
    frozenset({Effect.DETENT_TORQUE, Effect.CURRENT_DISTORTION}): (
        "record the drive's phase currents, or run at more currents: cogging does not change "
        "with current, distortion torque grows with it"
    ),
    frozenset({Effect.LOAD_RESONANCE, Effect.RELUCTANCE_TORQUE}): (
        "tap test or speed sweep with the rotor held: a compliant coupling keeps its frequency "
        "whatever the current, the magnetic spring's frequency moves with it"
    ),
    frozenset({Effect.MAGNETIC_SATURATION, Effect.RELUCTANCE_TORQUE}): (
        "characterize at more currents (a third of rated, and above rated if the drive allows "
        "it briefly): saturation's loss of torque grows faster than I², reluctance's spring "
        "grows as I²; or measure the holding torque against current with a torque wrench"
    ),
    frozenset({Effect.CURRENT_LOOP_LAG, Effect.SENSOR_CLOCK_DRIFT}): (
        "repeat with the sensor's sampling locked to SYNC (or a sensor whose clock is "
        "known): a lagging current loop keeps its phase shift, a drifting clock's changes "
        "along the recording"
    ),
    frozenset({Effect.CURRENT_LOOP_LAG, Effect.LOAD_RESONANCE}): (
        "record the phase currents while running: a lagging loop shows its phase shift "
        "in the current against the commanded angle; a compliance does not"
    ),
    frozenset({Effect.FRICTION, Effect.LOAD_RESONANCE}): (
        "repeat at higher speeds with the unit trimmed: friction's harmonics need the load "
        "to stall within a period, a compliance's response does not"
    ),
    frozenset({Effect.ROTOR_ECCENTRICITY, Effect.SENSOR_CLOCK_DRIFT}): (
        "hold one condition for several mechanical revolutions: eccentricity repeats with the "
        "rotor's angle, a drifting clock with time"
    ),
}
DEFAULT_EXPERIMENT = (
    "repeat the characterization with more speeds and currents, and trim steps of both signs, "
    "so that the two term groups' signatures (order, current scaling, load angle) part"
)


def separating_experiment(a: Effect, b: Effect) -> str:
    return SEPARATING_EXPERIMENTS.get(frozenset({a, b}), DEFAULT_EXPERIMENT)
