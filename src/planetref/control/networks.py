"""The adjustment networks of a georef run: a strip's MCPs and the joint campaign network.

:class:`StripMcps` is a strip after matching (camera, images, MCP table, check flags,
CCD-overlap ties); :func:`mcp_ground_sigmas` gives the a-priori weights of its MCPs'
ground points, :func:`joint_network` builds one network of every strip's camera, all
MCPs and the tie points between strips (``[campaign] adjust_together``) and
:func:`with_overlap_ties` adds the tie points between the overlapping CCDs of a strip
(``[frontend.ccd_overlap]``) to either network.
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
    from planetref.frontend.config import CampaignOptions, CcdOverlapConfig
    from planetref.frontend.overlap import OverlapTies
    from planetref.frontend.tiepoints import TiePoints
    from planetref.raster.image import CcdImage

__all__ = [
    "OVERLAP_PLANIMETRIC_SIGMA_M",
    "GroundSigmas",
    "McpSet",
    "StripMcps",
    "check_points",
    "joint_network",
    "mcp_ground_sigmas",
    "template_overlap",
    "template_support_m",
    "with_overlap_ties",
]


@dataclass(frozen=True)
class GroundSigmas:
    """A-priori sigmas of the MCPs' ground points.

    Attributes:
        sigma_m: ``(N, 3)`` sigmas (metres) along east, north, up (``local``) or X, Y, Z.
        local: The sigmas are along the local east, north, up axes.
    """

    sigma_m: NDArray[np.float64]
    local: bool = True


@dataclass(frozen=True)
class McpSet:
    """A strip's MCPs as the adjustment takes them: table, check flags, ground sigmas.

    Attributes:
        strip: The strip (camera id of its observations).
        table: The MCP table (:func:`~planetref.control.mcp.mcps_from_tiles`).
        check: Held-out check flag per MCP (:func:`check_points`).
        ground_sigma: The ground points' a-priori sigmas, or ``None`` (known ground).
    """

    strip: str
    table: McpTable
    check: NDArray[np.bool_]
    ground_sigma: GroundSigmas | None

    @classmethod
    def of(cls, strip: str, table: McpTable, check: NDArray[np.bool_]) -> McpSet:
        """The set of a table and its check flags, with the table's ground sigmas."""
        return cls(strip, table, np.asarray(check, bool), mcp_ground_sigmas(table))

    @classmethod
    def held_out(cls, strip: str, table: McpTable, options: McpOptions) -> McpSet:
        """The set of a table with its check points chosen by ``[mcp]`` (:func:`check_points`)."""
        check = check_points(
            table["tile_id"],
            table["ccd"],
            options.check_fraction,
            options.min_mcps,
            options.seed,
            options.check_blocks,
            line=table["line"],
        )
        return cls.of(strip, table, check)

    def __len__(self) -> int:
        return len(self.table)

    def network(
        self, camera: Camera, sigma_px: float, xyz: NDArray[np.float64] | None = None
    ) -> Network:
        """The one-strip network of these MCPs.

        Args:
            camera: The strip's camera.
            sigma_px: Each measure's sigma (px).
            xyz: ``(N, 3)`` ground points in place of the table's (e.g. the same MCPs
                on redrawn reference errors); ``None``: the table's.
        """
        from planetref.control.network import Network

        t = self.table
        gs = self.ground_sigma
        return Network.mcps(
            camera,
            line=t["line"],
            sample=t["sample"],
            xyz=t.xyz() if xyz is None else xyz,
            ccd=np.asarray(t["ccd"]).astype(str),
            camera_id=self.strip,
            sigma_px=sigma_px,
            check=self.check,
            ground_sigma_m=0.0 if gs is None else gs.sigma_m,
            ground_sigma_local=False if gs is None else gs.local,
            tile=np.asarray(t["tile_id"]).astype(str),
        )


@dataclass(frozen=True)
class StripMcps:
    """A strip after matching: its camera, images, MCPs and CCD-overlap ties.

    Attributes:
        id: The strip.
        camera: Its camera (initial).
        images: CCD name -> image.
        sizes: CCD name -> ``(lines, samples)``.
        mcps: Its MCPs, check flags and ground sigmas.
        overlap: Its tie points between overlapping CCDs (``[frontend.ccd_overlap]``),
            or ``None`` (not enabled).
    """

    id: str
    camera: Camera
    images: dict[str, CcdImage]
    sizes: dict[str, tuple[int, int]]
    mcps: McpSet
    overlap: OverlapTies | None = None


def mcp_ground_sigmas(table: Any) -> GroundSigmas | None:
    """MCP ground points' a-priori sigmas (east, north, up) if the table has them."""
    cols = getattr(table, "columns", {})
    if "sigma_ground_xy_m" not in cols or "sigma_ground_h_m" not in cols:
        return None
    xy = np.asarray(cols["sigma_ground_xy_m"], float)
    h = np.asarray(cols["sigma_ground_h_m"], float)
    return GroundSigmas(np.column_stack([xy, xy, h]), local=True)


def check_points(
    tile_id: Any,
    ccd: Any,
    fraction: float,
    min_mcps: int,
    seed: int,
    blocks: str = "tiles",
    line: Any = None,
) -> NDArray[np.bool_]:
    """The MCPs held out as check points.

    ``tiles``: whole tiles in a seeded random order until at least ``fraction`` of the
    MCPs are held out. A tile is skipped when holding it would

    * leave fewer than ``min_mcps`` adjusted MCPs or a CCD without any;
    * take the held-out share beyond ``2 x fraction`` (a few large tiles would otherwise
      hold out half the MCPs: on ``tiny`` ``hard`` XFeat* gave 6 tiles of 4-99 MCPs and
      the old rule held out 121 of 263 for a 10 % target);
    * (with ``line``) leave the lines it spans with fewer adjusted MCPs, over all CCDs,
      than half the MCPs there: a held-out tile must not take away the control of the
      part of the strip it checks, or the adjustment there is an extrapolation whose
      error rests on one or two random quantities (that XFeat* case: the second half of
      the strip kept 4 MCPs of 125, formal 36 m and true 13 m, with true / formal
      spreading 0.4-3.3 over redrawn reference errors in the same layout);
    * (with ``line``) span lines that a tile already held out spans: two CCDs' tiles of
      the same lines held out leave those lines to one CCD, whose few hundred pixels
      across the track hardly fix the strip's yaw there (XFeat* with NCC refinement on
      ``tiny``: ccd1's and ccd3's first tiles held out, true error 8.0 m against 3.5 m
      with ccd2's second tile held out).

    When no tile fits under the share's cap, the smallest tile that passes the other
    rules is held out. ``random``: ``round(fraction * n)`` single MCPs (when
    ``min_mcps`` remain).

    Args:
        tile_id: Tile of each MCP.
        ccd: CCD of each MCP.
        fraction: Share to hold out.
        min_mcps: Fewest MCPs the adjustment needs.
        seed: Seed of the draw.
        blocks: ``"tiles"`` or ``"random"``.
        line: Image line of each MCP (px), or ``None`` (no along-track rule).
    """
    tiles = np.asarray(tile_id).astype(str)
    ccds = np.asarray(ccd).astype(str)
    n = len(tiles)
    check = np.zeros(n, bool)
    target = round(fraction * n)
    rng = np.random.default_rng(seed)
    if not target or n - target < min_mcps:
        return check
    if blocks == "random":
        check[rng.choice(n, target, replace=False)] = True
        return check
    names, code = np.unique(tiles, return_inverse=True)
    lines = None if line is None else np.asarray(line, np.float64)

    def allowed(on: NDArray[np.bool_]) -> bool:
        rest = ~check & ~on
        if np.count_nonzero(rest) < min_mcps:
            return False
        if any(not np.any(rest & (ccds == c)) for c in np.unique(ccds[on])):
            return False
        if lines is not None:
            lo, hi = float(np.min(lines[on])), float(np.max(lines[on]))
            span = (lines >= lo) & (lines <= hi)
            if 2 * np.count_nonzero(span & rest) < np.count_nonzero(span):
                return False
            if np.any(check & span) or any(a <= hi and lo <= b for a, b in held_spans):
                return False
        return True

    def hold(on: NDArray[np.bool_]) -> None:
        check[on] = True
        if lines is not None:
            held_spans.append((float(np.min(lines[on])), float(np.max(lines[on]))))

    held_spans: list[tuple[float, float]] = []

    cap = 2 * target
    for t in rng.permutation(len(names)):
        if np.count_nonzero(check) >= target:
            break
        on = code == t
        if np.count_nonzero(check) + np.count_nonzero(on) > cap or not allowed(on):
            continue
        hold(on)
    if not np.any(check):
        sizes = np.bincount(code, minlength=len(names))
        for t in np.argsort(sizes, kind="stable"):
            on = code == t
            if allowed(on):
                hold(on)
                break
    return check


def template_support_m(
    name: str, options: Any, fine_upsample: int, ref_gsd_m: float
) -> float | None:
    """Ground size (m) of the pixels one match is computed from, for area-based matchers.

    A matcher that declares a :attr:`~planetref.matching.base.BaseMatcher.support_option`
    (NCC: a square template of ``2 t + 1`` fine-grid pixels, ``ref_gsd_m /
    fine_upsample`` each) computes neighbouring dense matches from shared pixels, so
    their errors are not independent. Feature matchers declare none: ``None`` (their
    keypoints are sparse; the descriptors' supports seldom overlap).

    Args:
        name: Registry name of the matcher.
        options: Its fine-stage options (fine-grid pixels).
        fine_upsample: The fine grid's factor over the reference grid.
        ref_gsd_m: The reference's ground sampling distance (m).
    """
    from planetref.matching.registry import MATCHERS

    spec = MATCHERS.get(name)
    option = (
        None if spec is None or spec.load_class is None else spec.matcher_class().support_option
    )
    if option is None or option not in options:
        return None
    return (2 * int(options[option]) + 1) * ref_gsd_m / max(int(fine_upsample), 1)


def template_overlap(ref_x: Any, ref_y: Any, support_m: float | None) -> float:
    """Mean number of MCPs per independent measurement (1: independent), from their overlap.

    Two matches whose square supports of side ``support_m`` overlap by a fraction
    ``rho = (1 - |dx|/T)(1 - |dy|/T)`` of their pixels share that fraction of their
    error (a correlation model of area-based matching). The mean over the MCPs of
    ``sum_j rho_ij`` (itself included) is the factor ``N / N_eff`` by which the
    measurements' covariance of a least-squares estimate from them is too small when
    they are taken as independent. Computed on a grid of ``T / 8`` cells with the
    triangle kernel (exact to the cell size).
    """
    x = np.asarray(ref_x, float)
    y = np.asarray(ref_y, float)
    if support_m is None or not support_m > 0 or x.size < 2:
        return 1.0
    from scipy.signal import fftconvolve

    cell = support_m / 8.0
    ix = np.floor((x - x.min()) / cell).astype(np.intp)
    iy = np.floor((y - y.min()) / cell).astype(np.intp)
    hist = np.zeros((int(iy.max()) + 1, int(ix.max()) + 1))
    np.add.at(hist, (iy, ix), 1.0)
    k = np.arange(-8, 9)
    tri = np.clip(1.0 - np.abs(k) / 8.0, 0.0, None)
    dens = fftconvolve(hist, np.outer(tri, tri), mode="same")
    return float(max(np.mean(dens[iy, ix]), 1.0))


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
    tile: list[str | None] = []
    xyz: dict[str, NDArray[np.float64]] = {}
    sig_m: dict[str, float] = {}
    kind: dict[str, str] = {}
    local: dict[str, bool] = {}
    for p in preps:
        t = p.mcps.table
        pts = [f"{p.id}:mcp{i}" for i in range(len(t))]
        pxyz = t.xyz()
        gs = p.mcps.ground_sigma
        for i, pid in enumerate(pts):
            xyz[pid], kind[pid] = pxyz[i], "mcp"
            sig_m[pid] = 0.0 if gs is None else gs.sigma_m[i]
            local[pid] = gs is not None and gs.local
        obs_cam += [p.id] * len(t)
        obs_pt += pts
        obs_ccd += list(np.asarray(t["ccd"]).astype(str))
        line.append(np.asarray(t["line"], float))
        sample.append(np.asarray(t["sample"], float))
        sig_px.append(np.full(len(t), mcp.sigma_px))
        check.append(p.mcps.check)
        tile += list(np.asarray(t["tile_id"]).astype(str))
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
        tile += [None, None]
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
        tile=tile,
    )


OVERLAP_PLANIMETRIC_SIGMA_M = 1000.0
"""A-priori sigma (m) of a CCD-overlap tie point's east and north (its rays decide them)."""


def with_overlap_ties(network: Network, ties: OverlapTies, cfg: CcdOverlapConfig) -> Network:
    """``network`` with the tie points between the overlapping CCDs of one strip added.

    Each tie is a point of kind ``"overlap"`` observed twice by the strip's camera (its two
    CCDs), with sigma ``cfg.sigma_px`` per measure; its ground is the reference DEM under
    the first CCD's ray, weighted by ``cfg.height_sigma_m`` in height (the two rays cross
    at the stagger angle only) and by :data:`OVERLAP_PLANIMETRIC_SIGMA_M` in east and
    north (the rays fix them to a fraction of a pixel; the loose sigma keeps every tie
    point determined whatever the outlier rule leaves of its rays). Each CCD pair's
    median offset from the camera's prediction (the CCDs' relative placement and lens,
    which the camera model does not estimate) is taken off the second CCD's measures,
    so the ties constrain only how that offset varies along the strip (and a constant
    CCD offset does not reach them: the adjustment's consider analysis gives their
    observations no CCD-offset term). The network's own points and observations come
    first, unchanged.

    Args:
        network: A strip's or a campaign's network (the strip's camera among its cameras).
        ties: The strip's overlap ties (:func:`planetref.frontend.overlap.find_overlap_ties`).
        cfg: Their sigmas.

    Raises:
        InputError: The strip's camera is not in the network, or a tie names a CCD it
            lacks.
    """
    from dataclasses import replace

    from planetref.errors import InputError

    t = len(ties)
    if not t:
        return network
    if ties.strip not in network.camera_ids:
        raise InputError(
            f"CCD-overlap ties of strip {ties.strip!r}: no such camera in the network "
            f"(it has {list(network.camera_ids)})",
            field="ccd_overlap",
        )
    ci = network.camera_ids.index(ties.strip)
    names = list(network.cameras[ci].ccd_names)
    unknown = sorted(set(np.unique(ties.ccd)) - set(names))
    if unknown:
        raise InputError(
            f"CCD-overlap ties of strip {ties.strip!r}: unknown CCD(s) {unknown} "
            f"(the camera has {names})",
            field="ccd_overlap",
        )
    # Each pair's constant offset from the prediction is the CCDs' relative placement
    # (and lens): nothing the attitude can explain, and nothing the camera model
    # estimates. Left in, it pulled the attitude into a rate that fits it; removed, the
    # ties carry the offsets' variation along the strip: the attitude's (jitter's)
    # change over the stagger time.
    line_b, sample_b = ties.line[:, 1].copy(), ties.sample[:, 1].copy()
    off = ties.offset_from_prediction
    for pair in {(str(a), str(b)) for a, b in ties.ccd}:
        on = (ties.ccd[:, 0] == pair[0]) & (ties.ccd[:, 1] == pair[1])
        line_b[on] -= np.median(off[on, 0])
        sample_b[on] -= np.median(off[on, 1])
    p0 = network.n_points
    sig = np.tile(
        [OVERLAP_PLANIMETRIC_SIGMA_M, OVERLAP_PLANIMETRIC_SIGMA_M, cfg.height_sigma_m], (t, 1)
    )
    local = np.broadcast_to(np.asarray(network.point_sigma_local, bool), (p0,))
    ccd_index = np.array([[names.index(str(c)) for c in row] for row in ties.ccd], np.intp)
    return replace(
        network,
        point_ids=np.concatenate([network.point_ids, np.array(ties.point_ids, dtype=str)]),
        point_xyz=np.concatenate([network.point_xyz, ties.xyz]),
        point_sigma_m=np.concatenate([network.point_sigma_m, sig]),
        point_kind=np.concatenate([network.point_kind, np.full(t, "overlap")]),
        point_sigma_local=np.concatenate([local, np.ones(t, bool)]),
        obs_camera=np.concatenate([network.obs_camera, np.full(2 * t, ci, np.intp)]),
        obs_ccd=np.concatenate([network.obs_ccd, ccd_index.ravel()]),
        obs_point=np.concatenate([network.obs_point, p0 + np.repeat(np.arange(t), 2)]),
        obs_line=np.concatenate(
            [network.obs_line, np.column_stack([ties.line[:, 0], line_b]).ravel()]
        ),
        obs_sample=np.concatenate(
            [network.obs_sample, np.column_stack([ties.sample[:, 0], sample_b]).ravel()]
        ),
        obs_sigma_px=np.concatenate(
            [network.obs_sigma_px, np.full((2 * t, 2), float(cfg.sigma_px))]
        ),
        obs_check=np.concatenate([network.obs_check, np.zeros(2 * t, bool)]),
        obs_tile=np.concatenate([network.obs_tile, np.full(2 * t, -1, np.intp)]),
        obs_ids=np.concatenate(
            [network.obs_ids, np.array([f"{p}/{k}" for p in ties.point_ids for k in "ab"])]
        ),
    )
