"""Benchmarks: speed and memory targets, one JSON object per line (``bench/run``)."""
