"""Array aliases used in type hints across the package.

Shapes and frames are given in each function's docstring; these aliases only
say the dtype.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
ImageU8 = NDArray[np.uint8]
ImageU16 = NDArray[np.uint16]
