"""The configuration reference, generated from the settings models.

Walks the pydantic models of :class:`planetref.pipeline.config.GeorefConfig` (the
``--config`` file of ``georef``/``compare``/``demo``) and
:class:`planetref.simulate.config.SimulationConfig` (the simulator's presets and override
files): every key, its type, default, unit and description. Descriptions come from a
field's ``description`` or else from the ``Attributes:`` section of its model's docstring
(Google style); units from the key's suffix (``_m`` metres, ...) when the description names
none. Nothing here is typed by hand, so a renamed key changes the page.
"""

from __future__ import annotations

import enum
import inspect
import re
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

# Unit suffixes of key names (the convention stated in planetref.simulate.config).
UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_rad_s2", "rad/s²"),
    ("_rad_s", "rad/s"),
    ("_m_s", "m/s"),
    ("_urad", "µrad"),
    ("_mrad", "mrad"),
    ("_rad", "rad"),
    ("_deg", "degrees"),
    ("_mm", "mm"),
    ("_km", "km"),
    ("_ms", "ms"),
    ("_hz", "Hz"),
    ("_ppm", "ppm"),
    ("_ref_px", "reference pixels"),
    ("_px", "pixels"),
    ("_e", "electrons"),
    ("_mb", "MB"),
    ("_m", "metres"),
    ("_s", "seconds"),
)


@dataclass(frozen=True)
class Key:
    """One documented key.

    Attributes:
        path: Dotted key, e.g. ``frontend.tile_size_ref_px`` (``[]`` marks an array of
            tables).
        type: The type as written in the reference.
        default: The default as TOML-like text (``-`` where the key is required).
        unit: Unit of the value (empty where it has none).
        description: What the key does.
        is_table: The key is a table (its keys follow).
    """

    path: str
    type: str
    default: str
    unit: str
    description: str
    is_table: bool


def _attribute_docs(model: type) -> dict[str, str]:
    """``{name: description}`` from the ``Attributes:`` sections of a class and its bases."""
    out: dict[str, str] = {}
    for cls in reversed(model.__mro__):
        if cls.__module__.split(".")[0] in {"pydantic", "builtins"}:
            continue  # BaseModel's own docstring documents its internals
        doc = inspect.getdoc(cls) if cls.__doc__ else None
        if not doc:
            continue
        lines = doc.splitlines()
        inside = False
        current: str | None = None
        for line in lines:
            if re.match(r"^(Attributes|Args|Keys):\s*$", line):
                inside = True
                current = None
                continue
            if not inside:
                continue
            if line and not line.startswith(" "):
                inside = False  # the next section (or prose) starts
                current = None
                continue
            m = re.match(r"^    (\w+)(?: \([^)]*\))?:\s*(.*)$", line)
            if m:
                current = m.group(1)
                out[current] = m.group(2).strip()
            elif current and line.strip():
                out[current] = f"{out[current]} {line.strip()}"
    return out


def _models_in(annotation: object) -> list[type[BaseModel]]:
    """The pydantic models an annotation holds (directly, in a union, list or tuple)."""
    if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in typing.get_args(annotation):
        out.extend(_models_in(arg))
    return out


def _is_array(annotation: object) -> bool:
    origin = typing.get_origin(annotation)
    if origin in (list, tuple):
        return True
    return any(_is_array(a) for a in typing.get_args(annotation) if a is not type(None))


def type_text(annotation: object) -> str:
    """A short, readable spelling of a type annotation."""
    if annotation is type(None):
        return "none"
    if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
        return "table"
    if inspect.isclass(annotation) and issubclass(annotation, enum.Enum):
        return " | ".join(repr(m.value) for m in annotation)
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_text(a) for a in args)
    if origin is typing.Annotated:
        return type_text(args[0])
    if origin in (list, tuple, set, frozenset):
        if origin is tuple and args and args[-1] is not Ellipsis:
            return "[" + ", ".join(type_text(a) for a in args) + "]"
        inner = type_text(args[0]) if args else "any"
        return f"array of {inner}"
    if origin is dict:
        return "table"
    if annotation is typing.Any:
        return "any"
    if inspect.isclass(annotation):
        return {"str": "string", "int": "integer", "float": "float", "bool": "boolean"}.get(
            annotation.__name__, annotation.__name__
        )
    return str(annotation).replace("typing.", "")


def _toml(value: object) -> str:
    """A default value as TOML-like text."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return _toml(value.value)
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    if isinstance(value, BaseModel):
        return "table"
    return str(value)


def unit_of(name: str, description: str) -> str:
    """The unit of a key: from its name's suffix, else the first unit the description names."""
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    m = re.search(
        r"\((metres|meters|pixels|reference pixels|CCD pixels|seconds|degrees|radians|"
        r"mm|MiB|MB|px|m)[),;]",
        description,
    )
    return m.group(1) if m else ""


def walk(model: type[BaseModel], prefix: str = "") -> Iterator[Key]:
    """Every key of ``model`` and its sub-tables, depth first, in declaration order."""
    docs = _attribute_docs(model)
    for name, field in model.model_fields.items():
        key = field.alias or name
        path = f"{prefix}{key}"
        description = (field.description or docs.get(name, "")).strip()
        if field.default_factory is not None:
            try:
                default_value = field.default_factory()  # type: ignore[call-arg]
            except TypeError:
                default_value = None
        else:
            default_value = field.default
        sub = _models_in(field.annotation)
        required = default_value is PydanticUndefined
        if sub:
            array = _is_array(field.annotation)
            shown = f"{path}[]" if array else path
            kind = "array of tables" if array else "table"
            if type(None) in typing.get_args(field.annotation):
                kind += " | none"
            default = "-" if required else ("table" if sub and not array else _toml(default_value))
            if isinstance(default_value, (list, tuple)) and not default_value:
                default = "[]"
            elif isinstance(default_value, (list, tuple)):
                default = f"{len(default_value)} tables"
            elif default_value is None:
                default = "none"
            yield Key(shown, kind, default, "", description, True)
            seen: set[type] = set()
            for m in sub:
                if m in seen:
                    continue
                seen.add(m)
                yield from walk(m, f"{shown}.")
            continue
        default = "-" if required else _toml(default_value)
        yield Key(
            path,
            type_text(field.annotation),
            default,
            unit_of(name, description),
            description,
            False,
        )


def _cell(text: str) -> str:
    # Sphinx roles of the docstrings (:class:`~a.b.C`) read as plain code here
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("|", "\\|").replace("\n", " ")


def markdown_tables(model: type[BaseModel], heading_level: int = 3) -> str:
    """One Markdown table per TOML table of ``model`` (the top level first)."""
    keys = list(walk(model))
    groups: dict[str, list[Key]] = {"": []}
    for k in keys:
        parent = k.path.rsplit(".", 1)[0] if "." in k.path else ""
        groups.setdefault(parent, []).append(k)
    tables = {k.path: k for k in keys if k.is_table}
    out: list[str] = []
    hashes = "#" * heading_level
    for parent, members in groups.items():
        leaves = [k for k in members if not k.is_table]
        subtables = [k for k in members if k.is_table]
        title = f"`[{parent}]`" if parent else "Top level"
        out.append(f"{hashes} {title}\n")
        if parent in tables and tables[parent].description:
            out.append(_cell(tables[parent].description) + "\n")
        if subtables:
            names = ", ".join(f"`[{t.path}]`" for t in subtables)
            out.append(f"Sub-tables: {names}.\n")
        if leaves:
            out.append("| key | type | default | unit | description |")
            out.append("|---|---|---|---|---|")
            for k in leaves:
                name = k.path.rsplit(".", 1)[-1]
                out.append(
                    f"| `{name}` | {_cell(k.type)} | `{_cell(k.default)}` | {_cell(k.unit)} "
                    f"| {_cell(k.description) or '*(no description)*'} |"
                )
            out.append("")
        elif not subtables and not parent:
            continue
    return "\n".join(out).rstrip() + "\n"


def page() -> str:
    """The whole configuration reference page (Markdown)."""
    from planetref.pipeline.config import GeorefConfig
    from planetref.simulate.config import SimulationConfig

    return (
        "# Configuration reference\n\n"
        "*Generated from the settings models by `docs/gen/config_ref.py` at every build; "
        "do not edit.*\n\n"
        "Every settings table is frozen and rejects unknown keys: a misspelt key is refused "
        "with one line naming the file, the dotted key and the valid keys of its table. "
        "Values in TOML; `none` means the key is left out (or set to its null default).\n\n"
        "## Run configuration (`--config FILE.toml`)\n\n"
        "Read by `planetref georef`, `compare` and `demo` "
        "(`planetref.pipeline.config.GeorefConfig`). "
        "Everything left out takes the default shown. `[matchers.NAME]` tables hold the "
        "options of one matcher (keyword arguments of its constructor; "
        "`planetref matchers` and `Matcher.option_names()` list them). The resolved "
        "configuration is written into every run folder as `config.json`.\n\n"
        + markdown_tables(GeorefConfig)
        + "\n## Simulation (`planetref simulate --config FILE.toml`)\n\n"
        "The simulator's presets (`tiny`, `hiric-strip`, `hiric`) are TOML files of this "
        "structure (`planetref.simulate.config.SimulationConfig`); an override file is "
        "merged into the preset table by table (arrays of tables replace the preset's "
        "whole array). The defaults below are the models' own, before a preset is laid "
        "over them.\n\n" + markdown_tables(SimulationConfig)
    )


if __name__ == "__main__":
    print(page())
