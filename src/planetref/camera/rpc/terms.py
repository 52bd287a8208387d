"""The 20 terms of an RPC00B cubic polynomial and their partial derivatives.

Term order of the NITF RPC00B specification (and GDAL's ``RPCComputeTerms``), in the
normalised ground coordinates ``L`` (longitude), ``P`` (latitude) and ``H`` (height)::

    1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³

Each function returns the terms (or their derivative with respect to one coordinate)
stacked on a new last axis of length 20, so ``terms @ coefficients`` evaluates the
polynomials.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__: list[str] = []


def _terms(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    return np.stack(
        [
            np.ones_like(L),
            L,
            P,
            H,
            L * P,
            L * H,
            P * H,
            L * L,
            P * P,
            H * H,
            P * L * H,
            L**3,
            L * P * P,
            L * H * H,
            L * L * P,
            P**3,
            P * H * H,
            L * L * H,
            P * P * H,
            H**3,
        ],
        axis=-1,
    )


def _terms_dl(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    z, o = np.zeros_like(L), np.ones_like(L)
    return np.stack(
        [
            z,
            o,
            z,
            z,
            P,
            H,
            z,
            2 * L,
            z,
            z,
            P * H,
            3 * L * L,
            P * P,
            H * H,
            2 * L * P,
            z,
            z,
            2 * L * H,
            z,
            z,
        ],
        axis=-1,
    )


def _terms_dp(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    z, o = np.zeros_like(L), np.ones_like(L)
    return np.stack(
        [
            z,
            z,
            o,
            z,
            L,
            z,
            H,
            z,
            2 * P,
            z,
            L * H,
            z,
            2 * L * P,
            z,
            L * L,
            3 * P * P,
            H * H,
            z,
            2 * P * H,
            z,
        ],
        axis=-1,
    )


def _terms_dh(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    z, o = np.zeros_like(L), np.ones_like(L)
    return np.stack(
        [
            z,
            z,
            z,
            o,
            z,
            L,
            P,
            z,
            z,
            2 * H,
            P * L,
            z,
            z,
            2 * L * H,
            z,
            z,
            2 * P * H,
            L * L,
            P * P,
            3 * H * H,
        ],
        axis=-1,
    )
