"""Reading TOML files (configurations, manifests, networks) with one-line errors."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any

from planetref.errors import InputError, MissingFileError

__all__ = ["read_toml"]


def read_toml(path: str | os.PathLike[str], what: str = "file") -> dict[str, Any]:
    """The tables of a TOML file.

    Args:
        path: The file.
        what: What the file is, for the missing-file message (e.g. ``"scene manifest"``).

    Raises:
        MissingFileError: ``"<what> not found"``, naming the path.
        InputError: The file cannot be read or is not valid TOML, naming the path.
    """
    p = Path(path)
    if not p.is_file():
        raise MissingFileError(f"{what} not found", path=p)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML ({exc})", path=p) from None
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc})", path=p) from None
    except RecursionError:
        raise InputError(f"the {what} is nested too deeply to be read", path=p) from None
