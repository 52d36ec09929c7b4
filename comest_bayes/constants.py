"""Constants shared by the stages (one home each)."""

from __future__ import annotations

import math

#: FWHM of a Gaussian in units of its standard deviation, 2 sqrt(2 ln 2) = 2.35482...
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))

__all__ = ["FWHM_PER_SIGMA"]
