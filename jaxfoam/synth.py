"""Deprecated alias of `fitting.synth` (moved with the calibration package); removed in the next release."""
from ._deprecated import alias

__getattr__, __dir__ = alias('synth', 'fitting.synth', ('fitting.synth', 'fitting.cli'))
