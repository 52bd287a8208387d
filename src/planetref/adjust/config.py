"""Typed configuration of the bundle adjustment.

Every unknown of the adjustment belongs to a *block* (the positions of a strip's
orientation nodes, their attitudes, the interior orientation, the offset of a CSM
image's pointing...), and every block is ``free`` (estimated without a-priori
information), ``fixed`` (kept at its initial value) or ``weighted`` (estimated with an
a-priori standard deviation around its initial value, a pseudo-observation).

Units are in the field names: ``_m`` metres, ``_mm`` millimetres, ``_rad`` radians,
``_m_s`` metres per second, ``_rad_s`` radians per second, ``_rad_s2`` radians per second
squared, ``_px`` pixels. A sigma may also be written as a string with an explicit unit,
converted to the field's unit: ``"20 urad"``, ``"5 arcsec"``, ``"0.1 mrad"``,
``"2 km"``, ``"10 um"``, ``"3 arcsec/s"``. Recognised units: lengths ``m km cm mm um``;
angles ``rad mrad urad µrad arcsec deg``; rates of either with ``/s``; angular
accelerations with ``/s2`` (or ``/s^2``).

All models are frozen pydantic models that reject unknown keys, so a typo in a TOML
file is an error and not a silent default.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, model_validator

from planetref.adjust.rpc_config import RpcParameters
from planetref.runtime.settings import Settings, validate_settings

__all__ = [
    "DEFAULT_REFERENCE_PATCH_M",
    "DEFAULT_TIE_SIGMA_M",
    "AdjustConfig",
    "AngleBlock",
    "AngularAccelerationBlock",
    "AngularRateBlock",
    "CcdPlacementBlock",
    "CsmParameters",
    "DiagnosticsConfig",
    "FocalLengthBlock",
    "InteriorBlock",
    "JitterConfig",
    "LengthBlock",
    "LineScanParameters",
    "Mode",
    "ObservationConfig",
    "OutlierConfig",
    "SolverConfig",
    "SystematicConfig",
    "VarianceConfig",
    "VelocityBlock",
    "parse_quantity",
    "validate_config",
]

Mode = Literal["free", "fixed", "weighted"]

_LENGTH = {"m": 1.0, "km": 1e3, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_ANGLE = {
    "rad": 1.0,
    "mrad": 1e-3,
    "urad": 1e-6,
    "µrad": 1e-6,
    "arcsec": math.pi / 648000.0,
    "deg": math.pi / 180.0,
}
_KINDS: dict[str, dict[str, float]] = {
    "m": _LENGTH,
    "mm": {k: v * 1e3 for k, v in _LENGTH.items()},
    "rad": _ANGLE,
    "m/s": {f"{k}/s": v for k, v in _LENGTH.items()},
    "rad/s": {f"{k}/s": v for k, v in _ANGLE.items()},
    "rad/s2": {
        **{f"{k}/s2": v for k, v in _ANGLE.items()},
        **{f"{k}/s^2": v for k, v in _ANGLE.items()},
    },
}
_QUANTITY = re.compile(r"^\s*([-+0-9.eE]+)\s*([^\s]+)\s*$")


def parse_quantity(value: Any, unit: str) -> float | None:
    """A number in ``unit``, from a number (already in ``unit``) or a string with a unit.

    Args:
        value: ``None``, a number, or a string such as ``"20 urad"``.
        unit: The target unit: ``"m"``, ``"mm"``, ``"rad"``, ``"m/s"``, ``"rad/s"`` or
            ``"rad/s2"``.

    Returns:
        The value converted to ``unit`` (``None`` stays ``None``).

    Raises:
        ValueError: For an unknown unit or a malformed string (pydantic turns it into a
            validation error naming the field).
    """
    if value is None:
        return None
    if isinstance(value, bool):
        raise ValueError(f"expected a number or a string with a unit, got {value!r}")
    if isinstance(value, int | float):
        return float(value)
    if isinstance(value, str):
        m = _QUANTITY.match(value)
        table = _KINDS[unit]
        if m is None or m.group(2) not in table:
            raise ValueError(
                f"expected '<number> <unit>' with a unit among {sorted(table)}, got {value!r}"
            )
        try:
            number = float(m.group(1))
        except ValueError:
            raise ValueError(f"malformed number in {value!r}") from None
        return number * table[m.group(2)]
    raise ValueError(f"expected a number or a string with a unit, got {value!r}")


def _unit(unit: str) -> BeforeValidator:
    return BeforeValidator(lambda v: parse_quantity(v, unit))


Metres = Annotated[float | None, _unit("m")]
Millimetres = Annotated[float | None, _unit("mm")]
Radians = Annotated[float | None, _unit("rad")]
MetresPerSecond = Annotated[float | None, _unit("m/s")]
RadiansPerSecond = Annotated[float | None, _unit("rad/s")]
RadiansPerSecond2 = Annotated[float | None, _unit("rad/s2")]


class _Block(Settings):
    """Common checks: a weighted block needs a positive finite sigma."""

    mode: Mode = "free"

    def _sigma_values(self) -> dict[str, float | None]:
        return {k: getattr(self, k) for k in type(self).model_fields if k.startswith("sigma")}

    @model_validator(mode="after")
    def _check_sigma(self) -> _Block:
        for name, value in self._sigma_values().items():
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value}")
            if self.mode == "weighted" and value is None:
                raise ValueError(f"mode 'weighted' needs {name}")
        return self


class LengthBlock(_Block):
    """A block of lengths (positions, position offsets).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_m: A-priori standard deviation (metres), required when weighted.
    """

    sigma_m: Metres = None


class VelocityBlock(_Block):
    """A block of rates of lengths (position drift).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_m_s: A-priori standard deviation (metres per second).
    """

    sigma_m_s: MetresPerSecond = None


class AngleBlock(_Block):
    """A block of angles (attitudes, pointing offsets).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_rad: A-priori standard deviation (radians; e.g. ``"20 urad"``).
    """

    sigma_rad: Radians = None


class AngularRateBlock(_Block):
    """A block of angular rates (pointing drift).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_rad_s: A-priori standard deviation (radians per second).
    """

    sigma_rad_s: RadiansPerSecond = None


class AngularAccelerationBlock(_Block):
    """A block of angular accelerations (quadratic pointing term).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_rad_s2: A-priori standard deviation (radians per second squared).
    """

    sigma_rad_s2: RadiansPerSecond2 = None


class FocalLengthBlock(_Block):
    """A focal-length correction.

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted``.
        sigma_mm: A-priori standard deviation (millimetres).
    """

    sigma_mm: Millimetres = None


class InteriorBlock(_Block):
    """Interior orientation (principal point ``x0, y0`` and focal length ``f``).

    Attributes:
        mode: ``free``, ``fixed`` or ``weighted`` (applies to all three).
        scope: ``strip``: one ``(x0, y0, f)`` per strip, shared by its CCDs; ``ccd``: one
            per CCD (realised in the native camera file by moving and scaling each CCD
            in the focal plane, which is exactly equivalent).
        sigma_principal_point_mm: A-priori sigma of ``x0`` and ``y0`` (mm).
        sigma_focal_length_mm: A-priori sigma of ``f`` (mm).
    """

    mode: Mode = "fixed"
    scope: Literal["strip", "ccd"] = "strip"
    sigma_principal_point_mm: Millimetres = None
    sigma_focal_length_mm: Millimetres = None


class CcdPlacementBlock(_Block):
    """Each CCD's placement in the focal plane (``x_mm``, ``y_mm``, ``angle_rad``).

    Estimated per CCD (self-calibration of a multi-CCD focal plane). A placement moves a
    CCD's image as the attitudes and the principal point move all of them, so it is
    only separable from those with a-priori sigmas (``weighted``) or with a reference
    CCD held fixed.

    Attributes:
        mode: ``fixed`` (default: the camera file's placement), ``free`` or ``weighted``.
        sigma_offset_mm: A-priori sigma of ``x_mm`` and ``y_mm`` (mm).
        sigma_angle_rad: A-priori sigma of ``angle_rad`` (radians).
        reference_ccd: Name of a CCD whose placement stays fixed (the focal-plane
            datum), or ``None``.
    """

    mode: Mode = "fixed"
    sigma_offset_mm: Millimetres = None
    sigma_angle_rad: Radians = None
    reference_ccd: str | None = None


class LineScanParameters(Settings):
    """Unknowns of a native line-scan strip (:class:`~planetref.camera.linescan.LineScanCamera`).

    Attributes:
        position: The ``X, Y, Z`` of every orientation node (metres).
        attitude: The ``phi, omega, kappa`` of every node (radians).
        interior: Interior orientation.
        ccd_placement: Per-CCD placement in the focal plane (fixed by default).
        min_obs_per_node: A node that is not fixed needs at least this many observations
            near it (nearer to it than to any other node: where its interpolation weight
            dominates); see ``weak_nodes``.
        weak_nodes: What to do with nodes below ``min_obs_per_node``: ``error`` raises an
            :class:`~planetref.errors.AdjustmentError` naming them; ``weight`` ties them
            to their initial values with ``weak_node_position_sigma_m`` and
            ``weak_node_attitude_sigma_rad`` and logs a warning; ``smooth`` makes the
            correction of a weak node continue the corrections of its neighbours
            towards the strip's centre (zero second difference, within
            ``weak_node_smooth_sigma_m`` / ``weak_node_smooth_sigma_rad``) and logs a
            warning. ``smooth`` (the default) suits nodes beyond the observed lines:
            their initial values are as wrong as the rest of the trajectory, so pulling
            them back to those values would bend the adjusted trajectory near the image
            ends.
        weak_node_position_sigma_m: Sigma for weak nodes' positions (metres).
        weak_node_attitude_sigma_rad: Sigma for weak nodes' attitudes (radians).
        weak_node_smooth_sigma_m: Sigma of the second difference of position
            corrections at a weak node (metres), with ``smooth``.
        weak_node_smooth_sigma_rad: The same for attitude corrections (radians).
    """

    position: LengthBlock = LengthBlock(mode="weighted", sigma_m=100.0)
    attitude: AngleBlock = AngleBlock(mode="free")
    interior: InteriorBlock = InteriorBlock()
    ccd_placement: CcdPlacementBlock = CcdPlacementBlock()
    min_obs_per_node: int = Field(3, ge=0)
    weak_nodes: Literal["error", "weight", "smooth"] = "smooth"
    weak_node_position_sigma_m: Metres = 100.0
    weak_node_attitude_sigma_rad: Radians = 1e-4
    weak_node_smooth_sigma_m: Metres = 0.1
    weak_node_smooth_sigma_rad: Radians = 1e-7


class CsmParameters(Settings):
    """Per-image corrections of CSM/ALE line-scan cameras (usgscsm's adjustable parameters).

    Position: offset and linear drift along the in-track, cross-track and radial axes.
    Pointing: offset, rate and acceleration of the omega, phi, kappa angles in the
    sensor frame. The sigmas are physical; they are converted to usgscsm's parameter
    scaling (metres) with each image's half duration, flying height and half swath.

    Attributes:
        position_offset: Sensor position offset (metres).
        position_rate: Sensor position drift (metres per second).
        pointing_offset: Pointing angle offsets (radians).
        pointing_rate: Pointing angle rates (radians per second).
        pointing_acceleration: Pointing angle accelerations (radians per second²).
        focal_length: Focal length correction (millimetres).
        fd_step_m: Central finite-difference step of the corrections, in usgscsm's
            metre units (the correction enters linearly to first order, so the step
            barely matters; 1 m is a fraction of a pixel for orbital cameras).
        fd_ground_step_m: Finite-difference step for ground coordinates (metres).
    """

    position_offset: LengthBlock = LengthBlock(mode="fixed")
    position_rate: VelocityBlock = VelocityBlock(mode="fixed")
    pointing_offset: AngleBlock = AngleBlock(mode="weighted", sigma_rad=1e-3)
    pointing_rate: AngularRateBlock = AngularRateBlock(mode="weighted", sigma_rad_s=1e-4)
    pointing_acceleration: AngularAccelerationBlock = AngularAccelerationBlock(mode="fixed")
    focal_length: FocalLengthBlock = FocalLengthBlock(mode="fixed")
    fd_step_m: float = Field(1.0, gt=0.0)
    fd_ground_step_m: float = Field(1.0, gt=0.0)


#: Default a-priori sigma of tie-point coordinates (metres per axis), as ISIS jigsaw
#: is commonly run: loose enough for any orbital camera's initial error, tight enough
#: that the network's datum cannot float (points rising kilometres to absorb a bias).
DEFAULT_TIE_SIGMA_M = 200.0


class ObservationConfig(Settings):
    """Default weights of observations and ground points.

    Attributes:
        sigma_px: Standard deviation of an image measure (pixels), for observations
            that carry none.
        mcp_ground: How the ground point of an MCP enters: ``fixed`` (taken as known) or
            ``weighted`` by ``mcp_ground_sigma_m`` (e.g. the reference GSD). MCP runs of
            the pipeline weight every MCP by its own a-priori sigmas (ortho GSD, DEM
            resolution and slope) whatever this says.
        mcp_ground_sigma_m: Ground sigma of weighted MCPs (metres, per axis).
        tie_apriori_sigma_m: A-priori sigma of tie-point coordinates (metres, per axis;
            default :data:`DEFAULT_TIE_SIGMA_M`); a network file's own sigmas win; ``None``
            leaves them free (the datum then rests on the camera priors alone and may
            float).
        min_tie_observations: A tie point (free, or under its a-priori sigma) needs at
            least this many observations (2); points with fewer are left out of the
            adjustment (status ``unusable``).
    """

    sigma_px: float = Field(1.0, gt=0.0)
    mcp_ground: Literal["fixed", "weighted"] = "fixed"
    mcp_ground_sigma_m: Metres = None
    tie_apriori_sigma_m: Metres = DEFAULT_TIE_SIGMA_M
    min_tie_observations: int = Field(2, ge=2)

    @model_validator(mode="after")
    def _check(self) -> ObservationConfig:
        if self.mcp_ground == "weighted" and self.mcp_ground_sigma_m is None:
            raise ValueError("mcp_ground 'weighted' needs mcp_ground_sigma_m")
        for name in ("mcp_ground_sigma_m", "tie_apriori_sigma_m"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        return self


class VarianceConfig(Settings):
    """Variance component estimation (VCE) of the observation groups.

    Groups: the image measures of MCPs and of tie points, per camera and CCD; the
    a-priori ground coordinates of weighted MCPs, planimetric and height apart. Each
    group's sigmas are scaled by ``sqrt(v^T P v / r)`` of the group (``r`` its
    redundancy, the sum of its redundancy numbers) and the adjustment is repeated until
    every factor is within ``tolerance`` of 1 (Foerstner's iteration), so that the final
    sigma0 is ~1 and the covariances mean what they say.

    Attributes:
        enabled: Estimate the variance components.
        max_iterations: Most re-weighting iterations.
        tolerance: Stop when every group's factor ``sigma_g`` is within this of 1.
        min_redundancy: A group with less redundancy than this keeps its a-priori
            sigmas (its factor is not estimable) and is reported as such.
        min_sigma_px: Image sigmas are not scaled below this (pixels): a group without
            noise (simulated, or duplicated measures) would otherwise take all weight.
        min_sigma_m: The same floor for a-priori ground sigmas (metres).
        max_step: A group's sigmas change by at most this factor (or its inverse) per
            iteration, which keeps the re-weighted adjustments well conditioned.
        mcp_weight_share: The MCP groups (image and ground) are adjusted with this share
            of the weight of their estimated sigma: ``1 / measurement_overlap`` when
            dense templates share their errors and other observations (CCD-overlap
            ties) must not be outweighed by MCPs counted many times over. Their factor
            is ``sqrt(v^T P v / (share r))``, so VCE still estimates the MCPs' own
            sigma; 1 (the default) is ordinary VCE. The jitter stage sets it.
    """

    enabled: bool = True
    max_iterations: int = Field(10, ge=1)
    tolerance: float = Field(0.02, gt=0.0)
    min_redundancy: float = Field(5.0, ge=0.0)
    min_sigma_px: float = Field(0.02, gt=0.0)
    min_sigma_m: float = Field(0.01, gt=0.0)
    max_step: float = Field(5.0, gt=1.0)
    mcp_weight_share: float = Field(1.0, gt=0.0, le=1.0)


class DiagnosticsConfig(Settings):
    """Thresholds of the warnings about the datum and the estimability.

    Attributes:
        point_shift_sigmas: Warn when a weighted point moves more than this many of its
            a-priori sigmas.
        camera_shift_m: Warn when a camera's ground footprint moves more than this
            (metres, largest over a grid of its image).
        max_correlation: Warn when two parameters correlate above this (absolute).
        separable_sigma_ratio: A self-calibration parameter is reported *not separable*
            when its a-posteriori sigma is more than this fraction of its a-priori
            sigma (the observations hardly improved on the prior) or when it correlates
            above ``max_correlation`` with another parameter. The sigmas are those of
            the full covariance (with the declared correlated errors,
            :class:`SystematicConfig`).
        check_self_calibration: When an optional calibration block (interior, CCD
            placement) is adjusted and there are check observations, repeat the
            adjustment without it and warn when the block raises the check error.
    """

    point_shift_sigmas: float = Field(3.0, gt=0.0)
    camera_shift_m: float = Field(100.0, gt=0.0)
    max_correlation: float = Field(0.99, gt=0.0, le=1.0)
    separable_sigma_ratio: float = Field(0.5, gt=0.0, le=1.0)
    check_self_calibration: bool = True


class SolverConfig(Settings):
    """Levenberg-Marquardt settings.

    Attributes:
        max_iterations: Most LM iterations per outlier round.
        ftol: Stop when the relative decrease of the cost is below this.
        xtol: Stop when every step is below this many standard deviations of its
            parameter (unit weight: ``sqrt(S^-1_ii)`` of the reduced system for camera
            parameters, ``1/sqrt(V_ii)`` for point coordinates).
        initial_lambda: Initial Marquardt damping (relative to the diagonal).
        min_lambda: Damping below which the solver takes pure Gauss-Newton steps.
        max_lambda: Damping beyond which the solver gives up (diverged).
        loss: Robust loss: ``linear`` (plain least squares), ``huber`` or ``cauchy``,
            applied by iteratively reweighted least squares to the normalised residual
            length of each observation.
        loss_scale_px: Scale of the robust loss in pixels; ``None`` estimates it at the
            start of every outlier round from the median absolute residual (MAD).
        loss_threshold: The loss turns from quadratic to robust at this many scales.
        loss_rounds: ``first``: the robust loss protects the first outlier round only
            (before any rejection), later rounds are plain least squares on the inliers,
            as the seed's rule defines the solution; ``all``: every round is robust.
        chunk_size: Observations evaluated at once (memory/speed trade-off).
        threads: Threads evaluating and accumulating chunks in parallel (``None``: the
            process's thread budget, :func:`planetref.runtime.threads.compute_threads`). Each
            thread sums its own contiguous share of the chunks; the shares are added
            in order, so a given thread count gives the same numbers every run.
        min_rcond: Reciprocal condition number of the (Jacobi-scaled) reduced normal
            matrix below which the problem is declared degenerate.
        rigid_start: Before the first outlier round, solve for one correction common
            to every orientation node of each line-scan strip (a rigid shift and
            rotation of the trajectory), then free the nodes. A line scanner is
            linearised at the projected line of each observation: from an initial
            camera a kilometre off along track the projected lines lag the measured
            ones by thousands of lines, the nodes beyond them get no partials (a null
            direction) and the node-wise solve crawls; the rigid solve removes the
            offset first.
    """

    max_iterations: int = Field(50, ge=1)
    ftol: float = Field(1e-12, ge=0.0)
    xtol: float = Field(1e-8, ge=0.0)
    initial_lambda: float = Field(1e-8, ge=0.0)
    min_lambda: float = Field(1e-10, gt=0.0)
    max_lambda: float = Field(1e12, gt=0.0)
    loss: Literal["linear", "huber", "cauchy"] = "huber"
    loss_scale_px: float | None = Field(None, gt=0.0)
    loss_threshold: float = Field(3.0, gt=0.0)
    loss_rounds: Literal["first", "all"] = "first"
    chunk_size: int = Field(32768, ge=256)
    threads: int | None = Field(None, ge=1)
    min_rcond: float = Field(1e-14, gt=0.0, lt=1.0)
    rigid_start: bool = True


class OutlierConfig(Settings):
    """The seed's outlier rule: inlier if the reprojection error is below k x RMSE.

    Attributes:
        enabled: Apply the rule (otherwise every valid observation is an inlier).
        k_rmse: The factor ``k`` (3 in the seed).
        max_rounds: Most adjust-and-reject rounds before giving up on a stable set.
    """

    enabled: bool = True
    k_rmse: float = Field(3.0, gt=0.0)
    max_rounds: int = Field(20, ge=1)


#: Patch size (m) of the reference's correlated error when none is declared.
DEFAULT_REFERENCE_PATCH_M = 1000.0


class SystematicConfig(Settings):
    """Correlated (systematic) errors the adjustment cannot estimate, and their accuracy.

    Each MCP's a-priori sigmas describe its own random error; errors that many MCPs share
    are not averaged away by their number, so the covariance takes them in as *consider*
    parameters (Schmidt-Kalman): parameters held at their nominal value, whose declared
    a-priori sigma is propagated through the sensitivity of the adjusted cameras to them
    (see docs/adjust.md, "Correlated errors"). They change the covariance, never the
    solution.

    * the reference's planimetric error: one 2-D offset (east, north) per square patch
      of ``reference_patch_m`` of the ground, shared by the MCPs in it, sigma
      ``reference_sigma_m`` per axis (the reference ortho's absolute accuracy, as its
      producer states it);
    * the CCDs' placement: one 2-D image offset (line, sample) per CCD, shared by every
      observation in it, sigma ``ccd_offset_sigma_px`` per axis (the calibration's
      accuracy), when the placement is not estimated;
    * the matcher's error common to a matching tile: one 2-D image offset (line,
      sample) per tile (:attr:`~planetref.control.network.Network.obs_tile`), shared by
      the tile's MCPs (a detector's sub-cell phase, the tile's homography), sigma
      ``tile_offset_sigma_px`` per axis, by default estimated from the tiles' residual
      sums (:func:`planetref.adjust.consider.estimate_key_sigma`).

    Attributes:
        reference_sigma_m: Per-axis sigma (m) of the reference's planimetric error common
            to a patch; ``None`` or 0: none.
        reference_patch_m: Size of the patches (m): the distance over which the
            reference's error is one (a source image of a mosaic, the wavelength of its
            warps); ``None``: :data:`DEFAULT_REFERENCE_PATCH_M`.
        ccd_offset_sigma_px: Per-axis sigma (image pixels) of each CCD's placement error
            left by the calibration; ``None`` or 0: none. Not used for cameras whose CCD
            placement is estimated (weighted or free).
        tile_offset_sigma_px: Per-axis sigma (image pixels) of a matching tile's common
            offset: a number, ``"estimate"`` (default: from the tiles' residuals, per
            axis, after the other terms' share; 0 where they show nothing more), or
            ``None``/0: none. Networks without tiles have no such term.
        tile_offset_axes: ``"pooled"`` (default): one estimated sigma for both axes;
            ``"per-axis"``: line and sample estimated apart (needs many tiles).
        measurement_overlap: Mean number of observations per independent measurement
            (dense area-based matches sharing template pixels, see
            :func:`planetref.control.networks.template_overlap`); the measurements'
            share of the covariance is multiplied by it. 1: independent.
    """

    reference_sigma_m: Metres = None
    reference_patch_m: Metres = None
    ccd_offset_sigma_px: float | None = Field(None, ge=0.0)
    tile_offset_sigma_px: Annotated[float, Field(ge=0.0)] | Literal["estimate"] | None = "estimate"
    tile_offset_axes: Literal["pooled", "per-axis"] = "pooled"
    measurement_overlap: float = Field(1.0, ge=1.0)

    @model_validator(mode="after")
    def _positive(self) -> SystematicConfig:
        if self.reference_sigma_m is not None and self.reference_sigma_m < 0:
            raise ValueError("reference_sigma_m must be >= 0")
        if self.reference_patch_m is not None and not self.reference_patch_m > 0:
            raise ValueError("reference_patch_m must be > 0")
        return self

    @property
    def patch_m(self) -> float:
        """The patch size in use (m)."""
        return (
            DEFAULT_REFERENCE_PATCH_M if self.reference_patch_m is None else self.reference_patch_m
        )


class JitterConfig(Settings):
    """The jitter stage: high-frequency attitude on dense nodes after the seed's adjustment.

    Native line-scan strips are re-sampled on nodes ``node_spacing_lines`` apart and their
    attitudes adjusted again (positions, interior and CCD placement held at the seed's
    solution) under a smoothness prior derived from the declared jitter: each attitude
    correction is weighted towards the seed with ``amplitude_rad``, and its second
    difference over three nodes with ``smoothness_sigma_rad`` (by default
    ``amplitude_rad * 4 sin^2(pi max_frequency_hz dt)``, ``dt`` the node spacing in
    seconds: the second difference of a sinusoid of that amplitude at the band's edge).
    See :mod:`planetref.adjust.jitter` and docs/adjust.md ("Jitter").

    Attributes:
        enabled: Run the stage (off by default).
        node_spacing_lines: Line spacing of the dense nodes (lines).
        amplitude_rad: Declared jitter amplitude per axis (radians; e.g. ``"5 urad"``).
        max_frequency_hz: Upper edge of the jitter band (Hz) the prior lets through.
        smoothness_sigma_rad: Sigma of the second difference of an attitude correction
            over consecutive nodes (radians); ``None``: derived as above.
        mcp_support_m: Ground size (m) of the pixels one MCP is computed from (an area
            matcher's template; ``georef`` sets it from the matcher); ``None``: point
            measurements. A template averages the jitter over its along-track extent
            ``L``: a sinusoid of frequency ``f`` is measured ``sinc(pi f L / v)`` times
            its amplitude (``v`` the ground speed), which bounds the resolution limit.
        keep: ``if_check_improves`` (default): keep the dense solution only when the
            held-out check observations fit it better than the seed's (otherwise the
            seed's solution is the result, with a warning); ``always``.
    """

    enabled: bool = False
    node_spacing_lines: int = Field(32, ge=2)
    amplitude_rad: Radians = 5e-6
    max_frequency_hz: float = Field(20.0, gt=0.0)
    smoothness_sigma_rad: Radians = None
    mcp_support_m: Metres = None
    keep: Literal["if_check_improves", "always"] = "if_check_improves"

    @model_validator(mode="after")
    def _check(self) -> JitterConfig:
        for name in ("amplitude_rad", "smoothness_sigma_rad", "mcp_support_m"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        if self.amplitude_rad is None:
            raise ValueError("amplitude_rad is required")
        return self


class AdjustConfig(Settings):
    """Everything the adjustment can be told.

    Attributes:
        linescan: Unknowns of native line-scan strips.
        csm: Unknowns of CSM/ALE line-scan images.
        rpc: Unknowns of RPC images (the image-space bias model).
        fixed_cameras: Ids of cameras (strips or images) held fixed entirely.
        observations: Default weights of observations and ground points.
        solver: Levenberg-Marquardt settings.
        outliers: The outlier rule.
        variance: Variance component estimation.
        diagnostics: Thresholds of the datum and estimability warnings.
        systematic: Correlated errors taken into the covariance (consider parameters).
        jitter: The jitter stage (dense attitude nodes after the seed's adjustment).
    """

    linescan: LineScanParameters = LineScanParameters()
    csm: CsmParameters = CsmParameters()
    rpc: RpcParameters = RpcParameters()
    fixed_cameras: tuple[str, ...] = ()
    observations: ObservationConfig = ObservationConfig()
    solver: SolverConfig = SolverConfig()
    outliers: OutlierConfig = OutlierConfig()
    variance: VarianceConfig = VarianceConfig()
    diagnostics: DiagnosticsConfig = DiagnosticsConfig()
    systematic: SystematicConfig = SystematicConfig()
    jitter: JitterConfig = JitterConfig()


def validate_config(data: Any, *, source: str | None = None) -> AdjustConfig:
    """Validate a plain mapping (e.g. a TOML table) into an :class:`AdjustConfig`.

    Args:
        data: The mapping, or an :class:`AdjustConfig` (returned unchanged).
        source: File the mapping came from, for messages.

    Returns:
        The validated configuration.

    Raises:
        InputError: Naming the source, the first offending field and what was expected.
    """
    if isinstance(data, AdjustConfig):
        return data
    return validate_settings(AdjustConfig, data, source=source, what="adjustment configuration")
