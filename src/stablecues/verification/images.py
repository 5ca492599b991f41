"""Moved to :mod:`stablecues.detection.pair`; see :mod:`stablecues._compat`."""

from .._compat import moved

moved(__name__)
