"""The body an RPC refers to (ellipsoid and kind of latitude).

Bodies and latitudes
--------------------
RPC00B files carry no datum: the standard (and GDAL) assume WGS84 geodetic longitude,
latitude and ellipsoidal height. Planetary RPCs (e.g. Mars, written by ASP or by
:func:`fit_rpc`) use another body, here described by an :class:`RpcBody` (an ellipsoid
and the kind of latitude the RPC's LAT_OFF/LAT_SCALE refer to). The writers of this
module record the body in a form every GDAL reader ignores: extra top-level keywords
after ``END_GROUP = IMAGE`` in an ``.RPB``, extra ``PLANETREF_*`` lines at the end of
an ``_RPC.TXT``, and a ``PLANETREF`` metadata domain in a GeoTIFF. Files without it are
taken to be Earth WGS84 with geodetic latitude.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

from planetref.camera.rpc.model import fmt, parse_number
from planetref.errors import (
    InputError,
)
from planetref.geometry.geodesy import (
    EARTH_WGS84,
    MARS_IAU2015_SPHERE,
    Ellipsoid,
    LatitudeKind,
)

__all__ = ["EARTH_BODY", "MARS_BODY", "RpcBody"]


# --------------------------------------------------------------------------- bodies


@dataclass(frozen=True)
class RpcBody:
    """The body an RPC's ground coordinates refer to.

    Attributes:
        ellipsoid: Reference ellipsoid of longitude, latitude and height.
        latitude_kind: Which latitude LAT_OFF/LAT_SCALE refer to: ``"planetographic"``
            (geodetic, the RPC00B standard) or ``"planetocentric"``.
    """

    ellipsoid: Ellipsoid
    latitude_kind: LatitudeKind

    def __post_init__(self) -> None:
        if self.latitude_kind not in ("planetocentric", "planetographic"):
            raise InputError(f"unknown latitude kind {self.latitude_kind!r}", field="latitude_kind")

    @classmethod
    def resolve(
        cls, body: str | Ellipsoid | RpcBody, latitude_kind: LatitudeKind | None = None
    ) -> RpcBody:
        """Normalise the ways planetref accepts a body.

        Args:
            body: ``"earth"`` (WGS84, geodetic latitude), ``"mars"`` (IAU 2015 sphere,
                planetocentric latitude), an :class:`Ellipsoid` or an :class:`RpcBody`.
            latitude_kind: Overrides the latitude kind. For a bare ellipsoid the default
                is geodetic ("planetographic", the RPC00B convention) unless it is a
                sphere, where both kinds coincide and planetref's planetocentric
                default is used.

        Raises:
            InputError: For an unknown body name.
        """
        if isinstance(body, RpcBody):
            base = body
        elif isinstance(body, Ellipsoid):
            base = cls(body, "planetocentric" if body.is_sphere else "planetographic")
        elif isinstance(body, str) and body.lower() in _NAMED_BODIES:
            base = _NAMED_BODIES[body.lower()]
        else:
            raise InputError(
                f"unknown body {body!r}; expected 'earth', 'mars', an Ellipsoid or an RpcBody",
                field="body",
            )
        if latitude_kind is not None and latitude_kind != base.latitude_kind:
            return cls(base.ellipsoid, latitude_kind)
        return base

    def _items(self) -> dict[str, str]:
        return {
            "BODY_NAME": self.ellipsoid.name,
            "SEMI_MAJOR_M": fmt(self.ellipsoid.semi_major_m),
            "SEMI_MINOR_M": fmt(self.ellipsoid.semi_minor_m),
            "LATITUDE": self.latitude_kind,
        }

    @classmethod
    def _from_items(
        cls, items: Mapping[str, str], path: str | os.PathLike[str] | None, prefix: str
    ) -> RpcBody | None:
        upper = {k.upper(): v for k, v in items.items()}
        if "SEMI_MAJOR_M" not in upper:
            return None
        a = parse_number(upper["SEMI_MAJOR_M"], path, prefix + "SEMI_MAJOR_M")
        b = parse_number(upper.get("SEMI_MINOR_M", ""), path, prefix + "SEMI_MINOR_M")
        kind = upper.get("LATITUDE", "").strip().strip('"').lower()
        if kind not in ("planetocentric", "planetographic"):
            raise InputError(
                f"expected 'planetocentric' or 'planetographic', got {kind!r}",
                path=path,
                field=prefix + "LATITUDE",
            )
        name = upper.get("BODY_NAME", "").strip().strip('"')
        try:
            ell = Ellipsoid(a, b, name)
        except InputError as exc:
            raise InputError(str(exc), path=path, field=prefix + "SEMI_MAJOR_M") from None
        return cls(ell, kind)  # type: ignore[arg-type]


EARTH_BODY = RpcBody(EARTH_WGS84, "planetographic")


MARS_BODY = RpcBody(MARS_IAU2015_SPHERE, "planetocentric")


_NAMED_BODIES = {"earth": EARTH_BODY, "mars": MARS_BODY}
