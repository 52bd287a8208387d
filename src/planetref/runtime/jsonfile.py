"""Reading JSON files (cameras, ISDs) with one-line errors, like the TOML reader."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from planetref.errors import InputError, MissingFileError

__all__ = ["read_json"]


def read_json(path: str | os.PathLike[str], what: str = "file") -> Any:
    """The decoded content of a JSON file.

    Args:
        path: The file.
        what: What the file is, for the messages (e.g. ``"ISD"``).

    Raises:
        MissingFileError: ``"<what> not found"``, naming the path.
        InputError: The file cannot be read, is not valid JSON (with the line and column)
            or is nested too deeply to be decoded, naming the path.
    """
    p = Path(path)
    if not p.is_file():
        raise MissingFileError(f"{what} not found", path=p)
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(
            f"not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})", path=p
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the {what} ({exc})", path=p) from None
    except RecursionError:
        raise InputError(f"the {what} is nested too deeply to be read", path=p) from None
