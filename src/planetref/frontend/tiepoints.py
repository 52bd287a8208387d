"""Tie points between the strips of a campaign, for one joint adjustment.

For each pair of CCD images of *different* strips whose footprints (through the initial
cameras and the reference DEM) overlap on the reference grid, the overlap is cut into
windows of at most ``tie_window_ref_px``; in each window both images are orthorectified
onto the same reference-grid window (:func:`~planetref.frontend.orthorectify.orthorectify`),
the two orthos are matched with the run's matcher, the matches verified with RANSAC
(:func:`~planetref.frontend.robust.verify_points`) and a translation consensus, and
every inlier is mapped back to raw ``(line, sample)`` in both images
(:meth:`~planetref.frontend.orthorectify.OrthoTile.to_raw`). Its a-priori ground point is
the reference DEM under the mean map position of the two keypoints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.errors import PlanetrefError

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera, Terrain
    from planetref.frontend.config import CampaignOptions, FrontendConfig
    from planetref.matching.base import Matcher
    from planetref.raster.image import CcdImage
    from planetref.raster.ortho import ReferenceOrtho, RefWindow

    #: One side of a pair: the strip's camera, the CCD image, the CCD name.
    ImageRef = tuple[Camera, CcdImage, str]

__all__ = ["TiePoints", "find_tie_points"]

log = logging.getLogger(__name__)


@dataclass
class TiePoints:
    """Tie points of a campaign: two observations (one per strip) per point.

    Attributes:
        point_ids: Point id per tie point, ``(T,)``.
        xyz: A-priori body-fixed XYZ (m) from the reference DEM, ``(T, 3)``.
        strip: ``(T, 2)`` strip ids of the two observations.
        ccd: ``(T, 2)`` CCD names (the cameras' names).
        line: ``(T, 2)`` raw lines.
        sample: ``(T, 2)`` raw samples.
        pairs: Per image pair ``"stripA/ccdI~stripB/ccdJ"``: number of tie points.
    """

    point_ids: list[str] = field(default_factory=list)
    xyz: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    strip: NDArray[np.str_] = field(default_factory=lambda: np.zeros((0, 2), str))
    ccd: NDArray[np.str_] = field(default_factory=lambda: np.zeros((0, 2), str))
    line: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    sample: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    pairs: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.point_ids)

    def per_strip_pair(self) -> dict[str, int]:
        """Tie points per pair of strips ``"stripA~stripB"``."""
        out: dict[str, int] = {}
        for a, b in self.strip:
            key = f"{a}~{b}"
            out[key] = out.get(key, 0) + 1
        return out


def _ccd_window(
    camera: Camera, ccd: str, ref: ReferenceOrtho, dem: Terrain, points_per_edge: int
) -> RefWindow | None:
    from planetref.frontend.tiles import Tile, tile_footprint

    n_lines, n_samples = camera.image_size(ccd)
    fp = tile_footprint(
        camera, Tile(f"{ccd}:all", ccd, 0, 0, n_lines, n_samples), ref, dem, points_per_edge
    )
    return fp.window


def _overlap_windows(
    wa: RefWindow, wb: RefWindow, ref_shape: tuple[int, int], side: int, min_side: int
) -> list[RefWindow]:
    """The overlap of two full-resolution windows, clipped to the ortho, cut in windows."""
    from planetref.raster.ortho import RefWindow

    a, b = wa.bounds_px, wb.bounds_px
    c0, r0 = max(a[0], b[0], 0), max(a[1], b[1], 0)
    c1, r1 = min(a[2], b[2], ref_shape[1]), min(a[3], b[3], ref_shape[0])
    if c1 - c0 < min_side or r1 - r0 < min_side:
        return []
    nc = max(1, int(np.ceil((c1 - c0) / side)))
    nr = max(1, int(np.ceil((r1 - r0) / side)))
    ce = np.linspace(c0, c1, nc + 1).round().astype(int)
    re = np.linspace(r0, r1, nr + 1).round().astype(int)
    return [
        RefWindow.around(ce[i], re[j], ce[i + 1], re[j + 1]) for j in range(nr) for i in range(nc)
    ]


def _match_window(
    window: RefWindow,
    a: ImageRef,
    b: ImageRef,
    ref: ReferenceOrtho,
    dem: Terrain,
    matcher: Matcher,
    fe: FrontendConfig,
    opts: CampaignOptions,
) -> tuple[F64, F64, F64, F64, F64] | None:
    """Tie points of two CCD images in one window.

    Returns:
        ``(xyz, line_a, sample_a, line_b, sample_b)``, or None when the window gives too
        few verified matches.
    """
    from planetref.camera.mapping import map_to_ground
    from planetref.frontend.orthorectify import orthorectify
    from planetref.frontend.robust import robust_translation, spread_select, verify_points
    from planetref.frontend.tile import inference_mode

    sides = []
    for camera, image, ccd in (a, b):
        o = orthorectify(image, camera, ccd, ref, dem, window, lattice_step=fe.lattice_step_ref_px)
        if o.valid.mean() < 0.05 or o.valid.sum() < 256:
            return None
        sides.append(o)
    oa, ob = sides
    with inference_mode():
        m = matcher.match(oa.image, ob.image, oa.valid, ob.valid)
    kp0 = np.asarray(m.keypoints0, np.float64).reshape(-1, 2)
    kp1 = np.asarray(m.keypoints1, np.float64).reshape(-1, 2)
    conf = np.asarray(m.confidence, np.float64).reshape(-1)
    if len(kp0) < opts.tie_min_inliers:
        return None
    inl = verify_points(
        kp0,
        kp1,
        fe.ransac_model,
        fe.ransac_threshold_ref_px,
        fe.ransac_confidence,
        fe.ransac_max_iters,
    )
    if inl.sum() < opts.tie_min_inliers:
        return None
    idx = np.flatnonzero(inl)
    # Both orthos come from cameras with similar errors: true ties share one displacement.
    _, cons = robust_translation(kp1[idx] - kp0[idx], fe.fine_radius_ref_px, conf[idx])
    idx = idx[cons]
    if len(idx) < opts.tie_min_inliers:
        return None
    la, sa, oka = oa.to_raw(kp0[idx, 0], kp0[idx, 1])
    lb, sb, okb = ob.to_raw(kp1[idx, 0], kp1[idx, 1])
    ok = oka & okb
    for o, ln, sm in ((a, la, sa), (b, lb, sb)):
        n_lines, n_samples = o[0].image_size(o[2])
        with np.errstate(invalid="ignore"):
            ok &= (ln >= 0) & (ln < n_lines) & (sm >= 0) & (sm < n_samples)
    idx, la, sa, lb, sb = idx[ok], la[ok], sa[ok], lb[ok], sb[ok]
    if len(idx) < opts.tie_min_inliers:
        return None
    keep = spread_select(la, sa, conf[idx], opts.tie_max_per_window)
    idx, la, sa, lb, sb = idx[keep], la[keep], sa[keep], lb[keep], sb[keep]
    ca, ra = window.to_ref_pixel(kp0[idx, 0], kp0[idx, 1])
    cb, rb = window.to_ref_pixel(kp1[idx, 0], kp1[idx, 1])
    mx, my = ref.pixel_to_map((ca + cb) / 2.0, (ra + rb) / 2.0)
    xyz, *_ = map_to_ground(ref, dem, mx, my)
    good = np.all(np.isfinite(xyz), axis=1)
    if good.sum() < opts.tie_min_inliers:
        return None
    return xyz[good], la[good], sa[good], lb[good], sb[good]


def find_tie_points(
    strips: dict[str, tuple[Camera, dict[str, CcdImage]]],
    ref: ReferenceOrtho,
    dem: Terrain,
    matcher: Matcher,
    frontend: FrontendConfig,
    options: CampaignOptions,
) -> TiePoints:
    """Match tie points between the overlapping CCD images of different strips.

    Args:
        strips: Strip id -> ``(camera, {ccd: CcdImage})`` (initial cameras).
        ref: The reference orthoimage (its grid; its pixels are not read).
        dem: The reference DEM.
        matcher: The run's (fine) matcher.
        frontend: :class:`~planetref.frontend.config.FrontendConfig` (RANSAC settings,
            lattice step, consensus radius).
        options: :class:`~planetref.frontend.config.CampaignOptions`.

    Returns:
        The tie points (possibly none).
    """
    windows = {}
    for sid, (camera, images) in strips.items():
        for ccd in images:
            w = _ccd_window(camera, ccd, ref, dem, frontend.footprint_points_per_edge)
            if w is not None:
                windows[(sid, ccd)] = w
    keys = list(windows)
    xyz, strip, ccd, line, sample, pids = [], [], [], [], [], []
    tp = TiePoints()
    for i, ka in enumerate(keys):
        for kb in keys[i + 1 :]:
            if ka[0] == kb[0]:
                continue
            pair = f"{ka[0]}/{ka[1]}~{kb[0]}/{kb[1]}"
            a = (strips[ka[0]][0], strips[ka[0]][1][ka[1]], ka[1])
            b = (strips[kb[0]][0], strips[kb[0]][1][kb[1]], kb[1])
            n_pair = 0
            for k, win in enumerate(
                _overlap_windows(
                    windows[ka],
                    windows[kb],
                    ref.shape,
                    options.tie_window_ref_px,
                    options.tie_min_overlap_ref_px,
                )
            ):
                try:
                    got = _match_window(win, a, b, ref, dem, matcher, frontend, options)
                except PlanetrefError as exc:
                    log.warning("tie points %s window %d: %s", pair, k, exc)
                    continue
                if got is None:
                    continue
                gx, la, sa, lb, sb = got
                n = len(gx)
                xyz.append(gx)
                strip.append(np.tile([ka[0], kb[0]], (n, 1)))
                ccd.append(np.tile([ka[1], kb[1]], (n, 1)))
                line.append(np.column_stack([la, lb]))
                sample.append(np.column_stack([sa, sb]))
                pids += [f"tie:{pair}:{k}:{j}" for j in range(n)]
                n_pair += n
            if n_pair:
                tp.pairs[pair] = n_pair
                log.info("tie points %s: %d", pair, n_pair)
    if pids:
        tp.point_ids = pids
        tp.xyz = np.concatenate(xyz)
        tp.strip = np.concatenate(strip).astype(str)
        tp.ccd = np.concatenate(ccd).astype(str)
        tp.line = np.concatenate(line)
        tp.sample = np.concatenate(sample)
    return tp
