"""Signal processing on sensor samples, and where their harmonics null (pure functions,
no I/O)."""

from station.dsp.demod import harmonic_phasors
from station.dsp.null import h1_then_h2_null

__all__ = ["h1_then_h2_null", "harmonic_phasors"]
