"""The RPC00B model: coefficients, normalisation, projection and localisation.

Model
-----
An RPC00B maps normalised ground coordinates ``L = (lon - LONG_OFF) / LONG_SCALE``,
``P = (lat - LAT_OFF) / LAT_SCALE``, ``H = (h - HEIGHT_OFF) / HEIGHT_SCALE`` to
normalised image coordinates ``r = LINE_NUM(P, L, H) / LINE_DEN(P, L, H)`` (same for
the sample), each a ratio of cubic polynomials with 20 terms in the order of the NITF
RPC00B specification, which is also GDAL's (``RPCComputeTerms`` in
``alg/gdal_rpc.cpp``)::

    1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³

Pixel convention
----------------
Raw RPC image coordinates ``r * LINE_SCALE + LINE_OFF`` put the *centre* of the first
pixel at 0. GDAL converts them to its own convention (top-left corner of the first
pixel at 0) by adding half a pixel, in ``RPCTransformPoint`` of ``alg/gdal_rpc.cpp``::

    *pdfPixel = dfResultX * SAMP_SCALE + SAMP_OFF + 0.5;
    *pdfLine  = dfResultY * LINE_SCALE + LINE_OFF + 0.5;

GDAL has no option that switches this off. planetref's convention is GDAL's (see
:mod:`planetref.camera.base`), so ``planetref line = raw line + 0.5``, and
:class:`RpcCamera` agrees with ``rasterio.transform.RPCTransformer`` to round-off.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.rpc.terms import terms, terms_dh, terms_dl, terms_dp
from planetref.errors import (
    InputError,
)
from planetref.geometry.geodesy import (
    wrap_longitude,
)

__all__ = ["Rpc"]


# GDAL metadata names of the scalar fields, in GDAL's _RPC.TXT order, with the
# attribute of Rpc and the DigitalGlobe .RPB keyword of each.
SCALARS: tuple[tuple[str, str, str], ...] = (
    ("ERR_BIAS", "err_bias", "errBias"),
    ("ERR_RAND", "err_rand", "errRand"),
    ("LINE_OFF", "line_off", "lineOffset"),
    ("SAMP_OFF", "samp_off", "sampOffset"),
    ("LAT_OFF", "lat_off", "latOffset"),
    ("LONG_OFF", "long_off", "longOffset"),
    ("HEIGHT_OFF", "height_off", "heightOffset"),
    ("LINE_SCALE", "line_scale", "lineScale"),
    ("SAMP_SCALE", "samp_scale", "sampScale"),
    ("LAT_SCALE", "lat_scale", "latScale"),
    ("LONG_SCALE", "long_scale", "longScale"),
    ("HEIGHT_SCALE", "height_scale", "heightScale"),
)


COEFFS: tuple[tuple[str, str, str], ...] = (
    ("LINE_NUM_COEFF", "line_num_coeff", "lineNumCoef"),
    ("LINE_DEN_COEFF", "line_den_coeff", "lineDenCoef"),
    ("SAMP_NUM_COEFF", "samp_num_coeff", "sampNumCoef"),
    ("SAMP_DEN_COEFF", "samp_den_coeff", "sampDenCoef"),
)


OPTIONAL = ("err_bias", "err_rand")


_SCALES = ("line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale")


N_TERMS = 20


# --------------------------------------------------------------------------- model


@dataclass(frozen=True)
class Rpc:
    """An RPC00B rational polynomial camera model, as GDAL and the NITF standard define it.

    Offsets and scales are in the units of the raw RPC: image coordinates in pixels with
    the centre of the first pixel at 0 (see the module docstring), longitude and
    latitude in degrees, heights in metres above the body's ellipsoid.

    Attributes:
        line_off: LINE_OFF, pixels.
        samp_off: SAMP_OFF, pixels.
        lat_off: LAT_OFF, degrees.
        long_off: LONG_OFF, degrees (east positive).
        height_off: HEIGHT_OFF, metres.
        line_scale: LINE_SCALE, pixels (non-zero).
        samp_scale: SAMP_SCALE, pixels (non-zero).
        lat_scale: LAT_SCALE, degrees (non-zero).
        long_scale: LONG_SCALE, degrees (non-zero).
        height_scale: HEIGHT_SCALE, metres (non-zero).
        line_num_coeff: The 20 LINE_NUM_COEFF coefficients.
        line_den_coeff: The 20 LINE_DEN_COEFF coefficients.
        samp_num_coeff: The 20 SAMP_NUM_COEFF coefficients.
        samp_den_coeff: The 20 SAMP_DEN_COEFF coefficients.
        err_bias: ERR_BIAS, metres (-1 for unknown), or None when absent.
        err_rand: ERR_RAND, metres (-1 for unknown), or None when absent.

    Raises:
        InputError: If a number is not finite, a scale is zero, a coefficient list does
            not hold exactly 20 numbers or a denominator is identically zero.
    """

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num_coeff: tuple[float, ...]
    line_den_coeff: tuple[float, ...]
    samp_num_coeff: tuple[float, ...]
    samp_den_coeff: tuple[float, ...]
    err_bias: float | None = None
    err_rand: float | None = None

    def __post_init__(self) -> None:
        _validate(self, path=None, names={f.name: f.name for f in fields(self)})

    @cached_property
    def _coeff_array(self) -> NDArray[np.float64]:
        # (20, 4): line num, line den, samp num, samp den, so one matrix product
        # evaluates the four polynomials.
        return np.array(
            [self.line_num_coeff, self.line_den_coeff, self.samp_num_coeff, self.samp_den_coeff],
            dtype=np.float64,
        ).T

    # -- conversions ----------------------------------------------------------------

    def to_gdal(self) -> dict[str, str]:
        """The model as GDAL ``RPC`` metadata (names and strings as in GDAL's RFC 22).

        Numbers use Python's shortest round-trip form, so GDAL reads back the same
        doubles. ``ERR_BIAS``/``ERR_RAND`` are left out when None.

        Returns:
            A dict suitable for ``rasterio.open(..., rpcs=...)`` or ``SetMetadata``.
        """
        out: dict[str, str] = {}
        for gdal_name, attr, _ in SCALARS:
            value = getattr(self, attr)
            if value is not None:
                out[gdal_name] = fmt(value)
        for gdal_name, attr, _ in COEFFS:
            out[gdal_name] = " ".join(fmt(v) for v in getattr(self, attr))
        return out

    @classmethod
    def from_gdal(
        cls, metadata: Mapping[str, str], *, path: str | os.PathLike[str] | None = None
    ) -> Rpc:
        """Parse GDAL ``RPC`` domain metadata (e.g. ``src.tags(ns="RPC")``).

        Unlike ``rasterio.rpc.RPC.from_gdal`` this rejects coefficient lists that do not
        hold exactly 20 numbers and values that are not numbers.

        Args:
            metadata: GDAL RPC metadata items; extra items (``MIN_LONG``...) are ignored.
            path: The file the metadata came from, for error messages.

        Raises:
            InputError: Naming the file and the field at fault.
        """
        upper = {str(k).upper(): str(v) for k, v in metadata.items()}
        values: dict[str, object] = {}
        for gdal_name, attr, _ in SCALARS:
            raw = upper.get(gdal_name)
            if raw is None or (attr in OPTIONAL and not raw.strip()):
                if attr in OPTIONAL:
                    continue
                raise InputError("missing", path=path, field=gdal_name)
            values[attr] = parse_number(raw, path, gdal_name)
        for gdal_name, attr, _ in COEFFS:
            raw = upper.get(gdal_name)
            if raw is None:
                raise InputError("missing", path=path, field=gdal_name)
            values[attr] = parse_list(raw, path, gdal_name)
        return build(values, path, {a: g for g, a, _ in SCALARS + COEFFS})

    def to_rasterio(self) -> object:
        """The model as a ``rasterio.rpc.RPC`` (floats; absent errors become None)."""
        from rasterio.rpc import RPC

        return RPC(
            height_off=self.height_off,
            height_scale=self.height_scale,
            lat_off=self.lat_off,
            lat_scale=self.lat_scale,
            line_den_coeff=list(self.line_den_coeff),
            line_num_coeff=list(self.line_num_coeff),
            line_off=self.line_off,
            line_scale=self.line_scale,
            long_off=self.long_off,
            long_scale=self.long_scale,
            samp_den_coeff=list(self.samp_den_coeff),
            samp_num_coeff=list(self.samp_num_coeff),
            samp_off=self.samp_off,
            samp_scale=self.samp_scale,
            err_bias=self.err_bias,
            err_rand=self.err_rand,
        )

    @classmethod
    def from_rasterio(cls, rpc: object) -> Rpc:
        """Build from a ``rasterio.rpc.RPC`` (e.g. ``src.rpcs``).

        Raises:
            InputError: If the RPC is invalid (see the class docstring).
        """
        values = {f.name: getattr(rpc, f.name) for f in fields(cls)}
        return cls(**values)

    # -- evaluation -----------------------------------------------------------------

    def normalize_ground(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Normalised ``(L, P, H)`` of ground coordinates.

        The longitude difference to LONG_OFF is wrapped to ``[-180, 180)`` so scenes
        across the antimeridian work (GDAL wraps only beyond ±270 degrees, which gives
        the same result everywhere an RPC is meaningful).

        Args:
            lon_deg: Longitude, degrees east.
            lat_deg: Latitude, degrees, of the kind the RPC was made with.
            height_m: Height above the ellipsoid, metres.

        Returns:
            ``(L, P, H)`` broadcast to a common shape.
        """
        lon, lat, h = np.broadcast_arrays(
            np.asarray(lon_deg, np.float64),
            np.asarray(lat_deg, np.float64),
            np.asarray(height_m, np.float64),
        )
        dlon = wrap_longitude(lon - self.long_off)
        return (
            dlon / self.long_scale,
            (lat - self.lat_off) / self.lat_scale,
            (h - self.height_off) / self.height_scale,
        )

    def evaluate_normalized(
        self, L: ArrayLike, P: ArrayLike, H: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Normalised image coordinates ``(rn, cn)`` of normalised ground coordinates.

        Returns:
            ``(line_n, sample_n)``; NaN where a denominator is exactly zero.
        """
        v = (
            terms(np.asarray(L, np.float64), np.asarray(P, np.float64), np.asarray(H, np.float64))
            @ self._coeff_array
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            rn = v[..., 0] / v[..., 1]
            cn = v[..., 2] / v[..., 3]
        return np.where(v[..., 1] != 0, rn, np.nan), np.where(v[..., 3] != 0, cn, np.nan)

    def project(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Ground to image, in planetref's pixel convention (first pixel centre at 0.5).

        Args:
            lon_deg: Longitude, degrees east.
            lat_deg: Latitude, degrees, of the kind the RPC was made with.
            height_m: Height above the ellipsoid, metres.

        Returns:
            ``(line, sample)`` in pixels, broadcast shape of the inputs.
        """
        rn, cn = self.evaluate_normalized(*self.normalize_ground(lon_deg, lat_deg, height_m))
        return (
            rn * self.line_scale + self.line_off + 0.5,
            cn * self.samp_scale + self.samp_off + 0.5,
        )

    def _project_with_jacobian(
        self,
        L: NDArray[np.float64],
        P: NDArray[np.float64],
        H: NDArray[np.float64],
        *,
        height: bool = False,
    ) -> tuple[NDArray[np.float64], ...]:
        # Image coordinates (pixels) and their derivatives with respect to normalised
        # L and P (and H with ``height``: two more, dl_dH and ds_dH), by the quotient
        # rule on the analytic term derivatives.
        c = self._coeff_array
        v = terms(L, P, H) @ c
        derivs = [terms_dl(L, P, H) @ c, terms_dp(L, P, H) @ c]
        if height:
            derivs.append(terms_dh(L, P, H) @ c)
        with np.errstate(divide="ignore", invalid="ignore"):
            line = v[..., 0] / v[..., 1] * self.line_scale + self.line_off + 0.5
            samp = v[..., 2] / v[..., 3] * self.samp_scale + self.samp_off + 0.5
            d2l, d2s = v[..., 1] ** 2, v[..., 3] ** 2
            dl = [
                (d[..., 0] * v[..., 1] - v[..., 0] * d[..., 1]) / d2l * self.line_scale
                for d in derivs
            ]
            ds = [
                (d[..., 2] * v[..., 3] - v[..., 2] * d[..., 3]) / d2s * self.samp_scale
                for d in derivs
            ]
        if height:
            return line, samp, dl[0], dl[1], ds[0], ds[1], dl[2], ds[2]
        return line, samp, dl[0], dl[1], ds[0], ds[1]

    def project_with_partials(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Ground to image with the analytic partial derivatives.

        Args:
            lon_deg: Longitude, degrees east.
            lat_deg: Latitude, degrees, of the kind the RPC was made with.
            height_m: Height above the ellipsoid, metres.

        Returns:
            ``(line, sample, d)``: as :meth:`project`, and ``d`` of shape ``(..., 2, 3)``,
            ``d(line, sample)/d(lon_deg, lat_deg, height_m)`` in pixels per degree and per
            metre.
        """
        L, P, H = self.normalize_ground(lon_deg, lat_deg, height_m)
        line, samp, dl_L, dl_P, ds_L, ds_P, dl_H, ds_H = self._project_with_jacobian(
            L, P, H, height=True
        )
        scale = np.array([self.long_scale, self.lat_scale, self.height_scale])
        d = np.stack(
            [np.stack([dl_L, dl_P, dl_H], axis=-1), np.stack([ds_L, ds_P, ds_H], axis=-1)],
            axis=-2,
        )
        return line, samp, d / scale

    def localize(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        height_m: ArrayLike,
        *,
        tol_px: float = 1e-8,
        max_iter: int = 60,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Image to ground at given heights: invert the RPC by damped Newton iterations.

        Starts at (LONG_OFF, LAT_OFF) and takes Newton steps with the analytic Jacobian
        of the rational polynomials, halving a step whenever it would not reduce the
        reprojection error (far from the solution the rational functions can be
        strongly non-linear). Convergence is quadratic, so the result is usually exact
        to round-off (~1e-10 px).

        Args:
            line: Line coordinate(s), planetref convention (first pixel centre at 0.5).
            sample: Sample coordinate(s).
            height_m: Height(s) above the ellipsoid, metres (broadcast).
            tol_px: Convergence threshold on the reprojection error, pixels.
            max_iter: Maximum number of evaluations (Newton steps and step halvings).

        Returns:
            ``(lon_deg, lat_deg)``: longitude in ``[-180, 180)``, latitude of the RPC's
            kind, broadcast shape of the inputs; NaN where the error did not get below
            ``tol_px``.
        """
        ln, sm, h = np.broadcast_arrays(
            np.asarray(line, np.float64),
            np.asarray(sample, np.float64),
            np.asarray(height_m, np.float64),
        )
        shape = ln.shape
        ln, sm, h = ln.ravel(), sm.ravel(), h.ravel()
        H = (h - self.height_off) / self.height_scale
        L = np.zeros_like(ln)
        P = np.zeros_like(ln)
        # State at the current iterate: residuals, error and Jacobian; alpha is the
        # step fraction, halved after a rejected trial and reset after an accepted one.
        pl, ps, ja, jb, jc, jd = self._project_with_jacobian(L, P, H)
        rl, rs = pl - ln, ps - sm
        err = np.hypot(rl, rs)
        alpha = np.ones_like(L)
        active = np.isfinite(err) & ~(err < tol_px)
        for _ in range(max_iter):
            i = np.flatnonzero(active)
            if i.size == 0:
                break
            det = ja[i] * jd[i] - jb[i] * jc[i]
            with np.errstate(divide="ignore", invalid="ignore"):
                dL = (jd[i] * rl[i] - jb[i] * rs[i]) / det
                dP = (-jc[i] * rl[i] + ja[i] * rs[i]) / det
            tL, tP = L[i] - alpha[i] * dL, P[i] - alpha[i] * dP
            tl, ts, ta, tb, tc, td = self._project_with_jacobian(tL, tP, H[i])
            trl, trs = tl - ln[i], ts - sm[i]
            te = np.hypot(trl, trs)
            better = te < err[i]
            a = i[better]
            L[a], P[a], rl[a], rs[a], err[a] = (
                tL[better],
                tP[better],
                trl[better],
                trs[better],
                te[better],
            )
            ja[a], jb[a], jc[a], jd[a] = ta[better], tb[better], tc[better], td[better]
            alpha[a] = 1.0
            r = i[~better]
            alpha[r] *= 0.5
            # Stop where converged, where the step is undefined, or where even a tiny
            # step no longer helps (the error is then at round-off or a local minimum).
            stop = (te < tol_px) & better
            stop |= ~(np.isfinite(dL) & np.isfinite(dP))
            stop |= alpha[i] < 2.0**-20
            active[i[stop]] = False
        good = err < tol_px
        lon = np.where(good, wrap_longitude(L * self.long_scale + self.long_off), np.nan)
        lat = np.where(good, P * self.lat_scale + self.lat_off, np.nan)
        return lon.reshape(shape), lat.reshape(shape)


def fmt(value: float) -> str:
    # repr() is the shortest string that round-trips a double (also through strtod).
    return repr(float(value))


def _validate(rpc: Rpc, path: str | os.PathLike[str] | None, names: Mapping[str, str]) -> None:
    for f in fields(rpc):
        value = getattr(rpc, f.name)
        name = names.get(f.name, f.name)
        if f.name.endswith("_coeff"):
            if isinstance(value, str | bytes):
                raise InputError("expected 20 numbers, got a string", path=path, field=name)
            try:
                seq = tuple(float(v) for v in value)
            except (TypeError, ValueError):
                raise InputError(
                    f"expected 20 numbers, got {value!r}", path=path, field=name
                ) from None
            if len(seq) != N_TERMS:
                raise InputError(f"expected 20 coefficients, got {len(seq)}", path=path, field=name)
            bad = [i for i, v in enumerate(seq) if not math.isfinite(v)]
            if bad:
                raise InputError(
                    f"coefficient {bad[0] + 1} is not finite ({seq[bad[0]]})", path=path, field=name
                )
            if f.name.endswith("_den_coeff") and not any(seq):
                raise InputError("all denominator coefficients are zero", path=path, field=name)
            object.__setattr__(rpc, f.name, seq)
        else:
            if value is None and f.name in OPTIONAL:
                continue
            try:
                num = float(value)
            except (TypeError, ValueError):
                raise InputError(
                    f"expected a number, got {value!r}", path=path, field=name
                ) from None
            if not math.isfinite(num):
                raise InputError(f"must be finite, got {num}", path=path, field=name)
            if f.name in _SCALES and num == 0.0:
                raise InputError("scale must be non-zero", path=path, field=name)
            object.__setattr__(rpc, f.name, num)


def build(
    values: Mapping[str, object], path: str | os.PathLike[str] | None, names: Mapping[str, str]
) -> Rpc:
    # Validate with the file's own field names before the dataclass validates again
    # with attribute names (which cannot name the file).
    rpc = object.__new__(Rpc)
    for f in fields(Rpc):
        object.__setattr__(rpc, f.name, values.get(f.name))
    _validate(rpc, path, names)
    return Rpc(**{f.name: getattr(rpc, f.name) for f in fields(Rpc)})


# What C's strtod (GDAL's CPLAtof) reads in full; anything else (Fortran "1.0D-05",
# "12x") GDAL would read silently as a different number, so it is an error here.
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


_UNITS = {"pixel", "pixels", "degree", "degrees", "deg", "meter", "meters", "metre", "metres", "m"}


def parse_number(raw: str, path: str | os.PathLike[str] | None, name: str) -> float:
    words = raw.strip().rstrip(";").split()
    # GeoEye _rpc.txt files append a unit to some values ("+0123.000 meters").
    if not words or len(words) > 2 or (len(words) == 2 and words[1].lower() not in _UNITS):
        raise InputError(f"expected a number, got {raw.strip()!r}", path=path, field=name)
    token = words[0]
    if not _NUMBER.match(token):
        if token.lower().lstrip("+-") in {"nan", "inf", "infinity"}:
            raise InputError(f"must be finite, got {token}", path=path, field=name)
        raise InputError(f"expected a number, got {token!r}", path=path, field=name)
    value = float(token)
    if not math.isfinite(value):
        raise InputError(f"must be finite, got {token}", path=path, field=name)
    return value


def parse_list(raw: str, path: str | os.PathLike[str] | None, name: str) -> tuple[float, ...]:
    tokens = [t for t in re.split(r"[\s,]+", raw.strip()) if t]
    if len(tokens) != N_TERMS:
        raise InputError(f"expected 20 coefficients, got {len(tokens)}", path=path, field=name)
    return tuple(parse_number(t, path, f"{name}[{i + 1}]") for i, t in enumerate(tokens))
