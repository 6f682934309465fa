"""Signal processing on sensor samples (pure functions, no I/O)."""

from station.dsp.demod import harmonic_phasors

__all__ = ["harmonic_phasors"]
