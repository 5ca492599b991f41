"""stablecues: place recognition and loop-closure detection with memorable, stable cues."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
