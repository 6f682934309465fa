"""What the diagnosis's model must get right on recordings of known physics.

Each test records one development trial in process (the truth known, seeds
below ``TRIAL_SEED_FLOOR``) and checks one piece of the model against it:
not whether the search names the right id (the acceptance test and the
benchmark judge that) but whether the model can describe the physics at all.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from scipy.optimize._lsq import trf
from threadpoolctl import threadpool_limits

from station.analysis import segments
from station.analysis.harmonics import demodulate
from station.analysis.pipeline import measure, tangential_signal
from station.analysis.segments import ChainDecay
from station.core import Effect
from station.diagnosis import axes, chain, diagnose, floors, observations
from station.diagnosis import candidates as candidates_module
from station.diagnosis import fit as fit_module
from station.diagnosis import nominal as nominal_module
from station.diagnosis.candidates import (
    REGRID_KEEP,
    candidate_of,
    coupling_as_belt,
    fit_spec,
    kept_physics,
)
from station.diagnosis.effects import friction as friction_module
from station.diagnosis.effects import grid_shared, terms
from station.diagnosis.effects.current_distortion import DEAD_TIME_KNEE
from station.diagnosis.effects.friction import (
    FRICTION_SMOOTHING_MAX,
    SETTLED_SCALE,
    cell_means,
    cell_means_made,
    friction_response,
    friction_response_on,
    friction_shapes,
    load_velocity,
)
from station.diagnosis.effects.load_resonance import belt_as_coupling
from station.diagnosis.effects.magnetic_saturation import saturation_shapes, saturation_slopes
from station.diagnosis.effects.sensor_clock_drift import (
    CLOCK_PEAKS,
    CLOCK_RATES_PPM,
    MIN_CLOCK_PPM,
    ClockScan,
    sawtooth_mean,
    segment_delays,
)
from station.diagnosis.effects.sensor_clock_drift import starts as clock_starts
from station.diagnosis.fit import (
    HEAT_FIELD,
    REJECT_MARGIN,
    Fit,
    best_of,
    chosen_starts,
    covariance,
    first_passes_shared,
    fit,
    held_out,
    jacobian,
    polish,
    polished_on,
    rank_passed,
    resting,
    screen,
)
from station.diagnosis.hooks import Role
from station.diagnosis.layout import ChainKind, ModelSpec, chain_for
from station.diagnosis.model import FRICTION_KEYS, GRID, Model
from station.diagnosis.motion import Motion
from station.diagnosis.name import (
    MODEL_ERROR_SHARE,
    Search,
    compare,
    explains_the_rest,
    local_groups,
    tied_to_rotor,
    unexplained_of,
    without_soakers,
)
from station.diagnosis.nominal import (
    GRID_EXACT,
    SETTLE_TRUST_CHI2,
    Nominal,
    _refine_angles,
    fit_nominal,
    nominal_of,
    nominal_starts,
    settle_fallback,
    settling_warnings,
    transplanted,
)
from station.diagnosis.observations import (
    DIAGNOSIS_ORDERS,
    Holds,
    NotDiagnosable,
    Observations,
    observe,
)
from station.diagnosis.results import Candidate
from station.physics.motor import rest_angle
from station.physics.params import SensorParams, UnnamedEffect
from station.schedules import RandomCharacterizationRanges, random_characterization
from station.sim.concealed import PLANT_SUBSTEPS, Case, TrialClass, plan_trial
from station.sim.inprocess import simulate_timeline
from station.sim.population import belt_mode_motor_held_hz, draw_unit

if TYPE_CHECKING:  # not imported at run time: pytest would take the class for tests
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from station.analysis.timeline import Timeline
    from station.diagnosis.results import Test


def _case(cls: TrialClass, seed: int, *, first_draw: bool = False) -> Case:
    """A development case as its plant was when the test was written: these tests pin
    mechanisms on particular plants, drawn before every unit had a healthy unit's bearings
    (``Case.paper_bearings``); the acceptance test draws today's units."""
    return Case(cls, seed, first_draw=first_draw, paper_bearings=True)


# A case's plan, recording, observations and fits are made once per process and shared
# by every test that reads them (a second to seconds each): they are frozen, and no test
# changes them.
_plan = functools.cache(plan_trial)


@functools.cache
def _timeline(case: Case) -> Timeline:
    """The case's recording, made in process."""
    plan = _plan(case)
    return simulate_timeline(plan.unit, plan.schedule, seed=case.seed, loss=plan.loss,
                             substeps=PLANT_SUBSTEPS)


def _clock_estimates(model: Model, start: NDArray[np.float64]) -> list[dict[str, list[float]]]:
    """The clock's estimated starts, screened by the fit as ``candidates.fit_spec`` has them."""
    estimates = terms(Effect.SENSOR_CLOCK_DRIFT).estimates
    assert estimates is not None
    return estimates(model, start, screen)


@functools.cache
def _observations(case: Case) -> Observations:
    return observe(_timeline(case))


def _observed(effect: Effect, seed: int) -> tuple[Observations, Case]:
    case = _case(TrialClass(frozenset({effect})), seed)
    return _observations(case), case


@functools.cache
def _nominal_fit(case: Case) -> tuple[Observations, Nominal]:
    """The case's observations as the nominal fit settles them, and that fit."""
    with threadpool_limits(limits=1, user_api="blas"):
        return nominal_of(_timeline(case))


@functools.cache
def _grid_nominal(effect: Effect, seed: int) -> Nominal:
    """The nominal fit of a case's first observations (``fit_nominal``, no settling pass),
    which several tests start their searches from."""
    obs, _ = _observed(effect, seed)
    with threadpool_limits(limits=1, user_api="blas"):
        return fit_nominal(obs)


def _sensor_truth(sensor: SensorParams) -> dict[str, list[float]]:
    """The model's sensor low-pass 1/(1 + a1·s + a2·s²) at the plant sensor's own."""
    w0 = 2 * math.pi * sensor.bandwidth_hz
    return {"sensor_a1_ms": [2 * sensor.damping_ratio / w0 * 1e3],
            "sensor_a2_ms2": [1e6 / w0**2]}


def _truth_start(model: Model, case: Case) -> np.ndarray:
    """The model's parameters at the plant's own values where the model has them."""
    unit = _plan(case).unit
    motor = unit.motor
    p = model.with_values(model.layout.start(), _sensor_truth(unit.sensor))
    sl = model.layout.slices
    disk = unit.mechanics.disk
    assert disk is not None, "these development seeds draw disk units"
    inertia = motor.rotor_inertia_kgm2 + disk.inertia_kgm2
    w1 = math.sqrt(motor.rotor_teeth * motor.kt_Nm_per_A / inertia)
    drag = unit.mechanics.rotor_bearing.viscous_Nms
    p[sl["log_rotor_hz"]] = math.log(w1 / (2 * math.pi))
    p[sl["rotor_damping_ratio"]] = drag / motor.kt_Nm_per_A * w1 / (2 * motor.rotor_teeth)
    p[sl["amp_offset_mA"]] = (unit.amplifier.offset_a_mA, unit.amplifier.offset_b_mA)
    p[sl["amp_gain_error"]] = (unit.amplifier.gain_error_a, unit.amplifier.gain_error_b)
    # The bearings' Coulomb friction, in Kt units (a disk: the rotor is the load).
    bearing = unit.mechanics.rotor_bearing
    p[sl["friction_coulomb"]] = (bearing.coulomb_pos_Nm / motor.kt_Nm_per_A,
                                 bearing.coulomb_neg_Nm / motor.kt_Nm_per_A)
    return p


def _case_nominal(case: Case) -> Nominal:
    """The case's recording (made in process) and its nominal fit."""
    return _nominal_fit(case)[1]


def _with(nominal: Nominal, effect: Effect) -> Fit:
    """The nominal model with ``effect``'s group added, fitted as the diagnosis fits it."""
    base = nominal.balanced
    with threadpool_limits(limits=1, user_api="blas"):
        spec = replace(base.model.spec, effects=frozenset({effect}))
        return fit_spec(base.model.obs, spec, base, nominal.free)


@functools.cache
def _added(case: Case, effect: Effect) -> Test:
    """The case's nominal fit, tested against the same with ``effect``'s group added (as
    the diagnosis fits and compares them)."""
    nominal = _case_nominal(case)
    base, larger = nominal.balanced, _with(nominal, effect)
    with threadpool_limits(limits=1, user_api="blas"):
        return compare(Candidate(base.model.spec, base, held_out(base)),
                       Candidate(larger.model.spec, larger, held_out(larger)))


@pytest.mark.parametrize("with_higher_orders", [True, False])
def test_a_strong_flux_ripple_is_described_to_the_noise_only_with_the_higher_orders_swing(
    with_higher_orders: bool,
) -> None:
    """Strong ripple swings the rotor at orders above 8 too; the torque of orders 1..8
    is evaluated on that swing, and without it a few per cent of error stay."""
    obs, case = _observed(Effect.FLUX_HARMONICS, 24)
    if not with_higher_orders:
        obs = replace(obs, beyond=None)
    with threadpool_limits(limits=1, user_api="blas"):
        model = Model(ModelSpec(chain_for(obs.metadata.gear_ratio),
                                frozenset({Effect.FLUX_HARMONICS})), obs)
        # The load angles are no plant constant: each condition's balances its bearings'
        # friction, which a start at zero lies a few tenths of a radian from.
        result = fit(model, [_refine_angles(model, _truth_start(model, case))], keep=1,
                     max_nfev=100)
    per_dof = result.chi2 / result.dof
    if with_higher_orders:
        assert per_dof < 1.5
    else:
        assert per_dof > 2.0


def test_a_drifting_sensor_clock_is_found_from_the_recording_alone() -> None:
    """The periodogram of the segments' delays, its peaks and the sawtooth's phase give
    starts from which the fit lands on the plant's drift."""
    _, case = _observed(Effect.SENSOR_CLOCK_DRIFT, 24)
    truth = _plan(case).unit.sensor.clock_drift_ppm
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.SENSOR_CLOCK_DRIFT, 24).balanced
        model = Model(replace(nominal.model.spec,
                              effects=frozenset({Effect.SENSOR_CLOCK_DRIFT})), nominal.model.obs)
        start = transplanted(model, nominal)
        starts = [model.with_values(start, values)
                  for values in _clock_estimates(model, start)]
        result = fit(model, starts, keep=len(starts))
    assert result.scalar("clock_drift_ppm") == pytest.approx(truth, abs=5.0)
    assert result.chi2 < 0.5 * nominal.chi2


@pytest.mark.xfail(strict=True, reason=(
    "issue 90: with the bearings' Coulomb friction in the nominal model the holds' delays "
    "follow the plant's clock to a median of 0.069 of a SYNC period, not 0.05; a known "
    "regression to mend"))
def test_a_clocks_sawtooth_is_measured_at_its_full_size_so_its_rate_stands_out() -> None:
    """The segments' delays are Gauss-Newton steps on the model's own error: the phase of
    measured over the equation error's prediction, which follows the data below the
    rotor's mode, measured about half the sawtooth, and this trial's rate (−256 ppm,
    few segments) was not among the periodogram's twelve peaks. Between the holds of one
    condition the delay must now advance as the plant's clock does."""
    obs, case = _observed(Effect.SENSOR_CLOCK_DRIFT, 45)
    sensor = _plan(case).unit.sensor
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = fit_nominal(obs).balanced
        model = Model(replace(nominal.model.spec,
                              effects=frozenset({Effect.SENSOR_CLOCK_DRIFT})), nominal.model.obs)
        start = transplanted(model, nominal)
        delay, _ = segment_delays(model, start)
        peaks = clock_starts(model, start, CLOCK_PEAKS)
    assert peaks[0]["clock_drift_ppm"][0] == pytest.approx(sensor.clock_drift_ppm, abs=10.0)
    period = obs.metadata.sync_period_s
    n = obs.span.mean(axis=1)
    truth = (sensor.sample_phase - n * sensor.clock_drift_ppm * 1e-6) % 1.0
    steps, expected = [], []
    for c in range(len(obs.conditions)):
        mine = np.flatnonzero(obs.condition == c)
        steps += list(np.diff(delay[mine] / period))
        expected += list(np.diff(truth[mine]))
    # Wrapped into one period: a step across the sawtooth's wrap is a step all the same.
    gap = (np.array(steps) - np.array(expected) + 0.5) % 1.0 - 0.5
    assert np.median(np.abs(gap)) < 0.05, gap


def test_a_clocks_rate_and_its_aliases_are_told_from_the_holds_own_rhythm() -> None:
    """Holds of one length sample the sawtooth once each: rates one sawtooth per hold
    apart give the same delays at every hold's centre, so the periodogram cannot choose
    between them and the fit must see each (on a belt the screen dropped the true rate
    for its alias, sensor_clock_drift@572933410: χ² 156,125 where 865 was to be had).
    Rates that are aliases of no drift at all are the base model's delay, not a lead."""
    hold, holds, period = 429, 128, 1e-3
    centre = np.asarray(3000.0 + hold * (np.arange(holds) + 0.5), dtype=np.float64)
    drift, phase = -169.6, 0.3
    rng = np.random.default_rng(7)
    delay = period * ((phase - centre * drift * 1e-6) % 1.0) + rng.normal(0.0, 2e-5, holds)
    middle = 0.5 * (3000.0 + centre[-1] + hold / 2)
    scan = ClockScan(delay, np.ones(holds), centre, period, middle)
    peaks = [p["clock_drift_ppm"][0] for p in scan.peaks(CLOCK_PEAKS)]
    rates = [r for r in peaks if abs(r) >= MIN_CLOCK_PPM]
    family = scan.family(rates)
    step = 1e6 / hold  # ppm: one sawtooth more per hold
    assert any(abs(r - drift) < 2.0 for r in family)
    for rate in family:
        assert (rate - drift) / step == pytest.approx(round((rate - drift) / step), abs=0.01)
    assert any(abs(r - drift - step) < 2.0 for r in family)
    # Rates a whole number of sawtooths per hold from none (a recording's constant delay
    # makes peaks there) lead nothing, however strong.
    led = scan.family([step, -2.0 * step, *rates])
    assert sorted(led) == sorted(family)
    # The sawtooth's phase at the recording's middle comes with the rate.
    lead = next(p for p in scan.peaks(CLOCK_PEAKS) if abs(p["clock_drift_ppm"][0] - drift) < 2)
    expected = (phase - middle * drift * 1e-6) % 1.0
    assert (lead["clock_phase"][0] - expected + 0.5) % 1.0 - 0.5 == pytest.approx(0.0, abs=0.02)


@pytest.mark.parametrize("drift_ppm", [-2400.0, -37.0, 0.0, 5.0, 412.0])
def test_a_wrapping_clocks_segment_mean_is_the_mean_over_its_samples(drift_ppm: float) -> None:
    """The exact integral the clock model uses against the plain mean over the samples
    (the integral treats samples as a continuum: within a few parts in ten thousand)."""
    spans = np.array([[-20000.0, -19500.0], [300.0, 1100.0], [41000.0, 41250.0]])
    omega = np.array([2 * np.pi * 13.0, -2 * np.pi * 7.0, 2 * np.pi * 18.0])
    k = np.arange(1.0, 9.0)
    phase, t = 0.37, 1e-3
    a = k[None, :] * omega[:, None] * t
    exact = sawtooth_mean(phase - spans[:, 0] * drift_ppm * 1e-6,
                          phase - spans[:, 1] * drift_ppm * 1e-6, a)
    for s, (first, last) in enumerate(spans):
        n = np.arange(first, last) + 0.5
        delays = np.mod(phase - n * drift_ppm * 1e-6, 1.0)
        sampled = np.exp(-1j * a[s][:, None] * delays[None, :]).mean(axis=1)
        assert np.max(np.abs(exact[s] - sampled)) < 1e-3, (s, drift_ppm)


def test_the_saturation_group_can_only_take_torque_away_over_the_recorded_currents() -> None:
    """Any weights the group's bounds allow give a Kt that never rises with the current up
    to the recording's largest: a Kt rising with current is a reluctance spring, and a
    group that could pose as one would be named for it."""
    u2 = np.linspace(0.0, 1.0, 201) ** 2
    b1, b2 = saturation_shapes(u2)
    rng = np.random.default_rng(5)
    for w1, w2 in rng.uniform(0.0, 0.8, size=(200, 2)):
        kt = 1.0 - w1 * b1 - w2 * b2
        assert np.all(np.diff(kt) <= 1e-12)
    # Both ends of the family: falling early and levelling off, flat first and steepening.
    step = 1e-4
    ends = saturation_shapes(np.array([0.0, step, 1.0 - step, 1.0]))
    assert (ends[0][3] - ends[0][2]) / step < 1e-3 < (ends[0][1] - ends[0][0]) / step
    assert (ends[1][1] - ends[1][0]) / step < 1e-3 < (ends[1][3] - ends[1][2]) / step
    # The slopes the fit's Jacobian uses are the shapes' own derivatives.
    ahead, behind = saturation_shapes(u2 + 1e-6), saturation_shapes(u2 - 1e-6)
    for up, down, slope in zip(ahead, behind, saturation_slopes(u2), strict=True):
        assert np.allclose((up - down) / 2e-6, slope, atol=1e-6)


def test_a_saturating_motors_fall_of_torque_across_its_currents_is_measured() -> None:
    """The plant's 1/√(1 + (I/I_s)²) is not the model's law; the fall between the lowest
    and the largest current recorded must still come out within 4σ of the plant's."""
    case = _case(TrialClass(frozenset({Effect.MAGNETIC_SATURATION})), 24)
    motor = _plan(case).unit.motor
    result = _added(case, Effect.MAGNETIC_SATURATION).larger.fit
    model = result.model
    lowest = float(np.min(model.obs.amplitude_A))
    fitted = terms(Effect.MAGNETIC_SATURATION).readout(result, covariance(result))
    largest_drop = fitted["kt_drop_at_largest_current_percent"] / 100.0
    b1, b2 = saturation_shapes(np.array((lowest / model.largest_A) ** 2))
    w = result.params[model.layout.slices["saturation"]]
    lowest_drop = float(b1 * w[0] + b2 * w[1])
    measured = (1.0 - largest_drop) / (1.0 - lowest_drop)
    plant = float(motor.saturation_factor(model.largest_A) / motor.saturation_factor(lowest))
    assert plant < 0.97, "the development trial must saturate visibly"
    sigma = fitted["sigma_percent"] / 100.0
    assert abs(measured - plant) < 4.0 * sigma, (measured, plant, sigma)


def _leaving_more(candidate: Candidate, chi2: float) -> Candidate:
    """``candidate`` leaving ``chi2`` more on held-out data, spread over its conditions."""
    held = candidate.held
    return replace(candidate, held=replace(held, chi2=held.chi2 + chi2 / held.chi2.size))


def _beside(case: Case, first: Effect, second: Effect) -> Test:
    """The case's model with ``first``'s group, tested against the same with ``second``'s
    beside it (each judged as the search judges it)."""
    nominal = _case_nominal(case)
    smaller = _with(nominal, first)
    obs, chi2 = smaller.model.obs, nominal.balanced.chi2
    with threadpool_limits(limits=1, user_api="blas"):
        larger = fit_spec(obs, replace(smaller.model.spec, effects=frozenset({first, second})),
                          smaller, nominal.free)
        return compare(candidate_of(obs, chi2, smaller), candidate_of(obs, chi2, larger))


def test_a_once_per_revolution_load_without_airgap_modulation_is_an_eccentric_rotor() -> None:
    """CLI.md's rotor_eccentricity is a torque *or a load* periodic once per mechanical
    revolution, and a simulator written apart from ours may make it a load alone. A
    constant load within each electrical period puts no ripple of its own in the band:
    it slips the rotor along its spring, which turns every harmonic's phase, by a
    different amount at each trim step as the rotor turns. Development rotor
    eccentricity@101 (a disk) with the airgap's modulation taken out and its unbalance
    ten times the plant's (2.4 % of the holding torque) was named nothing, with a
    mismatch, until the group carried the load: nominal 7,161 held out, with it 1,175
    (its clean twin's nominal 1,395), at the plant's size and angle."""
    case = _case(TrialClass(frozenset({Effect.ROTOR_ECCENTRICITY})), 101)
    plan = _plan(case)
    ecc = plan.unit.motor.eccentricity
    assert ecc is not None
    load_only = replace(ecc, relative=0.0, unbalance_Nm=10.0 * ecc.unbalance_Nm)
    unit = replace(plan.unit, motor=replace(plan.unit.motor, eccentricity=load_only))
    timeline = simulate_timeline(unit, plan.schedule, seed=case.seed, loss=plan.loss,
                                 substeps=PLANT_SUBSTEPS)
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = nominal_of(timeline)[1]
    larger = _with(nominal, Effect.ROTOR_ECCENTRICITY)
    base = nominal.balanced
    with threadpool_limits(limits=1, user_api="blas"):
        test = compare(Candidate(base.model.spec, base, held_out(base)),
                       Candidate(larger.model.spec, larger, held_out(larger)))
    assert test.significant
    assert test.larger.held.total < 0.25 * test.smaller.held.total
    # U·cos φ and U·sin φ of the load U·sin(θ + φ), per holding torque at the largest current,
    # θ counted as the drive counts it: from the tooth the enabled field pulled the rotor
    # to, from where it rested when the unit arrived (``rest_angle``).
    u = complex(*larger.value("unbalance")) * larger.model.largest_A
    pitch = 2 * np.pi / unit.motor.rotor_teeth
    start = pitch * round(rest_angle(unit.motor) / pitch)
    plant = load_only.unbalance_Nm / unit.motor.kt_Nm_per_A * np.exp(
        1j * (ecc.unbalance_phase_rad + start))
    assert abs(u - plant) < 0.05 * abs(plant)
    assert abs(complex(*larger.value("eccentricity"))) < 0.01  # the airgap: 0.07 % fitted


def test_an_eccentric_rotor_beside_strong_flux_harmonics_is_judged_against_wrong_angles(
) -> None:
    """An eccentric rotor modulates a strong flux ripple by a few percent, far less than the
    share of the flux's χ² that the flux group's own errors may leave. Those errors do not
    follow where the rotor stands in its revolution, so the eccentricity is judged against
    itself fitted at twice and three times that angle instead, and counts, at the plant's
    size. Tied to the rotor's angle, it stays named where it leaves more than it takes
    (it takes only a part of what the modulated spring does beside the rotor's
    resonance), unlike an id that gains as much at any angle. On the twin with the flux
    alone it gains nothing at any angle."""
    flux, eccentric = Effect.FLUX_HARMONICS, Effect.ROTOR_ECCENTRICITY
    both = _case(TrialClass(frozenset({flux, eccentric})), 204)
    test = _beside(both, flux, eccentric)
    assert test.model_error < 0.1 * MODEL_ERROR_SHARE * test.smaller.explained
    assert test.significant
    fitted = abs(complex(*test.larger.fit.value("eccentricity")))
    plant = _plan(both).unit.motor.eccentricity
    assert plant is not None
    assert fitted == pytest.approx(plant.relative, rel=0.2)
    assert tied_to_rotor(test.smaller, test.larger)

    # Both models leaving, beyond the noise, twice what the eccentricity takes.
    values = test.larger.held.residuals.size
    left = 2.0 * test.held_gain + values + MODEL_ERROR_SHARE * test.larger.explained

    best, flux_only = _leaving_more(test.larger, left), _leaving_more(test.smaller, left)
    # Without the flux, the eccentricity alone would leave nearly all of the flux's ripple.
    eccentric_only = replace(_leaving_more(best, 1e6), wrong_angle=None,
                             spec=replace(best.spec, effects=frozenset({eccentric})))

    def lacking(model: Candidate) -> dict[Effect, Candidate]:
        return {e: c for e, c in ((flux, eccentric_only), (eccentric, flux_only))
                if e in model.effects}

    assert without_soakers(best, lacking).effects == {flux, eccentric}
    at_any_angle = replace(best, wrong_angle=best.fit.chi2)
    assert not tied_to_rotor(flux_only, at_any_angle)
    assert without_soakers(at_any_angle, lacking).effects == {flux}

    twin = _beside(_case(TrialClass(frozenset({flux})), 204), flux, eccentric)
    assert not twin.significant
    assert not tied_to_rotor(twin.smaller, twin.larger)


def test_a_coupling_beside_a_strong_detent_is_found_from_a_start_its_first_rank_passed_over(
) -> None:
    """Solved at each of the coupling's starts, a strong detent's linear parts favour any
    frequency where the ripple they leave is large, so the starts ranked best before a
    polish are not the ones that lead to the coupling: every start gets the short polish
    (``EffectTerms.tournament``). On this belt (a detent and a second compliance at 285 Hz) the
    two best-ranked starts settled at χ² 690 and the coupling did not count."""
    test = _coupling_beside_detent()
    assert test.significant
    plant = _plan(_DETENT_AND_COUPLING).unit.mechanics.coupling
    assert plant is not None
    fitted = math.exp(float(test.larger.fit.value("log_coupling_hz")[0]))
    assert fitted == pytest.approx(plant.resonance_hz, rel=0.1)


@pytest.mark.xfail(strict=True, reason=(
    "issue 90: with the bearings' Coulomb friction in the nominal model the pair stops at "
    "χ² 5,865 for 1,438 dof from flux's bent chain, and the whole diagnosis names "
    "magnetic_saturation beside the pair again; a known regression to mend"))
def test_a_larger_model_also_starts_from_the_chain_its_other_smaller_model_bent(
) -> None:
    """A bent smaller model's chain is wherever its groups hid best, not where the larger
    model's chain is. On this belt (detent torque and flux harmonics; rotor 221 Hz, load
    ratio 1.7, belt 414 Hz) detent alone bent the chain to a light load with a 130 Hz
    belt (χ² 76,902), flux alone to 148 and 359 Hz (127,303); the pair started from the
    better one only stopped at 4,945 and the diagnosis named magnetic saturation as a
    third effect for what was left. From flux's chain too, the pair reaches the plant's
    (development trial detent_torque+flux_harmonics@821054)."""
    detent, flux = Effect.DETENT_TORQUE, Effect.FLUX_HARMONICS
    case = _case(TrialClass(frozenset({detent, flux})), 821054)
    nominal = _case_nominal(case)
    base, obs = nominal.balanced, nominal.balanced.model.obs
    with threadpool_limits(limits=1, user_api="blas"):
        alone = {e: fit_spec(obs, replace(base.model.spec, effects=frozenset({e})), base,
                             nominal.free) for e in (detent, flux)}
        best, other = sorted(alone.values(), key=lambda f: f.chi2)
        pair = fit_spec(obs, replace(base.model.spec, effects=frozenset({detent, flux})),
                        best, nominal.free, others=[other])
    assert best.chi2 > 10 * best.dof  # both bent
    assert pair.chi2 < 2 * pair.dof
    belt = _plan(case).unit.mechanics.belt
    assert belt is not None
    plant_hz = belt_mode_motor_held_hz(belt)
    assert math.exp(float(pair.value("log_belt_hz")[0])) == pytest.approx(plant_hz, rel=0.1)


_DETENT_AND_COUPLING = _case(TrialClass(frozenset({Effect.DETENT_TORQUE,
                                                  Effect.LOAD_RESONANCE})), 1838253693,
                            first_draw=True)


@functools.cache
def _coupling_beside_detent() -> Test:
    return _beside(_DETENT_AND_COUPLING, Effect.DETENT_TORQUE, Effect.LOAD_RESONANCE)


def test_a_second_pass_keeps_a_group_in_its_range_where_a_basin_beside_it_is_no_longer_it(
) -> None:
    """A coupling damped at its bound of 2 is a filter, not a transmission mode, and is
    rejected. When the second pass's fit lands there while the first pass's fit of the
    same model did not, the model is polished again from the first pass's point, and
    that fit is kept if it stays in range; a rejected first fit, or a fit in range, is
    left as it is."""
    found = _coupling_beside_detent().larger.fit
    assert not found.rejected
    zeta = found.model.layout.slices["coupling_damping_ratio"]
    at_bound_params, at_bound_active = found.params.copy(), found.active.copy()
    at_bound_params[zeta], at_bound_active[zeta] = 2.0, 1
    filtered = replace(found, params=at_bound_params, active=at_bound_active)
    assert filtered.rejected == ("coupling_damping_ratio",)
    kept = kept_physics(found.model, filtered, found)
    assert not kept.rejected
    # Polished again from the first pass's point it may do better than the fit it replaces
    # (with the bearings' friction in the nominal model it ends 1.6 % lower), never worse.
    assert kept.chi2 <= found.chi2 * (1.0 + 1e-3)
    assert kept_physics(found.model, filtered, filtered) is filtered
    assert kept_physics(found.model, found, filtered) is found


def test_the_second_pass_tries_every_group_where_more_than_noise_is_left() -> None:
    """Beside a model at the noise the second pass tries what the first pass carried;
    beside one that leaves a significant residual, every group, since a group the first
    pass passed over beside a strong one may be what is left."""
    found = _coupling_beside_detent().larger
    carried = (Effect.DETENT_TORQUE, Effect.LOAD_RESONANCE)
    assert not unexplained_of(found).significant
    assert local_groups(found, carried) == carried
    values = found.held.residuals.size
    # Two per value: beyond the limit (1.25 per value and four σ) whatever the fit left.
    leaving = _leaving_more(found, 2.0 * values)
    assert unexplained_of(leaving).significant
    assert set(local_groups(leaving, carried)) == set(Effect)


def _one_hold_leaving(candidate: Candidate, chi2: float, holds: list[int]) -> Candidate:
    """``candidate`` whose held-out residuals leave ``chi2`` more, shared by ``holds``."""
    model = candidate.fit.model
    rows, conditions = model.residual_rows(), model.residual_conditions()
    residuals, per_condition = candidate.held.residuals.copy(), candidate.held.chi2.copy()
    for hold in holds:
        inside = rows == hold
        before = float(residuals[inside] @ residuals[inside])
        residuals[inside] = math.sqrt((before + chi2 / len(holds)) / np.count_nonzero(inside))
        per_condition[conditions[inside][0]] += chi2 / len(holds)
    return replace(candidate, held=replace(candidate.held, chi2=per_condition,
                                           residuals=residuals))


def test_a_residual_one_hold_carries_alone_is_no_mismatch_but_is_said_where() -> None:
    """Physics a model lacks shows in every hold of the operating points it touches; one
    hold alone beyond the noise is a transient its settling did not describe. The same
    excess shared by a few holds is a mismatch."""
    found = _coupling_beside_detent().larger
    assert unexplained_of(found).lone is None
    excess = 2.0 * found.held.residuals.size  # beyond 1.25 per value and four σ
    obs = found.fit.model.obs
    hold = obs.count // 2
    alone = unexplained_of(_one_hold_leaving(found, excess, [hold]))
    assert alone.chi2 > excess and not alone.significant
    assert alone.lone is not None
    assert alone.lone.condition == obs.conditions[int(obs.condition[hold])]
    assert alone.lone.start_s < obs.time_s[hold] < alone.lone.stop_s
    assert alone.lone.chi2 > excess
    assert "carried_by_one_hold" in alone.as_dict()
    shared = unexplained_of(_one_hold_leaving(found, excess, [hold - 9, hold, hold + 9]))
    assert shared.significant and shared.lone is None


@pytest.mark.xfail(strict=True, reason=(
    "issue 90: with the bearings' friction (its smoothing fitted) in the nominal model, the "
    "detent model polished from the coupling moved into the belt still leaves a held-out "
    "gain of 296 to the coupling, over its threshold of 9.4; a known regression to mend"))
def test_a_coupling_that_is_the_declared_belt_itself_does_not_count_as_a_second_mode(
) -> None:
    """On this belt (detent torque, no coupling; belt mode 143 Hz at ζ 0.12 with the motor
    held) the detent model's belt sat where it did nothing and a coupling took the belt's
    own mode: named load_resonance beside detent_torque, the trial scored 0 (benchmark,
    session 28). Polished from the coupling's point with the coupling's group taken out,
    the belt stays where it was; moved into the belt (``coupling_as_belt``), the model
    without the coupling fits as well as the one with it, and its belt is the plant's.

    That fit is made here from its point (the belt resting with a load of 5 % of the
    rotor and damped at 1.5, the coupling at the plant's belt with the inertia beyond it)
    on the recording's own weights, not searched for: on this trial the search's nominal
    bends its belt to about 12 Hz, and the weights it sets near that chain's modes are
    not the plant's. (That chain also used to ring out short holds, differently with the
    rounding of each machine's BLAS kernels, until a bent chain stopped settling any:
    ``SETTLE_TRUST_CHI2``.)"""
    detent, coupling = Effect.DETENT_TORQUE, Effect.LOAD_RESONANCE
    obs, case = _observed(detent, 1981511873)
    unit = _plan(case).unit
    motor, belt = unit.motor, unit.mechanics.belt
    assert belt is not None
    plant_hz = belt_mode_motor_held_hz(belt)
    at_rotor = motor.rotor_inertia_kgm2 + belt.motor_pulley_inertia_kgm2
    beyond = belt.load_inertia_kgm2 * belt.reduction**2
    spring = motor.rotor_teeth * motor.kt_Nm_per_A * unit.rated_current_mA * 1e-3
    w1 = math.sqrt(spring / (at_rotor + beyond))  # the rotor with all it carries
    model = Model(ModelSpec(ChainKind.BELT, frozenset({detent})), obs)
    larger_model = Model(ModelSpec(ChainKind.BELT, frozenset({detent, coupling})), obs)
    point = larger_model.with_values(larger_model.layout.start(), {
        **_sensor_truth(unit.sensor),
        "log_rotor_hz": [math.log(w1 / (2 * math.pi))],
        "log_load_ratio": [math.log(0.05)],
        "belt_damping_ratio": [1.5],
        "log_coupling_hz": [math.log(plant_hz)],
        "coupling_damping_ratio": [0.12],
        "coupling_fraction": [beyond / (at_rotor + beyond)],
    })
    with threadpool_limits(limits=1, user_api="blas"):
        larger = fit(larger_model, [_refine_angles(larger_model, point)], keep=1)
    # The χ² its groups took is not what is judged here: any nominal χ² does.
    with_coupling = candidate_of(obs, larger.chi2, larger)

    def against_coupling(start: NDArray[np.float64]) -> Test:
        with threadpool_limits(limits=1, user_api="blas"):
            kept = candidate_of(obs, larger.chi2, polish(model, start))
        return compare(kept, with_coupling)

    assert larger.chi2 < 2.0 * larger.dof  # the coupling carries the belt's mode
    assert against_coupling(transplanted(model, larger)).significant
    start = coupling_as_belt(model, larger)
    assert start is not None
    moved = against_coupling(start)
    assert not moved.significant
    fitted_hz = math.exp(float(moved.smaller.fit.value("log_belt_hz")[0]))
    assert fitted_hz == pytest.approx(plant_hz, rel=0.1)
    # A disk declares no belt to move it into.
    disk = Model(replace(model.spec, chain=ChainKind.RIGID), obs)
    assert coupling_as_belt(disk, larger) is None


def test_a_clean_belt_the_nominal_grid_missed_is_found_from_the_coupling_that_took_it(
) -> None:
    """The twin without its sensor's bend of benchmark trial
    unnamed:sensor_nonlinearity@932460708: a clean belt (240 Hz with the motor held, the
    load twelve times the rotor, untrimmed), whose nominal fit rested with its belt damped
    at its ceiling and left 2,428. A coupling at 251 Hz with 93 % of the inertia beyond
    it took that to 585 and was named, on a unit with nothing to name: the nominal was
    never polished from a point a larger model found. From that coupling moved into the
    declared belt (``coupling_as_belt``) it leaves 587, and the coupling gains nothing."""
    case = _case(TrialClass(frozenset(), frozenset({UnnamedEffect.SENSOR_NONLINEARITY})),
                932460708)
    plan = _plan(case)
    twin = draw_unit(case.seed, load=plan.unit.load, effects=frozenset(), unnamed=frozenset(),
                     bearings=case.bearings)
    timeline = simulate_timeline(twin, plan.schedule, seed=case.seed, loss=plan.loss,
                                 substeps=PLANT_SUBSTEPS)
    result = diagnose.diagnose(timeline)
    assert not result.effects
    assert result.extended.held.total < 0.3 * result.nominal.held.total


def test_a_coupling_gets_its_spring_back_from_a_belt_that_had_taken_the_couplings_mode(
) -> None:
    """On this belt (rotor, coupling at 64 Hz, pulley, belt at 405 Hz, load; detent
    torque) every model without the coupling put its belt at the chain's lowest mode with
    the rotor alone before it: the coupling's spring, taken for the belt's. From there
    the coupling's spread starts ended at χ² 1,310 and current-loop lag was named in its
    place (1,085); from the plant's own chain the coupling fits 1,029 (benchmark,
    session 47). ``belt_as_coupling`` moves the belt's spring into the coupling, splits
    what lay beyond between pulley and load, and puts a stiffer belt between them: the
    same mechanics below the new belt, and from there the fit finds the plant's chain."""
    detent, coupling = Effect.DETENT_TORQUE, Effect.LOAD_RESONANCE
    case = _case(TrialClass(frozenset({detent, coupling})), 1898614460, first_draw=True)
    obs = observe(_timeline(case))
    unit = _plan(case).unit
    motor, belt, plant = unit.motor, unit.mechanics.belt, unit.mechanics.coupling
    assert belt is not None and plant is not None
    rotor = motor.rotor_inertia_kgm2
    beyond = belt.motor_pulley_inertia_kgm2 + belt.load_inertia_kgm2 * belt.reduction**2
    spring = motor.rotor_teeth * motor.kt_Nm_per_A  # the field's, at 1 A
    smaller = Model(ModelSpec(ChainKind.BELT, frozenset({detent})), obs)
    larger = Model(ModelSpec(ChainKind.BELT, frozenset({detent, coupling})), obs)
    # The chain as the smaller models fitted it: the coupling's spring as the belt.
    taken = smaller.with_values(smaller.layout.start(), {
        **_sensor_truth(unit.sensor),
        "log_rotor_hz": [math.log(math.sqrt(spring / rotor) / (2 * math.pi))],
        "log_load_ratio": [math.log(beyond / rotor)],
        "log_belt_hz": [math.log(math.sqrt(plant.stiffness_Nm_per_rad / beyond)
                                 / (2 * math.pi))],
        "belt_damping_ratio": [plant.damping_ratio
                               * math.sqrt(belt.motor_pulley_inertia_kgm2 / beyond)],
    })
    with threadpool_limits(limits=1, user_api="blas"):
        base = fit(smaller, [_refine_angles(smaller, taken)], keep=1)
    start = transplanted(larger, base)
    chains = [larger.with_values(start, v) for v in belt_as_coupling(larger, start)]
    assert chains
    # The rotor stays as it was, with its drag; the coupling carries the belt's spring.
    swapped = chain.stages_at(larger, chains[0])
    unswapped = chain.stages_at(smaller, base.params)
    ratio2 = smaller.gear_ratio**2
    assert swapped[0].inertia == pytest.approx(unswapped[0].inertia, rel=1e-9)
    assert swapped[0].damping == pytest.approx(unswapped[0].damping, rel=1e-9)
    assert swapped[0].spring == pytest.approx(unswapped[0].spring * ratio2, rel=1e-9)
    assert swapped[0].spring_damping == pytest.approx(unswapped[0].spring_damping * ratio2,
                                                      rel=1e-9)
    assert (swapped[1].inertia + swapped[2].inertia * ratio2
            == pytest.approx(unswapped[1].inertia * ratio2, rel=1e-9))
    with threadpool_limits(limits=1, user_api="blas"):
        found = best_of(larger, chosen_starts(larger, chains, len(chains)), finalists=1,
                        heat=False)
    assert found.chi2 < 0.5 * base.chi2
    assert math.exp(found.scalar("log_coupling_hz")) == pytest.approx(plant.resonance_hz,
                                                                      rel=0.25)
    assert math.exp(found.scalar("log_belt_hz")) == pytest.approx(
        math.sqrt(belt.stiffness_Nm_per_rad / belt.load_inertia_kgm2) / (2 * math.pi),
        rel=0.35)
    # A disk has no belt to take a coupling's mode.
    disk = Model(ModelSpec(ChainKind.RIGID, frozenset({detent, coupling})), obs)
    assert belt_as_coupling(disk, disk.layout.start()) == []


def test_a_group_stopped_just_short_of_a_bound_it_may_not_rest_on_rests_there() -> None:
    """The solver stops short of a bound it presses by its own tolerances; within
    ``REJECT_MARGIN`` of its range the group is other physics as at the bound itself.
    Bounds a group may rest on stay free however near."""
    base = _concealed_friction().larger.fit.model
    effects = frozenset({Effect.LOAD_RESONANCE, Effect.SENSOR_CLOCK_DRIFT})
    model = Model(replace(base.spec, effects=effects), base.obs)
    sl = model.layout.slices
    x = model.layout.start()
    x[sl["coupling_damping_ratio"]] = 2.0 * (1.0 - 0.5 * REJECT_MARGIN)  # damper: rejected
    x[sl["clock_drift_ppm"]] = -5000.0 + 1.0  # a clock 5000 ppm off: rejected
    x[sl["coupling_fraction"]] = 0.99 - 1e-4  # a heavy load beyond it: allowed
    sides = resting(model, x, np.zeros(x.size, dtype=np.int8))
    assert sides[sl["coupling_damping_ratio"]].tolist() == [1]
    assert sides[sl["clock_drift_ppm"]].tolist() == [-1]
    assert sides[sl["coupling_fraction"]].tolist() == [0]
    x[sl["coupling_damping_ratio"]] = 2.0 * (1.0 - 2.0 * REJECT_MARGIN)
    assert resting(model, x, np.zeros(x.size, dtype=np.int8))[
        sl["coupling_damping_ratio"]].tolist() == [0]
    # What the solver found active stays so.
    solver = np.zeros(x.size, dtype=np.int8)
    solver[sl["coupling_fraction"]] = 1
    assert resting(model, x, solver)[sl["coupling_fraction"]].tolist() == [1]


@pytest.mark.parametrize(("seed", "bound"), [
    # Once a hundredth of the inertia beyond it (a filter); with friction evaluated on
    # the whole measured velocity, twice critical, 1.9998 of 2 (``REJECT_MARGIN``).
    # (Seed 94205421's coupling rested twice critical too, on the short holds its bent
    # nominal chain settled; on the others it rests on no bound, and the diagnosis names
    # friction alone, held-out χ² 152.7.)
    (1850757460, "coupling_damping_ratio"),
])
def test_a_coupling_resting_where_it_is_no_mode_is_not_named_beside_strong_friction(
        seed: int, bound: str) -> None:
    """What friction leaves on these disks (benchmark, session 25) a coupling takes part of
    only from a bound where it is no transmission mode; named load_resonance, the trials
    scored nothing. The gain is there (significant, were the bound allowed), the
    physics is not the id's."""
    friction, coupling = Effect.FRICTION, Effect.LOAD_RESONANCE
    test = _beside(_case(TrialClass(frozenset({friction})), seed), friction, coupling)
    fitted = test.larger.fit
    assert fitted.rejected == (bound,)
    assert not test.significant
    active = fitted.active.copy()
    active[fitted.model.layout.slices[bound]] = 0
    allowed = replace(fitted, active=active)
    assert replace(test, larger=replace(test.larger, fit=allowed)).significant


@functools.cache
def _concealed_friction() -> Test:
    """Friction concealed in a belt unit (seed 22: 19 % of the holding torque and more, past
    a healthy unit's; seed 26's 10 and 11 % are now within it), its group added: fitted
    once for the two tests of the smoothing's ceiling."""
    return _added(_case(TrialClass(frozenset({Effect.FRICTION})), 22), Effect.FRICTION)


def test_coulomb_friction_has_settled_at_every_hold_so_it_is_never_a_drag() -> None:
    """The group's smoothing may reach at most a tenth of the slowest mean load speed:
    there its torque no longer follows the load's swing, so it cannot be a drag rising
    with speed (a clean belt unit whose nominal chain was a little off once gained
    χ² ≈ 30 from a friction smoothed over half its top speed). The clean belt of seed 41
    gains nothing from the group; friction concealed in a belt unit counts."""
    clean = _added(_case(TrialClass(frozenset()), 41), Effect.FRICTION)
    assert not clean.significant
    assert clean.chi2_gain < max(clean.f_threshold, clean.bic_threshold)
    model = clean.larger.fit.model
    ceiling = model.with_values(clean.larger.fit.params,
                                {"log_friction_smoothing": [math.log(FRICTION_SMOOTHING_MAX)]})
    slowest = float(np.min(np.abs(model.obs.load_speed)))
    swing = slowest * np.linspace(0.8, 1.2, 41)[None, :]  # a 20 % ripple about it
    forward, _, slope, _ = friction_shapes(model, ceiling, swing)
    # (At a ceiling of 0.3 the slope times the speed was 0.03: a drag.)
    assert np.ptp(forward) < 1e-4
    assert np.max(np.abs(slope)) * slowest < 1e-4
    concealed = _concealed_friction()
    assert concealed.significant


def test_friction_responds_only_in_segments_where_it_has_a_slope_and_there_as_made_whole(
) -> None:
    """Segments whose load never nears a stop have no friction slope and are skipped in
    the response to a change of motion (the step's basis, a Jacobian's stacked points):
    the others must come out as the whole product makes them, to the bit."""
    # Seed 26's friction (10 and 11 %, within a healthy unit's) stops its load in some
    # segments, which seed 22's never does.
    fitted = _added(_case(TrialClass(frozenset({Effect.FRICTION})), 26), Effect.FRICTION
                    ).larger.fit
    model = fitted.model
    slope = model.motion(fitted.params).friction_slope.copy()
    slope[::2] = 0.0  # every other segment settled, whatever this fit's were
    assert np.any(slope[1::2])
    rng = np.random.default_rng(7)
    k = model.jw.shape[-1]
    change = rng.normal(size=model.jw.shape) + 1j * rng.normal(size=model.jw.shape)
    basis = np.eye(2 * k)[:, None, :k].astype(np.complex128)  # the step's, every segment
    stacked = np.stack([slope, 0.5 * slope])  # a Jacobian's points
    for slopes, x in ((slope, change), (stacked, change), (slope, basis)):
        quick = friction_response(model, slopes, x)
        assert np.array_equal(quick, friction_response_on(model, slopes, x, model.jw))
        assert not np.any(quick[..., ::2, :])


def test_friction_is_evaluated_on_the_whole_measured_velocity_orders_above_8_included(
) -> None:
    """A rough ripple swings the load at orders above 8 too, and where the load nearly
    stops in a period those orders decide when friction turns. They were in the rotor's
    swing but not in the velocity friction was evaluated on. Development trial
    friction+sensor_clock_drift@101 (a disk): with them, friction and the clock fitted
    together left a tenth of what friction alone leaves on held-out data; without, a
    third (24,372 of 65,516), and the diagnosis named friction alone. Its nominal fit
    (χ²/dof 110) is now too far from the recording to settle the short holds
    (``SETTLE_TRUST_CHI2``); on the others the pair leaves a fifth (11,954 of 57,621)."""
    case = _case(TrialClass(frozenset({Effect.FRICTION, Effect.SENSOR_CLOCK_DRIFT})), 101)
    nominal = _case_nominal(case)
    base = nominal.balanced
    obs = base.model.obs
    assert obs.beyond is not None and np.any(obs.beyond != 0)
    with threadpool_limits(limits=1, user_api="blas"):
        fitted = {effects: fit_spec(obs, replace(base.model.spec, effects=effects), base,
                                    nominal.free)
                  for effects in (frozenset({Effect.FRICTION}), case.cls.effects)}
    model, p = fitted[case.cls.effects].model, fitted[case.cls.effects].params
    below, above = axes.measured(model, p)
    assert above is not None
    sensor = model.sensor_response(p)
    whole = np.concatenate([below / sensor, above / model.sensor_response(p, beyond=True)],
                           axis=1) / model.radius
    k = np.arange(1, whole.shape[1] + 1)
    grid = np.arange(GRID) / GRID * 2 * math.pi
    ripple = ((whole / (1j * obs.omega[:, None] * k)) @ np.exp(1j * np.outer(k, grid))).real
    np.testing.assert_allclose(load_velocity(model, p), obs.load_speed[:, None] + ripple,
                               atol=1e-9 * float(np.max(np.abs(obs.load_speed))))
    alone, both = (held_out(fitted[e]).total for e in fitted)
    assert both < alone / 4


def test_coulomb_friction_resting_on_its_smoothing_ceiling_still_counts() -> None:
    """Where the load never nearly stops, the data do not fix the smoothing, and a fit may
    rest on its ceiling as on any value below: the group is still Coulomb friction there.
    (A benchmark belt with friction of 19 % of its holding torque fitted the ceiling,
    explained 6370 of its nominal held-out χ² of 8546, and was named nothing while such a
    fit did not count.)"""
    concealed = _concealed_friction()
    fitted = concealed.larger.fit
    active = fitted.active.copy()
    active[fitted.model.layout.slices["log_friction_smoothing"]] = 1
    resting = replace(fitted, active=active)
    assert resting.rejected == ()
    assert replace(concealed, larger=replace(concealed.larger, fit=resting)).significant


def test_a_group_added_never_leaves_the_fit_worse_than_the_model_it_extends() -> None:
    """Every start of a larger model has its linear parameters solved again; on a belt unit
    with a soft coupling that lost the nominal's own point and ended χ² 12 worse than the
    nominal, although saturation at zero is the nominal exactly."""
    case = _case(TrialClass(frozenset({Effect.LOAD_RESONANCE})), 43, first_draw=True)
    test = _added(case, Effect.MAGNETIC_SATURATION)
    assert test.larger.fit.chi2 <= test.smaller.fit.chi2 * (1.0 + 1e-6)


def test_holds_shorter_than_a_belts_decay_give_the_phasors_of_long_holds() -> None:
    """Development seed 44 draws a belt unit whose load mode (34 Hz at 1 A, damping
    0.056) needs about 0.5 s to forget a change. Holds of 0.45 s at 6–10 Hz once left
    one usable speed, and the recording was refused; with the mode's ringing fitted out
    beside the harmonics, every hold gives the phasors that holds of 4 s give."""
    seed = 44
    unit = _plan(_case(TrialClass(frozenset()), seed)).unit
    ranges = RandomCharacterizationRanges(
        speeds=(2, 2), electrical_hz=(6.0, 10.0), amplitudes=(2, 2), hold_s=(0.45, 0.45),
        both_signs_probability=0.0)
    short = random_characterization(np.random.default_rng(seed), ranges=ranges)
    long = replace(short, holds=tuple(replace(h, cycles=4000) for h in short.holds))
    recorded = simulate_timeline(unit, short, seed=seed, substeps=PLANT_SUBSTEPS)
    obs, fits = nominal_of(recorded)
    assert len({round(abs(c.electrical_hz), 1) for c in obs.conditions}) == 2
    assert obs.ringing > obs.count // 2
    settled = observe(simulate_timeline(unit, long, seed=seed + 1, substeps=PLANT_SUBSTEPS),
                      settle_fallback=settle_fallback(fits.free))
    assert settled.ringing == 0
    same = {(s.amplitude_mA, round(s.electrical_hz(0.001), 1), s.trims): i
            for i, s in enumerate(settled.segments)}
    signal = tangential_signal(recorded)
    fitted_out = ignored = 0.0
    for i, seg in enumerate(obs.segments):
        j = same[(seg.amplitude_mA, round(seg.electrical_hz(0.001), 1), seg.trims)]
        variance = obs.sigma[i] ** 2 + settled.sigma[j] ** 2
        fitted_out += float(np.sum(np.abs(obs.phasors[i] - settled.phasors[j]) ** 2 / variance))
        plain = demodulate(signal[seg.start:seg.stop], seg.electrical_angle(),
                           seg.samples_per_period, orders=obs.orders)
        ignored += float(np.sum(np.abs(plain.phasors[:obs.orders] - settled.phasors[j]) ** 2
                                / variance))
    values = 2 * obs.count * obs.orders
    # 1.41 per value fitted out against 2.72 with the same segments' ringing left in (1.36
    # before each trim step's slip along the spring moved the fitted chain a little).
    assert fitted_out / values < 1.7
    assert ignored / values > 1.8 * fitted_out / values


@pytest.mark.parametrize(("range_g", "advice"), [
    (8, "record with a larger range"),
    (16, "the sensor is at its widest range (16 g): record at lower speeds or currents"),
])
def test_a_recording_clipped_at_all_but_one_speed_is_refused_with_what_to_change(
        range_g: int, advice: str) -> None:
    """Clipping, not the schedule, left one speed: the refusal must say so, or the engineer
    records the same schedule again with the same range; and at the widest range it must
    name the operating point instead, which is all that is left to change."""
    seed = 42
    unit = _plan(_case(TrialClass(frozenset()), seed)).unit
    ranges = RandomCharacterizationRanges(speeds=(2, 2), electrical_hz=(15.0, 30.0),
                                          amplitudes=(2, 2), hold_s=(0.6, 0.6))
    schedule = replace(random_characterization(np.random.default_rng(seed), ranges=ranges),
                       sensor_range_g=range_g)
    recorded = simulate_timeline(unit, schedule, seed=seed, substeps=PLANT_SUBSTEPS)
    speed = np.abs(np.diff(recorded.position, prepend=recorded.position[0]))
    fast = speed > 0.5 * (speed.max() + np.median(speed[speed > 0]))
    assert 0.2 < np.mean(fast) < 0.6
    # Half of every fast sample at the full scale, as a sensor of too small a range gives.
    half = fast & (np.arange(fast.size) % 2 == 0)
    clipped = replace(recorded, saturated=recorded.saturated | half)
    assert len({round(abs(c.electrical_hz), 1) for c in observe(recorded).conditions}) == 2
    with pytest.raises(NotDiagnosable, match="clipped at the sensor's full scale") as refused:
        observe(clipped)
    assert str(refused.value).count(advice) == 1
    other = {8: "widest range", 16: "larger range"}[range_g]
    assert other not in str(refused.value)


def test_a_clocks_rate_chosen_by_a_scan_must_beat_what_the_scan_finds_in_noise() -> None:
    """The clock's rate is the best of a periodogram over about 240 independent rates of
    this 40 s recording (development seed 41, a clean belt unit): on noise alone its gain
    is the largest of that many chances, about 2·ln 240 ≈ 11 (here it was 11 once, and
    −4 since the plant's sensor reads the acceleration at its own instant: the clock's
    fit did not get back to the nominal's point). Its thresholds rise by that much over
    Schwarz's criterion for two parameters."""
    test = _added(_case(TrialClass(frozenset()), 41), Effect.SENSOR_CLOCK_DRIFT)
    span = test.larger.fit.model.obs.span
    trials = (CLOCK_RATES_PPM[-1] - CLOCK_RATES_PPM[0]) * 1e-6 * (span[-1, 1] - span[0, 0])
    assert trials > 100
    assert test.elsewhere == pytest.approx(2 * math.log(trials) * test.noise)
    assert test.bic_threshold == pytest.approx(
        2 * math.log(test.larger.fit.observations) * test.noise + test.elsewhere)
    assert test.chi2_gain < test.bic_threshold and not test.significant
    # Nothing is scanned when the clock is already in both models.
    assert compare(test.larger, test.larger).elsewhere == 0.0


def test_a_clock_fitted_at_syncs_own_rate_is_not_named_a_drifting_clock() -> None:
    """A clock whose fit ends within a few ppm of SYNC's rate holds one sub-sample phase
    throughout: the sensor's constant delay, with the sawtooth's hold beside it, which
    took what a loop lag or a coupling left on two benchmark trials (fitted at −0.06 and
    −1.6 ppm, named sensor_clock_drift). A concealed clock (development seed 24) counts;
    the same fit moved to within the band is rejected whatever it gains."""
    test = _added(_case(TrialClass(frozenset({Effect.SENSOR_CLOCK_DRIFT})), 24),
                  Effect.SENSOR_CLOCK_DRIFT)
    fitted = test.larger.fit
    assert test.significant
    assert abs(fitted.scalar("clock_drift_ppm")) > 10 * MIN_CLOCK_PPM
    assert fitted.rejected == ()
    at_sync = fitted.params.copy()
    at_sync[fitted.model.layout.slices["clock_drift_ppm"]] = -0.5 * MIN_CLOCK_PPM
    held = replace(fitted, params=at_sync)
    assert held.rejected == ("clock_drift_ppm",)
    assert not replace(test, larger=replace(test.larger, fit=held)).significant


def test_a_group_beside_others_must_gain_more_than_their_errors_leave_or_explain_the_rest(
) -> None:
    """A strong reluctance spring (development seed 24) is named beside nothing. Beside
    groups that took a million from the nominal χ², the same gain still counts, because
    it takes the held-out χ² to the noise: their fit's errors are spread over their own
    signal, and another group cannot take nearly all of them. Had it left most of the
    rest where it was, the thresholds would rise by ``MODEL_ERROR_SHARE`` of the million."""
    test = _added(_case(TrialClass(frozenset({Effect.RELUCTANCE_TORQUE})), 24),
                  Effect.RELUCTANCE_TORQUE)
    assert test.significant and test.model_error == 0.0
    explained = 2.0 * test.chi2_gain / MODEL_ERROR_SHARE
    smaller = replace(test.smaller, explained=explained)
    assert explains_the_rest(smaller, test.larger)
    beside = compare(smaller, test.larger)
    assert beside.model_error == 0.0 and beside.significant

    # The same gains with twice as much left beyond the larger model on held-out data.
    left = 2.0 * test.held_gain

    assert not explains_the_rest(_leaving_more(smaller, left), _leaving_more(test.larger, left))
    short = compare(_leaving_more(smaller, left), _leaving_more(test.larger, left))
    assert short.held_gain == pytest.approx(test.held_gain)
    assert short.model_error == pytest.approx(2.0 * test.chi2_gain)
    assert short.bic_threshold == pytest.approx(test.bic_threshold + short.model_error)
    assert not short.significant


def test_a_group_must_gain_beyond_what_it_leaves_in_the_cells_where_it_gains() -> None:
    """Development seed 61 draws a clean belt whose nominal fit is at the noise except in
    the two cells on the rotor's mode (order 4 at ±9 Hz, 980 mA: χ²/dof 19 and 29). Detent
    torque, at order 4, takes a part of that misfit: fitted and held out it clears the
    thresholds set by the whole recording's χ²/dof, and was named. Counted in units of
    what it still leaves in each cell it is far below them; a real reluctance spring
    (seed 24) leaves noise where it gains, and its gain counts almost whole. (Since every
    residual carries the measurement's own noise, ``Step``, the detent no longer gains
    held out either; and since each change's ringing is waited out down to the harmonics'
    resolution, the mode's cells are nearer the noise and its in-sample gain fell from
    above the whole recording's thresholds to 10 of 28: the cells' test is one guard of
    several, and must still hold.)"""
    spurious = _added(_case(TrialClass(), 61), Effect.DETENT_TORQUE)
    assert spurious.cell_chi2_gain < 0.6 * spurious.cell_threshold
    assert not spurious.significant
    real = _added(_case(TrialClass(frozenset({Effect.RELUCTANCE_TORQUE})), 24),
                  Effect.RELUCTANCE_TORQUE)
    assert real.significant
    assert real.cell_chi2_gain > 0.8 * real.chi2_gain
    assert real.cell_held_gain > 0.8 * real.held_gain


def test_each_trim_step_moves_the_rotor_along_its_spring_so_a_belt_beside_its_mode_balances(
) -> None:
    """Development seed 61 draws a clean belt unit whose rotor mode sits at 23 Hz at
    390 mA, beside a 21.5 Hz condition. There, the offsets and gain errors beating with
    the swing make a mean torque of several percent of the holding torque that changes
    with every trim step, and the rotor slips along its spring until the torque again
    meets the drag. With one load angle per condition the torque balance missed by 21
    times its floor there, and the clean unit's nominal fit ended at χ²/dof 5.8 (a
    mismatch reported on a clean unit); with each segment's slip it is at the noise."""
    case = _case(TrialClass(), 61)
    assert _plan(case).unit.mechanics.belt is not None
    balanced = _case_nominal(case).balanced
    assert balanced.chi2 / balanced.dof < 1.4
    balance = balanced.residuals[balanced.model.harmonic_values:-1]
    assert float(np.sqrt(np.mean(balance**2))) < 1.0  # each segment's, in its floor's units


def _clean(seed: int) -> tuple[Timeline, Case]:
    case = _case(TrialClass(), seed)
    return _timeline(case), case


def test_a_rotor_swinging_out_of_its_periodic_motion_is_skipped_and_said_why(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Seed 2018362960 (a fresh benchmark seed, where this was found) draws a clean disk
    whose rotor mode falls from 74 Hz at 1 A to about 40 Hz at its lowest currents, among
    its speeds, with offsets of 37 and 133 mA. Near there the rotor's own mode keeps
    swinging beside the harmonics, in some holds for good: what the harmonics leave is
    hundreds of times the noise. No periodic model describes those holds; kept, they left
    the nominal fit of a clean unit at χ²/dof 69, and every class drawn on it a mismatch.
    Where the rotor slips outright (400 and 450 mA at 39.5 Hz) the load's speed changes
    through the hold, and the speed rule skips those first; the control lifts both."""
    timeline, _ = _clean(2018362960)
    with threadpool_limits(limits=1, user_api="blas"):
        obs, nominal = nominal_of(timeline)
        skipped = [s for s in obs.skipped if "not periodic" in s.reason]
        assert len(skipped) >= 10
        assert all("times the noise" in s.reason for s in skipped)
        assert nominal.balanced.chi2 / nominal.balanced.dof < 1.5
        monkeypatch.setattr(observations, "NOT_PERIODIC_NOISE", math.inf)
        monkeypatch.setattr(observations, "SPEED_CHANGE_SHARE", math.inf)
        kept, with_them = nominal_of(timeline)
    assert kept.count > obs.count
    assert with_them.balanced.chi2 / with_them.balanced.dof > 10.0


def test_holds_where_a_rough_unit_nearly_loses_step_are_skipped_and_said_why(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Benchmark trial friction@2082563418 (a fresh seed, where this was found): a disk
    with Coulomb friction of 14 % of its holding torque and offsets of 100 and 200 mA,
    recorded untrimmed at 350 to 970 mA. At 350 mA the rotor nearly loses step in every
    hold and the motion is not periodic, though it stays under a fifth of the ripple.
    Kept, those holds left the nominal model at χ² 3.1 million for 817 values, which
    no group could fit, and the unit was named nothing; skipped, the nominal fit sees
    what friction leaves on the others."""
    timeline = _timeline(_case(TrialClass(frozenset({Effect.FRICTION})), 2082563418))
    with threadpool_limits(limits=1, user_api="blas"):
        obs, nominal = nominal_of(timeline)
        skipped = [s for s in obs.skipped if "not periodic" in s.reason]
        assert len(skipped) >= 10
        assert all("350 mA" in s.reason and "times the noise" in s.reason for s in skipped)
        assert sum("let change slowly" in s.reason for s in skipped) >= len(skipped) // 2
        assert {c.amplitude_mA for c in obs.conditions} == {870, 970}
        assert nominal.free.chi2 / nominal.free.dof < 2.0
        monkeypatch.setattr(observations, "NOT_PERIODIC_SLOW_SHARE", math.inf)
        kept, with_them = nominal_of(timeline)
    assert kept.count > obs.count
    assert with_them.free.chi2 / with_them.free.dof > 100.0


def test_holds_where_friction_holds_a_belted_load_still_after_a_reversal_are_skipped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Benchmark trial friction@416744003 (a fresh seed, where this was found): a belt of
    53 Hz whose load carries Coulomb friction of 26 and 33 % of the holding torque. After
    each reversal at 770 mA the load stands still until the motor has wound the belt
    through the friction's two levels, 0.4 s at 14 Hz and a whole hold and more at 6.5 Hz,
    then catches up. A load at rest is quiet, so neither the harmonics' residual nor the
    settling sees it; kept, the first 14 Hz hold alone left χ² 1,902 of the nominal fit's
    4,285 for 48 holds, and friction was not named. Its speed changes through the hold by
    nearly all of the load's speed, and so does the second 6.5 Hz hold's, whose first hold
    had not reached it."""
    timeline = _timeline(_case(TrialClass(frozenset({Effect.FRICTION})), 416744003))
    with threadpool_limits(limits=1, user_api="blas"):
        obs, nominal = nominal_of(timeline)
        changed = [s for s in obs.skipped if "speed changed" in s.reason]
        assert sum("through the hold" in s.reason for s in changed) == 3
        assert sum("in a later hold" in s.reason for s in changed) == 2
        assert all(s.reason.startswith("770 mA") for s in changed)
        assert any(s.start_s < 9.0 < s.stop_s and "-14.0 Hz" in s.reason for s in changed)
        assert len(obs.skipped) == len(changed)
        monkeypatch.setattr(observations, "SPEED_CHANGE_SHARE", math.inf)
        kept, with_them = nominal_of(timeline)
    assert kept.count == obs.count + len(changed)
    assert with_them.balanced.chi2 > 1.5 * nominal.balanced.chi2 + 1000.0


def test_harmonics_turning_with_the_rotor_are_a_periodic_motion() -> None:
    """Development disk rotor_eccentricity@24: the airgap's once-per-revolution modulation
    leaves up to 1,700 times the noise beside each hold's mean harmonics, at 4 to 13 % of
    the ripple. Let change slowly through the hold, the harmonics leave the noise, and
    every hold is kept; a rule on the noise alone would have dropped 8 of its 49."""
    case = _case(TrialClass(frozenset({Effect.ROTOR_ECCENTRICITY})), 24)
    timeline = _timeline(case)
    signal = tangential_signal(timeline)
    measured, _ = measure(timeline, observations.measure_options(DIAGNOSIS_ORDERS, None), map)
    assert observations.not_periodic(measured, DIAGNOSIS_ORDERS, signal) == {}
    # Nor does its load's speed change through a hold, though it swings once per revolution.
    assert observations.speed_changed(measured, signal, timeline.metadata) == {}
    noise = float(np.quantile([m.harmonics.noise_variance for m in measured],
                              observations.NOISE_QUANTILE))
    loud = [m for m in measured
            if m.harmonics.noise_variance > observations.NOT_PERIODIC_NOISE * noise]
    assert len(loud) >= 5


@pytest.mark.parametrize("seed", [15, pytest.param(56, marks=pytest.mark.xfail(strict=True, reason=(
    "issue 90: with the bearings' Coulomb friction in the nominal model this belt's load "
    "ratio is fitted at 5.6 ± 2.7 against the plant's 2.9 (χ²/dof 0.68): no longer "
    "resolved to 30 %; a known regression to mend")))])
def test_a_belt_is_fitted_on_its_own_chain_whatever_its_load_and_phase_imbalance(
    seed: int,
) -> None:
    """Two development belts whose nominal fits ran to a bound from the grid's best points.
    Seed 56: phase gains differing by 18 %, held equal while the grid was ranked, put its
    own chain 237th of 294 (χ²/dof 16,000, offsets at ±1000 mA). Seed 15: a load four
    times the rotor's inertia; the top of the ranking was a load too light to matter,
    and from there the load's inertia ran to its bound (χ²/dof 39)."""
    timeline, case = _clean(seed)
    unit = _plan(case).unit
    belt = unit.mechanics.belt
    assert belt is not None
    with threadpool_limits(limits=1, user_api="blas"):
        _, nominal = nominal_of(timeline)
    result = nominal.balanced
    assert result.chi2 / result.dof < 1.5
    motor_side = unit.motor.rotor_inertia_kgm2 + belt.motor_pulley_inertia_kgm2
    ratio = belt.load_inertia_kgm2 * belt.reduction**2 / motor_side
    belt_hz = belt_mode_motor_held_hz(belt)
    assert math.exp(result.scalar("log_load_ratio")) == pytest.approx(ratio, rel=0.3)
    assert math.exp(result.scalar("log_belt_hz")) == pytest.approx(belt_hz, rel=0.1)
    offsets = result.value("amp_offset_mA")
    assert offsets[0] == pytest.approx(unit.amplifier.offset_a_mA, abs=2.0)
    assert offsets[1] == pytest.approx(unit.amplifier.offset_b_mA, abs=2.0)


def test_a_grid_prescreened_by_its_first_linear_pass_keeps_the_exact_rankings_best_points(
) -> None:
    """Ranking all 294 points of a belt's grid by their true χ² costs two linear passes and
    a model evaluation each; the first pass's own prediction ranks them almost as well, so
    only the best ``GRID_EXACT`` get the rest. Whatever a caller takes from the top (at most
    six points) must be what the exact ranking gives: same points, same χ²."""
    clean = _observations(_case(TrialClass(), 15))
    with threadpool_limits(limits=1, user_api="blas"):
        model = Model(ModelSpec(ChainKind.BELT, dc_balance=False), clean)
        starts = nominal_starts(model)
        for split in (False, True):
            full = screen(model, starts, split=split)
            quick = screen(model, starts, split=split, exact=GRID_EXACT)
            assert len(quick) == len(full) == len(starts)
            for (chi2, x), (chi2_quick, x_quick) in zip(full[:6], quick[:6], strict=True):
                assert chi2_quick == pytest.approx(chi2, rel=1e-9)
                np.testing.assert_allclose(x_quick, x, rtol=1e-9, atol=1e-12)


def test_a_polish_goes_on_where_the_trust_regions_svd_does_not_converge(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """LAPACK's SVD behind each dense trust-region step can fail on a finite Jacobian
    (benchmark trial detent_torque@76034821): the polish must still improve on its
    start, not end the diagnosis."""
    clean = _observations(_case(TrialClass(), 15))
    failed: list[bool] = []

    def no_convergence(*args: Any, **kwargs: Any) -> None:
        failed.append(True)
        raise np.linalg.LinAlgError("SVD did not converge")

    with threadpool_limits(limits=1, user_api="blas"):
        model = Model(ModelSpec(ChainKind.BELT), clean)
        (chi2_start, start), *_ = screen(model, nominal_starts(model))
        monkeypatch.setattr(trf, "svd", no_convergence)
        polished = polish(model, start, max_nfev=8)
    assert failed
    assert polished.chi2 < chi2_start


def test_a_polish_going_on_from_a_stopped_one_reuses_its_jacobian_to_the_same_answer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A tournament's stages go on from fits that stopped on their evaluation budget:
    the Jacobian each stopped with is the one the next stage's solver asks for first.
    Given it, the next stage must end exactly where making it again ends, with one
    Jacobian fewer."""
    clean = _observations(_case(TrialClass(), 15))
    made: list[int] = []
    original = fit_module.jacobian

    def counted(model: Model, p: np.ndarray) -> np.ndarray:
        made.append(1)
        return original(model, p)

    with threadpool_limits(limits=1, user_api="blas"):
        model = Model(ModelSpec(ChainKind.BELT), clean)
        (_, start), *_ = screen(model, nominal_starts(model))
        stopped = polish(model, start, max_nfev=3)
        assert not stopped.converged
        monkeypatch.setattr(fit_module, "jacobian", counted)
        again = polish(model, stopped.params, max_nfev=6)
        made_again = len(made)
        made.clear()
        going_on = polished_on(stopped, max_nfev=6)
    assert len(made) == made_again - 1
    np.testing.assert_array_equal(going_on.params, again.params)
    np.testing.assert_array_equal(going_on.jacobian, again.jacobian)
    assert going_on.chi2 == again.chi2


def test_a_dead_time_is_made_on_the_grid_without_its_high_orders_folding_onto_the_low() -> None:
    """A dead time's error turns with the current's sign, whose harmonics fall only as 1/k:
    sampled on the model's grid its orders near the grid's size would fold onto the few the
    recording holds. Made four times finer and cut to the grid's orders, the currents'
    orders 1..8 are those of the error evaluated on a grid 64 times finer to 1e-4 of the
    error (what folds from the fine grid's own orders 184 and up, at the largest current's
    sharpest turn: 2e-6 A of 0.03); sampled on the grid itself, orders 40 and up fold in,
    some hundred times more."""
    obs = _observations(_case(TrialClass(frozenset({Effect.CURRENT_DISTORTION})), 15))
    spec = ModelSpec(chain_for(obs.metadata.gear_ratio), frozenset({Effect.CURRENT_DISTORTION}))
    model = Model(spec, obs)
    dead = (0.03, 0.02)
    p = model.with_values(model.layout.start(), {"dead_time": list(dead)})
    knee = DEAD_TIME_KNEE * obs.metadata.rated_current_mA * 1e-3
    dc_a, ac_a, dc_b, ac_b = model.current_coefficients(p)
    n = 64 * GRID
    synth = np.exp(1j * np.outer(model.current_orders, 2.0 * np.pi * np.arange(n) / n))
    for dc, ac, error, made in zip((dc_a, dc_b), (ac_a, ac_b), dead, model.currents(p),
                                   strict=True):
        before = dc + (ac @ synth).real
        exact = before - error * np.tanh(before / knee)
        want = np.fft.rfft(exact, axis=1)[:, 1:9] * (2.0 / n)
        have = np.fft.rfft(made, axis=1)[:, 1:9] * (2.0 / GRID)
        np.testing.assert_allclose(have, want, rtol=0.0, atol=1e-4 * error)
        sampled = exact[:, ::64]
        folded = np.fft.rfft(sampled, axis=1)[:, 1:9] * (2.0 / GRID)
        assert np.max(np.abs(folded - want)) > 3e-3 * error


def test_a_chain_grid_passed_once_for_every_linear_group_ranks_as_each_group_alone() -> None:
    """The first passes over a belt's grid are made once for all of ``grid_shared()`` (one
    linear design per point, from a model holding every one of them): each group must
    still get the points, and the χ², that screening the grid with its own model gives.
    That holds only for groups whose blocks all start at zero and there leave the
    nominal's motion as it is (an eccentric rotor's unbalance is nonlinear, and moves the
    motion only away from zero): at a grid point they only add rows to its design."""
    obs = _observations(_case(TrialClass(), 15))
    spec = ModelSpec(ChainKind.BELT)
    nominal = Model(spec, obs)
    x = nominal_starts(nominal)[0]
    sharing = grid_shared()
    assert sharing == {Effect.FLUX_HARMONICS, Effect.CURRENT_DISTORTION, Effect.DETENT_TORQUE,
                      Effect.RELUCTANCE_TORQUE, Effect.MAGNETIC_SATURATION,
                      Effect.ROTOR_ECCENTRICITY}
    for effect in sharing:
        blocks = terms(effect).blocks(spec.with_effect(effect), obs)
        assert all(np.all(np.asarray(b.start) == 0.0) for b in blocks), effect
        model = Model(spec.with_effect(effect), obs)
        at = model.with_values(model.layout.start(), {
            name: list(x[sl]) for name, sl in nominal.layout.slices.items()})
        np.testing.assert_array_equal(model.motion(at).te, nominal.motion(x).te)
    with threadpool_limits(limits=1, user_api="blas"):
        union = Model(replace(spec, effects=sharing), obs)
        effects = sorted(sharing)
        models = [Model(spec.with_effect(e), obs) for e in effects]
        shared = first_passes_shared(union, models, nominal_starts(union), GRID_EXACT)
        for effect, model, passed in zip(effects, models, shared, strict=True):
            assert len(passed) == GRID_EXACT
            alone = screen(model, nominal_starts(model), exact=GRID_EXACT)[:REGRID_KEEP]
            given = rank_passed(model, passed, GRID_EXACT)[:REGRID_KEEP]
            for (chi2, x), (chi2_given, x_given) in zip(alone, given, strict=True):
                assert chi2_given == pytest.approx(chi2, rel=1e-7), effect
                np.testing.assert_allclose(x_given, x, rtol=1e-5, atol=1e-5, err_msg=effect)


def test_both_rankings_of_the_nominal_grid_made_from_one_design_are_each_screens_own(
) -> None:
    """The nominal fit ranks its grid twice, with the gain errors held and with their
    difference solved (``fit_nominal``); both first passes are made from one linear
    design per point, and each ranking must be the one its own screen gives, to the bit."""
    clean = _observations(_case(TrialClass(), 15))
    with threadpool_limits(limits=1, user_api="blas"):
        model = Model(ModelSpec(ChainKind.BELT, dc_balance=False), clean)
        starts = nominal_starts(model)
        held, split = first_passes_shared(model, [model, model], starts, len(starts),
                                          split=[False, True])
        for passed, splits in ((held, False), (split, True)):
            own = screen(model, starts, split=splits, exact=GRID_EXACT)
            given = rank_passed(model, passed, GRID_EXACT, split=splits)
            assert [c for c, _ in given] == [c for c, _ in own]
            assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(given, own, strict=True))


def test_a_belt_whose_own_mode_lies_far_above_the_band_is_fitted_from_the_mode_it_swings_on(
) -> None:
    """Development seed 72 draws a clean belt whose load is 5.9 times the rotor side's
    inertia on a 230 Hz belt: the chain swings on one mode near 69 Hz in band, and the
    belt's own shows only as the few percent it bends the response. From the grid the
    fit ran to a load of ratio 0.001 with a heavily damped belt in band (χ²/dof 2.3), and
    a clean unit was given a load resonance. Started again with that 69 Hz mode kept at
    every ratio, it fits to the noise, with the belt where it is."""
    timeline, case = _clean(72)
    belt = _plan(case).unit.mechanics.belt
    assert belt is not None
    with threadpool_limits(limits=1, user_api="blas"):
        _, nominal = nominal_of(timeline)
    result = nominal.balanced
    assert result.chi2 / result.dof < 1.1
    assert held_out(result).total / result.observations < 1.1
    belt_hz = belt_mode_motor_held_hz(belt)
    assert math.exp(result.scalar("log_belt_hz")) == pytest.approx(belt_hz, rel=0.1)
    assert math.exp(result.scalar("log_load_ratio")) > 1.0


def test_a_model_judged_again_with_new_weights_is_polished_from_where_the_first_pass_left_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The second judgement (the floor magnified on the chosen model's modes) fits the
    same models again: searched from all their starts, a bent belt's spent most of its
    time finding the basin the first pass had found. Started from the first pass's fit,
    a reluctance spring's model (development seed 24) with the floor tripled needs no
    search and fits as well as the search does."""
    effects = frozenset({Effect.RELUCTANCE_TORQUE})
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.RELUCTANCE_TORQUE, 24)
        base = nominal.balanced
        first = Search(base.model.obs, Candidate(base.model.spec, base, held_out(base)),
                       nominal.free, None)
        earlier = first.get(effects)
        floored = base.model.obs.with_floor(
            3.0 * floors.floor(earlier.fit.model, earlier.fit.params))
        again = fit(Model(base.model.spec, floored), [base.params], keep=1)
        searched = fit_spec(floored, earlier.spec, again, nominal.free)
        calls: list[object] = []
        monkeypatch.setattr(candidates_module, "fit_spec", lambda *args: calls.append(args))
        second = Search(floored, Candidate(again.model.spec, again, held_out(again)),
                        nominal.free, None, first)
        polished = second.get(effects)
    assert not calls
    assert polished.fit.chi2 < earlier.fit.chi2 * 0.95  # the weights did move
    assert polished.fit.chi2 <= searched.chi2 * (1.0 + 1e-4)


def test_a_short_polish_of_every_start_picks_the_ones_worth_polishing_in_full() -> None:
    """A larger model has many starts (its base, the unbent chain, the group's own
    estimates): each is polished briefly (the better half past a first heat of a few
    evaluations) and only the two best go on, unless their short polish has already
    converged. On a drifting clock (development seed 24: its base and the group's
    estimates, six starts) that must end where polishing every start in full ends, for
    fewer evaluations."""
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.SENSOR_CLOCK_DRIFT, 24)
        base = nominal.balanced
        model = Model(replace(base.model.spec, effects=frozenset({Effect.SENSOR_CLOCK_DRIFT})),
                      base.model.obs)
        start = transplanted(model, base)
        estimated = [model.with_values(start, v)
                     for v in _clock_estimates(model, start)]
        chosen = chosen_starts(model, [start], 1, estimated)
        assert len(chosen) > HEAT_FIELD  # a field wide enough for the first heat
        counted = _Counting(model)
        every = best_of(counted, chosen)
        full = counted.calls
        counted.calls = 0
        picked = best_of(counted, chosen, finalists=2)
    assert picked.chi2 <= every.chi2 * (1.0 + 1e-3)
    assert counted.calls < full  # 397 against 447 when written


def test_a_coupling_behind_a_belt_is_found_from_a_start_that_begins_far_off() -> None:
    """A coupling's starts are chains spread over the grid, and three evaluations say
    little about which basin a chain is in: its tournament has no first heat. Development
    belt load_resonance@202 (rotor, coupling and pulley, belt, load: modes 44, 111 and
    278 Hz): the start that polishes to the plant's chain was at 1.2 million after three
    evaluations, in the lower half behind starts that stayed at the base, and was cut;
    the coupling then settled on a sliver of the rotor's inertia (χ² 6,089 for 1,594
    degrees of freedom) and the diagnosis named magnetic saturation instead."""
    case = _case(TrialClass(frozenset({Effect.LOAD_RESONANCE})), 202)  # development seed
    unit = _plan(case).unit
    mechanics = unit.mechanics
    assert mechanics.coupling is not None and mechanics.belt is not None
    nominal = _case_nominal(case)
    found = _with(nominal, Effect.LOAD_RESONANCE)
    assert nominal.balanced.chi2 > 100.0 * nominal.balanced.dof  # a bent nominal belt
    assert found.chi2 < 1.2 * found.dof
    fitted_hz = math.exp(found.scalar("log_coupling_hz"))
    assert abs(math.log(fitted_hz / mechanics.coupling.resonance_hz)) < 0.1
    pulley = mechanics.belt.motor_pulley_inertia_kgm2
    share = pulley / (unit.motor.rotor_inertia_kgm2 + pulley)
    assert abs(found.scalar("coupling_fraction") - share) < 0.1


def test_a_model_grown_from_a_drifting_clock_fits_the_clock_only_in_the_form_it_chose(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Whether the sensor holds its latest sample per SYNC or stamps its own is the
    sensor's, not the other groups': both forms are fitted where the clock first enters
    a model, the better kept, and a model grown from that one fits the clock only in the
    form it chose (fitting both again doubled the cost of every larger model)."""
    clock = frozenset({Effect.SENSOR_CLOCK_DRIFT})
    forms: list[bool] = []

    def counted(obs: Observations, spec: ModelSpec, base: Fit, free: Fit | None = None,
                grid: tuple[tuple[NDArray[np.float64], float], ...] | None = None,
                *, others: Sequence[Fit] = ()) -> Fit:
        forms.append(spec.clock_wraps)
        return fit_spec(obs, spec, base, free, grid, others=others)

    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.SENSOR_CLOCK_DRIFT, 24)
        base = nominal.balanced
        search = Search(base.model.obs, Candidate(base.model.spec, base, held_out(base)),
                        nominal.free, None)
        monkeypatch.setattr(candidates_module, "fit_spec", counted)
        single = search.get(clock)
        where_it_entered = list(forms)
        forms.clear()
        larger = search.get(clock | {Effect.CURRENT_LOOP_LAG})
    assert sorted(where_it_entered) == [False, True]
    assert forms == [single.spec.clock_wraps]
    assert larger.spec.clock_wraps == single.spec.clock_wraps


def test_the_settling_ends_when_a_pass_keeps_the_holds_it_kept_before(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Each pass of the settling observes the recording with the chain the last nominal
    fit found, then fits the nominal model again. A pass that would keep the holds an
    earlier one kept, each settled the same way, ends it before it observes anything:
    only their ringing poles' prior would have moved, a little with the fit
    (development trial detent_torque+flux_harmonics@101, a belt: 111 holds twice, each
    pole a few percent off the pass before). Here the same unit with a reluctance torque,
    whose nominal fit the chain is trusted to settle with (that trial's is not now:
    ``test_a_chain_bent_to_hide_a_strong_effect_settles_no_hold``)."""
    timeline = _timeline(_case(TrialClass(frozenset({Effect.RELUCTANCE_TORQUE})), 101))
    holds: list[Holds] = []
    observed: list[Observations] = []
    fitted: list[Observations] = []
    real_holds, real_observe = observations.settled_holds, observations.observe
    real_fit = nominal_module.fit_nominal

    def holding(timeline: Timeline, **kwargs: Any) -> Holds:
        holds.append(real_holds(timeline, **kwargs))
        return holds[-1]

    def observing(timeline: Timeline, **kwargs: Any) -> Observations:
        observed.append(real_observe(timeline, **kwargs))
        return observed[-1]

    def fitting(obs: Observations, **kwargs: Any) -> Nominal:
        fitted.append(obs)
        return real_fit(obs, **kwargs)

    monkeypatch.setattr(nominal_module, "settled_holds", holding)
    monkeypatch.setattr(nominal_module, "observe", observing)
    monkeypatch.setattr(nominal_module, "fit_nominal", fitting)
    obs, _ = nominal_of(timeline)
    # Before the passes, the holds the data settle alone; then two passes with new holds.
    assert len(holds) >= 4
    assert holds[-1] in holds[1:-1]
    assert len(set(holds[1:-1])) == len(holds) - 2  # each pass before it kept new holds
    # The first observation and one per pass but the last, each fitted once.
    assert len(observed) == len(fitted) == len(holds) - 1
    assert obs.segments == fitted[-1].segments


def test_a_chain_bent_to_hide_a_strong_effect_settles_no_hold(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A nominal fit far from its recording has bent its chain to hide what it lacks, and
    its modes are where the bend put them: none of the short holds is settled or rung
    out with them, and the diagnosis says why they are left out. On this development
    belt (a strong detent torque) the first fit leaves χ²/dof of about 290; the same unit
    with a weak reluctance torque has its short holds settled
    (``test_the_settling_ends_when_a_pass_keeps_the_holds_it_kept_before``)."""
    timeline = _timeline(_case(TrialClass(frozenset({Effect.DETENT_TORQUE})), 101))
    observed: list[Observations] = []
    real_observe = observations.observe

    def observing(timeline: Timeline, **kwargs: Any) -> Observations:
        observed.append(real_observe(timeline, **kwargs))
        return observed[-1]

    monkeypatch.setattr(nominal_module, "observe", observing)
    obs, fits = nominal_of(timeline)
    # Read once, before any chain is known; no pass observed it again with the bent one.
    assert len(observed) == 1 and obs is observed[0]
    assert fits.untrusted is not None and fits.untrusted > SETTLE_TRUST_CHI2
    assert fits.untrusted == pytest.approx(fits.free.chi2 / fits.free.dof)
    assert obs.model_settled == obs.ringing == 0
    assert any("too short to judge settling" in s.reason for s in obs.skipped)
    said = [w for w in settling_warnings(obs, fits.untrusted) if "not trusted" in w]
    assert len(said) == 1 and f"χ²/dof {fits.untrusted:.0f}" in said[0]
    assert not any("not trusted" in w for w in settling_warnings(obs, None))


class _Counting(Model):
    """The same model, counting its evaluations."""

    def __init__(self, model: Model) -> None:
        super().__init__(model.spec, model.obs)
        self.calls = 0

    def residuals(self, p: np.ndarray) -> np.ndarray:
        self.calls += 1
        return super().residuals(p)


@pytest.mark.parametrize("wraps", [False, True])
def test_a_model_keeping_its_pieces_between_evaluations_gives_what_a_fresh_model_gives(
        wraps: bool) -> None:
    """A model keeps the pieces of its last evaluations that a parameter does not enter
    (the sensor's response with its clock, the currents, the chain's transfer), since a
    Jacobian moves one parameter at a time. What it keeps must never stand in for what
    changed: along every column of a Jacobian and across jumps between points, a model
    with every group, on a belt, gives to the bit what a model made afresh gives."""
    obs, _ = _observed(Effect.FLUX_HARMONICS, 63)  # development seed 63 draws a belt
    spec = ModelSpec(chain_for(obs.metadata.gear_ratio), effects=frozenset(Effect),
                     clock_wraps=wraps, sensor_bend=True)
    kept = Model(spec, obs)
    low, high = kept.layout.bounds()
    span = np.where(np.isfinite(high - low), np.minimum(high - low, 1.0), 1.0)
    rng = np.random.default_rng(7)
    points = [np.clip(kept.layout.start() + 0.1 * span * rng.standard_normal(span.size),
                      low + 1e-6, high - 1e-6) for _ in range(4)]
    fresh = _Fresh(kept)
    with threadpool_limits(limits=1, user_api="blas"):
        # Back to points others have passed since: whatever is still kept of them must
        # be what the point itself gives.
        for p in [*points, points[0], points[2]]:
            assert np.array_equal(kept.residuals(p), fresh.residuals(p))
            assert np.array_equal(jacobian(kept, p), jacobian(fresh, p))
            assert np.array_equal(kept.linear_design(p)[1], fresh.linear_design(p)[1])


@pytest.mark.parametrize(("effects", "piece", "keys", "moving"), [
    ({Effect.SENSOR_CLOCK_DRIFT}, "_load_motion", (), 4),
    ({Effect.SENSOR_CLOCK_DRIFT, Effect.FRICTION}, "friction_torque", FRICTION_KEYS, 7),
])
def test_a_jacobian_makes_a_kept_piece_once_for_each_point_that_moves_it(
        effects: set[Effect], piece: str, keys: tuple[str, ...], moving: int,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A piece of the model kept between evaluations (``_Memo``: the sensor's response,
    the friction on the load's velocity) is made once at a Jacobian's base point, and of
    its columns only by those that move the piece's own parameters (both sides of
    each). Those columns come in runs: the sensor's filter's two, then the friction's
    levels and smoothing with the drifting clock's, five in a row. Kept as the two made
    last, the base's value was gone after two of them and made again for the column
    after."""
    obs, _ = _observed(Effect.FLUX_HARMONICS, 63)
    model = Model(ModelSpec(chain_for(obs.metadata.gear_ratio), effects=frozenset(effects)),
                  obs)
    made: list[int] = []
    # A method of the model, or a function of the friction's module that it calls.
    owner: Any = model if hasattr(model, piece) else friction_module
    original = getattr(owner, piece)

    def counted(*args: Any) -> Any:
        made.append(1)
        return original(*args)

    monkeypatch.setattr(owner, piece, counted)
    p = model.layout.start()
    keys = (*model.keys(Role.SENSOR), *keys)  # the sensor's, its clock's included
    reads = {i for name in keys if model.layout.has(name)
             for i in range(model.layout.size)[model.layout.slices[name]]}
    assert len(reads & set(model.motion_index().tolist())) == moving
    with threadpool_limits(limits=1, user_api="blas"):
        model.residuals(p)
        assert len(made) == 1
        jacobian(model, p)
    assert len(made) == 1 + 2 * moving


@pytest.mark.parametrize("eps", [5.0, 0.3, 1e-2, 1e-4])  # rad/s, against a swing of ±1.1
def test_friction_on_the_grid_is_its_mean_over_each_step_so_a_crossing_moves_it_smoothly(
        eps: float) -> None:
    """Sampled at the grid's points, a sign sharper than the velocity's change over a step
    is a jump that moves only when a point crosses zero: on development friction
    @1850757460 (the load nearly stopping in one segment) a sensor delay 0.01 ms longer
    moved that segment's χ² from 47 to 86,219. Each grid value is the mean over its
    step instead, the velocity straight between points: it agrees with a fine
    quadrature of tanh(v/ε) and tanh², from a smooth sign to a sharp one, and the
    band it gives (how each mean moves with its three points' velocities) is its own
    derivative, which the step is built from."""
    x = 2 * np.pi * np.arange(GRID) / GRID
    v = 0.5 + np.sin(x) + 0.1 * np.cos(3 * x)  # crosses zero twice a period
    mean_t, mean_t2, band_t, band_t2 = cell_means(v, eps)
    fine = np.linspace(-0.5, 0.5, 20001)[:-1]  # within each step, in steps
    where = x[:, None] + 2 * np.pi / GRID * fine[None, :]
    straight = np.interp(where.ravel() % (2 * np.pi), np.append(x, 2 * np.pi),
                         np.append(v, v[0])).reshape(where.shape)
    t = np.tanh(straight / eps)
    assert np.max(np.abs(mean_t - t.mean(axis=1))) < 1e-4
    assert np.max(np.abs(mean_t2 - (t * t).mean(axis=1))) < 1e-4
    h = 1e-7 * max(eps, 1e-3)
    for point in range(GRID):
        up, down = v.copy(), v.copy()
        up[point] += h
        down[point] -= h
        moved, back = cell_means(up, eps), cell_means(down, eps)
        for shape, band in ((0, band_t), (1, band_t2)):
            numeric = (moved[shape] - back[shape]) / (2.0 * h)
            for offset in (-1, 0, 1):  # the step whose previous, own or next point it is
                step = (point - offset) % GRID
                assert band[offset + 1, step] == pytest.approx(
                    numeric[step], rel=1e-4, abs=1e-6 / eps)


@pytest.mark.parametrize("margin", [1.0001, 1.5, 40.0])  # times SETTLED_SCALE·ε
def test_rows_whose_load_never_nears_a_stop_are_taken_as_settled_to_the_bit(
        margin: float) -> None:
    """A friction fit's rows are mostly segments whose load keeps turning one way far from
    zero speed, and only the others are made in full: a shortcut that moved a mean or a
    slope by an ulp would move every Jacobian column that differences ε."""
    x = 2 * np.pi * np.arange(GRID) / GRID
    eps = 3e-3
    swing = 0.2 * np.sin(x) + 0.05 * np.cos(3 * x)
    floor = margin * SETTLED_SCALE * eps - float(np.min(swing))  # lowest point at the margin
    rows = np.stack([floor + swing, -(floor + swing),  # settled, either way
                     0.1 + swing, swing, 1e-4 * swing])  # near, through and about zero
    quick, full = cell_means(rows, eps), cell_means_made(rows, eps)
    for shape, reference in zip(quick, full, strict=True):
        assert shape.shape == reference.shape
        assert np.array_equal(shape, reference)
    # The settled rows are what the shortcut gives: a sign, its square and no slope.
    assert np.array_equal(quick[0][:2], np.array([[1.0], [-1.0]]) * np.ones((2, GRID)))
    assert not quick[2][:2].any() and not quick[3][:2].any()
    # Any leading shape, as the Jacobian stacks its points.
    stacked = cell_means(np.stack([rows, rows[::-1]]), eps)
    assert np.array_equal(stacked[2][0], quick[2])


@pytest.mark.parametrize("smoothing", [0.1, 1e-3])  # of the slowest mean load speed
def test_the_step_is_the_equation_errors_own_derivative_in_the_measured_motion(
        smoothing: float) -> None:
    """The step carries each segment's equation error into its measured harmonics, so it
    must be the error's derivative in the measured motion, or a residual is not the
    measurement's own noise. Friction evaluated on the measured velocity varies with
    it over the period, far more where the load nearly stops, and moves every order
    with every other: with its mean slope alone the step missed that, and on a
    development disk whose load nearly stopped in one segment (friction
    @1850757460) a sensor delay 0.01 ms longer moved that segment's χ² from 47 to
    86,219. Each segment's error is differenced in its measured harmonics (the slip
    held, which the step leaves to the Jacobian), smooth and nearly sharp friction."""
    obs, _ = _observed(Effect.FRICTION, 24)  # development seed 24 draws a disk
    spec = ModelSpec(chain_for(obs.metadata.gear_ratio), effects=frozenset({Effect.FRICTION}))
    model = Model(spec, obs)
    p = model.with_values(model.layout.start(), {
        "friction_coulomb": [0.2, 0.3], "log_friction_smoothing": [math.log(smoothing)]})
    k = obs.orders
    scale = model.sensor_response(p) * model.radius  # measured harmonics per α

    def error(change: np.ndarray) -> np.ndarray:
        moved = Model(spec, replace(obs, phasors=obs.phasors + change * scale))
        m = moved.motion(p)
        held = m.shifted(-m.lag)
        out: np.ndarray = moved.error(p, held, moved.torque(p, held))
        return out

    m = model.motion(p)
    step = model.step_matrix(p, m.shifted(-m.lag))
    size = 1e-6 * float(np.max(np.abs(m.alpha)))
    numeric = np.empty_like(step)
    with threadpool_limits(limits=1, user_api="blas"):
        for j in range(2 * k):
            change = np.zeros((obs.count, k), dtype=np.complex128)
            change[:, j % k] = size if j < k else 1j * size
            column = (error(change) - error(-change)) / (2.0 * size)
            numeric[:, :, j] = np.concatenate([column.real, column.imag], axis=1)
    assert np.linalg.norm(step - numeric) <= 1e-6 * np.linalg.norm(numeric)


@pytest.mark.parametrize("seed", [63, 24])  # development seeds: a belt, and a disk
def test_every_column_of_the_jacobian_is_what_the_residuals_themselves_change_by(
        seed: int) -> None:
    """The solver stops where the Jacobian says the gradient vanishes, so a column that is
    not the residuals' own derivative stops it short of the optimum. A linear parameter
    also moves each segment's rotor along its spring and changes that spring's stiffness
    (a reluctance torque does little else): with those left out, a clean nominal point
    was taken for the reluctance model's optimum, 135 in χ² above it. Every column (the
    linear parameters' from the model's structure, the others' through the motion's
    differenced inputs, the load angles' from one shared step) is checked against
    central differences of the residuals, for a model with every group, at points
    scattered about the recording's nominal fit, the coupling's mode damped (left at
    its light starting damping, it can sit on an order's frequency, where the
    differences themselves are no reference)."""
    obs, _ = _observed(Effect.RELUCTANCE_TORQUE, seed)
    spec = ModelSpec(chain_for(obs.metadata.gear_ratio), effects=frozenset(Effect))
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.RELUCTANCE_TORQUE, seed).balanced
    model = Model(spec, nominal.model.obs)
    low, high = model.layout.bounds()
    span = np.where(np.isfinite(high - low), np.minimum(high - low, 1.0), 1.0)
    rng = np.random.default_rng(11)
    names = [b.name for b in model.layout.blocks for _ in range(b.size)]
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(2):
            p = np.clip(transplanted(model, nominal) + 0.02 * span * rng.standard_normal(span.size),
                        low + 1e-3 * span, high - 1e-3 * span)
            # Friction on (it starts at none), so that its smoothing's column is no zero.
            p = model.with_values(p, {"coupling_damping_ratio": [0.3],
                                      "friction_coulomb": [0.02, 0.03]})
            assert np.any(model.motion(p).lag != 0.0)  # the slip acts at these points
            analytic = jacobian(model, p)
            ranges = np.where(np.isfinite(high - low), high - low, 0.0)
            assert {"reluctance", "log_rotor_hz", "current_lag_ms", "load_angle_rad"} <= set(
                names)
            for i in range(p.size):
                # The differences are no exact reference at any one step: at 1e-5 a sharp
                # mode's curvature speaks (the rotor's frequency 3.6e-4 off), at 1e-6 the
                # rounding the step matrix magnifies near a mode (a smoothing's 2.6e-4 off),
                # and near a fold of the spring, where a column's norm reached 1.7e10, the
                # curvature at 1e-6 too (the rotor's damping 1.6e-2 off at 1e-5, 1.6e-4 at
                # 1e-6: falling as the step squared). A column must agree with one of them.
                errors, norms, columns = [], [], []
                for h in (1e-5, 1e-6, 1e-7):
                    step = h * max(1.0, abs(p[i]), 1e-2 * ranges[i])  # as ``fit.jacobian``
                    up, down = p.copy(), p.copy()
                    up[i] += step
                    down[i] -= step
                    column = (model.residuals(up) - model.residuals(down)) / (2.0 * step)
                    columns.append(column)
                    errors.append(float(np.linalg.norm(analytic[:, i] - column)))
                    norms.append(float(np.linalg.norm(column)))
                # The gain errors' design column alone was 3.5e-3 off, the offsets' 1e-2, a
                # clock's drift differenced by 1e-6 ppm 2.4e-4 (its phases round). A column
                # near zero is held to 1e-6 (a saturated friction's smoothing, 7e-7,
                # differenced to 4e-7), or to the differences' own disagreement where
                # that is more: friction's smoothing where the load never nears a stop
                # moves the residuals by their rounding alone (2.8e-6 at 1e-5, 1.3e-5 at
                # 1e-6), and a wrong column is wrong by the same at every step.
                spread = min(float(np.linalg.norm(a - b))
                             for a, b in itertools.pairwise(columns))
                assert min(errors) <= 1e-4 * max(*norms, 1e-2) + spread, (
                    names[i], errors, norms, spread)


class _Fresh(Model):
    """The same model made afresh for every evaluation: nothing kept from the last."""

    def __init__(self, model: Model) -> None:
        super().__init__(model.spec, model.obs)

    def residuals(self, p: np.ndarray) -> np.ndarray:
        return Model(self.spec, self.obs).residuals(p)

    def linear_design(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return Model(self.spec, self.obs).linear_design(p)


def _per_condition(model: Model, residuals: np.ndarray) -> np.ndarray:
    cond = model.residual_conditions()
    inside = cond >= 0
    return np.bincount(cond[inside], weights=residuals[inside] ** 2,
                       minlength=len(model.obs.conditions))


def test_a_held_out_condition_never_fits_better_than_the_fit_that_had_it() -> None:
    """A refit without a condition cannot fit that condition better than the fit with it:
    a one-step prediction from a fit short of its optimum (here two evaluations into a
    polish) would say it does, and made a clean belt's saturation group gain 1283 held
    out for 20 fitted."""
    with threadpool_limits(limits=1, user_api="blas"):
        base = _grid_nominal(Effect.RELUCTANCE_TORQUE, 24).balanced
        model = Model(replace(base.model.spec, effects=frozenset({Effect.RELUCTANCE_TORQUE})),
                      base.model.obs)
        early = polish(model, transplanted(model, base), max_nfev=2)
        held = held_out(early)
    assert not early.converged
    fitted = _per_condition(model, early.residuals)
    assert np.all(held.chi2 >= fitted * (1.0 - 1e-9))


def test_a_gain_the_smaller_model_recovers_when_polished_from_the_larger_is_not_counted(
) -> None:
    """A larger model fitted from a smaller one that stopped short of its optimum gains
    what the smaller left on the table, whichever group was added; before such a gain
    counts, the smaller model is polished from the larger's point and keeps the better
    fit (development trial friction@1672103899: five groups each gained 129 to 141 over
    friction). The nominal model is never refitted this way."""
    effects = frozenset({Effect.RELUCTANCE_TORQUE})
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.RELUCTANCE_TORQUE, 24)
        base = nominal.balanced
        nominal_candidate = Candidate(base.model.spec, base, held_out(base))
        search = Search(base.model.obs, nominal_candidate, nominal.free, None)
        good = search.get(effects)
        model = good.fit.model
        short = polish(model, transplanted(model, base), max_nfev=2)
        search.cache[(effects, False)] = Candidate(good.spec, short, held_out(short))
        larger = search.get(effects | {Effect.CURRENT_LOOP_LAG})
        before = compare(search.cache[(effects, False)], larger)
        after = search.refined([before])[0]
        unchanged = search.refined([compare(nominal_candidate, good)])[0]
    assert short.chi2 > good.fit.chi2 + 10.0  # the smaller model was left short
    assert after.smaller.fit.chi2 < short.chi2
    assert after.chi2_gain < before.chi2_gain
    assert search.latest(before.smaller) is after.smaller
    assert unchanged.smaller is nominal_candidate


def test_a_clean_units_noise_gives_no_group_that_reshapes_the_spring_a_gain() -> None:
    """Each residual must carry the measurement's own noise whatever the parameters: a
    spring whose stiffness varies over the period (this clean belt's offsets are a fifth
    of its current) couples each order's noise into its neighbours, and a residual
    divided by the mean stiffness alone let a steep saturation (Kt 30 % down at the
    largest current) gain 51 in χ² and a negative reluctance 45 on noise alone, more
    the more noise the recording had. Carried back by the whole Newton step, neither
    gains what chance allows two parameters (χ²₂ beyond 9.2 once in a hundred)."""
    nominal = _case_nominal(_case(TrialClass(frozenset()), 204))  # development seed 204
    for effect in (Effect.MAGNETIC_SATURATION, Effect.RELUCTANCE_TORQUE):
        assert nominal.balanced.chi2 - _with(nominal, effect).chi2 < 9.2, effect


def _held_per_value(timeline: Timeline) -> float:
    with threadpool_limits(limits=1, user_api="blas"):
        _, nominal = nominal_of(timeline)
        held = held_out(nominal.balanced)
    return held.total / held.residuals.size


def test_a_rough_disks_trim_steps_are_waited_out_until_their_ringing_is_below_the_noise(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Development disk none@208 swings at up to 15 m/s² and each trim step rings its
    47 Hz mode at some 3 m/s². After ln(300) e-foldings that ring is still ten times the
    noise of the harmonics: one hold alone left 40 % of the nominal χ², and the clean unit
    a mismatch (held-out χ² 1.94 per value). Waited out down to the harmonics' resolution,
    the unit is described to the noise."""
    timeline, _ = _clean(208)
    assert _held_per_value(timeline) < 1.25
    monkeypatch.setattr(ChainDecay, "kicked", lambda self, *_: self)
    assert _held_per_value(timeline) > 1.5


def test_a_chain_the_grid_missed_is_found_again_from_the_torque_balance() -> None:
    """Seed 362477267 (a benchmark seed, where this was found): a clean disk swinging at
    up to 130 m/s². Its grid's best start polished into a 58 Hz rotor with its load
    angles on their bounds (χ² 1.5 million); only the fit with the torque balance found
    the 74 Hz chain (χ² 3217). The free fit, the floor's weights and every segment's
    settling are then taken again from there: the clean unit is described to the noise,
    where it was left at 2.53 per value."""
    timeline, _ = _clean(362477267)
    with threadpool_limits(limits=1, user_api="blas"):
        _, nominal = nominal_of(timeline)
    free, balanced = nominal.free, nominal.balanced
    assert free.scalar("log_rotor_hz") == pytest.approx(balanced.scalar("log_rotor_hz"),
                                                         abs=0.01)
    held = held_out(balanced)
    assert held.total / held.residuals.size < 1.25


def test_a_ringing_rotor_whose_spring_swings_with_the_angle_is_fitted_out_with_its_sidebands(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Seed 22660216 (a benchmark seed, where this was found): a clean disk damped at
    ζ 0.03 whose mode (55 and 65 Hz at its two currents) sits on orders 4 and 5 of its
    13.5 Hz holds, too short to wait for. Offsets of 60-190 mA make its spring swing with
    the electrical angle, so the transient rings beside the mode at ± the electrical
    frequency too; fitted at the mode alone, that was left at the neighbouring orders
    (held-out χ² 3.45 per value, 1.59 with the sidebands; 5.01 before this and the
    spring the swing averages); still above the noise."""
    timeline, _ = _clean(22660216)
    assert _held_per_value(timeline) < 2.0
    monkeypatch.setattr(segments, "SIDEBANDS", ())
    assert _held_per_value(timeline) > 3.0


def test_the_floor_of_an_order_that_rides_alone_is_its_own_magnification() -> None:
    """With no order coupled to another (the derivative each order's own spring against
    its own need), the floor carried through the whole derivative is each order's own
    magnification: its torque balance over its own spring less its need, as before."""
    obs, nominal = _nominal_fit(_case(TrialClass(), 204))
    fitted = nominal.free
    model, p = Model(fitted.model.spec, obs), fitted.params
    k = obs.orders

    def own_spring(self: Model, q: np.ndarray, m: Motion) -> np.ndarray:
        """d(error)/d(α) of each order alone: its spring at the period's mean less its need."""
        theta, need = chain.chain_response(self, m)
        out: np.ndarray = -floors.segment_springs(self, q, m)[:, None] * theta - need
        return out

    def alone(self: Model, q: np.ndarray, m: Motion) -> np.ndarray:
        sens = own_spring(self, q, m)
        matrix = np.zeros((obs.count, 2 * k, 2 * k))
        index = np.arange(k)
        matrix[:, index, index] = matrix[:, index + k, index + k] = sens.real
        matrix[:, index, index + k] = -sens.imag
        matrix[:, index + k, index] = sens.imag
        return matrix

    own = Model(fitted.model.spec, obs)
    own.step_matrix = alone.__get__(own)  # type: ignore[method-assign]
    m = own.motion(p)
    theta, need = chain.chain_response(own, m)
    spring = np.abs(floors.segment_springs(own, p, m)[:, None] * theta)
    expected = np.maximum((spring + np.abs(need)) / np.abs(own_spring(own, p, m)), 1.0)
    assert floors.magnification(own, p) == pytest.approx(expected, rel=1e-6)
    assert np.max(floors.magnification(model, p) / expected) > 1.0 + 1e-3  # coupling is there


def test_a_segment_near_its_springs_fold_is_uncertain_at_every_order_its_swing_reaches() -> None:
    """Seed 1306254870 (a benchmark seed, where this was found): a clean 16 g disk, ζ 0.017,
    whose only hold at 660 mA and -27.5 Hz puts order 2 on its 55 Hz mode. Its swing
    rides the sinusoidal spring near a fold: ζ changed by 0.6 % moved orders 2 and 3 by
    half. With the floor of each order's own magnification, orders 1 and 3-5
    were trusted to the noise and holding the hold out missed them by up to 47 σ (held-out
    χ² 10.8 per value of the clean unit, 593 per value of that condition). Carried
    through the whole derivative, the floor covers them."""
    timeline, _ = _clean(1306254870)
    with threadpool_limits(limits=1, user_api="blas"):
        _, nominal = nominal_of(timeline)
        held = held_out(nominal.balanced)
    conditions = nominal.balanced.model.residual_conditions()
    per_condition = held.chi2 / np.bincount(conditions[conditions >= 0])
    assert held.total / held.residuals.size < 1.25
    assert float(np.max(per_condition)) < 3.0


def test_the_noise_leaves_its_own_share_of_a_strong_ripples_values_not_one_each() -> None:
    """σ carries the model floor where the ripple is strong, so the noise leaves less than
    one per value there: a clean belt's held-out χ² is near what its noise leaves
    (``Model.noise_chi2``), far below one per value."""
    base = _case_nominal(_case(TrialClass(frozenset()), 41)).balanced
    held = held_out(base)
    values = held.residuals.size
    noise = base.model.noise_chi2()
    assert noise < 0.9 * values
    assert abs(held.total - noise) < 0.5 * abs(held.total - values), (held.total, noise, values)


DISTORTION_AND_LAG = frozenset({Effect.CURRENT_DISTORTION, Effect.CURRENT_LOOP_LAG})


def _lag_beside_distortion(case: Case) -> tuple[Candidate, Candidate, Test]:
    """The case's distortion model and the pair with the loop lag, as the search fits
    them, and the test between the two."""
    nominal = _case_nominal(case)
    base = nominal.balanced
    with threadpool_limits(limits=1, user_api="blas"):
        search = Search(base.model.obs, Candidate(base.model.spec, base, held_out(base)),
                        nominal.free, None)
        distortion = search.get(frozenset({Effect.CURRENT_DISTORTION}))
        lagging = search.get(DISTORTION_AND_LAG)
        return distortion, lagging, compare(distortion, lagging)


@pytest.mark.xfail(strict=True, reason=(
    "issue 90: with the dead-time form in the distortion group, the pair's fit ends 42 in "
    "fitted χ² above the distortion's alone (held out 903 → 856, noise 751): the lag takes "
    "30 % of what is left, not 75 %, and goes unnamed; a known regression to mend"))
def test_a_loop_lag_beside_a_strong_current_distortion_is_named_when_it_leaves_the_noise(
) -> None:
    """The distortion takes so much that the share its own errors may leave
    (``MODEL_ERROR_SHARE``) is far above anything the lag gains; but what the distortion
    leaves held out is near the noise, and the lag takes it below: there are no errors of
    the distortion left for a group to soak up. Counted one per value, the noise seemed to
    leave more than the distortion did, and the lag was never named (development pair
    current_distortion+current_loop_lag@204). Its nominal fit (χ²/dof 770) now settles
    none of the short holds (``SETTLE_TRUST_CHI2``); on the others the distortion leaves
    887 for 851 values, of which the noise leaves 747, and the lag 773."""
    case = _case(TrialClass(DISTORTION_AND_LAG), 204)
    distortion, lagging, test = _lag_beside_distortion(case)
    # Beyond the noise the distortion leaves 140 held out, the lag 26 of it.
    noise = lagging.fit.model.noise_chi2()
    assert noise < lagging.held.total < distortion.held.total
    assert MODEL_ERROR_SHARE * distortion.explained > 5 * test.chi2_gain
    assert explains_the_rest(distortion, lagging)
    assert test.model_error == 0.0 and test.significant
    # The loop's time constant, each phase's: the plant's within a quarter.
    amplifier = _plan(case).unit.amplifier
    bandwidths = (amplifier.bandwidth_a_hz, amplifier.bandwidth_b_hz)
    truth = [1e3 / (2 * math.pi * hz) for hz in bandwidths if hz is not None]
    fitted = lagging.fit.params[lagging.fit.model.layout.slices["current_lag_ms"]]
    for f, t in zip(fitted, truth, strict=True):
        assert abs(f - t) < 0.25 * t, (fitted, truth)


def test_a_loop_lag_is_named_where_the_noise_estimate_exceeds_what_both_models_leave() -> None:
    """Benchmark pair current_distortion+current_loop_lag@1594235326 (a disk): the
    distortion took 3.1 million and left 756 held out, the lag took that to 637, and the
    noise was estimated to leave 1065, more than either. An estimate the best model beats
    by that much is too high (the strong ripple's floor in σ), so what the lag leaves
    bounds it: the lag took all that was left beyond it and is judged on the noise alone,
    not held to the distortion's model error (3,198, ``MODEL_ERROR_SHARE``)."""
    case = _case(TrialClass(DISTORTION_AND_LAG), 1594235326)
    distortion, lagging, test = _lag_beside_distortion(case)
    assert lagging.held.total < distortion.held.total < lagging.fit.model.noise_chi2()
    assert MODEL_ERROR_SHARE * distortion.explained > 10 * test.held_gain
    assert explains_the_rest(distortion, lagging)
    assert test.model_error == 0.0 and test.significant


def test_a_model_whose_polish_ran_out_is_finished_before_larger_ones_grow_from_it() -> None:
    """A model larger ones start from is polished on when its polish stopped at its
    evaluation budget: left short of its optimum, every larger model grown from it paid
    for the rest again (benchmark trial flux_harmonics@1818367323, flux alone stopped at
    χ² 5,430 and each of the ten models of the next size ended at 1,700). A finished
    one is left as it is."""
    flux = frozenset({Effect.FLUX_HARMONICS})
    with threadpool_limits(limits=1, user_api="blas"):
        nominal = _grid_nominal(Effect.FLUX_HARMONICS, 24)
        base = nominal.balanced
        search = Search(base.model.obs, Candidate(base.model.spec, base, held_out(base)),
                        nominal.free, None)
        done = search.get(flux)
        model = Model(done.spec, base.model.obs)
        cut = polish(model, model.with_values(done.fit.params, {"flux": [0.0] * 16}),
                     max_nfev=2)
        short = candidate_of(base.model.obs, base.chi2, cut)
        search.cache[(flux, False)] = short
        finished = search.finished([short, search.nominal])
    assert done.fit.converged and not cut.converged
    assert cut.chi2 > 2.0 * done.fit.chi2
    assert finished[0].fit.converged
    assert finished[0].fit.chi2 <= 1.01 * done.fit.chi2
    assert search.latest(short) is finished[0]
    assert finished[1] is search.nominal


def test_a_settling_pass_fits_the_nominal_again_from_the_chain_found_without_the_grid(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Development trial load_resonance@21, a belt: the chain its first fit settled adds
    short holds (645 values to 1,199). Fitted again from that first chain alone, the
    nominal model must end where a search of the whole chain grid on the added holds ends,
    and must not search the grid (most of a pass's cost)."""
    timeline = _timeline(_case(TrialClass(frozenset({Effect.LOAD_RESONANCE})), 21))
    with threadpool_limits(limits=1, user_api="blas"):
        first = nominal_module.aligned(timeline).first
        before = fit_nominal(first)
        settled, _ = nominal_of(timeline)
        assert settled.count > first.count
        grid = fit_nominal(settled)

        def no_grid(*_: object) -> None:
            raise AssertionError("the chain grid was searched again")

        monkeypatch.setattr(nominal_module, "nominal_starts", no_grid)
        again = fit_nominal(settled, previous=before)
    assert again.balanced.chi2 <= grid.balanced.chi2 * (1.0 + 1e-4)
    assert again.free.chi2 <= grid.free.chi2 * (1.0 + 1e-4)
