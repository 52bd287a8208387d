"""What the solver sees of a camera: the adjustable-camera protocol and its values.

The solver only sees :class:`AdjustableCamera`: a vector of local parameters (with
names, units, initial values, modes and a-priori sigmas), the projection of ground
points into one CCD with the partial derivatives of ``(line, sample)`` with respect to
the parameters and to the ground point, and the adjusted camera built from a parameter
vector.

Sparse Jacobian layout
----------------------
Each observation depends on a few parameters only (the ``k`` orientation nodes of its
Lagrange window plus the interior orientation, or the handful of correction terms of a
CSM image). A parameterisation lists its *patterns*, ``pattern_columns`` of shape
``(n_patterns, q)``: the local parameter indices (``-1`` = padding) of a set of
observations that share their dependencies; :meth:`AdjustableCamera.evaluate` returns
each observation's pattern and its ``(2, q)`` block of partials (rows ``line, sample``).
The solver accumulates normal equations per pattern with dense BLAS products.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import Mode
from planetref.arrays import F64

__all__ = ["MODE_CODE", "AdjustableCamera", "CoverageIssue", "Evaluation", "mode_and_sigma"]

MODE_CODE = {"free": 0, "weighted": 1, "fixed": 2}


class Evaluation:
    """Projections of ground points into one CCD, with partials.

    A model may hand its partials in factored form (``factors``, e.g. a line scanner's
    collinearity partials and Lagrange weights, whose products are the node columns):
    ``d_params`` and ``d_ground`` are then expanded on first use, and the solver's
    compiled linearisation reads the factors directly, so the ``(m, 2, q)`` block is
    never written for observations of fixed points.

    Attributes:
        line: Projected line (pixels), ``(m,)``; NaN where invalid.
        sample: Projected sample, ``(m,)``.
        valid: False where the point could not be projected.
        pattern: Local pattern index of each observation, ``(m,)``.
        d_params: ``d(line, sample)/d(params of the pattern)``, ``(m, 2, q)``.
        d_ground: ``d(line, sample)/d(X, Y, Z)`` per metre, ``(m, 2, 3)``.
        line_rate: Optional per-point hint for the next evaluation (for line scanners
            ``d offset / d line``), handed back as ``rate_guess``; ``None`` if unused.
        factors: ``None``, or an object with ``expand(rows=None) -> (d_params, d_ground)``
            (all rows, or those of a mask) and the
            arrays ``imp`` ``(m, 2, n_raw)``, ``weights`` ``(m, k)``, ``src`` ``(q,)``
            and ``node`` ``(q,)`` such that ``d_params[i, r, c] = imp[i, r, src[c]] *
            (weights[i, node[c]] if node[c] >= 0 else 1)``.
    """

    __slots__ = ("_d_ground", "_d_params", "factors", "line", "line_rate", "pattern", "sample",
                 "valid")  # fmt: skip

    def __init__(
        self,
        line: F64,
        sample: F64,
        valid: NDArray[np.bool_],
        pattern: NDArray[np.intp],
        d_params: F64 | None,
        d_ground: F64 | None,
        line_rate: F64 | None = None,
        *,
        factors: Any = None,
    ) -> None:
        if (d_params is None or d_ground is None) and factors is None:
            raise ValueError("an Evaluation needs its partials or their factors")
        self.line = line
        self.sample = sample
        self.valid = valid
        self.pattern = pattern
        self._d_params = d_params
        self._d_ground = d_ground
        self.line_rate = line_rate
        self.factors = factors

    def _expand(self) -> tuple[F64, F64]:
        pair: tuple[F64, F64] = self.factors.expand()
        self._d_params, self._d_ground = pair
        return pair

    @property
    def d_params(self) -> F64:
        """``d(line, sample)/d(params of the pattern)``, ``(m, 2, q)``."""
        d = self._d_params
        return self._expand()[0] if d is None else d

    @property
    def d_ground(self) -> F64:
        """``d(line, sample)/d(X, Y, Z)`` per metre, ``(m, 2, 3)``."""
        d = self._d_ground
        return self._expand()[1] if d is None else d


@dataclass(frozen=True)
class CoverageIssue:
    """A group of parameters that too few observations determine.

    Attributes:
        label: Human-readable name (e.g. ``"node 3"``).
        indices: Local parameter indices of the group.
        count: Observations found near the group.
        required: Observations required.
    """

    label: str
    indices: tuple[int, ...]
    count: int
    required: int


@runtime_checkable
class AdjustableCamera(Protocol):
    """One camera's unknowns and projections (see the module doc).

    Attributes:
        camera_id: The camera's id in the network.
        camera: The initial camera.
        names: Local parameter names, ``(n,)``.
        units: Unit of each parameter (``"m"``, ``"rad"``, ``"mm"``...).
        x0: Initial (a priori) parameter values, ``(n,)``.
        sigma: A-priori sigma per parameter (inf: free; used when weighted).
        mode: Per parameter ``0`` free, ``1`` weighted, ``2`` fixed.
        pattern_columns: ``(n_patterns, q)`` local parameter indices, ``-1`` padding.
        constraints: Linear pseudo-observations ``A (x - x0) = 0`` with weights ``w``
            (``(A, w)``, ``A`` of shape ``(c, n)``), or ``None``.
    """

    camera_id: str
    camera: Any
    names: tuple[str, ...]
    units: tuple[str, ...]
    x0: F64
    sigma: F64
    mode: NDArray[np.int8]
    pattern_columns: NDArray[np.intp]
    constraints: tuple[F64, F64] | None

    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project points into CCD ``ccd`` with parameters ``x``, with partials.

        ``line_guess`` and ``rate_guess`` are the previous evaluation's ``line`` and
        ``line_rate`` (or the observed lines and ``None``); they may be ignored. With
        ``partials=False`` only ``line``, ``sample`` and ``valid`` are needed.
        """
        ...

    def build(self, x: F64) -> Any:
        """The camera with parameters ``x``."""
        ...

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """Parameter groups that the observations (CCD index, line) leave weak."""
        ...

    def weaken(self, issues: list[CoverageIssue]) -> tuple[AdjustableCamera, list[str]]:
        """Deal with weak groups (weight, constrain or refuse them).

        Returns:
            ``(model, warnings)``: the parameterisation to adjust with (a new one when
            weak groups got weights or constraints; this one is never changed) and the
            warning messages.
        """
        ...


def mode_and_sigma(
    mode: Mode, sigma: float | None, n: int, fixed: bool
) -> tuple[NDArray[np.int8], F64]:
    """Per-parameter mode codes and sigmas of a block of ``n`` parameters.

    Args:
        mode: The block's mode.
        sigma: Its a-priori sigma (used when weighted).
        n: Number of parameters.
        fixed: Hold the block fixed whatever its mode (a fixed camera).

    Returns:
        ``(mode codes, sigmas)``; sigmas are inf unless weighted.
    """
    code = MODE_CODE["fixed" if fixed else mode]
    sig = np.full(n, np.inf if sigma is None or code != 1 else float(sigma))
    return np.full(n, code, np.int8), sig
