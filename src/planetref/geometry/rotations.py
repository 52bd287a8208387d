"""The phi-omega-kappa rotation of classical photogrammetry and its derivatives.

``R = R_phi(Y) @ R_omega(X) @ R_kappa(Z)`` (angles in radians) rotates camera-frame
vectors into the local frame, with

* ``R_phi = [[cos, 0, -sin], [0, 1, 0], [sin, 0, cos]]``,
* ``R_omega = [[1, 0, 0], [0, cos, -sin], [0, sin, cos]]``,
* ``R_kappa = [[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]]``.

Two forms of the same rotation live here: :func:`rotation_matrix` (and
:func:`rotation_matrix_derivatives`) build the ``(..., 3, 3)`` matrices, and
:func:`rotate_to_camera` applies ``R^T`` to vectors factor by factor, with the
derivatives of the result w.r.t. the three angles, which is what a vectorised projection
kernel needs (no 3x3 matrices per point). The tests prove that they agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from planetref.arrays import F64

__all__ = [
    "CameraFrameVectors",
    "axis_rotation",
    "rotate_to_camera",
    "rotation_matrix",
    "rotation_matrix_derivatives",
]


def axis_rotation(axis: int, angle: ArrayLike) -> F64:
    """Right-handed rotations by ``angle`` (rad) about the x (0), y (1) or z (2) axis.

    ``x: [[1, 0, 0], [0, c, -s], [0, s, c]]``, ``y: [[c, 0, s], [0, 1, 0], [-s, 0, c]]``,
    ``z: [[c, -s, 0], [s, c, 0], [0, 0, 1]]``; shape ``angle.shape + (3, 3)``.
    """
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    i, j = ((1, 2), (2, 0), (0, 1))[axis]
    r = np.zeros((*a.shape, 3, 3))
    r[..., axis, axis] = 1.0
    r[..., i, i], r[..., i, j], r[..., j, i], r[..., j, j] = c, -s, s, c
    return r


def _axis_rotations(phi: F64, omega: F64, kappa: F64) -> tuple[F64, F64, F64]:
    # R_phi is the rotation about y by -phi: the transpose of axis_rotation(1, phi).
    rp = np.ascontiguousarray(np.swapaxes(axis_rotation(1, phi), -1, -2))
    return rp, axis_rotation(0, omega), axis_rotation(2, kappa)


def rotation_matrix(phi: ArrayLike, omega: ArrayLike, kappa: ArrayLike) -> F64:
    """``R_phi(Y) @ R_omega(X) @ R_kappa(Z)`` (angles in radians), shape ``(..., 3, 3)``."""
    rp, ro, rk = _axis_rotations(*(np.asarray(a, dtype=np.float64) for a in (phi, omega, kappa)))
    return rp @ ro @ rk


def rotation_matrix_derivatives(
    phi: ArrayLike, omega: ArrayLike, kappa: ArrayLike
) -> tuple[F64, F64, F64, F64]:
    """The rotation and its derivatives w.r.t. phi, omega and kappa (per radian)."""
    phi, omega, kappa = (np.asarray(a, dtype=np.float64) for a in (phi, omega, kappa))
    rp, ro, rk = _axis_rotations(phi, omega, kappa)
    # d/da of a rotation about one axis is the generator applied to it.
    drp = np.zeros_like(rp)
    cp, sp = np.cos(phi), np.sin(phi)
    drp[..., 0, 0], drp[..., 0, 2], drp[..., 2, 0], drp[..., 2, 2] = -sp, -cp, cp, -sp
    dro = np.zeros_like(ro)
    co, so = np.cos(omega), np.sin(omega)
    dro[..., 1, 1], dro[..., 1, 2], dro[..., 2, 1], dro[..., 2, 2] = -so, -co, co, -so
    drk = np.zeros_like(rk)
    ck, sk = np.cos(kappa), np.sin(kappa)
    drk[..., 0, 0], drk[..., 0, 1], drk[..., 1, 0], drk[..., 1, 1] = -sk, -ck, ck, -sk
    r = rp @ ro @ rk
    return r, drp @ ro @ rk, rp @ dro @ rk, rp @ ro @ drk


@dataclass(frozen=True)
class CameraFrameVectors:
    """``R^T d`` for many vectors ``d``, with what its derivatives need.

    Attributes:
        u: First camera-frame component, ``(m,)``.
        v: Second component.
        w: Third component.
        jacobian: ``(m, 6, 3)`` indexed ``[point, q, component]``: ``d(u, v, w)/dq`` for
            ``q`` = the three components of ``d`` (rows 0-2, i.e. ``(R0 R)`` itself),
            then ``phi, omega, kappa`` (rows 3-5, per radian); ``None`` unless requested.
    """

    u: F64
    v: F64
    w: F64
    jacobian: F64 | None = None


def rotate_to_camera(
    phi: F64, omega: F64, kappa: F64, d: F64, *, r0: F64 | None = None, derivatives: bool = False
) -> CameraFrameVectors:
    """Apply ``(R0 R)^T`` to vectors, factor by factor (no matrices per point).

    Args:
        phi: Angles in radians, ``(m,)`` each (see the module doc).
        omega: See ``phi``.
        kappa: See ``phi``.
        d: Vectors in the frame ``R0`` maps to (e.g. body-fixed ``P - S``), ``(m, 3)``.
        r0: Optional constant rotation ``(3, 3)`` in front of ``R`` (identity if None).
        derivatives: Also return the derivatives w.r.t. the angles and the vectors.

    Returns:
        :class:`CameraFrameVectors`.
    """
    r0m = np.eye(3) if r0 is None else np.asarray(r0, np.float64)
    dl = d @ r0m  # R0^T d, row-wise
    cp, sp = np.cos(phi), np.sin(phi)
    co, so = np.cos(omega), np.sin(omega)
    ck, sk = np.cos(kappa), np.sin(kappa)
    d0, d1, d2 = dl[:, 0], dl[:, 1], dl[:, 2]
    # a = R_phi^T dl, b = R_omega^T a, (u, v, w) = R_kappa^T b.
    a0 = cp * d0 + sp * d2
    a2 = -sp * d0 + cp * d2
    b1 = co * d1 + so * a2
    b2 = -so * d1 + co * a2
    u = ck * a0 + sk * b1
    v = -sk * a0 + ck * b1
    if not derivatives:
        return CameraFrameVectors(u, v, b2)
    jac = np.empty((len(u), 6, 3))
    dang = jac[:, 3:]
    # phi: d a / d phi = (a2, 0, -a0)
    bp1 = so * (-a0)
    dang[:, 0, 0] = ck * a2 + sk * bp1
    dang[:, 0, 1] = -sk * a2 + ck * bp1
    dang[:, 0, 2] = co * (-a0)
    # omega: d b / d omega = (0, b2, -b1)
    dang[:, 1, 0] = sk * b2
    dang[:, 1, 1] = ck * b2
    dang[:, 1, 2] = -b1
    # kappa
    dang[:, 2, 0] = v
    dang[:, 2, 1] = -u
    dang[:, 2, 2] = 0.0
    dvec = jac[:, :3]
    for i in range(3):
        e0, e1, e2 = r0m[i, 0], r0m[i, 1], r0m[i, 2]
        ga0 = cp * e0 + sp * e2
        ga2 = -sp * e0 + cp * e2
        gb1 = co * e1 + so * ga2
        dvec[:, i, 0] = ck * ga0 + sk * gb1
        dvec[:, i, 1] = -sk * ga0 + ck * gb1
        dvec[:, i, 2] = -so * e1 + co * ga2
    return CameraFrameVectors(u, v, b2, jac)
