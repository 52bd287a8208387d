"""Lagrange interpolation over a sliding window of nodes, with time derivatives.

Nodes sit at increasing times ``t_0 < ... < t_{N-1}``. A time ``t`` in ``[t_i, t_{i+1})``
is interpolated from the ``k`` nodes ``i - k/2 + 1 ... i + k/2`` (``k`` = the order, at
most ``N``), the window clamped to the ends, so times before the first node or after the
last extrapolate with the first or last window.

Within one window the Lagrange basis polynomials are fixed, so they are tabulated once
as coefficients in ``tau = t - c`` (``c`` the mean time of the window's nodes; lowest
power first). Weights, interpolated values and their time derivatives are then Horner
evaluations: no per-point products over the nodes. The same tables serve the
interpolation of a whole node array per window (:meth:`LagrangeWindows.polynomials`),
which is what a projection kernel evaluated at many times wants.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.errors import InputError

__all__ = ["LagrangeWindows", "lagrange_window"]


class LagrangeWindows:
    """Sliding-window Lagrange interpolation at fixed node times.

    Args:
        times: Node times (any unit, here seconds), ``(N,)``, strictly increasing.
        order: Nodes per window ``k`` (>= 2; reduced to ``N`` when larger).

    Attributes:
        times: The node times.
        k: Nodes per window.
        n_windows: ``N - k + 1``; window ``s`` uses nodes ``s ... s + k - 1``.
        centre: Mean node time of each window, ``(n_windows,)``.
        coef: ``(n_windows, k basis, k powers)`` basis coefficients in ``tau``.
    """

    def __init__(self, times: ArrayLike, order: int) -> None:
        t = np.asarray(times, np.float64).ravel()
        if len(t) < 2 or np.any(np.diff(t) <= 0) or int(order) < 2:
            raise InputError("Lagrange nodes need >= 2 strictly increasing times and order >= 2")
        self.times = t
        self.k = min(int(order), len(t))
        self.n_windows = len(t) - self.k + 1
        idx = self.window_nodes(np.arange(self.n_windows))
        tn = t[idx]
        self.centre = tn.mean(axis=1)
        coef = np.zeros((self.n_windows, self.k, self.k))
        for s in range(self.n_windows):
            for j in range(self.k):
                others = np.delete(tn[s], j)
                den = np.prod(tn[s, j] - others)
                coef[s, j] = np.polynomial.polynomial.polyfromroots(others - self.centre[s]) / den
        self.coef = coef

    def window_nodes(self, start: NDArray[np.intp]) -> NDArray[np.intp]:
        """Node indices ``(m, k)`` of windows starting at ``start``."""
        return np.asarray(start)[:, None] + np.arange(self.k)[None, :]

    def window(self, t: F64) -> tuple[NDArray[np.intp], F64]:
        """Window start and ``tau = t - centre`` of times ``t``."""
        i = np.searchsorted(self.times, t, side="right") - 1
        start = np.clip(i - self.k // 2 + 1, 0, len(self.times) - self.k)
        return start, t - self.centre[start]

    def weights(
        self, t: ArrayLike, *, derivative: bool = False
    ) -> tuple[NDArray[np.intp], F64, F64 | None]:
        """Window start, weights ``(m, k)`` and (optionally) their time derivatives.

        Args:
            t: Times, ``(m,)``.
            derivative: Also return ``d w / d t`` (per time unit).

        Returns:
            ``(start, w, dw)``; the interpolated value is ``sum_j w[:, j] v[start + j]``;
            ``dw`` is ``None`` without ``derivative``.
        """
        start, tau = self.window(np.atleast_1d(np.asarray(t, np.float64)))
        return self.basis(start, tau, derivative=derivative)

    def basis(
        self, start: NDArray[np.intp], tau: F64, *, derivative: bool = False
    ) -> tuple[NDArray[np.intp], F64, F64 | None]:
        """:meth:`weights` from a window already found (:meth:`window`)."""
        c = self.coef[start]  # (m, k basis, k powers)
        w, dw = _horner(lambda q: c[:, :, q], tau[:, None], self.k, derivative)
        return start, w, dw

    def polynomials(self, values: F64) -> F64:
        """Per window, the interpolated ``values`` as polynomials in ``tau``.

        Args:
            values: Node values, ``(N, p)``.

        Returns:
            ``(n_windows, k powers, p)`` coefficients, lowest power first.
        """
        idx = self.window_nodes(np.arange(self.n_windows))
        return np.einsum("sjp,sjq->spq", self.coef, values[idx])

    def evaluate(
        self, poly: F64, start: NDArray[np.intp], tau: F64, *, derivative: bool = False
    ) -> tuple[F64, F64 | None]:
        """Interpolated values ``(m, p)`` (and their time derivatives) at windows/``tau``.

        Args:
            poly: :meth:`polynomials` of the node values.
            start: Window starts, ``(m,)`` (from :meth:`window`).
            tau: Times relative to the window centres, ``(m,)``.
            derivative: Also return ``d value / d t``.
        """
        pc = poly[start]  # (m, powers, p)
        return _horner(lambda q: pc[:, q], tau[:, None], self.k, derivative)


def _horner(
    coef: Callable[[int], F64], tau: F64, k: int, derivative: bool
) -> tuple[F64, F64 | None]:
    """``sum_q coef(q) tau^q`` for ``q < k`` and, optionally, its derivative in ``tau``."""
    val = coef(k - 1).copy()
    for q in range(k - 2, -1, -1):
        val *= tau
        val += coef(q)
    if not derivative:
        return val, None
    der = (k - 1) * coef(k - 1)
    for q in range(k - 2, 0, -1):
        der = der * tau + q * coef(q)
    return val, der


def lagrange_window(
    times: ArrayLike, t: ArrayLike, order: int
) -> tuple[NDArray[np.intp], F64, F64]:
    """Node indices, weights and weight derivatives of times ``t`` (see the module doc).

    Args:
        times: Node times, ``(N,)``, strictly increasing.
        t: Times to interpolate at, ``(m,)``.
        order: Nodes per window.

    Returns:
        ``(idx, w, dw)``, each ``(m, k)``: node indices, weights and ``d w / d t``.
    """
    win = LagrangeWindows(times, order)
    start, w, dw = win.weights(t, derivative=True)
    return win.window_nodes(start), w, np.asarray(dw)
