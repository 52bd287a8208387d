"""Synthetic Mars scenes with exact ground truth (``planetref simulate``).

The simulator builds a truth terrain (fractal relief, craters, wrinkle ridges, smooth
plains, dunes), renders HiRIC-like line-scan CCD images through the rigorous line-scan
camera model, a CTX-like reference orthoimage and a MOLA-like reference DEM, and
writes them as a scene directory described by ``scene.toml``
(see :mod:`planetref.scene.manifest` and ``docs/scene-manifest.md``).

Importing this package has no side effects; the heavy modules are imported lazily by
:func:`simulate_scene`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from planetref.simulate.config import SimulationConfig

__all__ = ["available_presets", "load_config", "simulate_scene"]


def available_presets() -> tuple[str, ...]:
    """Names of the presets shipped with planetref (see :mod:`planetref.simulate.config`)."""
    from planetref.simulate.config import available_presets as _f

    return _f()


def load_config(
    preset: str = "tiny",
    overrides: Any = None,
    *,
    seed: int | None = None,
    difficulty: str | None = None,
) -> SimulationConfig:
    """Load a preset, apply overrides; see :func:`planetref.simulate.config.load_config`."""
    from planetref.simulate.config import load_config as _f

    return _f(preset, overrides, seed=seed, difficulty=difficulty)


def simulate_scene(config: SimulationConfig, out_dir: Any, **kwargs: Any) -> Any:
    """Simulate and write a scene; see :func:`planetref.simulate.scene.simulate_scene`."""
    from planetref.simulate.scene import simulate_scene as _f

    return _f(config, out_dir, **kwargs)
