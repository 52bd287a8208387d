"""Compiled orthoimage block kernels (numba, ``nogil``): lattice to maps, resampling, cast.

The numpy/OpenCV reference is :func:`planetref.products.ortho_strip._resample_reference`
(``bilinear_lattice`` in float64, float32 maps, ``cv2.remap`` bilinear with a NaN
border, then :meth:`~planetref.products.ortho_strip.PixelType.cast`); these kernels do
the same arithmetic in one pass per stage and release the GIL, so the blocks of several
CCDs run in threads at once:

- :func:`lattice_maps`: the dense ``(line, sample)`` of a block from its lattice, exactly
  as :func:`~planetref.products.orthoimage.bilinear_lattice` (rows first, ``a (1 - f) +
  b f`` in float64, a zero weight ignores its end), rounded to float32, with the range of
  lines inside the image (the raw window to read).
- :func:`resample_bilinear`: bilinear sampling of the raw window as OpenCV 5's
  ``remap(INTER_LINEAR, BORDER_CONSTANT=NaN)`` computes it: ``a = fma(fx, s01 - s00,
  s00)``, ``b = fma(fx, s11 - s10, s10)``, ``fma(fy, b - a, a)`` in float32 with
  unquantised fractions; a pixel whose 2 x 2 support leaves the raw window is NaN. The
  tests bind it to ``cv2.remap`` (bit-identical on this machine's OpenCV; the bound
  stated there is 1e-3 DN).
- :func:`cast_block`: float values (NaN = no data) to the output integer type (round half
  to even, clip, nodata), as ``PixelType.cast``.
- :func:`halve_rows`: one overview level from the previous one, as GDAL's ``AVERAGE``
  (the numpy reference is :func:`planetref.products.overviews.halve_reference`).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["cast_block", "halve_rows", "lattice_maps", "resample_bilinear"]

njit = numba.njit(cache=True, nogil=True, error_model="numpy")


@intrinsic
def _fma32(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """``a * b + c`` in float32 with one rounding (LLVM's fma; libm's where no FMA unit)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        f32 = ir.FloatType()
        fnty = ir.FunctionType(f32, [f32, f32, f32])
        fn = builder.module.declare_intrinsic("llvm.fma", [f32], fnty)
        return builder.call(fn, args)

    return sig, codegen


@njit
def _lerp(a: float, b: float, f: float) -> float:
    if f == 0.0:
        return a
    if f == 1.0:
        return b
    return a * (1.0 - f) + b * f


@njit
def lattice_maps(
    lat_l: Any,
    lat_s: Any,
    ir_: Any,
    fr: Any,
    ic: Any,
    fc: Any,
    n_lines: int,
    n_samples: int,
    ml: Any,
    ms: Any,
) -> Any:
    """Dense float32 maps of a block from its lattice; the range of lines inside the image.

    Args:
        lat_l: Lattice lines, ``(n_r, n_c)`` float64.
        lat_s: Lattice samples, same shape.
        ir_: Lattice cell row of each output row, ``(R,)`` (``_cell``).
        fr: Fraction within it, ``(R,)``.
        ic: Lattice cell column of each output column, ``(C,)``.
        fc: Fraction within it, ``(C,)``.
        n_lines: Image lines.
        n_samples: Image samples.
        ml: Output lines, ``(R, C)`` float32 (filled).
        ms: Output samples, ``(R, C)`` float32 (filled).

    Returns:
        ``(any, lo, hi)``: whether a pixel is inside the image (``-1 < line < n_lines + 1``
        and likewise for samples) and the smallest and largest such line.
    """
    n_r, n_c = lat_l.shape
    n_out_c = ic.shape[0]
    tmp_l = np.empty(n_c)
    tmp_s = np.empty(n_c)
    lo, hi, found = np.inf, -np.inf, False
    lmax, smax = float(n_lines + 1), float(n_samples + 1)
    for r in range(ir_.shape[0]):
        if n_r == 1:
            for k in range(n_c):
                tmp_l[k] = lat_l[0, k]
                tmp_s[k] = lat_s[0, k]
        else:
            i0, f = ir_[r], fr[r]
            for k in range(n_c):
                tmp_l[k] = _lerp(lat_l[i0, k], lat_l[i0 + 1, k], f)
                tmp_s[k] = _lerp(lat_s[i0, k], lat_s[i0 + 1, k], f)
        for c in range(n_out_c):
            if n_c == 1:
                vl, vs = tmp_l[0], tmp_s[0]
            else:
                j0, g = ic[c], fc[c]
                vl = _lerp(tmp_l[j0], tmp_l[j0 + 1], g)
                vs = _lerp(tmp_s[j0], tmp_s[j0 + 1], g)
            l32, s32 = np.float32(vl), np.float32(vs)
            ml[r, c] = l32
            ms[r, c] = s32
            if l32 > -1.0 and l32 < lmax and s32 > -1.0 and s32 < smax:
                found = True
                lo = min(lo, float(l32))
                hi = max(hi, float(l32))
    return found, lo, hi


@njit
def resample_bilinear(
    raw: Any,
    l_lo: int,
    ml: Any,
    ms: Any,
    n_lines: int,
    n_samples: int,
    out: Any,
    dist: Any,
    want_dist: bool,
) -> None:
    """Bilinear samples of a raw window at the maps (pixel centres at +0.5), NaN outside.

    Args:
        raw: Raw lines ``l_lo:l_lo + H`` of the image, ``(H, W)`` float32 (NaN invalid).
        l_lo: First raw line of ``raw``.
        ml: Lines of the output pixels, ``(R, C)`` float32 (image pixel coordinates).
        ms: Samples, same shape.
        n_lines: Image lines (the inside test).
        n_samples: Image samples.
        out: ``(R, C)`` float32 values (filled; NaN where no value).
        dist: ``(R, C)`` float32 distances (samples) to the nearer side edge, ``-inf``
            where no value (filled when ``want_dist``).
        want_dist: Whether to fill ``dist``.
    """
    h, w = raw.shape
    half = np.float32(0.5)
    top = np.float32(l_lo + 0.5)
    nan32 = np.float32(np.nan)
    lmax, smax = float(n_lines + 1), float(n_samples + 1)
    fs = np.float32(n_samples)
    for r in range(ml.shape[0]):
        for c in range(ml.shape[1]):
            l32, s32 = ml[r, c], ms[r, c]
            val = nan32
            if l32 > -1.0 and l32 < lmax and s32 > -1.0 and s32 < smax:
                x = s32 - half
                y = l32 - top
                fx0 = math.floor(x)
                fy0 = math.floor(y)
                if fx0 >= 0.0 and fx0 < w - 1 and fy0 >= 0.0 and fy0 < h - 1:
                    sx, sy = int(fx0), int(fy0)
                    fx = x - np.float32(fx0)
                    fy = y - np.float32(fy0)
                    s00, s01 = raw[sy, sx], raw[sy, sx + 1]
                    s10, s11 = raw[sy + 1, sx], raw[sy + 1, sx + 1]
                    a = _fma32(fx, s01 - s00, s00)
                    b = _fma32(fx, s11 - s10, s10)
                    val = _fma32(fy, b - a, a)
            out[r, c] = val
            if want_dist:
                if np.isnan(val):
                    dist[r, c] = -np.inf
                else:
                    dist[r, c] = min(s32, fs - s32)


@njit
def cast_block(values: Any, lo: float, hi: float, nodata: float, out: Any) -> None:
    """Float values to an integer type: round half to even, clip to [lo, hi], NaN -> nodata."""
    for r in range(values.shape[0]):
        for c in range(values.shape[1]):
            v = values[r, c]
            if np.isnan(v):
                out[r, c] = nodata
            else:
                x = np.rint(np.float32(v))
                x = min(max(x, np.float32(lo)), np.float32(hi))
                out[r, c] = x


@njit
def halve_rows(src: Any, nodata: float, is_int: bool, out: Any) -> None:
    """Each 2 x 2 block of ``src``: the mean of its valid pixels, in ``src``'s type.

    Valid means ``v == v and v != nodata`` (NaN never is, so a float NaN nodata works
    too). The mean is taken in float64; integer types round it half away from zero, as
    GDAL does; a block without a valid pixel is ``nodata``.

    Args:
        src: ``(2 R, 2 C)`` pixels of one level.
        nodata: The nodata value.
        is_int: Whether the type is an integer one (round the mean).
        out: ``(R, C)`` pixels of the next level, same type (filled).
    """
    for r in range(out.shape[0]):
        for c in range(out.shape[1]):
            s, n = 0.0, 0
            for dr in range(2):
                for dc in range(2):
                    v = src[2 * r + dr, 2 * c + dc]
                    if v == v and v != nodata:
                        s += float(v)
                        n += 1
            if n == 0:
                out[r, c] = nodata
            else:
                m = s / n
                if is_int:
                    m = math.floor(m + 0.5) if m >= 0.0 else -math.floor(0.5 - m)
                out[r, c] = m
