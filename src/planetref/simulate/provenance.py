"""Where a simulated scene's realism settings come from, for reports.

A difficulty level such as ``realistic`` carries a ``[sources]`` table (the real
statistic each value reproduces) and ``[realism].easier_than_real`` (what still makes
the scene easier than real data); :class:`~planetref.simulate.config.SimulationConfig`
keeps both and the simulator writes them to ``truth/config.toml``. :func:`read_realism`
reads them back, with each setting's value, so that a report can print the table.
"""

from __future__ import annotations

import os
from typing import NamedTuple

from planetref.runtime.tomlfile import read_toml
from planetref.simulate.config import SimulationConfig, validate_config

__all__ = ["Realism", "SourcedValue", "read_realism", "realism_of"]


class SourcedValue(NamedTuple):
    """One realism setting: its dotted name, its value (as text) and its source."""

    key: str
    value: str
    source: str


class Realism(NamedTuple):
    """The sourced settings and the caveats of one scene's config."""

    level: str
    values: tuple[SourcedValue, ...]
    easier_than_real: tuple[str, ...]


def _value_text(value: object) -> str:
    if hasattr(value, "model_dump"):
        dumped = value.model_dump(mode="json")  # type: ignore[attr-defined]
        return ", ".join(f"{k} {v}" for k, v in dumped.items())
    if isinstance(value, tuple):
        return "(" + ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def realism_of(cfg: SimulationConfig) -> Realism:
    """The sourced settings of ``cfg`` (sorted by name) and its caveats."""
    values = []
    for key, source in sorted(cfg.sources.items()):
        obj: object = cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        values.append(SourcedValue(key, _value_text(obj), source))
    level = cfg.name.rpartition("-")[2] if cfg.sources else ""
    return Realism(level, tuple(values), tuple(cfg.realism.easier_than_real))


def read_realism(path: str | os.PathLike[str]) -> Realism:
    """:func:`realism_of` the config written to a scene's ``truth/config.toml``.

    Raises:
        MissingFileError: If the file does not exist.
        InputError: If it is not a valid simulation config.
    """
    table = read_toml(path, "simulation config")
    return realism_of(validate_config(table, source=str(path)))
