"""Rank check and a-posteriori statistics (sigma0, covariance, correlations) of a solution.

:class:`StatisticsMixin` is mixed into :class:`~planetref.adjust.solver.BundleSolver`:
after convergence ``sigma0 = sqrt(v^T P v / dof)``, camera covariance ``sigma0^2 S^-1``
with ``S`` the undamped reduced matrix, correlations. A rank-deficient reduced system
raises :class:`~planetref.errors.AdjustmentError` naming the parameters that the
observations do not determine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from planetref.adjust.linearization import quadratic
from planetref.adjust.schur import Iterate
from planetref.errors import AdjustmentError

if TYPE_CHECKING:
    from planetref.adjust.config import SolverConfig
    from planetref.control.network import PointMatrices

__all__ = ["StatisticsMixin"]

F64 = NDArray[np.float64]


class StatisticsMixin:
    """Rank check and statistics of a :class:`~planetref.adjust.solver.BundleSolver`.

    Uses the solver's ``n_params``, ``active``, ``prior_w``, ``con_a``, ``con_n``, ``con_w``,
    ``names``, ``cfg``, ``point_prior_w``, ``point_prior_axis_w``, ``_reduced`` and
    ``_prior_cost``.
    """

    # The host's state and methods used here, set by BundleSolver and SchurMixin (a
    # typed contract; annotations only, nothing is defined at run time).
    cfg: SolverConfig
    n_params: int
    names: list[str]
    active: NDArray[np.intp]
    prior_w: F64
    con_a: F64
    con_w: F64
    con_n: F64 | None
    point_prior_w: PointMatrices
    point_prior_axis_w: PointMatrices
    _reduced: Callable[[Iterate, float], tuple[F64, F64, F64, list[tuple[F64, F64, F64]]]]
    _prior_cost: Callable[[F64], float]

    def _check_rank(self, at: Iterate, when: str) -> None:
        lin = at.lin
        act = self.active
        if not act.size:
            return
        # Parameters that no observation (and no prior) touches at all.
        full_diag = np.diag(lin.n_cc)[: self.n_params][act] + self.prior_w[act]
        if self.con_n is not None:
            full_diag = full_diag + np.diag(self.con_n)[act]
        zero = np.flatnonzero(~(full_diag > 0))
        if zero.size:
            names = [self.names[act[i]] for i in zero[:8]]
            raise AdjustmentError(
                f"{zero.size} parameter(s) have no observations at all ({when} cameras): "
                f"{', '.join(names)}{' ...' if zero.size > 8 else ''}; fix them or give them "
                f"an a-priori sigma"
            )
        con_n, self.con_n = self.con_n, None  # the constraints are checked apart (below)
        try:
            s_mat, _, _, _ = self._reduced(at, 0.0)
        finally:
            self.con_n = con_n
        sa = s_mat[np.ix_(act, act)]
        # Scaled by the diagonal before the point elimination: a parameter that the
        # points absorb entirely (a datum defect) shows up as a (near-)zero eigenvalue.
        d = np.sqrt(full_diag)
        z = np.eye(act.size)
        if con_n is not None:
            # The constraints (e.g. smoothed weak nodes, sigma 1e-7 rad) are as good as
            # exact, and their weights dwarf the observations': checked as weights they
            # make any determined direction look singular next to them. Checked as exact:
            # the observations must determine every direction the constraints leave free
            # (their null space; each basis vector mixes only parameters that the
            # constraints tie together, so the diagonal scaling keeps its meaning).
            d = np.sqrt(np.diag(lin.n_cc)[: self.n_params][act] + self.prior_w[act])
            a_act = self.con_a[:, act]
            a_act = a_act[np.any(a_act != 0.0, axis=1)]
            if len(a_act):
                _, r_f, perm = scipy.linalg.qr(a_act, mode="economic", pivoting=True)
                tol = abs(r_f[0, 0]) * max(a_act.shape) * np.finfo(float).eps
                rank = int(np.sum(np.abs(np.diag(r_f)) > tol))
                n_free = act.size - rank
                basis = np.zeros((act.size, n_free))
                basis[perm[:rank]] = -scipy.linalg.solve_triangular(
                    r_f[:rank, :rank], r_f[:rank, rank:]
                )
                basis[perm[rank:]] = np.eye(n_free)
                z = basis / np.linalg.norm(basis, axis=0)
            sa = z.T @ sa @ z
            d = np.sqrt(np.maximum((z * z).T @ (d * d), 0.0))
            d = np.where(d > 0, d, 1.0)  # directions no observation touches: zero rows
        sh = sa / d[:, None] / d[None, :]
        ev, vec = np.linalg.eigh(0.5 * (sh + sh.T))
        rcond = max(ev[0], 0.0) / ev[-1] if ev[-1] > 0 else 0.0
        if not rcond > self.cfg.min_rcond:
            weights = np.abs(z @ vec[:, 0])
            weights /= max(float(np.linalg.norm(weights)), 1e-300)
            top = np.argsort(weights)[::-1][:6]
            names = [f"{self.names[act[i]]} ({weights[i]:.2f})" for i in top if weights[i] > 0.05]
            raise AdjustmentError(
                f"the reduced normal matrix is singular (reciprocal condition "
                f"{rcond:.2g} < {self.cfg.min_rcond:g}, {when} cameras): the observations do "
                f"not determine a combination of {', '.join(names)}; fix or weight these "
                f"parameters (e.g. a datum: a fixed camera or control points)"
            )

    def _statistics(self, at: Iterate) -> dict[str, object]:
        lin, _, c, xyz, xyz0, unknown = at
        p = self.n_params
        s_mat, _, _, _ = self._reduced(at, 0.0)
        act = self.active
        # v^T P v with the final (robust) weights, plus the pseudo-observations.
        vtpv = float(np.sum(lin.weight * np.where(lin.valid[:, None], lin.r, 0.0) ** 2))
        vtpv += 2.0 * self._prior_cost(c)
        n_prior = int(np.count_nonzero(self.prior_w)) + len(self.con_w)
        if len(unknown):
            dx = xyz[unknown] - xyz0[unknown]
            vtpv += quadratic(self.point_prior_w[unknown], dx)
            n_prior += int(np.count_nonzero(self.point_prior_axis_w[unknown]))
        n_obs = 2 * int(np.count_nonzero(lin.valid))
        n_unk = len(act) + 3 * len(unknown)
        dof = n_obs + n_prior - n_unk
        if dof <= 0:
            raise AdjustmentError(
                f"no redundancy: {n_obs // 2} observations ({n_obs} equations) and {n_prior} "
                f"a-priori constraints for {n_unk} unknowns; add observations or fix "
                f"parameters"
            )
        sigma0 = math.sqrt(vtpv / dof)
        cov = np.zeros((p, p))
        cofactor = np.zeros((p, p))
        if act.size:
            sa = s_mat[np.ix_(act, act)]
            d = np.sqrt(np.abs(np.diag(sa)))
            d = np.where(d > 0, d, 1.0)
            sh = sa / d[:, None] / d[None, :]
            try:
                factor = scipy.linalg.cho_factor(sh, lower=False, check_finite=False)
                inv = scipy.linalg.cho_solve(factor, np.eye(len(act)), check_finite=False)
            except np.linalg.LinAlgError:
                self._check_rank(at, "adjusted")
                raise AdjustmentError(
                    "the reduced normal matrix is not positive definite at the solution"
                ) from None
            cofactor[np.ix_(act, act)] = inv / d[:, None] / d[None, :]
            cov = sigma0**2 * cofactor
        sig = np.sqrt(np.diag(cov))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = cov / sig[:, None] / sig[None, :]
        corr[~np.isfinite(corr)] = 0.0
        return {
            "sigma0": sigma0,
            "dof": dof,
            "vtpv": vtpv,
            "covariance": cov,
            "cofactor": cofactor,
            "sigma": sig,
            "correlation": corr,
            "n_unknowns": n_unk,
            "n_equations": n_obs + n_prior,
        }
