"""Validation of the native line-scan camera JSON (format ``planetref-linescan``).

The format is documented in ``docs/camera-format.md``. Validation is done with pydantic
models that reject unknown keys and non-finite numbers, and every error becomes a
one-line :class:`~planetref.errors.InputError` naming the file and the field.
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError, field_validator

from planetref.errors import InputError, UnsupportedFormatError
from planetref.runtime.jsonfile import read_json
from planetref.runtime.settings import Settings, validation_problems

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


_Model = Settings


class BodyDoc(_Model):
    """The ``body`` object: the reference ellipsoid."""

    name: str = ""
    semi_major_m: FiniteFloat = Field(gt=0)
    semi_minor_m: FiniteFloat = Field(gt=0)
    latitude: Literal["planetocentric", "planetographic"] = "planetocentric"


class OrientationDoc(_Model):
    """The ``orientation`` object: node lines, node EOPs and the Lagrange order."""

    interpolation_order: int = Field(default=4, ge=2, le=16)
    node_lines: list[FiniteFloat] = Field(min_length=2)
    nodes: list[Annotated[list[FiniteFloat], Field(min_length=6, max_length=6)]]


class InteriorDoc(_Model):
    """The ``interior`` object: focal length and principal point (mm)."""

    focal_length_mm: FiniteFloat = Field(gt=0)
    x0_mm: FiniteFloat = 0.0
    y0_mm: FiniteFloat = 0.0


class CcdDoc(_Model):
    """One entry of ``ccds``: a CCD's size and placement in the focal plane."""

    name: str = Field(min_length=1)
    n_lines: int = Field(gt=0)
    n_samples: int = Field(gt=0)
    pixel_pitch_mm: FiniteFloat = Field(gt=0)
    x_mm: FiniteFloat
    y_mm: FiniteFloat
    angle_rad: FiniteFloat = 0.0
    distortion: Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0, 0.0]
    )


class CameraDoc(_Model):
    """The whole camera document."""

    format: Literal["planetref-linescan"]
    version: int
    name: str = ""
    body: BodyDoc
    frame_rotation: Annotated[
        list[Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]],
        Field(min_length=3, max_length=3),
    ]
    line_rates: list[Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]] = Field(
        min_length=1
    )
    orientation: OrientationDoc
    interior: InteriorDoc
    ccds: list[CcdDoc] = Field(min_length=1)

    @field_validator("version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if v != 1:
            raise ValueError(f"unsupported version {v}; this planetref reads version 1")
        return v


def load_json(path: str | os.PathLike[str]) -> Any:
    """Read a camera JSON file with one-line errors (see :mod:`planetref.runtime.jsonfile`)."""
    return read_json(path, "camera file")


def parse_document(doc: Any, *, path: str | os.PathLike[str] | None, factory: Any) -> Any:
    """Validate a decoded native camera document and build the camera with ``factory``."""
    import numpy as np

    from planetref.camera.linescan.sensor import CcdGeometry, InteriorOrientation, LineRateTable
    from planetref.geometry.geodesy import Ellipsoid

    if not isinstance(doc, dict) or doc.get("format") != "planetref-linescan":
        raise UnsupportedFormatError(
            'not a planetref line-scan camera (expected "format": "planetref-linescan")', path=path
        )
    try:
        m = CameraDoc.model_validate(doc)
    except ValidationError as exc:
        first = validation_problems(exc, CameraDoc)[0]
        raise InputError(first.text, path=path, field=first.key) from None
    if len(m.orientation.node_lines) != len(m.orientation.nodes):
        raise InputError(
            f"{len(m.orientation.node_lines)} node lines but {len(m.orientation.nodes)} nodes",
            path=path,
            field="orientation.nodes",
        )
    try:
        ell = Ellipsoid(m.body.semi_major_m, m.body.semi_minor_m, m.body.name)
        return factory(
            ellipsoid=ell,
            frame_rotation=np.asarray(m.frame_rotation, dtype=np.float64),
            line_rates=LineRateTable(tuple((s, t, d) for s, t, d in m.line_rates)),
            node_lines=np.asarray(m.orientation.node_lines, dtype=np.float64),
            nodes=np.asarray(m.orientation.nodes, dtype=np.float64),
            interior=InteriorOrientation(
                m.interior.focal_length_mm, m.interior.x0_mm, m.interior.y0_mm
            ),
            ccds=tuple(
                CcdGeometry(
                    c.name,
                    c.n_lines,
                    c.n_samples,
                    c.pixel_pitch_mm,
                    c.x_mm,
                    c.y_mm,
                    c.angle_rad,
                    (c.distortion[0], c.distortion[1], c.distortion[2], c.distortion[3]),
                )
                for c in m.ccds
            ),
            interpolation_order=m.orientation.interpolation_order,
            latitude_kind=m.body.latitude,
            name=m.name,
        )
    except InputError as exc:
        if exc.path is None and path is not None:
            raise InputError(str(exc), path=path) from None
        raise


__all__ = ["CameraDoc", "load_json", "parse_document"]
