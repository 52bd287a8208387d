"""Configuration of a georef run (typed, frozen, rejecting unknown keys).

A TOML file given with ``--config`` may hold the tables ``[frontend]``
(:class:`~planetref.frontend.config.FrontendConfig`), ``[adjust]``
(:class:`~planetref.adjust.config.AdjustConfig`), ``[mcp]``, ``[ortho]`` and
``[matchers.<name>]`` (options passed to that matcher's constructor) and ``[campaign]``
(:class:`CampaignOptions`: several strips adjusted together through tie points). Everything left
out takes the defaults below; the resolved configuration is written into every run
directory (``config.json``).
"""

from __future__ import annotations

import os
from typing import Any

from pydantic import Field

from planetref.adjust.config import AdjustConfig
from planetref.control.config import McpOptions
from planetref.frontend.config import CampaignOptions, FrontendConfig
from planetref.products.config import OrthoOptions
from planetref.runtime.settings import Settings, validate_settings
from planetref.runtime.tomlfile import read_toml

__all__ = [
    "CampaignOptions",
    "GeorefConfig",
    "McpOptions",
    "OrthoOptions",
    "load_config",
]


class GeorefConfig(Settings):
    """Everything a georef run can be told (see the module doc).

    Nothing is overridden for georef runs: every matcher is judged by
    :class:`~planetref.adjust.config.AdjustConfig`'s defaults (the same as ``planetref
    adjust``) and runs with its own default options unless ``[matchers.<name>]`` says
    otherwise, so that all matchers run on equal terms. Sub-pixel refinement is one
    setting for all matchers (``[frontend.refine]``).

    Attributes:
        frontend: Tiling, matching stages and verification of the front end.
        adjust: The bundle adjustment (the same settings as ``planetref adjust``).
        mcp: How matched control points enter the adjustment.
        ortho: The orthoimages written through the adjusted cameras.
        campaign: How the strips of a multi-strip scene are adjusted.
        matchers: Options per matcher, ``[matchers.<name>]`` (keywords of that matcher's
            constructor, e.g. ``max_keypoints`` of ``disk-lightglue``; ``planetref
            matchers`` and ``Matcher.option_names()`` list them); unknown options are
            refused when the matcher is built.
    """

    frontend: FrontendConfig = FrontendConfig()
    adjust: AdjustConfig = AdjustConfig()
    mcp: McpOptions = McpOptions()
    ortho: OrthoOptions = OrthoOptions()
    campaign: CampaignOptions = CampaignOptions()
    matchers: dict[str, dict[str, Any]] = Field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The resolved configuration as plain JSON types.

        The ``campaign`` table is left out while it holds the defaults, and
        ``frontend.ccd_overlap`` while it is off, so that runs without them keep their
        configuration digest (and resume as before).
        """
        doc = self.model_dump(mode="json")
        if self.campaign == CampaignOptions():
            doc.pop("campaign", None)
        if self.frontend.batch_tiles == 1:  # likewise for runs that do not batch tiles
            doc["frontend"].pop("batch_tiles")
        if not self.frontend.ccd_overlap.enabled:  # and for runs without overlap ties
            doc["frontend"].pop("ccd_overlap")
        return doc

    def identity_json(self) -> dict[str, Any]:
        """:meth:`to_json` less what does not change the results (``frontend.batch_tiles``).

        What a run folder's configuration digest is taken of, so that a run resumes
        whatever the batching.
        """
        doc = self.to_json()
        doc["frontend"].pop("batch_tiles", None)
        return doc


def load_config(path: str | os.PathLike[str] | None = None) -> GeorefConfig:
    """Read a georef configuration TOML file (``None``: the defaults).

    Raises:
        MissingFileError: No such file.
        InputError: Unreadable TOML, unknown keys (the message lists the valid ones) or
            bad values, naming the file and the key.
    """
    if path is None:
        return GeorefConfig()
    return config_from_mapping(read_toml(path, "configuration file"), source=str(path))


def config_from_mapping(doc: dict[str, Any], *, source: str | None = None) -> GeorefConfig:
    """Validate a mapping into a :class:`GeorefConfig` with one-line errors naming the file."""
    return validate_settings(GeorefConfig, doc, source=source)
