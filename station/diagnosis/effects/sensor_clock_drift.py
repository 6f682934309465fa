"""Sensor clock drift: a MEMS node whose sample clock runs off SYNC's, so each sample's
delay grows along the recording and wraps (the node holds its latest sample for each SYNC)
or drifts without wrapping (it stamps its own samples).

A clock within a few ppm of SYNC's is the sensor's constant delay, which every crystal has
and the nominal model keeps (``MIN_CLOCK_PPM``, the block's null band). The group's rate is
found by a periodogram over the segments' own delays (``ClockScan``) before any search.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms, Params, Screen, Starts
from station.diagnosis.effects.readings import sigmas, value
from station.diagnosis.hooks import Hooks, Phasors, Role
from station.diagnosis.layout import Block

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.observations import Observations

MIN_CLOCK_PPM = 5.0
"""A clock rate nearer SYNC's than this is the constant delay the base model has: over a
minute's recording it moves the samples by a third of a SYNC period at most, and the
clocks the group is for run tens to hundreds of ppm off. Periodogram peaks below it are
not started from, and a fit that ends below it is not a drifting clock
(``Block.null_band``)."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    drift = Block("clock_drift_ppm", 1, 0.0, -5000.0, 5000.0, rejects=(-1, 1),
                  null_band=MIN_CLOCK_PPM)
    if not spec.clock_wraps:
        return [drift]  # a constant part would be the sensor's delay again
    return [drift, Block("clock_phase", 1, 0.5, -0.5, 1.5)]


CLOCK_POINTS = 32
"""Sample times per segment where a clock that does not wrap is evaluated."""


def clock_middle(obs: Observations) -> float:
    """The sample number (from the first SYNC) the clock's phase is counted from: the
    recording's middle, where a change of rate moves no sample, so that rate and phase are
    nearly independent and a fit can walk their narrow valley."""
    return 0.5 * (float(obs.span[0, 0]) + float(obs.span[-1, 1]))


def sawtooth_mean(u0: NDArray[np.float64], u1: NDArray[np.float64],
                  a: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Mean of e^{-ja·frac(u)} for u running linearly from ``u0`` to ``u1`` (per row),
    for each column of ``a``: a wrapping clock's delays over a segment are T·frac(u).

    With G(v) = ∫₀ᵛ e^{-jax} dx = (1 − e^{-jav})/(ja), an antiderivative of the
    periodic integrand is F(u) = ⌊u⌋·G(1) + G(frac u), and the mean is
    [F(u₀) − F(u₁)]/(u₀ − u₁): exact, and smooth in the clock's rate and phase.
    """
    small = np.abs(a) < 1e-9
    ja = np.where(small, 1.0, 1j * a)

    def g(v: NDArray[np.float64]) -> NDArray[np.complex128]:
        out: NDArray[np.complex128] = np.where(small, v, (1.0 - np.exp(-ja * v)) / ja)
        return out

    def big_f(u: NDArray[np.float64]) -> NDArray[np.complex128]:
        part = np.broadcast_to((u - np.floor(u))[:, None], a.shape)
        out: NDArray[np.complex128] = np.floor(u)[:, None] * g(np.ones_like(a)) + g(part)
        return out

    width = (u0 - u1)[:, None]
    still = np.abs(width) < 1e-9  # no drift across the segment: the delay is constant
    safe = np.where(still, 1.0, width)
    mean = np.exp(-1j * a * np.mod(0.5 * (u0 + u1), 1.0)[:, None])
    out: NDArray[np.complex128] = np.where(still, mean, (big_f(u0) - big_f(u1)) / safe)
    return out


def sample_delay(model: Model, p: Params) -> NDArray[np.float64]:
    """How long before its SYNC each sample was taken (s), at ``CLOCK_POINTS`` sample
    numbers spread over each segment, (S, M), for a sensor that stamps its own samples:
    its clock, off by δ, drifts without bound. (One that holds its latest sample per SYNC
    lags by a sawtooth of one period instead, integrated exactly in ``sawtooth_mean``.)
    Counted from the recording's middle, like the sawtooth's phase."""
    obs = model.obs
    span = obs.span.astype(np.float64)
    frac = (np.arange(CLOCK_POINTS) + 0.5) / CLOCK_POINTS
    samples = span[:, :1] + (span[:, 1:] - span[:, :1]) * frac[None, :]
    t = obs.metadata.sync_period_s
    drift = model.scalar(p, "clock_drift_ppm") * 1e-6
    return np.asarray(-t * (samples - clock_middle(obs)) * drift, dtype=np.float64)


def clock_factor(model: Model, p: Params, k: NDArray[np.float64]) -> Phasors:
    """The mean of e^{-jkωd} over each segment's samples, d their delays, (S, K)."""
    obs = model.obs
    if model.spec.clock_wraps:
        # Integrated exactly: a sum over sample points jumps whenever a wrap crosses one
        # of them, and the fit then stalls on the steps.
        t = obs.metadata.sync_period_s
        drift = model.scalar(p, "clock_drift_ppm") * 1e-6
        phase = model.scalar(p, "clock_phase")
        span = obs.span.astype(np.float64) - clock_middle(obs)
        a = k[None, :] * obs.omega[:, None] * t  # (S, K)
        return sawtooth_mean(phase - span[:, 0] * drift, phase - span[:, 1] * drift, a)
    delay = sample_delay(model, p)  # (S, M)
    # e^{-jkωd} as powers of e^{-jωd}: one exponential per sample instead of one per order.
    z = np.exp(-1j * obs.omega[:, None] * delay)
    top = int(k.max())
    powers = np.cumprod(np.broadcast_to(z[:, None, :], (z.shape[0], top, z.shape[1])),
                        axis=1)
    out: Phasors = powers[:, k.astype(np.intp) - 1, :].mean(axis=2)
    return out


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
    return type(model)(model.spec, replace(obs, beyond=beyond,
                                           phasors=obs.phasors * np.exp(model.jw * delay[:, None])))


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
    periodogram over drift rates they make (``starts``). ``centre``: each
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
                   model.obs.metadata.sync_period_s, clock_middle(model.obs))

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


def starts(model: Model, p: Params, peaks: int = 3) -> list[Starts]:
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


def estimates(model: Model, p: Params, screen: Screen) -> list[Starts]:
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
    points = [model.with_values(p, values) for values in tried]
    out: dict[tuple[float, float], Starts] = {}
    kin: dict[float, Starts] = {}
    for _, x in screen(model, points):
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


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    rate, err = value(fit, sigmas(cov), "clock_drift_ppm")
    out: dict[str, Any] = {"clock_drift_ppm": rate, "clock_drift_ppm_sigma": err,
                           "sample_timing": ("latest sample held for each SYNC"
                                             if fit.model.spec.clock_wraps
                                             else "sample times drift without wrapping")}
    if fit.model.layout.has("clock_phase"):
        # Reported at the first SYNC, where a reader of the recording would count it from.
        at_start = fit.scalar("clock_phase") + clock_middle(fit.model.obs) * rate * 1e-6
        out["sample_phase"] = float(at_start) % 1.0
    return out


TERMS = EffectTerms(
    effect=Effect.SENSOR_CLOCK_DRIFT,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Kept by the nominal model: a clock within a few ppm of SYNC's is the sensor's "
        "constant delay (MIN_CLOCK_PPM, the group's null band); every crystal drifts "
        "that much. Named beyond it."),
    starts=starts,
    estimates=estimates,
    scan_trials=scan_trials,
    hooks=Hooks(reads={Role.SENSOR: ("clock_drift_ppm", "clock_phase")}, sensor=clock_factor),
)
