"""Array type aliases shared by every part of the package.

One alias per array type, so a signature reads the same everywhere: ``F64`` is a numpy
array of float64 of any shape (the shape and units are stated in each docstring).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["F64"]

#: A float64 numpy array (shape and units in the docstring of whatever takes it).
F64 = NDArray[np.float64]
