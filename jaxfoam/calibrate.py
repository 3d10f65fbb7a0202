"""Deprecated alias of `fitting` (moved with the calibration package); removed in the next release."""
from ._deprecated import alias

__getattr__, __dir__ = alias('calibrate', 'fitting', ('fitting', 'fitting.settings', 'fitting.result', 'fitting.problem', 'fitting.check', 'fitting.driver', 'fitting.plots', 'fitting.cli'))
