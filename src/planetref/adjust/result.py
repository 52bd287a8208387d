"""The outcome of an adjustment: :class:`AdjustmentResult` and its headline summary."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import AdjustConfig
from planetref.adjust.consider import ConsiderTerms
from planetref.adjust.jitter import JitterSeries
from planetref.adjust.models import AdjustableCamera
from planetref.arrays import F64
from planetref.control.network import Network

__all__ = ["STATUSES", "AdjustmentResult"]


#: Observation status codes of :attr:`AdjustmentResult.status`.
STATUSES = ("inlier", "outlier", "unusable", "check")


@dataclass(frozen=True, eq=False)
class AdjustmentResult:
    """Everything an adjustment produced.

    Attributes:
        network: The input network.
        config: The configuration used.
        models: The cameras' parameterisations (names, units, modes).
        cameras_initial: Camera id -> initial camera.
        cameras: Camera id -> adjusted camera.
        parameter_names: ``"camera_id:name"`` per global parameter.
        parameter_units: Unit per parameter.
        parameter_mode: ``0`` free, ``1`` weighted, ``2`` fixed, per parameter.
        x0: Initial parameter values.
        x: Adjusted parameter values.
        sigma: A-posteriori standard deviations (0 for fixed parameters).
        covariance: A-posteriori covariance of the parameters, ``(n, n)``: the
            measurements' (``sigma0^2 S^-1``) plus the declared correlated errors'
            (:attr:`consider`).
        covariance_measurement: The measurements' share alone, ``(n, n)``.
        consider: The correlated errors taken in as consider parameters, or ``None``.
        correlation: Correlation matrix, ``(n, n)``.
        point_xyz_initial: Initial point coordinates (after triangulation), ``(P, 3)``.
        point_xyz: Adjusted point coordinates, ``(P, 3)``.
        residual_initial: ``(line, sample)`` residuals (px) with the initial cameras and
            points, ``(M, 2)``, NaN where not projectable.
        residual: Residuals after the adjustment, ``(M, 2)``.
        status: Per observation ``inlier``, ``outlier``, ``unusable`` or ``check``.
        sigma0: A-posteriori standard deviation of unit weight.
        dof: Degrees of freedom (redundancy).
        metrics: Reprojection metrics before/after, overall, per camera and per CCD,
            and of the check observations (see :func:`adjust`).
        variance: Variance components per observation group, their iterations, and the
            degrees of freedom split into real observations (image measures, MCP
            ground coordinates) and pseudo-observations (camera priors, smoothing
            constraints, tie-point priors).
        points: Per point columns (a-priori and adjusted coordinates, sigmas, shifts;
            see :func:`~planetref.adjust.diagnostics.point_table`).
        diagnostics: Point and camera movements, strong correlations and the
            estimability of the self-calibration parameters.
        rounds: Per outlier round: inliers, RMSE, LM iterations, cost.
        converged: The last LM run converged and the inlier set is stable.
        warnings: Messages about auto-weighted groups, unusable points, instability.
        seconds: Wall time of the adjustment.
        jitter: Strip id -> estimated jitter of the jitter stage
            (:class:`~planetref.adjust.jitter.JitterSeries`); empty without it.
    """

    network: Network
    config: AdjustConfig
    models: list[AdjustableCamera]
    cameras_initial: dict[str, Any]
    cameras: dict[str, Any]
    parameter_names: list[str]
    parameter_units: list[str]
    parameter_mode: NDArray[np.int8]
    x0: F64
    x: F64
    sigma: F64
    covariance: F64
    correlation: F64
    point_xyz_initial: F64
    point_xyz: F64
    residual_initial: F64
    residual: F64
    status: NDArray[np.str_]
    sigma0: float
    dof: int
    metrics: dict[str, Any]
    covariance_measurement: F64 | None = None
    consider: ConsiderTerms | None = None
    variance: dict[str, Any] = field(default_factory=dict)
    points: dict[str, Any] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    rounds: list[dict[str, Any]] = field(default_factory=list)
    converged: bool = False
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    jitter: dict[str, JitterSeries] = field(default_factory=dict)

    @property
    def inlier(self) -> NDArray[np.bool_]:
        """True for inlier observations."""
        return self.status == "inlier"

    def summary(self) -> dict[str, Any]:
        """The headline numbers (the ``adjustment`` block of report.json)."""
        after = self.metrics["all"]["after"]
        before = self.metrics["all"]["before"]
        dof = self.variance.get("dof", {})
        return {
            "rmse_px_before": before["rmse_px"],
            "rmse_x_px": after["rmse_x_px"],
            "rmse_y_px": after["rmse_y_px"],
            "rmse_px_before_all": self.metrics["all"]["before_all"]["rmse_px"],
            "rmse_px": after["rmse_px"],
            "mean_px_before": before["mean_px"],
            "mean_px": after["mean_px"],
            "outlier_ratio_pct": after["outlier_ratio_pct"],
            "n_total": after["n_total"],
            "n_inliers": after["n_inliers"],
            "n_unusable": int(np.count_nonzero(self.status == "unusable")),
            "n_check": int(np.count_nonzero(self.status == "check")),
            "sigma0": self.sigma0,
            "sigma0_before_vce": self.variance.get("sigma0_before"),
            "sigma0_real": dof.get("sigma0_real"),
            "dof": self.dof,
            "redundancy_real": dof.get("redundancy_real"),
            "redundancy_pseudo": dof.get("redundancy_pseudo"),
            "n_pseudo_equations": dof.get("n_pseudo_equations"),
            "rounds": len(self.rounds),
            "converged": self.converged,
            "seconds": self.seconds,
        }
