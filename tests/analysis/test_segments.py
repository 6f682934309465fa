"""Steady segments (station.analysis.segments) of synthetic timelines.

The timelines are built sample by sample the way a drive reports a run
(integer position demand, trims in effect, statusword), with a tangential
acceleration whose harmonics depend on the trims, so every property of a
segment can be checked against the construction.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis import segments as segments_module
from station.analysis.harmonics import demodulate
from station.analysis.segments import (
    MIN_PERIODS,
    ChainDecay,
    Segment,
    Settling,
    constant_velocity_runs,
    holds,
    position_glitches,
    sensor_clock,
    settled_period,
    steady_segments,
    turning_with_rotor,
)
from station.analysis.timeline import LossReport, Timeline, unwrap_int32
from station.core import Trims
from tests.metadata import icd_metadata

MICROSTEPS = 256
CYCLE = 4 * MICROSTEPS  # microsteps per electrical period
PERIOD_S = 0.001
SPP = 50  # samples per electrical period at 20 Hz
V20 = CYCLE / SPP  # microsteps per sample at 20 Hz electrical
ENABLED = 0x0027  # CiA 402 "operation enabled"
DISABLED = 0x0040  # "switch on disabled"
NOMINAL = (0, 0, 10000, 10000)
NOISE = 0.02  # m/s² per sample

META = icd_metadata(
    serial="SN42",
    sync_period_s=PERIOD_S,
    microsteps_per_fullstep=MICROSTEPS,
    sensor_lsb_mps2=8 * 9.80665 / 32768,
)


@dataclass(frozen=True)
class Piece:
    """``samples`` SYNCs with the velocity going linearly from ``v0`` to ``v1``
    (microsteps per sample) and the drive reporting ``trims``."""

    samples: int
    v0: float
    v1: float | None = None
    trims: tuple[int, int, int, int] = NOMINAL
    status: int = ENABLED
    amplitude_mA: int = 1000


def steady(periods: int, trims: tuple[int, int, int, int] = NOMINAL, v: float = V20) -> Piece:
    return Piece(periods * round(CYCLE / abs(v)), v, trims=trims)


def h1_of(trims: Sequence[float]) -> complex:
    """The 1st harmonic nulls at offsets (-120, 55) mA (eq. 16: the two act in quadrature)."""
    return complex(2e-3 * np.exp(0.3j) * (trims[0] + 120) + 2e-3j * np.exp(0.3j) * (trims[1] - 55))


def h2_of(trims: Sequence[float]) -> complex:
    return complex(1e-4 * np.exp(1j) * ((trims[2] - trims[3]) / 2 + 150))


@dataclass
class Run:
    """A drive's run as it would reach the analysis: per-sample reports and the truth.

    After every change of the trims the ripple phasors move to their new values
    with the rotor's time constant ``tau_s`` (0: at once), and a lightly damped
    mode rings with ``ring`` m/s², decaying with the same time constant.
    """

    pieces: Sequence[Piece]
    start_position: int = 0
    phase: float = 0.0  # fraction of a microstep the integer position demand lags
    noise: float = NOISE
    tau_s: float = 0.0
    ring: float = 0.0
    seed: int = 0
    position: NDArray[np.int64] = field(init=False)
    signal: NDArray[np.float64] = field(init=False)
    bounds: list[int] = field(init=False)  # first sample of each piece, then the end
    trims: NDArray[np.int32] = field(init=False)

    def __post_init__(self) -> None:
        velocity = np.concatenate(
            [np.linspace(p.v0, p.v0 if p.v1 is None else p.v1, p.samples) for p in self.pieces]
        )
        travel = np.concatenate([[0.0], np.cumsum(velocity[1:])])
        self.position = self.start_position + np.round(travel + self.phase).astype(np.int64)
        self.bounds = [0, *np.cumsum([p.samples for p in self.pieces]).tolist()]
        self.trims = np.concatenate(
            [np.tile(np.array(p.trims, dtype=np.int32), (p.samples, 1)) for p in self.pieces]
        )
        h1 = np.array([h1_of(t) for t in self.trims])
        h2 = np.array([h2_of(t) for t in self.trims])
        changes = [0, *(np.flatnonzero(np.any(np.diff(self.trims, axis=0), axis=1)) + 1)]
        ends = [*changes[1:], h1.size]
        t = np.zeros(h1.size)
        for a, b in zip(changes, ends, strict=True):
            t[a:b] = np.arange(b - a) * PERIOD_S
        if self.tau_s > 0:
            # The phasors start where the previous hold left them (at rest: none).
            for h in (h1, h2):
                before = np.concatenate([[0j], h[np.array(changes[1:]) - 1]])
                for (a, b), old in zip(zip(changes, ends, strict=True), before, strict=True):
                    h[a:b] += (old - h[a:b]) * np.exp(-t[a:b] / self.tau_s)
        decay = np.exp(-t / self.tau_s) if self.tau_s > 0 else np.zeros(t.size)
        angle = self.angle
        rng = np.random.default_rng(self.seed)
        self.signal = (
            np.real(h1 * np.exp(1j * angle))
            + np.real(h2 * np.exp(2j * angle))
            + self.ring * decay * np.cos(2 * math.pi * 37.0 * t)
            + rng.normal(0.0, self.noise, angle.size)
        )

    @property
    def angle(self) -> NDArray[np.float64]:
        """ICD.md §2: the electrical angle the drive commands."""
        return 2 * math.pi * np.mod(self.position, CYCLE) / CYCLE

    def timeline(
        self,
        *,
        drive_lost: NDArray[np.bool_] | None = None,
        trims_lost: NDArray[np.bool_] | None = None,
        position: NDArray[np.int64] | None = None,
    ) -> Timeline:
        n = self.position.size
        drive_valid = np.ones(n, dtype=bool) if drive_lost is None else ~drive_lost
        trims_valid = np.ones(n, dtype=bool) if trims_lost is None else ~trims_lost
        status = np.concatenate([np.full(p.samples, p.status, np.uint16) for p in self.pieces])
        amplitude = np.concatenate(
            [np.full(p.samples, p.amplitude_mA, np.int32) for p in self.pieces]
        )
        pos = self.position if position is None else position
        # Rows of lost frames read zero, as the timeline documents.
        return Timeline(
            metadata=META,
            accel_counts=np.zeros((n, 3), dtype=np.int16),
            sensor_valid=np.ones(n, dtype=bool),
            saturated=np.zeros(n, dtype=bool),
            position=np.where(drive_valid, pos, 0).astype(np.int64),
            amplitude_mA=np.where(drive_valid, amplitude, 0).astype(np.int32),
            statusword=np.where(drive_valid, status, 0).astype(np.uint16),
            drive_valid=drive_valid,
            trims=np.where(trims_valid[:, None], self.trims, 0).astype(np.int32),
            trims_valid=trims_valid,
            losses=LossReport(
                syncs_seen=n,
                syncs_missing=0,
                sensor_samples_lost=0,
                drive_status_lost=int(np.count_nonzero(~drive_valid)),
                drive_trims_lost=int(np.count_nonzero(~trims_valid)),
                saturated_samples=0,
                frames_ignored=0,
                frames_malformed=0,
            ),
        )


def _calibration_like() -> Run:
    """Standstill, a velocity ramp, a baseline, three trim holds, a stop ramp, standstill."""
    return Run(
        [
            Piece(300, 0.0),
            Piece(200, 0.0, V20),  # 0.1 microstep/sample²: an ordinary profile ramp
            steady(12),
            steady(12, (-300, 0, 10000, 10000)),
            steady(12, (0, 200, 10000, 10000)),
            steady(12, (0, 0, 8000, 12000)),
            Piece(200, V20, 0.0),  # the stop ramp, back at nominal trims
            Piece(200, 0.0),
        ]
    )


def _check_on_the_line(seg: Segment, run: Run) -> None:
    """The segment's fitted line is the commanded position at every sample it covers."""
    n = np.arange(seg.samples)
    line = seg.position0 + seg.microsteps_per_sample * n
    assert np.max(np.abs(line - run.position[seg.start : seg.stop])) <= 0.5 + 1e-9
    angle = seg.electrical_angle()
    exact = run.angle[seg.start : seg.stop]
    wrapped = np.angle(np.exp(1j * (angle - exact)))
    assert np.max(np.abs(wrapped)) <= 2 * math.pi * 0.5 / CYCLE + 1e-9


# --------------------------------------------------------------------------- holds


def test_holds_split_where_trims_amplitude_or_enable_state_change() -> None:
    run = Run(
        [
            Piece(100, 0.0, status=DISABLED),
            Piece(100, 0.0),
            steady(4),
            steady(4, (10, 0, 10000, 10000)),
            Piece(100, V20, trims=(10, 0, 10000, 10000), amplitude_mA=800),
        ]
    )
    found = holds(run.timeline())
    # Velocity is no part of a hold: standstill and motion at one trim set are one hold.
    b = run.bounds
    assert [(h.start, h.stop) for h in found] == [(b[0], b[1]), (b[1], b[3]), (b[3], b[4]),
                                                  (b[4], b[5])]
    assert [h.enabled for h in found] == [False, True, True, True]
    assert [h.amplitude_mA for h in found] == [1000, 1000, 1000, 800]
    assert found[2].trims == (10, 0, 10000, 10000)


def test_lost_trim_frames_repeat_the_last_reported_trims() -> None:
    run = Run([steady(4), steady(4, (10, 0, 10000, 10000))])
    lost = np.zeros(run.position.size, dtype=bool)
    boundary = run.bounds[1]
    lost[[0, 1, 57, boundary]] = True  # including the first row and the first of the new hold
    found = holds(run.timeline(trims_lost=lost))
    assert [h.trims for h in found] == [NOMINAL, (10, 0, 10000, 10000)]
    assert found[1].start == boundary + 1  # one sample late, never early


# --------------------------------------------------------------------- segments


def test_each_steady_hold_gives_one_segment_with_its_trims() -> None:
    run = _calibration_like()
    segments, _ = steady_segments(run.timeline(), run.signal)
    trims = [s.trims for s in segments]
    assert trims == [
        Trims(0, 0, 10000, 10000),
        Trims(-300, 0, 10000, 10000),
        Trims(0, 200, 10000, 10000),
        Trims(0, 0, 8000, 12000),
    ]
    for seg in segments:
        assert seg.microsteps_per_sample == pytest.approx(V20, rel=1e-5)
        assert seg.electrical_hz(PERIOD_S) == pytest.approx(20.0, rel=1e-5)
        assert seg.amplitude_mA == 1000
        _check_on_the_line(seg, run)


def test_segments_are_whole_periods_ending_at_the_end_of_their_hold() -> None:
    run = _calibration_like()
    for settle in (None, 0.0, 2.0):
        segments, _ = steady_segments(run.timeline(), run.signal, settle_periods=settle)
        assert [s.stop for s in segments] == run.bounds[3:7]
        for seg in segments:
            assert seg.periods >= MIN_PERIODS
            assert seg.samples == seg.periods * SPP


def test_the_start_ramp_is_left_out_even_without_settling() -> None:
    run = _calibration_like()
    for settle in (None, 0.0):
        first = steady_segments(run.timeline(), run.signal, settle_periods=settle)[0][0]
        assert first.start >= run.bounds[2]  # the ramp is samples 300..500
        assert first.held_from == 0  # the baseline hold began at standstill


def _stop_ramp_within_a_hold() -> Run:
    """Some benches slow down before they change the trims: the ramp is inside the hold."""
    return Run([Piece(200, 0.0), Piece(100, 0.0, V20), steady(12), Piece(100, V20, 0.0),
                Piece(200, 0.0)])


@pytest.mark.parametrize("settle", [None, 0.0])
def test_a_stop_ramp_inside_a_hold_is_left_out(settle: float | None) -> None:
    run = _stop_ramp_within_a_hold()
    segments, _ = steady_segments(run.timeline(), run.signal, settle_periods=settle)
    assert len(segments) == 1
    assert run.bounds[2] <= segments[0].start and segments[0].stop <= run.bounds[3]


def test_a_constant_velocity_run_does_not_reach_into_a_ramp() -> None:
    run = _stop_ramp_within_a_hold()
    tl = run.timeline()
    found = constant_velocity_runs(tl.position, tl.drive_valid, 0, tl.samples)
    moving = [r for r in found if r[1] > run.bounds[2] and r[0] < run.bounds[3]]
    assert len(moving) == 1
    assert run.bounds[2] <= moving[0][0] and moving[0][1] <= run.bounds[3], moving


def test_constant_velocity_runs_do_not_overlap() -> None:
    """Where rounding makes the window test flicker at a ramp's end, one stretch of
    samples must still be reported once, not twice."""
    run = _calibration_like()
    tl = run.timeline()
    for hold in holds(tl):
        found = constant_velocity_runs(tl.position, tl.drive_valid, hold.start, hold.stop)
        assert all(a[1] <= b[0] for a, b in itertools.pairwise(found)), found


def test_profile_ramps_leave_nothing_rejected() -> None:
    """A clean run has nothing to reject: a ramp is not a steady stretch gone wrong."""
    for run in (_calibration_like(), _stop_ramp_within_a_hold()):
        for settle in (None, 0.0, 2.0):
            rejected = steady_segments(run.timeline(), run.signal, settle_periods=settle)[1]
            assert rejected == [], (settle, rejected)


def test_lost_drive_frames_do_not_move_or_break_segments() -> None:
    run = _calibration_like()
    rng = np.random.default_rng(3)
    drive_lost = rng.random(run.position.size) < 0.05
    trims_lost = rng.random(run.position.size) < 0.05
    clean, clean_rejected = steady_segments(run.timeline(), run.signal, settle_periods=1.0)
    lossy, rejected = steady_segments(
        run.timeline(drive_lost=drive_lost, trims_lost=trims_lost), run.signal, settle_periods=1.0
    )
    assert len(rejected) == len(clean_rejected)
    assert [s.trims for s in lossy] == [s.trims for s in clean]
    for a, b in zip(lossy, clean, strict=True):
        # A late trims report may end a hold one sample late: the segment ends before it.
        assert b.stop - 1 <= a.stop <= b.stop
        assert a.microsteps_per_sample == pytest.approx(V20, rel=1e-5)
        _check_on_the_line(a, run)


def test_a_misplaced_position_sample_is_ignored() -> None:
    """A drive frame placed one sample early reads a whole sample's travel off the line."""
    run = _calibration_like()
    glitch = run.bounds[3] + 123
    position = run.position.copy()
    position[glitch] = position[glitch + 1]
    tl = run.timeline(position=position)
    assert np.flatnonzero(position_glitches(tl.position, tl.drive_valid)).tolist() == [glitch]
    segments, rejected = steady_segments(tl, run.signal)
    clean, clean_rejected = steady_segments(run.timeline(), run.signal)
    assert len(rejected) == len(clean_rejected)
    assert [(s.start, s.stop, s.trims) for s in segments] == [
        (s.start, s.stop, s.trims) for s in clean
    ]
    for seg in segments:
        _check_on_the_line(seg, run)


def test_position_past_the_int32_range_keeps_the_electrical_angle() -> None:
    """The reader hands over the position unwrapped; the angle must not jump at 2³¹."""
    start = 2**31 - 5000
    run = Run([steady(12), steady(12, (-300, 0, 10000, 10000))], start_position=start)
    raw = ((run.position + 2**31) % 2**32 - 2**31).astype(np.int32)
    assert raw.min() < 0 < raw.max()  # the raw int32 values do wrap
    unwrapped = unwrap_int32(raw) - int(raw[0]) + start
    np.testing.assert_array_equal(unwrapped, run.position)
    segments, rejected = steady_segments(run.timeline(position=unwrapped), run.signal)
    assert rejected == [] and len(segments) == 2
    assert segments[1].start < 5000 / V20 + run.bounds[1] < segments[1].stop  # spans the wrap
    for seg in segments:
        _check_on_the_line(seg, run)
    seg = segments[1]
    h = demodulate(run.signal[seg.start : seg.stop], seg.electrical_angle(), SPP)
    assert abs(h.h(1) - h1_of((-300, 0, 10000, 10000))) < 4 * math.sqrt(h.var(1))


def test_negative_velocity_gives_a_negative_electrical_frequency() -> None:
    run = Run([steady(12, v=-V20), steady(12, (-300, 0, 10000, 10000), v=-V20)])
    segments, rejected = steady_segments(run.timeline(), run.signal)
    assert rejected == [] and len(segments) == 2
    for seg in segments:
        assert seg.electrical_hz(PERIOD_S) == pytest.approx(-20.0, rel=1e-5)
        assert seg.velocity(PERIOD_S) == pytest.approx(-V20 / PERIOD_S, rel=1e-5)
        assert seg.samples == seg.periods * SPP
        _check_on_the_line(seg, run)


def test_standstill_and_a_disabled_drive_give_no_segment() -> None:
    run = Run([Piece(1000, 0.0), Piece(600, V20, status=DISABLED)])
    assert steady_segments(run.timeline(), run.signal) == ([], [])


# --------------------------------------------------------------------- settling


def _as_tuple(t: Trims) -> tuple[float, float, float, float]:
    return (t.offset_a_mA, t.offset_b_mA, t.gain_a, t.gain_b)


def _phasor_error(run: Run, seg: Segment) -> float:
    """|Ĥ1 − H1| of the segment in m/s²."""
    h = demodulate(run.signal[seg.start : seg.stop], seg.electrical_angle(), SPP)
    return abs(h.h(1) - h1_of(_as_tuple(seg.trims)))


def _offset_sweep(tau_s: float, periods: int, ring: float = 0.3) -> Run:
    return Run(
        [steady(periods, (o, 0, 10000, 10000)) for o in (-400, -200, 0, 200, 400)],
        tau_s=tau_s,
        ring=ring,
    )


def test_the_transient_after_each_trim_change_is_dropped() -> None:
    run = _offset_sweep(tau_s=0.1, periods=40)
    judged, rejected = steady_segments(run.timeline(), run.signal)
    assert rejected == [] and len(judged) == 5
    for seg, stop in zip(judged, run.bounds[1:], strict=True):
        assert seg.stop == stop
        # A step of 0.4 m/s² decays into noise of 0.006 per period in ln(70) ≈ 4 τ.
        assert 0.25 <= (seg.start - seg.held_from) * PERIOD_S <= 1.0
    # White noise of 0.02 m/s² gives Ĥ1 a standard deviation of 0.02·√(2/N) (N ≥ 1000).
    sigma = NOISE * math.sqrt(2 / 1000)
    assert max(_phasor_error(run, s) for s in judged) < 4 * sigma
    # Kept in, the same transient biases the phasors far beyond their noise.
    unsettled, _ = steady_segments(run.timeline(), run.signal, settle_periods=0.0)
    assert max(_phasor_error(run, s) for s in unsettled) > 10 * sigma


def test_a_hold_whose_rotor_never_settles_is_rejected_with_the_reason() -> None:
    # A time constant far beyond the 1 s holds. Without the ring: a mode still ringing
    # at the end of its hold cannot be told from steady vibration by that hold alone.
    run = _offset_sweep(tau_s=3.0, periods=20, ring=0.0)
    segments, rejected = steady_segments(run.timeline(), run.signal)
    assert segments == []
    assert [r.reason for r in rejected] == ["the rotor did not settle within the hold"] * 5
    assert [r.stop for r in rejected] == run.bounds[1:]


RING_HZ, RING_TAU_S = 37.0, 0.8
"""A belt mode at 37 Hz decaying with τ = 0.8 s: ln 300 ≈ 5.7 τ = 4.6 s to forget a
change, against holds of 0.25 s."""


def _ringing_run(periods: int = 5) -> Run:
    """Trim holds of 5 periods each (too short for the data to judge); after every change
    the chain's mode rings on through the whole hold (the phasors step at once)."""
    return _rung(periods, complex(-1.0 / RING_TAU_S, 2 * math.pi * RING_HZ), 0.3)


def _since_change(run: Run) -> NDArray[np.float64]:
    """Seconds since each sample's hold began."""
    change = np.zeros(run.signal.size)
    for a, b in itertools.pairwise(run.bounds):
        change[a:b] = np.arange(b - a) * PERIOD_S
    return change


def _rung(periods: int, pole: complex, amplitude: float) -> Run:
    """Trim holds of ``periods`` each, every change ringing a mode at ``pole`` (1/s)."""
    run = _offset_sweep(tau_s=0.0, periods=periods, ring=0.0)
    change = _since_change(run)
    run.signal += amplitude * np.exp(pole.real * change) * np.cos(pole.imag * change)
    return run


def _belt_decay(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
    """What a fitted chain says of the belt above: its pole, and a 20 ms floor."""
    pole = complex(-1.0 / RING_TAU_S, 2 * math.pi * RING_HZ)
    return ChainDecay((pole,), math.log(300.0), 0.02)


def test_a_hold_shorter_than_the_chains_decay_has_its_ringing_fitted_out() -> None:
    run = _ringing_run()
    # On the data alone, holds this short cannot be judged, so none is used.
    alone, _ = steady_segments(run.timeline(), run.signal)
    assert alone == []
    segments, rejected = steady_segments(run.timeline(), run.signal,
                                         settle_fallback=_belt_decay)
    assert rejected == [] and len(segments) == 5
    sigma = NOISE * math.sqrt(2 / 200)  # Ĥ's noise over 4 periods of 50 samples
    for seg in segments:
        assert seg.settling is Settling.RINGING
        (pole,) = seg.ringing  # per sample
        assert pole == pytest.approx(complex(-PERIOD_S / RING_TAU_S,
                                             2 * math.pi * RING_HZ * PERIOD_S))
        # Only the floor is waited for: the hold keeps all but its first period.
        assert seg.periods == 4
        window = run.signal[seg.start:seg.stop]
        fitted = seg.harmonics(window, orders=8)
        trims = _as_tuple(seg.trims)
        # Within the uncertainty the fit reports. A pole known only to first order (a
        # double one) costs order 2, 3 Hz from it over 0.2 s, three quarters of its
        # precision: the price of a hold this short beside a mode.
        assert abs(fitted.h(1) - h1_of(trims)) < 4 * math.sqrt(fitted.var(1))
        assert abs(fitted.h(2) - h2_of(trims)) < 4 * math.sqrt(fitted.var(2))
        assert math.sqrt(fitted.var(2)) < 5 * sigma
        # Left in, the ringing biases the phasors far beyond their noise (most at order
        # 2, 40 Hz, beside the mode).
        ignored = demodulate(window, seg.electrical_angle(), SPP)
        assert abs(ignored.h(2) - h2_of(trims)) > 10 * sigma


def test_a_hold_the_data_judge_settled_beside_a_mode_still_ringing_has_it_fitted_out() -> None:
    """Holds of 12 periods with the same ringing: the data take them as settled (orders 1
    and 2 barely see a 37 Hz mode), but the model wants 4.6 s and the hold leaves no room
    to wait: the ringing is fitted out from where the data settled, and order 2 (40 Hz,
    beside the mode), which the data's judgement alone leaves biased, comes out right."""
    run = _ringing_run(periods=12)
    data, _ = steady_segments(run.timeline(), run.signal)
    segments, _ = steady_segments(run.timeline(), run.signal, settle_fallback=_belt_decay)
    assert [s.settling for s in segments] == [Settling.RINGING] * 5
    assert [(s.start, s.stop) for s in segments] == [(s.start, s.stop) for s in data]

    def worst(chosen: list[Segment]) -> float:
        return max(abs(seg.harmonics(run.signal[seg.start:seg.stop], orders=8).h(2)
                       - h2_of(_as_tuple(seg.trims))) for seg in chosen)

    sigma = NOISE * math.sqrt(2 / (min(s.samples for s in data)))
    assert worst(segments) < 4 * sigma < 10 * sigma < worst(data)


def test_a_hold_too_short_for_a_fast_decay_waits_as_long_as_it_can() -> None:
    """The same holds and a ring ten times stronger, decaying in 50 ms: the model's plain
    wait (0.28 s) fits the hold, and the ring's strength asks for more than the hold has;
    waiting until three periods are left takes it down further than twelve periods from
    the data's judgement average it."""
    pole = complex(-1.0 / 0.05, 2 * math.pi * RING_HZ)
    run = _rung(12, pole, 3.0)

    def decay(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
        return ChainDecay((pole,), math.log(300.0), 0.02, 1e-4)

    data, _ = steady_segments(run.timeline(), run.signal)
    segments, _ = steady_segments(run.timeline(), run.signal, settle_fallback=decay)
    waited = [s for s in segments if s.settling is Settling.MODEL]
    assert waited and all(s.periods == MIN_PERIODS for s in waited)

    def bias(seg: Segment) -> float:
        h = demodulate(run.signal[seg.start:seg.stop], seg.electrical_angle(), SPP)
        return abs(h.h(2) - h2_of(_as_tuple(seg.trims)))

    assert max(bias(s) for s in segments) < max(bias(s) for s in data)


@pytest.mark.parametrize(("floor_s", "settling"), [(0.2, Settling.MODEL), (0.3, Settling.DATA)])
def test_a_wait_with_no_mode_to_fit_out_is_kept_only_if_the_hold_has_room_for_it(
    floor_s: float, settling: Settling,
) -> None:
    """Holds of 8 periods (0.4 s) the data judge settled at once. A prior's 0.2 s wait
    leaves 4 periods and is taken; 0.3 s would leave 2, so the data's judgement stands."""
    run = Run([steady(8), steady(8, (-300, 0, 10000, 10000))])

    def prior(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
        return ChainDecay((), math.log(300.0), floor_s)

    segments, rejected = steady_segments(run.timeline(), run.signal, settle_fallback=prior)
    assert rejected == []
    assert [s.settling for s in segments][1:] == [settling]
    assert segments[1].periods == (4 if settling is Settling.MODEL else 8)


def test_a_change_that_rings_hard_is_waited_out_down_to_the_harmonics_resolution() -> None:
    """The same 0.3 m/s² ringing, seen from a decay that resolves 1e-4 m/s²: 1/300 of it is
    still ten times that, so the hold waits for ln(0.3/1e-4) e-foldings (as far as the
    hold allows), not ln(300); with a coarse resolution nothing changes."""
    pole = complex(-1.0 / 0.05, 2 * math.pi * RING_HZ)
    run = _rung(40, pole, 0.3)

    def waits(resolution: float) -> list[float]:
        def decay(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
            return ChainDecay((pole,), math.log(300.0), 0.02, resolution)
        segments, _ = steady_segments(run.timeline(), run.signal, settle_fallback=decay)
        return [(s.start - s.held_from) * PERIOD_S for s in segments]

    plain = math.log(300.0) * 0.05
    # Sharp enough to see the ringing in a hold's first period: waited out further.
    assert all(w >= math.log(0.3 / 1e-4) * 0.05 - PERIOD_S * SPP for w in waits(1e-4)[1:])
    # Coarse: the plain e-foldings, or the data's own judgement where it is later.
    assert all(w >= plain - PERIOD_S for w in waits(1.0))
    assert sum(waits(1e-4)) > sum(waits(1.0))


def test_kicked_decay_counts_e_foldings_down_to_the_resolution_and_never_fewer() -> None:
    pole = complex(-10.0, 300.0)
    decay = ChainDecay((pole,), math.log(300.0), 0.02, 0.01)
    assert decay.kicked(100.0).e_foldings == pytest.approx(math.log(1e4))
    assert decay.kicked(1.0).e_foldings == pytest.approx(math.log(300.0))
    assert decay.kicked(0.0) is decay
    assert ChainDecay((pole,), 2.0, 0.02).kicked(1e6).e_foldings == 2.0
    assert decay.slowest_decay_per_s() == pytest.approx(10.0)


def test_a_ring_seen_long_after_its_change_is_referred_back_to_it_in_e_foldings() -> None:
    """A well damped mode seen a second after its change would have rung e^10000 times
    harder at the change, beyond any float: its wait is that second and the e-foldings
    from what is seen down to the resolution."""
    fast = ChainDecay((complex(-1e4, 3e4),), math.log(300.0), 0.02, 0.01)
    assert fast.kicked(1.0, since_s=1.0).settle_s() == pytest.approx(1.0 + math.log(100.0) / 1e4)
    slow = ChainDecay((complex(-10.0, 300.0),), math.log(300.0), 0.02, 0.01)
    assert slow.kicked(0.5, since_s=0.1).e_foldings == pytest.approx(
        slow.kicked(0.5 * math.e).e_foldings)


def test_a_ringing_modulated_by_the_electrical_angle_is_fitted_out_with_its_sidebands(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A rotor whose spring swings with the electrical angle rings at the mode and beside it
    at ± the electrical frequency: fitted at the mode alone, the sidebands are left as
    seven times the noise and orders 1 and 2 lose five sixths of their precision; with
    them, the phasors are right within the precision the noise allows."""
    run = _ringing_run()
    change = _since_change(run)
    angle = 2 * math.pi * change / (SPP * PERIOD_S)
    envelope = 0.3 * np.exp(-change / RING_TAU_S)
    run.signal += envelope * np.cos(2 * math.pi * RING_HZ * change + angle + 0.7)
    segments, _ = steady_segments(run.timeline(), run.signal, settle_fallback=_belt_decay)

    def worst() -> tuple[float, float, float]:
        """The largest error of orders 1 and 2 in units of the σ the fit reports, that σ
        for order 1, and the residual's rms."""
        errors, sigma, left = [], 0.0, 0.0
        for seg in segments:
            h = seg.harmonics(run.signal[seg.start:seg.stop], orders=8)
            errors += [abs(h.h(k) - (h1_of, h2_of)[k - 1](_as_tuple(seg.trims)))
                       / math.sqrt(h.var(k)) for k in (1, 2)]
            sigma, left = max(sigma, math.sqrt(h.var(1))), max(left, h.residual_rms)
        return max(errors), sigma, left

    error, sigma, left = worst()
    assert error < 4 and left < 1.2 * NOISE
    monkeypatch.setattr("station.analysis.segments.SIDEBANDS", ())
    _, alone, left = worst()
    assert left > 5 * NOISE and alone > 5 * sigma


def test_a_chain_decay_waits_for_every_mode_when_the_hold_allows_it() -> None:
    slow, fast = complex(-2.0, 200.0), complex(-60.0, 900.0)
    decay = ChainDecay((fast, slow), math.log(300.0), 0.02)
    e = math.log(300.0)
    assert decay.settle_s() == pytest.approx(e / 2.0)
    wait, ringing = decay.plan(10.0, 1.0)
    assert wait == pytest.approx(e / 2.0) and ringing == ()
    # Too short to wait for the slow mode: it alone is fitted out, the fast one waited for.
    wait, ringing = decay.plan(1.0, 0.5)
    assert wait == pytest.approx(e / 60.0) and ringing == (slow,)
    # Too short even for the fast one: both fitted out after the floor.
    wait, ringing = decay.plan(0.1, 0.05)
    assert wait == pytest.approx(0.02) and ringing == (slow, fast)


def test_a_fixed_settle_count_drops_exactly_that_many_periods() -> None:
    run = _calibration_like()
    segments, _ = steady_segments(run.timeline(), run.signal, settle_periods=2)
    for seg in segments[1:]:
        # Holds after the first start at a trim change: 12 periods, 2 dropped.
        assert seg.start - seg.steady_from == 2 * SPP
        assert seg.periods == 10
    baseline = segments[0]
    assert 2 * SPP <= baseline.start - baseline.steady_from < 3 * SPP
    # The data have no say: a transient that never settles is cut the same way.
    unsettled = _offset_sweep(tau_s=3.0, periods=20)
    fixed, rejected = steady_segments(unsettled.timeline(), unsettled.signal, settle_periods=2)
    assert rejected == [] and [s.periods for s in fixed] == [18] * 5


@pytest.mark.parametrize("phase", [0.0, 0.15, 0.6, 0.9])
def test_no_whole_period_is_lost_to_the_rounding_of_the_fitted_speed(phase: float) -> None:
    """Holds of exactly 12 periods: with 2 dropped, 10 remain, whether the line fitted
    through the integer position demand comes out a hair fast or a hair slow."""
    run = Run([steady(12), steady(12, (-300, 0, 10000, 10000))], phase=phase)
    segments, _ = steady_segments(run.timeline(), run.signal, settle_periods=2)
    assert [(s.periods, s.start - s.steady_from) for s in segments] == [(10, 2 * SPP)] * 2


def test_fewer_than_the_minimum_periods_are_rejected() -> None:
    run = Run([steady(12), steady(MIN_PERIODS + 1, (-300, 0, 10000, 10000))])
    segments, rejected = steady_segments(run.timeline(), run.signal, settle_periods=2)
    assert len(segments) == 1
    assert [r.reason for r in rejected] == [f"fewer than {MIN_PERIODS} settled electrical periods"]
    assert (rejected[0].start, rejected[0].stop) == (run.bounds[1], run.bounds[2])


def _per_period(rng: np.random.Generator, trend: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """Per-period phasors of orders 1 and 2: a level, a trend and noise of 0.01."""
    scatter = 0.01 * (rng.normal(size=trend.shape) + 1j * rng.normal(size=trend.shape))
    return np.array([0.3 + 0.1j, -0.05j]) + trend + scatter


def test_settled_period_finds_the_end_of_a_decay() -> None:
    rng = np.random.default_rng(1)
    k = np.arange(40)[:, None]
    assert settled_period(_per_period(rng, np.zeros((40, 2), np.complex128))) == 0
    decay = np.exp(-k / 2.0) * np.array([1.0, 0.5j])  # 1 -> noise (0.01) in ~9 periods
    first = settled_period(_per_period(rng, decay))
    assert first is not None and 6 <= first <= 14


def test_settled_period_refuses_a_trend_that_lasts_to_the_end() -> None:
    """A rotor still drifting at the end of the hold has no settled level to find,
    however the drift compares with the noise."""
    rng = np.random.default_rng(2)
    k = np.arange(40)[:, None]
    for slope in (0.005, 0.0125, 0.05):
        trend = (slope * k) * np.array([1.0, 1.0])
        assert settled_period(_per_period(rng, trend.astype(np.complex128))) is None, slope
    assert settled_period(_per_period(rng, np.zeros((5, 2), np.complex128))) is None  # too short


TEETH = META.rotor_teeth  # electrical periods per mechanical revolution


def _one_point(rng: np.random.Generator, levels: Sequence[complex], periods: int,
               change: Callable[[NDArray[np.float64], int], NDArray[Any]]
               ) -> list[tuple[NDArray[np.complex128], NDArray[np.float64]]]:
    """Holds one after the other at one operating point, each at its own level times
    (1 + ``change``(its periods' mechanical angles, its index)), with scatter of 0.01."""
    out = []
    for i, level in enumerate(levels):
        angle = 2 * math.pi * (np.arange(periods) + i * periods) / TEETH
        orders = level * np.array([1.0, 0.4j]) * (1.0 + change(angle, i))[:, None]
        out.append((orders + 0.01 * (rng.normal(size=orders.shape)
                                     + 1j * rng.normal(size=orders.shape)), angle))
    return out


LEVELS = (0.5, 0.3 + 0.2j, 0.6 - 0.1j, 0.4j)
"""Four trim holds' ripple levels at one operating point."""


def test_holds_that_change_only_as_the_rotor_turns_are_told_from_transients() -> None:
    rng = np.random.default_rng(7)
    # Each hold half a revolution, the level swinging by ±30 %, two periods that
    # lost samples: no settled level for the data alone, yet nothing rings.
    swing = _one_point(rng, LEVELS, 25, lambda angle, _: 0.3 * np.cos(angle + 0.4))
    swing[1][0][[3, 8]] += 2.0
    assert all(settled_period(z) is None for z, _ in swing)
    assert turning_with_rotor(swing) == [True] * 4
    # Holds at their levels with scatter alone fit any turn: no turn to speak of, and the
    # data's own verdict on them stands.
    assert not any(turning_with_rotor(_one_point(rng, LEVELS, 25, lambda a, _: 0.0 * a)))
    # A slow approach from each hold's change to its level looks alike over one hold, but
    # it restarts at every change, from the previous level.
    def approach(angle: NDArray[np.float64], i: int) -> NDArray[np.complex128]:
        since = np.arange(angle.size)
        before = LEVELS[i - 1] if i else 0.0
        return np.asarray((before / LEVELS[i] - 1.0) * np.exp(-since / 20.0), np.complex128)

    assert not any(turning_with_rotor(_one_point(rng, LEVELS, 25, approach)))
    alone = swing[:1]  # one hold cannot tell the two apart
    assert turning_with_rotor(alone) == [False]


ECCENTRIC_SWING = 0.2
"""The ripple's level swings by ±20 % once per revolution: a few percent of eccentricity
beside a mode the operating point sits near."""


def _fast_chain(amplitude_mA: int, electrical_hz: float) -> ChainDecay:
    """A fitted chain whose only mode (200 Hz, τ = 5 ms) is forgotten within 30 ms."""
    return ChainDecay((complex(-200.0, 2 * math.pi * 200.0),), math.log(300.0), 0.02)


def test_a_hold_whose_ripple_swings_with_the_rotors_angle_is_kept_at_its_mean() -> None:
    run = _offset_sweep(tau_s=0.0, periods=25, ring=0.0)
    mechanical = 2 * math.pi * run.position / (CYCLE * TEETH)
    clean = Run(run.pieces, noise=0.0).signal
    run.signal = run.signal + ECCENTRIC_SWING * np.cos(mechanical) * clean
    # The data alone see holds that never settle; the chain says nothing rings so long.
    alone, rejected = steady_segments(run.timeline(), run.signal)
    assert alone == [] and len(rejected) == 5
    segments, rejected = steady_segments(run.timeline(), run.signal,
                                         settle_fallback=_fast_chain)
    assert rejected == [] and len(segments) == 5
    for seg in segments:
        assert seg.settling is Settling.MODEL
        window = run.signal[seg.start:seg.stop]
        swing = 1.0 + ECCENTRIC_SWING * np.mean(np.cos(mechanical[seg.start:seg.stop]))
        fitted = seg.harmonics(window, orders=2)
        # The mean over the hold is the ripple at the hold's mean mechanical angle.
        truth = h1_of(_as_tuple(seg.trims)) * swing
        assert abs(fitted.h(1) - truth) < 4 * math.sqrt(fitted.var(1))
    # A slow approach is still no steady hold, whatever the chain says.
    slow = _offset_sweep(tau_s=3.0, periods=25, ring=0.0)
    kept, rejected = steady_segments(slow.timeline(), slow.signal,
                                     settle_fallback=_fast_chain)
    assert kept == []
    assert [r.reason for r in rejected] == ["the rotor did not settle within the hold"] * 5


CLOCK_PPM = 500.0
"""A sensor clock off by 500 ppm: over a 40-period hold every order turns by 2πk·0.02."""


def _clocked(pieces: Sequence[Piece], rates: Sequence[float]
             ) -> tuple[Timeline, NDArray[np.float64]]:
    """A run whose sensor, in piece i, samples ever later by ``rates[i]`` of the SYNC
    period per SYNC (a sensor's own clock), with low noise so that the turn shows."""
    run = Run(pieces, noise=0.0)
    velocity = np.concatenate([np.full(p.samples, p.v0) for p in pieces])
    travel = np.concatenate([[0.0], np.cumsum(velocity[1:])])
    n = np.arange(travel.size, dtype=np.float64)
    instant = n.copy()
    for (a, b), rate in zip(itertools.pairwise(run.bounds), rates, strict=True):
        instant[a:b] = a + (n[a:b] - a) * (1.0 + rate)
    angle = 2 * math.pi * np.interp(instant, n, travel) / CYCLE
    h1 = np.array([h1_of(t) for t in run.trims])
    h2 = np.array([h2_of(t) for t in run.trims])
    noise = np.random.default_rng(5).normal(0.0, 0.002, n.size)
    signal = np.real(h1 * np.exp(1j * angle)) + np.real(h2 * np.exp(2j * angle)) + noise
    return run.timeline(), signal


def _both_ways() -> list[Piece]:
    return [steady(40, (o, 0, 10000, 10000), v) for v in (V20, -V20) for o in (-200, 0, 200)]


def test_holds_a_sensor_clock_turns_alike_are_judged_settled_with_the_turn_taken_out(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A sensor stamping samples by its own clock makes every hold's phasors turn
    steadily, in both directions: the rotor has settled, the time base has not.
    Judged as they are, all six holds are refused (sensor_clock_drift@1819040141: 13 of
    48 refused, and the clock never named)."""
    pieces = _both_ways()
    timeline, signal = _clocked(pieces, [CLOCK_PPM * 1e-6] * len(pieces))
    segments, rejected = steady_segments(timeline, signal, settle_orders=(1, 2))
    assert rejected == [] and len(segments) == len(pieces)
    assert all(s.settling is Settling.DATA for s in segments)
    monkeypatch.setattr(segments_module, "clock_rate", lambda turns: 0.0)
    segments, rejected = steady_segments(timeline, signal, settle_orders=(1, 2))
    assert segments == []
    assert {r.reason for r in rejected} == {"the rotor did not settle within the hold"}


def test_a_hold_that_turns_alone_is_not_taken_for_a_clock() -> None:
    """One hold turning its own way is that hold's transient, not the time base: the
    others keep it from being taken out, and it is still refused."""
    pieces = _both_ways()
    rates = [0.0] * len(pieces)
    rates[2] = CLOCK_PPM * 1e-6
    timeline, signal = _clocked(pieces, rates)
    segments, rejected = steady_segments(timeline, signal, settle_orders=(1, 2))
    assert len(segments) == len(pieces) - 1
    assert [(r.start, r.reason) for r in rejected] == [
        (rejected[0].start, "the rotor did not settle within the hold")]
    bounds = np.cumsum([0, *(p.samples for p in pieces)])
    assert bounds[2] <= rejected[0].start < bounds[3]


@pytest.mark.parametrize("ppm", [-800.0, 300.0])
def test_a_clock_is_measured_from_the_turns_of_every_hold(ppm: float) -> None:
    """The pooled rate is the clock's, signed to time, not to the direction of rotation."""
    timeline, signal = _clocked(_both_ways(), [ppm * 1e-6] * 6)
    assert sensor_clock(timeline, signal) == pytest.approx(ppm * 1e-6, rel=0.05)
    assert segments_module.clock_rate([(0.0, 1e-5)] * 6) == 0.0
    assert segments_module.clock_rate([(1e-3, 1e-5)] * 2) == 0.0  # two holds are no clock
