"""The 20 terms of an RPC00B cubic polynomial and their partial derivatives.

Term order of the NITF RPC00B specification (and GDAL's ``RPCComputeTerms``), in the
normalised ground coordinates ``L`` (longitude), ``P`` (latitude) and ``H`` (height)::

    1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³

Each function returns the terms (or their derivative with respect to one coordinate)
stacked on a new last axis of length 20, so ``terms @ coefficients`` evaluates the
polynomials. The terms and the three derivatives are all generated from :data:`TERMS`, so
the calculus is written once.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__: list[str] = []

#: The 20 monomials in RPC00B order, each the product of its letters (left to right).
TERMS: tuple[str, ...] = (
    *("", "L", "P", "H", "LP", "LH", "PH", "LL", "PP", "HH"),
    *("PLH", "LLL", "LPP", "LHH", "LLP", "PPP", "PHH", "LLH", "PPH", "HHH"),
)


def _monomials(
    L: NDArray[np.float64],
    P: NDArray[np.float64],
    H: NDArray[np.float64],
    wrt: str | None = None,
) -> NDArray[np.float64]:
    """The 20 terms, or their derivatives with respect to ``wrt`` (``"L"``, ``"P"``, ``"H"``).

    The derivative of a monomial is its exponent of ``wrt`` times the monomial with one
    factor ``wrt`` fewer (zero when it has none).
    """
    L, P, H = np.broadcast_arrays(L, P, H)
    value = {"L": L, "P": P, "H": H}
    columns = []
    for term in TERMS:
        power = 1
        if wrt is not None:
            power = term.count(wrt)
            term = term.replace(wrt, "", 1)
        if power == 0:
            columns.append(np.zeros_like(L))
        elif not term:
            columns.append(np.ones_like(L))
        elif len(term) == 3 and len(set(term)) == 1:
            columns.append(value[term[0]] ** 3)
        else:
            product = value[term[0]] if power == 1 else power * value[term[0]]
            for name in term[1:]:
                product = product * value[name]
            columns.append(product)
    return np.stack(columns, axis=-1)


def terms(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    return _monomials(L, P, H)


def terms_dl(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    return _monomials(L, P, H, "L")


def terms_dp(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    return _monomials(L, P, H, "P")


def terms_dh(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    return _monomials(L, P, H, "H")
