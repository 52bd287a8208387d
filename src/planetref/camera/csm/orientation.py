"""Quaternions and rotation matrices as usgscsm (and ALE, through Eigen) compute them.

Quaternions are scalar-first ``[w, x, y, z]`` and not renormalised between operations, so
that resampled attitudes match usgscsm's to the last bit that matters.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from planetref.camera.csm.interpolation import interp_index
from planetref.camera.csm.isd import CsmOrientations

__all__ = []


# ---------------------------------------------------------------------------------------
# Quaternions as Eigen (hence ALE) computes them: scalar-first [w, x, y, z], not
# renormalised between operations, so that resampled attitudes match usgscsm's.
# ---------------------------------------------------------------------------------------


def _qmul(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by + ay * bw + az * bx - ax * bz,
            aw * bz + az * bw + ax * by - ay * bx,
        ],
        axis=-1,
    )


def _qinv(q: NDArray[np.float64]) -> NDArray[np.float64]:
    n2 = np.sum(q * q, axis=-1, keepdims=True)
    return q * np.array([1.0, -1.0, -1.0, -1.0]) / n2


def _qslerp(
    a: NDArray[np.float64], b: NDArray[np.float64], t: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Eigen's ``QuaternionBase::slerp`` (also extrapolates for t outside [0, 1])."""
    d = np.sum(a * b, axis=-1)
    abs_d = np.abs(d)
    linear = abs_d >= 1.0 - np.finfo(np.float64).eps
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.arccos(np.where(linear, 0.0, abs_d))
        sin_t = np.sin(theta)
        s0 = np.where(linear, 1.0 - t, np.sin((1.0 - t) * theta) / sin_t)
        s1 = np.where(linear, t, np.sin(t * theta) / sin_t)
    s1 = np.where(d < 0, -s1, s1)
    return s0[..., None] * a + s1[..., None] * b


def qmatrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Eigen's ``toRotationMatrix`` (exact rotation only for unit quaternions)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    tx, ty, tz = 2 * x, 2 * y, 2 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    m = np.stack(
        [
            1 - (tyy + tzz),
            txy - twz,
            txz + twy,
            txy + twz,
            1 - (txx + tzz),
            tyz - twx,
            txz - twy,
            tyz + twx,
            1 - (txx + tyy),
        ],
        axis=-1,
    )
    return m.reshape((*q.shape[:-1], 3, 3))


def quat_from_matrix(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Eigen's rotation matrix -> quaternion (Shoemake), ``[w, x, y, z]``."""
    t = float(np.trace(m))
    q = np.zeros(4)
    if t > 0:
        t = math.sqrt(t + 1.0)
        q[0] = 0.5 * t
        t = 0.5 / t
        q[1] = (m[2, 1] - m[1, 2]) * t
        q[2] = (m[0, 2] - m[2, 0]) * t
        q[3] = (m[1, 0] - m[0, 1]) * t
    else:
        i = 0
        if m[1, 1] > m[0, 0]:
            i = 1
        if m[2, 2] > m[i, i]:
            i = 2
        j, k = (i + 1) % 3, (i + 2) % 3
        t = math.sqrt(m[i, i] - m[j, j] - m[k, k] + 1.0)
        q[1 + i] = 0.5 * t
        t = 0.5 / t
        q[0] = (m[k, j] - m[j, k]) * t
        q[1 + j] = (m[j, i] + m[i, j]) * t
        q[1 + k] = (m[k, i] + m[i, k]) * t
    return q


class AleOrientations:
    """The part of ALE's ``Orientations`` that usgscsm uses (SLERP interpolation)."""

    def __init__(
        self,
        rotations: NDArray[np.float64],
        times: NDArray[np.float64],
        avs: NDArray[np.float64] | None,
        const: NDArray[np.float64],
    ) -> None:
        self.rotations = rotations
        self.times = times
        self.avs = avs
        self.const = const

    @classmethod
    def from_isd(cls, o: CsmOrientations) -> AleOrientations:
        return cls(
            np.array(o.quaternions),
            np.array(o.times),
            None if o.angular_velocities is None else np.array(o.angular_velocities),
            quat_from_matrix(np.asarray(o.constant_rotation)),
        )

    def interpolate(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        t = np.asarray(t, dtype=np.float64)
        if len(self.times) > 1:
            idx, frac = interp_index(self.times, t)
            q = _qslerp(self.rotations[idx], self.rotations[idx + 1], frac)
        elif self.avs is None:
            q = np.broadcast_to(self.rotations[0], (*t.shape, 4))
        else:
            av = self.avs[0]
            n = float(np.linalg.norm(av))
            axis = av / n if n > 0 else av
            half = 0.5 * (t - self.times[0]) * n
            spin = np.concatenate(
                [np.cos(half)[..., None], np.sin(half)[..., None] * axis], axis=-1
            )
            q = _qmul(spin, self.rotations[0])
        return _qmul(np.broadcast_to(self.const, q.shape), q)

    def interpolate_av(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        t = np.asarray(t, dtype=np.float64)
        if self.avs is None:
            return np.zeros((*t.shape, 3))
        if len(self.times) == 1:
            return np.broadcast_to(self.avs[0], (*t.shape, 3)).copy()
        idx, frac = interp_index(self.times, t)
        a, b = self.avs[idx], self.avs[idx + 1]
        return a + frac[..., None] * (b - a)

    def inverse(self) -> AleOrientations:
        # The constant rotation is folded into the time-dependent ones (ALE's inverse()).
        rots = _qmul(_qinv(self.rotations), _qinv(self.const)[None, :])
        return AleOrientations(rots, self.times, None, np.array([1.0, 0.0, 0.0, 0.0]))

    def compose(self, rhs: AleOrientations) -> AleOrientations:
        """``self * rhs`` on the union of both time grids (ALE's ``operator*=``)."""
        times = np.unique(np.concatenate([self.times, rhs.times]))
        inv_const = _qinv(self.const)
        lhs_rot = _qmul(np.broadcast_to(inv_const, (len(times), 4)), self.interpolate(times))
        rots = _qmul(lhs_rot, rhs.interpolate(times))
        return AleOrientations(rots, times, None, self.const)

    def rotate_states(
        self, t: NDArray[np.float64], pos: NDArray[np.float64], vel: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """ALE's ``rotateStateAt``: ``p' = R p`` and ``v' = R v + R [av]^T p``."""
        rot = qmatrix(self.interpolate(t))
        av = self.interpolate_av(t)
        ax, ay, az = av[:, 0], av[:, 1], av[:, 2]
        zero = np.zeros_like(ax)
        # ALE's avSkewMatrix: the transpose of the usual cross-product matrix.
        skew = np.stack([zero, az, -ay, -az, zero, ax, ay, -ax, zero], -1).reshape(-1, 3, 3)
        new_pos = np.einsum("mij,mj->mi", rot, pos)
        new_vel = np.einsum("mij,mj->mi", rot, vel) + np.einsum("mij,mj->mi", rot @ skew, pos)
        return new_pos, new_vel


# ---------------------------------------------------------------------------------------
# The camera
# ---------------------------------------------------------------------------------------


def euler_matrix(
    a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Port of usgscsm's ``calculateRotationMatrixFromEuler`` (row-major), shape ``(M, 3, 3)``."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    m = np.stack(
        [
            cb * cc,
            -ca * sc + sa * sb * cc,
            sa * sc + ca * sb * cc,
            cb * sc,
            ca * cc + sa * sb * sc,
            -sa * cc + ca * sb * sc,
            -sb,
            sa * cb,
            ca * cb,
        ],
        axis=-1,
    )
    return m.reshape((*a.shape, 3, 3))
