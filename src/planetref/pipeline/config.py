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
from typing import Any, Literal

from pydantic import Field

from planetref.adjust.config import AdjustConfig
from planetref.frontend.config import FrontendConfig
from planetref.settings import Settings, validate_settings
from planetref.tomlfile import read_toml

__all__ = [
    "CampaignOptions",
    "GeorefConfig",
    "McpOptions",
    "OrthoOptions",
    "load_config",
]


class McpOptions(Settings):
    """How matched control points enter the adjustment.

    Attributes:
        sigma_px: Standard deviation of an MCP's image measure (pixels of the CCD image).
        check_fraction: Share of MCPs held out as check points (not adjusted; their
            residuals are reported), drawn with ``seed``.
        check_blocks: ``tiles``: whole tiles are held out (at least ``check_fraction``
            of the MCPs), so that no check point has an adjusted neighbour sharing its
            reference patch and template pixels (independent check points);
            ``random``: single MCPs drawn at random (their neighbours pin them).
        seed: Seed of the check-point draw.
        min_mcps: Fewest MCPs a strip needs to be adjusted.
    """

    sigma_px: float = Field(1.0, gt=0.0)
    check_fraction: float = Field(0.1, ge=0.0, lt=1.0)
    check_blocks: Literal["tiles", "random"] = "tiles"
    seed: int = 0
    min_mcps: int = Field(12, ge=1)


class OrthoOptions(Settings):
    """The orthoimage of each CCD through the adjusted camera and the reference DEM.

    Attributes:
        enabled: Write them.
        gsd_m: Pixel size (metres); ``None``: the CCD image's own GSD.
    """

    enabled: bool = True
    gsd_m: float | None = Field(None, gt=0.0)


class CampaignOptions(Settings):
    """How the strips of a scene (a campaign) are adjusted.

    With ``adjust_together`` false (the default) every strip is adjusted on its own with
    its MCPs. With it true and several strips, tie points are matched between the
    overlapping CCD images of different strips (both orthorectified onto the same
    reference-grid window through their initial cameras and the DEM), and one network
    with every strip's camera, all MCPs and the tie points is adjusted once.

    Attributes:
        adjust_together: Adjust all strips in one network tied by tie points.
        tie_sigma_m: A-priori sigma (metres, per axis) of a tie point's ground
            coordinates, taken from the reference DEM at its map position; ``None``: free
            (its XYZ are unknowns). That position comes from the *initial* cameras, so a
            sigma below their ground error (``frontend.uncertainty_m``) pulls the strips
            back towards it: on the two-strip tiny scene (107 m initial error) 5 m gave
            14 m after adjustment, 300 m or free gave 0.7 m.
        tie_sigma_px: Standard deviation of a tie point's image measures (CCD pixels).
        tie_window_ref_px: Side of the reference-grid windows an overlap is cut into
            for matching (reference pixels).
        tie_max_per_window: Most tie points kept per window (spread over it).
        tie_min_inliers: Fewest verified matches a window needs to give tie points.
        tie_min_overlap_ref_px: Smallest overlap side (reference pixels) worth matching.
    """

    adjust_together: bool = False
    tie_sigma_m: float | None = Field(None, gt=0.0)
    tie_sigma_px: float = Field(1.0, gt=0.0)
    tie_window_ref_px: int = Field(512, ge=32)
    tie_max_per_window: int = Field(100, ge=1)
    tie_min_inliers: int = Field(8, ge=4)
    tie_min_overlap_ref_px: int = Field(24, ge=8)


class GeorefConfig(Settings):
    """Everything a georef run can be told (see the module doc).

    Nothing is overridden for georef runs: every matcher is judged by
    :class:`~planetref.adjust.config.AdjustConfig`'s defaults (the same as ``planetref
    adjust``) and runs with its own default options unless ``[matchers.<name>]`` says
    otherwise, so that all matchers run on equal terms. Sub-pixel refinement is one
    setting for all matchers (``[frontend.refine]``).
    """

    frontend: FrontendConfig = FrontendConfig()
    adjust: AdjustConfig = AdjustConfig()
    mcp: McpOptions = McpOptions()
    ortho: OrthoOptions = OrthoOptions()
    campaign: CampaignOptions = CampaignOptions()
    matchers: dict[str, dict[str, Any]] = Field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The resolved configuration as plain JSON types.

        The ``campaign`` table is left out while it holds the defaults, so that runs
        without it keep their configuration digest (and resume as before).
        """
        doc = self.model_dump(mode="json")
        if self.campaign == CampaignOptions():
            doc.pop("campaign", None)
        if self.frontend.batch_tiles == 1:  # likewise for runs that do not batch tiles
            doc["frontend"].pop("batch_tiles")
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
