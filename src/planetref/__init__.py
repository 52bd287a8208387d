"""planetref: georeferencing of planetary push-broom imagery without ground control points.

Importing the package has no side effects: no weights are loaded, no global
configuration is changed.
"""

from importlib.metadata import PackageNotFoundError, version

from planetref.errors import PlanetrefError

try:
    __version__ = version("planetref")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["PlanetrefError", "__version__"]
