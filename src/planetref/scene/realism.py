"""Where a simulated scene's realism settings come from, read back for reports.

A difficulty level such as ``realistic`` carries a ``[sources]`` table (the real
statistic each value reproduces) and ``[realism].easier_than_real`` (what still makes
the scene easier than real data); the simulator writes both, with every setting, to the
scene's ``truth/config.toml``. :func:`read_realism` reads them back as data (the file's
tables, not the simulator's models), so a report needs nothing of the simulator.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import NamedTuple

from planetref.runtime.tomlfile import read_toml

__all__ = ["Realism", "SourcedValue", "read_realism", "realism_from_table", "value_text"]


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


def value_text(value: object) -> str:
    """A setting's value as the report prints it (tables as ``key value, ...``)."""
    if isinstance(value, Mapping):
        return ", ".join(f"{k} {v}" for k, v in value.items())
    if isinstance(value, tuple | list):
        return "(" + ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def realism_from_table(table: Mapping[str, object]) -> Realism:
    """The sourced settings (sorted by name) and caveats of a simulation config's tables."""
    sources = table.get("sources") or {}
    values = []
    for key, source in sorted(dict(sources).items()):  # type: ignore[call-overload]
        obj: object = table
        for part in str(key).split("."):
            obj = obj.get(part, "default") if isinstance(obj, Mapping) else "default"
        values.append(SourcedValue(str(key), value_text(obj), str(source)))
    name = str(table.get("name", ""))
    level = name.rpartition("-")[2] if sources else ""
    realism = table.get("realism") or {}
    caveats = realism.get("easier_than_real", ()) if isinstance(realism, Mapping) else ()
    return Realism(level, tuple(values), tuple(str(c) for c in caveats))


def read_realism(path: str | os.PathLike[str]) -> Realism:
    """The realism of the simulation config written to a scene's ``truth/config.toml``.

    Raises:
        MissingFileError: If the file does not exist.
        InputError: If it is not valid TOML.
    """
    return realism_from_table(read_toml(path, "simulation config"))
