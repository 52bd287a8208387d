"""The matchers of a georef run: recipes for the workers, instances in process.

Each matcher's class declares what the front end must set (its pixel-length options, a
bounded search, a dense mode; :class:`~planetref.matching.base.BaseMatcher`), and
:func:`matcher_options` is the one place that turns those declarations and the front
end's settings into the options of the fine and coarse instances.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from planetref.frontend.config import FrontendConfig
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
    name: str, options: Mapping[str, Any], fe: FrontendConfig, ref_gsd_m: float
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The registry options of a run's fine and coarse matchers.

    What each matcher needs is read from its class's declarations, never from its name
    (:class:`~planetref.matching.base.BaseMatcher`): its pixel-length options are set in
    reference pixels and passed in fine-grid pixels (times ``fine_upsample``), so a finer
    grid keeps their ground size; a matcher with a dense mode runs it on the fine stage,
    one match per ``dense_spacing_ref_px`` cell; a matcher that searches a bounded radius
    around the same pixel (area-based NCC) gets a fine radius covering the window's pad
    plus what the coarse stage leaves, and a coarse-stage instance whose radius covers
    the a-priori uncertainty at the coarse scale. The others search the whole window with
    their own defaults and serve both stages.

    Args:
        name: Registry name of the matcher.
        options: The user's options of that matcher (``[matchers.<name>]``).
        fe: The front end's settings.
        ref_gsd_m: Ground sampling distance of the reference ortho (metres).

    Returns:
        ``(fine_options, coarse_options)``; ``coarse_options`` is None when the fine
        matcher serves both stages.
    """
    from planetref.frontend.coarse import coarse_search_radius
    from planetref.matching.registry import MATCHERS

    options = dict(options)
    spec = MATCHERS.get(name)
    if spec is None or spec.load_class is None:  # unknown names fail when built
        return options, None
    cls = spec.matcher_class()
    up = fe.fine_upsample
    fine = dict(options)
    if cls.runs_dense():
        fine.setdefault(cls.dense_option, fe.dense_spacing_ref_px * up)
    # The pixel lengths keep their ground size on the fine grid (``up`` times finer), so
    # a finer grid adds detail to each template instead of halving the ground it sees.
    for opt in cls.pixel_options:
        fine[opt] = int(options.get(opt, cls.option_default(opt))) * up
    if cls.search_option is None:
        return fine, None
    # A bounded search looks around the same pixel of the other window, and the front
    # end's windows are padded: the fine stage must reach the pad plus what the coarse
    # stage leaves; the coarse stage the whole a-priori uncertainty.
    fine.setdefault(
        cls.search_option, (fe.fine_pad_ref_px + int(np.ceil(fe.coarse_radius_ref_px)) + 4) * up
    )
    coarse = {**cls.coarse_defaults, **options}
    # At the coarse level the front end picks for this uncertainty (FrontendConfig.
    # coarse_level), so the radius stays bounded by the window whatever the uncertainty.
    radius = coarse_search_radius(fe, ref_gsd_m)
    coarse[cls.search_option] = max(radius, int(coarse.get(cls.search_option, 0)))
    return fine, coarse


def matcher_recipes(
    name: str,
    options: Mapping[str, Any],
    fe: FrontendConfig,
    ref_gsd_m: float,
    *,
    weights_dir: str | os.PathLike[str] | None = None,
    device: str = "cpu",
) -> MatcherPair:
    """The recipes of a run's fine and coarse matchers (see :func:`matcher_options`).

    ``device`` (the run's ``--device``, resolved) goes to every learned matcher's
    constructor, here and only here.
    """
    from planetref.frontend.tasks import MatcherRecipe

    wd = None if weights_dir is None else str(Path(weights_dir).resolve())
    fine_opts, coarse_opts = matcher_options(name, options, fe, ref_gsd_m)
    coarse = None if coarse_opts is None else MatcherRecipe(name, coarse_opts, wd, device)
    return MatcherPair(MatcherRecipe(name, fine_opts, wd, device), coarse)


def build_matchers(
    name: str,
    options: Mapping[str, Any],
    fe: FrontendConfig,
    ref_gsd_m: float,
    *,
    weights_dir: str | os.PathLike[str] | None = None,
) -> tuple[Matcher, Matcher]:
    """The fine-stage and coarse-stage matchers of a run, built.

    Returns:
        ``(fine, coarse)`` matchers (the same object when one serves both stages).
    """
    return matcher_recipes(name, options, fe, ref_gsd_m, weights_dir=weights_dir).built()


def matcher_weight_files(name: str, weights_dir: str | os.PathLike[str] | None) -> list[Path]:
    """The weight files of a registered matcher that are present (their sha256 is identity)."""
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import weights_dir as resolve_dir

    spec = MATCHERS.get(name)
    if spec is None:
        return []
    folder = resolve_dir(weights_dir)
    return [folder / w for w in spec.weights if (folder / w).is_file()]
