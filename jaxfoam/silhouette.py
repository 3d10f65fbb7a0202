"""Deprecated alias of `fitting.silhouette` (moved with the calibration package); removed in the next release."""
from ._deprecated import alias

__getattr__, __dir__ = alias('silhouette', 'fitting.silhouette', ('fitting.silhouette',))
