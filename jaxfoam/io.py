"""Deprecated alias of `fitting.io` (moved with the calibration package); removed in the next release."""
from ._deprecated import alias

__getattr__, __dir__ = alias('io', 'fitting.io', ('fitting.io',))
