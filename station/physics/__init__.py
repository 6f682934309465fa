"""The simulated unit's physics: torque model, unit parameters, plant, optimal trims.

Pure numpy/scipy and ``math``; no I/O. The simulated devices drive a ``Plant``
one SYNC period at a time; the truth a calibration is judged against comes
from ``optimal_trims`` on the same plant.
"""

from station.core import Axis
from station.physics.motor import (
    DetentHarmonic,
    Eccentricity,
    FluxHarmonic,
    MotorParams,
    inductance_matrix,
    inductance_matrix_derivative,
    magnetic_stiffness,
    mutual_inductances,
    ripple_harmonic_magnitudes,
    saturation_current_for_drop,
    torque,
    torque_closed_form,
    torque_components,
    torque_numerical,
)
from station.physics.optimum import optimal_trims, settle_time_s, steady_harmonics
from station.physics.params import (
    AmplifierParams,
    BeltParams,
    CouplingParams,
    CurrentHarmonic,
    DiskParams,
    EffectForm,
    FrictionParams,
    MechanicsParams,
    SensorParams,
    UnitParams,
    UnnamedEffect,
    derive_unit,
)
from station.physics.plant import (
    Chain,
    DriveCommand,
    LumpedFriction,
    Mode,
    Plant,
    build_chain,
    commanded_currents_A,
    modal_analysis,
    substeps_for,
)

__all__ = [
    "AmplifierParams",
    "Axis",
    "BeltParams",
    "Chain",
    "CouplingParams",
    "CurrentHarmonic",
    "DetentHarmonic",
    "DiskParams",
    "DriveCommand",
    "Eccentricity",
    "EffectForm",
    "FluxHarmonic",
    "FrictionParams",
    "LumpedFriction",
    "MechanicsParams",
    "Mode",
    "MotorParams",
    "Plant",
    "SensorParams",
    "UnitParams",
    "UnnamedEffect",
    "build_chain",
    "commanded_currents_A",
    "derive_unit",
    "inductance_matrix",
    "inductance_matrix_derivative",
    "magnetic_stiffness",
    "modal_analysis",
    "mutual_inductances",
    "optimal_trims",
    "ripple_harmonic_magnitudes",
    "saturation_current_for_drop",
    "settle_time_s",
    "steady_harmonics",
    "substeps_for",
    "torque",
    "torque_closed_form",
    "torque_components",
    "torque_numerical",
]
