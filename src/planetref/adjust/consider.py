"""Correlated errors as *consider* parameters: the covariance of what the MCPs share.

The adjustment weights every MCP by its own random error. Errors that many MCPs share --
the reference ortho's offset over a patch of ground, a CCD's placement error that every
observation in it carries, a matcher's error common to the matches of one tile (its
window's sub-pixel phase, its homography) -- are not averaged away by the number of
MCPs, so a covariance that treats the MCPs as independent is too optimistic by about the
square root of their number. Consider analysis (Schmidt's "consider" covariance, as in
orbit determination) propagates such parameters ``z``, held at their nominal values with
a declared sigma, through the sensitivity of the estimate to them: ``c_hat - c = G z + noise`` with
``G = S^-1 d(rhs)/dz`` (:meth:`~planetref.adjust.statistics.StatisticsMixin.
consider_sensitivity`), so ``Cov(c) = sigma0^2 S^-1 + G Sigma_z G^T``. The estimate is
unchanged; a ground point of the image additionally moves with a CCD's offset directly
(:func:`planetref.adjust.precision.formal_ground_precision` adds that term; a tile's
offset is the matcher's error, not the image's geometry, and has no such term).

The reference's and the CCDs' sigmas are declared (their common part never shows in
the residuals); the tiles' is estimated from the tiles' residual sums
(:func:`estimate_key_sigma`): a tile's offset is partly left in its residuals, and how
much the sensitivity says.

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

__all__ = [
    "KINDS",
    "ConsiderLayout",
    "ConsiderSensitivity",
    "ConsiderTerms",
    "TileEstimate",
    "consider_layout",
    "estimate_key_sigma",
]


#: Consider-parameter kinds, in column order.
KINDS = ("reference", "ccd", "tile")


@dataclass(frozen=True)
class TileEstimate:
    """The per-tile matcher offsets' sigma, estimated from the tiles' residual sums.

    Attributes:
        sigma_px: Estimated sigma (line, sample), image pixels (0 where the residuals
            show no more than the other terms explain).
        n_tiles: Tiles with used observations.
        observed: ``u^T u`` per axis (the tiles' weighted residual sums squared, summed).
        expected_without: Its expectation without tile offsets (measurement noise and
            the declared consider terms), per axis.
        relative_sd: Approximate relative standard deviation of the variance estimate
            (Gaussian quadratic form): few tiles, a rough estimate.
        per_axis_px: The sigmas (line, sample) estimated per axis, for information.
        sums: The tiles' weighted residual sums ``u`` (line, sample alternating).
        response: Their response ``M`` to every consider parameter, ``(2 n_tiles, K)``.
    """

    sigma_px: tuple[float, float]
    n_tiles: int
    observed: tuple[float, float]
    expected_without: tuple[float, float]
    relative_sd: float
    per_axis_px: tuple[float, float] = (math.nan, math.nan)
    sums: F64 = field(default_factory=lambda: np.zeros(0), repr=False)
    response: F64 = field(default_factory=lambda: np.zeros((0, 0)), repr=False)


@dataclass(frozen=True)
class ConsiderLayout:
    """Where the consider parameters sit: patches of points, keys of observations.

    Columns: ``2 n_patches`` reference-patch offsets (east, north), then per observation
    key kind (``"ccd"``, ``"tile"``, in that order) two columns (line, sample) per key.

    Attributes:
        point_patch: Patch index per point (-1: none), ``(P,)``.
        n_patches: Number of patches.
        obs_keys: Per key kind present, ``(kind, key per observation (-1: none), n_keys)``.
        names: Per column, its name.
        units: Per column, ``"m"`` or ``"px"``.
        kinds: Per column, its kind (:data:`KINDS`).
        sigma: Per column, the declared sigma (0 for a sigma still to estimate).
        ccd: Per column ``(camera_id, ccd, axis)`` of a CCD offset, else ``None``.
    """

    point_patch: NDArray[np.intp]
    n_patches: int
    obs_keys: tuple[tuple[str, NDArray[np.intp], int], ...]
    names: list[str]
    units: list[str]
    kinds: list[str]
    sigma: F64
    ccd: list[tuple[str, str, int] | None]

    @property
    def n_columns(self) -> int:
        """``K``."""
        return len(self.names)

    def columns(self, kind: str) -> slice:
        """The columns of one kind (an empty slice when absent)."""
        idx = [i for i, k in enumerate(self.kinds) if k == kind]
        return slice(idx[0], idx[-1] + 1) if idx else slice(0, 0)

    def keys(self) -> list[tuple[str, NDArray[np.intp], int]]:
        """Per observation key kind ``(kind, key per observation, first column)``."""
        return [(k, key, self.columns(k).start) for k, key, _ in self.obs_keys]


@dataclass(frozen=True)
class ConsiderSensitivity:
    """What one pass over the solution gives of the consider parameters.

    Attributes:
        g: ``d(adjusted parameter)/d(consider parameter)``, ``(p, K)``.
        response: ``D_T^T P R D`` of the estimated kind's columns ``T``, ``(|T|, K)``, or
            ``None`` (see :meth:`~planetref.adjust.statistics.StatisticsMixin.
            consider_sensitivity`).
        sums: ``D_T^T P v``: the weighted residual sums of those columns, or ``None``.
    """

    g: F64
    response: F64 | None = None
    sums: F64 | None = None


@dataclass(frozen=True)
class ConsiderTerms:
    """The consider parameters of an adjustment and their effect on its parameters.

    Attributes:
        names: One per consider parameter (``"reference patch 3 east"``,
            ``"strip1/ccd2 line offset"``, ``"strip1 tile 4 sample offset"``).
        units: ``"m"`` (reference patches) or ``"px"`` (CCD and tile offsets) per parameter.
        sigma: Declared (or estimated) sigma per parameter.
        sensitivity: ``d(adjusted parameter)/d(consider parameter)``, ``(p, K)``.
        ccd: Per parameter ``(camera_id, ccd, axis)`` of a CCD offset (axis 0 line, 1
            sample), ``None`` for a reference patch or a tile.
        patch_m: Patch size (m), for the report.
        n_patches: Number of reference patches with MCPs.
        kinds: Per parameter its kind (:data:`KINDS`).
        tile: The tile offsets' estimate, when estimated.
        point_patch: Reference patch of each network point (-1: none), ``(P,)``.
    """

    names: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    sigma: F64 = field(default_factory=lambda: np.zeros(0))
    sensitivity: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    ccd: list[tuple[str, str, int] | None] = field(default_factory=list)
    patch_m: float = math.nan
    n_patches: int = 0
    kinds: list[str] = field(default_factory=list)
    tile: TileEstimate | None = None
    point_patch: NDArray[np.intp] | None = field(default=None, repr=False)

    @property
    def column_kinds(self) -> list[str]:
        """Per parameter its kind (:data:`KINDS`).

        Terms saved before kinds existed had reference patches (unit ``"m"``) and CCD
        offsets only.
        """
        return self.kinds or ["reference" if u == "m" else "ccd" for u in self.units]

    @property
    def covariance(self) -> F64:
        """``G Sigma_z G^T``: their share of the parameters' covariance, ``(p, p)``."""
        g = self.sensitivity
        return (g * self.sigma**2) @ g.T

    def summary(self) -> dict[str, Any]:
        """What report.json says of them."""
        kinds = self.column_kinds
        ref = [s for s, k in zip(self.sigma, kinds, strict=True) if k == "reference"]
        ccd = [s for s, k in zip(self.sigma, kinds, strict=True) if k == "ccd"]
        n_tile = sum(1 for k in kinds if k == "tile") // 2
        tile = self.tile
        t0 = kinds.index("tile") if n_tile else -1
        tile_sigma = (
            [float(v) for v in tile.sigma_px]
            if tile is not None
            else ([float(self.sigma[t0]), float(self.sigma[t0 + 1])] if n_tile else None)
        )
        return {
            "reference_sigma_m": float(ref[0]) if ref else None,
            "reference_patch_m": self.patch_m if ref else None,
            "n_reference_patches": self.n_patches,
            "ccd_offset_sigma_px": float(ccd[0]) if ccd else None,
            "n_ccd_offsets": len(ccd) // 2,
            "tile_offset_sigma_px": tile_sigma,
            "tile_offset_source": None if not n_tile else ("estimated" if tile else "declared"),
            "n_tile_offsets": n_tile,
            # Infinite where the estimate is 0 (no signal): JSON has no infinity.
            "tile_offset_relative_sd": (
                float(tile.relative_sd)
                if tile is not None and math.isfinite(tile.relative_sd)
                else None
            ),
            "tile_offset_per_axis_px": (
                None if tile is None else [float(v) for v in tile.per_axis_px]
            ),
        }


def consider_layout(
    net: Network,
    cfg: SystematicConfig,
    weighted_mcp: NDArray[np.bool_],
    placement_estimated: list[bool],
    used: NDArray[np.bool_] | None = None,
) -> ConsiderLayout:
    """Patches of the MCPs and keys of the CCDs and tiles that carry consider parameters.

    Args:
        net: The network.
        cfg: Declared accuracies.
        weighted_mcp: Per point, a weighted MCP (its a-priori coordinates come from the
            reference).
        placement_estimated: Per camera, its CCD placement is adjusted (no CCD offsets).
        used: Per observation, used by the solution (tiles are numbered over the used
            observations only: a held-out tile has no column); ``None``: all.

    Returns:
        The layout; tile columns carry sigma 0 when their sigma is to be estimated.
    """
    names: list[str] = []
    units: list[str] = []
    kinds: list[str] = []
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
                kinds.append("reference")
                sigma.append(s_ref)
                ccd.append(None)
    obs_keys: list[tuple[str, NDArray[np.intp], int]] = []
    s_ccd = cfg.ccd_offset_sigma_px or 0.0
    if s_ccd > 0:
        obs_key = np.full(net.n_obs, -1, np.intp)
        n_keys = 0
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
                    kinds.append("ccd")
                    sigma.append(s_ccd)
                    ccd.append((net.camera_ids[ci], name, axis))
        if n_keys:
            obs_keys.append(("ccd", obs_key, n_keys))
    s_tile = cfg.tile_offset_sigma_px
    tile = np.asarray(net.obs_tile)
    on_tile = (tile >= 0) & (np.ones(net.n_obs, bool) if used is None else used)
    if s_tile is not None and s_tile != 0 and np.any(on_tile):
        ids, key = np.unique(tile[on_tile], return_inverse=True)
        obs_key = np.full(net.n_obs, -1, np.intp)
        obs_key[on_tile] = key.ravel()
        value = 0.0 if s_tile == "estimate" else float(s_tile)
        first = np.flatnonzero(on_tile)[np.unique(key.ravel(), return_index=True)[1]]
        for k, t in enumerate(ids):
            cam_id = net.camera_ids[int(net.obs_camera[first[k]])]
            for ax in ("line", "sample"):
                names.append(f"{cam_id} tile {int(t)} {ax} offset")
                units.append("px")
                kinds.append("tile")
                sigma.append(value)
                ccd.append(None)
        obs_keys.append(("tile", obs_key, len(ids)))
    return ConsiderLayout(
        point_patch=point_patch,
        n_patches=n_patches,
        obs_keys=tuple(obs_keys),
        names=names,
        units=units,
        kinds=kinds,
        sigma=np.asarray(sigma, np.float64),
        ccd=ccd,
    )


def estimate_key_sigma(
    sens: ConsiderSensitivity,
    layout: ConsiderLayout,
    kind: str,
    sigma0: float,
    per_axis: bool = False,
) -> TileEstimate:
    """The sigma of one key kind's offsets (the same on both axes) from its residual sums.

    Method of moments (the variance-component estimator of a random effect): with ``u``
    the keys' weighted residual sums and ``M`` their response to every consider
    parameter (:class:`ConsiderSensitivity`), ``E[u_a^T u_a] = sigma0^2 tr(M_aa) +
    sum_j sigma_j^2 |M_aj|^2`` per axis ``a``, ``j`` over the other kinds' declared
    parameters and the keys' own (line and sample). One variance for both axes is
    solved from the two equations' sum, non-negative: with a dozen tiles the per-axis
    variances (kept as ``per_axis_px``, from the 2 x 2 system) are too rough to tell
    the axes apart (XFeat-LighterGlue on hiric-strip ``moderate``: 1.07 and 0.0 px
    where the truth's tile means scatter by 0.7 and 0.8 px). An offset that the cameras
    absorb (a common one, or one that the orientation nodes fit) leaves no residual and
    is not seen: the estimate is what the residuals show, scaled by how much of an
    offset they keep.

    Args:
        sens: The sensitivity with ``response`` of ``kind``.
        layout: The layout.
        kind: The key kind (``"tile"``).
        sigma0: The measurements' sigma (their covariance ``sigma0^2 P^-1``).
        per_axis: Use the per-axis sigmas instead of the pooled one.
    """
    from scipy.optimize import nnls

    cols = layout.columns(kind)
    if sens.response is None or sens.sums is None:
        raise ValueError("the sensitivity has no response; pass response=kind")
    m = sens.response
    u = sens.sums
    n = cols.stop - cols.start
    own = np.zeros(layout.n_columns, bool)
    own[cols] = True
    line_cols = np.arange(cols.start, cols.stop, 2)
    samp_cols = line_cols + 1
    declared = layout.sigma**2 * ~own
    a = np.zeros((2, 2))
    rhs = np.zeros(2)
    base = np.zeros(2)
    seen = np.zeros(2)
    for ax in range(2):
        rows = np.arange(ax, n, 2)
        mr = m[rows]
        seen[ax] = float(u[rows] @ u[rows])
        base[ax] = sigma0**2 * float(np.trace(mr[:, rows + cols.start])) + float(
            np.sum(mr**2 @ declared)
        )
        a[ax] = [np.sum(mr[:, line_cols] ** 2), np.sum(mr[:, samp_cols] ** 2)]
        rhs[ax] = seen[ax] - base[ax]
    ok = bool(np.all(np.isfinite(a)) and np.sum(a) > 0)
    axes = nnls(a, rhs)[0] if ok else np.zeros(2)
    pooled = max(float(np.sum(rhs)) / float(np.sum(a)), 0.0) if ok else 0.0
    var = axes if per_axis else np.array([pooled, pooled])
    # Relative SD of the sum of squares (a Gaussian quadratic form: Var = 2 tr(Sigma_u^2)),
    # approximately that of the variance estimate it gives.
    own_var = np.zeros(layout.n_columns)
    own_var[line_cols], own_var[samp_cols] = var[0], var[1]
    cov_u = sigma0**2 * m[:, cols] + (m * (declared + own_var)) @ m.T
    signal = float(np.sum(a @ var))
    rel = math.sqrt(2.0 * float(np.sum(cov_u * cov_u.T))) / signal if signal > 0 else math.inf
    return TileEstimate(
        sigma_px=(float(math.sqrt(var[0])), float(math.sqrt(var[1]))),
        n_tiles=n // 2,
        observed=(float(seen[0]), float(seen[1])),
        expected_without=(float(base[0]), float(base[1])),
        relative_sd=rel,
        per_axis_px=(float(math.sqrt(axes[0])), float(math.sqrt(axes[1]))),
        sums=u,
        response=m,
    )
