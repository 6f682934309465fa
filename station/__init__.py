"""End-of-line calibration station for hybrid stepper motor drives."""

__version__ = "0.1.0"
