"""The settings toolkit: strict frozen models, one-line errors naming the file, deep merge."""

from __future__ import annotations

import pytest
from pydantic import Field, ValidationError

from planetref.errors import InputError
from planetref.runtime.settings import Settings, deep_merge, validate_settings


class Inner(Settings):
    size: int = Field(3, ge=1)


class Outer(Settings):
    name: str = "x"
    inner: Inner = Inner()


def test_models_are_frozen_and_strict():
    o = Outer()
    with pytest.raises(ValidationError):
        o.name = "y"  # type: ignore[misc]
    with pytest.raises(ValidationError):
        Outer(nmae="y")  # type: ignore[call-arg]


def test_one_line_errors_name_file_key_and_valid_keys():
    with pytest.raises(InputError) as ei:
        validate_settings(Outer, {"inner": {"sise": 3}}, source="run.toml")
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith("run.toml")
    assert "inner.sise" in msg and "valid keys: size" in msg
    with pytest.raises(InputError, match=r"'inner.size': Input should be greater than or equal"):
        validate_settings(Outer, {"inner": {"size": 0}})
    assert validate_settings(Outer, {"inner": {"size": 7}}).inner.size == 7
    assert validate_settings(Outer, None) == Outer()


def test_deep_merge_merges_tables_and_replaces_the_rest():
    base = {"a": {"b": 1, "c": [1, 2]}, "d": 1}
    over = {"a": {"c": [3]}, "e": {"f": 2}}
    out = deep_merge(base, over)
    assert out == {"a": {"b": 1, "c": [3]}, "d": 1, "e": {"f": 2}}
    assert base == {"a": {"b": 1, "c": [1, 2]}, "d": 1}  # inputs untouched
    out["e"]["f"] = 9
    assert over["e"]["f"] == 2


def test_bad_values_name_the_value_and_non_tables_are_refused():
    with pytest.raises(InputError, match=r"'inner.size': Input should be .* \(got 0\)"):
        validate_settings(Outer, {"inner": {"size": 0}}, source="run.toml")
    with pytest.raises(InputError, match=r"run.toml: invalid thing: expected a table, got list"):
        validate_settings(Outer, [1, 2], source="run.toml", what="thing")  # type: ignore[arg-type]


def test_every_config_uses_the_one_translator_with_the_full_key():
    from planetref.adjust.config import validate_config as adjust_config
    from planetref.pipeline.config import config_from_mapping
    from planetref.simulate.config import validate_config as simulation_config

    with pytest.raises(InputError) as ei:
        config_from_mapping({"adjust": {"solver": {"los": "huber"}}}, source="g.toml")
    msg = str(ei.value)
    assert msg.startswith("g.toml: invalid settings: unknown key 'adjust.solver.los'")
    assert "(valid keys: " in msg and "loss" in msg
    with pytest.raises(InputError, match=r"invalid adjustment configuration: 'solver.loss': "):
        adjust_config({"solver": {"loss": "squared"}})
    with pytest.raises(InputError, match=r"invalid simulation config: unknown key 'colour' \("):
        simulation_config({"colour": 1})


def _package_modules():
    import ast
    from pathlib import Path

    import planetref

    root = Path(planetref.__file__).parent
    for path in sorted(root.rglob("*.py")):
        yield path.relative_to(root).as_posix(), ast.parse(path.read_text(encoding="utf-8"))


def test_settings_is_the_only_pydantic_base_and_error_translator():
    # Every settings model derives from planetref.runtime.settings.Settings (frozen, unknown keys
    # rejected) and every output record from its Record: no other module builds a pydantic
    # base, sets a model_config, or reads a ValidationError's errors() itself.
    import ast

    offenders = []
    for name, tree in _package_modules():
        if name == "runtime/settings.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "pydantic":
                bad = {a.name for a in node.names} & {"BaseModel", "ConfigDict"}
                offenders += [f"{name}: imports {b}" for b in sorted(bad)]
            elif isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "model_config" for t in node.targets
            ):
                offenders.append(f"{name}: sets model_config")
            elif (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "errors"
                and not node.args
            ):
                offenders.append(f"{name}:{node.lineno}: calls .errors()")
    assert offenders == []
