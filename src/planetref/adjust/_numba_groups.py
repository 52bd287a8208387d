"""numba implementation of the variance components' image-group passes (lazy import).

The twins of :func:`planetref.adjust.variance._group_order_numpy` and
:func:`planetref.adjust.variance._group_vtpv_numpy` (the numpy references; a test binds
both bit for bit): a stable counting sort of the observations by (point kind, camera,
CCD), and the per-group ``v^T P v`` summed row by row, as ``np.bincount`` sums.
Importing this module imports numba; the functions compile on first use or load from
numba's on-disk cache.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_order(
    obs: Any,
    obs_camera: Any,
    obs_ccd: Any,
    obs_point: Any,
    kind_of_pt: Any,
    base: int,
    n_keys: int,
    n_kinds: int,
) -> tuple[Any, Any]:
    """Positions into ``obs`` sorted (stably) by ``kind * n_keys + camera * base + ccd``.

    ``base``: the most CCDs of a camera; ``n_keys``: cameras times ``base``. Returns
    ``(order, bounds)``: the positions, and for each code ``c`` its range
    ``order[bounds[c]:bounds[c + 1]]``.
    """
    m = obs.shape[0]
    n_code = n_kinds * n_keys
    code = np.empty(m, np.int64)
    bounds = np.zeros(n_code + 1, np.int64)
    for i in range(m):
        o = obs[i]
        c = kind_of_pt[obs_point[o]] * n_keys + obs_camera[o] * base + obs_ccd[o]
        code[i] = c
        bounds[c + 1] += 1
    for c in range(n_code):
        bounds[c + 1] += bounds[c]
    pos = bounds[:n_code].copy()
    order = np.empty(m, np.intp)
    for i in range(m):
        c = code[i]
        order[pos[c]] = i
        pos[c] += 1
    return order, bounds


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_vtpv(group: Any, w: F64, v: F64, n_groups: int) -> F64:
    """Per group, ``sum w_l v_l^2 + w_s v_s^2`` over the rows (``group`` per row, -1: none)."""
    out = np.zeros(n_groups)
    for i in range(group.shape[0]):
        g = group[i]
        if g >= 0:
            out[g] += w[i, 0] * (v[i, 0] * v[i, 0]) + w[i, 1] * (v[i, 1] * v[i, 1])
    return out
