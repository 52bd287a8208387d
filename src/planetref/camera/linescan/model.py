"""The rigorous push-broom (line-scan) camera: the orientation image model (OIM).

Model
-----
* **Time.** Image line ``l`` (continuous, pixel-corner convention: line ``i`` spans
  ``[i, i+1)`` and its centre is ``i + 0.5``) is exposed at ``t(l)`` given by a
  piecewise-linear :class:`LineRateTable`.
* **Exterior orientation (EO).** ``N`` orientation nodes at fixed image lines each hold
  ``X, Y, Z`` (metres, body-fixed) and ``phi, omega, kappa`` (radians). The EO of any
  line is the Lagrange interpolation, in time, of the ``k`` neighbouring nodes
  (``k = interpolation_order``, default 4): for ``t`` in ``[t_i, t_{i+1})`` the nodes
  ``i - k/2 + 1 ... i + k/2`` (clamped to the ends) are used.
* **Rotation.** ``R = R0 @ R_phi(Y) @ R_omega(X) @ R_kappa(Z)``, the phi-omega-kappa
  sequence of classical photogrammetry, rotates camera-frame vectors into the body-fixed
  frame. ``R0`` (``frame_rotation``) is a constant rotation from a local frame (for
  instance the orbit frame: x along track, y across track, z radial up) to the body-fixed
  frame, so that the adjustable angles stay small and far from gimbal lock.
* **Camera frame and collinearity.** The camera looks along ``-z``; the focal plane's x
  axis points along track (the line direction) and y across track (the sample
  direction). With ``[U, V, W] = R^T (P - S)``: ``x - x0 = -f U / W`` and
  ``y - y0 = -f V / W`` (focal-plane millimetres).
* **Interior orientation (IO).** Principal point ``(x0, y0)`` and focal length ``f``
  (mm), shared by every CCD of the camera.
* **CCDs.** Each CCD is a line of ``n_samples`` pixels of pitch ``p`` (mm) whose
  sample-0 edge sits at ``(x_mm, y_mm)`` in the focal plane, rotated by ``angle_rad``
  from the y axis: sample ``s`` is at ``(x_mm + s p sin a, y_mm + s p cos a)``. Several
  CCDs (HiRIC's three TDI arrays) share one EO and IO.
* **Lens distortion (optional, simulation truths).** A CCD may carry Brown-Conrady
  ``distortion = (k1, k2, p1, p2)`` (:mod:`~planetref.camera.linescan.lens`); the
  estimated model has none.

Image coordinates are ``(line, sample)`` with the first pixel's centre at ``(0.5, 0.5)``,
as everywhere in planetref.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.camera.base import ConstantHeight, ImagePoints, OnMiss, Terrain
from planetref.camera.linescan.kernel import RAW_COLUMNS, LineScanKernel
from planetref.camera.linescan.sensor import CcdGeometry, InteriorOrientation, LineRateTable
from planetref.errors import GeometryError, InputError
from planetref.geometry.geodesy import Ellipsoid, LatitudeKind, ray_ellipsoid_intersection
from planetref.geometry.rotations import rotation_matrix
from planetref.runtime.atomic import write_json_atomic

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "CcdGeometry",
    "ImagePartials",
    "InteriorOrientation",
    "LineRateTable",
    "LineScanCamera",
]

FORMAT_NAME = "planetref-linescan"
FORMAT_VERSION = 1


# ----------------------------------------------------------------- partials
@dataclass(frozen=True)
class ImagePartials:
    """Partial derivatives of image coordinates, vectorised over ``M`` observations.

    Rows are ordered ``(line, sample)``. Each observation depends on ``k`` orientation
    nodes (its Lagrange window), listed in ``node_index``.

    Attributes:
        line: Projected line of each ground point, shape ``(M,)``.
        sample: Projected sample, shape ``(M,)``.
        node_index: Indices of the nodes each observation depends on, ``(M, k)``.
        d_nodes: ``d(line, sample) / d(node params)``, shape ``(M, 2, k, 6)``; the
            parameters are ``X, Y, Z`` (per metre) and ``phi, omega, kappa`` (per radian).
        d_interior: ``d(line, sample) / d(x0, y0, f)`` (per millimetre), ``(M, 2, 3)``.
        d_ground: ``d(line, sample) / d(X, Y, Z)`` of the ground point (per metre),
            ``(M, 2, 3)``.
        d_ccd: ``d(line, sample) / d(x_mm, y_mm, angle_rad)`` of the CCD's placement in
            the focal plane (per millimetre, per radian), ``(M, 2, 3)``.
    """

    line: F64
    sample: F64
    node_index: NDArray[np.intp]
    d_nodes: F64
    d_interior: F64
    d_ground: F64
    d_ccd: F64

    def dense_nodes(self, n_nodes: int) -> F64:
        """The node partials scattered into a dense ``(M, 2, n_nodes * 6)`` array."""
        m, _, k, _ = self.d_nodes.shape
        out = np.zeros((m, 2, n_nodes, 6))
        rows = np.repeat(np.arange(m), k)
        for c in range(2):
            out[rows, c, self.node_index.ravel()] = self.d_nodes[:, c].reshape(m * k, 6)
        return out.reshape(m, 2, n_nodes * 6)


# ------------------------------------------------------------------- camera
@dataclass(frozen=True, eq=False)
class LineScanCamera:
    """The rigorous line-scan camera (orientation image model); see the module doc.

    Attributes:
        ellipsoid: The body (heights, latitudes) the camera refers to.
        frame_rotation: ``R0``, shape ``(3, 3)``, local frame -> body-fixed.
        line_rates: Line -> time table.
        node_lines: Image lines of the orientation nodes, shape ``(N,)``, increasing.
        nodes: ``(N, 6)`` node parameters ``X, Y, Z`` (m), ``phi, omega, kappa`` (rad).
        interpolation_order: Number ``k`` of nodes in each Lagrange window.
        interior: Interior orientation.
        ccds: The CCDs; names must be unique.
        latitude_kind: Latitude convention of the lon/lat interfaces.
        name: Free-form identifier (e.g. the strip id).
    """

    ellipsoid: Ellipsoid
    frame_rotation: F64
    line_rates: LineRateTable
    node_lines: F64
    nodes: F64
    interior: InteriorOrientation
    ccds: tuple[CcdGeometry, ...]
    interpolation_order: int = 4
    latitude_kind: LatitudeKind = "planetocentric"
    name: str = ""
    _kernel: LineScanKernel = field(init=False, repr=False)
    _poly: F64 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        r0 = np.array(self.frame_rotation, dtype=np.float64)
        if r0.shape != (3, 3) or not np.all(np.isfinite(r0)):
            raise InputError("must be a finite 3x3 matrix", field="frame_rotation")
        if np.abs(r0 @ r0.T - np.eye(3)).max() > 1e-9 or np.linalg.det(r0) < 0:
            raise InputError(
                "must be a proper rotation (orthonormal, det +1)", field="frame_rotation"
            )
        lines = np.array(self.node_lines, dtype=np.float64).ravel()
        nodes = np.array(self.nodes, dtype=np.float64)
        if nodes.ndim != 2 or nodes.shape[1] != 6:
            raise InputError(f"must have shape (N, 6), got {nodes.shape}", field="nodes")
        if len(lines) != len(nodes):
            raise InputError(f"{len(lines)} node lines for {len(nodes)} nodes", field="node_lines")
        if len(lines) < 2:
            raise InputError("at least 2 orientation nodes are needed", field="nodes")
        if not (np.all(np.isfinite(lines)) and np.all(np.isfinite(nodes))):
            raise InputError("must be finite (NaN or inf found)", field="nodes")
        times = self.line_rates.time(lines)
        if np.any(np.diff(times) <= 0):
            raise InputError("node times must strictly increase", field="node_lines")
        if int(self.interpolation_order) < 2:
            raise InputError(
                f"must be >= 2, got {self.interpolation_order}", field="interpolation_order"
            )
        if not self.ccds:
            raise InputError("a camera needs at least one CCD", field="ccds")
        names = [c.name for c in self.ccds]
        if len(set(names)) != len(names):
            raise InputError(f"CCD names must be unique, got {names}", field="ccds")
        for arr in (r0, lines, nodes, times):
            arr.setflags(write=False)
        object.__setattr__(self, "frame_rotation", r0)
        object.__setattr__(self, "node_lines", lines)
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "ccds", tuple(self.ccds))
        object.__setattr__(self, "interpolation_order", int(self.interpolation_order))
        kernel = LineScanKernel(self.line_rates, lines, int(self.interpolation_order), r0)
        object.__setattr__(self, "_kernel", kernel)
        object.__setattr__(self, "_poly", kernel.eo_poly(nodes))

    # ------------------------------------------------------------ basics
    @property
    def ccd_names(self) -> tuple[str, ...]:
        """Names of the CCDs; the first is the default."""
        return tuple(c.name for c in self.ccds)

    @property
    def n_nodes(self) -> int:
        """Number of orientation nodes."""
        return len(self.nodes)

    def ccd(self, name: str | None = None) -> CcdGeometry:
        """The CCD called ``name`` (the first one when ``None``)."""
        if name is None:
            return self.ccds[0]
        for c in self.ccds:
            if c.name == name:
                return c
        raise InputError(f"unknown CCD {name!r}; this camera has {list(self.ccd_names)}")

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)`` of a CCD image."""
        c = self.ccd(ccd)
        return int(c.n_lines), int(c.n_samples)

    def replace(self, **changes: Any) -> LineScanCamera:
        """A copy with some attributes replaced (e.g. ``nodes=``, ``interior=``)."""
        return replace(self, **changes)

    # ------------------------------------------------------------ exterior orientation
    @property
    def kernel(self) -> LineScanKernel:
        """The projection kernel of this camera (time model, node windows, ``R0``)."""
        return self._kernel

    def exterior(self, line: ArrayLike) -> tuple[F64, F64]:
        """Exterior orientation at continuous line coordinates.

        Returns:
            ``(S, R)``: perspective centres (m, body-fixed, ``(M, 3)``) and rotations
            camera -> body-fixed (``(M, 3, 3)``).
        """
        line = np.atleast_1d(np.asarray(line, dtype=np.float64))
        eo = self._kernel.exterior(self._poly, line)
        return eo[:, :3], self.frame_rotation @ rotation_matrix(eo[:, 3], eo[:, 4], eo[:, 5])

    def look_rays(
        self, line: ArrayLike, sample: ArrayLike, *, ccd: str | None = None
    ) -> tuple[F64, F64]:
        """Body-fixed rays of image points.

        Returns:
            ``(origin, direction)``: perspective centres (m) and unit look directions,
            each ``(M, 3)``.
        """
        line, sample = np.broadcast_arrays(
            np.atleast_1d(np.asarray(line, np.float64)),
            np.atleast_1d(np.asarray(sample, np.float64)),
        )
        c = self.ccd(ccd)
        x, y = c.focal_plane(sample)
        io = self.interior
        v_cam = np.stack(
            [x - io.x0_mm, y - io.y0_mm, np.full_like(x, -io.focal_length_mm)], axis=-1
        )
        origin, rot = self.exterior(line)
        d = np.einsum("mij,mj->mi", rot, v_cam)
        return origin, d / np.linalg.norm(d, axis=-1, keepdims=True)

    # ------------------------------------------------------------ image -> ground
    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> F64:
        """Intersect the rays of image points with a height, ellipsoid or DEM.

        Args:
            line: Line coordinates (first pixel centre at 0.5), ``(M,)`` or scalar.
            sample: Sample coordinates, same shape.
            terrain: Height in metres above the ellipsoid, or any :class:`Terrain`.
            ccd: CCD name (default: the first CCD).
            on_miss: ``"raise"`` a :class:`GeometryError` naming the first ray that
                misses, or ``"nan"`` to return NaN rows for them.

        Returns:
            Body-fixed XYZ in metres, shape ``(M, 3)``.
        """
        origin, direction = self.look_rays(line, sample, ccd=ccd)
        if isinstance(terrain, int | float | np.floating | np.integer):
            terrain = ConstantHeight(self.ellipsoid, float(terrain))
        if isinstance(terrain, ConstantHeight):
            s = ray_ellipsoid_intersection(origin, direction, terrain.ellipsoid, terrain.height_m)
            xyz = origin + s[:, None] * direction
            miss = ~np.isfinite(s)
            if np.any(miss) and on_miss == "raise":
                i = int(np.flatnonzero(miss)[0])
                raise GeometryError(
                    f"the ray of image point (line {np.atleast_1d(line)[i % np.size(line)]}, "
                    f"sample {np.atleast_1d(sample)[i % np.size(sample)]}) misses the surface "
                    f"at height {terrain.height_m} m"
                )
            return xyz
        from planetref.geometry.terrain import intersect_terrain

        return intersect_terrain(origin, direction, terrain, on_miss=on_miss)

    # ------------------------------------------------------------ ground -> image
    def _lines(self, p: F64, c: CcdGeometry, line_guess: ArrayLike | None) -> F64:
        """Starting lines: the guesses, or a bracketed search in chunks of 65536."""
        m = len(p)
        if line_guess is not None:
            return np.array(np.broadcast_to(np.asarray(line_guess, np.float64), (m,)))
        io = self.interior.as_array()
        line = np.full(m, np.nan)
        chunk = 65536
        for a in range(0, m, chunk):
            b = min(a + chunk, m)
            line[a:b] = self._kernel.search_lines(self._poly, io, c, p[a:b])
        return line

    def ground_to_image(
        self, xyz: ArrayLike, *, ccd: str | None = None, line_guess: ArrayLike | None = None
    ) -> ImagePoints:
        """Project body-fixed points into a CCD image.

        The line is found by solving ``offset(line) = 0`` (the point lies in the plane
        of the CCD's line of sight at that line's time; see
        :mod:`planetref.camera.linescan.kernel`): a bracketed, safeguarded Newton
        search over the node span, vectorised over points, then chord steps to
        ``1e-6`` line and a final Newton step (exact to ~1e-10 line). Outside the
        image the solution is still computed where it exists within the orientation
        nodes' span (extrapolating the EO up to one node spacing beyond the first and
        last node); ``in_image`` tells. Points behind the camera or whose line cannot
        be found come back with ``valid=False`` and NaN coordinates.

        Args:
            xyz: Body-fixed points in metres, shape ``(M, 3)`` or ``(3,)``.
            ccd: CCD name (default: the first CCD).
            line_guess: Optional starting lines (e.g. the observed lines in an
                adjustment), which skip the bracketing search.

        Returns:
            :class:`ImagePoints` (line, sample, valid, in_image).
        """
        p = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if p.shape[-1] != 3:
            raise InputError(f"xyz must have shape (M, 3), got {np.shape(xyz)}")
        c = self.ccd(ccd)
        start = self._lines(p, c, line_guess)
        line, sample, ok, _ = self._kernel.project(
            self._poly, self.interior.as_array(), c, p, start.copy(), None
        )
        ok &= np.isfinite(start)
        line[~ok] = np.nan
        sample[~ok] = np.nan
        in_image = ok & (line >= 0) & (line < c.n_lines) & (sample >= 0) & (sample < c.n_samples)
        return ImagePoints(line=line, sample=sample, valid=ok, in_image=in_image)

    # ------------------------------------------------------------ partials
    def image_partials(
        self, xyz: ArrayLike, *, ccd: str | None = None, line_guess: ArrayLike | None = None
    ) -> ImagePartials:
        """Exact partial derivatives of the projected ``(line, sample)`` of ground points.

        The projection is the implicit solution ``offset(line; theta, P) = 0`` of
        :meth:`ground_to_image`; by the implicit-function theorem
        ``dline/dq = -(d offset/dq) / (d offset/dline)`` and
        ``dsample/dq = d sample/dq + (d sample/dline) dline/dq`` for every parameter
        ``q`` (node EO, interior orientation, ground coordinates, CCD placement), as
        computed by the one projection kernel (:mod:`planetref.camera.linescan.kernel`).

        Args:
            xyz: Ground points in metres, ``(M, 3)``.
            ccd: CCD name.
            line_guess: Optional starting lines for the projection.

        Returns:
            :class:`ImagePartials`. Rows for points that cannot be projected are NaN.
        """
        p = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        c = self.ccd(ccd)
        start = self._lines(p, c, line_guess)
        kern = self._kernel
        proj = kern.project_with_partials(
            self._poly, self.interior.as_array(), c, p, start.copy(), None
        )
        ok = proj.valid & np.isfinite(start)
        cols = RAW_COLUMNS
        d_nodes = kern.node_partials(proj)
        out = (
            d_nodes,
            proj.partials[:, :, cols["interior"]],
            proj.partials[:, :, cols["ground"]],
            proj.partials[:, :, cols["ccd"]],
        )
        line, sample = proj.line, proj.sample
        bad = ~ok
        line[bad] = np.nan
        sample[bad] = np.nan
        for arr in out:
            arr[bad] = np.nan
        return ImagePartials(line, sample, kern.windows.window_nodes(proj.start), *out)

    # ------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        """The native JSON document of this camera (see :func:`LineScanCamera.from_dict`)."""
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": self.name,
            "body": {
                "name": self.ellipsoid.name,
                "semi_major_m": self.ellipsoid.semi_major_m,
                "semi_minor_m": self.ellipsoid.semi_minor_m,
                "latitude": self.latitude_kind,
            },
            "frame_rotation": self.frame_rotation.tolist(),
            "line_rates": [list(r) for r in self.line_rates.rows],
            "orientation": {
                "interpolation_order": self.interpolation_order,
                "node_lines": self.node_lines.tolist(),
                "nodes": self.nodes.tolist(),
            },
            "interior": {
                "focal_length_mm": self.interior.focal_length_mm,
                "x0_mm": self.interior.x0_mm,
                "y0_mm": self.interior.y0_mm,
            },
            "ccds": [
                {
                    "name": c.name,
                    "n_lines": int(c.n_lines),
                    "n_samples": int(c.n_samples),
                    "pixel_pitch_mm": c.pixel_pitch_mm,
                    "x_mm": c.x_mm,
                    "y_mm": c.y_mm,
                    "angle_rad": c.angle_rad,
                    **({"distortion": list(c.distortion)} if any(c.distortion) else {}),
                }
                for c in self.ccds
            ],
        }

    @classmethod
    def from_dict(cls, doc: Any, *, path: str | os.PathLike[str] | None = None) -> LineScanCamera:
        """Build a camera from a native JSON document (validated; see docs/camera-format.md).

        Raises:
            InputError: Naming ``path`` and the offending field.
        """
        from planetref.camera.linescan.schema import parse_document

        return parse_document(doc, path=path, factory=cls)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> LineScanCamera:
        """Read a native JSON camera file."""
        from planetref.camera.linescan.schema import load_json

        return cls.from_dict(load_json(path), path=path)

    def to_json(self, path: str | os.PathLike[str]) -> Path:
        """Write the native JSON camera file atomically (temporary file, then rename)."""
        return write_json_atomic(path, self.to_dict())
