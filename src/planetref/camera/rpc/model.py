"""Rational polynomial cameras (RPC00B): files, projection, localisation and fitting.

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

Bodies and latitudes
--------------------
RPC00B files carry no datum: the standard (and GDAL) assume WGS84 geodetic longitude,
latitude and ellipsoidal height. Planetary RPCs (e.g. Mars, written by ASP or by
:func:`fit_rpc`) use another body, here described by an :class:`RpcBody` (an ellipsoid
and the kind of latitude the RPC's LAT_OFF/LAT_SCALE refer to). The writers of this
module record the body in a form every GDAL reader ignores: extra top-level keywords
after ``END_GROUP = IMAGE`` in an ``.RPB``, extra ``PLANETREF_*`` lines at the end of
an ``_RPC.TXT``, and a ``PLANETREF`` metadata domain in a GeoTIFF. Files without it are
taken to be Earth WGS84 with geodetic latitude.

Exactness
---------
The text writers print every number with Python's shortest round-trip representation,
so ``read_rpc(write(x)) == x`` exactly and GDAL (``CPLAtof``) reads the same doubles.
GDAL's GeoTIFF RPC tag stores doubles but reports them with ``%.15g``; the GeoTIFF
writer therefore also stores the exact values in the ``PLANETREF`` domain, which the
reader prefers when they agree with the RPC tag to 15 digits.
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.atomic import atomic_path, write_text_atomic
from planetref.camera.base import ConstantHeight, ImagePoints, OnMiss, Terrain
from planetref.camera.geodesy import (
    EARTH_WGS84,
    MARS_IAU2015_SPHERE,
    Ellipsoid,
    LatitudeKind,
    lonlat_to_xyz,
    wrap_longitude,
    xyz_to_lonlat,
)
from planetref.errors import (
    GeometryError,
    InputError,
    MissingFileError,
    UnsupportedFormatError,
)

__all__ = [
    "EARTH_BODY",
    "MARS_BODY",
    "FitReport",
    "Rpc",
    "RpcBody",
    "RpcCamera",
    "fit_rpc",
    "read_rpc",
    "read_rpc_body",
    "rpc_sidecar_path",
    "write_rpc",
    "write_rpc_geotiff",
    "write_rpc_rpb",
    "write_rpc_txt",
]

RpcFormat = Literal["rpb", "txt", "geotiff"]

# GDAL metadata names of the scalar fields, in GDAL's _RPC.TXT order, with the
# attribute of Rpc and the DigitalGlobe .RPB keyword of each.
_SCALARS: tuple[tuple[str, str, str], ...] = (
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
_COEFFS: tuple[tuple[str, str, str], ...] = (
    ("LINE_NUM_COEFF", "line_num_coeff", "lineNumCoef"),
    ("LINE_DEN_COEFF", "line_den_coeff", "lineDenCoef"),
    ("SAMP_NUM_COEFF", "samp_num_coeff", "sampNumCoef"),
    ("SAMP_DEN_COEFF", "samp_den_coeff", "sampDenCoef"),
)
_OPTIONAL = ("err_bias", "err_rand")
_SCALES = ("line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale")
_N_TERMS = 20


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
        for gdal_name, attr, _ in _SCALARS:
            value = getattr(self, attr)
            if value is not None:
                out[gdal_name] = _fmt(value)
        for gdal_name, attr, _ in _COEFFS:
            out[gdal_name] = " ".join(_fmt(v) for v in getattr(self, attr))
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
        for gdal_name, attr, _ in _SCALARS:
            raw = upper.get(gdal_name)
            if raw is None or (attr in _OPTIONAL and not raw.strip()):
                if attr in _OPTIONAL:
                    continue
                raise InputError("missing", path=path, field=gdal_name)
            values[attr] = _parse_number(raw, path, gdal_name)
        for gdal_name, attr, _ in _COEFFS:
            raw = upper.get(gdal_name)
            if raw is None:
                raise InputError("missing", path=path, field=gdal_name)
            values[attr] = _parse_list(raw, path, gdal_name)
        return _build(values, path, {a: g for g, a, _ in _SCALARS + _COEFFS})

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
        return cls(**values)  # type: ignore[arg-type]

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
            _terms(np.asarray(L, np.float64), np.asarray(P, np.float64), np.asarray(H, np.float64))
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
        self, L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], ...]:
        # Image coordinates (pixels) and their derivatives with respect to normalised
        # L and P, by the quotient rule on the analytic term derivatives.
        c = self._coeff_array
        v = _terms(L, P, H) @ c
        vl = _terms_dl(L, P, H) @ c
        vp = _terms_dp(L, P, H) @ c
        with np.errstate(divide="ignore", invalid="ignore"):
            line = v[..., 0] / v[..., 1] * self.line_scale + self.line_off + 0.5
            samp = v[..., 2] / v[..., 3] * self.samp_scale + self.samp_off + 0.5
            d2l, d2s = v[..., 1] ** 2, v[..., 3] ** 2
            dl_dL = (vl[..., 0] * v[..., 1] - v[..., 0] * vl[..., 1]) / d2l * self.line_scale
            dl_dP = (vp[..., 0] * v[..., 1] - v[..., 0] * vp[..., 1]) / d2l * self.line_scale
            ds_dL = (vl[..., 2] * v[..., 3] - v[..., 2] * vl[..., 3]) / d2s * self.samp_scale
            ds_dP = (vp[..., 2] * v[..., 3] - v[..., 2] * vp[..., 3]) / d2s * self.samp_scale
        return line, samp, dl_dL, dl_dP, ds_dL, ds_dP

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

    def _project_without_jacobian(
        self, L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        rn, cn = self.evaluate_normalized(L, P, H)
        return (
            rn * self.line_scale + self.line_off + 0.5,
            cn * self.samp_scale + self.samp_off + 0.5,
        )


def _terms(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    return np.stack(
        [
            np.ones_like(L),
            L,
            P,
            H,
            L * P,
            L * H,
            P * H,
            L * L,
            P * P,
            H * H,
            P * L * H,
            L**3,
            L * P * P,
            L * H * H,
            L * L * P,
            P**3,
            P * H * H,
            L * L * H,
            P * P * H,
            H**3,
        ],
        axis=-1,
    )


def _terms_dl(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    z, o = np.zeros_like(L), np.ones_like(L)
    return np.stack(
        [
            z,
            o,
            z,
            z,
            P,
            H,
            z,
            2 * L,
            z,
            z,
            P * H,
            3 * L * L,
            P * P,
            H * H,
            2 * L * P,
            z,
            z,
            2 * L * H,
            z,
            z,
        ],
        axis=-1,
    )


def _terms_dp(
    L: NDArray[np.float64], P: NDArray[np.float64], H: NDArray[np.float64]
) -> NDArray[np.float64]:
    L, P, H = np.broadcast_arrays(L, P, H)
    z, o = np.zeros_like(L), np.ones_like(L)
    return np.stack(
        [
            z,
            z,
            o,
            z,
            L,
            z,
            H,
            z,
            2 * P,
            z,
            L * H,
            z,
            2 * L * P,
            z,
            L * L,
            3 * P * P,
            H * H,
            z,
            2 * P * H,
            z,
        ],
        axis=-1,
    )


def _fmt(value: float) -> str:
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
            if len(seq) != _N_TERMS:
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
            if value is None and f.name in _OPTIONAL:
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


def _build(
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


def _parse_number(raw: str, path: str | os.PathLike[str] | None, name: str) -> float:
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


def _parse_list(raw: str, path: str | os.PathLike[str] | None, name: str) -> tuple[float, ...]:
    tokens = [t for t in re.split(r"[\s,]+", raw.strip()) if t]
    if len(tokens) != _N_TERMS:
        raise InputError(f"expected 20 coefficients, got {len(tokens)}", path=path, field=name)
    return tuple(_parse_number(t, path, f"{name}[{i + 1}]") for i, t in enumerate(tokens))


# --------------------------------------------------------------------------- bodies


@dataclass(frozen=True)
class RpcBody:
    """The body an RPC's ground coordinates refer to.

    Attributes:
        ellipsoid: Reference ellipsoid of longitude, latitude and height.
        latitude_kind: Which latitude LAT_OFF/LAT_SCALE refer to: ``"planetographic"``
            (geodetic, the RPC00B standard) or ``"planetocentric"``.
    """

    ellipsoid: Ellipsoid
    latitude_kind: LatitudeKind

    def __post_init__(self) -> None:
        if self.latitude_kind not in ("planetocentric", "planetographic"):
            raise InputError(f"unknown latitude kind {self.latitude_kind!r}", field="latitude_kind")

    @classmethod
    def resolve(
        cls, body: str | Ellipsoid | RpcBody, latitude_kind: LatitudeKind | None = None
    ) -> RpcBody:
        """Normalise the ways planetref accepts a body.

        Args:
            body: ``"earth"`` (WGS84, geodetic latitude), ``"mars"`` (IAU 2015 sphere,
                planetocentric latitude), an :class:`Ellipsoid` or an :class:`RpcBody`.
            latitude_kind: Overrides the latitude kind. For a bare ellipsoid the default
                is geodetic ("planetographic", the RPC00B convention) unless it is a
                sphere, where both kinds coincide and planetref's planetocentric
                default is used.

        Raises:
            InputError: For an unknown body name.
        """
        if isinstance(body, RpcBody):
            base = body
        elif isinstance(body, Ellipsoid):
            base = cls(body, "planetocentric" if body.is_sphere else "planetographic")
        elif isinstance(body, str) and body.lower() in _NAMED_BODIES:
            base = _NAMED_BODIES[body.lower()]
        else:
            raise InputError(
                f"unknown body {body!r}; expected 'earth', 'mars', an Ellipsoid or an RpcBody",
                field="body",
            )
        if latitude_kind is not None and latitude_kind != base.latitude_kind:
            return cls(base.ellipsoid, latitude_kind)
        return base

    def _items(self) -> dict[str, str]:
        return {
            "BODY_NAME": self.ellipsoid.name,
            "SEMI_MAJOR_M": _fmt(self.ellipsoid.semi_major_m),
            "SEMI_MINOR_M": _fmt(self.ellipsoid.semi_minor_m),
            "LATITUDE": self.latitude_kind,
        }

    @classmethod
    def _from_items(
        cls, items: Mapping[str, str], path: str | os.PathLike[str] | None, prefix: str
    ) -> RpcBody | None:
        upper = {k.upper(): v for k, v in items.items()}
        if "SEMI_MAJOR_M" not in upper:
            return None
        a = _parse_number(upper["SEMI_MAJOR_M"], path, prefix + "SEMI_MAJOR_M")
        b = _parse_number(upper.get("SEMI_MINOR_M", ""), path, prefix + "SEMI_MINOR_M")
        kind = upper.get("LATITUDE", "").strip().strip('"').lower()
        if kind not in ("planetocentric", "planetographic"):
            raise InputError(
                f"expected 'planetocentric' or 'planetographic', got {kind!r}",
                path=path,
                field=prefix + "LATITUDE",
            )
        name = upper.get("BODY_NAME", "").strip().strip('"')
        try:
            ell = Ellipsoid(a, b, name)
        except InputError as exc:
            raise InputError(str(exc), path=path, field=prefix + "SEMI_MAJOR_M") from None
        return cls(ell, kind)  # type: ignore[arg-type]


EARTH_BODY = RpcBody(EARTH_WGS84, "planetographic")
MARS_BODY = RpcBody(MARS_IAU2015_SPHERE, "planetocentric")
_NAMED_BODIES = {"earth": EARTH_BODY, "mars": MARS_BODY}


# --------------------------------------------------------------------------- readers


def read_rpc(path: str | os.PathLike[str]) -> Rpc:
    """Read an RPC00B model, recognising the format by the file's content.

    Supported: a GeoTIFF (or any raster GDAL reads) with RPC metadata, read through
    rasterio; a DigitalGlobe/ENVI ``.RPB`` (``BEGIN_GROUP = IMAGE ... lineNumCoef =
    (...)``); a GDAL/GeoEye ``_RPC.TXT`` (``LINE_OFF: ...`` key/value lines).

    Args:
        path: The file.

    Returns:
        The validated model.

    Raises:
        MissingFileError: If the file does not exist.
        UnsupportedFormatError: If it is none of the formats above.
        InputError: If it is truncated, garbled, misses a field or holds invalid
            numbers; the message names the file and the field.
    """
    return _read(path)[0]


def read_rpc_body(path: str | os.PathLike[str]) -> RpcBody | None:
    """The body planetref recorded in an RPC file, or None (then assume Earth WGS84).

    Raises:
        The errors of :func:`read_rpc`.
    """
    return _read(path)[1]


def _read(path: str | os.PathLike[str]) -> tuple[Rpc, RpcBody | None]:
    p = Path(path)
    if not p.exists():
        raise MissingFileError("RPC file not found", path=p)
    if p.is_dir():
        raise UnsupportedFormatError("is a directory, not an RPC file", path=p)
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _read_raster(p)
    if b"\x00" not in head:
        text = head.decode("latin-1")
        if re.search(r"BEGIN_GROUP\s*=\s*IMAGE|\blineNumCoef\b|\blineOffset\b", text, re.I):
            return _read_rpb(p)
        if re.search(r"^\s*(LINE_OFF|LINE_NUM_COEFF_1)\s*[:=]", text, re.I | re.M):
            return _read_txt(p)
        if not text.strip():
            raise UnsupportedFormatError("empty file, expected RPC coefficients", path=p)
    # Other rasters GDAL can read (NITF with an RPC00B TRE, JP2 with sidecars...).
    try:
        return _read_raster(p)
    except UnsupportedFormatError:
        raise UnsupportedFormatError(
            "not an RPC file: expected a GeoTIFF with RPC metadata, a .RPB file or an "
            "_RPC.TXT file",
            path=p,
        ) from None


def _read_raster(p: Path) -> tuple[Rpc, RpcBody | None]:
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(p) as src:
            gdal_md = src.tags(ns="RPC")
            extra = src.tags(ns="PLANETREF")
    except RasterioIOError as exc:
        raise UnsupportedFormatError(f"cannot be opened by GDAL ({exc})", path=p) from None
    if not gdal_md:
        raise InputError("the raster has no RPC metadata", path=p, field="RPC")
    rpc = Rpc.from_gdal(gdal_md, path=p)
    body = RpcBody._from_items(
        {k: v for k, v in extra.items() if not k.startswith("RPC_")}, p, "PLANETREF:"
    )
    exact = {k[4:]: v for k, v in extra.items() if k.startswith("RPC_")}
    if exact:
        try:
            candidate = Rpc.from_gdal(exact, path=p)
        except InputError:
            candidate = None
        # Use the exact copy only if it is what the RPC tag holds (to GDAL's 15 digits),
        # so an RPC rewritten later by other software wins over a stale copy.
        if candidate is not None and _agrees(candidate, rpc):
            rpc = candidate
    return rpc, body


def _agrees(exact: Rpc, reported: Rpc) -> bool:
    def same(a: float | None, b: float | None) -> bool:
        if a is None or b is None:
            # GDAL reports absent ERR_BIAS/ERR_RAND of a GeoTIFF tag as -1.
            return (a if a is not None else -1.0) == (b if b is not None else -1.0)
        return a == b or float(f"{a:.15g}") == b

    for f in fields(Rpc):
        a, b = getattr(exact, f.name), getattr(reported, f.name)
        if f.name.endswith("_coeff"):
            if not all(same(x, y) for x, y in zip(a, b, strict=True)):
                return False
        elif not same(a, b):
            return False
    return True


def _strip_comments(text: str) -> str:
    # CPLKeywordParser (GDAL's .RPB reader) skips C-style comments too.
    return re.sub(r"/\*.*?\*/", " ", text, flags=re.S)


_RPB_STATEMENT = re.compile(r"([A-Za-z_][\w.]*)\s*=\s*(\([^()]*\)|\"[^\"]*\"|[^;\n]*)\s*;?")


def _read_rpb(p: Path) -> tuple[Rpc, RpcBody | None]:
    text = _strip_comments(p.read_text(encoding="latin-1"))
    items: dict[str, str] = {}
    for m in _RPB_STATEMENT.finditer(text):
        items.setdefault(m.group(1).lower(), m.group(2).strip())
    if "(" in text and text.count("(") != text.count(")"):
        # An unterminated coefficient list: name the first list that is not closed.
        for _, _, rpb_name in _COEFFS:
            m = re.search(rf"\b{rpb_name}\s*=\s*\(([^()]*)(\(|$)", text, re.I)
            if m:
                raise InputError(
                    "unterminated coefficient list (truncated file?)", path=p, field=rpb_name
                )
    values: dict[str, object] = {}
    for _, attr, rpb_name in _SCALARS:
        raw = items.get(rpb_name.lower())
        if raw is None:
            if attr in _OPTIONAL:
                continue
            raise InputError("missing", path=p, field=rpb_name)
        values[attr] = _parse_number(raw, p, rpb_name)
    for _, attr, rpb_name in _COEFFS:
        raw = items.get(rpb_name.lower())
        if raw is None:
            raise InputError("missing", path=p, field=rpb_name)
        raw = raw.strip()
        if not (raw.startswith("(") and raw.endswith(")")):
            raise InputError(f"expected '(c1, ..., c20)', got {raw[:40]!r}", path=p, field=rpb_name)
        values[attr] = _parse_list(raw[1:-1], p, rpb_name)
    rpc = _build(values, p, {a: r for _, a, r in _SCALARS + _COEFFS})
    body_items = {
        k[len("planetref") :].upper(): v for k, v in items.items() if k.startswith("planetref")
    }
    body_items = {_RPB_BODY_KEYS.get(k, k): v for k, v in body_items.items()}
    return rpc, RpcBody._from_items(body_items, p, "planetref")


# .RPB keyword suffix (after "planetref") -> RpcBody item name.
_RPB_BODY_KEYS = {
    "BODYNAME": "BODY_NAME",
    "SEMIMAJORAXIS": "SEMI_MAJOR_M",
    "SEMIMINORAXIS": "SEMI_MINOR_M",
    "LATITUDE": "LATITUDE",
}


def _read_txt(p: Path) -> tuple[Rpc, RpcBody | None]:
    items: dict[str, tuple[str, int]] = {}
    for lineno, raw_line in enumerate(p.read_text(encoding="latin-1").splitlines(), 1):
        line = raw_line.strip()
        if not line:
            continue
        m = re.match(r"^([A-Za-z_]\w*)\s*[:=]\s*(.*)$", line)
        if m is None:
            raise InputError(f"line {lineno}: expected 'KEY: value', got {line[:40]!r}", path=p)
        items.setdefault(m.group(1).upper(), (m.group(2), lineno))
    values: dict[str, object] = {}
    for gdal_name, attr, _ in _SCALARS:
        if gdal_name not in items:
            if attr in _OPTIONAL:
                continue
            raise InputError("missing", path=p, field=gdal_name)
        values[attr] = _parse_number(items[gdal_name][0], p, gdal_name)
    for gdal_name, attr, _ in _COEFFS:
        coeffs = []
        for i in range(1, _N_TERMS + 1):
            key = f"{gdal_name}_{i}"
            if key not in items:
                raise InputError("missing", path=p, field=key)
            coeffs.append(_parse_number(items[key][0], p, key))
        if f"{gdal_name}_{_N_TERMS + 1}" in items:
            raise InputError(
                "more than 20 coefficients", path=p, field=f"{gdal_name}_{_N_TERMS + 1}"
            )
        values[attr] = tuple(coeffs)
    rpc = _build(values, p, {a: g for g, a, _ in _SCALARS + _COEFFS})
    body_items = {
        k[len("PLANETREF_") :]: v for k, (v, _) in items.items() if k.startswith("PLANETREF_")
    }
    return rpc, RpcBody._from_items(body_items, p, "PLANETREF_")


# --------------------------------------------------------------------------- writers


def rpc_sidecar_path(
    image_path: str | os.PathLike[str], fmt: Literal["rpb", "txt"] = "rpb"
) -> Path:
    """Where GDAL looks for an RPC sidecar of an image.

    Args:
        image_path: The image, e.g. ``scene.tif``.
        fmt: ``"rpb"`` for ``scene.RPB`` or ``"txt"`` for ``scene_RPC.TXT``.

    Returns:
        The sidecar path next to the image.
    """
    p = Path(image_path)
    if fmt == "rpb":
        return p.with_suffix(".RPB")
    if fmt == "txt":
        return p.with_name(p.stem + "_RPC.TXT")
    raise InputError(f"unknown sidecar format {fmt!r}; expected 'rpb' or 'txt'", field="fmt")


def write_rpc_rpb(rpc: Rpc, path: str | os.PathLike[str], *, body: RpcBody | None = None) -> Path:
    """Write a DigitalGlobe ``.RPB`` file in the layout GDAL's ``GDALWriteRPBFile`` uses.

    The body, if given, goes into ``planetref*`` keywords after ``END_GROUP = IMAGE``,
    which GDAL's keyword parser reads and ignores. The file is written atomically.

    Args:
        rpc: The model.
        path: Output path (GDAL finds it next to ``scene.tif`` as ``scene.RPB``).
        body: The body to record, or None to record nothing (readers then assume Earth).

    Returns:
        The path written.
    """
    p = Path(path)
    out = ['satId = "NONE";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for _, attr, rpb_name in _SCALARS:
        value = getattr(rpc, attr)
        if value is not None:
            out.append(f"\t{rpb_name} = {_fmt(value)};")
    for _, attr, rpb_name in _COEFFS:
        coeffs = [_fmt(v) for v in getattr(rpc, attr)]
        out.append(f"\t{rpb_name} = (")
        out.extend(f"\t\t\t{c}," for c in coeffs[:-1])
        out.append(f"\t\t\t{coeffs[-1]});")
    out.append("END_GROUP = IMAGE")
    if body is not None:
        items = body._items()
        out.append(f'planetrefBodyName = "{_quote_safe(items["BODY_NAME"])}";')
        out.append(f"planetrefSemiMajorAxis = {items['SEMI_MAJOR_M']};")
        out.append(f"planetrefSemiMinorAxis = {items['SEMI_MINOR_M']};")
        out.append(f'planetrefLatitude = "{items["LATITUDE"]}";')
    out.append("END;")
    write_text_atomic(p, "\n".join(out) + "\n", encoding="ascii")
    return p


def _quote_safe(text: str) -> str:
    return re.sub(r'["\n\r;]', " ", text)


def write_rpc_txt(rpc: Rpc, path: str | os.PathLike[str], *, body: RpcBody | None = None) -> Path:
    """Write a ``_RPC.TXT`` file in the layout of GDAL's ``GDALWriteRPCTXTFile``.

    The body, if given, goes into trailing ``PLANETREF_*`` lines that GDAL ignores.
    Every line stays under the 100 characters GDAL's reader accepts. The file is
    written atomically.

    Args:
        rpc: The model.
        path: Output path (GDAL finds it next to ``scene.tif`` as ``scene_RPC.TXT``).
        body: The body to record, or None.

    Returns:
        The path written.
    """
    p = Path(path)
    out = []
    for gdal_name, attr, _ in _SCALARS:
        value = getattr(rpc, attr)
        if value is not None:
            out.append(f"{gdal_name}: {_fmt(value)}")
    for gdal_name, attr, _ in _COEFFS:
        out.extend(f"{gdal_name}_{i}: {_fmt(v)}" for i, v in enumerate(getattr(rpc, attr), 1))
    if body is not None:
        out.extend(f"PLANETREF_{k}: {_quote_safe(v)[:60]}" for k, v in body._items().items())
    write_text_atomic(p, "\n".join(out) + "\n", encoding="ascii")
    return p


def write_rpc_geotiff(
    rpc: Rpc,
    path: str | os.PathLike[str],
    *,
    data: ArrayLike | None = None,
    body: RpcBody | None = None,
) -> Path:
    """Embed an RPC into a GeoTIFF (GDAL's RPC TIFF tag), atomically.

    With ``data`` a new GeoTIFF holding that image is written; without it the RPC of
    the existing GeoTIFF at ``path`` is replaced (the file is copied, updated and
    renamed over the original). The exact values and the body also go into the
    ``PLANETREF`` metadata domain (the GDAL_METADATA TIFF tag), because GDAL reports
    the RPC tag with only 15 significant digits.

    Args:
        rpc: The model.
        path: The GeoTIFF.
        data: Image of shape ``(rows, cols)`` or ``(bands, rows, cols)``, or None.
        body: The body to record, or None.

    Returns:
        The path written.

    Raises:
        MissingFileError: If ``data`` is None and ``path`` does not exist.
        InputError: If ``data`` has the wrong number of dimensions.
    """
    import rasterio

    p = Path(path)
    extra = {f"RPC_{k}": v for k, v in rpc.to_gdal().items()}
    for name in ("ERR_BIAS", "ERR_RAND"):
        # An empty value marks "absent", overriding any stale copy in an updated file.
        extra.setdefault(f"RPC_{name}", "")
    if body is not None:
        extra.update(body._items())
    if data is None:
        if not p.exists():
            raise MissingFileError("GeoTIFF to update not found (pass data= to create one)", path=p)
        with atomic_path(p) as tmp:
            shutil.copyfile(p, tmp)
            with rasterio.open(tmp, "r+") as dst:
                # The setter replaces the whole RPC domain; rasterio drops an error
                # value of exactly 0, which the item update puts back.
                dst.rpcs = rpc.to_rasterio()
                dst.update_tags(ns="RPC", **rpc.to_gdal())
                dst.update_tags(ns="PLANETREF", **extra)
        return p
    arr = np.asarray(data)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise InputError(f"expected a 2-D or 3-D image, got shape {arr.shape}", field="data")
    with atomic_path(p) as tmp:
        with rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=arr.shape[2],
            height=arr.shape[1],
            count=arr.shape[0],
            dtype=arr.dtype,
            rpcs=rpc.to_gdal(),
        ) as dst:
            dst.write(arr)
            dst.update_tags(ns="PLANETREF", **extra)
    return p


def write_rpc(
    rpc: Rpc,
    path: str | os.PathLike[str],
    *,
    fmt: RpcFormat | None = None,
    body: RpcBody | None = None,
) -> Path:
    """Write an RPC in the format given by ``fmt`` or by the file name.

    ``*.RPB`` -> :func:`write_rpc_rpb`; ``*.TXT`` (e.g. ``scene_RPC.TXT``) ->
    :func:`write_rpc_txt`; ``*.tif``/``*.tiff`` -> :func:`write_rpc_geotiff` updating
    the existing GeoTIFF.

    Args:
        rpc: The model.
        path: Output path.
        fmt: ``"rpb"``, ``"txt"`` or ``"geotiff"``; inferred from the suffix when None.
        body: The body to record, or None.

    Returns:
        The path written.

    Raises:
        UnsupportedFormatError: If the format cannot be inferred.
    """
    p = Path(path)
    if fmt is None:
        suffix = p.suffix.lower()
        fmt = {".rpb": "rpb", ".txt": "txt", ".tif": "geotiff", ".tiff": "geotiff"}.get(suffix)  # type: ignore[assignment]
        if fmt is None:
            raise UnsupportedFormatError(
                "cannot tell the RPC format from the suffix; use .RPB, _RPC.TXT or .tif "
                "or pass fmt=",
                path=p,
            )
    if fmt == "rpb":
        return write_rpc_rpb(rpc, p, body=body)
    if fmt == "txt":
        return write_rpc_txt(rpc, p, body=body)
    if fmt == "geotiff":
        return write_rpc_geotiff(rpc, p, body=body)
    raise UnsupportedFormatError(f"unknown RPC format {fmt!r}", path=p, field="fmt")


# --------------------------------------------------------------------------- camera


class RpcCamera:
    """A :class:`~planetref.camera.base.Camera` defined by an RPC00B model.

    Image coordinates follow planetref's convention (first pixel centre at 0.5), which
    is GDAL's: ``project`` equals ``rasterio.transform.RPCTransformer.rowcol`` without
    rounding, and ``localize`` equals its ``xy(..., offset="ul")``.

    Args:
        rpc: The model.
        ellipsoid: The body the RPC's longitudes, latitudes and heights refer to
            (``EARTH_WGS84`` for Earth imagery, ``MARS_IAU2015_SPHERE`` for Mars).
        latitude_kind: The latitude LAT_OFF/LAT_SCALE refer to: ``"planetographic"``
            (geodetic; Earth RPCs) or ``"planetocentric"``.
        image_size: ``(n_lines, n_samples)`` of the image.
        name: The name of the camera's single CCD.

    Raises:
        InputError: If the latitude kind or image size is invalid.
    """

    def __init__(
        self,
        rpc: Rpc,
        ellipsoid: Ellipsoid,
        latitude_kind: LatitudeKind,
        image_size: tuple[int, int],
        name: str = "rpc",
    ) -> None:
        if latitude_kind not in ("planetocentric", "planetographic"):
            raise InputError(f"unknown latitude kind {latitude_kind!r}", field="latitude_kind")
        try:
            n_lines, n_samples = (int(v) for v in image_size)
        except (TypeError, ValueError):
            raise InputError(
                f"expected (n_lines, n_samples), got {image_size!r}", field="image_size"
            ) from None
        if n_lines <= 0 or n_samples <= 0:
            raise InputError(f"image size must be positive, got {image_size!r}", field="image_size")
        self.rpc = rpc
        self.ellipsoid = ellipsoid
        self.latitude_kind: LatitudeKind = latitude_kind
        self._size = (n_lines, n_samples)
        self.name = name

    def __repr__(self) -> str:
        return (
            f"RpcCamera(name={self.name!r}, size={self._size}, "
            f"body={self.ellipsoid.name!r}, latitude={self.latitude_kind!r})"
        )

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        body: str | Ellipsoid | RpcBody | None = None,
        *,
        latitude_kind: LatitudeKind | None = None,
        image_size: tuple[int, int] | None = None,
        name: str | None = None,
    ) -> RpcCamera:
        """Read an RPC file (any format :func:`read_rpc` reads) into a camera.

        Args:
            path: A raster with RPC metadata, or an ``.RPB``/``_RPC.TXT`` file.
            body: ``"earth"``, ``"mars"``, an :class:`Ellipsoid` or an :class:`RpcBody`.
                When None, the body planetref recorded in the file, else Earth WGS84
                with geodetic latitude (the RPC00B standard, which GDAL assumes).
            latitude_kind: Overrides the latitude kind of ``body``.
            image_size: ``(n_lines, n_samples)``. When None: the raster's size, or for
                a sidecar the size of the image next to it (``scene.tif`` for
                ``scene.RPB`` or ``scene_RPC.TXT``).
            name: CCD name (default: the file's stem).

        Raises:
            InputError: If the image size is needed but cannot be found, and the
                errors of :func:`read_rpc`.
        """
        p = Path(path)
        rpc, stored = _read(p)
        if body is None:
            resolved = RpcBody.resolve(stored or EARTH_BODY, latitude_kind)
        else:
            resolved = RpcBody.resolve(body, latitude_kind)
        if image_size is None:
            try:
                image_size = _find_image_size(p)
            except InputError:
                # No raster beside the sidecar: the RPC's normalisation domain is the
                # best estimate of the image extent (only ``in_image`` depends on it).
                image_size = (
                    max(1, math.ceil(rpc.line_off + abs(rpc.line_scale) + 0.5)),
                    max(1, math.ceil(rpc.samp_off + abs(rpc.samp_scale) + 0.5)),
                )
                logging.getLogger(__name__).warning(
                    "%s: no raster beside the RPC file; image size taken from the RPC "
                    "domain as %s lines x %s samples",
                    p,
                    *image_size,
                )
        return cls(rpc, resolved.ellipsoid, resolved.latitude_kind, image_size, name or p.stem)

    # -- Camera protocol ------------------------------------------------------------

    @property
    def ccd_names(self) -> tuple[str, ...]:
        """The single CCD name."""
        return (self.name,)

    def _check_ccd(self, ccd: str | None) -> None:
        if ccd is not None and ccd != self.name:
            raise InputError(
                f"unknown CCD {ccd!r}; this RPC camera has only {self.name!r}", field="ccd"
            )

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)``."""
        self._check_ccd(ccd)
        return self._size

    def project(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Ground (lon, lat in this camera's latitude kind, degrees; h, metres) to image.

        Returns:
            ``(line, sample)`` in pixels (first pixel centre at 0.5), broadcast shape.
        """
        return self.rpc.project(lon_deg, lat_deg, height_m)

    def localize(
        self, line: ArrayLike, sample: ArrayLike, height_m: ArrayLike, *, tol_px: float = 1e-8
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Image to lon/lat (degrees, this camera's latitude kind) at given heights (m).

        Newton iterations on the rational polynomials with their analytic Jacobian,
        to ``tol_px`` pixels of reprojection error; NaN where they do not converge.
        """
        return self.rpc.localize(line, sample, height_m, tol_px=tol_px)

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points (metres, shape ``(M, 3)`` or ``(3,)``) into the image.

        Returns:
            :class:`ImagePoints`; ``valid`` is False only for non-finite input or a zero
            denominator (an RPC extrapolates everywhere, so far-away points are
            "valid" but not ``in_image``).
        """
        self._check_ccd(ccd)
        pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        lon, lat, h = xyz_to_lonlat(pts, self.ellipsoid, self.latitude_kind)
        line, sample = self.rpc.project(lon, lat, h)
        valid = np.isfinite(line) & np.isfinite(sample)
        n_lines, n_samples = self._size
        with np.errstate(invalid="ignore"):
            in_image = valid & (line >= 0) & (line < n_lines) & (sample >= 0) & (sample < n_samples)
        return ImagePoints(
            np.where(valid, line, np.nan), np.where(valid, sample, np.nan), valid, in_image
        )

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> NDArray[np.float64]:
        """Intersect the RPC's lines of sight with a height or a terrain.

        For a height, the RPC is inverted at that height. For a :class:`Terrain`, the
        line of sight (the curve ``h -> localize(line, sample, h)``) is marched from
        above ``max_height_m`` down to below ``min_height_m`` in steps that move at
        most ``sampling_m`` horizontally, and the first crossing is refined by
        regula falsi (Illinois) to 0.1 mm in height. Terrain heights are compared as
        heights above the terrain's own ellipsoid at its planetocentric lon/lat.

        Args:
            line: Line coordinates (planetref convention), shape ``(M,)`` or scalar.
            sample: Sample coordinates, same shape.
            terrain: A :class:`Terrain`, or a height in metres above this camera's
                ellipsoid.
            ccd: Must be None or this camera's name.
            on_miss: ``"raise"`` a :class:`GeometryError` if any point has no solution
                (no convergence, terrain hole, no crossing), or return NaN rows.

        Returns:
            Body-fixed XYZ, metres, shape ``(M, 3)``.
        """
        self._check_ccd(ccd)
        ln, sm = np.broadcast_arrays(np.asarray(line, np.float64), np.asarray(sample, np.float64))
        ln, sm = ln.ravel(), sm.ravel()
        if isinstance(terrain, ConstantHeight) and terrain.ellipsoid == self.ellipsoid:
            terrain = float(terrain.height_m)
        if isinstance(terrain, Terrain):
            xyz = self._intersect_terrain(ln, sm, terrain)
        else:
            try:
                h = float(terrain)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise InputError(
                    f"terrain must be a Terrain or a height in metres, got {terrain!r}",
                    field="terrain",
                ) from None
            lon, lat = self.rpc.localize(ln, sm, h)
            xyz = lonlat_to_xyz(lon, lat, h, self.ellipsoid, self.latitude_kind)
        bad = ~np.all(np.isfinite(xyz), axis=1)
        if on_miss == "raise" and np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise GeometryError(
                f"{int(bad.sum())} of {bad.size} image points have no ground intersection "
                f"(first: line {ln[i]:.3f}, sample {sm[i]:.3f}): the RPC inversion did not "
                "converge or the line of sight misses the terrain"
            )
        return xyz

    def _terrain_residual(
        self,
        ln: NDArray[np.float64],
        sm: NDArray[np.float64],
        h: NDArray[np.float64],
        terrain: Terrain,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        # Height of the line-of-sight point above the terrain surface, and the point.
        lon, lat = self.rpc.localize(ln, sm, h)
        xyz = lonlat_to_xyz(lon, lat, h, self.ellipsoid, self.latitude_kind)
        tlon, tlat, th = xyz_to_lonlat(xyz, terrain.ellipsoid, "planetocentric")
        surface = np.asarray(terrain.height(tlon, tlat), dtype=np.float64)
        return th - surface, xyz

    def _intersect_terrain(
        self, ln: NDArray[np.float64], sm: NDArray[np.float64], terrain: Terrain
    ) -> NDArray[np.float64]:
        m = ln.size
        lo, hi = float(terrain.min_height_m), float(terrain.max_height_m)
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
            raise InputError(
                f"terrain height bounds must be finite with min <= max, got [{lo}, {hi}]",
                field="terrain",
            )
        # The bounds are heights above the terrain's ellipsoid and the march is in
        # heights above the camera's: widen by the largest separation of the two
        # ellipsoids, plus a margin so that a surface touching its bounds is bracketed.
        other = terrain.ellipsoid
        margin = (
            1.0
            + 1e-3 * (hi - lo)
            + abs(other.semi_major_m - self.ellipsoid.semi_major_m)
            + abs(other.semi_minor_m - self.ellipsoid.semi_minor_m)
        )
        top, bottom = hi + margin, lo - margin
        _, xyz_top = self._terrain_residual(ln, sm, np.full(m, top), terrain)
        _, xyz_bot = self._terrain_residual(ln, sm, np.full(m, bottom), terrain)
        chord = np.linalg.norm(xyz_top - xyz_bot, axis=1)
        horizontal = np.sqrt(np.maximum(chord**2 - (top - bottom) ** 2, 0.0))
        sampling = float(terrain.sampling_m)
        reach = float(np.nanmax(horizontal)) if np.any(np.isfinite(horizontal)) else 0.0
        n_steps = 1
        if math.isfinite(sampling) and sampling > 0:
            n_steps = int(min(max(math.ceil(reach / sampling), 1), 100_000))
        heights = np.linspace(top, bottom, n_steps + 1)

        h_a = np.full(m, np.nan)  # last height above the surface (residual > 0)
        r_a = np.full(m, np.nan)
        h_b = np.full(m, np.nan)  # first height at or below it
        r_b = np.full(m, np.nan)
        found = np.zeros(m, dtype=bool)
        prev_h = np.full(m, np.nan)
        prev_r = np.full(m, np.nan)
        for hk in heights:
            idx = np.flatnonzero(~found)
            if idx.size == 0:
                break
            r, _ = self._terrain_residual(ln[idx], sm[idx], np.full(idx.size, hk), terrain)
            cross = (prev_r[idx] > 0) & (r <= 0)
            ci = idx[cross]
            h_a[ci], r_a[ci] = prev_h[ci], prev_r[ci]
            h_b[ci], r_b[ci] = hk, r[cross]
            found[ci] = True
            prev_h[idx], prev_r[idx] = hk, r

        xyz = np.full((m, 3), np.nan)
        idx = np.flatnonzero(found)
        if idx.size == 0:
            return xyz
        ha, ra, hb, rb = h_a[idx], r_a[idx], h_b[idx], r_b[idx]
        h_best = hb.copy()
        side = np.zeros(idx.size, dtype=int)
        live = np.ones(idx.size, dtype=bool)
        for _ in range(100):
            k = np.flatnonzero(live)
            if k.size == 0:
                break
            hn = hb[k] - rb[k] * (hb[k] - ha[k]) / (rb[k] - ra[k])
            hn = np.where(np.isfinite(hn), hn, 0.5 * (ha[k] + hb[k]))
            rn, _ = self._terrain_residual(ln[idx[k]], sm[idx[k]], hn, terrain)
            h_best[k] = hn
            above = rn > 0
            below = rn <= 0
            # Illinois modification: when the same end survives twice in a row, halve
            # its residual so that the bracket shrinks from both sides.
            ha[k] = np.where(above, hn, ha[k])
            hb[k] = np.where(below, hn, hb[k])
            ra[k] = np.where(above, rn, np.where(side[k] == -1, 0.5 * ra[k], ra[k]))
            rb[k] = np.where(below, rn, np.where(side[k] == 1, 0.5 * rb[k], rb[k]))
            side[k] = np.where(above, 1, -1)
            # A terrain hole inside the bracket (NaN) ends the search for that point.
            hole = ~np.isfinite(rn)
            h_best[k[hole]] = np.nan
            done = hole | (np.abs(rn) < 1e-4) | (np.abs(ha[k] - hb[k]) < 1e-6)
            live[k[done]] = False
        r_final, xyz_final = self._terrain_residual(ln[idx], sm[idx], h_best, terrain)
        ok = np.isfinite(r_final) & (np.abs(r_final) < 1e-2)
        xyz[idx[ok]] = xyz_final[ok]
        return xyz


def _find_image_size(p: Path) -> tuple[int, int]:
    import rasterio
    from rasterio.errors import RasterioIOError

    candidates = [p]
    name = p.name
    if name.lower().endswith("_rpc.txt"):
        stem = name[: -len("_rpc.txt")]
    elif name.lower().endswith(".rpb"):
        stem = name[:-4]
    else:
        stem = None
    if stem is not None:
        candidates = sorted(
            q
            for q in p.parent.glob(stem + ".*")
            if q.suffix.lower() in {".tif", ".tiff", ".ntf", ".jp2", ".img", ".cub", ".vrt"}
        )
    for q in candidates:
        try:
            with rasterio.open(q) as src:
                return (src.height, src.width)
        except RasterioIOError:
            continue
    raise InputError(
        "cannot tell the image size: no raster found next to this RPC file; "
        "pass image_size=(n_lines, n_samples)",
        path=p,
        field="image_size",
    )


# --------------------------------------------------------------------------- fitting


@dataclass(frozen=True)
class FitReport:
    """How well a fitted RPC reproduces the camera it was fitted to.

    Errors are ground -> image: the ground points that the rigorous camera localises
    from a grid of image points at several heights are projected with the fitted RPC
    and compared with the grid, in pixels, per image axis and as 2-D distances.

    Attributes:
        fit_rms_line_px: RMS line error on the fitting grid.
        fit_rms_sample_px: RMS sample error on the fitting grid.
        fit_max_px: Largest 2-D error on the fitting grid.
        check_rms_line_px: RMS line error on the check grid (cell centres of the fitting
            grid, at more heights, so no check point was used in the fit).
        check_rms_sample_px: RMS sample error on the check grid.
        check_max_px: Largest 2-D error on the check grid.
        check_max_ground_m: Largest distance (metres) between the rigorous ground point
            and the fitted RPC's localisation of the same image point and height, on the
            check grid (image -> ground direction).
        min_abs_denominator: Smallest ``|denominator|`` of the fitted RPC over both
            grids (values far below 1 warn of a pole near the image).
        n_fit: Number of fitting points (after dropping points the camera could not
            localise).
        n_check: Number of check points.
        n_dropped: Grid points the camera could not localise (on_miss NaN).
        iterations: Reweighting iterations used.
        regularization: The Tikhonov parameter used.
    """

    fit_rms_line_px: float
    fit_rms_sample_px: float
    fit_max_px: float
    check_rms_line_px: float
    check_rms_sample_px: float
    check_max_px: float
    check_max_ground_m: float
    min_abs_denominator: float
    n_fit: int
    n_check: int
    n_dropped: int
    iterations: int
    regularization: float

    @property
    def fit_rms_px(self) -> float:
        """2-D RMS error on the fitting grid, pixels."""
        return math.hypot(self.fit_rms_line_px, self.fit_rms_sample_px)

    @property
    def check_rms_px(self) -> float:
        """2-D RMS error on the check grid, pixels."""
        return math.hypot(self.check_rms_line_px, self.check_rms_sample_px)

    def summary(self) -> str:
        """A one-line human-readable summary."""
        return (
            f"RPC fit: fit RMS {self.fit_rms_px:.3g} px (max {self.fit_max_px:.3g}), "
            f"check RMS {self.check_rms_px:.3g} px (max {self.check_max_px:.3g}, "
            f"{self.check_max_ground_m:.3g} m), {self.n_fit} fit / {self.n_check} check "
            f"points, {self.iterations} iterations"
        )


@dataclass
class _Samples:
    line: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    sample: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    lon: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    lat: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    h: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    xyz: NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 3)))
    dropped: int = 0


def _sample_camera(
    camera: object,
    ccd: str | None,
    lines: NDArray[np.float64],
    samples: NDArray[np.float64],
    heights: NDArray[np.float64],
) -> _Samples:
    ll, ss = np.meshgrid(lines, samples, indexing="ij")
    ll, ss = ll.ravel(), ss.ravel()
    out_l, out_s, out_xyz, out_h = [], [], [], []
    for h in heights:
        xyz = np.asarray(
            camera.image_to_ground(
                ll,
                ss,
                terrain=float(h),
                ccd=ccd,  # type: ignore[attr-defined]
                on_miss="nan",
            ),
            dtype=np.float64,
        )
        out_l.append(ll)
        out_s.append(ss)
        out_xyz.append(xyz.reshape(-1, 3))
        out_h.append(np.full(ll.size, h))
    xyz = np.concatenate(out_xyz)
    ok = np.all(np.isfinite(xyz), axis=1)
    lon, lat, hh = xyz_to_lonlat(
        xyz[ok],
        camera.ellipsoid,  # type: ignore[attr-defined]
        camera.latitude_kind,
    )  # type: ignore[attr-defined]
    return _Samples(
        np.concatenate(out_l)[ok],
        np.concatenate(out_s)[ok],
        lon,
        lat,
        hh,
        xyz[ok],
        int((~ok).sum()),
    )


def _solve_rational(
    T: NDArray[np.float64], y: NDArray[np.float64], reg: float, max_iter: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    # Tao & Hu (2001): linearise y = N/D as N - y*D = 0 with D's constant term fixed to
    # 1, weight each equation by 1/D of the previous solution so that the residual
    # tends to the true y - N/D, and regularise with a ridge term. The augmented least
    # squares problem is solved directly (better conditioned than normal equations).
    n = T.shape[0]
    A = np.hstack([T, -y[:, None] * T[:, 1:]])
    ridge = math.sqrt(reg) * np.eye(A.shape[1])
    w = np.ones(n)
    best: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None
    used = 0
    for it in range(1, max_iter + 1):
        used = it
        Aw = np.vstack([A * (w / math.sqrt(n))[:, None], ridge])
        bw = np.concatenate([y * w / math.sqrt(n), np.zeros(A.shape[1])])
        x, *_ = np.linalg.lstsq(Aw, bw, rcond=None)
        num = x[:_N_TERMS]
        den = np.concatenate([[1.0], x[_N_TERMS:]])
        d = T @ den
        with np.errstate(divide="ignore", invalid="ignore"):
            rms = float(np.sqrt(np.mean((T @ num / d - y) ** 2)))
        if not math.isfinite(rms):
            break
        if best is not None and rms >= best[0] * (1 - 1e-3):
            if rms < best[0]:
                best = (rms, num, den)
            break
        best = (rms, num, den)
        w = 1.0 / np.where(np.abs(d) > 1e-12, d, 1e-12)
    if best is None:
        raise GeometryError("RPC fit failed: the least-squares problem has no finite solution")
    return best[1], best[2], used


def fit_rpc(
    camera: object,
    *,
    height_range_m: tuple[float, float],
    ccd: str | None = None,
    grid: tuple[int, int, int] = (21, 21, 7),
    regularization: float = 1e-12,
    max_iter: int = 10,
) -> tuple[Rpc, FitReport]:
    """Fit a terrain-independent RPC00B to any planetref camera.

    The camera is sampled on a 3-D grid: ``n_lines x n_samples`` image points spanning
    the image from edge to edge, each localised with ``camera.image_to_ground(...,
    terrain=h)`` at ``n_heights`` heights spanning ``height_range_m``. The ground points
    are converted to lon/lat/h with the camera's ellipsoid and latitude kind (which the
    RPC then uses), normalised, and the line and sample rational polynomials are solved
    separately by linear least squares with Tikhonov regularisation and iterative
    reweighting by the previous denominator (Tao & Hu 2001). The check grid is the set
    of cell centres of the image grid at ``2 * n_heights + 1`` heights.

    Args:
        camera: Any object implementing :class:`~planetref.camera.base.Camera`.
        height_range_m: ``(h_min, h_max)``, metres above the camera's ellipsoid, the
            heights the RPC must be valid for (``h_max > h_min``).
        ccd: Which CCD to fit (default: the camera's first).
        grid: ``(n_lines, n_samples, n_heights)`` of the fitting grid (at least
            ``(4, 4, 3)``; 39 unknowns per axis).
        regularization: Tikhonov parameter on the normalised coefficients, relative to
            the mean squared (weighted) equation. Small values (1e-14 to 1e-8) barely
            bias a well-determined fit and keep near-degenerate denominators (a camera
            that is almost affine in height) close to 1.
        max_iter: Maximum reweighting iterations.

    Returns:
        ``(rpc, report)``. The RPC's image offsets/scales put the image centre at 0 and
        the edges at ±1; the ground ones do the same for the sampled ground extent.

    Raises:
        InputError: For an invalid grid or height range.
        GeometryError: If the camera localises too few grid points or the fit fails.
    """
    try:
        h_min, h_max = (float(v) for v in height_range_m)
    except (TypeError, ValueError):
        raise InputError(
            f"expected (h_min, h_max), got {height_range_m!r}", field="height_range_m"
        ) from None
    if not (math.isfinite(h_min) and math.isfinite(h_max) and h_max > h_min):
        raise InputError(
            f"need finite h_max > h_min, got {height_range_m!r}", field="height_range_m"
        )
    try:
        n_l, n_s, n_h = (int(v) for v in grid)
    except (TypeError, ValueError):
        raise InputError(
            f"expected (n_lines, n_samples, n_heights), got {grid!r}", field="grid"
        ) from None
    if n_l < 4 or n_s < 4 or n_h < 3:
        raise InputError(f"grid must be at least (4, 4, 3), got {grid!r}", field="grid")
    if not (math.isfinite(regularization) and regularization >= 0):
        raise InputError(f"must be finite and >= 0, got {regularization}", field="regularization")

    n_lines, n_samples = camera.image_size(ccd)  # type: ignore[attr-defined]
    lines = np.linspace(0.0, n_lines, n_l)
    samples = np.linspace(0.0, n_samples, n_s)
    heights = np.linspace(h_min, h_max, n_h)
    fit = _sample_camera(camera, ccd, lines, samples, heights)
    if fit.line.size < 2 * 39:
        raise GeometryError(
            f"the camera localised only {fit.line.size} of "
            f"{n_l * n_s * n_h} grid points; at least 78 are needed"
        )

    lon_ref = float(np.median(fit.lon))
    dlon = wrap_longitude(fit.lon - lon_ref)
    lon_lo, lon_hi = float(dlon.min()), float(dlon.max())
    lat_lo, lat_hi = float(fit.lat.min()), float(fit.lat.max())
    long_off = float(wrap_longitude(lon_ref + 0.5 * (lon_lo + lon_hi)))
    lat_off = 0.5 * (lat_lo + lat_hi)
    long_scale = 0.5 * (lon_hi - lon_lo)
    lat_scale = 0.5 * (lat_hi - lat_lo)
    if not (long_scale > 0 and lat_scale > 0):
        raise GeometryError("the sampled ground points span no area; cannot fit an RPC")
    height_off, height_scale = 0.5 * (h_min + h_max), 0.5 * (h_max - h_min)
    # Raw RPC image coordinates have the first pixel centre at 0 (planetref: 0.5).
    line_off, line_scale = 0.5 * n_lines - 0.5, 0.5 * n_lines
    samp_off, samp_scale = 0.5 * n_samples - 0.5, 0.5 * n_samples

    def normalised(s: _Samples) -> NDArray[np.float64]:
        return _terms(
            wrap_longitude(s.lon - long_off) / long_scale,
            (s.lat - lat_off) / lat_scale,
            (s.h - height_off) / height_scale,
        )

    T = normalised(fit)
    rn = (fit.line - 0.5 - line_off) / line_scale
    cn = (fit.sample - 0.5 - samp_off) / samp_scale
    line_num, line_den, it_l = _solve_rational(T, rn, regularization, max_iter)
    samp_num, samp_den, it_s = _solve_rational(T, cn, regularization, max_iter)
    rpc = Rpc(
        line_off=line_off,
        samp_off=samp_off,
        lat_off=lat_off,
        long_off=long_off,
        height_off=height_off,
        line_scale=line_scale,
        samp_scale=samp_scale,
        lat_scale=lat_scale,
        long_scale=long_scale,
        height_scale=height_scale,
        line_num_coeff=tuple(line_num),
        line_den_coeff=tuple(line_den),
        samp_num_coeff=tuple(samp_num),
        samp_den_coeff=tuple(samp_den),
    )

    check_lines = 0.5 * (lines[:-1] + lines[1:])
    check_samples = 0.5 * (samples[:-1] + samples[1:])
    check_heights = np.linspace(h_min, h_max, 2 * n_h + 1)
    chk = _sample_camera(camera, ccd, check_lines, check_samples, check_heights)

    def errors(s: _Samples) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        pl, ps = rpc.project(s.lon, s.lat, s.h)
        return pl - s.line, ps - s.sample

    fl, fs = errors(fit)
    cl, cs = errors(chk)
    back_lon, back_lat = rpc.localize(chk.line, chk.sample, chk.h)
    back = lonlat_to_xyz(
        back_lon,
        back_lat,
        chk.h,
        camera.ellipsoid,  # type: ignore[attr-defined]
        camera.latitude_kind,
    )  # type: ignore[attr-defined]
    ground_err = np.linalg.norm(back - chk.xyz, axis=1)
    dens = np.concatenate([normalised(fit), normalised(chk)]) @ np.stack(
        [rpc._coeff_array[:, 1], rpc._coeff_array[:, 3]], axis=1
    )

    def rms(v: NDArray[np.float64]) -> float:
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    def vmax(v: NDArray[np.float64]) -> float:
        return float(np.max(v)) if v.size else float("nan")

    report = FitReport(
        fit_rms_line_px=rms(fl),
        fit_rms_sample_px=rms(fs),
        fit_max_px=vmax(np.hypot(fl, fs)),
        check_rms_line_px=rms(cl),
        check_rms_sample_px=rms(cs),
        check_max_px=vmax(np.hypot(cl, cs)),
        check_max_ground_m=float(np.max(ground_err)) if ground_err.size else float("nan"),
        min_abs_denominator=float(np.min(np.abs(dens))),
        n_fit=int(fit.line.size),
        n_check=int(chk.line.size),
        n_dropped=fit.dropped + chk.dropped,
        iterations=max(it_l, it_s),
        regularization=float(regularization),
    )
    return rpc, report
