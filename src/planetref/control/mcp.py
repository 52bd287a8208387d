"""Matched control points (MCPs): from tile matches to a table, and the table's files.

An MCP ties a raw CCD image position to a point of the reference: CCD id, raw
``(line, sample)`` (first pixel centre at ``(0.5, 0.5)``), reference map coordinates
``(ref_x, ref_y)`` in the reference CRS, planetocentric latitude and east longitude
(degrees), the height bilinearly sampled from the reference DEM (metres above its
body), body-fixed XYZ (metres), the matcher's confidence and the tile id.

:func:`mcps_from_tiles` builds the table from the results of the matching front end and
counts what it drops: points whose DEM height is NaN (holes, outside the DEM), points
outside the reference orthoimage, and duplicates (the same CCD position found twice,
e.g. in overlapping tiles; the most confident copy is kept).

:func:`write_mcps` writes Parquet (``.parquet``) or CSV (``.csv``) plus a GeoPackage point
layer in the reference CRS; :func:`read_mcps` reads any of the three back. Every file is
written to a temporary name in the target folder and renamed into place, so a reader
never sees a half-written file.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.control.ground_sigma import (
    GROUND_SIGMA_H_FLOOR_M,
    GROUND_SIGMA_XY_REF_PX,
    ground_sigmas,
    reference_gsd_m,
)
from planetref.errors import InputError, MissingFileError, UnsupportedFormatError
from planetref.runtime.atomic import atomic_path

__all__ = [
    "GROUND_SIGMA_H_FLOOR_M",
    "GROUND_SIGMA_XY_REF_PX",
    "MCP_COLUMNS",
    "OPTIONAL_COLUMNS",
    "McpCounts",
    "McpTable",
    "ground_sigmas",
    "mcps_from_matches",
    "mcps_from_tiles",
    "read_mcps",
    "reference_gsd_m",
    "write_mcps",
]

MCP_COLUMNS: tuple[str, ...] = (
    "mcp_id",
    "ccd",
    "tile_id",
    "line",
    "sample",
    "ref_x",
    "ref_y",
    "lon_deg",
    "lat_deg",
    "height_m",
    "x_m",
    "y_m",
    "z_m",
    "confidence",
    "matcher",
)
"""Columns of an MCP table, in file order."""

OPTIONAL_COLUMNS: tuple[str, ...] = ("sigma_ground_xy_m", "sigma_ground_h_m", "sigma_image_px")
"""Columns a table may carry after :data:`MCP_COLUMNS`: the a-priori sigmas of the
MCP's ground point (planimetric, metres, per horizontal axis; height, metres; see
:func:`ground_sigmas`) and, if the front end refined the match, its image precision
(pixels)."""

_STR = frozenset({"ccd", "tile_id", "matcher"})
_INT = frozenset({"mcp_id"})
_CRS_KEY = b"planetref:crs_wkt"
_COUNTS_KEY = b"planetref:counts"
GPKG_LAYER = "mcps"


@dataclass
class McpCounts:
    """What happened to the candidate points on their way to MCPs.

    Attributes:
        candidates: Points offered (inliers of ``ok`` tiles).
        nan_dem: Dropped: the reference DEM has no height there (hole or outside it).
        outside_reference: Dropped: outside the reference orthoimage's extent.
        duplicates: Dropped: another point of the same CCD within the duplicate radius
            was more confident.
        kept: MCPs in the table.
        tiles_skipped: Tiles whose status was not ``ok`` (their points are not used).
    """

    candidates: int = 0
    nan_dem: int = 0
    outside_reference: int = 0
    duplicates: int = 0
    kept: int = 0
    tiles_skipped: int = 0

    def to_dict(self) -> dict[str, int]:
        """Plain dict of the counts."""
        return {k: int(v) for k, v in self.__dict__.items()}

    def __add__(self, other: McpCounts) -> McpCounts:
        return McpCounts(**{k: getattr(self, k) + getattr(other, k) for k in self.__dict__})


def _as_column(name: str, values: ArrayLike, n: int | None = None) -> NDArray[Any]:
    if name in _STR:
        arr = np.asarray(values, dtype=object).ravel()
        arr = np.array([str(v) for v in arr], dtype=object)
    elif name in _INT:
        arr = np.asarray(values, dtype=np.int64).ravel()
    else:
        arr = np.asarray(values, dtype=np.float64).ravel()
    if n is not None and arr.size == 1 and n != 1:
        arr = np.repeat(arr, n)
    return arr


@dataclass
class McpTable:
    """A column table of MCPs (see :data:`MCP_COLUMNS`).

    Attributes:
        columns: Column name -> 1-D array (object arrays of ``str`` for ``ccd``,
            ``tile_id``, ``matcher``; int64 ``mcp_id``; float64 otherwise).
        crs_wkt: WKT of the reference CRS of ``ref_x``/``ref_y`` (None if unknown, e.g. a
            CSV read back on its own).
        counts: The drop counts of the conversion that built the table, if known.
    """

    columns: dict[str, NDArray[Any]]
    crs_wkt: str | None = None
    counts: McpCounts | None = field(default=None)

    def __post_init__(self) -> None:
        missing = [c for c in MCP_COLUMNS if c not in self.columns]
        if missing:
            raise InputError(f"MCP table lacks columns {missing}")
        extra = sorted(set(self.columns) - set(MCP_COLUMNS) - set(OPTIONAL_COLUMNS))
        if extra:
            raise InputError(f"unknown MCP table columns {extra}")
        n = len(np.asarray(self.columns["mcp_id"]).ravel())
        names = [*MCP_COLUMNS, *(c for c in OPTIONAL_COLUMNS if c in self.columns)]
        cols = {c: _as_column(c, self.columns[c], n) for c in names}
        lengths = {c: len(v) for c, v in cols.items()}
        if len(set(lengths.values())) != 1:
            raise InputError(f"MCP table columns differ in length: {lengths}")
        self.columns = cols

    @classmethod
    def empty(cls, crs_wkt: str | None = None) -> McpTable:
        """A table without rows."""
        return cls({c: np.empty(0) for c in MCP_COLUMNS}, crs_wkt)

    def __len__(self) -> int:
        return len(self.columns["mcp_id"])

    def __getitem__(self, name: str) -> NDArray[Any]:
        return self.columns[name]

    def __repr__(self) -> str:
        return f"McpTable(n={len(self)})"

    def select(self, selection: ArrayLike) -> McpTable:
        """Rows picked by a boolean mask or an index array (counts are not carried)."""
        sel = np.asarray(selection)
        return McpTable({c: v[sel] for c, v in self.columns.items()}, self.crs_wkt)

    @classmethod
    def concatenate(cls, tables: Iterable[McpTable]) -> McpTable:
        """Stack tables (renumbering ``mcp_id`` from 0); the first CRS wins."""
        tables = list(tables)
        if not tables:
            return cls.empty()
        names = [
            *MCP_COLUMNS,
            *(c for c in OPTIONAL_COLUMNS if all(c in t.columns for t in tables)),
        ]
        cols = {c: np.concatenate([t.columns[c] for t in tables]) for c in names}
        cols["mcp_id"] = np.arange(len(cols["mcp_id"]), dtype=np.int64)
        counts = None
        if all(t.counts is not None for t in tables):
            counts = McpCounts()
            for t in tables:
                counts = counts + t.counts  # type: ignore[operator]
        return cls(cols, next((t.crs_wkt for t in tables if t.crs_wkt), None), counts)

    def xyz(self) -> NDArray[np.float64]:
        """``(N, 3)`` body-fixed XYZ (m)."""
        return np.column_stack([self.columns["x_m"], self.columns["y_m"], self.columns["z_m"]])

    # -- arrow ------------------------------------------------------------------------
    def to_arrow(self) -> Any:
        """A ``pyarrow.Table`` with the CRS and counts in the schema metadata."""
        import pyarrow as pa

        arrays = []
        names = list(self.columns)
        for c in names:
            v = self.columns[c]
            if c in _STR:
                arrays.append(pa.array([str(x) for x in v], type=pa.string()))
            elif c in _INT:
                arrays.append(pa.array(v, type=pa.int64()))
            else:
                arrays.append(pa.array(v, type=pa.float64()))
        meta = {}
        if self.crs_wkt:
            meta[_CRS_KEY] = self.crs_wkt.encode()
        if self.counts is not None:
            meta[_COUNTS_KEY] = json.dumps(self.counts.to_dict()).encode()
        return pa.Table.from_arrays(arrays, names=names).replace_schema_metadata(meta or None)

    @classmethod
    def from_arrow(cls, table: Any, crs_wkt: str | None = None) -> McpTable:
        """Inverse of :meth:`to_arrow` (missing metadata: ``crs_wkt`` as given)."""
        names = set(table.column_names)
        missing = [c for c in MCP_COLUMNS if c not in names]
        if missing:
            raise InputError(f"MCP file lacks columns {missing}")
        meta = table.schema.metadata or {}
        crs = meta.get(_CRS_KEY)
        counts = meta.get(_COUNTS_KEY)
        cols = {}
        for c in [*MCP_COLUMNS, *(c for c in OPTIONAL_COLUMNS if c in names)]:
            col = table.column(c)
            if c in _STR:
                cols[c] = np.array(
                    ["" if v is None else str(v) for v in col.to_pylist()], dtype=object
                )
            else:
                cols[c] = col.to_numpy(zero_copy_only=False)
        return cls(
            cols,
            crs.decode() if crs else crs_wkt,
            McpCounts(**json.loads(counts)) if counts else None,
        )


# --------------------------------------------------------------------------- building


def _duplicates(
    ccd: NDArray[Any],
    line: NDArray[np.float64],
    sample: NDArray[np.float64],
    conf: NDArray[np.float64],
    radius: float,
) -> NDArray[np.bool_]:
    """True for points to drop: a more confident point of the same CCD is within radius."""
    from scipy.spatial import cKDTree

    drop = np.zeros(len(line), bool)
    if len(line) < 2:
        return drop
    for c in np.unique(ccd):
        idx = np.flatnonzero(ccd == c)
        if len(idx) < 2:
            continue
        pts = np.column_stack([line[idx], sample[idx]])
        pairs = cKDTree(pts).query_pairs(r=max(radius, 0.0), output_type="ndarray")
        if not len(pairs):
            continue
        neighbours: dict[int, list[int]] = {}
        for a, b in pairs.tolist():
            neighbours.setdefault(a, []).append(b)
            neighbours.setdefault(b, []).append(a)
        # Highest confidence first; ties by position in the input, for determinism. Only
        # points with a neighbour can lose.
        crowded = np.fromiter(neighbours, dtype=np.intp)
        order = crowded[np.lexsort((crowded, -conf[idx][crowded]))]
        taken = np.zeros(len(idx), bool)
        for i in order.tolist():
            if taken[i]:
                continue
            for j in neighbours[i]:
                if not taken[j]:
                    taken[j] = True
                    drop[idx[j]] = True
    return drop


def mcps_from_matches(
    *,
    ccd: ArrayLike,
    tile_id: ArrayLike,
    line: ArrayLike,
    sample: ArrayLike,
    ref_x: ArrayLike,
    ref_y: ArrayLike,
    confidence: ArrayLike,
    matcher: str,
    ref: Any,
    dem: Any,
    duplicate_radius_px: float = 1.0,
) -> McpTable:
    """Turn correspondences into MCPs, sampling heights from the reference DEM.

    Args:
        ccd: CCD name per point (or one name for all).
        tile_id: Tile id per point (or one for all).
        line: Raw line per point.
        sample: Raw sample per point.
        ref_x: Reference map x per point (reference CRS units).
        ref_y: Reference map y per point.
        confidence: Matcher confidence per point.
        matcher: Matcher name.
        ref: The :class:`~planetref.raster.ortho.ReferenceOrtho` (CRS and extent).
        dem: The reference DEM (a :class:`~planetref.raster.dem.GridTerrain`, or any
            terrain with ``height(lon, lat)`` and an ``ellipsoid``).
        duplicate_radius_px: Points of the same CCD closer than this (raw pixels) are
            duplicates; the most confident is kept. A negative value disables the check.

    Returns:
        The table, with ``counts`` telling what was dropped.
    """
    from planetref.camera.mapping import map_to_ground

    line_a = np.asarray(line, np.float64).ravel()
    n = len(line_a)
    cols: dict[str, NDArray[Any]] = {
        "ccd": _as_column("ccd", ccd, n),
        "tile_id": _as_column("tile_id", tile_id, n),
        "line": line_a,
        "sample": _as_column("sample", sample, n),
        "ref_x": _as_column("ref_x", ref_x, n),
        "ref_y": _as_column("ref_y", ref_y, n),
        "confidence": _as_column("confidence", confidence, n),
    }
    lengths = {k: len(v) for k, v in cols.items()}
    if len(set(lengths.values())) != 1:
        raise InputError(f"correspondence arrays differ in length: {lengths}")
    counts = McpCounts(candidates=n)
    col, row = ref.map_to_pixel(cols["ref_x"], cols["ref_y"])
    inside = ref.contains_pixel(col, row)
    counts.outside_reference = int((~inside).sum())
    xyz, lon, lat, h = map_to_ground(ref, dem, cols["ref_x"], cols["ref_y"])
    has_h = np.isfinite(h) & inside
    counts.nan_dem = int((inside & ~np.isfinite(h)).sum())
    keep = has_h & np.isfinite(cols["line"]) & np.isfinite(cols["sample"])
    if duplicate_radius_px >= 0:
        dup = np.zeros(n, bool)
        k = np.flatnonzero(keep)
        dup[k] = _duplicates(
            cols["ccd"][k],
            cols["line"][k],
            cols["sample"][k],
            cols["confidence"][k],
            duplicate_radius_px,
        )
        counts.duplicates = int(dup.sum())
        keep &= ~dup
    counts.kept = int(keep.sum())
    out = {k: v[keep] for k, v in cols.items()}
    s_xy, s_h = ground_sigmas(ref, dem, out["ref_x"], out["ref_y"])
    out.update(
        mcp_id=np.arange(counts.kept, dtype=np.int64),
        lon_deg=lon[keep],
        lat_deg=lat[keep],
        height_m=h[keep],
        x_m=xyz[keep, 0],
        y_m=xyz[keep, 1],
        z_m=xyz[keep, 2],
        matcher=np.array([matcher] * counts.kept, dtype=object),
        sigma_ground_xy_m=s_xy,
        sigma_ground_h_m=s_h,
    )
    return McpTable(out, ref.crs.to_wkt(), counts)


def mcps_from_tiles(
    results: Iterable[Any], *, ref: Any, dem: Any, duplicate_radius_px: float = 1.0
) -> McpTable:
    """MCPs from the front end's tile results (only tiles with status ``ok``).

    Args:
        results: :class:`~planetref.frontend.result.TileResult` objects (or a
            :class:`~planetref.frontend.result.StripMatches`' ``tiles``).
        ref: The reference orthoimage.
        dem: The reference DEM.
        duplicate_radius_px: See :func:`mcps_from_matches`.

    Returns:
        The table; ``counts.tiles_skipped`` counts the tiles that were not ``ok``.
    """
    results = list(getattr(results, "tiles", results))
    ok = [r for r in results if r.status == "ok"]
    matchers = sorted({r.matcher for r in ok})
    if len(matchers) > 1:
        raise InputError(
            f"tile results of several matchers {matchers}; build one MCP table per matcher"
        )

    def cat(name: str) -> NDArray[np.float64]:
        return (
            np.concatenate([np.asarray(getattr(r, name), np.float64) for r in ok])
            if ok
            else np.empty(0)
        )

    ccd = np.concatenate([[r.tile.ccd] * r.n_points for r in ok]) if ok else np.empty(0)
    tid = np.concatenate([[r.tile_id] * r.n_points for r in ok]) if ok else np.empty(0)
    table = mcps_from_matches(
        ccd=ccd,
        tile_id=tid,
        line=cat("line"),
        sample=cat("sample"),
        ref_x=cat("ref_x"),
        ref_y=cat("ref_y"),
        confidence=cat("confidence"),
        matcher=matchers[0] if matchers else "",
        ref=ref,
        dem=dem,
        duplicate_radius_px=duplicate_radius_px,
    )
    if table.counts is not None:
        table.counts.tiles_skipped = len(results) - len(ok)
    return table


# --------------------------------------------------------------------------- files


def _write_table(table: McpTable, path: Path) -> None:
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    # pyarrow wants to create the file itself.
    with atomic_path(path, create=False) as tmp:
        if path.suffix.lower() == ".parquet":
            pq.write_table(table.to_arrow(), tmp)
        else:
            pacsv.write_csv(table.to_arrow(), tmp)


def _wkb_points(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[Any]:
    rec = np.zeros(len(x), np.dtype([("order", "u1"), ("type", "<u4"), ("x", "<f8"), ("y", "<f8")]))
    rec["order"], rec["type"], rec["x"], rec["y"] = 1, 1, x, y  # little-endian Point
    return np.array([r.tobytes() for r in rec], dtype=object)


def _write_gpkg(table: McpTable, path: Path) -> None:
    from pyogrio.raw import write

    if not table.crs_wkt:
        raise InputError("a GeoPackage needs the reference CRS; the table has none")
    names = list(table.columns)
    values = [table.columns[c] for c in names]
    with atomic_path(path, create=False) as tmp:  # GDAL creates the GeoPackage itself
        write(
            str(tmp),
            _wkb_points(table["ref_x"], table["ref_y"]),
            values,
            names,
            driver="GPKG",
            layer=GPKG_LAYER,
            geometry_type="Point",
            crs=table.crs_wkt,
        )


def write_mcps(
    table: McpTable, path: str | PathLike[str], *, gpkg: bool | str | PathLike[str] = True
) -> list[Path]:
    """Write an MCP table as Parquet or CSV, plus a GeoPackage point layer.

    Args:
        table: The MCPs.
        path: ``.parquet`` or ``.csv`` file (or ``.gpkg`` to write only the GeoPackage).
        gpkg: Also write a GeoPackage (layer ``mcps``, points at ``(ref_x, ref_y)`` in the
            reference CRS): True puts it next to ``path`` with suffix ``.gpkg``; a path
            names it; False skips it.

    Returns:
        The files written.

    Raises:
        UnsupportedFormatError: Another suffix.
        InputError: A GeoPackage for a table without CRS.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".parquet", ".csv", ".gpkg"):
        raise UnsupportedFormatError("MCP files must end in .parquet, .csv or .gpkg", path=p)
    p.parent.mkdir(parents=True, exist_ok=True)
    written = []
    if suffix == ".gpkg":
        _write_gpkg(table, p)
        return [p]
    _write_table(table, p)
    written.append(p)
    if gpkg is not False:
        g = p.with_suffix(".gpkg") if gpkg is True else Path(gpkg)
        _write_gpkg(table, g)
        written.append(g)
    return written


def read_mcps(path: str | PathLike[str], *, crs: object = None) -> McpTable:
    """Read MCPs from Parquet, CSV or a GeoPackage written by :func:`write_mcps`.

    Args:
        path: The file.
        crs: CRS to attach when the file carries none (CSV).

    Raises:
        MissingFileError: No such file.
        UnsupportedFormatError: Another suffix, or an unreadable file.
        InputError: Missing columns.
    """
    p = Path(path)
    if not p.exists():
        raise MissingFileError("MCP file not found", path=p)
    suffix = p.suffix.lower()
    crs_wkt = None
    if crs is not None:
        from pyproj import CRS

        crs_wkt = CRS.from_user_input(crs).to_wkt()
    try:
        if suffix == ".parquet":
            import pyarrow.parquet as pq

            return McpTable.from_arrow(pq.read_table(p), crs_wkt)
        if suffix == ".csv":
            import pyarrow as pa
            import pyarrow.csv as pacsv

            types = {
                c: (pa.string() if c in _STR else pa.int64() if c in _INT else pa.float64())
                for c in (*MCP_COLUMNS, *OPTIONAL_COLUMNS)
            }
            opts = pacsv.ConvertOptions(column_types=types, strings_can_be_null=False)
            return McpTable.from_arrow(pacsv.read_csv(p, convert_options=opts), crs_wkt)
        if suffix == ".gpkg":
            from pyogrio.raw import read

            meta, _, _, fields = read(str(p), layer=GPKG_LAYER)
            cols: Mapping[str, Any] = dict(zip(meta["fields"], fields, strict=True))
            missing = [c for c in MCP_COLUMNS if c not in cols]
            if missing:
                raise InputError(f"MCP layer lacks columns {missing}", path=p)
            keep = [*MCP_COLUMNS, *(c for c in OPTIONAL_COLUMNS if c in cols)]
            return McpTable({c: cols[c] for c in keep}, meta.get("crs") or crs_wkt)
    except (OSError, ValueError, RuntimeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise UnsupportedFormatError(f"cannot read MCPs ({exc})", path=p) from None
    raise UnsupportedFormatError("MCP files must end in .parquet, .csv or .gpkg", path=p)
