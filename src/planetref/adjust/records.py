"""Checks of a network's records: measures inside their images, points' 3-vectors.

Shared by :meth:`planetref.adjust.problem.Network.from_records` (networks built in code)
and :func:`planetref.adjust.network.read_network` (network files), so that both refuse the
same records.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.base import Camera
from planetref.errors import InputError

__all__ = ["IMAGE_MARGIN_PX", "check_in_images", "outside_image", "point_value"]

F64 = NDArray[np.float64]

IMAGE_MARGIN_PX = 1.0
"""How far outside its image's edges a measure may lie (sub-pixel measures on border
pixels, in either pixel convention); a measure farther out is refused."""


def outside_image(line: ArrayLike, sample: ArrayLike, size: tuple[int, int]) -> NDArray[np.bool_]:
    """Which ``(line, sample)`` (planetref convention) lie more than 1 px outside the image.

    Args:
        line: Lines, pixels (the image spans ``0 .. n_lines``).
        sample: Samples, pixels.
        size: ``(n_lines, n_samples)``.

    Returns:
        True where a measure is farther than :data:`IMAGE_MARGIN_PX` outside (or not finite).
    """
    lo = -IMAGE_MARGIN_PX
    with np.errstate(invalid="ignore"):
        ok_l = (np.asarray(line) >= lo) & (np.asarray(line) <= size[0] + IMAGE_MARGIN_PX)
        ok_s = (np.asarray(sample) >= lo) & (np.asarray(sample) <= size[1] + IMAGE_MARGIN_PX)
    return ~(ok_l & ok_s)


def point_value(
    values: Mapping[str, ArrayLike], pid: str, field: str, *, exact: bool = False
) -> F64:
    """A point's 3-vector (XYZ, or sigmas that may be one scalar), naming the point if bad."""
    if pid not in values:
        raise InputError(f"no value for point {pid!r}", field=field)
    v = np.asarray(values[pid], dtype=np.float64)
    if v.shape != (3,) and (exact or v.size != 1):
        raise InputError(f"point {pid!r}: expected 3 values, got shape {v.shape}", field=field)
    return np.broadcast_to(v.reshape(-1), (3,)) if v.size == 1 else v


def check_in_images(
    cameras: Mapping[str, Camera],
    cam_ids: list[str],
    cam_i: NDArray[np.intp],
    ccd_i: NDArray[np.intp],
    line: F64,
    sample: F64,
    obs_ids: Sequence[str] | None,
) -> None:
    """Refuse the first finite measure lying more than 1 px outside its image."""
    cams = [cameras[c] for c in cam_ids]
    for c, cam in enumerate(cams):
        for k, ccd in enumerate(cam.ccd_names):
            sel = np.flatnonzero((cam_i == c) & (ccd_i == k))
            if sel.size == 0:
                continue
            size = tuple(int(n) for n in cam.image_size(ccd))
            with np.errstate(invalid="ignore"):
                bad = (
                    outside_image(line[sel], sample[sel], size)
                    & np.isfinite(line[sel])
                    & np.isfinite(sample[sel])
                )
            if np.any(bad):
                j = int(sel[np.flatnonzero(bad)[0]])
                oid = str(j) if obs_ids is None else str(obs_ids[j])
                image = cam_ids[c] if len(cam.ccd_names) == 1 else f"{cam_ids[c]}/{ccd}"
                raise InputError(
                    f"observation {j} (id {oid!r}): line {line[j]:g}, sample {sample[j]:g} "
                    f"is outside image {image!r} (0 to {size[0]} lines, 0 to {size[1]} "
                    f"samples; {int(np.count_nonzero(bad))} of {sel.size} measures of it)",
                    field="line",
                )
