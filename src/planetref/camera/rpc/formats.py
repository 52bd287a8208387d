"""Readers and writers of RPCs: GeoTIFF metadata, DigitalGlobe ``.RPB`` and GDAL ``_RPC.TXT``.

Exactness
---------
The text writers print every number with Python's shortest round-trip representation,
so ``read_rpc(write(x)) == x`` exactly and GDAL (``CPLAtof``) reads the same doubles.
GDAL's GeoTIFF RPC tag stores doubles but reports them with ``%.15g``; the GeoTIFF
writer therefore also stores the exact values in the ``PLANETREF`` domain, which the
reader prefers when they agree with the RPC tag to 15 digits.
"""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import fields
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from planetref.camera.rpc.body import RpcBody
from planetref.camera.rpc.model import (
    COEFFS,
    N_TERMS,
    OPTIONAL,
    SCALARS,
    Rpc,
    build,
    fmt,
    parse_list,
    parse_number,
)
from planetref.errors import (
    InputError,
    MissingFileError,
    UnsupportedFormatError,
)
from planetref.runtime.atomic import atomic_path, write_text_atomic

__all__ = [
    "RpcFormat",
    "read_rpc",
    "read_rpc_body",
    "rpc_sidecar_path",
    "write_rpc",
    "write_rpc_geotiff",
    "write_rpc_rpb",
    "write_rpc_txt",
]


RpcFormat = Literal["rpb", "txt", "geotiff"]


# --------------------------------------------------------------------------- readers


def read_rpc(path: str | os.PathLike[str]) -> Rpc:
    """Read an RPC00B model, recognising the format by the file's content.

    Supported: a GeoTIFF (or any raster GDAL reads) with RPC metadata, read through
    rasterio; a DigitalGlobe/ENVI ``.RPB`` (``BEGIN_GROUP = IMAGE ... lineNumCoef =
    (...)``); a GDAL/GeoEye ``_RPC.TXT`` (``LINE_OFF: ...`` key/value lines).

    Args:
        path: The file.

    Returns:
        The validated model.

    Raises:
        MissingFileError: If the file does not exist.
        UnsupportedFormatError: If it is none of the formats above.
        InputError: If it is truncated, garbled, misses a field or holds invalid
            numbers; the message names the file and the field.
    """
    return read(path)[0]


def read_rpc_body(path: str | os.PathLike[str]) -> RpcBody | None:
    """The body planetref recorded in an RPC file, or None (then assume Earth WGS84).

    Raises:
        The errors of :func:`read_rpc`.
    """
    return read(path)[1]


def read(path: str | os.PathLike[str]) -> tuple[Rpc, RpcBody | None]:
    p = Path(path)
    if not p.exists():
        raise MissingFileError("RPC file not found", path=p)
    if p.is_dir():
        raise UnsupportedFormatError("is a directory, not an RPC file", path=p)
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _read_raster(p)
    if b"\x00" not in head:
        text = head.decode("latin-1")
        if re.search(r"BEGIN_GROUP\s*=\s*IMAGE|\blineNumCoef\b|\blineOffset\b", text, re.I):
            return _read_rpb(p)
        if re.search(r"^\s*(LINE_OFF|LINE_NUM_COEFF_1)\s*[:=]", text, re.I | re.M):
            return _read_txt(p)
        if not text.strip():
            raise UnsupportedFormatError("empty file, expected RPC coefficients", path=p)
    # Other rasters GDAL can read (NITF with an RPC00B TRE, JP2 with sidecars...).
    try:
        return _read_raster(p)
    except UnsupportedFormatError:
        raise UnsupportedFormatError(
            "not an RPC file: expected a GeoTIFF with RPC metadata, a .RPB file or an "
            "_RPC.TXT file",
            path=p,
        ) from None


def _read_raster(p: Path) -> tuple[Rpc, RpcBody | None]:
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        with rasterio.open(p) as src:
            gdal_md = src.tags(ns="RPC")
            extra = src.tags(ns="PLANETREF")
    except RasterioIOError as exc:
        raise UnsupportedFormatError(f"cannot be opened by GDAL ({exc})", path=p) from None
    if not gdal_md:
        raise InputError("the raster has no RPC metadata", path=p, field="RPC")
    rpc = Rpc.from_gdal(gdal_md, path=p)
    body = RpcBody._from_items(
        {k: v for k, v in extra.items() if not k.startswith("RPC_")}, p, "PLANETREF:"
    )
    exact = {k[4:]: v for k, v in extra.items() if k.startswith("RPC_")}
    if exact:
        try:
            candidate = Rpc.from_gdal(exact, path=p)
        except InputError:
            candidate = None
        # Use the exact copy only if it is what the RPC tag holds (to GDAL's 15 digits),
        # so an RPC rewritten later by other software wins over a stale copy.
        if candidate is not None and _agrees(candidate, rpc):
            rpc = candidate
    return rpc, body


def _agrees(exact: Rpc, reported: Rpc) -> bool:
    def same(a: float | None, b: float | None) -> bool:
        if a is None or b is None:
            # GDAL reports absent ERR_BIAS/ERR_RAND of a GeoTIFF tag as -1.
            return (a if a is not None else -1.0) == (b if b is not None else -1.0)
        return a == b or float(f"{a:.15g}") == b

    for f in fields(Rpc):
        a, b = getattr(exact, f.name), getattr(reported, f.name)
        if f.name.endswith("_coeff"):
            if not all(same(x, y) for x, y in zip(a, b, strict=True)):
                return False
        elif not same(a, b):
            return False
    return True


def _strip_comments(text: str) -> str:
    # CPLKeywordParser (GDAL's .RPB reader) skips C-style comments too.
    return re.sub(r"/\*.*?\*/", " ", text, flags=re.S)


_RPB_STATEMENT = re.compile(r"([A-Za-z_][\w.]*)\s*=\s*(\([^()]*\)|\"[^\"]*\"|[^;\n]*)\s*;?")


def _read_rpb(p: Path) -> tuple[Rpc, RpcBody | None]:
    text = _strip_comments(p.read_text(encoding="latin-1"))
    items: dict[str, str] = {}
    for m in _RPB_STATEMENT.finditer(text):
        items.setdefault(m.group(1).lower(), m.group(2).strip())
    if "(" in text and text.count("(") != text.count(")"):
        # An unterminated coefficient list: name the first list that is not closed.
        for _, _, rpb_name in COEFFS:
            if re.search(rf"\b{rpb_name}\s*=\s*\(([^()]*)(\(|$)", text, re.I):
                raise InputError(
                    "unterminated coefficient list (truncated file?)", path=p, field=rpb_name
                )
    values: dict[str, object] = {}
    for _, attr, rpb_name in SCALARS:
        raw = items.get(rpb_name.lower())
        if raw is None:
            if attr in OPTIONAL:
                continue
            raise InputError("missing", path=p, field=rpb_name)
        values[attr] = parse_number(raw, p, rpb_name)
    for _, attr, rpb_name in COEFFS:
        raw = items.get(rpb_name.lower())
        if raw is None:
            raise InputError("missing", path=p, field=rpb_name)
        raw = raw.strip()
        if not (raw.startswith("(") and raw.endswith(")")):
            raise InputError(f"expected '(c1, ..., c20)', got {raw[:40]!r}", path=p, field=rpb_name)
        values[attr] = parse_list(raw[1:-1], p, rpb_name)
    rpc = build(values, p, {a: r for _, a, r in SCALARS + COEFFS})
    body_items = {
        k[len("planetref") :].upper(): v for k, v in items.items() if k.startswith("planetref")
    }
    body_items = {_RPB_BODY_KEYS.get(k, k): v for k, v in body_items.items()}
    return rpc, RpcBody._from_items(body_items, p, "planetref")


# .RPB keyword suffix (after "planetref") -> RpcBody item name.
_RPB_BODY_KEYS = {
    "BODYNAME": "BODY_NAME",
    "SEMIMAJORAXIS": "SEMI_MAJOR_M",
    "SEMIMINORAXIS": "SEMI_MINOR_M",
    "LATITUDE": "LATITUDE",
}


def _read_txt(p: Path) -> tuple[Rpc, RpcBody | None]:
    items: dict[str, tuple[str, int]] = {}
    for lineno, raw_line in enumerate(p.read_text(encoding="latin-1").splitlines(), 1):
        line = raw_line.strip()
        if not line:
            continue
        m = re.match(r"^([A-Za-z_]\w*)\s*[:=]\s*(.*)$", line)
        if m is None:
            raise InputError(f"line {lineno}: expected 'KEY: value', got {line[:40]!r}", path=p)
        items.setdefault(m.group(1).upper(), (m.group(2), lineno))
    values: dict[str, object] = {}
    for gdal_name, attr, _ in SCALARS:
        if gdal_name not in items:
            if attr in OPTIONAL:
                continue
            raise InputError("missing", path=p, field=gdal_name)
        values[attr] = parse_number(items[gdal_name][0], p, gdal_name)
    for gdal_name, attr, _ in COEFFS:
        coeffs = []
        for i in range(1, N_TERMS + 1):
            key = f"{gdal_name}_{i}"
            if key not in items:
                raise InputError("missing", path=p, field=key)
            coeffs.append(parse_number(items[key][0], p, key))
        if f"{gdal_name}_{N_TERMS + 1}" in items:
            raise InputError(
                "more than 20 coefficients", path=p, field=f"{gdal_name}_{N_TERMS + 1}"
            )
        values[attr] = tuple(coeffs)
    rpc = build(values, p, {a: g for g, a, _ in SCALARS + COEFFS})
    body_items = {
        k[len("PLANETREF_") :]: v for k, (v, _) in items.items() if k.startswith("PLANETREF_")
    }
    return rpc, RpcBody._from_items(body_items, p, "PLANETREF_")


# --------------------------------------------------------------------------- writers


def rpc_sidecar_path(
    image_path: str | os.PathLike[str], fmt: Literal["rpb", "txt"] = "rpb"
) -> Path:
    """Where GDAL looks for an RPC sidecar of an image.

    Args:
        image_path: The image, e.g. ``scene.tif``.
        fmt: ``"rpb"`` for ``scene.RPB`` or ``"txt"`` for ``scene_RPC.TXT``.

    Returns:
        The sidecar path next to the image.
    """
    p = Path(image_path)
    if fmt == "rpb":
        return p.with_suffix(".RPB")
    if fmt == "txt":
        return p.with_name(p.stem + "_RPC.TXT")
    raise InputError(f"unknown sidecar format {fmt!r}; expected 'rpb' or 'txt'", field="fmt")


def write_rpc_rpb(rpc: Rpc, path: str | os.PathLike[str], *, body: RpcBody | None = None) -> Path:
    """Write a DigitalGlobe ``.RPB`` file in the layout GDAL's ``GDALWriteRPBFile`` uses.

    The body, if given, goes into ``planetref*`` keywords after ``END_GROUP = IMAGE``,
    which GDAL's keyword parser reads and ignores. The file is written atomically.

    Args:
        rpc: The model.
        path: Output path (GDAL finds it next to ``scene.tif`` as ``scene.RPB``).
        body: The body to record, or None to record nothing (readers then assume Earth).

    Returns:
        The path written.
    """
    p = Path(path)
    out = ['satId = "NONE";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for _, attr, rpb_name in SCALARS:
        value = getattr(rpc, attr)
        if value is not None:
            out.append(f"\t{rpb_name} = {fmt(value)};")
    for _, attr, rpb_name in COEFFS:
        coeffs = [fmt(v) for v in getattr(rpc, attr)]
        out.append(f"\t{rpb_name} = (")
        out.extend(f"\t\t\t{c}," for c in coeffs[:-1])
        out.append(f"\t\t\t{coeffs[-1]});")
    out.append("END_GROUP = IMAGE")
    if body is not None:
        items = body._items()
        out.append(f'planetrefBodyName = "{_quote_safe(items["BODY_NAME"])}";')
        out.append(f"planetrefSemiMajorAxis = {items['SEMI_MAJOR_M']};")
        out.append(f"planetrefSemiMinorAxis = {items['SEMI_MINOR_M']};")
        out.append(f'planetrefLatitude = "{items["LATITUDE"]}";')
    out.append("END;")
    write_text_atomic(p, "\n".join(out) + "\n", encoding="ascii")
    return p


def _quote_safe(text: str) -> str:
    return re.sub(r'["\n\r;]', " ", text)


def write_rpc_txt(rpc: Rpc, path: str | os.PathLike[str], *, body: RpcBody | None = None) -> Path:
    """Write a ``_RPC.TXT`` file in the layout of GDAL's ``GDALWriteRPCTXTFile``.

    The body, if given, goes into trailing ``PLANETREF_*`` lines that GDAL ignores.
    Every line stays under the 100 characters GDAL's reader accepts. The file is
    written atomically.

    Args:
        rpc: The model.
        path: Output path (GDAL finds it next to ``scene.tif`` as ``scene_RPC.TXT``).
        body: The body to record, or None.

    Returns:
        The path written.
    """
    p = Path(path)
    out = []
    for gdal_name, attr, _ in SCALARS:
        value = getattr(rpc, attr)
        if value is not None:
            out.append(f"{gdal_name}: {fmt(value)}")
    for gdal_name, attr, _ in COEFFS:
        out.extend(f"{gdal_name}_{i}: {fmt(v)}" for i, v in enumerate(getattr(rpc, attr), 1))
    if body is not None:
        out.extend(f"PLANETREF_{k}: {_quote_safe(v)[:60]}" for k, v in body._items().items())
    write_text_atomic(p, "\n".join(out) + "\n", encoding="ascii")
    return p


def write_rpc_geotiff(
    rpc: Rpc,
    path: str | os.PathLike[str],
    *,
    data: ArrayLike | None = None,
    body: RpcBody | None = None,
) -> Path:
    """Embed an RPC into a GeoTIFF (GDAL's RPC TIFF tag), atomically.

    With ``data`` a new GeoTIFF holding that image is written; without it the RPC of
    the existing GeoTIFF at ``path`` is replaced (the file is copied, updated and
    renamed over the original). The exact values and the body also go into the
    ``PLANETREF`` metadata domain (the GDAL_METADATA TIFF tag), because GDAL reports
    the RPC tag with only 15 significant digits.

    Args:
        rpc: The model.
        path: The GeoTIFF.
        data: Image of shape ``(rows, cols)`` or ``(bands, rows, cols)``, or None.
        body: The body to record, or None.

    Returns:
        The path written.

    Raises:
        MissingFileError: If ``data`` is None and ``path`` does not exist.
        InputError: If ``data`` has the wrong number of dimensions.
    """
    import rasterio

    p = Path(path)
    extra = {f"RPC_{k}": v for k, v in rpc.to_gdal().items()}
    for name in ("ERR_BIAS", "ERR_RAND"):
        # An empty value marks "absent", overriding any stale copy in an updated file.
        extra.setdefault(f"RPC_{name}", "")
    if body is not None:
        extra.update(body._items())
    if data is None:
        if not p.exists():
            raise MissingFileError("GeoTIFF to update not found (pass data= to create one)", path=p)
        with atomic_path(p) as tmp:
            shutil.copyfile(p, tmp)
            with rasterio.open(tmp, "r+") as dst:
                # The setter replaces the whole RPC domain; rasterio drops an error
                # value of exactly 0, which the item update puts back.
                dst.rpcs = rpc.to_rasterio()
                dst.update_tags(ns="RPC", **rpc.to_gdal())
                dst.update_tags(ns="PLANETREF", **extra)
        return p
    arr = np.asarray(data)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise InputError(f"expected a 2-D or 3-D image, got shape {arr.shape}", field="data")
    with atomic_path(p) as tmp:
        with rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=arr.shape[2],
            height=arr.shape[1],
            count=arr.shape[0],
            dtype=arr.dtype,
            rpcs=rpc.to_gdal(),
        ) as dst:
            dst.write(arr)
            dst.update_tags(ns="PLANETREF", **extra)
    return p


def write_rpc(
    rpc: Rpc,
    path: str | os.PathLike[str],
    *,
    fmt: RpcFormat | None = None,
    body: RpcBody | None = None,
) -> Path:
    """Write an RPC in the format given by ``fmt`` or by the file name.

    ``*.RPB`` -> :func:`write_rpc_rpb`; ``*.TXT`` (e.g. ``scene_RPC.TXT``) ->
    :func:`write_rpc_txt`; ``*.tif``/``*.tiff`` -> :func:`write_rpc_geotiff` updating
    the existing GeoTIFF.

    Args:
        rpc: The model.
        path: Output path.
        fmt: ``"rpb"``, ``"txt"`` or ``"geotiff"``; inferred from the suffix when None.
        body: The body to record, or None.

    Returns:
        The path written.

    Raises:
        UnsupportedFormatError: If the format cannot be inferred.
    """
    p = Path(path)
    if fmt is None:
        suffix = p.suffix.lower()
        fmt = {".rpb": "rpb", ".txt": "txt", ".tif": "geotiff", ".tiff": "geotiff"}.get(suffix)  # type: ignore[assignment]
        if fmt is None:
            raise UnsupportedFormatError(
                "cannot tell the RPC format from the suffix; use .RPB, _RPC.TXT or .tif "
                "or pass fmt=",
                path=p,
            )
    if fmt == "rpb":
        return write_rpc_rpb(rpc, p, body=body)
    if fmt == "txt":
        return write_rpc_txt(rpc, p, body=body)
    if fmt == "geotiff":
        return write_rpc_geotiff(rpc, p, body=body)
    raise UnsupportedFormatError(f"unknown RPC format {fmt!r}", path=p, field="fmt")
