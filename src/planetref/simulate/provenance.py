"""Where a simulated scene's realism settings come from: the typed side, for the simulator.

A difficulty level such as ``realistic`` carries a ``[sources]`` table (the real
statistic each value reproduces) and ``[realism].easier_than_real`` (what still makes
the scene easier than real data); :class:`~planetref.simulate.config.SimulationConfig`
keeps both and the simulator writes them to ``truth/config.toml``. Reports read them
back as data with :func:`planetref.scene.realism.read_realism`; :func:`realism_of` gives
the same from a config in memory.
"""

from __future__ import annotations

from planetref.scene.realism import Realism, SourcedValue, value_text
from planetref.simulate.config import SimulationConfig

__all__ = ["realism_of"]


def realism_of(cfg: SimulationConfig) -> Realism:
    """The sourced settings of ``cfg`` (sorted by name) and its caveats."""
    values = []
    for key, source in sorted(cfg.sources.items()):
        obj: object = cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        if hasattr(obj, "model_dump"):
            obj = obj.model_dump(mode="json")  # a table: printed as its keys and values
        values.append(SourcedValue(key, value_text(obj), source))
    level = cfg.name.rpartition("-")[2] if cfg.sources else ""
    return Realism(level, tuple(values), tuple(cfg.realism.easier_than_real))
