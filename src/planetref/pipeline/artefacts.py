"""The artefacts a georef run's stages hand each other, and the adjustment's resume.

Per strip: :class:`~planetref.control.networks.StripMcps` (the matching stage's MCPs,
check flags and ground sigmas) -> :class:`~planetref.adjust.result.AdjustmentResult` ->
:class:`StripProducts` (the files written) and :class:`StripOutcome` (the strip's report
blocks and residuals) -> :class:`~planetref.report.model.GeorefReport`.

The adjustment is the one costly step after the matching (whose tiles resume from their
journal inside the front end): :func:`solve_or_reload` saves each
:class:`AdjustmentResult` in the run folder (``<strip>/adjustment/result.pkl``) beside a
fingerprint of its inputs (``result.inputs.sha256``: the network, the settings, the
planetref version). A re-run whose inputs have the same fingerprint reloads it instead
of solving; a re-run without the file (deleted) or with other inputs solves again, and
everything after the adjustment is written again either way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import pickle
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from planetref import __version__

if TYPE_CHECKING:  # pragma: no cover
    from planetref.adjust.config import AdjustConfig
    from planetref.adjust.result import AdjustmentResult
    from planetref.control.network import Network
    from planetref.report.model import StripReport

__all__ = [
    "RESULT_NAME",
    "RESULT_STAMP",
    "StripOutcome",
    "StripProducts",
    "adjustment_fingerprint",
    "load_result",
    "solve_or_reload",
]

log = logging.getLogger("planetref.pipeline.georef")


class RunFiles(Protocol):
    """What the adjustment's resume needs of a run folder: recorded paths inside it.

    A :class:`~planetref.pipeline.rundir.RunDir` is one.
    """

    def file(self, *parts: str) -> Path:
        """A path inside the run folder, recorded as the run's."""
        ...


#: The saved adjustment of a strip (or a campaign) inside its ``adjustment`` folder.
RESULT_NAME = "result.pkl"
#: Its inputs' fingerprint, beside it.
RESULT_STAMP = "result.inputs.sha256"


@dataclass
class StripProducts:
    """The files a strip's run wrote (``GeorefOutcome.files[<strip>]``).

    Attributes:
        mcps: The MCP table (``mcps.parquet``, ``mcps.gpkg``).
        adjustment: The adjustment's outputs (:func:`~planetref.report.adjustment.
            write_outputs`: name -> path, ``cameras`` -> id -> paths, ``plots``).
        exports: ASP GCP and ISIS control network files (name -> path); None: not made
            for this strip (a joint adjustment writes the campaign's).
        ortho: Orthoimages and mosaic; None: orthoimages disabled.
        isd: The adjusted camera's CSM ISDs.
        ccd_overlap: The tie points between its overlapping CCDs (``ccd_overlap_ties.csv``);
            None: not made (``[frontend.ccd_overlap]`` off).
    """

    mcps: list[str] = field(default_factory=list)
    adjustment: dict[str, Any] = field(default_factory=dict)
    exports: dict[str, str] | None = None
    ortho: list[str] | None = None
    isd: list[str] = field(default_factory=list)
    ccd_overlap: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The files by kind (the kinds made)."""
        out: dict[str, Any] = {"mcps": self.mcps, "adjustment": self.adjustment}
        if self.exports is not None:
            out["exports"] = self.exports
        if self.ortho is not None:
            out["ortho"] = self.ortho
        out["isd"] = self.isd
        if self.ccd_overlap is not None:
            out["ccd_overlap"] = self.ccd_overlap
        return out


@dataclass
class StripOutcome:
    """A strip after its adjustment and outputs.

    Attributes:
        report: Its blocks of report.json (``strips.<id>``).
        products: The files written.
        residual: Its observations' ``(line, sample)`` residuals after the adjustment (px).
        inlier: Their inlier flags.
    """

    report: StripReport
    products: StripProducts
    residual: NDArray[np.float64]
    inlier: NDArray[np.bool_]


def _update_array(h: Any, a: Any) -> None:
    arr = np.ascontiguousarray(np.asarray(a))
    h.update(f"{arr.dtype.str}{arr.shape}".encode())
    if arr.dtype.kind in "OU":
        h.update(json.dumps(arr.astype(str).tolist()).encode())
    else:
        h.update(arr.tobytes())


def adjustment_fingerprint(network: Network, config: AdjustConfig) -> str | None:
    """SHA-256 of what an adjustment is computed from: its network, settings and code.

    The network's observations, points, sigmas and flags, its initial cameras
    (their ``to_dict``), the settings and planetref's version. ``None`` when a camera
    cannot describe itself (no ``to_dict``): such an adjustment is never reloaded.
    """
    h = hashlib.sha256()
    h.update(f"planetref {__version__}\n".encode())
    h.update(config.model_dump_json().encode())
    for f in dataclasses.fields(network):
        value = getattr(network, f.name)
        h.update(f"\n{f.name}:".encode())
        if f.name == "cameras":
            for cam in value:
                to_dict = getattr(cam, "to_dict", None)
                if to_dict is None:
                    return None
                h.update(json.dumps(to_dict(), sort_keys=True, default=repr).encode())
        elif isinstance(value, np.ndarray | list | tuple):
            _update_array(h, value)
        else:
            h.update(repr(value).encode())
    return h.hexdigest()


def solve_or_reload(
    run: RunFiles,
    folder: tuple[str, ...],
    network: Network,
    config: AdjustConfig,
    solve: Callable[[Network, AdjustConfig], AdjustmentResult],
) -> tuple[AdjustmentResult, bool]:
    """The adjustment of ``network``: reloaded from the run folder when its inputs match.

    Args:
        run: The run folder.
        folder: The adjustment's folder inside it (``(<strip>, "adjustment")``).
        network: The network to adjust.
        config: The adjustment's settings.
        solve: The adjustment (:func:`planetref.adjust.api.adjust`).

    Returns:
        ``(result, reloaded)``.
    """
    from planetref.runtime.atomic import write_bytes_atomic, write_text_atomic

    digest = adjustment_fingerprint(network, config)
    path = run.file(*folder, RESULT_NAME)
    stamp = run.file(*folder, RESULT_STAMP)
    recorded = _stamp_of(stamp)
    if digest is not None and recorded is not None and recorded[0] == digest and path.is_file():
        try:
            result = _read_result(path, recorded[1])
        except _UNREADABLE as exc:
            log.warning("%s: cannot reload (%s); adjusting again", path, exc)
        else:
            log.info("%s: inputs unchanged, adjustment reloaded", "/".join(folder))
            return result, True
    stamp.unlink(missing_ok=True)  # never a stamp beside another run's result
    result = solve(network, config)
    if digest is not None:
        data = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
        write_bytes_atomic(path, data)
        write_text_atomic(stamp, f"{digest}\n{hashlib.sha256(data).hexdigest()}\n")
    return result, False


_UNREADABLE = (OSError, ValueError, pickle.UnpicklingError, EOFError, AttributeError, ImportError)


def _read_result(path: Path, sha256: str) -> AdjustmentResult:
    """Unpickle a saved adjustment whose bytes have the recorded digest.

    Only the bytes a run wrote are unpickled: their own digest is in the stamp (a
    truncated, foreign or edited file raises ``ValueError``, never loads).
    """
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != sha256:
        raise ValueError("its content is not the one recorded")
    result: AdjustmentResult = pickle.loads(data)
    return result


def load_result(folder: str | Path) -> AdjustmentResult | None:
    """The adjustment a run saved in ``folder`` (``<run>/<strip>/adjustment``), or None.

    None when the folder has no result, no stamp, or a result whose bytes are not the
    ones its stamp records (the same check as a resumed run's).
    """
    path, stamp = Path(folder) / RESULT_NAME, Path(folder) / RESULT_STAMP
    recorded = _stamp_of(stamp)
    if recorded is None or not path.is_file():
        return None
    try:
        return _read_result(path, recorded[1])
    except _UNREADABLE as exc:
        log.warning("%s: cannot load (%s)", path, exc)
        return None


def _stamp_of(path: Path) -> tuple[str, str] | None:
    """``(inputs' digest, result file's sha256)`` recorded in a stamp, or None."""
    try:
        lines = path.read_text(encoding="utf-8").split()
    except OSError:
        return None
    return (lines[0], lines[1]) if len(lines) == 2 else None
