"""Explicit download of official weight files (``planetref weights download``).

Nothing else in planetref downloads. A file is fetched from its official URL (then its
mirrors, in :data:`~planetref.matching.weights.WEIGHT_FILES` order) into the weights
directory through a temporary file in that directory, hashed while it streams, and renamed
into place only when its sha256 (or git blob id) is the official one; a mismatch is refused
and leaves nothing behind. Files without a reference checksum are refused unless the caller
says ``allow_unverified``.
"""

from __future__ import annotations

import hashlib
import urllib.error
import urllib.request
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

from planetref.errors import WeightsError
from planetref.matching.weights import WEIGHT_FILES, WeightFile, weights_dir
from planetref.runtime.atomic import atomic_path

__all__ = ["download_weight", "weight_names"]

USER_AGENT = "planetref-weights/1"


def weight_names(spec: Sequence[str]) -> list[str]:
    """Expand ``all``, matcher names and cache file names into cache file names.

    Raises:
        WeightsError: A name that is neither (the message lists the valid ones).
    """
    from planetref.matching.registry import MATCHERS

    out: list[str] = []
    for item in spec:
        if item == "all":
            out += list(WEIGHT_FILES)
        elif item in MATCHERS:
            out += list(MATCHERS[item].weights)
        elif item in WEIGHT_FILES:
            out.append(item)
        else:
            raise WeightsError(
                f"unknown weight or matcher name {item!r}; valid: 'all', matchers "
                f"{', '.join(MATCHERS)}, files {', '.join(WEIGHT_FILES)}"
            )
    return list(dict.fromkeys(out))


def _fetch(url: str, tmp: Path, info: WeightFile, timeout: float, progress: bool) -> str:
    """Stream ``url`` into ``tmp``; return ``sha256:blob`` hex digests."""
    from tqdm import tqdm

    request = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
    with urllib.request.urlopen(request, timeout=timeout) as response:
        total = response.headers.get("Content-Length")
        size = int(total) if total and total.isdigit() else info.size
        chunks = []
        sha = hashlib.sha256()
        with (
            open(tmp, "wb") as fh,
            tqdm(
                total=size,
                unit="B",
                unit_scale=True,
                desc=info.name,
                disable=not progress,
                leave=False,
            ) as bar,
        ):
            while True:
                chunk = response.read(1 << 20)
                if not chunk:
                    break
                fh.write(chunk)
                sha.update(chunk)
                chunks.append(len(chunk))
                bar.update(len(chunk))
    n = sum(chunks)
    blob = hashlib.sha1(f"blob {n}\0".encode(), usedforsecurity=False)
    with open(tmp, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            blob.update(chunk)
    return f"{sha.hexdigest()}:{blob.hexdigest()}"


def download_weight(
    name: str,
    weights_dir_: str | PathLike[str] | None = None,
    *,
    urls: Sequence[str] | None = None,
    allow_unverified: bool = False,
    overwrite: bool = False,
    timeout: float = 60.0,
    progress: bool = True,
) -> Path:
    """Fetch one weight file from its official URL into the weights directory.

    Args:
        name: Cache file name (a key of :data:`~planetref.matching.weights.WEIGHT_FILES`).
        weights_dir_: Weights directory (see :func:`~planetref.matching.weights.weights_dir`);
            created if needed.
        urls: URLs to try instead of the official URL and mirrors (tests, local mirrors).
        allow_unverified: Accept a file for which no reference checksum is known.
        overwrite: Replace a file already there (default: keep it and return its path).
        timeout: Network timeout per request, seconds.
        progress: Show a progress bar (tqdm, on stderr).

    Returns:
        Path of the verified file.

    Raises:
        WeightsError: Unknown name, no reference checksum (without ``allow_unverified``),
            every URL failing, or a checksum mismatch (nothing is written then).
    """
    info = WEIGHT_FILES.get(name)
    if info is None:
        raise WeightsError(f"unknown weight file {name!r}; known: {', '.join(WEIGHT_FILES)}")
    if not (info.sha256 or info.git_blob) and not allow_unverified:
        raise WeightsError(
            f"{name}: no reference sha256 is known, so a download cannot be verified; "
            "pass --unverified to accept it anyway"
        )
    target = weights_dir(weights_dir_) / name
    if target.is_file() and not overwrite:
        return target
    errors = []
    for url in urls if urls is not None else (info.url, *info.mirrors):
        try:
            with atomic_path(target) as tmp:
                digest = _fetch(url, tmp, info, timeout, progress)
                sha, blob = digest.split(":")
                if (info.sha256 or info.git_blob) and sha != info.sha256 and blob != info.git_blob:
                    raise WeightsError(
                        f"{name} from {url} has sha256 {sha}, expected {info.sha256}: refused, "
                        "nothing written"
                    )
            return target
        except (urllib.error.URLError, OSError, ValueError) as exc:
            errors.append(f"{url}: {exc}")
    raise WeightsError(f"{name}: download failed from every URL ({'; '.join(errors)})")
