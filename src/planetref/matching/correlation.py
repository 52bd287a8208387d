"""Batched zero-mean normalised cross-correlation (ZNCC) and sub-pixel peak fitting.

The arithmetic shared by the NCC matcher (:mod:`planetref.matching.ncc`) and the sub-pixel
refinement (:mod:`planetref.matching.refine`): many templates, each correlated with its own
search window, into one stack, and the sub-pixel position of many correlation peaks at once.

Array layout: a surface value ``S[n, i, j]`` is the ZNCC of template ``n`` with the part of
window ``n`` whose top-left pixel is ``(row i, column j)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["INVALID", "bilinear", "quadratic_peaks", "zncc_surfaces"]

#: Value given to surface positions without a defined correlation (below any ZNCC).
INVALID = -2.0


def zncc_surfaces(
    templates: NDArray[np.floating], windows: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Correlate each template with its own search window.

    OpenCV's ``matchTemplate`` (``TM_CCOEFF_NORMED``, zero-mean NCC, float32) per template,
    into one preallocated stack: the loop body is a single C call, every other step of the
    callers is vectorised over the stack. (Measured on 728 HiRISE templates of 21 x 21 in
    53 x 53 windows: this loop 0.30 s, a batched float32 FFT 0.41 s, float64
    ``scipy.signal.fftconvolve`` 1.27 s.)

    Args:
        templates: ``(N, a, b)`` templates.
        windows: ``(N, H, W)`` search windows, ``H >= a`` and ``W >= b``.

    Returns:
        ``(N, H - a + 1, W - b + 1)`` ZNCC surfaces in ``[-1, 1]``; positions where the
        correlation is undefined (a flat window or template) hold :data:`INVALID`.
    """
    import cv2

    t = np.ascontiguousarray(templates, np.float32)
    w = np.ascontiguousarray(windows, np.float32)
    n, a, b = t.shape
    out = np.empty((n, w.shape[1] - a + 1, w.shape[2] - b + 1), np.float32)
    for k in range(n):
        cv2.matchTemplate(w[k], t[k], cv2.TM_CCOEFF_NORMED, result=out[k])
    res = out.astype(np.float64)
    res[~np.isfinite(res)] = INVALID
    flat_t = t.reshape(n, -1).std(axis=1) <= 1e-7 * (1.0 + np.abs(t).reshape(n, -1).max(axis=1))
    res[flat_t] = INVALID
    return np.clip(res, INVALID, 1.0)


# least-squares quadratic on a 3x3 patch: f = a + b x + c y + d x^2 + e x y + g y^2
_XX, _YY = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
_DESIGN = np.column_stack(
    [np.ones(9), _XX.ravel(), _YY.ravel(), _XX.ravel() ** 2, (_XX * _YY).ravel(), _YY.ravel() ** 2]
)
_PINV = np.linalg.pinv(_DESIGN)


def quadratic_peaks(
    patches: NDArray[np.floating], method: str = "quadratic"
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Sub-pixel peaks of many 3x3 correlation patches centred on their integer maximum.

    ``"quadratic"`` fits a 2-D quadratic by least squares to the 9 values and falls back to
    the per-axis parabolas where the fit has no maximum within one pixel; ``"parabola"``
    uses the per-axis parabolas only.

    Args:
        patches: ``(N, 3, 3)`` values, ``[row, column]``, the maximum at ``[1, 1]``.
        method: ``"quadratic"`` or ``"parabola"``.

    Returns:
        ``(dx, dy, value, ok)``, each ``(N,)``: offset of the peak from the centre pixel
        (columns, rows), interpolated peak value, and whether a peak was found.
    """
    p = np.asarray(patches, np.float64).reshape(-1, 9)
    n = len(p)
    dx = np.zeros(n)
    dy = np.zeros(n)
    val = p[:, 4].copy()
    done = np.zeros(n, bool)
    if method == "quadratic":
        a, b, c, d, e, g = (_PINV @ p.T).reshape(6, n)
        det = 4.0 * d * g - e * e
        good = (d < 0) & (det > 0)
        safe = np.where(good, det, 1.0)
        qx = (-2.0 * g * b + e * c) / safe
        qy = (-2.0 * d * c + e * b) / safe
        good &= (np.abs(qx) <= 1.0) & (np.abs(qy) <= 1.0)
        dx[good], dy[good] = qx[good], qy[good]
        val[good] = (a + b * qx + c * qy + d * qx * qx + e * qx * qy + g * qy * qy)[good]
        done |= good
    fm, f0, fp, gm, gp = p[:, 3], p[:, 4], p[:, 5], p[:, 1], p[:, 7]
    den_x = fm - 2.0 * f0 + fp
    den_y = gm - 2.0 * f0 + gp
    good = ~done & (den_x < 0) & (den_y < 0)
    px = 0.5 * (fm - fp) / np.where(good, den_x, -1.0)
    py = 0.5 * (gm - gp) / np.where(good, den_y, -1.0)
    good &= (np.abs(px) <= 1.0) & (np.abs(py) <= 1.0)
    dx[good], dy[good] = px[good], py[good]
    val[good] = (f0 - 0.25 * (fm - fp) * px - 0.25 * (gm - gp) * py)[good]
    done |= good
    return dx, dy, val, done


def bilinear(
    image: NDArray[np.floating],
    x: NDArray[np.floating],
    y: NDArray[np.floating],
    valid: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Bilinear interpolation at corner-convention coordinates.

    Pixel ``(row r, column c)`` has its centre at ``(x, y) = (c + 0.5, r + 0.5)``. A sample
    is defined when its four neighbouring pixel centres lie inside the image and are valid.

    Args:
        image: ``(H, W)`` image, or ``(H, W, C)`` to sample ``C`` channels at once.
        x: Column coordinates, any shape.
        y: Row coordinates, same shape.
        valid: Optional ``(H, W)`` validity mask.

    Returns:
        ``(values, defined)``: values shaped like ``x`` (plus ``C`` last for a stack),
        ``defined`` shaped like ``x``; undefined samples are 0.
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    cx = np.asarray(x, np.float64) - 0.5
    cy = np.asarray(y, np.float64) - 0.5
    finite = np.isfinite(cx) & np.isfinite(cy)
    c0 = np.floor(np.where(finite, cx, -10.0))
    r0 = np.floor(np.where(finite, cy, -10.0))
    fx, fy = cx - c0, cy - r0
    c0 = c0.astype(np.int64)
    r0 = r0.astype(np.int64)
    # a sample exactly on the last pixel centre uses that pixel only
    c1 = np.where(fx > 0, c0 + 1, c0)
    r1 = np.where(fy > 0, r0 + 1, r0)
    inside = finite & (c0 >= 0) & (r0 >= 0) & (c1 < w) & (r1 < h)
    i00 = np.where(inside, r0 * w + c0, 0)
    i01 = np.where(inside, r0 * w + c1, 0)
    i10 = np.where(inside, r1 * w + c0, 0)
    i11 = np.where(inside, r1 * w + c1, 0)
    flat = img.reshape(h * w, -1)
    if img.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    else:
        flat = flat[:, 0]
    top = flat[i00] * (1 - fx) + flat[i01] * fx
    out = top * (1 - fy) + (flat[i10] * (1 - fx) + flat[i11] * fx) * fy
    if valid is not None:
        vf = np.asarray(valid).reshape(-1)
        inside &= vf[i00] & vf[i01] & vf[i10] & vf[i11]
    mask = inside[..., None] if img.ndim == 3 else inside
    return np.where(mask, out, 0.0), inside
