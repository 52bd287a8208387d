"""Rigorous line-scan bundle adjustment with matched control points and tie points.

The entry point is :func:`adjust`, which takes a :class:`Network` (cameras, ground
points, image observations) and an :class:`AdjustConfig` and returns an
:class:`AdjustmentResult` (adjusted cameras, parameters with a-posteriori sigmas and
correlations, residuals, inlier flags, metrics before/after). :func:`read_network`
reads a ``NETWORK.toml`` control network (:mod:`planetref.adjust.network_file`);
:func:`planetref.report.adjustment.write_outputs` writes the adjusted cameras, residual
table, report.json/report.md and residual plots. See docs/adjust.md.
"""

from planetref.adjust.api import adjust
from planetref.adjust.config import AdjustConfig, validate_config
from planetref.adjust.models import (
    AdjustableCamera,
    CsmParameterization,
    Evaluation,
    LineScanParameterization,
    parameterize,
)
from planetref.adjust.network_file import NetworkFile, read_network
from planetref.adjust.rays import triangulate
from planetref.adjust.result import AdjustmentResult
from planetref.control.network import Network

__all__ = [
    "AdjustConfig",
    "AdjustableCamera",
    "AdjustmentResult",
    "CsmParameterization",
    "Evaluation",
    "LineScanParameterization",
    "Network",
    "NetworkFile",
    "adjust",
    "parameterize",
    "read_network",
    "triangulate",
    "validate_config",
]
