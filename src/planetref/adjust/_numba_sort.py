"""numba implementation of the layout's stable sort (imported lazily).

The twin of the numpy reference in :func:`planetref.adjust.solver._group_order`
(``np.argsort(kind="stable")`` by line, then by group; a test binds both). Importing this
module imports numba; the functions compile on first use or load from numba's on-disk
cache.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

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
