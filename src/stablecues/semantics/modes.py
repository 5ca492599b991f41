"""The masking modes by name (:mod:`.masking` defines what each does), apart from the masking
code so that ``stablecues segment --help`` lists them without importing numpy or OpenCV."""

from __future__ import annotations

#: the masking modes, in the order :mod:`.masking`'s docstring describes them
MODES = ("hard", "dilate", "patch", "dynamic", "none")
