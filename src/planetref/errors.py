"""The exception hierarchy of planetref.

Every error that planetref raises on purpose derives from :class:`PlanetrefError`.
The subclasses also derive from the matching built-in type (``ValueError``,
``FileNotFoundError``...), so callers may catch either, as rasterio does.
The CLI prints ``str(error)`` as a single line, so messages name the file and the
field or value at fault and say what was expected.
"""

from __future__ import annotations

from os import PathLike


class PlanetrefError(Exception):
    """Root of all planetref errors."""


class InputError(PlanetrefError, ValueError):
    """Malformed or inconsistent input (a file, a field, an argument)."""

    def __init__(
        self, message: str, *, path: str | PathLike[str] | None = None, field: str | None = None
    ) -> None:
        self.path = None if path is None else str(path)
        self.field = field
        parts = []
        if self.path is not None:
            parts.append(self.path)
        if field:
            parts.append(f"field '{field}'")
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class MissingFileError(PlanetrefError, FileNotFoundError):
    """A required file does not exist."""

    def __init__(self, message: str, *, path: str | PathLike[str] | None = None) -> None:
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)

    def __str__(self) -> str:
        return str(self.args[0])


class UnsupportedFormatError(InputError):
    """A file whose format planetref does not recognise or support."""


class CrsError(InputError):
    """A coordinate reference system that is missing, wrong or incompatible."""


class GeometryError(PlanetrefError, ValueError):
    """A geometric computation has no valid answer.

    For example a ray misses the terrain, a point lies behind the camera, or an
    iteration does not converge.
    """


class OutputError(PlanetrefError, OSError):
    """An output cannot be written (disk full, permissions, a writer library failing).

    The message names the file.
    """

    def __init__(self, message: str, *, path: str | PathLike[str] | None = None) -> None:
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)

    def __str__(self) -> str:
        return str(self.args[0])


class RunDirError(InputError):
    """A run folder that cannot be claimed (foreign, in use, another run, inputs changed)."""


class WeightsError(PlanetrefError, FileNotFoundError):
    """Pretrained weights are missing or do not match their expected checksum."""

    def __str__(self) -> str:
        return str(self.args[0])


class MatchingError(PlanetrefError, RuntimeError):
    """Matching failed in a way the caller must know about (e.g. zero matches)."""


class MatcherFailedError(MatchingError):
    """A matcher ran but its run could not finish: too few MCPs, a degenerate adjustment.

    Unlike missing weights (the matcher could not run at all), such a run is a result: a
    comparison keeps it as a row (NCP 0, its tiles failed, its funnel and the reason).

    Attributes:
        matching: Strip id -> the ``matching`` block of each strip matched so far.
        report: The failed run's report.json content, once the run has written it.
    """

    def __init__(
        self,
        message: str,
        *,
        matching: dict[str, dict[str, object]] | None = None,
        report: dict[str, object] | None = None,
    ) -> None:
        super().__init__(message)
        self.matching = dict(matching or {})
        self.report = report


class AdjustmentError(PlanetrefError, RuntimeError):
    """The bundle adjustment is degenerate, diverged or cannot start."""


def library_reason(exc: BaseException) -> str:
    """The first line of what a library said about an error.

    rasterio raises ``RasterioIOError("Read failed. See previous exception for details.")``
    with GDAL's own message (which block, which file) as its cause: that one is used.
    """
    for e in (exc.__cause__, exc):
        text = str(e).strip() if e is not None else ""
        if text:
            return text.splitlines()[0]
    return type(exc).__name__


__all__ = [
    "AdjustmentError",
    "CrsError",
    "GeometryError",
    "InputError",
    "MatcherFailedError",
    "MatchingError",
    "MissingFileError",
    "OutputError",
    "PlanetrefError",
    "RunDirError",
    "UnsupportedFormatError",
    "WeightsError",
    "library_reason",
]
