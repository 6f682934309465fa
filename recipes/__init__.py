"""The station's shipped calibration recipes (``*.toml``).

A package only so that ``importlib.resources`` finds the files the same way in
a source tree, an editable install and a wheel; see ``station.recipes``.
"""
