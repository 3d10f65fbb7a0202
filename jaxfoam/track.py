"""Deprecated alias of `fitting.track` (moved with the calibration package); removed in the next release."""
from ._deprecated import alias

__getattr__, __dir__ = alias('track', 'fitting.track', ('fitting.track', 'fitting.video', 'fitting.cli'))
