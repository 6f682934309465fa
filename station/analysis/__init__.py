"""Offline analysis: trims from any ICD.md §5 recording.

Reading and timeline assembly turn a CAN log into per-SYNC arrays; the rest
(segmenting, demodulation, estimation) are pure functions on those arrays, so
a recording from another bench goes through exactly the code a live
calibration uses.
"""
