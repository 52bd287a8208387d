"""Formal ground precision of adjusted cameras, over the true error's image grid.

The adjustment's parameter covariance says how well the cameras are known; what a user
(and a simulated scene's truth check) reads is a ground position. This module propagates
the covariance to the ground: for each pixel of the same regular grid that
:func:`~planetref.adjust.metrics.geolocation_error` measures the true error on, the ground point
at fixed terrain moves with the parameters as ``dX = J dc`` (``J`` from the model's
analytic partials, :func:`analytic_ground_jacobian`, or by central differences of
:meth:`image_to_ground`, :func:`ground_jacobian`; metres per parameter unit), so its
covariance is ``J C J^T`` and
the expected squared ground error is its trace. The RMS over the grid is the formal
counterpart of the true RMS ground error; their ratio ``true / formal`` is ~1 when the
covariance means what it says.

Without truth, two adjustments of one strip from different matchers check each other
(:func:`camera_agreement`): both rest on the same reference, DEM and cameras, so the
reference's and the CCD placement's errors move both alike, and the difference of their
ground positions over the grid should be as large as the two matchers' own errors
(measurement noise and the per-tile matcher offsets) predict. A matcher with an error
common to all its tiles (a bias no residual of its own shows) disagrees with the others
beyond that prediction. With three matchers or more, the excess of each pair
(difference squared minus its prediction) splits into one unmodelled error per matcher
(:func:`excess_error`, the "three-cornered hat" of clock and gauge comparisons): the
part of a matcher's ground error that its own covariance misses, estimated without
truth.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.metrics import geolocation_error, image_grid
from planetref.arrays import F64

__all__ = [
    "OWN_CONSIDER_KINDS",
    "CameraAgreement",
    "analytic_ground_jacobian",
    "camera_agreement",
    "check_tile_misfit",
    "excess_error",
    "formal_ground_precision",
    "ground_jacobian",
]


#: Finite-difference step of a parameter, in its a-posteriori sigmas: small against the
#: scale on which the ground point bends (a camera moves by a tenth of its uncertainty),
#: large against the projections' rounding.
_FD_SIGMAS = 0.1

#: Consider kinds that are a matcher's own error (not shared by another matcher's
#: adjustment of the same strip on the same reference): the per-tile matcher offsets.
OWN_CONSIDER_KINDS: tuple[str, ...] = ("tile",)


def ground_jacobian(
    model: Any,
    x: F64,
    sigma: F64,
    active: NDArray[np.intp],
    line: F64,
    sample: F64,
    ccd: str,
    terrain: Any,
) -> F64:
    """``d(ground XYZ)/d(parameter)`` of image points at fixed terrain, ``(n, 3, k)``.

    Args:
        model: The camera's :class:`~planetref.adjust.models.AdjustableCamera`.
        x: The camera's adjusted local parameter vector.
        sigma: A-posteriori sigma per local parameter (sets each step).
        active: Local indices of the parameters to differentiate (``k`` of them).
        line: Image lines (px), ``(n,)``.
        sample: Image samples, ``(n,)``.
        ccd: CCD name.
        terrain: Height or terrain, as for ``image_to_ground``.

    Returns:
        Metres per parameter unit; NaN rows where a ray misses.
    """
    out = np.full((len(line), 3, len(active)), np.nan)
    for k, i in enumerate(active):
        h = _FD_SIGMAS * float(sigma[i]) if sigma[i] > 0 else 1e-6 * max(abs(float(x[i])), 1.0)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        gp = model.build(xp).image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
        gm = model.build(xm).image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
        out[:, :, k] = (gp - gm) / (2.0 * h)
    return out


def analytic_ground_jacobian(
    model: Any,
    x: F64,
    active: NDArray[np.intp],
    line: F64,
    sample: F64,
    ccd: str,
    height: float,
) -> F64:
    """:func:`ground_jacobian` from the model's analytic partials (one projection).

    The grid pixels' ground points at ``height`` are projected with the partials of
    ``(line, sample)`` by the parameters ``P`` and by the ground ``G``; holding the pixel
    and the height, the ground moves in the local east-north plane by
    ``-(G E^T)^-1 P`` per parameter (``E`` the east and north unit vectors).
    """
    from planetref.control.network import enu_rotation

    cam = model.build(x)
    xyz = cam.image_to_ground(line, sample, height, ccd=ccd, on_miss="nan")
    out = np.full((len(line), 3, len(active)), np.nan)
    ok = np.all(np.isfinite(xyz), axis=1)
    if not np.any(ok):
        return out
    idx = list(cam.ccd_names).index(ccd)
    ev = model.evaluate(x, xyz[ok], idx, np.asarray(line, np.float64)[ok], partials=True)
    en = enu_rotation(xyz[ok])[:, :2, :]  # (m, 2, 3)
    a = np.einsum("mij,mkj->mik", ev.d_ground, en)  # d(line, sample)/d(east, north)
    move = -np.linalg.solve(a, ev.d_params)  # (m, 2, q): east, north per parameter
    xyz_move = np.einsum("mki,mkq->miq", en, move)  # (m, 3, q)
    cols = np.asarray(model.pattern_columns)[ev.pattern]  # (m, q) local, -1 padding
    full = np.zeros((int(np.count_nonzero(ok)), 3, len(x)))
    rows = np.broadcast_to(np.arange(len(cols))[:, None], cols.shape)
    keep = cols >= 0
    for axis in range(3):
        np.add.at(full[:, axis, :], (rows[keep], cols[keep]), xyz_move[:, axis, :][keep])
    good = np.asarray(ev.valid, bool)
    sub = full[:, :, active]
    sub[~good] = np.nan
    out[ok] = sub
    return out


def _mean_height(cam: Any, line: F64, sample: F64, ccd: str, terrain: Any) -> float:
    """Mean ellipsoid height (m) of the grid's terrain intersections.

    The partials are taken at this constant height: differences of intersections with a
    rough DEM (posts of a few metres) would add the terrain's texture to every step and
    break the position-attitude cancellation that the covariance encodes; at the few
    tenths of a degree off nadir of a push-broom strip the height's variation over the
    image changes the partials by millimetres.
    """
    if isinstance(terrain, int | float):
        return float(terrain)
    from planetref.geometry.geodesy import xyz_to_lonlat

    xyz = cam.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
    ok = np.all(np.isfinite(xyz), axis=1)
    if not np.any(ok):
        return 0.0
    return float(np.mean(xyz_to_lonlat(xyz[ok], cam.ellipsoid)[2]))


def formal_ground_precision(
    result: Any,
    camera_id: str,
    *,
    terrain: Any = 0.0,
    grid: tuple[int, int] = (21, 21),
    covariance: F64 | None = None,
    consider_kinds: Collection[str] | None = None,
) -> dict[str, Any]:
    """Formal RMS ground error of one adjusted camera over a regular image grid per CCD.

    With the result's consider parameters (:attr:`~planetref.adjust.result.
    AdjustmentResult.consider`), a grid point's ground error is ``J dc + D z`` with
    ``dc = n + G z`` (``n`` the measurements' error, covariance
    :attr:`~planetref.adjust.result.AdjustmentResult.covariance_measurement`) and ``D``
    the direct move of the ground point with its own CCD's offset (``z`` in pixels), so
    its covariance is ``J C_n J^T + (J G + D) Sigma_z (J G + D)^T``.

    Args:
        result: An :class:`~planetref.adjust.result.AdjustmentResult`.
        camera_id: The camera (strip) to assess.
        terrain: Height (m) or terrain the grid pixels are intersected with (the true
            error's terrain, so that both are taken at the same points).
        grid: ``(n_lines, n_samples)`` nodes per CCD, as
            :func:`~planetref.adjust.metrics.geolocation_error`.
        covariance: A parameter covariance to propagate alone instead (no consider
            parameters), e.g. the measurements' share.
        consider_kinds: Only the consider parameters of these kinds
            (:data:`~planetref.adjust.consider.KINDS`) beside the measurements' share,
            e.g. :data:`OWN_CONSIDER_KINDS`; None: all of them.

    Returns:
        ``{"rms_m", "ccds": {ccd: rms_m}, "n"}``: the square root of the mean trace of
        the ground covariance (metres; the expected RMS of the 3-D ground error at
        fixed terrain, mostly horizontal).
    """
    consider = getattr(result, "consider", None) if covariance is None else None
    cov = (
        np.asarray(covariance, np.float64) if covariance is not None else _measurement_share(result)
    )
    ids = list(result.cameras)
    ci = ids.index(camera_id)
    sizes = [len(m.x0) for m in result.models]
    off = int(np.sum(sizes[:ci]))
    model = result.models[ci]
    n = sizes[ci]
    loc = slice(off, off + n)
    c_loc = cov[loc, loc]
    total = np.asarray(result.covariance, np.float64)[loc, loc] if consider else c_loc
    sig = np.sqrt(np.maximum(np.diag(total), 0.0))
    active = np.flatnonzero(sig > 0)
    x = np.asarray(result.x[loc], np.float64)
    cam = result.cameras[camera_id]
    if consider is not None:
        sigma_z = np.asarray(consider.sigma, np.float64)
        if consider_kinds is not None:
            kinds = np.asarray(consider.column_kinds, dtype=object)
            sigma_z = np.where(np.isin(kinds, list(consider_kinds)), sigma_z, 0.0)
    per_ccd: dict[str, float] = {}
    sq: list[F64] = []
    for ccd in cam.ccd_names:
        line, sample = image_grid(cam, ccd, grid)
        height = _mean_height(cam, line, sample, ccd, terrain)
        tr = np.zeros(len(line))
        if active.size:
            try:
                jac = analytic_ground_jacobian(model, x, active, line, sample, ccd, height)
            except (AttributeError, TypeError, ValueError, np.linalg.LinAlgError):
                # Models without analytic partials in this form: central differences.
                jac = ground_jacobian(model, x, sig, active, line, sample, ccd, height)
            tr = np.einsum("nik,kl,nil->n", jac, c_loc[np.ix_(active, active)], jac)
        if consider is not None:
            g = consider.sensitivity[loc][active]  # (k, K)
            jz = np.einsum("nik,kz->niz", jac, g) if active.size else 0.0
            jz = jz + _direct(consider, camera_id, ccd, cam, line, sample, height)
            tr = tr + np.einsum("niz,z,niz->n", jz, sigma_z**2, jz)
        ok = np.isfinite(tr)
        per_ccd[ccd] = float(np.sqrt(np.mean(tr[ok]))) if np.any(ok) else float("nan")
        sq.append(tr[ok])
    allv = np.concatenate(sq) if sq else np.zeros(0)
    return {
        "rms_m": float(np.sqrt(np.mean(allv))) if allv.size else float("nan"),
        "ccds": per_ccd,
        "n": int(allv.size),
    }


@dataclass(frozen=True)
class CameraAgreement:
    """Two matchers' adjustments of one strip, compared with no truth.

    Attributes:
        camera_id: The strip.
        matchers: The two matchers ``(a, b)``.
        diff_m: RMS over the image grid (every CCD) of the ground distance between the
            two adjusted cameras' terrain intersections of the same pixel, metres.
        own_m: Each one's formal ground precision from its own errors only (the
            measurements and :data:`OWN_CONSIDER_KINDS`), metres, same grid.
        n: Grid points used.
    """

    camera_id: str
    matchers: tuple[str, str]
    diff_m: float
    own_m: tuple[float, float]
    n: int

    @property
    def predicted_m(self) -> float:
        """The difference's RMS if both adjustments' own errors are what they say."""
        return math.hypot(*self.own_m)

    @property
    def ratio(self) -> float:
        """``diff_m / predicted_m``: ~1 when both agree within their own precision."""
        p = self.predicted_m
        return self.diff_m / p if p > 0 else math.inf


def camera_agreement(
    a: Any,
    b: Any,
    camera_id: str,
    *,
    matchers: tuple[str, str] = ("a", "b"),
    terrain: Any = 0.0,
    grid: tuple[int, int] = (21, 21),
) -> CameraAgreement:
    """How far two adjustments of one strip (from different matchers) put its pixels apart.

    The ground difference of the two adjusted cameras over the true error's image grid,
    beside what the two adjustments' own errors predict for it: each one's measurement
    covariance and own consider terms (:data:`OWN_CONSIDER_KINDS`), taken as
    independent. The reference's and the CCD placement's errors are left out of the
    prediction: the same reference and cameras move both adjustments alike (nearly: two
    matchers sample the reference's patches with different MCPs). A ratio well above 1
    against every other matcher marks one with an error that its own residuals do not
    show, e.g. one common to all its tiles.

    Args:
        a: One :class:`~planetref.adjust.result.AdjustmentResult` with ``camera_id``.
        b: Another, of the same strip (same CCDs, image size).
        camera_id: The strip.
        matchers: Their names, for the record.
        terrain: Height (m) or terrain the grid pixels are intersected with.
        grid: ``(n_lines, n_samples)`` nodes per CCD.
    """
    ca, cb = a.cameras[camera_id], b.cameras[camera_id]
    sq, n = 0.0, 0
    for ccd in ca.ccd_names:
        g = geolocation_error(cb, ca, ccd=ccd, terrain=terrain, grid=grid)
        if g["n"] and math.isfinite(g["rms_m"]):
            sq += float(g["rms_m"]) ** 2 * int(g["n"])
            n += int(g["n"])
    own = tuple(
        float(
            formal_ground_precision(
                r, camera_id, terrain=terrain, grid=grid, consider_kinds=OWN_CONSIDER_KINDS
            )["rms_m"]
        )
        for r in (a, b)
    )
    return CameraAgreement(
        camera_id=camera_id,
        matchers=matchers,
        diff_m=math.sqrt(sq / n) if n else math.nan,
        own_m=(own[0], own[1]),
        n=n,
    )


def excess_error(pairs: Sequence[CameraAgreement]) -> dict[str, float]:
    """Each matcher's ground error beyond its own formal precision (m), from the pairs.

    Per strip, the pairs' excess ``diff^2 - predicted^2`` is modelled as ``e_a^2 +
    e_b^2`` (independent unmodelled errors of the two matchers) and solved for the
    ``e^2`` by non-negative least squares (the three-cornered hat). It needs three
    matchers of a strip at least (two give one equation for two unknowns); strips with
    fewer are left out. Several strips: the RMS of a matcher's strips.

    Args:
        pairs: :func:`camera_agreement` of the pairs of matchers (each strip's pairs).

    Returns:
        Matcher -> excess RMS ground error (m); empty when no strip has three matchers.
    """
    from scipy.optimize import nnls

    by_strip: dict[str, list[CameraAgreement]] = {}
    for a in pairs:
        if math.isfinite(a.diff_m) and math.isfinite(a.predicted_m):
            by_strip.setdefault(a.camera_id, []).append(a)
    sq: dict[str, list[float]] = {}
    for group in by_strip.values():
        names = sorted({n for a in group for n in a.matchers})
        if len(names) < 3:
            continue
        col = {n: i for i, n in enumerate(names)}
        design = np.zeros((len(group), len(names)))
        rhs = np.zeros(len(group))
        for k, a in enumerate(group):
            design[k, [col[a.matchers[0]], col[a.matchers[1]]]] = 1.0
            rhs[k] = a.diff_m**2 - a.predicted_m**2
        if np.linalg.matrix_rank(design) < len(names):
            continue
        e2, _ = nnls(design, rhs)
        for n, v in zip(names, e2, strict=True):
            sq.setdefault(n, []).append(float(v))
    return {n: math.sqrt(sum(v) / len(v)) for n, v in sq.items()}


def _measurement_share(result: Any) -> F64:
    """The parameters' covariance less the consider terms' share (all of it without them)."""
    if getattr(result, "consider", None) is not None and result.covariance_measurement is not None:
        return np.asarray(result.covariance_measurement, np.float64)
    return np.asarray(result.covariance, np.float64)


def _direct(
    consider: Any, camera_id: str, ccd: str, cam: Any, line: F64, sample: F64, height: float
) -> F64:
    """``D``: ground move (m) of each grid pixel per pixel of its CCD's offset, ``(n, 3, K)``.

    The true camera sees at pixel ``u`` what the model sees at ``u - z``: the pixel's
    ground point is off by ``d(ground)/d(pixel) z`` (central differences, half a pixel).
    """
    out = np.zeros((len(line), 3, len(consider.sigma)))
    for k, item in enumerate(consider.ccd):
        if item is None or item[0] != camera_id or item[1] != ccd:
            continue
        d = np.array([0.5, 0.0]) if item[2] == 0 else np.array([0.0, 0.5])
        gp = cam.image_to_ground(line + d[0], sample + d[1], height, ccd=ccd, on_miss="nan")
        gm = cam.image_to_ground(line - d[0], sample - d[1], height, ccd=ccd, on_miss="nan")
        out[:, :, k] = gp - gm
    return out


def check_tile_misfit(result: Any) -> dict[str, Any] | None:
    """The held-out tiles' mean misfits against their formal prediction: a truth-free anchor.

    A check tile (whole tiles held out, :func:`~planetref.control.networks.check_points`)
    is an independent measurement of the adjusted cameras: the mean misfit ``m`` of its
    MCPs (projected reference point minus observed pixel, per axis) is, under the
    adjustment's own error model, ``a (c_hat - c) + sum_z (a G_z + d_z) z + o + n`` with
    ``a`` the misfit's derivative by the camera's parameters (the model's partials,
    averaged over the tile), ``G`` the consider sensitivities, ``d_z`` the direct effect of a
    consider parameter on the misfit (a CCD offset moves the observation, a reference
    patch's offset the reference point), ``o`` the tile's own matcher offset (the
    adjustment's tile sigma) and ``n`` the MCPs' noise averaged over the tile (their
    scatter over ``n`` times the template overlap). ``m / sqrt(Var m)`` is ~N(0, 1)
    when the covariance means what it says; the RMS of these over the check tiles and
    both axes is ~1 (and within a few tiles' chi-square spread of it) on real data as on
    simulated data, where the true error is unknown.

    Args:
        result: An :class:`~planetref.adjust.result.AdjustmentResult` with check
            observations of known tiles.

    Returns:
        ``{"n_tiles", "rms_normalised", "tiles": [{"tile", "camera", "n", "misfit_px",
        "predicted_sd_px", "normalised"}]}``, or ``None`` without such check tiles.
    """
    from planetref.control.network import enu_rotation

    net = result.network
    tiles = np.asarray(net.obs_tile)
    res = np.asarray(result.residual, np.float64)
    chk = np.flatnonzero(np.asarray(net.obs_check) & (tiles >= 0) & np.all(np.isfinite(res), 1))
    if not chk.size:
        return None
    consider = getattr(result, "consider", None)
    cov = _measurement_share(result)
    total_sigma = np.sqrt(np.maximum(np.diag(np.asarray(result.covariance, np.float64)), 0.0))
    sizes = [len(m.x0) for m in result.models]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    overlap = float((result.variance or {}).get("measurement_overlap") or 1.0)
    tile_sigma = np.zeros(2)
    if consider is not None and "tile" in consider.column_kinds:
        k0 = consider.column_kinds.index("tile")
        tile_sigma = np.asarray(consider.sigma[k0 : k0 + 2], np.float64)
    xyz_all = np.asarray(result.point_xyz_initial, np.float64)
    out: list[dict[str, Any]] = []
    for t in np.unique(tiles[chk]):
        obs = chk[tiles[chk] == t]
        ci = int(net.obs_camera[obs[0]])
        cam_id = net.camera_ids[ci]
        ccd_i = int(net.obs_ccd[obs[0]])
        obs = obs[(net.obs_camera[obs] == ci) & (net.obs_ccd[obs] == ccd_i)]
        ccd = net.cameras[ci].ccd_names[ccd_i]
        model = result.models[ci]
        loc = slice(offs[ci], offs[ci + 1])
        x = np.asarray(result.x[loc], np.float64)
        pts = net.obs_point[obs]
        xyz = xyz_all[pts]
        m = np.mean(res[obs], axis=0)
        n = len(obs)
        spread = np.var(res[obs], axis=0, ddof=1) if n > 1 else np.zeros(2)
        var = overlap * spread / max(n, 1) + tile_sigma**2
        sig = total_sigma[loc]
        act = np.flatnonzero(sig > 0)
        # The misfits' partials by the camera's parameters and by the ground, from the
        # model's own (as the solver's): mean over the tile's MCPs.
        ev = model.evaluate(x, xyz, ccd_i, np.asarray(net.obs_line)[obs], partials=True)
        good = np.asarray(ev.valid, bool)
        cols = np.asarray(model.pattern_columns)[ev.pattern]  # (n, q) local, -1 padding
        dpar = np.zeros((2, len(x)))
        keep = (cols >= 0) & good[:, None]
        for axis in range(2):
            np.add.at(dpar[axis], cols[keep], np.asarray(ev.d_params)[:, axis, :][keep])
        a = dpar[:, act] / max(int(np.count_nonzero(good)), 1)
        c_loc = cov[loc, loc][np.ix_(act, act)]
        var = var + np.einsum("ak,kl,al->a", a, c_loc, a)
        if consider is not None and len(consider.sigma):
            s = a @ np.asarray(consider.sensitivity)[loc][act]  # (2, K)
            for k, item in enumerate(consider.ccd):
                if item is not None and item[0] == cam_id and item[1] == ccd:
                    s[item[2], k] -= 1.0  # the observation moves, the misfit the other way
            patch = consider.point_patch
            if patch is not None and consider.n_patches:
                en = enu_rotation(xyz)[:, :2, :]  # (n, 2, 3)
                # d(line, sample)/d(east, north) of each reference point.
                d_en = np.einsum("nij,nkj->nik", np.asarray(ev.d_ground), en)
                pp = patch[pts]
                on = (pp >= 0) & good
                for axis in range(2):
                    for comp in range(2):
                        np.add.at(s[axis], 2 * pp[on] + comp, d_en[on, axis, comp] / n)
            var = var + (s**2) @ (np.asarray(consider.sigma) ** 2)
        sd = np.sqrt(var)
        out.append(
            {
                "tile": int(t),
                "camera": cam_id,
                "ccd": ccd,
                "n": int(n),
                "misfit_px": [float(v) for v in m],
                "predicted_sd_px": [float(v) for v in sd],
                "normalised": [float(v) for v in m / sd],
            }
        )
    z = np.array([r["normalised"] for r in out], np.float64).ravel()
    return {
        "n_tiles": len(out),
        "rms_normalised": float(np.sqrt(np.mean(z**2))) if z.size else float("nan"),
        "tiles": out,
    }
