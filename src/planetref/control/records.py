"""A network's records and their checks: measures inside their images, points' 3-vectors.

Shared by :meth:`planetref.control.network.Network.from_records` (networks built in code)
and :func:`planetref.adjust.network_file.read_network` (network files), so that both refuse the
same records.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.camera.base import Camera
from planetref.errors import InputError

__all__ = [
    "IMAGE_MARGIN_PX",
    "NetworkRecords",
    "check_in_images",
    "outside_image",
    "point_value",
]


IMAGE_MARGIN_PX = 1.0
"""How far outside its image's edges a measure may lie (sub-pixel measures on border
pixels, in either pixel convention); a measure farther out is refused."""


@dataclass(frozen=True)
class NetworkRecords:
    """The records of a network by string ids, as given to ``Network.from_records``.

    Attributes:
        obs_camera: Camera id of each observation.
        obs_point: Point id of each observation.
        line: Observed lines (planetref convention), pixels.
        sample: Observed samples, pixels.
        point_xyz: Point id -> a priori XYZ (metres; NaN for unknown free points).
        point_sigma_m: A scalar/3-vector for all points, or point id -> sigma(s), metres.
        point_kind: ``"mcp"``/``"tie"`` for all points, or point id -> kind.
        obs_ccd: CCD name per observation (``None``: the camera's first CCD).
        sigma_px: Sigma of each observation (pixels), scalar, ``(M,)`` or ``(M, 2)``.
        check: Held-out check flags.
        obs_ids: Observation ids (``None``: row numbers).
        point_sigma_local: Sigmas along east, north, up, for all points or point id -> flag.
        tile: Matching tile id per observation, or ``None`` (see ``Network.obs_tile``).
    """

    obs_camera: Sequence[str]
    obs_point: Sequence[str]
    line: ArrayLike
    sample: ArrayLike
    point_xyz: Mapping[str, ArrayLike]
    point_sigma_m: ArrayLike | Mapping[str, ArrayLike]
    point_kind: str | Mapping[str, str]
    obs_ccd: Sequence[str | None] | None
    sigma_px: ArrayLike
    check: ArrayLike
    obs_ids: Sequence[str] | None
    point_sigma_local: bool | Mapping[str, bool]
    tile: Sequence[str | None] | None = None


def outside_image(
    line: ArrayLike, sample: ArrayLike, size: tuple[ArrayLike, ArrayLike]
) -> NDArray[np.bool_]:
    """Which ``(line, sample)`` (planetref convention) lie more than 1 px outside the image.

    Args:
        line: Lines, pixels (the image spans ``0 .. n_lines``).
        sample: Samples, pixels.
        size: ``(n_lines, n_samples)``, numbers or arrays broadcasting with ``line``.

    Returns:
        True where a measure is farther than :data:`IMAGE_MARGIN_PX` outside (or not finite).
    """
    lo = -IMAGE_MARGIN_PX
    line, sample = np.asarray(line), np.asarray(sample)
    with np.errstate(invalid="ignore"):
        ok_l = (line >= lo) & (line <= np.asarray(size[0]) + IMAGE_MARGIN_PX)
        ok_s = (sample >= lo) & (sample <= np.asarray(size[1]) + IMAGE_MARGIN_PX)
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
    """Refuse the first finite measure lying more than 1 px outside its image.

    Args:
        cameras: Camera id -> camera.
        cam_ids: The camera ids in index order.
        cam_i: Camera index of each measure.
        ccd_i: CCD index (into the camera's ``ccd_names``) of each measure.
        line: Lines (planetref convention).
        sample: Samples.
        obs_ids: Measure ids (default: their indices).

    Raises:
        InputError: Naming the first measure outside (index, id, value, image, its size)
            and how many of that image's measures are.
    """
    cams = [cameras[c] for c in cam_ids]
    n_ccd = max(len(c.ccd_names) for c in cams)
    sizes = np.zeros((len(cams), n_ccd, 2))
    for c, cam in enumerate(cams):
        for k, ccd in enumerate(cam.ccd_names):
            sizes[c, k] = cam.image_size(ccd)
    size = sizes[cam_i, ccd_i]
    bad = outside_image(line, sample, (size[:, 0], size[:, 1])) & np.isfinite(line)
    bad &= np.isfinite(sample)
    if not np.any(bad):
        return
    j = int(np.flatnonzero(bad)[0])
    c, k = int(cam_i[j]), int(ccd_i[j])
    cam, ccd = cams[c], cams[c].ccd_names[k]
    same = (cam_i == c) & (ccd_i == k)
    oid = str(j) if obs_ids is None else str(obs_ids[j])
    image = cam_ids[c] if len(cam.ccd_names) == 1 else f"{cam_ids[c]}/{ccd}"
    nl, ns = (int(n) for n in sizes[c, k])
    raise InputError(
        f"observation {j} (id {oid!r}): line {line[j]:g}, sample {sample[j]:g} is outside "
        f"image {image!r} (0 to {nl} lines, 0 to {ns} samples; "
        f"{int(np.count_nonzero(bad & same))} of {int(np.count_nonzero(same))} measures of it)",
        field="line",
    )
