"""What a concealed trial's plan must hold before anything is diagnosed: a unit that could
run its schedule."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import SENSOR_RANGES_G, STANDARD_GRAVITY, Effect, LoadKind
from station.diagnosis.nominal import nominal_of
from station.physics.params import UnitParams
from station.physics.plant import modal_analysis
from station.schedules import (
    RANDOM_CHARACTERIZATION,
    Schedule,
    random_characterization,
    velocity_for,
)
from station.sim.concealed import (
    BELT_MODE_MARGIN,
    COUPLING_REACH_ORDER,
    COUPLING_SPAN,
    FRICTION_HEADROOM,
    Case,
    TrialClass,
    _belt_free_hz,
    _ceiling,
    _coupling_within_reach,
    _kept_as_planned,
    _load_for,
    _runnable,
    _steady_peaks,
    coupling_mode_hz,
    nominal_equivalent,
    plan_trial,
)
from station.sim.inprocess import simulate_timeline
from station.sim.population import draw_unit


@pytest.mark.parametrize("seed", [26, 28])
def test_friction_with_its_viscous_part_stays_within_reach_of_every_moving_hold(
    seed: int,
) -> None:
    """Development belt units whose viscous drag at speed had taken the rotor to 83° of
    load angle, next to stalling, when only the Coulomb part was checked."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.FRICTION})), seed))
    unit, friction = plan.unit, plan.unit.mechanics.load_friction
    assert friction is not None
    worst = 0.0
    for hold in (h for h in plan.schedule.holds if h.velocity):
        electrical_hz = abs(hold.velocity) / (4.0 * plan.schedule.microsteps)
        load_rad_s = 2 * math.pi * electrical_hz / unit.motor.rotor_teeth * unit.gear_ratio
        needed = (max(friction.coulomb_pos_Nm, friction.coulomb_neg_Nm)
                  + friction.viscous_Nms * load_rad_s)
        capacity = unit.motor.holding_torque_Nm(hold.amplitude_mA / 1000) / unit.gear_ratio
        worst = max(worst, needed / capacity)
    assert worst <= FRICTION_HEADROOM + 1e-9



def _lowest_mode_hz(unit: UnitParams) -> float:
    return modal_analysis(unit, float(unit.rated_current_mA))[0].frequency_hz


def test_a_belt_units_twin_without_its_coupling_keeps_the_couplings_compliance_in_the_belt(
) -> None:
    """Development pair detent+load_resonance@1, a belt: the coupling's compliance in series
    with the belt sets the chain's low mode, which a twin with the belt alone would move
    far (CLI.md: a declared belt's compliance is nominal physics)."""
    cls = TrialClass(frozenset({Effect.DETENT_TORQUE, Effect.LOAD_RESONANCE}))
    unit = plan_trial(Case(cls, 1, first_draw=True)).unit
    assert unit.mechanics.belt is not None and unit.mechanics.coupling is not None
    bare = draw_unit(1, load=unit.load, effects=frozenset({Effect.DETENT_TORQUE}))
    twin = nominal_equivalent(bare, unit)
    assert twin.mechanics.coupling is None
    assert twin.motor == unit.motor
    assert _lowest_mode_hz(twin) == pytest.approx(_lowest_mode_hz(unit), rel=0.05)
    assert _lowest_mode_hz(bare) > 2 * _lowest_mode_hz(unit)


def test_a_disk_units_twin_without_its_coupling_is_the_rigid_disk() -> None:
    cls = TrialClass(frozenset({Effect.LOAD_RESONANCE}))
    unit = plan_trial(Case(cls, 21)).unit
    assert unit.mechanics.disk is not None and unit.mechanics.coupling is not None
    bare = draw_unit(21, load=unit.load, effects=frozenset())
    assert nominal_equivalent(bare, unit) is bare


def test_the_speeds_a_unit_falls_out_of_step_at_are_left_out_of_its_characterization() -> None:
    """Bench, session 15 (flux_harmonics@1173083428, a disk): above 20 Hz electrical the
    unit stalled at every current, its steady motion filled the widest range, and the
    diagnosis refused the recording. Left out, the two slow speeds make a recording the
    diagnosis takes."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.FLUX_HARMONICS})), 1173083428))
    speeds = {abs(h.velocity) for h in plan.schedule.holds if h.velocity}
    assert speeds == {8192, 9216}
    assert plan.schedule.sensor_range_g < 16
    run = simulate_timeline(plan.unit, plan.schedule, seed=plan.case.seed, loss=plan.loss)
    assert nominal_of(run)[1].balanced.chi2 > 0  # not refused


@pytest.mark.parametrize(("stalled", "spared", "kept"), [
    (set(), 0, 3),  # nothing stalled: as drawn
    ({3}, 0, 3),  # one hold clipped at a speed, the others not: a swing, not a stall
    ({0}, 0, 2),  # one speed stalled: the two others
    ({0}, 3, 2),  # a speed clipped in all but three holds: stalled still
    ({0, 1}, 0, 0),  # one speed would be left: no characterization
])
def test_a_stalled_speed_is_dropped_only_while_two_speeds_remain(
        stalled: set[int], spared: int, kept: int) -> None:
    three = replace(RANDOM_CHARACTERIZATION, speeds=(3, 3))
    schedule = random_characterization(np.random.default_rng(3), ranges=three)
    speeds = sorted({abs(h.velocity) for h in schedule.holds if h.velocity})
    full = 16 * STANDARD_GRAVITY
    peaks = [full if h.velocity and speeds.index(abs(h.velocity)) in stalled
             else (1.0 if h.velocity else 0.0) for h in schedule.holds]
    if stalled == {3}:  # not a speed: one hold of the first speed clips
        peaks[next(i for i, h in enumerate(schedule.holds) if h.velocity)] = full
    at_first = [i for i, h in enumerate(schedule.holds) if abs(h.velocity) == speeds[0]]
    assert len(at_first) > 4 * spared
    for i in at_first[:spared]:  # holds the stalled speed happened not to clip in
        peaks[i] = 0.8 * full
    assert max(peaks) == (1.0 if not stalled else full)
    runnable = _runnable(schedule, peaks)
    if not kept:
        assert runnable is None
        return
    assert runnable is not None
    out, peak = runnable
    assert len({abs(h.velocity) for h in out.holds if h.velocity}) == kept
    assert peak == (1.0 if kept == 2 else max(peaks))


def _running_hz(seed: int) -> set[float]:
    """The electrical speeds at which a detent+flux trial's planned unit runs without
    clipping the widest range (the plan's schedule probed at 16 g)."""
    cls = TrialClass(frozenset({Effect.DETENT_TORQUE, Effect.FLUX_HARMONICS}))
    plan = plan_trial(Case(cls, seed))
    probe = replace(plan.schedule, sensor_range_g=max(SENSOR_RANGES_G))
    run = simulate_timeline(plan.unit, probe, seed=plan.case.seed)
    clipped = 0.99 * max(SENSOR_RANGES_G) * STANDARD_GRAVITY
    return {abs(h.velocity) / (4 * probe.microsteps)
            for h, peak in zip(probe.holds, _steady_peaks(run, probe), strict=True)
            if h.velocity and peak < clipped}


def test_a_unit_that_runs_at_one_drawn_speed_only_is_characterized_at_others() -> None:
    """Benchmark, session 25 (detent_torque+flux_harmonics@1456061531, a disk): of its two
    drawn speeds the unit stalled at 37.5 Hz, and the recording, left with one speed, was
    refused. The trial draws another characterization, one the unit runs at two speeds
    of."""
    assert len(_running_hz(1456061531)) >= 2


def test_a_unit_that_stalls_above_a_speed_is_characterized_again_below_it() -> None:
    """Benchmark, session 50 (detent_torque+flux_harmonics@1730680244, a disk that runs only
    below about 10 Hz electrical): ten characterizations drawn over the whole 5-40 Hz all
    stalled, and the last one's recording was refused. Each new draw now stays below the
    slowest speed the unit fell out of step at so far, as the engineer would write it."""
    running = _running_hz(1730680244)
    assert len(running) >= 2
    assert max(running) < 13.5  # the first draw's slowest stall


@pytest.mark.parametrize(("stalled_hz", "below_hz", "ceiling"), [
    ((), 40.0, 40.0),  # nothing stalled: as before
    ((13.5, 24.0), 40.0, 13.0),  # below the slowest stall
    ((13.5,), 9.0, 9.0),  # never above an earlier ceiling
    ((5.0, 5.5), 40.0, 5.5),  # never so low that two speeds cannot be drawn
])
def test_the_next_characterization_stays_below_the_slowest_stalled_speed(
        stalled_hz: tuple[float, ...], below_hz: float, ceiling: float) -> None:
    schedule = random_characterization(np.random.default_rng(5))
    # Holds at the stalled speeds (every one of them clipped) beside the drawn ones.
    stalls = {velocity_for(f, schedule.microsteps) for f in stalled_hz}
    holds = [*schedule.holds, *(replace(schedule.holds[1], velocity=v) for v in stalls)]
    full = 16 * STANDARD_GRAVITY
    peaks = [full if abs(h.velocity) in stalls else 1.0 for h in holds]
    assert _ceiling(replace(schedule, holds=tuple(holds)), peaks, below_hz) == ceiling


def _fastest_hz(schedule: Schedule) -> float:
    return max(abs(h.velocity) for h in schedule.holds) / (4.0 * schedule.microsteps)


@pytest.mark.parametrize("load", [LoadKind.DISK, LoadKind.BELT])
def test_a_concealed_coupling_is_put_where_the_schedules_harmonics_reach_its_mode(
    load: LoadKind,
) -> None:
    """A coupling drawn over 60-400 Hz whatever the schedule was beyond every order the
    drive's strong harmonics reached on 7 of 8 benchmark trials: nothing to see. Moved
    within reach, never onto a belt's own free mode; left alone where it was already
    there; the same from the same seed."""
    effects = frozenset({Effect.LOAD_RESONANCE})
    moved = kept = 0
    for seed in range(40):
        unit = draw_unit(seed, load=load, effects=effects)
        if unit.mechanics.belt is not None and (
                BELT_MODE_MARGIN * _belt_free_hz(unit.mechanics.belt)
                >= COUPLING_REACH_ORDER * RANDOM_CHARACTERIZATION.electrical_hz[1]):
            continue  # ``plan_trial`` puts such a coupling on a disk
        schedule = random_characterization(np.random.default_rng(seed))
        reach = COUPLING_REACH_ORDER * _fastest_hz(schedule)
        placed = _coupling_within_reach(unit, schedule, seed)
        mode = coupling_mode_hz(placed)
        assert placed.mechanics.coupling is not None
        assert placed.mechanics.coupling.damping_ratio == unit.mechanics.coupling.damping_ratio  # type: ignore[union-attr]
        assert placed == _coupling_within_reach(unit, schedule, seed)
        if coupling_mode_hz(unit) <= reach:
            assert placed == unit
            kept += 1
            continue
        moved += 1
        if unit.mechanics.belt is None:
            assert reach / COUPLING_SPAN <= mode <= reach * (1 + 1e-9)
        else:
            floor = BELT_MODE_MARGIN * _belt_free_hz(unit.mechanics.belt)
            assert mode >= floor * (1 - 1e-9)
            assert mode <= max(reach, floor) * (1 + 1e-9)
        assert placed.motor == unit.motor and placed.mechanics.belt == unit.mechanics.belt
    assert moved >= 5 and kept >= 1


def test_a_belt_whose_pulley_and_load_swing_apart_beyond_any_reach_carries_its_coupling_on_a_disk(
) -> None:
    """Such a belt's coupling can only soften the belt, which CLI.md makes nominal physics:
    a trial concealing it would conceal nothing."""
    effects = frozenset({Effect.LOAD_RESONANCE})
    widest = COUPLING_REACH_ORDER * RANDOM_CHARACTERIZATION.electrical_hz[1]
    seen = set()
    for seed in range(40):
        belt = draw_unit(seed, load=LoadKind.BELT, effects=effects).mechanics.belt
        assert belt is not None
        reachable = BELT_MODE_MARGIN * _belt_free_hz(belt) < widest
        case = Case(TrialClass(effects), seed)
        assert _load_for(case, LoadKind.BELT) is (LoadKind.BELT if reachable else LoadKind.DISK)
        assert _load_for(case, LoadKind.DISK) is LoadKind.DISK
        assert _load_for(Case(TrialClass(frozenset({Effect.DETENT_TORQUE})), seed),
                         LoadKind.BELT) is LoadKind.BELT
        seen.add(reachable)
    assert seen == {True, False}


def test_a_twin_keeps_the_coupling_and_friction_its_unit_was_planned_with() -> None:
    """The plan moves a coupling and scales friction for its schedule; a twin drawn again
    from the seed would carry them as first drawn, and differ from its unit by more than
    the effect taken away."""
    effects = frozenset({Effect.LOAD_RESONANCE, Effect.FRICTION, Effect.DETENT_TORQUE})
    unit = draw_unit(5, load=LoadKind.DISK, effects=effects)
    mech = unit.mechanics
    assert mech.coupling is not None and mech.load_friction is not None
    planned = replace(unit, mechanics=replace(
        mech, coupling=replace(mech.coupling, stiffness_Nm_per_rad=1.0),
        load_friction=replace(mech.load_friction, coulomb_pos_Nm=0.0)))
    kept = effects - {Effect.DETENT_TORQUE}
    twin = _kept_as_planned(draw_unit(5, load=LoadKind.DISK, effects=kept), planned)
    assert twin.mechanics.coupling == planned.mechanics.coupling
    assert twin.mechanics.load_friction == planned.mechanics.load_friction
    bare = _kept_as_planned(draw_unit(5, load=LoadKind.DISK, effects=frozenset()), planned)
    assert bare.mechanics.coupling is None and bare.mechanics.load_friction is None
