"""Settings of the control stage: how matched control points enter the adjustment."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from planetref.runtime.settings import Settings

__all__ = ["McpOptions"]


class McpOptions(Settings):
    """How matched control points enter the adjustment.

    Attributes:
        sigma_px: Standard deviation of an MCP's image measure (pixels of the CCD image).
        check_fraction: Share of MCPs held out as check points (not adjusted; their
            residuals are reported), drawn with ``seed``.
        check_blocks: ``tiles``: whole tiles are held out (at least ``check_fraction``
            of the MCPs where the tiles allow, at most twice it, never most of the
            MCPs of the lines a tile spans, never two tiles of the same lines), so that
            no check point has an adjusted neighbour sharing its reference patch and
            template pixels (independent check points) while the strip stays
            controlled where it is checked;
            ``random``: single MCPs drawn at random (their neighbours pin them).
        seed: Seed of the check-point draw.
        min_mcps: Fewest MCPs a strip needs to be adjusted.
    """

    sigma_px: float = Field(1.0, gt=0.0)
    check_fraction: float = Field(0.1, ge=0.0, lt=1.0)
    check_blocks: Literal["tiles", "random"] = "tiles"
    seed: int = 0
    min_mcps: int = Field(12, ge=1)
