"""Compatibility name of :func:`planetref.geometry.terrain.intersect_terrain`.

The ray/terrain intersection (with its rule at DEM holes) lives in
:mod:`planetref.geometry.terrain`; import it from there.
"""

from planetref.geometry.terrain import intersect_terrain

__all__ = ["intersect_terrain"]
