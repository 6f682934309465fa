"""Diagnosis: where a recording departs from the paper's model, what physics that is, and
how much better the model fits with it (issue: locate, name, model, prove).

Pure numpy/scipy on the harmonics of a recording's steady segments; no I/O
except the HTML report, which only reads the results.
"""
