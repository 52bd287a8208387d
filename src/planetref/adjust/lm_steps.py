"""Pieces of the Levenberg-Marquardt loop of :class:`~planetref.adjust.solver.BundleSolver`.

The report of a run (:class:`LmReport`), the camera gradient of the cost, the cost's
resolution (what the projections' rounding lets a cost comparison say) and the
Anderson acceleration of linearly converging undamped Gauss-Newton steps
(:func:`anderson_correction`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from planetref.arrays import F64

if TYPE_CHECKING:  # pragma: no cover
    from planetref.adjust.linearization import Linearization

__all__ = [
    "ANDERSON_DEPTH",
    "CORRECT_MAX_LAMBDA",
    "LmReport",
    "anderson_correction",
    "cost_resolution",
]


@dataclass
class LmReport:
    """What one Levenberg-Marquardt run did.

    Attributes:
        iterations: Accepted iterations.
        evaluations: Model evaluations (accepted and rejected steps).
        converged: True when a convergence criterion was met.
        reason: Why it stopped.
        cost_initial: Cost at the start (half the weighted robust sum of squares).
        cost_final: Cost at the end.
        history: ``(iteration, cost, lambda)`` per accepted step.
        seconds: Wall time.
        cpu_seconds: Process CPU time (robust when other jobs share the cores).
    """

    iterations: int = 0
    evaluations: int = 0
    converged: bool = False
    reason: str = ""
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    history: list[tuple[int, float, float]] = field(default_factory=list)
    seconds: float = 0.0
    cpu_seconds: float = 0.0


#: Precision of a projection (px): the kernels converge to ~1e-9 px whatever the guesses.
PROJECTION_PX = 1e-9
#: Largest damping at which a step counts as Gauss-Newton for the Anderson correction.
CORRECT_MAX_LAMBDA = 1e-6
#: Most earlier undamped steps an Anderson step combines.
ANDERSON_DEPTH = 3
#: Step-length ratios (this step / the previous one, in ``S``'s metric) of a linearly
#: converging sequence: below, Gauss-Newton converges fast and its step is taken as it
#: is; above, the steps grow.
_LINEAR_RATIO = (0.2, 1.5)


def anderson_correction(
    history: list[tuple[F64, F64]], c: F64, step: F64 | None, s_mat: F64
) -> F64 | None:
    """Correction of an undamped Gauss-Newton step of a linearly converging sequence.

    Where the residuals are systematic (a model that cannot fit the data exactly), the
    second-order term ``sum r_i H_i`` that Gauss-Newton drops from the cost's Hessian
    is not small in weakly determined directions (positions against attitudes of
    neighbouring nodes): ``J^T W J`` misjudges the curvature there and Gauss-Newton
    converges only linearly. Successive steps repeat those directions with lengths in
    near-constant ratios: measured on the demo's NCC network, reversing with a ratio of
    0.67 before and 0.93-0.97 after the variance re-weighting (hundreds of iterations
    to converge). Gauss-Newton is then a fixed-point iteration ``c -> c + f(c)`` whose
    error shrinks geometrically in a few directions, and Anderson's acceleration (type
    II, Walker & Ni 2011) combines the last steps into the step to the iteration's
    limit: ``f_k - (dC + dF) gamma`` with ``gamma`` the least-squares fit of ``f_k`` by
    the differences ``dF`` of the steps, ``dC`` of the iterates (for one direction it is
    Aitken's extrapolation ``f_k / (1 - rho)``). The fit is taken in the metric of the
    reduced normal matrix ``S``; the points follow by back substitution; the LM loop
    keeps the result only if the cost falls, else it takes the plain step.

    Args:
        history: ``(c_j, f_j)`` of the previous consecutive undamped iterations, oldest
            first: the iterate and its plain Gauss-Newton step.
        c: This iterate.
        step: Its plain undamped step, or ``None`` (damped: never corrected).
        s_mat: The reduced normal matrix ``S`` of this iteration, ``(p, p)``.

    Returns:
        The correction to add to the step (parameter units), or ``None``.
    """
    if step is None or not history:
        return None
    f_prev = history[-1][1]
    n_prev2 = float(f_prev @ s_mat @ f_prev)
    n_step2 = float(step @ s_mat @ step)
    if not (n_prev2 > 0.0 and n_step2 > 0.0):
        return None
    if not _LINEAR_RATIO[0] < math.sqrt(n_step2 / n_prev2) < _LINEAR_RATIO[1]:
        return None
    pts = [*history[-ANDERSON_DEPTH:], (c, step)]
    d_c = np.column_stack([b[0] - a[0] for a, b in itertools.pairwise(pts)])
    d_f = np.column_stack([b[1] - a[1] for a, b in itertools.pairwise(pts)])
    sd = s_mat @ d_f
    gram = d_f.T @ sd
    # A ridge of 1e-10 of the trace: nearly parallel differences stay solvable.
    gram[np.diag_indices_from(gram)] += 1e-10 * max(float(np.trace(gram)), 1e-300)
    try:
        gamma = np.linalg.solve(gram, sd.T @ step)
    except np.linalg.LinAlgError:
        return None
    corr = -(d_c + d_f) @ gamma
    new = step + corr
    # A combination far longer than the plain step is not a limit the steps point to.
    if not np.all(np.isfinite(new)) or float(new @ s_mat @ new) > 100.0 * n_step2:
        return None
    return corr


def cost_resolution(lin: Linearization) -> float:
    """Three standard deviations of the cost's noise from the projections' precision.

    ``cost = 0.5 sum w r^2`` moves by ``sum w r delta`` when every projection moves by an
    independent ``delta`` of :data:`PROJECTION_PX`: ``sd = PROJECTION_PX
    sqrt(sum (w r)^2)``.
    """
    wr = lin.weight * np.where(lin.valid[:, None], lin.r, 0.0)
    return 3.0 * PROJECTION_PX * float(np.sqrt(np.sum(wr * wr)))
