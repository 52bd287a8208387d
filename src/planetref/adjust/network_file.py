"""Read a control network: ``NETWORK.toml`` and its measures CSV.

``NETWORK.toml``::

    measures = "measures.csv"          # relative to the TOML file
    convention = "isis"                # or "csm" (planetref's): pixel convention of the
                                       # measures; isis = 1-based, first centre at 1.0
    [images]                           # image_id -> camera file (relative paths)
    "MRO/CTX/0884541979:200" = "P15_006844_2009_XN_20N286W.lev1.json"
    "strip7/ccd2" = { camera = "strip7.json", ccd = "ccd2" }   # one CCD of a strip
    [adjustment]                       # optional: an AdjustConfig table (docs/adjust.md)
    csm.pointing_offset = { mode = "weighted", sigma_rad = "1 mrad" }

Measures CSV, one row per image measure, header required; columns (order free)::

    point_id, point_type, apriori_x_m, apriori_y_m, apriori_z_m, image_id, sample, line

and optionally ``measure_id``, ``sigma_px`` (or ``sigma_line_px`` and
``sigma_sample_px``), ``sigma_x_m``, ``sigma_y_m``, ``sigma_z_m`` (a-priori sigmas of
``Constrained`` points), ``check`` (``true``/``1`` holds the measure out) and
``tile_id`` (the matching tile a measure came from, per image; measures of one tile
share a matcher offset in the covariance, ``[adjustment] systematic.tile_offset_sigma_px``).

Point types (case-insensitive, ISIS names): ``Free`` - a tie point whose coordinates
are unknowns (a priori coordinates are the starting values; empty ones are
triangulated); ``Fixed`` - ground known (an MCP); ``Constrained`` - ground weighted by
``sigma_*_m`` or the configuration's ``observations.mcp_ground_sigma_m``. Image ids that
map to the same camera file with different CCDs form one strip.
"""

from __future__ import annotations

import csv
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from planetref.adjust.config import AdjustConfig, validate_config
from planetref.camera.base import isis_to_csm
from planetref.camera.io import load_camera
from planetref.control.network import Network
from planetref.control.records import IMAGE_MARGIN_PX
from planetref.errors import InputError, MissingFileError
from planetref.runtime.tomlfile import read_toml

__all__ = ["NetworkFile", "read_network", "safe_name"]

REQUIRED_COLUMNS = (
    "point_id",
    "point_type",
    "apriori_x_m",
    "apriori_y_m",
    "apriori_z_m",
    "image_id",
    "sample",
    "line",
)
OPTIONAL_COLUMNS = (
    "measure_id",
    "sigma_px",
    "sigma_line_px",
    "sigma_sample_px",
    "sigma_x_m",
    "sigma_y_m",
    "sigma_z_m",
    "check",
    "tile_id",
)
POINT_TYPES = ("free", "fixed", "constrained")
_TOP_KEYS = {"measures", "convention", "images", "adjustment"}


@dataclass(frozen=True, eq=False)
class NetworkFile:
    """A network read from disk.

    Attributes:
        network: The network (measures converted to planetref's pixel convention).
        config: The configuration: the file's ``[adjustment]`` table over the defaults.
        config_table: The raw ``[adjustment]`` table (empty if absent).
        path: The TOML file.
        measures_path: The CSV file.
        convention: The measures' pixel convention as written in the file.
        camera_files: Camera id -> camera file.
        image_map: Image id -> ``(camera id, CCD name or None)``.
    """

    network: Network
    config: AdjustConfig
    config_table: dict[str, Any]
    path: Path
    measures_path: Path
    convention: str
    camera_files: dict[str, Path]
    image_map: dict[str, tuple[str, str | None]]


def safe_name(text: str) -> str:
    """A file-name-safe version of an id (``MRO/CTX/08:200`` -> ``MRO_CTX_08_200``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "camera"


def _float(text: str, path: Path, row: int, column: str, *, allow_empty: bool = False) -> float:
    s = text.strip()
    if s == "" and allow_empty:
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise InputError(
            f"row {row}: expected a number, got {text!r}", path=path, field=column
        ) from None
    if not math.isfinite(v):
        raise InputError(f"row {row}: must be finite, got {text!r}", path=path, field=column)
    return v


def _bool(text: str, path: Path, row: int) -> bool:
    s = text.strip().lower()
    if s in ("", "0", "false", "no", "f", "n"):
        return False
    if s in ("1", "true", "yes", "t", "y"):
        return True
    raise InputError(f"row {row}: expected true/false, got {text!r}", path=path, field="check")


def _check_in_image(
    measure: tuple[float, float],
    size: tuple[int, int],
    convention: str,
    path: Path,
    row: int,
    image_id: str,
) -> None:
    """Refuse a measure that lies more than 1 px outside its image.

    ``measure`` is ``(line, sample)`` as written in the file; ``size`` is the image's
    ``(n_lines, n_samples)``. In planetref's convention the image spans ``0 .. n`` (pixel
    edges); in ISIS's it spans ``0.5 .. n + 0.5``. The 1 px margin accepts sub-pixel
    measures on the border pixels of either convention.
    """
    shift = 0.5 if convention == "isis" else 0.0
    for name, value, n in (("line", measure[0], size[0]), ("sample", measure[1], size[1])):
        v = value - shift  # planetref convention
        if not -IMAGE_MARGIN_PX <= v <= n + IMAGE_MARGIN_PX:
            lo, hi = f"{shift:g}", f"{n + shift:g}"
            raise InputError(
                f"row {row}: {name} {value:g} is outside image {image_id!r} ({lo} to {hi})",
                path=path,
                field=name,
            )


def read_network(
    path: str | os.PathLike[str], config: AdjustConfig | dict[str, Any] | None = None
) -> NetworkFile:
    """Read ``NETWORK.toml``, its measures CSV and its cameras.

    Args:
        path: The TOML file.
        config: Overrides: a configuration applied instead of the file's
            ``[adjustment]`` table (``None``: the file's table over the defaults).

    Returns:
        The :class:`NetworkFile`.

    Raises:
        MissingFileError: The TOML, CSV or a camera file is missing.
        InputError: Naming the file, row and column at fault.
    """
    p = Path(path)
    doc = read_toml(p, "network file")
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {unknown}; expected {sorted(_TOP_KEYS)}", path=p)
    if "measures" not in doc or not isinstance(doc["measures"], str):
        raise InputError(
            "missing or non-string 'measures' (the measures CSV)", path=p, field="measures"
        )
    convention = doc.get("convention", "csm")
    if convention not in ("isis", "csm"):
        raise InputError(f"must be 'isis' or 'csm', got {convention!r}", path=p, field="convention")
    images = doc.get("images")
    if not isinstance(images, dict) or not images:
        raise InputError(
            "missing or empty [images] table (image_id -> camera file)", path=p, field="images"
        )
    table = doc.get("adjustment", {})
    if not isinstance(table, dict):
        raise InputError("must be a table", path=p, field="adjustment")
    cfg = (
        validate_config(config, source=str(p))
        if config is not None
        else validate_config(table, source=str(p))
    )
    base = p.parent

    # Cameras: image ids that share a file are CCDs of one strip.
    image_map: dict[str, tuple[str, str | None]] = {}
    by_file: dict[Path, list[tuple[str, str | None]]] = {}
    for image_id, entry in images.items():
        if isinstance(entry, str):
            cam_file, ccd = entry, None
        elif isinstance(entry, dict):
            extra = sorted(set(entry) - {"camera", "ccd"})
            if extra or not isinstance(entry.get("camera"), str):
                raise InputError(
                    f"expected a file name or {{camera = FILE, ccd = NAME}}, got {entry!r}",
                    path=p,
                    field=f"images.{image_id}",
                )
            cam_file, ccd = entry["camera"], entry.get("ccd")
            if ccd is not None and not isinstance(ccd, str):
                raise InputError(
                    f"ccd must be a string, got {ccd!r}", path=p, field=f"images.{image_id}.ccd"
                )
        else:
            raise InputError(
                f"expected a file name, got {entry!r}", path=p, field=f"images.{image_id}"
            )
        f = (base / cam_file).resolve()
        by_file.setdefault(f, []).append((image_id, ccd))
    cameras: dict[str, Any] = {}
    camera_files: dict[str, Path] = {}
    for f, entries in by_file.items():
        if not f.is_file():
            raise MissingFileError(f"camera file of image {entries[0][0]!r} not found", path=f)
        cam = load_camera(f)
        cam_id = entries[0][0] if len(entries) == 1 else f.stem
        if cam_id in cameras:
            cam_id = f"{cam_id}#{len(cameras)}"
        cameras[cam_id] = cam
        camera_files[cam_id] = f
        for image_id, ccd in entries:
            if ccd is not None and ccd not in cam.ccd_names:
                raise InputError(
                    f"camera {f.name} has no CCD {ccd!r} (it has {list(cam.ccd_names)})",
                    path=p,
                    field=f"images.{image_id}",
                )
            image_map[image_id] = (cam_id, ccd)

    csv_path = (base / doc["measures"]).resolve()
    if not csv_path.is_file():
        raise MissingFileError("measures file not found", path=csv_path)
    network = _read_measures(csv_path, convention, cameras, image_map, cfg)
    return NetworkFile(network, cfg, dict(table), p, csv_path, convention, camera_files, image_map)


def _read_measures(
    path: Path,
    convention: str,
    cameras: dict[str, Any],
    image_map: dict[str, tuple[str, str | None]],
    cfg: AdjustConfig,
) -> Network:
    try:
        fh = open(path, newline="", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc})", path=path) from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except UnicodeDecodeError:
            raise InputError("not UTF-8 text; save the file as UTF-8", path=path) from None
        except StopIteration:
            raise InputError("empty file (a header row is required)", path=path) from None
        except csv.Error as exc:  # a field over csv.field_size_limit(), a stray NUL...
            raise InputError(
                f"not a valid CSV file (line {reader.line_num}: {exc})", path=path
            ) from None
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if missing:
            raise InputError(f"missing column(s) {missing}; the header is {header}", path=path)
        extra = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
        if extra:
            raise InputError(
                f"unknown column(s) {extra}; optional columns are {list(OPTIONAL_COLUMNS)}",
                path=path,
            )
        col = {c: i for i, c in enumerate(header)}
        try:
            rows = list(reader)
        except UnicodeDecodeError as exc:
            raise InputError(
                f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start} of "
                "a read block); save the file as UTF-8",
                path=path,
            ) from None
        except csv.Error as exc:
            raise InputError(
                f"not a valid CSV file (line {reader.line_num}: {exc})", path=path
            ) from None
    if not rows:
        raise InputError("no measures (only a header)", path=path)
    obs_cam, obs_ccd, obs_pt, line, sample, sig, check, ids = [], [], [], [], [], [], [], []
    tiles: list[str | None] = []
    points: dict[str, dict[str, Any]] = {}
    for k, row in enumerate(rows):
        rn = k + 2  # 1-based file line (header is line 1)
        if len(row) == 0 or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"row {rn}: {len(row)} fields for {len(header)} columns", path=path)

        def get(name: str, row: list[str] = row) -> str:
            return row[col[name]] if name in col else ""

        pid = get("point_id").strip()
        if not pid:
            raise InputError(f"row {rn}: empty point id", path=path, field="point_id")
        ptype = get("point_type").strip().lower()
        if ptype not in POINT_TYPES:
            raise InputError(
                f"row {rn}: unknown point type {get('point_type')!r}; expected "
                f"Free, Fixed or Constrained",
                path=path,
                field="point_type",
            )
        image_id = get("image_id").strip()
        if image_id not in image_map:
            raise InputError(
                f"row {rn}: image {image_id!r} is not in the [images] table",
                path=path,
                field="image_id",
            )
        xyz = tuple(
            _float(get(c), path, rn, c, allow_empty=ptype == "free")
            for c in ("apriori_x_m", "apriori_y_m", "apriori_z_m")
        )
        psig = tuple(
            _float(get(c), path, rn, c, allow_empty=True)
            for c in ("sigma_x_m", "sigma_y_m", "sigma_z_m")
        )
        prev = points.get(pid)
        if prev is None:
            points[pid] = {"type": ptype, "xyz": xyz, "sigma": psig, "row": rn}
        else:
            if prev["type"] != ptype:
                raise InputError(
                    f"row {rn}: point {pid!r} is {ptype} here but "
                    f"{prev['type']} on row {prev['row']}",
                    path=path,
                    field="point_type",
                )
            a, b = np.array(prev["xyz"]), np.array(xyz)
            same = np.all((np.isnan(a) & np.isnan(b)) | (np.abs(a - b) <= 1e-6))
            if not same:
                raise InputError(
                    f"row {rn}: point {pid!r} has other a priori coordinates "
                    f"than on row {prev['row']}",
                    path=path,
                    field="apriori_x_m",
                )
        s_line = s_samp = cfg.observations.sigma_px
        if "sigma_px" in col and get("sigma_px").strip():
            s_line = s_samp = _float(get("sigma_px"), path, rn, "sigma_px")
        if "sigma_line_px" in col and get("sigma_line_px").strip():
            s_line = _float(get("sigma_line_px"), path, rn, "sigma_line_px")
        if "sigma_sample_px" in col and get("sigma_sample_px").strip():
            s_samp = _float(get("sigma_sample_px"), path, rn, "sigma_sample_px")
        if not (s_line > 0 and s_samp > 0):
            raise InputError(f"row {rn}: measure sigmas must be > 0", path=path, field="sigma_px")
        cam_id, ccd = image_map[image_id]
        meas_l = _float(get("line"), path, rn, "line")
        meas_s = _float(get("sample"), path, rn, "sample")
        _check_in_image(
            (meas_l, meas_s), cameras[cam_id].image_size(ccd), convention, path, rn, image_id
        )
        obs_cam.append(cam_id)
        obs_ccd.append(ccd)
        obs_pt.append(pid)
        line.append(meas_l)
        sample.append(meas_s)
        sig.append((s_line, s_samp))
        check.append(_bool(get("check"), path, rn) if "check" in col else False)
        ids.append(get("measure_id").strip() or f"row{rn}")
        tiles.append(get("tile_id").strip() or None)
    if len(set(ids)) != len(ids):
        raise InputError("measure ids must be unique", path=path, field="measure_id")
    line_a, sample_a = np.asarray(line), np.asarray(sample)
    if convention == "isis":
        line_a, sample_a = isis_to_csm(line_a, sample_a)
    point_xyz, point_sigma, point_kind = {}, {}, {}
    obs_cfg = cfg.observations
    for pid, info in points.items():
        point_xyz[pid] = info["xyz"]
        given = np.array(info["sigma"])
        if info["type"] == "free":
            s = obs_cfg.tie_apriori_sigma_m
            point_sigma[pid] = np.full(3, np.inf if s is None else s)
            point_kind[pid] = "tie"
        elif info["type"] == "fixed":
            s = obs_cfg.mcp_ground_sigma_m if obs_cfg.mcp_ground == "weighted" else 0.0
            point_sigma[pid] = np.full(3, s)
            point_kind[pid] = "mcp"
        else:
            if np.all(np.isfinite(given)):
                sg = given
            elif obs_cfg.mcp_ground_sigma_m is not None:
                sg = np.where(np.isfinite(given), given, obs_cfg.mcp_ground_sigma_m)
            else:
                raise InputError(
                    f"row {info['row']}: Constrained point {pid!r} needs "
                    f"sigma_x_m/sigma_y_m/sigma_z_m or the configuration's "
                    f"observations.mcp_ground_sigma_m",
                    path=path,
                    field="sigma_x_m",
                )
            if np.any(sg <= 0):
                raise InputError(
                    f"row {info['row']}: sigmas of a Constrained point must be > 0",
                    path=path,
                    field="sigma_x_m",
                )
            point_sigma[pid] = sg
            point_kind[pid] = "mcp"
    return Network.from_records(
        cameras,
        obs_camera=obs_cam,
        obs_point=obs_pt,
        line=line_a,
        sample=sample_a,
        point_xyz=point_xyz,
        point_sigma_m=point_sigma,
        point_kind=point_kind,
        obs_ccd=obs_ccd,
        sigma_px=np.asarray(sig),
        check=check,
        obs_ids=ids,
        source=path,
        tile=tiles if "tile_id" in col else None,
    )
