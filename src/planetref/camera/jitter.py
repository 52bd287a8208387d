"""How attitude jitter reaches a line-scan camera's nodes and its CCD overlaps.

Two questions about high-frequency attitude, answered from the camera alone:

* **What can a node series carry?** Orientation nodes every ``s`` lines of period ``p``
  sample the attitude at ``1 / (s p)`` Hz: nothing above the Nyquist frequency
  ``1 / (2 s p)`` (:func:`node_nyquist_hz`) survives, and Lagrange interpolation of
  order ``k`` between the nodes already loses amplitude well below it
  (:func:`interpolation_limit_hz`: the highest frequency it keeps within a tolerance).
* **What do the CCD overlaps see?** Neighbouring CCDs of a staggered focal plane see the
  same ground ``dt`` seconds apart (:func:`stagger_lines` measures the line offset
  through the camera). The difference of their image positions of one ground point is
  the attitude's change over ``dt``: a jitter component ``A sin(2 pi f t + phi)`` leaves
  ``A |2 sin(pi f dt)|`` in it (:func:`overlap_transfer`), which vanishes at ``f = 0``
  and at every multiple of ``1 / dt`` (:func:`overlap_blind_frequencies`) and is below
  ``A`` under ``1 / (6 dt)`` (:func:`overlap_unit_gain_hz`). Tie points between the
  overlaps therefore see the high frequencies that MCPs against a 5 m reference see
  poorly, and nothing of the slow attitude: together with MCPs a model resolves
  jitter up to the node series' limit, except near the blind frequencies.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.errors import InputError
from planetref.geometry.lagrange import LagrangeWindows

__all__ = [
    "interpolation_limit_hz",
    "interpolation_loss",
    "node_nyquist_hz",
    "overlap_blind_frequencies",
    "overlap_transfer",
    "overlap_unit_gain_hz",
    "stagger_lines",
    "stagger_points",
]


def node_nyquist_hz(line_period_s: float, node_spacing_lines: float) -> float:
    """Nyquist frequency (Hz) of orientation nodes every ``node_spacing_lines`` lines.

    ``line_rate / (2 * spacing) = 1 / (2 * spacing * line_period_s)``.
    """
    if not (line_period_s > 0 and node_spacing_lines > 0):
        raise InputError("line period and node spacing must be > 0", field="node_spacing_lines")
    return 1.0 / (2.0 * float(node_spacing_lines) * float(line_period_s))


def interpolation_loss(cycles_per_node: float, order: int, n_phase: int = 16) -> float:
    """Worst error of Lagrange interpolation of a unit sinusoid between its nodes.

    Nodes at integer positions sample ``sin(2 pi c x + phi)`` (``c`` cycles per node
    spacing); the interpolation of ``order`` nodes per window (the camera's) is compared
    with the sinusoid at 64 points per node interval over ``n_phase`` phases.

    Args:
        cycles_per_node: ``f * spacing * line_period`` (0.5 at the Nyquist frequency).
        order: Nodes per Lagrange window.
        n_phase: Phases tried.

    Returns:
        The largest absolute error (the sinusoid's amplitude is 1).
    """
    k = int(order)
    nodes = np.arange(-2 * k, 2 * k + 2, dtype=np.float64)
    win = LagrangeWindows(nodes, k)
    x = np.linspace(0.0, 1.0, 65)[:-1]
    start, w, _ = win.weights(x)
    idx = win.window_nodes(start)
    worst = 0.0
    for phi in np.linspace(0.0, np.pi, n_phase, endpoint=False):
        v = np.sin(2.0 * np.pi * cycles_per_node * nodes + phi)
        got = np.sum(w * v[idx], axis=1)
        want = np.sin(2.0 * np.pi * cycles_per_node * x + phi)
        worst = max(worst, float(np.max(np.abs(got - want))))
    return worst


def interpolation_limit_hz(
    line_period_s: float, node_spacing_lines: float, order: int, tolerance: float = 0.01
) -> float:
    """Highest frequency (Hz) whose sinusoid the node series carries within ``tolerance``.

    The error of Lagrange interpolation (:func:`interpolation_loss`) grows with the
    frequency; this bisects for where it reaches ``tolerance`` of the amplitude. Order
    4 keeps 1 % up to 0.13 cycles per node (0.26 of the Nyquist frequency) and 5 % up
    to 0.20.

    Args:
        line_period_s: Line period (s).
        node_spacing_lines: Lines between nodes.
        order: Nodes per Lagrange window.
        tolerance: Error allowed, as a fraction of the amplitude.
    """
    lo, hi = 0.0, 0.5
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if interpolation_loss(mid, order) <= tolerance:
            lo = mid
        else:
            hi = mid
    return lo / (float(node_spacing_lines) * float(line_period_s))


def overlap_transfer(frequency_hz: ArrayLike, dt_s: float) -> F64:
    """Gain ``|2 sin(pi f dt)|`` of a jitter component in a CCD-overlap difference.

    A pointing ``A sin(2 pi f t + phi)`` moves the image of a ground point seen at ``t``
    and at ``t + dt`` by its values there; their difference is
    ``2 A sin(pi f dt) cos(2 pi f (t + dt/2) + phi)``.

    Args:
        frequency_hz: Frequencies (Hz).
        dt_s: Time between the two CCDs' views of one ground point (s); the stagger
            in lines (:func:`stagger_lines`) times the line period.

    Returns:
        The gains, the shape of ``frequency_hz``.
    """
    f = np.asarray(frequency_hz, np.float64)
    return np.abs(2.0 * np.sin(np.pi * f * float(dt_s)))


def overlap_blind_frequencies(dt_s: float, max_frequency_hz: float) -> F64:
    """The frequencies (Hz, ``0 < f <= max_frequency_hz``) an overlap cannot see: ``k / dt``."""
    dt = abs(float(dt_s))
    if dt == 0:
        raise InputError("the CCDs are not staggered (dt = 0): the overlap sees no jitter")
    n = math.floor(float(max_frequency_hz) * dt)
    return np.arange(1, n + 1, dtype=np.float64) / dt


def overlap_unit_gain_hz(dt_s: float) -> float:
    """Lowest frequency (Hz) at which the overlap difference has gain 1: ``1 / (6 dt)``.

    Below it the difference is smaller than the jitter itself (``~ 2 pi f dt``), so its
    noise enters an estimate of the jitter amplified by ``1 / |2 sin(pi f dt)|``.
    """
    dt = abs(float(dt_s))
    if dt == 0:
        raise InputError("the CCDs are not staggered (dt = 0): the overlap sees no jitter")
    return 1.0 / (6.0 * dt)


def stagger_lines(
    camera: Camera,
    ccd_a: str,
    ccd_b: str,
    line: ArrayLike,
    sample: ArrayLike,
    terrain: Terrain | float = 0.0,
) -> tuple[F64, F64]:
    """Where CCD ``ccd_b`` sees the ground that ``ccd_a`` sees at ``(line, sample)``.

    Args:
        camera: The camera.
        ccd_a: The CCD of the given image points.
        ccd_b: The other CCD.
        line: Lines in ``ccd_a`` (pixels).
        sample: Samples in ``ccd_a``.
        terrain: The ground (a terrain or a height above the ellipsoid, m).

    Returns:
        ``(line_b, sample_b)``; ``line_b - line`` is the stagger in lines (its time is
        that times the line period), NaN where the ray misses or does not project.
    """
    lb, sb, _ = stagger_points(camera, ccd_a, ccd_b, line, sample, terrain)
    return lb, sb


def stagger_points(
    camera: Camera,
    ccd_a: str,
    ccd_b: str,
    line: ArrayLike,
    sample: ArrayLike,
    terrain: Terrain | float = 0.0,
) -> tuple[F64, F64, F64]:
    """:func:`stagger_lines` with the ground points it went through.

    Returns:
        ``(line_b, sample_b, xyz)``: as :func:`stagger_lines`, and the ``(N, 3)`` ground
        points (body-fixed, m) of ``(line, sample)`` in ``ccd_a``, NaN where the ray misses.
    """
    ln = np.atleast_1d(np.asarray(line, np.float64))
    sm = np.atleast_1d(np.asarray(sample, np.float64))
    xyz = camera.image_to_ground(ln, sm, terrain, ccd=ccd_a, on_miss="nan")
    ok = np.all(np.isfinite(xyz), axis=1)
    lb = np.full(len(ln), np.nan)
    sb = np.full(len(ln), np.nan)
    if ok.any():
        ip = camera.ground_to_image(xyz[ok], ccd=ccd_b)
        lb[ok] = np.where(ip.valid, ip.line, np.nan)
        sb[ok] = np.where(ip.valid, ip.sample, np.nan)
    return lb, sb, xyz
