"""The same least-squares problem solved by ``scipy.optimize.least_squares``.

A cross-check of the bundle solver (tests) and the baseline of the benchmark: the
unknowns are the non-fixed camera parameters and the coordinates of the non-fixed
points; the residuals are the whitened observation residuals ``r / sigma`` of the given
observations and the whitened pseudo-observations of weighted parameters and points. The
residual and Jacobian come from the same :class:`~planetref.adjust.models.AdjustableCamera`
evaluations as the bundle solver's (one evaluation serves both at a given ``x``), or,
with ``kernel="camera"``, from the native camera's public API
(:meth:`~planetref.camera.linescan.LineScanCamera.image_partials`, what a scipy user
would call); the Jacobian is handed over as a ``scipy.sparse`` CSR matrix. No robust
loss.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.optimize
import scipy.sparse

from planetref.adjust.config import AdjustConfig, validate_config
from planetref.adjust.models import Evaluation, LineScanParameterization, parameterize
from planetref.adjust.solver import BundleSolver
from planetref.arrays import F64
from planetref.control.network import Network
from planetref.errors import InputError

__all__ = ["ScipyProblem", "solve_with_scipy"]


class ScipyProblem:
    """Residual and sparse Jacobian of a network for ``scipy.optimize.least_squares``.

    Args:
        network: The network (all non-check observations take part).
        config: The configuration (modes and sigmas; the loss is ignored).
        kernel: ``"planetref"``: the parameterisations' evaluations (the bundle solver's
            fused kernel); ``"camera"``: ``LineScanCamera.image_partials`` for native
            strips (interior scope ``strip`` only).
    """

    def __init__(
        self,
        network: Network,
        config: AdjustConfig | dict[str, Any] | None = None,
        kernel: str = "planetref",
    ) -> None:
        cfg = validate_config(config if config is not None else {})
        if kernel not in ("planetref", "camera"):
            raise InputError(f"kernel must be 'planetref' or 'camera', got {kernel!r}")
        if kernel == "camera" and cfg.linescan.interior.scope != "strip":
            raise InputError("kernel 'camera' supports the interior scope 'strip' only")
        self.kernel = kernel
        self.net = network
        self.models = [
            parameterize(cid, cam, cfg)
            for cid, cam in zip(network.camera_ids, network.cameras, strict=True)
        ]
        self.solver = BundleSolver(network, self.models, cfg.solver)
        s = self.solver
        self.obs = np.flatnonzero(~network.obs_check)
        pts = network.obs_point[self.obs]
        self.unknown = np.unique(pts[~s.point_fixed[pts]])
        umap = np.full(network.n_points, -1, np.intp)
        umap[self.unknown] = np.arange(len(self.unknown))
        self.obs_unknown = umap[pts]
        self.n_cam = len(s.active)
        self.cam_map = np.full(s.n_params + 1, -1, np.intp)
        self.cam_map[s.active] = np.arange(self.n_cam)
        self.weighted_c = np.flatnonzero(s.mode == 1)
        self.weighted_p = self.unknown[np.any(s.point_prior_axis_w[self.unknown] > 0, axis=1)]
        self.xyz_fixed = np.nan_to_num(network.point_xyz)
        self._cache: tuple[bytes, tuple[F64, scipy.sparse.csr_matrix]] | None = None

    def x0(self) -> F64:
        """Initial vector ``[active camera parameters, unknown point XYZ]``."""
        return np.concatenate(
            [self.solver.x0[self.solver.active], self.xyz_fixed[self.unknown].ravel()]
        )

    def split(self, x: F64) -> tuple[F64, F64]:
        """Global camera vector and all point coordinates of ``x``."""
        c = self.solver.x0.copy()
        c[self.solver.active] = x[: self.n_cam]
        xyz = self.xyz_fixed.copy()
        xyz[self.unknown] = x[self.n_cam :].reshape(-1, 3)
        return c, xyz

    def _evaluate(self, x: F64) -> tuple[F64, scipy.sparse.csr_matrix]:
        key = np.asarray(x).tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        s = self.solver
        net = self.net
        c, xyz = self.split(x)
        m = len(self.obs)
        res = np.empty(2 * m)
        rows, cols, vals = [], [], []
        sig = net.obs_sigma_px[self.obs]
        for mi, ccd, pos in s._groups(self.obs):
            model = self.models[mi]
            xc = c[s.offsets[mi] : s.offsets[mi + 1]]
            o = self.obs[pos]
            if self.kernel == "camera" and isinstance(model, LineScanParameterization):
                ev = _camera_evaluation(model, xc, xyz[net.obs_point[o]], ccd, s.line_guess[o])
            else:
                ev = model.evaluate(
                    xc, xyz[net.obs_point[o]], ccd, s.line_guess[o], rate_guess=s.rate_guess[o]
                )
            s._remember(o, ev)
            r = np.stack([ev.line - net.obs_line[o], ev.sample - net.obs_sample[o]], 1)
            r /= sig[pos]
            res[2 * pos], res[2 * pos + 1] = r[:, 0], r[:, 1]
            q = ev.d_params.shape[2]
            gcols = s.cols[ev.pattern + s.pat_offsets[mi], :q]
            lc = self.cam_map[gcols]  # -1 for fixed/padding
            for k in range(2):
                keep = lc >= 0
                rr = np.broadcast_to((2 * pos + k)[:, None], lc.shape)
                rows.append(rr[keep])
                cols.append(lc[keep])
                vals.append((ev.d_params[:, k, :] / sig[pos, k, None])[keep])
                uo = self.obs_unknown[pos]
                has = uo >= 0
                if np.any(has):
                    rows.append(np.repeat(2 * pos[has] + k, 3))
                    cols.append((self.n_cam + 3 * uo[has][:, None] + np.arange(3)).ravel())
                    vals.append((ev.d_ground[has, k, :] / sig[pos[has], k, None]).ravel())
        n_rows = 2 * m
        extra = []
        # Pseudo-observations of weighted camera parameters and points.
        wc = self.weighted_c
        if wc.size:
            sc = s.sigma[wc]
            extra.append((c[wc] - s.x0[wc]) / sc)
            rows.append(n_rows + np.arange(wc.size))
            cols.append(self.cam_map[wc])
            vals.append(1.0 / sc)
            n_rows += wc.size
        wp = self.weighted_p
        if wp.size:
            # Whitening L = diag(1/sigma) R of each point (L^T L = its weight matrix).
            w = np.sqrt(s.point_prior_axis_w[wp])[:, :, None] * s.net.point_frame_matrices(wp)
            dxp = xyz[wp] - self.xyz_fixed[wp]
            extra.append(np.einsum("pij,pj->pi", w, dxp).ravel())
            umap = np.searchsorted(self.unknown, wp)
            base = n_rows + 3 * np.arange(wp.size)
            rows.append(np.repeat(base[:, None] + np.arange(3), 3, axis=1).ravel())
            cols.append(
                np.broadcast_to(
                    (self.n_cam + 3 * umap[:, None] + np.arange(3))[:, None, :], (wp.size, 3, 3)
                ).ravel()
            )
            vals.append(w.ravel())
            n_rows += 3 * wp.size
        full = np.concatenate([res, *extra])
        jac = scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(n_rows, self.n_cam + 3 * len(self.unknown)),
        )
        self._cache = (key, (full, jac))
        return full, jac

    def fun(self, x: F64) -> F64:
        """Whitened residual vector."""
        return self._evaluate(x)[0]

    def jac(self, x: F64) -> scipy.sparse.csr_matrix:
        """Sparse Jacobian of :meth:`fun`."""
        return self._evaluate(x)[1]


def _camera_evaluation(
    model: LineScanParameterization, x: F64, xyz: F64, ccd: int, line_guess: F64
) -> Evaluation:
    """An :class:`Evaluation` from ``LineScanCamera.image_partials`` (the public API)."""
    cam = model.build(x)
    ip = cam.image_partials(xyz, ccd=cam.ccds[ccd].name, line_guess=line_guess)
    m, _, k, _ = ip.d_nodes.shape
    valid = np.isfinite(ip.line) & np.isfinite(ip.sample)
    start = ip.node_index[:, 0]
    d_params = np.concatenate([ip.d_nodes.reshape(m, 2, 6 * k), ip.d_interior], axis=2)
    d_params[~valid] = 0.0
    d_ground = np.where(valid[:, None, None], ip.d_ground, 0.0)
    # Window start -> pattern: the parameterisation's columns of that window.
    return Evaluation(ip.line, ip.sample, valid, np.where(valid, start, 0), d_params, d_ground)


def solve_with_scipy(
    network: Network,
    config: AdjustConfig | dict[str, Any] | None = None,
    *,
    kernel: str = "planetref",
    **options: Any,
) -> tuple[F64, F64, Any]:
    """Solve a network with ``scipy.optimize.least_squares`` (no outlier rejection).

    Args:
        network: The network.
        config: Modes and sigmas (the robust loss is ignored).
        kernel: ``"planetref"`` or ``"camera"`` (see :class:`ScipyProblem`).
        **options: Passed to ``least_squares`` (defaults: ``method="trf"``,
            ``x_scale="jac"``, ``tr_solver="lsmr"``, tolerances 1e-12).

    Returns:
        ``(global camera vector, point XYZ (P, 3), scipy result)``.
    """
    prob = ScipyProblem(network, config, kernel=kernel)
    kw: dict[str, Any] = {
        "method": "trf",
        "x_scale": "jac",
        "tr_solver": "lsmr",
        "ftol": 1e-12,
        "xtol": 1e-12,
        "gtol": 1e-12,
    }
    kw.update(options)
    out = scipy.optimize.least_squares(prob.fun, prob.x0(), jac=prob.jac, **kw)
    c, xyz = prob.split(out.x)
    return c, xyz, out
