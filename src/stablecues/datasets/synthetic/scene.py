"""Moved; see :mod:`stablecues._compat`."""

from ..._compat import moved

moved(__name__)
