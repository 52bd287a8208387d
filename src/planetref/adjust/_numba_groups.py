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

from planetref.arrays import F64

#: Buckets longer than this are sorted by numba's merge sort instead of by insertion.
_INSERTION_MAX = 48


#: Widest digit of the radix sort (bits): 4096 counters and write streams stay in the
#: L1/L2 caches (16-bit digits, 65536 streams, took 2.6x as long over 1e6 random keys).
_RADIX_BITS = 12


@numba.njit(cache=True, nogil=True, error_model="numpy")
def radix_order(keys: Any, n_keys: int) -> tuple[Any, Any]:
    """The stable sorting permutation of ``keys`` (integers in ``[0, n_keys)``); sorted keys.

    Equal to ``np.argsort(keys, kind="stable")``: least-significant-digit radix passes,
    each a counting sort by one digit of at most :data:`_RADIX_BITS` bits (the key's bits
    split evenly over the fewest such passes), so the counters and the write positions
    stay in cache where one counting sort over millions of keys would not.
    """
    m = keys.shape[0]
    order = np.arange(m)
    k = keys.copy()
    total = 1
    while (n_keys - 1) >> total > 0:
        total += 1
    passes = (total + _RADIX_BITS - 1) // _RADIX_BITS
    bits = (total + passes - 1) // passes
    size = 1 << bits
    mask = size - 1
    for p in range(passes):
        shift = p * bits
        start = np.zeros(size + 1, np.intp)
        for i in range(m):
            start[((k[i] >> shift) & mask) + 1] += 1
        for d in range(size):
            start[d + 1] += start[d]
        new_order = np.empty(m, np.intp)
        new_k = np.empty_like(k)
        for i in range(m):
            d = (k[i] >> shift) & mask
            j = start[d]
            new_order[j] = order[i]
            new_k[j] = k[i]
            start[d] = j + 1
        order = new_order
        k = new_k
    return order, k


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_line_order(bucket: Any, n_buckets: int, line: Any) -> Any:
    """The stable order by ``(bucket, line)``.

    ``bucket`` is monotonic in ``line`` within a group (``group * span + line bin``). A
    radix sort by bucket, then each bucket (a few observations of one line bin) sorted
    by line, stably: the same permutation as a stable sort by line, then by group.
    """
    order, keys = radix_order(bucket, n_buckets)
    m = order.shape[0]
    ls = np.empty(m)
    for i in range(m):
        ls[i] = line[order[i]]
    a = 0
    while a < m:
        b = a + 1
        while b < m and keys[b] == keys[a]:
            b += 1
        if b - a > _INSERTION_MAX:
            sub = np.argsort(ls[a:b], kind="mergesort")
            seg = order[a:b].copy()
            vals = ls[a:b].copy()
            for j in range(b - a):
                order[a + j] = seg[sub[j]]
                ls[a + j] = vals[sub[j]]
        else:
            for j in range(a + 1, b):  # insertion sort: stable (strict comparison)
                o = order[j]
                v = ls[j]
                q = j - 1
                while q >= a and ls[q] > v:
                    order[q + 1] = order[q]
                    ls[q + 1] = ls[q]
                    q -= 1
                order[q + 1] = o
                ls[q + 1] = v
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
    order, _ = radix_order(code, n_code)
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
