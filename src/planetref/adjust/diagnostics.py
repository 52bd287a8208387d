"""What the adjustment moved and what it could not determine.

* **Points**: a-priori and adjusted coordinates of every point, their a-priori and
  a-posteriori sigmas and the shift (metres, and in a-priori sigmas for weighted
  points); a warning when weighted points move beyond ``point_shift_sigmas``.
* **Cameras**: how far each camera's ground footprint moved (a grid of its image
  intersected with the height of its points, initial against adjusted camera); a
  warning beyond ``camera_shift_m``.
* **Correlations**: a warning when any two parameters correlate beyond
  ``max_correlation``.
* **Self-calibration**: for every interior-orientation parameter (``x0``, ``y0``,
  ``f``, CCD placement, CSM focal length) that was estimated, its a-priori and
  a-posteriori sigma, its strongest correlations (with single parameters, with the
  camera's mean node height, and its multiple correlation with all other
  parameters) and a verdict in words: *separable* or *not separable* and why.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import DiagnosticsConfig
from planetref.arrays import F64
from planetref.control.network import Network, small_unique
from planetref.geometry.geodesy import xyz_to_lonlat

__all__ = [
    "SELF_CALIBRATION",
    "camera_shifts",
    "correlation_warnings",
    "point_table",
    "self_calibration",
]


#: Parameter names (after ``camera_id:``) that are interior orientation / self-calibration.
SELF_CALIBRATION = re.compile(r"(^|[.\]:])(x0|y0|f|focal_m|focal|placement\w*|ccd_\w+)$|interior")

#: Multiple correlation above which a free self-calibration parameter is not separable.
_MULTIPLE_CORRELATION = 0.999


def point_table(
    net: Network,
    xyz0: F64,
    xyz: F64,
    sigma_prior: F64,
    frame: Any,
    cofactor: tuple[NDArray[np.intp], F64],
    sigma0: float,
) -> dict[str, Any]:
    """Per point: a-priori and adjusted coordinates, sigmas and shifts.

    Only the points that moved, have a cofactor block or a weighted a-priori sigma are
    converted, rotated and normalised; the others get their values directly (no shift,
    the a-priori geodetic coordinates), equal to what the full computation gives them.

    Args:
        net: The network (ids, kinds, the first camera's ellipsoid).
        xyz0: A-priori (or triangulated) XYZ, ``(P, 3)``.
        xyz: Adjusted XYZ, ``(P, 3)``.
        sigma_prior: A-priori sigmas used in the final adjustment (after variance
            component scaling), in each point's sigma frame, ``(P, 3)``.
        frame: Rotations XYZ -> sigma frame, indexed like ``(P, 3, 3)`` (an array or
            :class:`~planetref.control.network.PointFrames`).
        cofactor: ``(points, blocks)``: indices of the unknown points ``(u,)`` and
            their 3x3 cofactor blocks (XYZ), ``(u, 3, 3)``.
        sigma0: A-posteriori sigma of unit weight.

    Returns:
        Column name -> array (see :func:`planetref.report.adjustment.write_points`).
    """
    from planetref.control.network import enu_rotation

    ell = net.cameras[0].ellipsoid
    n = net.n_points
    fin = np.isfinite(xyz0)
    ok0 = fin[:, 0] & fin[:, 1] & fin[:, 2]
    every = bool(np.all(ok0))
    d = xyz - xyz0
    # Points that did not move (fixed ones) keep their a-priori geodetic coordinates and
    # have no shift: only the others are converted.
    moved = ok0 & ((d[:, 0] != 0.0) | (d[:, 1] != 0.0) | (d[:, 2] != 0.0))
    if every:
        lon0, lat0, h0 = xyz_to_lonlat(xyz0, ell)
    else:
        lon0, lat0, h0 = (np.full(n, np.nan) for _ in range(3))
        if np.any(ok0):
            lon0[ok0], lat0[ok0], h0[ok0] = xyz_to_lonlat(xyz0[ok0], ell)
    lon1, lat1, h1 = lon0.copy(), lat0.copy(), h0.copy()
    mv = np.flatnonzero(moved)
    if mv.size:
        lon1[mv], lat1[mv], h1[mv] = xyz_to_lonlat(xyz[mv], ell)
    # Rows whose shifts are not simply 0 (unmoved) or NaN (no a-priori coordinates).
    other = mv if every else np.flatnonzero(moved | ~ok0)
    d_enu = np.zeros((n, 3))
    d_enu[~ok0] = np.nan
    shift_m = np.zeros(n)
    shift_m[other] = np.linalg.norm(d[other], axis=1)
    cof_idx, cof_blocks = cofactor
    cof_idx = np.asarray(cof_idx, np.intp)
    has = ok0[cof_idx]
    cof_pts = cof_idx[has]
    need = moved.copy()
    need[cof_pts] = True
    # ENU rotations of the points that moved or have a cofactor block only.
    rot = np.flatnonzero(need)
    enu = enu_rotation(xyz0[rot]) if len(rot) else np.zeros((0, 3, 3))
    d_enu[mv] = np.einsum("pij,pj->pi", enu[np.searchsorted(rot, mv)], d[mv])
    shift_h = np.zeros(n)  # hypot(0, 0) of the points that did not move
    shift_h[~ok0] = np.nan
    shift_h[mv] = np.hypot(d_enu[mv, 0], d_enu[mv, 1])
    post = np.zeros((n, 3))
    if len(cof_pts):
        e = enu[np.searchsorted(rot, cof_pts)]
        q = np.asarray(cof_blocks)[has]
        var = np.einsum("pij,pjk,pik->pi", e, q, e)  # diag(E Q E^T)
        post[cof_pts] = sigma0 * np.sqrt(np.maximum(var, 0.0))
    # Shifts in a-priori sigmas: only points with a finite positive sigma have one.
    prior_ok = np.isfinite(sigma_prior) & (sigma_prior > 0)
    wp = np.flatnonzero(prior_ok[:, 0] | prior_ok[:, 1] | prior_ok[:, 2])
    shift_sigma = np.full(n, np.nan)
    if wp.size:
        d_frame = np.einsum("pij,pj->pi", frame[wp], d[wp])
        with np.errstate(divide="ignore", invalid="ignore"):
            norm = np.where(prior_ok[wp], np.abs(d_frame) / sigma_prior[wp], np.nan)
        s_w = np.max(np.where(np.isnan(norm), -np.inf, norm), axis=1)
        s_w[~np.isfinite(s_w)] = np.nan
        shift_sigma[wp] = s_w
    return {
        "point_id": np.asarray(net.point_ids),
        "kind": np.asarray(net.point_kind),
        "xyz_apriori": xyz0,
        "xyz": xyz,
        "lat_apriori": lat0,
        "lon_apriori": lon0,
        "height_apriori": h0,
        "lat": lat1,
        "lon": lon1,
        "height": h1,
        "sigma_apriori": sigma_prior,
        "sigma_local": np.asarray(net.point_sigma_local),
        "sigma_enu": post,
        "shift_m": shift_m,
        "shift_horizontal_m": shift_h,
        "shift_up_m": d_enu[:, 2],
        "shift_sigma": shift_sigma,
    }


def point_summary(
    table: dict[str, Any],
    used: NDArray[np.bool_],
    cfg: DiagnosticsConfig,
    kind_codes: tuple[NDArray[np.str_], NDArray[np.intp]] | None = None,
) -> tuple[dict[str, Any], list[str], list[str]]:
    """Movement statistics of the points per kind, the warning lines and the notes.

    ``kind_codes``: ``(kinds, code)`` of ``table["kind"]`` when already known
    (:attr:`~planetref.control.network.Network.point_kind_codes`).

    Returns:
        ``(statistics, warnings, notes)``: the line about weighted points beyond
        ``point_shift_sigmas`` is a warning when chance does not explain it (more such
        points, or a larger largest shift, than Gaussian a-priori errors give), else a
        note (the expected tail of the a-priori errors).
    """
    out: dict[str, Any] = {}
    warnings: list[str] = []
    notes: list[str] = []
    kinds, code = kind_codes if kind_codes is not None else small_unique(table["kind"])
    finite = used & np.isfinite(table["shift_m"])
    for c in np.flatnonzero(np.bincount(code[used], minlength=len(kinds))):
        k = str(kinds[c])
        m = finite & (code == c)
        s = table["shift_m"][m]
        if not s.size:
            continue
        out[k] = {
            "n": int(s.size),
            "mean_shift_m": float(np.mean(s)),
            "rms_shift_m": float(np.sqrt(np.mean(s**2))),
            "max_shift_m": float(np.max(s)),
            "mean_up_m": float(np.mean(table["shift_up_m"][m])),
            "mean_horizontal_m": float(np.mean(table["shift_horizontal_m"][m])),
        }
    ns = table["shift_sigma"]
    beyond = used & np.isfinite(ns) & (ns > cfg.point_shift_sigmas)
    if np.any(beyond):
        j = int(np.flatnonzero(beyond)[np.argmax(ns[beyond])])
        sa = table["sigma_apriori"][used]
        n_axes = int(np.count_nonzero(np.isfinite(sa) & (sa > 0)))
        chance = n_axes * math.erfc(cfg.point_shift_sigmas / math.sqrt(2.0))
        # A warning when chance does not explain it: more points than a Poisson count
        # of mean `chance` reaches (mean + 3 sd + 1), or a largest shift that Gaussian
        # errors give in fewer than one such network in twenty (a 5 % test: a blunder).
        too_many = beyond.sum() > chance + 3.0 * math.sqrt(chance) + 1.0
        too_far = n_axes * math.erfc(float(ns[j]) / math.sqrt(2.0)) < 0.05
        (warnings if too_many or too_far else notes).append(
            f"{int(beyond.sum())} weighted point(s) moved more than "
            f"{cfg.point_shift_sigmas:g} sigma from their a-priori coordinates (largest: "
            f"{table['point_id'][j]} by {ns[j]:.3g} sigma, {table['shift_m'][j]:.4g} m; "
            f"Gaussian errors would give at most ~{chance:.3g} by chance)"
        )
    return out, warnings, notes


def camera_shifts(
    net: Network,
    cams0: list[Any],
    cams1: list[Any],
    xyz: F64,
    cfg: DiagnosticsConfig,
    grid: int = 5,
    heights: F64 | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """How far each camera's ground footprint moved (per CCD, metres).

    A ``grid x grid`` set of pixels of each CCD image is intersected with the sphere at
    the median height of the camera's points by the initial and the adjusted camera.
    ``heights``: the points' heights above the first camera's ellipsoid (NaN where
    ``xyz`` is not finite), when already known (:func:`point_table`).

    Returns:
        ``({camera_id: {ccd: {"mean_m", "max_m"}, "max_m": ...}}, warnings)``.
    """
    out: dict[str, Any] = {}
    moved: list[str] = []
    for ci, cid in enumerate(net.camera_ids):
        c0, c1 = cams0[ci], cams1[ci]
        # The points the camera observes.
        seen = np.zeros(net.n_points, bool)
        seen[net.obs_point if len(cams0) == 1 else net.obs_point[net.obs_camera == ci]] = True
        if heights is not None and c0.ellipsoid == net.cameras[0].ellipsoid:
            hp = heights[seen]
            hp = hp[np.isfinite(hp)]
        else:
            p = xyz[seen]
            p = p[np.all(np.isfinite(p), axis=1)]
            hp = xyz_to_lonlat(p, c0.ellipsoid)[2] if len(p) else np.zeros(0)
        h = float(np.median(hp)) if len(hp) else 0.0
        per: dict[str, Any] = {}
        for ccd in c0.ccd_names:
            nl, ns = c0.image_size(ccd)
            ll, ss = np.meshgrid(
                np.linspace(0.5, nl - 0.5, grid), np.linspace(0.5, ns - 0.5, grid), indexing="ij"
            )
            g0 = c0.image_to_ground(ll.ravel(), ss.ravel(), h, ccd=ccd, on_miss="nan")
            g1 = c1.image_to_ground(ll.ravel(), ss.ravel(), h, ccd=ccd, on_miss="nan")
            dist = np.linalg.norm(g1 - g0, axis=1)
            dist = dist[np.isfinite(dist)]
            per[ccd] = {
                "mean_m": float(np.mean(dist)) if dist.size else math.nan,
                "max_m": float(np.max(dist)) if dist.size else math.nan,
            }
        mx = max((v["max_m"] for v in per.values()), default=math.nan)
        out[cid] = {"ccds": per, "max_m": mx, "height_m": h}
        if mx > cfg.camera_shift_m:
            moved.append(f"{cid} {mx:.4g} m")
    warnings = []
    if moved:
        warnings.append(
            f"{len(moved)} camera footprint(s) moved more than {cfg.camera_shift_m:g} m: "
            + ", ".join(moved)
        )
    return out, warnings


def correlation_warnings(
    names: list[str], corr: F64, cfg: DiagnosticsConfig
) -> tuple[dict[str, Any], list[str]]:
    """Pairs of parameters correlating beyond the threshold (count, largest).

    The same attitude angle at two adjacent orientation nodes of a strip always
    correlates highly (Lagrange interpolation couples neighbours; ~0.9999 is normal):
    such pairs are counted and reported (``n_adjacent_node_pairs``) but do not raise
    the warning, which is kept for pairs the observations should separate.
    """
    c = np.abs(np.triu(np.asarray(corr), 1))
    if not c.size:
        return {"n_pairs_above": 0, "threshold": cfg.max_correlation}, []
    above = np.argwhere(c > cfg.max_correlation)
    info: dict[str, Any] = {"n_pairs_above": len(above), "threshold": cfg.max_correlation}
    if not len(above):
        return info, []
    i, j = map(int, np.unravel_index(int(np.argmax(c)), c.shape))
    info["largest"] = [names[i], names[j], float(corr[i, j])]
    expected = np.array([_adjacent_node_angles(names[a], names[b]) for a, b in above], bool)
    info["n_adjacent_node_pairs"] = int(np.count_nonzero(expected))
    other = above[~expected]
    info["n_other_pairs"] = len(other)
    # The same angle of one camera two or more nodes apart: still the interpolation's
    # coupling (through the nodes between), not two kinds of parameter the observations
    # should separate; counted so that the caller can tell them apart.
    info["n_same_angle_node_pairs"] = sum(_same_angle_nodes(names[a], names[b]) for a, b in other)
    if not len(other):
        return info, []
    k = int(np.argmax(c[other[:, 0], other[:, 1]]))
    i, j = int(other[k, 0]), int(other[k, 1])
    info["largest_other"] = [names[i], names[j], float(corr[i, j])]
    excluded = (
        f"; {info['n_adjacent_node_pairs']} pair(s) of the same angle at adjacent nodes, "
        "expected with Lagrange interpolation, are not counted here"
        if info["n_adjacent_node_pairs"]
        else ""
    )
    return info, [
        f"{len(other)} parameter pair(s) correlate above {cfg.max_correlation:g} (largest: "
        f"{names[i]} and {names[j]} at {corr[i, j]:.6f}): the observations hardly separate "
        f"them; fix or weight one of them{excluded}"
    ]


_NODE_PARAM = re.compile(r"^(?P<cam>.*):node(?P<node>\d+)\.(?P<param>\w+)$")


def _angle_nodes(a: str, b: str) -> tuple[int, int] | None:
    """The two nodes of the same attitude angle of one camera, or None for another pair."""
    ma, mb = _NODE_PARAM.match(a), _NODE_PARAM.match(b)
    if ma is None or mb is None:
        return None
    same = ma["cam"] == mb["cam"] and ma["param"] == mb["param"]
    if not same or ma["param"] not in ("phi", "omega", "kappa"):
        return None
    return int(ma["node"]), int(mb["node"])


def _same_angle_nodes(a: str, b: str) -> bool:
    """True for the same attitude angle of one camera at two different nodes."""
    nodes = _angle_nodes(a, b)
    return nodes is not None and nodes[0] != nodes[1]


def _adjacent_node_angles(a: str, b: str) -> bool:
    """True for the same attitude angle of one camera at two adjacent nodes."""
    nodes = _angle_nodes(a, b)
    return nodes is not None and abs(nodes[0] - nodes[1]) == 1


def _mean_height_direction(names: list[str], x0: F64, camera: str) -> F64 | None:
    """Weights of a camera's node positions forming its mean radial node height."""
    w = np.zeros(len(names))
    found = 0
    pat = re.compile(rf"^{re.escape(camera)}:node(\d+)\.([XYZ])$")
    nodes: dict[str, dict[str, int]] = {}
    for i, n in enumerate(names):
        m = pat.match(n)
        if m:
            nodes.setdefault(m.group(1), {})[m.group(2)] = i
    for idx in nodes.values():
        if len(idx) != 3:
            continue
        ii = [idx["X"], idx["Y"], idx["Z"]]
        p = x0[ii]
        w[ii] = p / np.linalg.norm(p)
        found += 1
    return w / found if found else None


def self_calibration(
    names: list[str],
    mode: NDArray[np.int8],
    sigma_prior: F64,
    x0: F64,
    x: F64,
    cov: F64,
    cfg: DiagnosticsConfig,
) -> tuple[list[dict[str, Any]], list[str]]:
    """Estimability of the interior-orientation parameters that were adjusted.

    Args:
        names: ``camera:name`` of every parameter.
        mode: 0 free, 1 weighted, 2 fixed.
        sigma_prior: A-priori sigmas (weighted parameters).
        x0: Initial values.
        x: Adjusted values.
        cov: A-posteriori covariance.
        cfg: Thresholds.

    Returns:
        ``(rows, warnings)``: one row per parameter with ``separable`` and ``verdict``
        (a sentence).
    """
    rows: list[dict[str, Any]] = []
    warnings: list[str] = []
    act = np.flatnonzero(mode != 2)
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / sig[:, None] / sig[None, :]
    corr[~np.isfinite(corr)] = 0.0
    # Multiple correlation of each active parameter with all the others.
    mult = np.full(len(names), np.nan)
    if act.size > 1:
        ca = corr[np.ix_(act, act)]
        try:
            inv = np.linalg.inv(ca)
            mult[act] = np.sqrt(np.clip(1.0 - 1.0 / np.diag(inv), 0.0, 1.0))
        except np.linalg.LinAlgError:
            mult[act] = 1.0
    for i in act:
        cam, _, local = names[i].partition(":")
        if not SELF_CALIBRATION.search(local):
            continue
        others = np.array([k for k in act if k != i], np.intp)
        top = others[np.argsort(-np.abs(corr[i, others]))[:3]] if others.size else others
        hw = _mean_height_direction(names, x0, cam)
        r_height = math.nan
        if hw is not None:
            var_h = float(hw @ cov @ hw)
            if var_h > 0 and sig[i] > 0:
                r_height = float((cov[i] @ hw) / math.sqrt(var_h) / sig[i])
        prior = float(sigma_prior[i]) if mode[i] == 1 else math.inf
        ratio = sig[i] / prior if math.isfinite(prior) else math.nan
        reasons = []
        if math.isfinite(ratio) and ratio > cfg.separable_sigma_ratio:
            reasons.append(
                f"its a-posteriori sigma is {100 * ratio:.0f} % of the a-priori one (the "
                f"observations add little to the prior)"
            )
        if top.size and abs(corr[i, top[0]]) > cfg.max_correlation:
            reasons.append(f"it correlates at {corr[i, top[0]]:.4f} with {names[top[0]]}")
        if math.isfinite(r_height) and abs(r_height) > cfg.max_correlation:
            reasons.append(f"it correlates at {r_height:.4f} with the mean node height")
        if mode[i] == 0 and mult[i] > _MULTIPLE_CORRELATION:
            reasons.append(f"its multiple correlation with the other parameters is {mult[i]:.5f}")
        separable = not reasons
        corr_txt = ", ".join(f"{names[k]} {corr[i, k]:+.3f}" for k in top)
        verdict = (
            f"{names[i]}: separable (sigma {sig[i]:.3g}, correction {x[i] - x0[i]:+.4g}, "
            f"{abs(x[i] - x0[i]) / sig[i] if sig[i] > 0 else math.inf:.2g} sigma)"
            if separable
            else f"{names[i]}: NOT separable: {'; '.join(reasons)}; its correction "
            f"{x[i] - x0[i]:+.4g} is not a measurement of the parameter"
        )
        rows.append(
            {
                "name": names[i],
                "mode": {0: "free", 1: "weighted"}[int(mode[i])],
                "initial": float(x0[i]),
                "adjusted": float(x[i]),
                "correction": float(x[i] - x0[i]),
                "sigma_prior": prior,
                "sigma": float(sig[i]),
                "sigma_ratio": ratio,
                "correlation_mean_node_height": r_height,
                "multiple_correlation": float(mult[i]),
                "top_correlations": [[names[k], float(corr[i, k])] for k in top],
                "correlations_text": corr_txt,
                "separable": separable,
                "verdict": verdict,
            }
        )
        if not separable:
            warnings.append(verdict)
    return rows, warnings
