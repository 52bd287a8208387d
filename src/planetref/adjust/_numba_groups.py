"""numba implementation of the adjustment's grouping passes (lazy import).

The twins of :func:`planetref.adjust.variance._group_order_numpy` and
:func:`planetref.adjust.variance._group_vtpv_numpy` (the numpy references; a test binds
both bit for bit): a stable counting sort of the observations by (point kind, camera,
CCD), and the per-group ``v^T P v`` summed row by row, as ``np.bincount`` sums; and of
the layout's stable order by (camera, CCD, line) (:func:`planetref.adjust.solver.
_group_order`). One module, so that no compiled function calls into another file
(numba's cache would not see a change there). Importing this module imports numba;
the functions compile on first use or load from numba's on-disk cache.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

#: Buckets longer than this are sorted by numba's merge sort instead of by insertion.
_INSERTION_MAX = 48


@numba.njit(cache=True, nogil=True, error_model="numpy")
def counting_order(keys: Any, n_keys: int) -> Any:
    """The stable sorting permutation of ``keys`` (integers in ``[0, n_keys)``).

    Equal to ``np.argsort(keys, kind="stable")``: one counting pass, one prefix sum, one
    scatter (O(m + n_keys) instead of a comparison sort).
    """
    m = keys.shape[0]
    start = np.zeros(n_keys + 1, np.intp)
    for i in range(m):
        start[keys[i] + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    order = np.empty(m, np.intp)
    for i in range(m):
        k = keys[i]
        order[start[k]] = i
        start[k] += 1
    return order


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_line_order(bucket: Any, n_buckets: int, line: Any) -> Any:
    """The stable order by ``(bucket, line)``.

    ``bucket`` is monotonic in ``line`` within a group (``group * span + floor(line) -
    lo``). A counting sort by bucket, then each bucket (a few observations of one image line)
    sorted by line, stably: the same permutation as a stable sort by line, then by group.
    """
    order = counting_order(bucket, n_buckets)
    m = order.shape[0]
    a = 0
    while a < m:
        b = a + 1
        while b < m and bucket[order[b]] == bucket[order[a]]:
            b += 1
        if b - a > _INSERTION_MAX:
            seg = order[a:b].copy()
            sub = np.argsort(line[seg], kind="mergesort")
            for j in range(b - a):
                order[a + j] = seg[sub[j]]
        else:
            for j in range(a + 1, b):  # insertion sort: stable (strict comparison)
                o = order[j]
                v = line[o]
                q = j - 1
                while q >= a and line[order[q]] > v:
                    order[q + 1] = order[q]
                    q -= 1
                order[q + 1] = o
        a = b
    return order


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
    order = counting_order(code, n_code)
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
