"""Every settings key is in the generated configuration reference, with its real default."""

from __future__ import annotations

import inspect
import re
import tomllib
import typing

import config_ref
import pytest
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from planetref.pipeline.config import GeorefConfig
from planetref.simulate.config import SimulationConfig


def _sub_models(annotation) -> list[type[BaseModel]]:
    if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in typing.get_args(annotation) for m in _sub_models(a)]


def _keys(model: type[BaseModel], table: str = ""):
    """(table, key, field) of every leaf key, walked independently of the generator."""
    for name, field in model.model_fields.items():
        subs = _sub_models(field.annotation)
        if subs:
            array = typing.get_origin(field.annotation) in (list, tuple) or any(
                typing.get_origin(a) in (list, tuple) for a in typing.get_args(field.annotation)
            )
            sub_table = f"{table}.{name}" if table else name
            if array:
                sub_table += "[]"
            for m in dict.fromkeys(subs):
                yield from _keys(m, sub_table)
        else:
            yield table, name, field


def _sections(page: str) -> dict[str, str]:
    """The text under each ``### `[table]``` heading of one half of the page."""
    out: dict[str, str] = {}
    parts = re.split(r"^### (.+)$", page, flags=re.M)
    for title, body in zip(parts[1::2], parts[2::2], strict=True):
        m = re.fullmatch(r"`\[(.+)\]`", title.strip())
        out[m.group(1) if m else ""] = body
    return out


PAGE = config_ref.page()
RUN_HALF, SIM_HALF = PAGE.split("## Simulation", 1)


@pytest.mark.parametrize(
    ("model", "half"), [(GeorefConfig, RUN_HALF), (SimulationConfig, SIM_HALF)]
)
def test_every_key_is_documented_with_its_default(model, half):
    sections = _sections(half)
    keys = list(_keys(model))
    assert len(keys) > 30  # the walk found the settings (not an empty model)
    missing, undocumented, wrong_default = [], [], []
    for table, name, field in keys:
        body = sections.get(table)
        row = None
        if body is not None:
            row = next((ln for ln in body.splitlines() if ln.startswith(f"| `{name}` |")), None)
        if row is None:
            missing.append(f"{table}.{name}")
            continue
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", row)[1:-1]]
        if not cells[4] or "no description" in cells[4]:
            undocumented.append(f"{table}.{name}")
        default = field.default
        if default is PydanticUndefined or field.default_factory is not None:
            continue
        if isinstance(default, (bool, int, float, str)) or default is None:
            text = cells[2].strip("`").replace("\\|", "|")
            shown = None if text == "none" else tomllib.loads(f"v = {text}")["v"]
            if shown != default:
                wrong_default.append(f"{table}.{name}: {text} != {default!r}")
    assert not missing, f"keys missing from the configuration reference: {missing}"
    assert not undocumented, f"keys without a description: {undocumented}"
    assert not wrong_default, wrong_default


def test_units_come_from_the_key_names():
    rows = {k.path: k for k in config_ref.walk(GeorefConfig)}
    assert rows["frontend.uncertainty_m"].unit == "metres"
    assert rows["frontend.tile_size_ref_px"].unit == "reference pixels"
    assert rows["mcp.sigma_px"].unit == "pixels"
    assert rows["frontend.coarse"].unit == ""


def test_attribute_docs_follow_continuation_lines():
    class Example(BaseModel):
        """An example.

        Attributes:
            alpha_m: First line
                and its continuation.
            beta: Second.

        Raises:
            Nothing here.
        """

        alpha_m: float = 1.5
        beta: int = 2

    docs = config_ref._attribute_docs(Example)
    assert docs == {"alpha_m": "First line and its continuation.", "beta": "Second."}
