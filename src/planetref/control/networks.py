"""The adjustment networks of a georef run: a strip's MCPs and the joint campaign network.

:class:`StripMcps` is a strip after matching (camera, images, MCP table, check flags);
:func:`mcp_ground_sigmas` gives the a-priori weights of its MCPs' ground points and
:func:`joint_network` builds one network of every strip's camera, all MCPs and the tie
points between strips (``[campaign] adjust_together``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.control.config import McpOptions
    from planetref.control.mcp import McpTable
    from planetref.control.network import Network
    from planetref.frontend.config import CampaignOptions
    from planetref.frontend.tiepoints import TiePoints
    from planetref.raster.image import CcdImage

__all__ = ["StripMcps", "joint_network", "mcp_ground_sigmas"]


@dataclass
class StripMcps:
    """A strip after matching: its camera, images, MCPs and check flags."""

    id: str
    camera: Camera
    images: dict[str, CcdImage]
    sizes: dict[str, tuple[int, int]]
    table: McpTable
    check: NDArray[np.bool_]
    out: dict[str, Any]


def mcp_ground_sigmas(table: Any) -> dict[str, Any]:
    """MCP ground points weighted by their a-priori sigmas (east, north, up) if known."""
    cols = getattr(table, "columns", {})
    if "sigma_ground_xy_m" not in cols or "sigma_ground_h_m" not in cols:
        return {}
    xy = np.asarray(cols["sigma_ground_xy_m"], float)
    h = np.asarray(cols["sigma_ground_h_m"], float)
    return {"ground_sigma_m": np.column_stack([xy, xy, h]), "ground_sigma_local": True}


def joint_network(
    preps: list[StripMcps], ties: TiePoints, mcp: McpOptions, opts: CampaignOptions
) -> Network:
    """One network of every strip's camera, all MCPs and the tie points between strips.

    Args:
        preps: The strips after matching.
        ties: Tie points between the strips.
        mcp: How MCPs enter (their image sigma).
        opts: The campaign's tie-point sigmas.
    """
    from planetref.control.network import Network

    obs_cam: list[str] = []
    obs_pt: list[str] = []
    obs_ccd: list[str] = []
    line: list[NDArray[np.float64]] = []
    sample: list[NDArray[np.float64]] = []
    sig_px: list[NDArray[np.float64]] = []
    check: list[NDArray[np.bool_]] = []
    xyz: dict[str, NDArray[np.float64]] = {}
    sig_m: dict[str, float] = {}
    kind: dict[str, str] = {}
    local: dict[str, bool] = {}
    for p in preps:
        t = p.table
        pts = [f"{p.id}:mcp{i}" for i in range(len(t))]
        pxyz = t.xyz()
        gs = mcp_ground_sigmas(t).get("ground_sigma_m")
        for i, pid in enumerate(pts):
            xyz[pid], kind[pid] = pxyz[i], "mcp"
            sig_m[pid] = 0.0 if gs is None else gs[i]
            local[pid] = gs is not None
        obs_cam += [p.id] * len(t)
        obs_pt += pts
        obs_ccd += list(np.asarray(t["ccd"]).astype(str))
        line.append(np.asarray(t["line"], float))
        sample.append(np.asarray(t["sample"], float))
        sig_px.append(np.full(len(t), mcp.sigma_px))
        check.append(p.check)
    tie_sigma = np.inf if opts.tie_sigma_m is None else float(opts.tie_sigma_m)
    for i, pid in enumerate(ties.point_ids):
        xyz[pid], sig_m[pid], kind[pid] = ties.xyz[i], tie_sigma, "tie"
        for k in range(2):
            obs_cam.append(str(ties.strip[i, k]))
            obs_pt.append(pid)
            obs_ccd.append(str(ties.ccd[i, k]))
        line.append(ties.line[i])
        sample.append(ties.sample[i])
        sig_px.append(np.full(2, opts.tie_sigma_px))
        check.append(np.zeros(2, bool))
    return Network.from_records(
        {p.id: p.camera for p in preps},
        obs_camera=obs_cam,
        obs_point=obs_pt,
        line=np.concatenate(line),
        sample=np.concatenate(sample),
        point_xyz=xyz,
        point_sigma_m=sig_m,
        point_kind=kind,
        obs_ccd=obs_ccd,
        sigma_px=np.concatenate(sig_px),
        check=np.concatenate(check),
        point_sigma_local=local,
    )
