"""The jitter stage: high-frequency attitude of line-scan strips on dense orientation nodes.

After the seed's node adjustment (orientation nodes a few hundred lines apart), each
adjusted native line-scan strip is re-sampled on *dense* nodes (``node_spacing_lines``
apart, e.g. 32) that reproduce the seed's smooth trajectory exactly at the start, and
the attitudes of those nodes are adjusted again with the same observations, under a
smoothness prior (see :class:`JitterParameterization`):

* positions, interior orientation and CCD placement stay at the seed's values (fixed);
* each attitude correction ``d`` (node angle minus the seed's) is weighted towards 0
  with the declared jitter amplitude ``amplitude_rad``;
* the second difference ``d[i-1] - 2 d[i] + d[i+1]`` of each angle is weighted towards
  0 with ``sigma_dd = amplitude_rad * 4 sin^2(pi f_max dt)`` (``dt`` the node spacing in
  seconds, ``f_max = max_frequency_hz``): a sinusoid of the declared amplitude at the
  band's edge has second differences of exactly that amplitude, slower ones smaller.

Where the observations are dense the data decide; in a gap the prior holds the
correction to a smooth (linear) bridge of its neighbours decaying towards the seed, so
no jitter is invented there. The dense nodes use the camera's own kernel and
partials (a :class:`~planetref.camera.linescan.LineScanCamera` with more nodes), so the
adjusted cameras, ISDs and orthoimages carry the jitter without new code.

The estimated jitter is the small rotation from the seed's attitude to the dense one in
the camera frame, ``R_seed^T R_dense ~ I + [w]x``, ``w = (roll, pitch, yaw)`` about the
camera's ``x`` (along track), ``y`` and ``z`` axes: the simulator's jitter definition
(``J = Rx(roll) Ry(pitch) Rz(yaw)`` multiplied on the right of the orbit frame and
pointing). Its formal sigma propagates the dense nodes' attitude covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import AdjustConfig, JitterConfig, LineScanParameters
from planetref.adjust.models.linescan import LineScanParameterization
from planetref.adjust.models.protocol import CoverageIssue
from planetref.arrays import F64
from planetref.camera.linescan import LineScanCamera
from planetref.geometry.rotations import rotation_matrix

__all__ = [
    "JitterParameterization",
    "JitterResolution",
    "JitterSeries",
    "attitude_difference",
    "densify",
    "jitter_config",
    "jitter_series",
    "line_of_sight_difference",
    "mcps_by_overlap",
    "resolution_limit",
    "smoothness_sigma_rad",
    "true_jitter",
]

AXES = ("roll", "pitch", "yaw")


def smoothness_sigma_rad(cfg: JitterConfig, dt_s: float) -> float:
    """Sigma of an attitude correction's second difference over nodes ``dt_s`` apart (rad).

    ``cfg.smoothness_sigma_rad`` when given, else ``amplitude_rad * 4 sin^2(pi f dt)``
    with ``f`` the band's upper edge, capped at the nodes' Nyquist frequency.
    """
    if cfg.smoothness_sigma_rad is not None:
        return float(cfg.smoothness_sigma_rad)
    f = min(cfg.max_frequency_hz, 0.5 / dt_s)
    return float(cast_float(cfg.amplitude_rad) * 4.0 * math.sin(math.pi * f * dt_s) ** 2)


def cast_float(v: float | None) -> float:
    """A unit field declared ``float | None`` that has a float default."""
    if v is None:
        raise ValueError("a jitter amplitude is needed")
    return float(v)


def densify(camera: LineScanCamera, spacing_lines: int) -> LineScanCamera:
    """The camera on nodes ``spacing_lines`` apart that reproduce its trajectory.

    The dense nodes cover the imaged lines plus ``interpolation_order`` spacings on
    either side (inside the camera's own node span); each node's values are the
    camera's interpolated ``X, Y, Z, phi, omega, kappa`` at its line, so the dense
    camera differs from the sparse one by the interpolation error of a smooth
    trajectory sampled densely (far below a micro-radian).

    Args:
        camera: The seed's adjusted camera.
        spacing_lines: Line spacing of the dense nodes.

    Returns:
        The same camera with dense nodes.
    """
    n_lines = max(c.n_lines for c in camera.ccds)
    k = camera.interpolation_order
    lo = max(float(camera.node_lines[0]), -k * spacing_lines)
    hi = min(float(camera.node_lines[-1]), n_lines + k * spacing_lines)
    lines = np.arange(lo, hi + 1e-9, float(spacing_lines))
    if lines[-1] < hi - 1e-9:
        lines = np.append(lines, hi)
    kern = camera.kernel
    nodes = kern.exterior(kern.eo_poly(camera.nodes), lines)
    return camera.replace(node_lines=lines, nodes=np.asarray(nodes, np.float64))


def jitter_config(cfg: AdjustConfig, mcp_overlap: float = 1.0) -> AdjustConfig:
    """The seed's configuration for the dense stage: positions, interior, placement fixed.

    With ``mcp_overlap`` ``f > 1`` (the MCPs' measurement overlap, when the network
    also holds CCD-overlap ties) the MCPs are adjusted with ``1 / f`` of their weight
    (:func:`mcps_by_overlap` scales their sigmas, VCE's ``mcp_weight_share`` keeps the
    share) and the covariance needs no sandwich for them (``measurement_overlap`` 1):
    ``f`` overlapping MCPs are one measurement, not ``f``, against the ties.
    """
    ls = cfg.linescan
    amp = cast_float(cfg.jitter.amplitude_rad)
    dense = ls.model_copy(
        update={
            "position": ls.position.model_copy(update={"mode": "fixed"}),
            "attitude": ls.attitude.model_copy(update={"mode": "weighted", "sigma_rad": amp}),
            "interior": ls.interior.model_copy(update={"mode": "fixed"}),
            "ccd_placement": ls.ccd_placement.model_copy(update={"mode": "fixed"}),
        }
    )
    update: dict[str, Any] = {"linescan": dense}
    f = float(mcp_overlap)
    if f > 1.0:
        update["systematic"] = cfg.systematic.model_copy(update={"measurement_overlap": 1.0})
        update["variance"] = cfg.variance.model_copy(update={"mcp_weight_share": 1.0 / f})
    return cfg.model_copy(update=update)


def mcps_by_overlap(network: Any, overlap: float) -> Any:
    """The network with its MCPs' image and ground sigmas times ``sqrt(overlap)``.

    ``overlap`` MCPs whose templates share their pixels carry one measurement's
    information: weighted ``1 / overlap`` each, together they count once against the
    other observations and the priors. Fixed (0) and free (inf) ground sigmas stay.
    """
    if overlap <= 1.0:
        return network
    mcp = network.is_kind("mcp")
    k = math.sqrt(overlap)
    obs_sigma = np.array(network.obs_sigma_px, np.float64, copy=True)
    obs_sigma[mcp[network.obs_point]] *= k
    pt_sigma = np.array(network.point_sigma_m, np.float64, copy=True)
    scale = mcp[:, None] & np.isfinite(pt_sigma) & (pt_sigma > 0)
    pt_sigma[scale] *= k
    return replace(network, obs_sigma_px=obs_sigma, point_sigma_m=pt_sigma)


class JitterParameterization(LineScanParameterization):
    """Dense attitude nodes of a strip with the jitter stage's smoothness prior.

    A :class:`~planetref.adjust.models.linescan.LineScanParameterization` of the dense
    camera (positions, interior and placement fixed, attitudes weighted by the declared
    amplitude) whose ``constraints`` are the second differences of every attitude angle
    over consecutive nodes, with weight ``1 / smoothness_sigma_rad(dt)^2``. Coverage is
    never an issue: the prior determines every node.

    Args:
        camera_id: The strip's id.
        camera: The dense camera (:func:`densify`).
        config: The line-scan settings of :func:`jitter_config`.
        jitter: The jitter settings.
        fixed: Hold the strip fixed.
    """

    def __init__(
        self,
        camera_id: str,
        camera: LineScanCamera,
        config: LineScanParameters,
        jitter: JitterConfig,
        *,
        fixed: bool = False,
    ) -> None:
        super().__init__(camera_id, camera, config, fixed=fixed)
        n = camera.n_nodes
        times = camera.line_rates.time(camera.node_lines)
        dt = float(np.median(np.diff(times)))
        self.smooth_sigma_rad = smoothness_sigma_rad(jitter, dt)
        if fixed or n < 3:
            return
        rows = []
        for i in range(1, n - 1):
            for c in range(3, 6):
                rows.append((6 * (i - 1) + c, 6 * i + c, 6 * (i + 1) + c))
        a = np.zeros((len(rows), len(self.x0)))
        r = np.arange(len(rows))
        idx = np.array(rows)
        a[r, idx[:, 0]] = 1.0
        a[r, idx[:, 1]] = -2.0
        a[r, idx[:, 2]] = 1.0
        w = np.full(len(rows), 1.0 / self.smooth_sigma_rad**2)
        self.constraints = (a, w)

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """None: the smoothness prior holds nodes without observations."""
        return []


def attitude_difference(a: LineScanCamera, b: LineScanCamera, lines: F64) -> F64:
    """Small rotation from ``a``'s attitude to ``b``'s in the camera frame (rad).

    ``R_a^T R_b ~ I + [w]x`` at each line; ``w = (roll, pitch, yaw)``, ``(m, 3)``.
    """
    _, ra = a.exterior(lines)
    _, rb = b.exterior(lines)
    d = np.einsum("mji,mjk->mik", ra, rb)
    return _vee(d)


def line_of_sight_difference(
    a: LineScanCamera, b: LineScanCamera, lines: F64, height_m: float = 0.0
) -> F64:
    """Pointing of ``b`` relative to ``a`` as the image sees it (rad), ``(m, 3)``.

    The ground points of the middle CCD's centre pixel at ``lines`` through either
    camera (at ``height_m``), their offset rotated into ``a``'s camera frame and divided
    by the range: ``roll = dy / range``, ``pitch = -dx / range`` (the rotation of ``a``
    that moves its ray by as much). Unlike :func:`attitude_difference` it includes the
    effect of position differences, so attitude errors that compensate position errors
    (invisible in the image) cancel. ``yaw`` is :func:`attitude_difference`'s (the
    centre pixel does not see it).
    """
    lines = np.asarray(lines, np.float64)
    mid = a.ccds[len(a.ccds) // 2]
    sample = np.full(len(lines), 0.5 * mid.n_samples)
    ga = a.image_to_ground(lines, sample, height_m, ccd=mid.name, on_miss="nan")
    gb = b.image_to_ground(lines, sample, height_m, ccd=mid.name, on_miss="nan")
    sa, ra = a.exterior(lines)
    rng = np.linalg.norm(ga - sa, axis=1)
    dc = np.einsum("mji,mj->mi", ra, gb - ga)
    out = attitude_difference(a, b, lines)
    out[:, 0] = dc[:, 1] / rng
    out[:, 1] = -dc[:, 0] / rng
    return out


def true_jitter(series: JitterSeries, dense: LineScanCamera, truth: LineScanCamera) -> F64:
    """The truth's pointing relative to the seed at the series' lines (rad), ``(m, 3)``.

    What the stage should find: the estimate minus its true error, ``w_est -
    line_of_sight_difference(truth, dense)`` (small angles add), so attitude errors that
    only compensate position errors cancel as in the image. Yaw is NaN: the centre
    pixel does not see it, and the seed's yaw (barely observable on a narrow swath)
    may wander by far more than any jitter.
    """
    out = np.asarray(series.angles_rad - line_of_sight_difference(truth, dense, series.line))
    out[:, 2] = np.nan
    return out


def _vee(d: F64) -> F64:
    return 0.5 * np.stack(
        [d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], axis=1
    )


@dataclass(frozen=True)
class JitterResolution:
    """What limits the frequencies the jitter stage can recover (one strip).

    Attributes:
        line_period_s: Seconds per image line.
        node_spacing_lines: Spacing of the dense nodes (lines).
        node_limit_hz: ``1 / (4 dt)``: four nodes per period, where order-4 Lagrange
            interpolation still reproduces a sinusoid's amplitude within a few per cent
            (the Nyquist frequency ``1 / (2 dt)`` is the hard bound).
        mcp_gap_lines: 95 % of the imaged lines lie in gaps between observed lines no
            longer than this (lines; every CCD of the strip together).
        max_gap_lines: Longest gap between observed lines (lines).
        mcp_limit_hz: ``1 / (2 mcp_gap_lines * line_period_s)``: a period must span two
            typical gaps to be sampled.
        support_lines: Along-track extent of one MCP's template (lines; 0: points).
        support_limit_hz: ``0.360 / (support_lines * line_period_s)``: where the
            template's averaging, ``sinc(pi f L)``, measures a sinusoid at 80 % of its
            amplitude (inf without templates).
        band_hz: The prior's band edge (``max_frequency_hz``).
        stagger_lines: Along-track offset between the staggered CCDs (lines): tie points
            between overlapping CCDs see jitter as ``w(t + s) - w(t)``, blind at
            multiples of ``stagger_blind_hz``; MCPs against the reference are not.
        stagger_blind_hz: ``1 / (stagger_lines * line_period_s)``, or ``None`` without
            stagger.
        limit_hz: The resolution limit: the smallest of the node, MCP gap, template
            and band limits.
    """

    line_period_s: float
    node_spacing_lines: float
    node_limit_hz: float
    mcp_gap_lines: float
    max_gap_lines: float
    mcp_limit_hz: float
    support_lines: float
    support_limit_hz: float
    band_hz: float
    stagger_lines: float
    stagger_blind_hz: float | None
    limit_hz: float

    def to_dict(self) -> dict[str, Any]:
        """Plain values (report.json)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def resolution_limit(camera: LineScanCamera, lines: F64, cfg: JitterConfig) -> JitterResolution:
    """The highest jitter frequency one strip's observations and nodes can recover.

    Args:
        camera: The dense camera.
        lines: Observed lines of the strip's inlier observations (every CCD).
        cfg: The jitter settings.
    """
    period = float(np.median(np.diff(camera.line_rates.time(np.array([0.0, 1.0, 2.0])))))
    spacing = float(np.median(np.diff(camera.node_lines)))
    node_limit = 1.0 / (4.0 * spacing * period)
    n_lines = max(c.n_lines for c in camera.ccds)
    obs = np.unique(np.clip(np.asarray(lines, np.float64), 0.0, n_lines))
    edges = np.concatenate([[0.0], obs, [float(n_lines)]])
    gaps = np.sort(np.diff(edges))
    if gaps.size and gaps.sum() > 0:
        covered = np.cumsum(gaps) / gaps.sum()
        g95 = float(gaps[min(int(np.searchsorted(covered, 0.95)), gaps.size - 1)])
    else:
        g95 = float(n_lines)
    g95 = max(g95, 1.0)
    mcp_limit = 1.0 / (2.0 * g95 * period)
    xs = sorted({c.x_mm for c in camera.ccds})
    pitch = camera.ccds[0].pixel_pitch_mm
    stagger = (xs[-1] - xs[0]) / pitch if len(xs) > 1 else 0.0
    blind = 1.0 / (stagger * period) if stagger > 0 else None
    support = 0.0
    support_limit = math.inf
    if cfg.mcp_support_m:
        support = float(cfg.mcp_support_m) / _metres_per_line(camera, n_lines)
        # sinc(x) = 0.8 at x = 1.1311: a template of T seconds measures a sinusoid at
        # f = 1.1311 / (pi T) = 0.360 / T at 80 % of its amplitude.
        support_limit = 0.360 / (support * period)
    return JitterResolution(
        line_period_s=period,
        node_spacing_lines=spacing,
        node_limit_hz=node_limit,
        mcp_gap_lines=g95,
        max_gap_lines=float(gaps[-1]) if gaps.size else float(n_lines),
        mcp_limit_hz=mcp_limit,
        support_lines=support,
        support_limit_hz=support_limit,
        band_hz=float(cfg.max_frequency_hz),
        stagger_lines=float(stagger),
        stagger_blind_hz=blind,
        limit_hz=float(min(node_limit, mcp_limit, support_limit, cfg.max_frequency_hz)),
    )


def _metres_per_line(camera: LineScanCamera, n_lines: int) -> float:
    """Along-track ground distance of one line at the middle CCD's centre (m)."""
    mid = camera.ccds[len(camera.ccds) // 2]
    lines = np.array([0.25, 0.75]) * n_lines
    g = camera.image_to_ground(lines, np.full(2, 0.5 * mid.n_samples), 0.0, ccd=mid.name)
    return float(np.linalg.norm(g[1] - g[0]) / (lines[1] - lines[0]))


@dataclass(frozen=True)
class JitterSeries:
    """The estimated jitter of one strip, at its dense nodes inside the image.

    Attributes:
        camera_id: The strip.
        line: Node lines, ``(m,)``.
        time_s: Their times (s, the camera's time model).
        angles_rad: Jitter ``(roll, pitch, yaw)`` (rad): the dense attitude minus the
            seed's, in the camera frame, ``(m, 3)``.
        sigma_rad: Formal standard deviation of each (rad), ``(m, 3)``.
        resolution: The strip's resolution limit.
        smooth_sigma_rad: The prior's second-difference sigma (rad).
        amplitude_rad: The prior's declared amplitude (rad).
    """

    camera_id: str
    line: F64
    time_s: F64
    angles_rad: F64
    sigma_rad: F64
    resolution: JitterResolution
    smooth_sigma_rad: float
    amplitude_rad: float

    def summary(self) -> dict[str, Any]:
        """Headline numbers (report.json ``jitter`` block)."""
        rms = np.sqrt(np.mean(self.angles_rad**2, axis=0)) * 1e6
        sig = np.sqrt(np.mean(self.sigma_rad**2, axis=0)) * 1e6
        return {
            "n_nodes": len(self.line),
            "rms_urad": {a: float(v) for a, v in zip(AXES, rms, strict=True)},
            "formal_sigma_urad": {a: float(v) for a, v in zip(AXES, sig, strict=True)},
            "smoothness_sigma_urad": self.smooth_sigma_rad * 1e6,
            "amplitude_prior_urad": self.amplitude_rad * 1e6,
            "resolution": self.resolution.to_dict(),
        }


def jitter_series(
    model: JitterParameterization,
    seed_camera: LineScanCamera,
    x: F64,
    covariance: F64,
    obs_lines: F64,
    cfg: JitterConfig,
) -> JitterSeries:
    """The estimated jitter of one strip and its formal sigma.

    Args:
        model: The strip's dense parameterisation.
        seed_camera: The seed's adjusted camera.
        x: The model's adjusted local parameters.
        covariance: Their covariance, ``(n, n)`` (local).
        obs_lines: Lines of the strip's inlier observations.
        cfg: The jitter settings.
    """
    dense = model.build(x)
    n_lines = max(c.n_lines for c in dense.ccds)
    node_lines = np.asarray(dense.node_lines)
    inside = np.flatnonzero((node_lines >= 0.0) & (node_lines <= n_lines))
    lines = node_lines[inside]
    w = attitude_difference(seed_camera, dense, lines)
    # Formal sigma: w is (to first order) a linear map J of the node's angles (the
    # dense camera interpolates its nodes exactly at their lines); J by differences.
    nodes = np.asarray(dense.nodes)[inside]
    base = rotation_matrix(nodes[:, 3], nodes[:, 4], nodes[:, 5])
    h = 1e-7
    jac = np.empty((len(lines), 3, 3))
    for j in range(3):
        ang = nodes[:, 3:].copy()
        ang[:, j] += h
        pert = rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
        jac[:, :, j] = _vee(np.einsum("mji,mjk->mik", base, pert)) / h
    sigma = np.empty((len(lines), 3))
    for m, i in enumerate(inside):
        s = slice(6 * i + 3, 6 * i + 6)
        c = covariance[s, s]
        sigma[m] = np.sqrt(np.maximum(np.diag(jac[m] @ c @ jac[m].T), 0.0))
    return JitterSeries(
        camera_id=model.camera_id,
        line=lines,
        time_s=np.asarray(dense.line_rates.time(lines), np.float64),
        angles_rad=w,
        sigma_rad=sigma,
        resolution=resolution_limit(dense, obs_lines, cfg),
        smooth_sigma_rad=model.smooth_sigma_rad,
        amplitude_rad=cast_float(cfg.amplitude_rad),
    )


def dense_cameras(cameras: dict[str, Any], cfg: AdjustConfig) -> dict[str, Any]:
    """Seed cameras with dense nodes (native line-scan strips not held fixed)."""
    out = {}
    for cid, cam in cameras.items():
        if isinstance(cam, LineScanCamera) and cid not in cfg.fixed_cameras:
            out[cid] = densify(cam, cfg.jitter.node_spacing_lines)
        else:
            out[cid] = cam
    return out


def replace_cameras(network: Any, cameras: dict[str, Any]) -> Any:
    """The network with other cameras (same ids, CCDs and image sizes)."""
    return replace(network, cameras=tuple(cameras[c] for c in network.camera_ids))
