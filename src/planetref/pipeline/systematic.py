"""The declared accuracies of a run's correlated errors, from its config and its scene.

The adjustment models the reference's error shared by the MCPs of a patch and each CCD's
placement error as systematic parameters with priors (``[adjust.systematic]``,
docs/adjust.md). Their sizes are declared: by the run config, else by the scene manifest
(what a user knows of the reference mosaic and the camera's calibration), else by the
defaults below. :func:`systematic_settings` is the one place that decides which.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from planetref.adjust.config import AdjustConfig
    from planetref.frontend.config import FrontendConfig
    from planetref.scene.manifest import SceneManifest

__all__ = [
    "DEFAULT_CCD_ACCURACY_PX",
    "DEFAULT_REFERENCE_ACCURACY_REF_PX",
    "declared_uncertainty",
    "systematic_settings",
]

#: The reference's planimetric accuracy (reference pixels, per axis) when neither the run
#: config nor the scene manifest states it: a mosaic registered to its own pixel.
DEFAULT_REFERENCE_ACCURACY_REF_PX = 1.0
#: A CCD's placement accuracy (image pixels, per axis) when neither states it.
DEFAULT_CCD_ACCURACY_PX = 0.5


def systematic_settings(
    adjust: AdjustConfig,
    manifest: SceneManifest,
    strip_ids: list[str],
    ref_gsd_m: float,
    overlap: float = 1.0,
) -> tuple[AdjustConfig, dict[str, Any]]:
    """The adjustment settings with the declared accuracies of the correlated errors.

    Each of ``[adjust.systematic]``'s values that the run config leaves unset comes from
    the scene manifest (``[reference] accuracy_m``, ``accuracy_length_m``; the strips'
    ``ccd_accuracy_px``, the largest of ``strip_ids``), else from the defaults
    (:data:`DEFAULT_REFERENCE_ACCURACY_REF_PX` reference pixels,
    :data:`DEFAULT_CCD_ACCURACY_PX`).

    ``overlap`` (:func:`template_overlap` of the MCPs) becomes ``measurement_overlap``
    unless the config sets one above 1.

    Returns:
        ``(settings, source)``: the adjustment settings and, per value, where it came
        from (``"config"``, ``"scene"`` or ``"default"``), for the report.
    """
    sysc = adjust.systematic
    ref = manifest.reference
    src: dict[str, Any] = {}
    upd: dict[str, Any] = {}
    if sysc.reference_sigma_m is None:
        declared = ref.accuracy_m
        upd["reference_sigma_m"] = (
            declared if declared is not None else DEFAULT_REFERENCE_ACCURACY_REF_PX * ref_gsd_m
        )
        src["reference_sigma_m"] = "scene" if declared is not None else "default"
    else:
        src["reference_sigma_m"] = "config"
    if sysc.reference_patch_m is None and ref.accuracy_length_m is not None:
        upd["reference_patch_m"] = ref.accuracy_length_m
        src["reference_patch_m"] = "scene"
    else:
        src["reference_patch_m"] = "config" if sysc.reference_patch_m is not None else "default"
    if sysc.ccd_offset_sigma_px is None:
        values = [
            s.ccd_accuracy_px
            for s in manifest.strips
            if s.id in strip_ids and s.ccd_accuracy_px is not None
        ]
        upd["ccd_offset_sigma_px"] = max(values) if values else DEFAULT_CCD_ACCURACY_PX
        src["ccd_offset_sigma_px"] = "scene" if values else "default"
    else:
        src["ccd_offset_sigma_px"] = "config"
    tile = sysc.tile_offset_sigma_px
    src["tile_offset_sigma_px"] = (
        "estimated" if tile == "estimate" else ("config" if tile else "none")
    )
    if sysc.measurement_overlap == 1.0:
        upd["measurement_overlap"] = max(float(overlap), 1.0)
        src["measurement_overlap"] = "matches"
    else:
        src["measurement_overlap"] = "config"
    new = sysc.model_copy(update=upd)
    return adjust.model_copy(update={"systematic": new}), src


def declared_uncertainty(
    frontend: FrontendConfig, manifest: SceneManifest
) -> tuple[FrontendConfig, str]:
    """The front end's settings with the a-priori uncertainty the scene declares.

    ``frontend.uncertainty_m`` (how far the coarse stage searches) comes from the run
    config when it sets it, else from the scene manifest (the largest of its strips'
    ``initial_uncertainty_m``), else it keeps its default.

    Returns:
        ``(settings, source)``: the settings and where the uncertainty came from
        (``"config"``, ``"scene"`` or ``"default"``).
    """
    if "uncertainty_m" in frontend.model_fields_set:
        return frontend, "config"
    values = [s.initial_uncertainty_m for s in manifest.strips if s.initial_uncertainty_m]
    if not values:
        return frontend, "default"
    return frontend.model_copy(update={"uncertainty_m": float(max(values))}), "scene"
