"""The matchers of a georef run: recipes for the workers, instances in process.

NCC runs in dense mode on the fine stage (one template per ``dense_spacing_ref_px`` grid
cell) with a search radius that covers the fine window's pad, and gets a coarse-stage
instance whose radius covers the a-priori uncertainty; the other matchers run with their
own defaults (keypoint budgets included) and serve both stages.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planetref.pipeline.config import GeorefConfig

if TYPE_CHECKING:  # pragma: no cover
    from planetref.frontend.tasks import MatcherRecipe
    from planetref.matching.base import Matcher

__all__ = [
    "MatcherPair",
    "build_matchers",
    "matcher_options",
    "matcher_recipes",
    "matcher_weight_files",
]


@dataclass(frozen=True)
class MatcherPair:
    """The matchers of a run: recipes (what workers build) and, in process, instances.

    Attributes:
        fine: Fine-stage recipe.
        coarse: Coarse-stage recipe; None: the fine matcher serves both stages.
        instances: Prebuilt ``(fine, coarse)`` instances (e.g. reused across the runs of
            ``compare``); None: built from the recipes when first needed.
    """

    fine: MatcherRecipe
    coarse: MatcherRecipe | None = None
    instances: tuple[Matcher, Matcher] | None = None

    def built(self) -> tuple[Matcher, Matcher]:
        """``(fine, coarse)`` instances (the same object twice without a coarse recipe)."""
        if self.instances is None:
            fine = self.fine.build()
            coarse = fine if self.coarse is None else self.coarse.build()
            object.__setattr__(self, "instances", (fine, coarse))
        return self.instances  # type: ignore[return-value]


def matcher_options(
    name: str, cfg: GeorefConfig, ref_gsd_m: float
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The registry options of a run's fine and coarse matchers.

    Area-based NCC searches a fixed radius around each template, so its coarse-stage
    instance gets a radius that covers the a-priori uncertainty at the coarse scale; the
    fine stage runs in dense mode: one template per ``dense_spacing_ref_px`` grid cell.
    Cell, search radius and template radius are set in reference pixels and passed in
    fine-grid pixels (times ``fine_upsample``): the same template count, template ground
    size and ground search on any fine grid. The other matchers search the whole window
    with their own defaults and serve both stages.

    Returns:
        ``(fine_options, coarse_options)``; ``coarse_options`` is None when the fine
        matcher serves both stages.
    """
    options = dict(cfg.matchers.get(name, {}))
    fe = cfg.frontend
    if name != "ncc":
        if name == "loftr" and _loftr_is_dense():
            options.setdefault("dense_spacing_px", fe.dense_spacing_ref_px * fe.fine_upsample)
        return options, None
    up = fe.fine_upsample
    # NCC looks for each template around the same pixel of the other window, and the
    # front end's windows are padded: the fine stage must reach the pad plus what the
    # coarse stage leaves; the coarse stage the whole a-priori uncertainty.
    fine_radius = (fe.fine_pad_ref_px + int(np.ceil(fe.coarse_radius_ref_px)) + 4) * up
    coarse_radius = int(np.ceil(fe.uncertainty_m / (ref_gsd_m * fe.coarse_factor))) + 4
    coarse_opts = {"spacing": 8, **options}
    coarse_opts["search_radius"] = max(coarse_radius, int(coarse_opts.get("search_radius", 0)))
    dense = fe.dense_spacing_ref_px * up
    # The template keeps its ground size too (the fine grid is ``up`` times finer), so a
    # finer grid adds detail to each template instead of halving the ground it sees.
    template = int(options.get("template_radius", _ncc_default("template_radius"))) * up
    fine_opts = {
        "search_radius": fine_radius,
        "dense_spacing_px": dense,
        **options,
        "template_radius": template,
    }
    return fine_opts, coarse_opts


def _ncc_default(option: str) -> Any:
    """The NCC matcher's own default of one option (imports its module only)."""
    import inspect

    from planetref.matching.ncc import NccMatcher

    return inspect.signature(NccMatcher).parameters[option].default


def _loftr_is_dense() -> bool:
    """Whether this LoFTR takes a ``dense_spacing_px`` option (imports its module only)."""
    import inspect

    from planetref.matching.loftr import LoftrMatcher

    return "dense_spacing_px" in inspect.signature(LoftrMatcher).parameters


def matcher_recipes(
    name: str,
    cfg: GeorefConfig,
    ref_gsd_m: float,
    *,
    weights_dir: str | os.PathLike[str] | None = None,
) -> MatcherPair:
    """The recipes of a run's fine and coarse matchers (see :func:`matcher_options`)."""
    from planetref.frontend.tasks import MatcherRecipe

    wd = None if weights_dir is None else str(Path(weights_dir).resolve())
    fine_opts, coarse_opts = matcher_options(name, cfg, ref_gsd_m)
    coarse = None if coarse_opts is None else MatcherRecipe(name, coarse_opts, wd)
    return MatcherPair(MatcherRecipe(name, fine_opts, wd), coarse)


def build_matchers(
    name: str,
    cfg: GeorefConfig,
    ref_gsd_m: float,
    *,
    weights_dir: str | os.PathLike[str] | None = None,
) -> tuple[Matcher, Matcher]:
    """The fine-stage and coarse-stage matchers of a run, built.

    Returns:
        ``(fine, coarse)`` matchers (the same object when one serves both stages).
    """
    return matcher_recipes(name, cfg, ref_gsd_m, weights_dir=weights_dir).built()


def matcher_weight_files(name: str, weights_dir: str | os.PathLike[str] | None) -> list[Path]:
    """The weight files of a registered matcher that are present (their sha256 is identity)."""
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import weights_dir as resolve_dir

    spec = MATCHERS.get(name)
    if spec is None:
        return []
    folder = resolve_dir(weights_dir)
    return [folder / w for w in spec.weights if (folder / w).is_file()]
