"""Throwaway infrastructure for the tests and the benchmarks, never for the station
itself: the runtime imports nothing from here (an import-linter contract)."""
