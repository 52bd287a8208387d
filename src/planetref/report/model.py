"""report.json of a georef run as one typed model: :class:`GeorefReport`.

The blocks (:mod:`planetref.report.blocks`) build these models; :meth:`GeorefReport.to_json`
gives report.json's content. A key is written when its builder set it, even to ``None``,
and absent otherwise (``exclude_unset``), so optional keys (``true_outliers``,
``campaign``, ``input_warnings``, a failed run's ``failed``) keep their place in the file.
Metrics computed by the adjustment (per CCD, check MCPs, variance components, the
geolocation error per CCD) are JSON objects whose keys the adjustment owns
(:func:`planetref.adjust.metrics.reprojection_metrics`); they travel as such.

The JSON schema of the model is published in docs/reference/report-schema.json
(:func:`report_schema`; a test checks that it matches the model).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from planetref.runtime.settings import Record

__all__ = [
    "AdjustmentSummary",
    "CampaignBlock",
    "CcdOverlapBlock",
    "CcdOverlapPair",
    "CheckBlock",
    "FrontendSettings",
    "GeorefReport",
    "LostTile",
    "MatchingSummary",
    "StripMatching",
    "StripReport",
    "TrueOutliers",
    "report_schema",
]

#: A JSON object computed by the adjustment (its keys are the adjustment's).
Metrics = dict[str, Any]


class ReportModel(Record):
    """A block of report.json: no key beyond the declared ones, written as set."""

    def to_json(self) -> dict[str, Any]:
        """The block as report.json holds it (the keys set, in declaration order)."""
        return self.model_dump(mode="python", exclude_unset=True)


class CcdMatching(ReportModel):
    """Table 1 of one CCD image."""

    ncp: int = Field(description="Matched control points delivered to the adjustment.")
    sdu_pct: float = Field(description="Spatial distribution uniformity of the MCPs (%).")


class LostTile(ReportModel):
    """A tile that gave no MCPs, and why."""

    tile: str
    status: str
    message: str
    strip: str | None = Field(None, description="The strip (in the run's pooled block).")


class TrueOutliers(ReportModel):
    """True outlier ratio of the matches after RANSAC (simulated scenes)."""

    n: int
    n_unmeasured: int
    n_over_1px: int
    n_over_3px: int
    pct_over_1px: float | None
    pct_over_3px: float | None
    median_px: float | None


class FrontendSettings(ReportModel):
    """The front-end settings that decide what the matching figures mean."""

    refine: str
    fine_upsample: int
    dense_spacing_ref_px: int
    max_mcps_per_tile: int
    protocol: str


class StripMatching(ReportModel):
    """The ``matching`` block of one strip (``strips.<id>.matching``)."""

    ccds: dict[str, CcdMatching]
    ncp: int
    n_mcps: int
    tiles_total: int
    tiles_failed: int
    tiles_thinned: int = 0
    tile_status: dict[str, int]
    coarse_sources: dict[str, int] = Field(default_factory=dict)
    tiles_lost: list[LostTile]
    funnel: dict[str, int] = Field(default_factory=dict)
    drops: dict[str, int] = Field(default_factory=dict)
    mcp_counts: dict[str, int] = Field(default_factory=dict)
    true_outliers: TrueOutliers | None = None


class MatchingSummary(ReportModel):
    """The run's ``matching`` block: every strip's CCDs, their counts summed."""

    ccds: dict[str, CcdMatching]
    ncp: int
    sdu_pct: float
    tiles_total: int = 0
    tiles_failed: int = 0
    tiles_thinned: int = 0
    coarse_sources: dict[str, int] = Field(default_factory=dict)
    tiles_lost: list[LostTile] = Field(default_factory=list)
    funnel: dict[str, int] = Field(default_factory=dict)
    drops: dict[str, int] = Field(default_factory=dict)
    true_outliers: TrueOutliers | None = None
    settings: FrontendSettings | None = None


class AdjustmentSummary(ReportModel):
    """An ``adjustment`` block: Table 2 after the adjustment, then its statistics.

    The same block for a strip alone, a strip of a joint network, the joint network and
    several strips pooled; each sets the entries it has.
    """

    rmse_px_before: float | None
    rmse_px: float | None
    rmse_x_px: float | None = None
    rmse_y_px: float | None = None
    mean_px: float | None
    mean_x_px: float | None = None
    mean_y_px: float | None = None
    max_x_px: float | None
    max_y_px: float | None
    min_x_px: float | None
    min_y_px: float | None
    outlier_ratio_pct: float | None
    n_total: int
    n_inliers: int
    sigma0: float
    converged: bool
    n_tie_observations: int | None = None
    sigma0_before_vce: float | None = None
    measurement_overlap: float | None = None
    sigma0_real: float | None = None
    dof: Metrics | None = None
    variance_components: list[Metrics] | None = None
    systematic: Metrics | None = None
    check_mcps: Metrics | None = None
    ccds: dict[str, Metrics] | None = None
    systematic_source: Metrics | None = None
    n_tie_points: int | None = None
    tie_rmse_px: float | None = None
    tie_rmse_px_before: float | None = None


class CheckBlock(ReportModel):
    """The true geolocation error before and after the adjustment (simulated scenes)."""

    geoloc_rmse_m_before: float | None = None
    geoloc_rmse_m: float | None = None
    formal_rmse_m: float | None = None
    true_over_formal: float | None = None
    geoloc_rmse_px_before: float | None = None
    geoloc_rmse_px: float | None = None
    geoloc_max_m: float | None = None
    ccds: dict[str, dict[str, Metrics]] | None = None


class CcdOverlapPair(ReportModel):
    """The tie points of one pair of overlapping CCDs (``strips.<id>.ccd_overlap.pairs``)."""

    n_ties: int
    stagger_lines: float = Field(description="Median line difference of the pair's ties.")
    stagger_s: float | None = Field(description="The stagger as a time (s).")
    unit_gain_hz: float | None = Field(
        description="Frequency (Hz) where the overlap's gain |2 sin(pi f dt)| reaches 1."
    )
    gain_at_10hz: float | None = Field(description="The overlap's gain at 10 Hz.")


class CcdOverlapBlock(ReportModel):
    """A strip's tie points between overlapping CCDs (``[frontend.ccd_overlap]``)."""

    n_ties: int
    pairs: dict[str, CcdOverlapPair]
    sigma_px: float
    rmse_px_before: float | None
    rmse_px: float | None
    n_inlier_observations: int | None = None


class StripReport(ReportModel):
    """One strip's blocks (``strips.<id>``)."""

    matching: StripMatching
    adjustment: AdjustmentSummary | None = None
    check: CheckBlock | None = None
    ccd_overlap: CcdOverlapBlock | None = None
    warnings: list[str] | None = None
    failed: str | None = None


class CampaignBlock(ReportModel):
    """The joint adjustment of several strips (``[campaign] adjust_together``)."""

    adjust_together: bool
    n_tie_points: int
    n_tie_observations: int
    tie_points_per_strip_pair: dict[str, int]
    tie_points_per_image_pair: dict[str, int]
    tie_sigma_m: float | None
    files: dict[str, Any]


class GeorefReport(ReportModel):
    """report.json of a georef run."""

    matcher: str
    scene: str
    planetref_version: str
    failed: str | None = Field(None, description="Why the run stopped (it ran, but failed).")
    strips_not_run: list[str] | None = None
    matching: MatchingSummary
    adjustment: AdjustmentSummary | None
    check: CheckBlock | None
    timing_s: dict[str, float]
    strips: dict[str, StripReport]
    campaign: CampaignBlock | None = None
    input_warnings: list[str] | None = None
    resumed: bool | None = None


def report_schema() -> dict[str, Any]:
    """The JSON schema of :class:`GeorefReport` (docs/reference/report-schema.json)."""
    return GeorefReport.model_json_schema(mode="serialization")
