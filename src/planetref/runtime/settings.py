"""The settings toolkit: one frozen pydantic base, one error translator, one deep merge.

Every settings model of planetref derives from :class:`Settings` (frozen, unknown keys
rejected); :func:`validate_settings` turns a mapping (e.g. a TOML table) into a model and
any pydantic error into ONE line naming the file, the key and the valid keys of the table
where the problem is (:func:`describe_validation_error`, built on
:func:`validation_problems`, which file readers use to name the field at fault);
:func:`deep_merge` lays overrides over defaults table by table. There is no other
pydantic error translator and no other deep merge in planetref.

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
from typing import Any, NamedTuple, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from planetref.errors import InputError

__all__ = [
    "Problem",
    "Record",
    "Settings",
    "deep_merge",
    "describe_validation_error",
    "model_at",
    "validate_settings",
    "validation_problems",
]

M = TypeVar("M", bound=BaseModel)


class Settings(BaseModel):
    """Base of every settings model: frozen (hashable, never mutated), unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class Record(BaseModel):
    """Base of every output record (report.json's blocks): unknown keys rejected.

    Not frozen: a record is filled in as a run goes, and what was set is what is written.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=False)


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


class Problem(NamedTuple):
    """One problem of a pydantic error.

    Attributes:
        key: Dotted key at fault (``""``: the whole document).
        text: What is wrong, without the key (``unknown key (valid keys: a, b)``,
            ``Input should be ... (got 'x')``).
        unknown: The key is not a field of its table.
    """

    key: str
    text: str
    unknown: bool


def validation_problems(exc: ValidationError, root: type[BaseModel]) -> list[Problem]:
    """Every problem of a pydantic error, in pydantic's order.

    The text of an unknown key lists the valid keys of its table; that of a bad value
    gives pydantic's reason and the value (shortened to 60 characters; not for whole
    tables), plus the valid keys of the table when the key is not one of its fields.

    Args:
        exc: The pydantic error.
        root: The model that was validated (to find the table of each location).

    Returns:
        The :class:`Problem` of each error.
    """
    out = []
    for err in exc.errors():
        loc = tuple(p for p in err.get("loc", ()) if not str(p).startswith("function-"))
        where = ".".join(str(p) for p in loc)
        model = model_at(loc, root) if loc else root
        valid = ", ".join(model.model_fields) if model is not None else "?"
        if err.get("type") == "extra_forbidden":
            out.append(Problem(where, f"unknown key (valid keys: {valid})", True))
            continue
        text = str(err.get("msg", "invalid value")).replace("\n", " ")
        value = err.get("input")
        if "input" in err and err.get("type") != "missing" and not isinstance(value, Mapping):
            shown = repr(value)
            text += f" (got {shown if len(shown) <= 60 else shown[:57] + '...'})"
        if model is not None and loc and str(loc[-1]) not in model.model_fields:
            text += f" (valid keys: {valid})"
        out.append(Problem(where, text, False))
    return out


def describe_validation_error(exc: ValidationError, root: type[BaseModel]) -> tuple[str, str]:
    """One line describing every problem of ``exc``, and the dotted key of the first.

    Unknown keys read ``unknown key 'a.b' (valid keys: ...)``, bad values
    ``'a.b': reason (got value)`` (see :func:`validation_problems`).

    Returns:
        ``(message, key)``; ``key`` is ``""`` for a problem with the whole document.
    """
    problems = validation_problems(exc, root)
    parts = []
    for p in problems:
        if p.unknown:
            parts.append(f"unknown key '{p.key}' {p.text.removeprefix('unknown key ')}")
        else:
            parts.append(f"'{p.key}': {p.text}" if p.key else p.text)
    return "; ".join(parts), problems[0].key if problems else ""


def validate_settings(
    model: type[M],
    values: Mapping[str, Any] | None,
    *,
    source: str | None = None,
    what: str = "settings",
) -> M:
    """Validate a mapping into a settings model, with a one-line error.

    Args:
        model: The settings class.
        values: The mapping (None: the defaults).
        source: The file the values came from (named in the error).
        what: What the values are, for the message (``invalid <what>: ...``).

    Raises:
        InputError: Unknown keys (listing the valid ones) or bad values, naming the file.
    """
    if values is not None and not isinstance(values, Mapping):
        raise InputError(
            f"invalid {what}: expected a table, got {type(values).__name__}", path=source
        )
    try:
        return model.model_validate(dict(values or {}))
    except ValidationError as exc:
        message, _ = describe_validation_error(exc, model)
        raise InputError(f"invalid {what}: {message}", path=source) from None
    except InputError as exc:
        # A validator of a nested model raised one already: add the file.
        if source is None or exc.path is not None:
            raise
        raise InputError(str(exc), path=source) from None
