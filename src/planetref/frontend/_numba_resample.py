"""numba implementation of the orthorectification's bilinear block sampling (lazy import).

The twin of :func:`planetref.frontend.resample.bilinear_blocks_numpy` (scipy's
``map_coordinates(order=1, mode="constant", cval=0)`` on the block means and on their
validity; a test binds both to equality): one pass over the output pixels gathers the four
block means and validities of each. Importing this module imports numba; the function
compiles on first use or loads from numba's on-disk cache.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True, nogil=True)
def bilinear_pair(
    block: NDArray[np.float32],
    valid: NDArray[np.bool_],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    out: NDArray[np.float32],
    vfrac: NDArray[np.float32],
) -> None:
    """Bilinear block mean and valid fraction at fractional ``(u, v)`` block indices.

    Points outside ``[0, rows - 1] x [0, cols - 1]`` (or NaN) get 0, as scipy's
    ``mode="constant"`` gives; the weights and the order of the sums are scipy's, so the
    float32 results are the same.

    Args:
        block: ``(rows, cols)`` block means.
        valid: ``(rows, cols)`` block validity.
        u: Row coordinates ``(n,)`` (block centres at integers).
        v: Column coordinates ``(n,)``.
        out: ``(n,)`` output values (written).
        vfrac: ``(n,)`` output valid fractions (written).
    """
    rows, cols = block.shape
    for n in range(u.shape[0]):
        a, b = u[n], v[n]
        if not (a >= 0.0 and a <= rows - 1 and b >= 0.0 and b <= cols - 1):
            out[n] = 0.0
            vfrac[n] = 0.0
            continue
        fa, fb = math.floor(a), math.floor(b)
        ta, tb = a - fa, b - fb
        i0, j0 = int(fa), int(fb)
        i1, j1 = min(i0 + 1, rows - 1), min(j0 + 1, cols - 1)
        w00 = (1.0 - ta) * (1.0 - tb)
        w01 = (1.0 - ta) * tb
        w10 = ta * (1.0 - tb)
        w11 = ta * tb
        out[n] = (
            w00 * np.float64(block[i0, j0])
            + w01 * np.float64(block[i0, j1])
            + w10 * np.float64(block[i1, j0])
            + w11 * np.float64(block[i1, j1])
        )
        vfrac[n] = (
            w00 * (1.0 if valid[i0, j0] else 0.0)
            + w01 * (1.0 if valid[i0, j1] else 0.0)
            + w10 * (1.0 if valid[i1, j0] else 0.0)
            + w11 * (1.0 if valid[i1, j1] else 0.0)
        )
