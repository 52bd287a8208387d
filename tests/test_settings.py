"""The settings toolkit: strict frozen models, one-line errors naming the file, deep merge."""

from __future__ import annotations

import pytest
from pydantic import Field, ValidationError

from planetref.errors import InputError
from planetref.settings import Settings, deep_merge, validate_settings


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
