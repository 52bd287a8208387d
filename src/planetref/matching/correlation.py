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

__all__ = ["INVALID", "quadratic_peaks", "zncc_surfaces"]

#: Value given to surface positions without a defined correlation (below any ZNCC).
INVALID = -2.0


def zncc_surfaces(
    templates: NDArray[np.floating],
    windows: NDArray[np.floating],
    masks: NDArray[np.bool_] | None = None,
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
        masks: Optional ``(N, a, b)`` template masks: where a mask has a False pixel the
            ZNCC of that template is taken over its True pixels only (means, variances
            and the product all over the same pixels of template and window; OpenCV's
            masked ``TM_CCOEFF_NORMED``). Templates whose mask is all True take the
            unmasked path.

    Returns:
        ``(N, H - a + 1, W - b + 1)`` ZNCC surfaces in ``[-1, 1]``; positions where the
        correlation is undefined (a flat window or template) hold :data:`INVALID`.
    """
    import cv2

    t = np.ascontiguousarray(templates, np.float32)
    w = np.ascontiguousarray(windows, np.float32)
    n, a, b = t.shape
    out = np.empty((n, w.shape[1] - a + 1, w.shape[2] - b + 1), np.float32)
    partial = np.zeros(n, bool) if masks is None else ~np.asarray(masks, bool).all(axis=(1, 2))
    for k in np.flatnonzero(~partial):
        cv2.matchTemplate(w[k], t[k], cv2.TM_CCOEFF_NORMED, result=out[k])
    for k in np.flatnonzero(partial):
        m = np.asarray(masks[k], np.float32)  # type: ignore[index]
        out[k] = cv2.matchTemplate(w[k], t[k], cv2.TM_CCOEFF_NORMED, mask=m)
    res = out.astype(np.float64)
    res[~np.isfinite(res)] = INVALID
    flat = t.reshape(n, -1).astype(np.float64)
    wt = np.ones_like(flat) if masks is None else np.asarray(masks, bool).reshape(n, -1)
    cnt = np.maximum(wt.sum(axis=1), 1)
    mean = (flat * wt).sum(axis=1) / cnt
    spread = np.sqrt(((flat - mean[:, None]) ** 2 * wt).sum(axis=1) / cnt)
    flat_t = spread <= 1e-7 * (1.0 + np.abs(flat * wt).max(axis=1))
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
