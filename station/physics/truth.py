"""A unit's truth file: every constant of the simulated unit, and each effect it has with
the figures a diagnosis is scored against.

Apart from ``params`` because some figures (the load's modes) need the plant, which
builds on the parameters: the truth sits above both.
"""

from __future__ import annotations

import math
from typing import Any

from station.core import Effect
from station.physics.params import UnitParams, UnnamedEffect, as_jsonable
from station.physics.plant import modal_analysis


def unit_truth(unit: UnitParams) -> dict[str, Any]:
    """JSON-ready truth: every constant, and each enabled effect with its own.

    ``out_of_vocabulary`` lists, apart from ``effects``, what no id may
    name (``UnnamedEffect``), so a scorer can tell a missed effect from
    an honest "unknown".
    """
    out: dict[str, Any] = {
        "serial": unit.serial,
        "serial_number": unit.serial_number,
        "rated_current_mA": unit.rated_current_mA,
        "microsteps": unit.microsteps,
        "rotor_teeth": unit.rotor_teeth,
        "load": unit.load.value,
        "gear_ratio": unit.gear_ratio,
        "sensor_radius_m": unit.sensor_radius_m,
        "kt_Nm_per_A": unit.motor.kt_Nm_per_A,
        "holding_torque_Nm": unit.motor.holding_torque_Nm(unit.rated_current_mA / 1000.0),
        "motor": as_jsonable(unit.motor),
        "amplifier": as_jsonable(unit.amplifier),
        "mechanics": as_jsonable(unit.mechanics),
        "sensor": as_jsonable(unit.sensor),
        "effects": [
            {"id": effect.value, "parameters": _effect_parameters(unit, effect)}
            for effect in sorted(unit.effects)
        ],
        "out_of_vocabulary": [
            {"id": unnamed.value, "parameters": _unnamed_parameters(unit, unnamed)}
            for unnamed in sorted(unit.unnamed_effects)
        ],
    }
    return out


def _unnamed_parameters(unit: UnitParams, unnamed: UnnamedEffect) -> dict[str, Any]:
    s = unit.sensor
    match unnamed:
        case UnnamedEffect.SENSOR_NONLINEARITY:
            return {"c2": s.nonlinearity_c2, "c3": s.nonlinearity_c3,
                    "deviation_at_full_scale": abs(s.nonlinearity_c2)
                    + abs(s.nonlinearity_c3),
                    "law": "a + c2*a^2/FS + c3*a^3/FS^2 per axis, FS = range_g*g0"}
        case UnnamedEffect.SENSOR_TILT:
            return {"tilt_rad": s.tilt_rad, "tilt_deg": math.degrees(s.tilt_rad),
                    "law": "t' = cos(a)*t + sin(a)*r, r' = cos(a)*r - sin(a)*t"}


def _effect_parameters(unit: UnitParams, effect: Effect) -> dict[str, Any]:
    m, a, mech, s = unit.motor, unit.amplifier, unit.mechanics, unit.sensor
    match effect:
        case Effect.FLUX_HARMONICS:
            return {"phase_a": as_jsonable(m.flux_a), "phase_b": as_jsonable(m.flux_b),
                    "Lm1_H": m.Lm1_H}
        case Effect.DETENT_TORQUE:
            peaks = {
                f"peak_torque_order_{d.order}_Nm": 0.5 * d.order * m.rotor_teeth
                * d.amplitude_H * m.field_current_A**2
                for d in m.detent
            }
            return {"harmonics": as_jsonable(m.detent), **peaks}
        case Effect.RELUCTANCE_TORQUE:
            unequal = ({"L1_unequal": m.L1_unequal,
                        "law": "L11 = L0 + L1(1 + u)cos 2θe, L22 = L0 − L1(1 − u)cos 2θe"}
                       if m.L1_unequal else {})
            return {"L1_H": m.L1_H, "peak_torque_at_rated_Nm": m.rotor_teeth * m.L1_H
                    * (unit.rated_current_mA / 1000.0) ** 2, **unequal}
        case Effect.LOAD_RESONANCE:
            modes = modal_analysis(unit, float(unit.rated_current_mA))
            where = (as_jsonable(mech.coupling) if mech.coupling is not None else
                     {"second_belt_mode": as_jsonable(mech.belt.second_mode if mech.belt
                                                      else None)})
            return {**where,
                    "chain_modes_at_rated_current": [
                        {"frequency_hz": float(m.frequency_hz),
                         "damping_ratio": float(m.damping_ratio)} for m in modes]}
        case Effect.CURRENT_DISTORTION:
            dead = ({"dead_time_mA": a.dead_time_mA, "dead_time_knee_mA": a.dead_time_knee_mA,
                     "law": "i - dead_time * tanh(i / knee) on each phase"}
                    if a.dead_time_mA else {})
            return {"phase_a": as_jsonable(a.distortion_a), "phase_b": as_jsonable(a.distortion_b),
                    **dead}
        case Effect.CURRENT_LOOP_LAG:
            pi = ({"pi_loop": as_jsonable(a.pi_loop),
                   "law": "PI on R-L phases, Kp = 2*pi*bandwidth*L, Ki = Kp*R/L, "
                          "back-EMF speed * dtau/di"} if a.pi_loop is not None else {})
            return {"bandwidth_a_hz": a.bandwidth_a_hz, "bandwidth_b_hz": a.bandwidth_b_hz,
                    **pi}
        case Effect.FRICTION:
            return as_jsonable(mech.load_friction)  # type: ignore[no-any-return]
        case Effect.SENSOR_CLOCK_DRIFT:
            return {"clock_drift_ppm": s.clock_drift_ppm, "sample_phase": s.sample_phase}
        case Effect.MAGNETIC_SATURATION:
            rated_A = unit.rated_current_mA / 1000.0
            return {"saturation_current_A": m.saturation_current_A,
                    "kt_drop_at_rated": 1.0 - float(m.saturation_factor(rated_A)),
                    "holding_torque_at_rated_Nm": m.holding_torque_Nm(rated_A)
                    * float(m.saturation_factor(rated_A)),
                    "law": "tau_pm * 1/sqrt(1 + (|i|/saturation_current_A)^2)"}
        case Effect.ROTOR_ECCENTRICITY:
            return {**as_jsonable(m.eccentricity),
                    "law": "airgap torque * (1 + relative*cos(theta + phase_rad)); "
                           "rotor load -unbalance_Nm*sin(theta + unbalance_phase_rad)"}
