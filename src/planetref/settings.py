"""The settings toolkit: one frozen pydantic base, one error translator, one deep merge.

Every settings model of planetref derives from :class:`Settings` (frozen, unknown keys
rejected); :func:`validate_settings` turns a mapping (e.g. a TOML table) into a model and
any pydantic error into ONE line naming the file, the key and the valid keys of the table
where the problem is (:func:`describe_validation_error`); :func:`deep_merge` lays
overrides over defaults table by table.

Example::

    class Tiles(Settings):
        size: int = Field(256, ge=32)

    validate_settings(Tiles, {"sise": 3}, source="run.toml")
    # InputError: run.toml: invalid settings: unknown key 'sise' (valid keys: size)
"""

from __future__ import annotations

import copy
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from planetref.errors import InputError

__all__ = ["Settings", "deep_merge", "describe_validation_error", "model_at", "validate_settings"]

M = TypeVar("M", bound=BaseModel)


class Settings(BaseModel):
    """Base of every settings model: frozen (hashable, never mutated), unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of ``base`` with ``over`` laid over it.

    Tables (mappings) merge key by key, recursively; any other value (numbers, strings,
    arrays, arrays of tables) replaces the base value. Neither input is modified.
    """
    out = {k: copy.deepcopy(v) for k, v in base.items()}
    for key, value in over.items():
        old = out.get(key)
        if isinstance(value, Mapping) and isinstance(old, Mapping):
            out[key] = deep_merge(old, value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def model_at(loc: tuple[Any, ...], root: type[BaseModel]) -> type[BaseModel] | None:
    """The model class holding the field at ``loc`` (None when it is not a model field)."""
    model: type[BaseModel] = root
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        fld = model.model_fields.get(str(part))
        if fld is None:
            return None
        nxt = None
        for cand in (fld.annotation, *typing.get_args(fld.annotation)):
            for c in (cand, *typing.get_args(cand)):
                if isinstance(c, type) and issubclass(c, BaseModel):
                    nxt = c
                    break
            if nxt is not None:
                break
        if nxt is None:
            return None
        model = nxt
    return model


def describe_validation_error(exc: ValidationError, root: type[BaseModel]) -> tuple[str, str]:
    """One line describing every problem of ``exc``, and the dotted key of the first.

    Unknown keys come with the valid keys of their table; a bad value with pydantic's
    reason.

    Returns:
        ``(message, key)``; ``key`` is ``""`` for a problem with the whole document.
    """
    parts = []
    first = ""
    for err in exc.errors():
        loc = tuple(p for p in err.get("loc", ()) if not str(p).startswith("function-"))
        where = ".".join(str(p) for p in loc)
        first = first or where
        model = model_at(loc, root) if loc else root
        valid = ", ".join(model.model_fields) if model is not None else ""
        if err.get("type") == "extra_forbidden":
            parts.append(f"unknown key '{where}' (valid keys: {valid})")
        else:
            msg = str(err.get("msg", "invalid value")).replace("\n", " ")
            parts.append(f"'{where}': {msg}" if where else msg)
    return "; ".join(parts), first


def validate_settings(
    model: type[M], values: Mapping[str, Any] | None, *, source: str | None = None
) -> M:
    """Validate a mapping into a settings model, with a one-line error.

    Args:
        model: The settings class.
        values: The mapping (None: the defaults).
        source: The file the values came from (named in the error).

    Raises:
        InputError: Unknown keys (listing the valid ones) or bad values, naming the file.
    """
    try:
        return model.model_validate(dict(values or {}))
    except ValidationError as exc:
        message, _ = describe_validation_error(exc, model)
        raise InputError(f"invalid settings: {message}", path=source) from None
    except InputError as exc:
        # A validator of a nested model raised one already: add the file.
        if source is None or exc.path is not None:
            raise
        raise InputError(str(exc), path=source) from None
