"""Correlated errors as *consider* parameters: the covariance of what the MCPs share.

The adjustment weights every MCP by its own random error. Errors that many MCPs share --
the reference ortho's offset over a patch of ground, a CCD's placement error that every
observation in it carries -- are not averaged away by the number of MCPs, so a covariance
that treats the MCPs as independent is too optimistic by about the square root of their
number. Consider analysis (Schmidt's "consider" covariance, as in orbit determination)
propagates such parameters ``z``, held at their nominal values with a declared sigma,
through the sensitivity of the estimate to them: ``c_hat - c = G z + noise`` with
``G = S^-1 d(rhs)/dz`` (:meth:`~planetref.adjust.statistics.StatisticsMixin.
consider_sensitivity`), so ``Cov(c) = sigma0^2 S^-1 + G Sigma_z G^T``. The estimate is
unchanged; a ground point of the image additionally moves with a CCD's offset directly
(:func:`planetref.adjust.precision.formal_ground_precision` adds that term).

Why consider parameters and not estimated nuisance offsets: an offset common to a
patch and a camera's position are nearly the same unknown (a shift of the whole strip's
ground); estimating both with a prior gives the camera the same covariance up to the
(small) efficiency gain of down-weighting crowded patches, while the consider form adds
no unknowns to the compiled point elimination and costs one linearisation at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import SystematicConfig
from planetref.arrays import F64
from planetref.control.network import Network, enu_rotation

__all__ = ["ConsiderTerms", "consider_layout"]


@dataclass(frozen=True)
class ConsiderTerms:
    """The consider parameters of an adjustment and their effect on its parameters.

    Attributes:
        names: One per consider parameter (``"reference patch 3 east"``,
            ``"strip1/ccd2 line offset"``).
        units: ``"m"`` (reference patches) or ``"px"`` (CCD offsets) per parameter.
        sigma: Declared sigma per parameter.
        sensitivity: ``d(adjusted parameter)/d(consider parameter)``, ``(p, K)``.
        ccd: Per parameter ``(camera_id, ccd, axis)`` of a CCD offset (axis 0 line, 1
            sample), ``None`` for a reference patch.
        patch_m: Patch size (m), for the report.
        n_patches: Number of reference patches with MCPs.
    """

    names: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    sigma: F64 = field(default_factory=lambda: np.zeros(0))
    sensitivity: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    ccd: list[tuple[str, str, int] | None] = field(default_factory=list)
    patch_m: float = math.nan
    n_patches: int = 0

    @property
    def covariance(self) -> F64:
        """``G Sigma_z G^T``: their share of the parameters' covariance, ``(p, p)``."""
        g = self.sensitivity
        return (g * self.sigma**2) @ g.T

    def summary(self) -> dict[str, Any]:
        """What report.json says of them."""
        ref = [s for s, u in zip(self.sigma, self.units, strict=True) if u == "m"]
        ccd = [s for s, u in zip(self.sigma, self.units, strict=True) if u == "px"]
        return {
            "reference_sigma_m": float(ref[0]) if ref else None,
            "reference_patch_m": self.patch_m if ref else None,
            "n_reference_patches": self.n_patches,
            "ccd_offset_sigma_px": float(ccd[0]) if ccd else None,
            "n_ccd_offsets": len(ccd) // 2,
        }


def consider_layout(
    net: Network,
    cfg: SystematicConfig,
    weighted_mcp: NDArray[np.bool_],
    placement_estimated: list[bool],
) -> tuple[NDArray[np.intp], int, NDArray[np.intp], int, list[str], list[str], F64, list[Any]]:
    """Patches of the MCPs and keys of the CCDs that carry consider parameters.

    Args:
        net: The network.
        cfg: Declared accuracies.
        weighted_mcp: Per point, a weighted MCP (its a-priori coordinates come from the
            reference).
        placement_estimated: Per camera, its CCD placement is adjusted (no CCD offsets).

    Returns:
        ``(point_patch, n_patches, obs_key, n_keys, names, units, sigma, ccd)``: patch index
        per point (-1: none), key index per observation (-1: none), and per consider
        parameter its name, unit, sigma and CCD (see :class:`ConsiderTerms`).
    """
    names: list[str] = []
    units: list[str] = []
    sigma: list[float] = []
    ccd: list[Any] = []
    point_patch = np.full(net.n_points, -1, np.intp)
    n_patches = 0
    s_ref = cfg.reference_sigma_m or 0.0
    if s_ref > 0 and np.any(weighted_mcp):
        idx = np.flatnonzero(weighted_mcp)
        xyz = net.point_xyz[idx]
        centre = np.mean(xyz, axis=0)
        rot = enu_rotation(centre[None])[0]
        en = (xyz - centre) @ rot[:2].T  # east, north (m) in the centre's tangent plane
        size = cfg.patch_m
        cell = np.floor(en / size).astype(np.int64)
        _, inv = np.unique(cell, axis=0, return_inverse=True)
        point_patch[idx] = inv.ravel()
        n_patches = int(inv.max()) + 1
        for k in range(n_patches):
            for ax in ("east", "north"):
                names.append(f"reference patch {k} {ax}")
                units.append("m")
                sigma.append(s_ref)
                ccd.append(None)
    obs_key = np.full(net.n_obs, -1, np.intp)
    n_keys = 0
    s_ccd = cfg.ccd_offset_sigma_px or 0.0
    if s_ccd > 0:
        # CCD-overlap ties (kind "overlap") carry no CCD offset: each CCD pair's median
        # offset is taken off their measures (control.networks.with_overlap_ties), which
        # takes a constant offset of either CCD off with it; propagated through the ties
        # (hundreds of precise measures) it would move the attitude by what the ties
        # never see (tiny, sift: formal 6.6 m against a true 1.7 m).
        tied = net.is_kind("overlap")[net.obs_point]
        for ci, cam in enumerate(net.cameras):
            if placement_estimated[ci]:
                continue
            on_cam = (net.obs_camera == ci) & ~tied
            for k, name in enumerate(cam.ccd_names):
                on = on_cam & (net.obs_ccd == k)
                if not np.any(on):
                    continue
                obs_key[on] = n_keys
                n_keys += 1
                for axis, ax in enumerate(("line", "sample")):
                    label = net.camera_ids[ci] if len(cam.ccd_names) == 1 else name
                    names.append(f"{net.camera_ids[ci]}/{label} {ax} offset")
                    units.append("px")
                    sigma.append(s_ccd)
                    ccd.append((net.camera_ids[ci], name, axis))
    return (
        point_patch,
        n_patches,
        obs_key,
        n_keys,
        names,
        units,
        np.asarray(sigma, np.float64),
        ccd,
    )
