"""The sensor's own sample instants (station.analysis.sampling), on synthetic holds."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis.harmonics import demodulate
from station.analysis.sampling import (
    ClockPhase,
    RateObservation,
    observe_rate,
    pooled_clock,
    pooled_rate,
    sample_delays,
    wrap_sign,
)

SPP = 50.0  # 20 Hz at a 1 ms SYNC
SAMPLES = 300  # a 2 + 4 period hold
ORDERS = 16
STEP = 2 * math.pi / SPP
# Order -> phasor of A·cos(kθ + φ): a unit near its null, H1 0.15 m/s², beside detent and
# flux orders of tens of m/s² (the units where a wrap mattered).
CONTENT: dict[int, complex] = {
    1: 0.15 * np.exp(0.7j),
    2: 0.05 * np.exp(-0.3j),
    4: 40.0 * np.exp(1.1j),
    5: 3.0 * np.exp(-2.0j),
    8: 12.0 * np.exp(0.4j),
    12: 4.0 * np.exp(2.5j),
}


def hold(delays: NDArray[np.float64], noise: float = 0.02, seed: int = 1
         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A hold's samples as a sensor late by ``delays`` (samples) read them, and the
    SYNC's own angles."""
    n = np.arange(delays.size, dtype=np.float64)
    angle = 0.3 + STEP * n
    at = angle + STEP * delays
    y = 9.0 + sum(abs(z) * np.cos(k * at + np.angle(z)) for k, z in CONTENT.items())
    y = y + np.random.default_rng(seed).normal(0.0, noise, delays.size)
    return np.asarray(y, dtype=np.float64), angle


def sawtooth(rate: float, first: float, samples: int = SAMPLES) -> NDArray[np.float64]:
    """Delays of a clock of ``rate`` (u per sample) starting at ``first``, wrapped into
    (−1, 0]: the latest sample the sensor took before each SYNC."""
    u = first + rate * np.arange(samples, dtype=np.float64)
    return -np.mod(-u, 1.0)


def h1_error(y: NDArray[np.float64], angle: NDArray[np.float64],
             delays: NDArray[np.float64] | None, truth: NDArray[np.float64]) -> float:
    """|ΔH1| of the demodulation against the waveform's, turned to the hold's mean instant."""
    at = angle if delays is None else angle + STEP * delays
    h1 = demodulate(y, at, SPP, orders=ORDERS).h(1)
    return float(abs(h1 - CONTENT[1] * np.exp(1j * STEP * float(truth.mean()))))


@pytest.mark.parametrize("ppm", [-480.0, -226.0, 150.0, 455.0])
def test_a_hold_times_its_sensor_s_clock_from_its_own_waveform(ppm: float) -> None:
    delays = sawtooth(ppm * 1e-6, -0.4)
    y, angle = hold(delays)
    seen = observe_rate(y, angle, SPP)
    assert abs(seen.rate - ppm * 1e-6) < max(5 * seen.sigma, 5e-6)
    assert seen.sigma < 20e-6


def test_a_sensor_on_the_sync_shows_no_rate() -> None:
    y, angle = hold(np.zeros(SAMPLES), seed=4)
    seen = observe_rate(y, angle, SPP)
    assert abs(seen.rate) < 5 * seen.sigma
    delays = sample_delays(y, angle, SPP, 0.0, wrap=0.0)
    assert delays.wrap_at is None and not delays.delays.any()


@pytest.mark.parametrize(("ppm", "first"), [(-300.0, -0.95), (400.0, -0.02)])
def test_a_skipped_or_repeated_sample_is_found_where_it_is(ppm: float, first: float) -> None:
    # A faster clock skips a sample (the delay jumps by +1), a slower one repeats one (−1).
    delays = sawtooth(ppm * 1e-6, first)
    jumps = np.flatnonzero(np.abs(np.diff(delays)) > 0.5) + 1
    assert jumps.size == 1
    y, angle = hold(delays)
    seen = observe_rate(y, angle, SPP)
    assert abs(seen.rate - ppm * 1e-6) < max(5 * seen.sigma, 5e-6)
    found = sample_delays(y, angle, SPP, ppm * 1e-6, wrap=wrap_sign(ppm * 1e-6))
    assert found.wrap_at == int(jumps[0])
    # Relative instants right to a few hundredths of a sample.
    spread = (found.delays - delays) - np.mean(found.delays - delays)
    assert float(np.max(np.abs(spread))) < 0.03
    # The near-null H1 the skipped sample drowned is back.
    before = h1_error(y, angle, None, delays)
    after = h1_error(y, angle, found.delays, delays)
    assert before > 0.05 and after < 0.005


def test_a_wrap_of_the_wrong_sign_for_the_clock_is_not_taken() -> None:
    # A slower clock repeats samples; a step the other way is not its wrap.
    delays = sawtooth(-300e-6, -0.95)
    y, angle = hold(delays)
    assert sample_delays(y, angle, SPP, 300e-6, wrap=wrap_sign(300e-6)).wrap_at is None


def test_holds_of_one_run_agree_on_one_clock() -> None:
    # Six holds 300 samples apart, one sawtooth through them all.
    ppm = -226.0
    run = sawtooth(ppm * 1e-6, -0.1, 6 * SAMPLES)
    seen = []
    for i in range(6):
        y, angle = hold(run[i * SAMPLES:(i + 1) * SAMPLES], seed=10 + i)
        seen.append(observe_rate(y, angle, SPP))
    assert pooled_rate(seen) == pytest.approx(ppm * 1e-6, abs=10e-6)
    # A clock-free sensor's holds pool to none.
    still = [observe_rate(*hold(np.zeros(SAMPLES), seed=20 + i), SPP) for i in range(6)]
    assert pooled_rate(still) == 0.0


def test_one_hold_s_transient_is_not_taken_for_the_clock() -> None:
    # Holds after large steps rang and timed wildly, each with a small σ of its noise;
    # the rest agree on the clock within their scatter (seed 9329's rounds, in ppm).
    wild = [(-510, 12), (33, 16), (-1703, 84), (1501, 89), (-1732, 44), (2826, 113)]
    agreeing = [(-485, 9), (-361, 6), (-277, 8), (-402, 6), (-368, 6), (-283, 6),
                (-341, 6), (-418, 7), (-359, 1)]
    observations = [RateObservation(r * 1e-6, s * 1e-6) for r, s in wild]
    assert pooled_rate(observations) == 0.0
    observations += [RateObservation(r * 1e-6, s * 1e-6) for r, s in agreeing]
    assert pooled_rate(observations) == pytest.approx(-361e-6, abs=15e-6)
    assert pooled_rate([RateObservation(0.0, math.inf)] * 5) == 0.0


def test_holds_timed_closely_outweigh_the_scatter_of_those_timed_loosely() -> None:
    # Seed 508770410, a rough belt with a 215 ppm clock: two holds timed it to 10 ppm, the
    # rest scattered about it by some twice their own σ. The median of the rates alone,
    # with their spread for its error, found 210 ± 53 ppm and took it for no clock.
    timed = [(387, 82), (317, 164), (194, 30), (125, 63), (361, 45), (645, 219),
             (195, 9), (210, 10), (164, 41)]
    pooled = pooled_clock([RateObservation(r * 1e-6, s * 1e-6) for r, s in timed])
    assert pooled.clear_of_zero
    assert pooled.rate == pytest.approx(200e-6, abs=15e-6)
    # The same holds about no clock at all stay no clock.
    still = [RateObservation((r - 200) * 1e-6, s * 1e-6) for r, s in timed]
    assert pooled_rate(still) == 0.0


def test_a_few_holds_timed_far_more_closely_than_the_rest_do_not_outvote_them() -> None:
    # Seed 5020 on Modbus: the longest holds' speed errors took up the −226 ppm clock and
    # left 5 ± 0.1 ppm; the other holds timed it within their 8 ppm. Weighed by their own
    # σ alone, the eight would be the clock.
    rng = np.random.default_rng(3)
    biased = [RateObservation(4.7e-6, 0.1e-6)] * 8
    honest = [RateObservation(float(r) * 1e-6, 8e-6) for r in rng.normal(-226.0, 18.0, 28)]
    assert pooled_rate(biased + honest) == pytest.approx(-226e-6, abs=12e-6)


def test_a_rate_beyond_what_a_hold_can_follow_is_a_transient_not_a_clock() -> None:
    # Ringing holds of a 137 ppm unit once pooled to −21,058 ppm: a clock that fast would
    # wrap within every hold. Such holds are left out; alone, they pool to nothing.
    wild = [RateObservation(r * 1e-6, 300e-6) for r in (-21_058, -18_300, -25_900, -9_700)]
    assert pooled_rate(wild) == 0.0
    settled = [RateObservation(r * 1e-6, 8e-6) for r in (131, 140, 129, 145, 138)]
    assert pooled_rate(wild + settled) == pytest.approx(138e-6, abs=5e-6)


def test_a_weak_or_short_hold_times_nothing() -> None:
    y, angle = hold(np.zeros(40))
    assert math.isinf(observe_rate(y, angle, SPP).sigma)
    y, angle = hold(np.zeros(SAMPLES))
    y[:] = np.nan
    assert math.isinf(observe_rate(y, angle, SPP).sigma)


@pytest.mark.parametrize("ppm", [-480.0, 455.0])
def test_the_run_s_clock_puts_every_hold_on_one_sawtooth_from_a_few_wraps_placed(
    ppm: float,
) -> None:
    # Twenty seconds of a drifting clock: nine wraps or more, of which the holds placed
    # two, each a few samples off. Every sample's delay then follows the sawtooth up to
    # one constant (a turn shared by every phasor of the run) but next to a wrap.
    samples = 20_000
    run = sawtooth(ppm * 1e-6, -0.3, samples)
    wraps = np.flatnonzero(np.abs(np.diff(run)) > 0.5) + 1
    assert wraps.size >= 9
    clock = ClockPhase.of(ppm * 1e-6, [int(wraps[1]) + 3, int(wraps[4]) - 2])
    index = np.arange(samples, dtype=np.float64)
    offset = clock.delays(index) - run
    away = np.ones(samples, dtype=bool)
    for w in wraps:
        away[max(0, w - 10):w + 10] = False
    assert float(np.ptp(offset[away])) < 1e-9
    # A hold that placed a wrap of its own keeps it where it found it, not where the
    # lattice of the others puts it.
    own = int(wraps[6])
    hold_index = np.arange(own - 150, own + 150)
    shifted = clock.delays(hold_index.astype(np.float64), own) - run[hold_index]
    assert float(np.ptp(shifted)) < 1e-9
    assert shifted[0] == pytest.approx(offset[away][0])


@pytest.mark.parametrize("ppm", [-214.0, 214.0])
@pytest.mark.parametrize("early", [True, False])
def test_a_hold_that_found_no_wrap_keeps_the_lattice_s_wrap_outside_itself(
    ppm: float, early: bool,
) -> None:
    # The lattice's next wrap, 1/|δ| on from the one placed, lands 40 samples into a hold
    # (or 40 from its end) that the waveform shows has none: the hold takes it to fall
    # at its nearer end, so its delays are a ramp without a step, and the count the
    # lattice has on the far side of the hold is kept.
    rate = ppm * 1e-6
    clock = ClockPhase.of(rate, [1_000])
    assert clock.anchor is not None
    period = 1.0 / abs(rate)
    start = int(clock.anchor + period) - (40 if early else 210)
    index = np.arange(start, start + 250, dtype=np.float64)
    stepped = clock.delays(index)
    assert float(np.ptp(np.diff(stepped))) > 0.5  # the lattice puts a wrap inside
    clear = clock.delays(index, searched=True)
    assert float(np.ptp(np.diff(clear))) < 1e-12  # a ramp, no step
    kept = stepped[-1] if early else stepped[0]
    assert (clear[-1] if early else clear[0]) == pytest.approx(kept)


def test_without_a_wrap_placed_the_run_s_clock_is_its_ramp() -> None:
    clock = ClockPhase.of(-200e-6, [])
    index = np.arange(0.0, 3000.0)
    assert clock.anchor is None
    assert np.allclose(clock.delays(index), -200e-6 * index)
    assert not ClockPhase.of(0.0, [1000]).delays(index).any()
