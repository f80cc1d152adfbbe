"""The calibration model: named terms, the model file, stepwise selection, identification.

Pure computation (numpy/scipy only): no I/O beyond the model file, no asyncio, no zenoh.
"""

from nanodrift.model import axis_terms, effect_terms  # noqa: F401  (register the multi-axis and discovery terms' names)
