"""Pieces of the Levenberg-Marquardt loop of :class:`~planetref.adjust.solver.BundleSolver`.

The report of a run (:class:`LmReport`), the camera gradient of the cost, the cost's
resolution (what the projections' rounding lets a cost comparison say) and the
correction of undamped Gauss-Newton steps that reverse the previous one
(:func:`oscillation_correction`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover
    from planetref.adjust.linearization import _Linearization
    from planetref.adjust.solver import BundleSolver

__all__ = [
    "CORRECT_MAX_LAMBDA",
    "LmReport",
    "camera_gradient",
    "cost_resolution",
    "oscillation_correction",
]

F64 = NDArray[np.float64]


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
#: Largest damping at which a step counts as Gauss-Newton for the oscillation correction.
CORRECT_MAX_LAMBDA = 1e-6
#: |cosine| above which two successive Gauss-Newton steps count as one direction.
_ALIGNED_COS = 0.8
#: Step-length ratios within which a reversing / a shrinking sequence is corrected
#: (the latter at most 5 x extrapolated).
_REVERSING_RATIO = (0.2, 1.5)
_SHRINKING_RATIO = (0.2, 0.8)


def oscillation_correction(step: F64 | None, prev: F64 | None, s_mat: F64) -> F64 | None:
    """Correction of an undamped Gauss-Newton step that repeats the previous one's direction.

    Where the residuals are systematic (a model that cannot fit the data exactly), the
    neglected second-order term ``sum r_i H_i`` of the cost's Hessian is not small in a
    weakly determined direction (positions against attitudes of neighbouring nodes):
    ``J^T W J`` misjudges the curvature there and Gauss-Newton converges only linearly.
    Successive steps then point along one direction with lengths in a near-constant
    ratio: reversing (the curvature underestimated, every step overshoots; measured on
    the demo's NCC network: ratio 0.67 before, 0.93-0.97 after the variance
    re-weighting, hundreds of iterations to converge) or shrinking (overestimated).
    The error along that direction is a geometric sequence with ratio ``rho`` (``-q``
    or ``+q``): the step's component along the previous one, scaled by
    ``1 / (1 - rho)`` (Aitken's extrapolation), lands at its limit. Components and
    lengths are taken in the metric of the reduced normal matrix ``S``; the points
    follow by back substitution; the LM loop accepts the result only if the cost falls
    (and takes the plain step otherwise).

    Args:
        step: This iteration's undamped camera step, or ``None`` (damped: never
            corrected).
        prev: The previous accepted undamped camera step, or ``None``.
        s_mat: The reduced normal matrix ``S`` of this iteration, ``(p, p)``.

    Returns:
        The correction to add to the step (parameter units), or ``None``.
    """
    if step is None or prev is None:
        return None
    sp = s_mat @ prev
    n_prev2 = float(prev @ sp)
    n_step2 = float(step @ s_mat @ step)
    if not (n_prev2 > 0.0 and n_step2 > 0.0):
        return None
    along = float(step @ sp) / n_prev2  # step = along * prev + (S-orthogonal rest)
    cos = along * math.sqrt(n_prev2 / n_step2)
    q = math.sqrt(n_step2 / n_prev2)
    if cos <= -_ALIGNED_COS and _REVERSING_RATIO[0] < q < _REVERSING_RATIO[1]:
        rho = -q
    elif cos >= _ALIGNED_COS and _SHRINKING_RATIO[0] < q < _SHRINKING_RATIO[1]:
        rho = q
    else:
        return None
    return (1.0 / (1.0 - rho) - 1.0) * along * prev


def cost_resolution(lin: _Linearization) -> float:
    """Three standard deviations of the cost's noise from the projections' precision.

    ``cost = 0.5 sum w r^2`` moves by ``sum w r delta`` when every projection moves by an
    independent ``delta`` of :data:`PROJECTION_PX`: ``sd = PROJECTION_PX
    sqrt(sum (w r)^2)``.
    """
    wr = lin.weight * np.where(lin.valid[:, None], lin.r, 0.0)
    return 3.0 * PROJECTION_PX * float(np.sqrt(np.sum(wr * wr)))


def camera_gradient(lin: _Linearization, solver: BundleSolver, c: F64) -> F64:
    """Gradient of the cost w.r.t. the camera parameters (observations and priors)."""
    p = solver.n_params
    grad = lin.g_c[:p] + solver.prior_w * (c - solver.x0)
    if solver.con_n is not None:
        grad = grad + solver.con_n @ (c - solver.x0)
    return grad
