"""The sensor of a line-scan camera: line timing, interior orientation, CCD placement.

The parts of :class:`~planetref.camera.linescan.model.LineScanCamera` that do not move
with the orientation: :class:`LineRateTable` (image line -> time),
:class:`InteriorOrientation` (principal point and focal length, mm) and
:class:`CcdGeometry` (a CCD line's placement in the focal plane and its optional lens
distortion). The projection kernel and the camera file schema both build on them.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.camera.linescan.lens import NO_DISTORTION, ideal_position
from planetref.errors import InputError

__all__ = ["CcdGeometry", "InteriorOrientation", "LineRateTable"]


# --------------------------------------------------------------------------- time
@dataclass(frozen=True)
class LineRateTable:
    """Line -> time mapping.

    Attributes:
        rows: ``((start_line, start_time_s, period_s), ...)`` sorted by start line; row
            ``i`` applies from its start line up to the next row's. Before the first
            row the first row is extrapolated. Times are seconds (any epoch; only
            differences matter), periods seconds per line (> 0).
    """

    rows: tuple[tuple[float, float, float], ...]

    def __post_init__(self) -> None:
        rows = tuple(tuple(float(v) for v in r) for r in self.rows)
        if not rows:
            raise InputError("line rate table is empty", field="line_rates")
        for i, r in enumerate(rows):
            if len(r) != 3 or not all(math.isfinite(v) for v in r):
                raise InputError(f"row {i} must be 3 finite numbers, got {r}", field="line_rates")
            if r[2] <= 0:
                raise InputError(f"row {i}: period must be > 0 s, got {r[2]}", field="line_rates")
        starts = [r[0] for r in rows]
        if any(b <= a for a, b in itertools.pairwise(starts)):
            raise InputError("start lines must increase", field="line_rates")
        object.__setattr__(self, "rows", rows)

    @property
    def _arrays(self) -> tuple[F64, F64, F64]:
        a = np.asarray(self.rows, dtype=np.float64)
        return a[:, 0], a[:, 1], a[:, 2]

    def _row(self, line: F64) -> NDArray[np.intp]:
        starts = self._arrays[0]
        return np.clip(np.searchsorted(starts, line, side="right") - 1, 0, len(starts) - 1)

    def time(self, line: ArrayLike) -> F64:
        """Exposure time (s) of continuous line coordinates."""
        line = np.asarray(line, dtype=np.float64)
        starts, t0, period = self._arrays
        i = self._row(line)
        return t0[i] + (line - starts[i]) * period[i]

    def period(self, line: ArrayLike) -> F64:
        """Seconds per line at the given lines (``dt/dline``)."""
        line = np.asarray(line, dtype=np.float64)
        return self._arrays[2][self._row(line)]

    def line(self, time: ArrayLike) -> F64:
        """Inverse of :meth:`time` (continuous line of a time in seconds)."""
        t = np.asarray(time, dtype=np.float64)
        starts, t0, period = self._arrays
        i = np.clip(np.searchsorted(t0, t, side="right") - 1, 0, len(t0) - 1)
        return starts[i] + (t - t0[i]) / period[i]


# ---------------------------------------------------------------- interior, CCDs
@dataclass(frozen=True)
class InteriorOrientation:
    """Interior orientation shared by all CCDs of a camera.

    Attributes:
        focal_length_mm: Focal length ``f`` in millimetres (> 0).
        x0_mm: Principal point, along-track focal-plane coordinate (mm).
        y0_mm: Principal point, across-track focal-plane coordinate (mm).
    """

    focal_length_mm: float
    x0_mm: float = 0.0
    y0_mm: float = 0.0

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "x0_mm", "y0_mm"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(
                    f"must be finite, got {getattr(self, name)}", field=f"interior.{name}"
                )
        if self.focal_length_mm <= 0:
            raise InputError(
                f"must be > 0, got {self.focal_length_mm}", field="interior.focal_length_mm"
            )

    def as_array(self) -> F64:
        """``[x0_mm, y0_mm, f_mm]``, the order used by :class:`ImagePartials`."""
        return np.array([self.x0_mm, self.y0_mm, self.focal_length_mm])

    @classmethod
    def from_array(cls, values: ArrayLike) -> InteriorOrientation:
        """Inverse of :meth:`as_array`."""
        x0, y0, f = (float(v) for v in np.asarray(values, dtype=np.float64))
        return cls(focal_length_mm=f, x0_mm=x0, y0_mm=y0)


@dataclass(frozen=True)
class CcdGeometry:
    """Placement of one line-array CCD in the focal plane.

    Attributes:
        name: Identifier of the CCD (unique within a camera).
        n_lines: Number of image lines of this CCD's image.
        n_samples: Number of pixels of the array.
        pixel_pitch_mm: Pixel size in millimetres (> 0).
        x_mm: Along-track focal-plane coordinate of the sample-0 edge (mm).
        y_mm: Across-track focal-plane coordinate of the sample-0 edge (mm).
        angle_rad: Rotation of the array from the focal plane's y axis (radians).
        distortion: Lens distortion ``(k1, k2, p1, p2)`` seen by this CCD (mm^-2,
            mm^-4, mm^-1, mm^-1; :mod:`~planetref.camera.linescan.lens`); zeros: none.
    """

    name: str
    n_lines: int
    n_samples: int
    pixel_pitch_mm: float
    x_mm: float
    y_mm: float
    angle_rad: float = 0.0
    distortion: tuple[float, float, float, float] = NO_DISTORTION

    def __post_init__(self) -> None:
        where = f"ccds[{self.name}]"
        if not self.name:
            raise InputError("CCD name must not be empty", field="ccds.name")
        if int(self.n_lines) <= 0 or int(self.n_samples) <= 0:
            raise InputError(
                f"n_lines and n_samples must be > 0, got {self.n_lines}, {self.n_samples}",
                field=where,
            )
        for name in ("pixel_pitch_mm", "x_mm", "y_mm", "angle_rad"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"{name} must be finite", field=where)
        if len(self.distortion) != 4 or not all(math.isfinite(v) for v in self.distortion):
            raise InputError("distortion must be 4 finite numbers (k1, k2, p1, p2)", field=where)
        if self.pixel_pitch_mm <= 0:
            raise InputError(f"pixel_pitch_mm must be > 0, got {self.pixel_pitch_mm}", field=where)

    def focal_plane(self, sample: ArrayLike) -> tuple[F64, F64]:
        """Focal-plane ``(x, y)`` in mm of samples (with distortion: the ideal position)."""
        s = np.asarray(sample, dtype=np.float64) * self.pixel_pitch_mm
        x = self.x_mm + s * math.sin(self.angle_rad)
        y = self.y_mm + s * math.cos(self.angle_rad)
        return ideal_position(x, y, self.distortion)
