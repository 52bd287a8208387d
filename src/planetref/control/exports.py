"""MCPs and tie points exported for other tools: an ASP GCP file and an ISIS-style CSV.

ASP ground control points (``.gcp``), as ``bundle_adjust`` reads them (ASP docs,
"Ground control points / File format"): one point per line, space-separated::

    id lat lon height sigma1 sigma2 sigma3  image col row sigma_col sigma_row  [image ...]

* ``id``: integer (the CSV's ``asp_id`` links it to planetref's point id);
* ``lat``/``lon``: degrees, *geodetic* latitude on the scene's body and east longitude in
  ``[-180, 180)`` (identical to planetocentric on a sphere); ``height``: metres above the
  body (pass ``--datum D_MARS`` for the IAU sphere, or ``--semi-major-axis`` /
  ``--semi-minor-axis`` for another body);
* ``sigma1..3``: the point's a-priori standard deviations in metres, written as
  (north, east, up), i.e. latitude, longitude, height: use ASP's
  ``--use-lon-lat-height-gcp-error``. A point with a free ground position (a tie point
  with ``tie_sigma_m`` unset) gets :data:`FREE_SIGMA_M` (ASP needs a finite positive
  sigma);
* per image: the image file (absolute path, as planetref read it), ``col``/``row`` with
  the first pixel's *centre* at ``(0, 0)`` (ASP's convention; planetref's image
  coordinates put it at 0.5, so ``col = sample - 0.5``, ``row = line - 0.5``) and their
  sigmas in pixels.

ISIS-style control network CSV (one row per measure, a header line), with the names of
ISIS control network fields (ControlPoint / ControlMeasure) where one exists:

``PointId`` (planetref's id), ``asp_id``, ``PointType`` (``Constrained``: a-priori ground
with sigmas; ``Free``: no ground constraint), ``planetref_kind`` (``mcp`` | ``tie``),
``check`` (an MCP held out of the adjustment as a check point), ``AprioriX``,
``AprioriY``, ``AprioriZ`` (body-fixed metres), ``AprioriLatitude`` (planetocentric
degrees, ISIS's default), ``AprioriLongitude`` (positive east, ``[0, 360)``, ISIS's
default), ``AprioriRadius`` (metres from the body centre), ``AprioriLatitudeSigma``,
``AprioriLongitudeSigma``, ``AprioriRadiusSigma`` (metres; empty when free),
``SerialNumber`` (the image file: planetref has no ISIS serial numbers), ``ccd``,
``planetref_tile`` (the matching tile an MCP's measure came from: the measures of one
tile share the matcher's error there, which ``planetref adjust`` models when a network's
measures CSV gives it as ``tile_id``; empty for tie points),
``Sample``, ``Line`` (ISIS pixel convention: the first pixel's centre at ``(1, 1)``, so
``Sample = sample + 0.5``), ``SampleSigma``, ``LineSigma`` (pixels), ``MeasureType``
(``RegisteredSubPixel``: matched automatically to sub-pixel precision).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.geometry.geodesy import Ellipsoid, xyz_to_lonlat
from planetref.runtime.atomic import write_text_atomic

__all__ = [
    "CNET_COLUMNS",
    "FREE_SIGMA_M",
    "ControlPoints",
    "write_asp_gcp",
    "write_isis_cnet_csv",
]

#: Sigma (m) written to the ASP GCP file for a point whose ground position is free.
FREE_SIGMA_M = 1.0e6

CNET_COLUMNS = (
    "PointId",
    "asp_id",
    "PointType",
    "planetref_kind",
    "check",
    "AprioriX",
    "AprioriY",
    "AprioriZ",
    "AprioriLatitude",
    "AprioriLongitude",
    "AprioriRadius",
    "AprioriLatitudeSigma",
    "AprioriLongitudeSigma",
    "AprioriRadiusSigma",
    "SerialNumber",
    "ccd",
    "planetref_tile",
    "Sample",
    "Line",
    "SampleSigma",
    "LineSigma",
    "MeasureType",
)


@dataclass(frozen=True)
class ControlPoints:
    """Points with a-priori ground positions and their image measures.

    Attributes:
        point_id: Point ids, ``(P,)``.
        kind: ``"mcp"`` or ``"tie"`` per point.
        xyz: A-priori body-fixed XYZ (m), ``(P, 3)``.
        sigma_m: A-priori (north, east, up) sigmas (m), ``(P, 3)``; ``inf`` = free.
        check: True for MCPs held out as check points, ``(P,)``.
        obs_point: Index of each measure's point, ``(M,)``.
        obs_image: Image file of each measure, ``(M,)``.
        obs_ccd: CCD name of each measure, ``(M,)``.
        line: Measured line (planetref pixels: first pixel's corner at 0), ``(M,)``.
        sample: Measured sample, ``(M,)``.
        sigma_px: Sigma of the measure (pixels), ``(M,)``.
        obs_tile: Matching tile of each measure (``""``: none, e.g. a tie point),
            ``(M,)``; empty (the default): none for every measure.
    """

    point_id: NDArray[Any]
    kind: NDArray[Any]
    xyz: F64
    sigma_m: F64
    check: NDArray[np.bool_]
    obs_point: NDArray[np.intp]
    obs_image: NDArray[Any]
    obs_ccd: NDArray[Any]
    line: F64
    sample: F64
    sigma_px: F64
    obs_tile: NDArray[Any] = field(default_factory=lambda: np.empty(0, dtype=object))

    @classmethod
    def from_mcps(
        cls,
        table: Any,
        images: Mapping[str, str | os.PathLike[str]],
        *,
        sigma_px: float,
        check: NDArray[np.bool_] | None = None,
        prefix: str = "",
    ) -> ControlPoints:
        """MCPs of one strip (an :class:`~planetref.control.mcp.McpTable`).

        Args:
            table: The MCP table.
            images: CCD name -> image file.
            sigma_px: Sigma of every image measure (pixels).
            check: Check-point flags per MCP (default none).
            prefix: Prefix of the point ids (e.g. ``"strip1:"``).
        """
        n = len(table)
        cols = getattr(table, "columns", {})
        if "sigma_ground_xy_m" in cols and "sigma_ground_h_m" in cols:
            xy = np.asarray(cols["sigma_ground_xy_m"], float)
            sig = np.column_stack([xy, xy, np.asarray(cols["sigma_ground_h_m"], float)])
        else:
            sig = np.full((n, 3), np.inf)
        ccd = np.asarray(table["ccd"]).astype(str)
        ids = np.asarray(table["mcp_id"])
        return cls(
            point_id=np.array([f"{prefix}mcp{int(i)}" for i in ids], dtype=object),
            kind=np.full(n, "mcp", dtype=object),
            xyz=np.asarray(table.xyz(), float).reshape(n, 3),
            sigma_m=sig,
            check=np.zeros(n, bool) if check is None else np.asarray(check, bool),
            obs_point=np.arange(n, dtype=np.intp),
            obs_image=np.array([str(images[c]) for c in ccd], dtype=object),
            obs_ccd=ccd.astype(object),
            line=np.asarray(table["line"], float),
            sample=np.asarray(table["sample"], float),
            sigma_px=np.full(n, float(sigma_px)),
            obs_tile=np.asarray(table["tile_id"]).astype(str).astype(object),
        )

    @classmethod
    def from_ties(
        cls,
        ties: Any,
        images: Mapping[tuple[str, str], str | os.PathLike[str]],
        *,
        sigma_m: float | None,
        sigma_px: float,
    ) -> ControlPoints:
        """Tie points of a campaign (a :class:`~planetref.frontend.tiepoints.TiePoints`).

        Args:
            ties: The tie points (two measures each).
            images: ``(strip, ccd)`` -> image file.
            sigma_m: A-priori ground sigma per axis (m); None: free.
            sigma_px: Sigma of every image measure (pixels).
        """
        t = len(ties)
        s = np.inf if sigma_m is None else float(sigma_m)
        strips = np.asarray(ties.strip).reshape(t, 2)
        ccds = np.asarray(ties.ccd).reshape(t, 2)
        return cls(
            point_id=np.array(list(ties.point_ids), dtype=object),
            kind=np.full(t, "tie", dtype=object),
            xyz=np.asarray(ties.xyz, float).reshape(t, 3),
            sigma_m=np.full((t, 3), s),
            check=np.zeros(t, bool),
            obs_point=np.repeat(np.arange(t, dtype=np.intp), 2),
            obs_image=np.array(
                [
                    str(images[(str(a), str(c))])
                    for a, c in zip(strips.ravel(), ccds.ravel(), strict=True)
                ],
                dtype=object,
            ),
            obs_ccd=ccds.ravel().astype(str).astype(object),
            line=np.asarray(ties.line, float).ravel(),
            sample=np.asarray(ties.sample, float).ravel(),
            sigma_px=np.full(2 * t, float(sigma_px)),
        )

    @classmethod
    def concatenate(cls, parts: Sequence[ControlPoints]) -> ControlPoints:
        """Several sets in one (measure indices renumbered)."""
        offsets = np.cumsum([0] + [len(p.point_id) for p in parts[:-1]])
        return cls(
            point_id=np.concatenate([p.point_id for p in parts]),
            kind=np.concatenate([p.kind for p in parts]),
            xyz=np.concatenate([p.xyz for p in parts]).reshape(-1, 3),
            sigma_m=np.concatenate([p.sigma_m for p in parts]).reshape(-1, 3),
            check=np.concatenate([p.check for p in parts]),
            obs_point=np.concatenate(
                [p.obs_point + o for p, o in zip(parts, offsets, strict=True)]
            ),
            obs_image=np.concatenate([p.obs_image for p in parts]),
            obs_ccd=np.concatenate([p.obs_ccd for p in parts]),
            line=np.concatenate([p.line for p in parts]),
            sample=np.concatenate([p.sample for p in parts]),
            sigma_px=np.concatenate([p.sigma_px for p in parts]),
            obs_tile=np.concatenate([p.tiles for p in parts]),
        )

    @property
    def tiles(self) -> NDArray[Any]:
        """:attr:`obs_tile`, one per measure (``""`` for all when it was not given)."""
        if len(self.obs_tile) == len(self.line):
            return self.obs_tile
        return np.full(len(self.line), "", dtype=object)


def _num(v: float) -> str:
    return repr(float(v))


def write_asp_gcp(
    points: ControlPoints, ellipsoid: Ellipsoid, path: str | os.PathLike[str]
) -> Path:
    """Write the points as an ASP ``.gcp`` file (see the module doc), atomically.

    Returns:
        The path written.
    """
    lon, lat, h = xyz_to_lonlat(points.xyz, ellipsoid, "planetographic")
    sig = np.where(np.isfinite(points.sigma_m), points.sigma_m, FREE_SIGMA_M)
    order = np.argsort(points.obs_point, kind="stable")
    starts = np.searchsorted(points.obs_point[order], np.arange(len(points.point_id) + 1))
    lines = []
    for i in range(len(points.point_id)):
        head = [str(i), _num(lat[i]), _num(lon[i]), _num(h[i]), *(_num(v) for v in sig[i])]
        for k in order[starts[i] : starts[i + 1]]:
            head += [
                str(points.obs_image[k]),
                _num(points.sample[k] - 0.5),
                _num(points.line[k] - 0.5),
                _num(points.sigma_px[k]),
                _num(points.sigma_px[k]),
            ]
        lines.append(" ".join(head))
    return write_text_atomic(Path(path), "\n".join(lines) + ("\n" if lines else ""))


def write_isis_cnet_csv(
    points: ControlPoints, ellipsoid: Ellipsoid, path: str | os.PathLike[str]
) -> Path:
    """Write the points as an ISIS-style control network CSV (see the module doc).

    Returns:
        The path written.
    """
    lon, lat, _ = xyz_to_lonlat(points.xyz, ellipsoid, "planetocentric")
    radius = np.linalg.norm(points.xyz, axis=1)
    tiles = points.tiles
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CNET_COLUMNS)
    for k in range(len(points.line)):
        i = int(points.obs_point[k])
        sig = points.sigma_m[i]
        free = not np.all(np.isfinite(sig))
        w.writerow(
            [
                points.point_id[i],
                i,
                "Free" if free else "Constrained",
                points.kind[i],
                bool(points.check[i]),
                *(_num(v) for v in points.xyz[i]),
                _num(lat[i]),
                _num(lon[i] % 360.0),
                _num(radius[i]),
                *(["", "", ""] if free else [_num(v) for v in sig]),
                points.obs_image[k],
                points.obs_ccd[k],
                tiles[k],
                _num(points.sample[k] + 0.5),
                _num(points.line[k] + 0.5),
                _num(points.sigma_px[k]),
                _num(points.sigma_px[k]),
                "RegisteredSubPixel",
            ]
        )
    return write_text_atomic(Path(path), buf.getvalue())
