"""What an adjustment works on: cameras, ground points and image observations.

A :class:`Network` holds

* the cameras (each a strip or an image, identified by a string id; a camera may have
  several CCDs),
* the ground points, each with a priori body-fixed XYZ (metres) and a per-axis sigma
  that says how the point enters: ``0`` = fixed (an MCP taken as known), finite > 0 =
  weighted (an MCP weighted by the reference resolution, or a constrained tie point),
  ``inf`` = free (a tie point whose coordinates are unknowns),
* the observations: one image measure ``(line, sample)`` of one point in one CCD of one
  camera, in planetref's pixel convention (first pixel centre at ``(0.5, 0.5)``), with a
  sigma in pixels. Observations flagged ``check`` are held out: they do not enter the
  adjustment and are only evaluated (check MCPs).

Free points with NaN coordinates are triangulated from their observations before the
adjustment starts.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from os import PathLike
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.camera.base import Camera
from planetref.control.records import NetworkRecords, check_in_images, point_value
from planetref.errors import InputError

__all__ = [
    "Network",
    "PointFrames",
    "PointKind",
    "PointMatrices",
    "enu_rotation",
    "small_unique",
    "tile_codes",
]

PointKind = str  # "mcp", "tie" or "overlap" (a CCD-overlap tie; see adjust.api)


def _as_float(a: ArrayLike, shape: tuple[int, ...], name: str) -> F64:
    try:
        arr = np.array(np.broadcast_to(np.asarray(a, dtype=np.float64), shape))
    except ValueError:
        raise InputError(
            f"expected shape {shape} (or broadcastable), got {np.shape(a)}", field=name
        ) from None
    return arr


@dataclass(frozen=True, eq=False)
class Network:
    """Cameras, ground points and observations (see the module doc).

    Attributes:
        cameras: The cameras, ``len == len(camera_ids)``.
        camera_ids: Unique camera (strip/image) ids.
        point_ids: Unique point ids, ``(P,)``.
        point_xyz: A priori body-fixed XYZ in metres, ``(P, 3)``; NaN allowed for free
            points (triangulated).
        point_sigma_m: Per-axis a-priori sigma (metres), ``(P, 3)``: 0 fixed, inf free.
        point_kind: ``"mcp"``, ``"tie"`` or ``"overlap"`` per point, ``(P,)``: how a
            point is reported; tie and overlap points are unknowns under their sigma,
            and overlap ties' observations are judged by the outlier rule apart and
            left out of the reprojection metrics (CCD-overlap ties of one strip).
        obs_camera: Camera index of each observation, ``(M,)``.
        obs_ccd: CCD index (into the camera's ``ccd_names``), ``(M,)``.
        obs_point: Point index, ``(M,)``.
        obs_line: Observed line (pixels, first pixel centre at 0.5), ``(M,)``.
        obs_sample: Observed sample, ``(M,)``.
        obs_sigma_px: Sigma of ``(line, sample)`` in pixels, ``(M, 2)``.
        obs_check: True for held-out check observations, ``(M,)``.
        obs_ids: Observation ids, ``(M,)`` strings.
        point_sigma_local: Per point, ``(P,)``: True when its three sigmas are along the
            local east, north and up (radial) directions at the point instead of the
            body-fixed X, Y, Z axes (MCPs: planimetric sigmas from the ortho, height
            sigma from the DEM).
        obs_tile: Per observation, the index of its matching tile (the block of measures
            that one matcher run on one image window produced, and that shares the
            matcher's error there: its sub-pixel phase, its homography), ``-1`` for
            none (tie points; networks read from files without a ``tile_id``),
            ``(M,)``. The adjustment's covariance takes a per-tile offset in as a
            consider parameter (:class:`~planetref.adjust.config.SystematicConfig`).
    """

    cameras: tuple[Camera, ...]
    camera_ids: tuple[str, ...]
    point_ids: NDArray[np.str_]
    point_xyz: F64
    point_sigma_m: F64
    point_kind: NDArray[np.str_]
    obs_camera: NDArray[np.intp]
    obs_ccd: NDArray[np.intp]
    obs_point: NDArray[np.intp]
    obs_line: F64
    obs_sample: F64
    obs_sigma_px: F64
    obs_check: NDArray[np.bool_]
    obs_ids: NDArray[np.str_]
    point_sigma_local: NDArray[np.bool_] | bool = False
    obs_tile: NDArray[np.intp] | None = None

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        ids = tuple(str(c) for c in self.camera_ids)
        if not cams:
            raise InputError("a network needs at least one camera", field="cameras")
        if len(ids) != len(cams):
            raise InputError(f"{len(ids)} camera ids for {len(cams)} cameras", field="camera_ids")
        if len(set(ids)) != len(ids):
            raise InputError(f"camera ids must be unique, got {list(ids)}", field="camera_ids")
        n_pts = len(np.atleast_1d(self.point_ids))
        pids = np.asarray(self.point_ids, dtype=str).reshape(n_pts)
        if len(np.unique(pids)) != n_pts:
            raise InputError("point ids must be unique", field="point_ids")
        xyz = _as_float(self.point_xyz, (n_pts, 3), "point_xyz")
        sig = _as_float(self.point_sigma_m, (n_pts, 3), "point_sigma_m")
        bad_sig = np.any(np.isnan(sig) | (sig < 0), axis=1)
        if np.any(bad_sig):
            i = int(np.flatnonzero(bad_sig)[0])
            raise InputError(
                f"point {str(pids[i])!r}: sigmas must be >= 0 (0 fixed, inf free), got "
                f"{sig[i].tolist()}",
                field="point_sigma_m",
            )
        kind = np.asarray(np.broadcast_to(np.asarray(self.point_kind, dtype=str), (n_pts,)))
        bad_xyz = ~np.all(np.isfinite(xyz), axis=1) & ~np.all(np.isinf(sig), axis=1)
        if np.any(bad_xyz):
            i = int(np.flatnonzero(bad_xyz)[0])
            raise InputError(
                f"point {str(pids[i])!r} is fixed or weighted but has no finite a priori XYZ",
                field="point_xyz",
            )
        m = len(np.atleast_1d(self.obs_point))
        oids = (
            np.asarray(self.obs_ids, dtype=str).reshape(m)
            if np.size(self.obs_ids)
            else np.array([str(i) for i in range(m)], dtype=str)
        )

        def first_bad(bad: NDArray[np.bool_], what: Callable[[int], str], field: str) -> None:
            """Name the first observation flagged in ``bad`` (and how many are)."""
            if np.any(bad):
                k = int(np.flatnonzero(bad)[0])
                raise InputError(
                    f"observation {k} (id {str(oids[k])!r}): {what(k)} "
                    f"({int(np.count_nonzero(bad))} of {m} observations)",
                    field=field,
                )

        cam_i = np.asarray(self.obs_camera, dtype=np.intp).reshape(m)
        ccd_i = np.asarray(np.broadcast_to(np.asarray(self.obs_ccd, dtype=np.intp), (m,)))
        pt_i = np.asarray(self.obs_point, dtype=np.intp).reshape(m)
        first_bad(
            (cam_i < 0) | (cam_i >= len(cams)),
            lambda k: f"camera index {cam_i[k]} out of range (0 to {len(cams) - 1})",
            "obs_camera",
        )
        first_bad(
            (pt_i < 0) | (pt_i >= n_pts),
            lambda k: f"point index {pt_i[k]} out of range (0 to {n_pts - 1})",
            "obs_point",
        )
        n_ccd = np.array([len(c.ccd_names) for c in cams])
        first_bad(
            (ccd_i < 0) | (ccd_i >= n_ccd[cam_i]),
            lambda k: (
                f"CCD index {ccd_i[k]} out of range (camera {ids[cam_i[k]]!r} has "
                f"{n_ccd[cam_i[k]]})"
            ),
            "obs_ccd",
        )
        line = _as_float(self.obs_line, (m,), "obs_line")
        sample = _as_float(self.obs_sample, (m,), "obs_sample")
        first_bad(
            ~(np.isfinite(line) & np.isfinite(sample)),
            lambda k: f"line and sample must be finite, got {line[k]:g}, {sample[k]:g}",
            "obs_line",
        )
        sig_px = np.array(np.asarray(self.obs_sigma_px, dtype=np.float64))
        sig_px = _as_float(
            sig_px[..., None] if sig_px.ndim == 1 else sig_px, (m, 2), "obs_sigma_px"
        )
        first_bad(
            ~np.all(np.isfinite(sig_px) & (sig_px > 0), axis=1),
            lambda k: f"sigmas must be finite and > 0 pixels, got {sig_px[k].tolist()}",
            "obs_sigma_px",
        )
        check = np.asarray(np.broadcast_to(np.asarray(self.obs_check, dtype=bool), (m,)))
        local = np.array(np.broadcast_to(np.asarray(self.point_sigma_local, bool), (n_pts,)))
        tile = (
            np.full(m, -1, np.intp)
            if self.obs_tile is None
            else np.array(np.broadcast_to(np.asarray(self.obs_tile, np.intp), (m,)))
        )
        first_bad(tile < -1, lambda k: f"tile index {tile[k]} < -1", "obs_tile")
        for name, value in (
            ("point_sigma_local", local),
            ("cameras", cams),
            ("camera_ids", ids),
            ("point_ids", pids),
            ("point_xyz", xyz),
            ("point_sigma_m", sig),
            ("point_kind", kind),
            ("obs_camera", cam_i),
            ("obs_ccd", ccd_i),
            ("obs_point", pt_i),
            ("obs_line", line),
            ("obs_sample", sample),
            ("obs_sigma_px", sig_px),
            ("obs_check", check),
            ("obs_ids", oids),
            ("obs_tile", tile),
        ):
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ helpers
    @property
    def n_obs(self) -> int:
        """Number of observations (including check observations)."""
        return len(self.obs_point)

    @property
    def n_points(self) -> int:
        """Number of ground points."""
        return len(self.point_ids)

    def ccd_name(self, obs: int) -> str:
        """CCD name of an observation."""
        return self.cameras[self.obs_camera[obs]].ccd_names[self.obs_ccd[obs]]

    def image_labels(self) -> NDArray[np.str_]:
        """``"camera_id"`` (single-CCD cameras) or ``"camera_id/ccd"`` per observation."""
        labels = []
        for ci, cam in enumerate(self.cameras):
            names = cam.ccd_names
            labels.append(
                [
                    self.camera_ids[ci] if len(names) == 1 else f"{self.camera_ids[ci]}/{n}"
                    for n in names
                ]
            )
        return np.array(
            [labels[c][k] for c, k in zip(self.obs_camera, self.obs_ccd, strict=True)], dtype=str
        )

    @cached_property
    def point_kind_codes(self) -> tuple[NDArray[np.str_], NDArray[np.intp]]:
        """``(kinds, code)``: the sorted distinct point kinds and each point's index in them.

        The same as ``np.unique(point_kind, return_inverse=True)``, computed once and by
        comparisons (a handful of kinds) instead of a sort of every string.
        """
        kinds, code = small_unique(self.point_kind)
        return kinds, code

    def is_kind(self, kind: str) -> NDArray[np.bool_]:
        """Per point, whether it is of ``kind`` (``"mcp"``, ``"tie"``, ``"overlap"``)."""
        kinds, code = self.point_kind_codes
        hit = np.flatnonzero(kinds == kind)
        return code == hit[0] if hit.size else np.zeros(self.n_points, bool)

    def point_frame_matrices(self, points: NDArray[np.intp] | None = None) -> F64:
        """Rotations from body-fixed XYZ to each point's sigma frame, ``(P, 3, 3)``.

        Identity for points with XYZ sigmas; rows east, north, up (radial) for points
        with local sigmas (up is the geocentric radial direction; it differs from the
        ellipsoid normal by a fraction of a degree, nothing for a sigma).

        Args:
            points: Only these points (indices), ``(n, 3, 3)``; ``None``: every point.
        """
        idx = np.arange(self.n_points) if points is None else np.asarray(points, np.intp)
        out = np.broadcast_to(np.eye(3), (len(idx), 3, 3)).copy()
        xyz = self.point_xyz[idx]
        # An array once constructed (__post_init__); asarray narrows the field's type.
        local = np.asarray(self.point_sigma_local)
        loc = np.flatnonzero(local[idx] & np.all(np.isfinite(xyz), axis=1))
        if loc.size:
            out[loc] = enu_rotation(xyz[loc])
        return out

    def replace_points(self, point_xyz: F64) -> Network:
        """A copy with other a priori point coordinates."""
        return replace(self, point_xyz=point_xyz)

    def _fields(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_records(
        cls,
        cameras: Mapping[str, Camera],
        *,
        obs_camera: Sequence[str],
        obs_point: Sequence[str],
        line: ArrayLike,
        sample: ArrayLike,
        point_xyz: Mapping[str, ArrayLike],
        point_sigma_m: ArrayLike | Mapping[str, ArrayLike] = np.inf,
        point_kind: str | Mapping[str, str] = "tie",
        obs_ccd: Sequence[str | None] | None = None,
        sigma_px: ArrayLike = 1.0,
        check: ArrayLike = False,
        obs_ids: Sequence[str] | None = None,
        point_sigma_local: bool | Mapping[str, bool] = False,
        source: str | PathLike[str] | None = None,
        tile: Sequence[str | None] | None = None,
    ) -> Network:
        """Build a network from string ids (e.g. rows of a measures table).

        Every record is checked before the network is built: lengths, camera, point and
        CCD names, each point's XYZ, sigmas and kind, finite measures and sigmas, and each
        measure inside its image (at most 1 px outside its edges, as for network files);
        the first bad record is named in a one-line :class:`InputError` (with ``source``,
        when given, as the file).

        Args:
            cameras: Camera id -> camera.
            obs_camera: Camera id of each observation.
            obs_point: Point id of each observation.
            line: Observed lines (planetref convention).
            sample: Observed samples.
            point_xyz: Point id -> a priori XYZ (metres; NaN for unknown free points).
            point_sigma_m: A scalar/3-vector for all points, or point id -> sigma(s).
            point_kind: ``"mcp"``/``"tie"`` for all points, or point id -> kind.
            obs_ccd: CCD name per observation (``None``: the camera's first CCD).
            sigma_px: Sigma of each observation (pixels), scalar, ``(M,)`` or ``(M, 2)``.
            check: Held-out check flags.
            obs_ids: Observation ids (default: row numbers).
            point_sigma_local: Sigmas along east, north, up (see the class doc), for all
                points or point id -> flag.
            source: The file the records come from (named in errors).
            tile: Matching tile id per observation (``None`` or empty: none); ids are
                taken per camera (the same id in two strips is two tiles).

        Raises:
            InputError: A bad record (see above), naming ``source`` and the record.
        """
        try:
            records = NetworkRecords(
                obs_camera=obs_camera,
                obs_point=obs_point,
                line=line,
                sample=sample,
                point_xyz=point_xyz,
                point_sigma_m=point_sigma_m,
                point_kind=point_kind,
                obs_ccd=obs_ccd,
                sigma_px=sigma_px,
                check=check,
                obs_ids=obs_ids,
                point_sigma_local=point_sigma_local,
                tile=tile,
            )
            return cls._from_records(cameras, records)
        except InputError as exc:
            if source is None or exc.path is not None:
                raise
            raise InputError(str(exc), path=source) from None

    @classmethod
    def _from_records(cls, cameras: Mapping[str, Camera], rec: NetworkRecords) -> Network:
        """:meth:`from_records` on its records (without the ``source`` of its errors)."""
        m = len(rec.obs_point)
        for name, seq in (
            ("obs_camera", rec.obs_camera),
            ("obs_ccd", rec.obs_ccd),
            ("obs_ids", rec.obs_ids),
            ("tile", rec.tile),
        ):
            if seq is not None and len(seq) != m:
                raise InputError(f"{len(seq)} entries for {m} observations (obs_point)", field=name)
        cam_ids = list(cameras)
        cam_index = {c: i for i, c in enumerate(cam_ids)}
        pids = list(rec.point_xyz)
        p_index = {p: i for i, p in enumerate(pids)}
        ci = np.empty(m, np.intp)
        pi = np.empty(m, np.intp)
        ki = np.zeros(m, np.intp)
        for k in range(m):
            c = rec.obs_camera[k]
            if c not in cam_index:
                raise InputError(
                    f"observation {k}: unknown camera {c!r}; known: {cam_ids}", field="obs_camera"
                )
            ci[k] = cam_index[c]
            p = rec.obs_point[k]
            if p not in p_index:
                raise InputError(f"observation {k}: unknown point {p!r}", field="obs_point")
            pi[k] = p_index[p]
            if rec.obs_ccd is not None and rec.obs_ccd[k] is not None:
                names = cameras[c].ccd_names
                if rec.obs_ccd[k] not in names:
                    raise InputError(
                        f"observation {k}: camera {c!r} has no CCD "
                        f"{rec.obs_ccd[k]!r} (it has {list(names)})",
                        field="ccd",
                    )
                ki[k] = names.index(rec.obs_ccd[k])
        _refuse_duplicate_measures(ci, ki, pi, cam_ids, pids, rec.obs_ids)
        xyz = np.array([point_value(rec.point_xyz, p, "point_xyz", exact=True) for p in pids])
        xyz = xyz.reshape(-1, 3)
        if isinstance(rec.point_sigma_m, Mapping):
            sig = np.array(
                [point_value(rec.point_sigma_m, p, "point_sigma_m") for p in pids]
            ).reshape(-1, 3)
        else:
            sig = np.broadcast_to(np.asarray(rec.point_sigma_m, np.float64), (len(pids), 3))
        if isinstance(rec.point_sigma_local, Mapping):
            local = np.array([bool(rec.point_sigma_local.get(p, False)) for p in pids], dtype=bool)
        else:
            local = np.full(len(pids), bool(rec.point_sigma_local))
        if isinstance(rec.point_kind, Mapping):
            missing = [p for p in pids if p not in rec.point_kind]
            if missing:
                raise InputError(f"no kind for point {missing[0]!r}", field="point_kind")
            kind = np.array([rec.point_kind[p] for p in pids], dtype=str)
        else:
            kind = np.array([rec.point_kind] * len(pids), dtype=str)
        line_a = _as_float(rec.line, (m,), "line")
        sample_a = _as_float(rec.sample, (m,), "sample")
        check_in_images(cameras, cam_ids, ci, ki, line_a, sample_a, rec.obs_ids)
        return cls(
            cameras=tuple(cameras.values()),
            camera_ids=tuple(cam_ids),
            point_ids=np.array(pids, dtype=str),
            point_xyz=xyz,
            point_sigma_m=sig,
            point_kind=kind,
            obs_camera=ci,
            obs_ccd=ki,
            obs_point=pi,
            obs_line=line_a,
            obs_sample=sample_a,
            obs_sigma_px=np.asarray(rec.sigma_px, np.float64),
            obs_check=np.asarray(rec.check, bool),
            obs_ids=np.array(
                rec.obs_ids if rec.obs_ids is not None else [str(i) for i in range(m)], dtype=str
            ),
            point_sigma_local=local,
            obs_tile=None if rec.tile is None else tile_codes(rec.obs_camera, rec.tile),
        )

    @classmethod
    def mcps(
        cls,
        camera: Camera,
        *,
        line: ArrayLike,
        sample: ArrayLike,
        xyz: ArrayLike,
        ccd: ArrayLike | str | None = None,
        camera_id: str = "strip",
        ground_sigma_m: ArrayLike = 0.0,
        sigma_px: ArrayLike = 1.0,
        check: ArrayLike = False,
        ground_sigma_local: bool = False,
        tile: ArrayLike | None = None,
    ) -> Network:
        """A network of matched control points of one camera (one point per observation).

        Args:
            camera: The camera (strip).
            line: Observed lines, ``(M,)``.
            sample: Observed samples, ``(M,)``.
            xyz: Reference ground points (metres), ``(M, 3)``.
            ccd: CCD name(s) of the observations (a name, ``(M,)`` names, or ``None`` for
                the first CCD).
            camera_id: Id of the camera.
            ground_sigma_m: 0 (known ground, default), or a sigma in metres: one for all,
                ``(M,)`` per point, or ``(M, 3)`` per point and axis.
            ground_sigma_local: The ``(M, 3)`` sigmas are along east, north, up (e.g.
                ``(sigma_ground_xy_m, sigma_ground_xy_m, sigma_ground_h_m)`` of the MCP
                table) instead of X, Y, Z.
            sigma_px: Sigma of each measure (pixels).
            check: Held-out check flags.
            tile: Matching tile id per observation (:attr:`obs_tile`), or ``None``.
        """
        line = np.atleast_1d(np.asarray(line, np.float64))
        m = len(line)
        names = camera.ccd_names
        if ccd is None:
            ki = np.zeros(m, np.intp)
        else:
            arr = np.broadcast_to(np.asarray(ccd, dtype=str), (m,))
            lookup = {n: i for i, n in enumerate(names)}
            unknown = sorted(set(np.unique(arr)) - set(lookup))
            if unknown:
                raise InputError(
                    f"unknown CCD(s) {unknown}; the camera has {list(names)}", field="ccd"
                )
            ki = np.array([lookup[n] for n in arr], dtype=np.intp)
        gs = np.asarray(ground_sigma_m, np.float64)
        if gs.ndim == 1:  # one sigma per point, the same on every axis
            gs = gs[:, None]
        return cls(
            cameras=(camera,),
            camera_ids=(camera_id,),
            point_ids=np.array([f"mcp{i}" for i in range(m)], dtype=str),
            point_xyz=np.asarray(xyz, np.float64).reshape(m, 3),
            point_sigma_m=_as_float(gs, (m, 3), "ground_sigma_m"),
            point_kind=np.array(["mcp"] * m, dtype=str),
            obs_camera=np.zeros(m, np.intp),
            obs_ccd=ki,
            obs_point=np.arange(m),
            obs_line=line,
            obs_sample=np.asarray(sample, np.float64),
            obs_sigma_px=np.asarray(sigma_px, np.float64),
            obs_check=np.asarray(check, bool),
            obs_ids=np.array([str(i) for i in range(m)], dtype=str),
            point_sigma_local=bool(ground_sigma_local),
            obs_tile=None
            if tile is None
            else tile_codes([camera_id] * m, np.broadcast_to(np.asarray(tile, str), (m,))),
        )


def tile_codes(camera: Sequence[str], tile: Sequence[str | None] | ArrayLike) -> NDArray[np.intp]:
    """:attr:`Network.obs_tile` of per-observation camera and tile ids.

    Args:
        camera: Camera id per observation.
        tile: Tile id per observation; ``None`` or ``""``: none (``-1``).

    Returns:
        One index per distinct ``(camera, tile)`` pair, in order of first appearance.
    """
    keys = [
        None if t is None or str(t) == "" else (str(c), str(t))
        for c, t in zip(camera, np.asarray(tile, dtype=object).ravel(), strict=True)
    ]
    index: dict[tuple[str, str], int] = {}
    out = np.full(len(keys), -1, np.intp)
    for k, key in enumerate(keys):
        if key is not None:
            out[k] = index.setdefault(key, len(index))
    return out


def small_unique(values: ArrayLike, limit: int = 16) -> tuple[NDArray[Any], NDArray[np.intp]]:
    """``np.unique(values, return_inverse=True)`` for arrays of a few distinct values.

    One comparison pass per distinct value (strings are never sorted); falls back to
    ``np.unique`` beyond ``limit`` distinct values.
    """
    v = np.asarray(values).ravel()
    code = np.empty(len(v), np.intp)
    found: list[Any] = []  # scalars of v's dtype
    rest = np.arange(len(v))
    while rest.size:
        if len(found) == limit:
            u, inv = np.unique(v, return_inverse=True)
            return u, inv.ravel().astype(np.intp)
        x = v[rest[0]]
        same = v[rest] == x
        code[rest[same]] = len(found)
        found.append(x)
        rest = rest[~same]
    uniq = np.array(found, dtype=v.dtype)
    order = np.argsort(uniq, kind="stable")
    rank = np.empty(len(order), np.intp)
    rank[order] = np.arange(len(order))
    return uniq[order], rank[code]


def enu_rotation(xyz: F64) -> F64:
    """Rows east, north, up (geocentric radial) at body-fixed points, ``(n, 3, 3)``.

    Args:
        xyz: Body-fixed points (metres), ``(n, 3)``, not at the body's centre.

    Returns:
        Rotation matrices ``R`` with ``R @ d`` the east, north, up components of ``d``.
    """
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    up = p / np.linalg.norm(p, axis=1, keepdims=True)
    east = np.cross(np.array([0.0, 0.0, 1.0]), up)
    norm = np.linalg.norm(east, axis=1, keepdims=True)
    # At a pole east is undefined: any horizontal direction will do.
    east = np.where(norm > 1e-12, east / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0])
    north = np.cross(up, east)
    return np.stack([east, north, up], axis=1)


class PointMatrices:
    """Per-point arrays (``3 x 3`` matrices, or rows) held for a few points, zero for all others.

    Indexing with point indices gives ``(n, *item)`` like the dense ``(P, *item)`` array
    it stands for, without that array: a network of a million fixed MCPs has no weighted
    point, and its set-up should not write tens of MB of zeros.

    Args:
        n_points: ``P``.
        points: The points that have a value (distinct indices).
        matrices: Their values, ``(len(points), *item)`` (e.g. ``(k, 3, 3)``).
        index: The position map of another :class:`PointMatrices` over the same
            ``points`` (shared instead of built again), or ``None``.
    """

    def __init__(
        self,
        n_points: int,
        points: NDArray[np.intp],
        matrices: F64,
        *,
        index: NDArray[np.intp] | None = None,
    ) -> None:
        if index is None:
            index = np.full(n_points, -1, np.intp)
            index[points] = np.arange(len(points))
        self._pos = index
        self._m = np.asarray(matrices, np.float64)
        self.shape = (n_points, *self._m.shape[1:])

    @property
    def index(self) -> NDArray[np.intp]:
        """Position of each point's value in the held values (-1: none), ``(P,)``."""
        return self._pos

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, points: NDArray[np.intp]) -> F64:
        pos = self._pos[points]
        out = np.zeros((*np.shape(pos), *self.shape[1:]))
        hit = pos >= 0
        out[hit] = self._m[pos[hit]]
        return out


class PointFrames:
    """The points' sigma frames, computed only for the points asked for.

    Indexed like the ``(P, 3, 3)`` array of :meth:`Network.point_frame_matrices`.

    Args:
        network: The network.
    """

    def __init__(self, network: Network) -> None:
        self._net = network
        self.shape = (network.n_points, 3, 3)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, points: NDArray[np.intp]) -> F64:
        """Frames of the points with these indices, ``(len(points), 3, 3)``."""
        return self._net.point_frame_matrices(np.asarray(points, np.intp))


def _refuse_duplicate_measures(
    ci: NDArray[np.intp],
    ki: NDArray[np.intp],
    pi: NDArray[np.intp],
    cam_ids: list[str],
    pids: list[str],
    obs_ids: Sequence[Any] | None,
) -> None:
    """Refuse a point measured twice in the same image (camera and CCD).

    A duplicated measure row (a file concatenated twice, a copy-paste) would count with
    double weight and shrink the reported precision; it is refused, naming both rows.

    Raises:
        InputError: The first duplicate, with both observations' ids (or indices).
    """
    if ci.size < 2:
        return
    key = np.stack([ci, ki, pi], axis=1)
    _, counts = np.unique(key, axis=0, return_counts=True)
    if np.all(counts == 1):
        return
    order = np.lexsort((np.arange(ci.size), pi, ki, ci))
    sk = key[order]
    same = np.all(sk[1:] == sk[:-1], axis=1)
    j = int(np.flatnonzero(same)[0])
    a, b = sorted((int(order[j]), int(order[j + 1])))

    def name(k: int) -> str:
        return f"{obs_ids[k]!r}" if obs_ids is not None else f"observation {k}"

    n_dup = int(np.sum(counts - 1))
    raise InputError(
        f"{name(a)} and {name(b)} measure point {pids[int(pi[a])]!r} in image "
        f"{cam_ids[int(ci[a])]!r} twice ({n_dup} duplicated measure(s) in all); a duplicate "
        "would count with double weight: remove it",
        field="obs_point",
    )
