"""Rankings over several scenes (seeds): mean and spread per matcher, paired differences.

One scene ranks matchers by chance as much as by skill: switching the variance-component
estimation alone moved NCC's true error on tiny ``hard`` by 12 %, the size of the gaps
between matchers. :func:`summarize_seeds` takes the comparison reports of several
scenes (``planetref demo --seeds N``: the same preset, seeds ``s .. s+N-1``; or
``planetref compare`` over several scenes) and gives, per matcher and metric of Tables
1-2 and the true error, the mean, the standard deviation (``ddof = 1``) and the range
over the scenes; and per pair of matchers and headline metric the *paired* differences
(same scene), whose mean is compared with its standard error ``SE = sd / sqrt(n)``:

* a gap is **beyond noise** when ``|mean difference| > 2 SE`` (and ``n >= 2``): about a
  95 % interval for many scenes, a weak rule for few (with 3 scenes a paired t-test
  needs ``|mean| > 4.3 SE`` for p < 0.05, so a gap marked here is a hint, not proof);
* the paired t-test's p-value is printed beside it, and from 6 scenes on the Wilcoxon
  signed-rank test's (below 6 it cannot reach p < 0.05 whatever the data).

A failed matcher (NCP 0, no adjustment) counts in the NCP and SDU means and is missing
from the adjustment's: ``n`` says how many scenes each mean stands on.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planetref.runtime.atomic import atomic_path, write_json_atomic, write_text_atomic

__all__ = [
    "NOISE_SE",
    "SEED_METRICS",
    "MetricSpec",
    "PairedDiff",
    "SeedsSummary",
    "Spread",
    "paired_difference",
    "summarize_seeds",
    "write_seeds_report",
]

NOISE_SE = 2.0
"""A mean paired difference beyond this many standard errors is called beyond noise."""


def _adj(key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: (r.get("adjustment") or {}).get(key)


def _chk(key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: (r.get("check") or {}).get(key)


def _agr(key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: (r.get("agreement") or {}).get(key)


def _match(key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: (r.get("matching") or {}).get(key)


def _tor(key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: ((r.get("matching") or {}).get("true_outliers") or {}).get(key)


def _ccd(ccd: str, key: str) -> Callable[[Mapping[str, Any]], Any]:
    return lambda r: (((r.get("matching") or {}).get("ccds") or {}).get(ccd) or {}).get(key)


@dataclass(frozen=True)
class MetricSpec:
    """A metric summarised over seeds.

    Attributes:
        key: Short name (JSON key).
        label: Table header.
        get: Its value in one run's report.json (None when missing).
        better: ``"higher"``, ``"lower"``, or ``""`` (signed, no direction).
        headline: Ranked with paired differences (the headline figure's panels).
    """

    key: str
    label: str
    get: Callable[[Mapping[str, Any]], Any]
    better: str = ""
    headline: bool = False


SEED_METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("ncp", "NCP", _match("ncp"), "higher", True),
    MetricSpec("sdu_pct", "SDU (%)", _match("sdu_pct"), "higher", True),
    MetricSpec("tiles_failed", "tiles failed", _match("tiles_failed"), "lower"),
    MetricSpec("rmse_px", "RMSE (px)", _adj("rmse_px"), "lower", True),
    MetricSpec("mean_px", "Mean (px)", _adj("mean_px"), "lower"),
    MetricSpec("max_x_px", "Max X (px)", _adj("max_x_px")),
    MetricSpec("max_y_px", "Max Y (px)", _adj("max_y_px")),
    MetricSpec("min_x_px", "Min X (px)", _adj("min_x_px")),
    MetricSpec("min_y_px", "Min Y (px)", _adj("min_y_px")),
    MetricSpec("outlier_ratio_pct", "OR (%)", _adj("outlier_ratio_pct"), "lower", True),
    MetricSpec("sigma0", "sigma0", _adj("sigma0")),
    MetricSpec("geoloc_rmse_m", "true error (m)", _chk("geoloc_rmse_m"), "lower", True),
    MetricSpec("geoloc_max_m", "max true error (m)", _chk("geoloc_max_m"), "lower"),
    MetricSpec("true_over_formal", "true / formal", _chk("true_over_formal")),
    MetricSpec("excess_m", "excess (m)", _agr("excess_m"), "lower"),
    MetricSpec(
        "true_over_formal_with_excess",
        "true / formal with excess",
        _agr("true_over_formal_with_excess"),
    ),
    MetricSpec("true_or_1px_pct", "true OR >1 px (%)", _tor("pct_over_1px"), "lower"),
    MetricSpec("true_or_3px_pct", "true OR >3 px (%)", _tor("pct_over_3px"), "lower", True),
)
"""The metrics of Tables 1-2, the true error, its calibration (true over the formal
precision, without and with the matcher's excess error of the comparison's three-cornered
hat) and the true outlier ratio, in table order."""


@dataclass(frozen=True)
class Spread:
    """One metric of one matcher over the seeds.

    Attributes:
        values: Per seed (None where the run has no value, e.g. failed).
        n: Seeds with a value.
        mean: Their mean (None for ``n = 0``).
        std: Their standard deviation, ``ddof = 1`` (None for ``n < 2``).
        min: Smallest value.
        max: Largest value.
    """

    values: list[float | None]
    n: int
    mean: float | None
    std: float | None
    min: float | None
    max: float | None

    @classmethod
    def of(cls, values: Sequence[float | None]) -> Spread:
        """The spread of per-seed values (None and non-finite ones left out)."""
        vals = [None if v is None or not math.isfinite(float(v)) else float(v) for v in values]
        good = np.array([v for v in vals if v is not None], float)
        n = int(good.size)
        return cls(
            values=vals,
            n=n,
            mean=float(good.mean()) if n else None,
            std=float(good.std(ddof=1)) if n >= 2 else None,
            min=float(good.min()) if n else None,
            max=float(good.max()) if n else None,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "values": self.values,
            "n": self.n,
            "mean": self.mean,
            "std": self.std,
            "min": self.min,
            "max": self.max,
        }


@dataclass(frozen=True)
class PairedDiff:
    """Paired differences ``a - b`` of one metric over the seeds where both have a value.

    Attributes:
        a: First matcher.
        b: Second matcher.
        metric: Metric key.
        n: Seeds with both values.
        mean: Mean difference (None for ``n = 0``).
        se: Standard error of the mean difference, ``sd / sqrt(n)`` (None for ``n < 2``).
        beyond_noise: ``|mean| > NOISE_SE * se`` with ``n >= 2`` (a zero ``se`` with a
            non-zero mean counts: every seed gave the same gap).
        p_ttest: Two-sided paired t-test p-value (None for ``n < 2`` or no spread).
        p_wilcoxon: Two-sided Wilcoxon signed-rank p-value (from 6 seeds on; None below).
        better: The better matcher when the gap is beyond noise (None otherwise or for a
            metric without a direction).
    """

    a: str
    b: str
    metric: str
    n: int
    mean: float | None
    se: float | None
    beyond_noise: bool
    p_ttest: float | None
    p_wilcoxon: float | None
    better: str | None

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return dict(self.__dict__)


def paired_difference(
    a: str,
    b: str,
    metric: MetricSpec,
    va: Sequence[float | None],
    vb: Sequence[float | None],
) -> PairedDiff:
    """Paired differences ``va - vb`` (same seed) and whether they are beyond noise.

    Args:
        a: Name of the first matcher.
        b: Name of the second.
        metric: The metric (its direction names the better matcher).
        va: Per-seed values of ``a``.
        vb: Per-seed values of ``b`` (same seeds, same order).
    """
    d = np.array(
        [
            x - y
            for x, y in zip(va, vb, strict=True)
            if x is not None and y is not None and math.isfinite(x) and math.isfinite(y)
        ],
        float,
    )
    n = int(d.size)
    mean = float(d.mean()) if n else None
    se = float(d.std(ddof=1) / math.sqrt(n)) if n >= 2 else None
    beyond = bool(
        n >= 2 and mean is not None and se is not None and abs(mean) > NOISE_SE * se and mean != 0
    )
    p_t = p_w = None
    if n >= 2 and se:
        from scipy import stats

        p_t = float(stats.ttest_rel(d, np.zeros(n)).pvalue)
    if n >= 6 and np.any(d != 0):
        from scipy import stats

        p_w = float(stats.wilcoxon(d).pvalue)
    better = None
    if beyond and metric.better and mean is not None:
        a_higher = mean > 0
        better = a if a_higher == (metric.better == "higher") else b
    return PairedDiff(a, b, metric.key, n, mean, se, beyond, p_t, p_w, better)


@dataclass
class SeedsSummary:
    """Rankings over several scenes.

    Attributes:
        seeds: Label of each scene (e.g. ``"seed0"``), in order.
        matchers: Matchers in the order of the first report they appear in.
        metrics: Metric key -> matcher -> :class:`Spread`.
        pairs: Paired differences of the headline metrics (every pair of matchers).
        failed: Matcher -> the seeds where its run failed.
        skipped: Matcher -> why it could not run (from any scene).
        protocol: Front-end protocol of the runs (``"default"``, ``"paper"``, mixed).
        ranking: The ranking sentences, one per headline metric with values.
        specs: The metrics summarised, in table order: :data:`SEED_METRICS` with Table 1's
            NCP and SDU of each CCD after the totals.
    """

    seeds: list[str]
    matchers: list[str]
    metrics: dict[str, dict[str, Spread]]
    pairs: list[PairedDiff]
    failed: dict[str, list[str]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    protocol: str = "default"
    ranking: list[str] = field(default_factory=list)
    specs: list[MetricSpec] = field(default_factory=lambda: list(SEED_METRICS))

    def to_dict(self) -> dict[str, Any]:
        """The seeds.json content."""
        return {
            "seeds": self.seeds,
            "n_seeds": len(self.seeds),
            "matchers": self.matchers,
            "noise_rule": f"|mean paired difference| > {NOISE_SE:g} x its standard error",
            "protocol": self.protocol,
            "metrics": {
                k: {m: s.to_dict() for m, s in per.items()} for k, per in self.metrics.items()
            },
            "pairs": [p.to_dict() for p in self.pairs],
            "failed": self.failed,
            "skipped": self.skipped,
            "ranking": self.ranking,
        }

    def pair(self, metric: str, a: str, b: str) -> PairedDiff | None:
        """The paired difference of ``a`` and ``b`` (either order) for a metric."""
        for p in self.pairs:
            if p.metric == metric and {p.a, p.b} == {a, b}:
                return p
        return None


def summarize_seeds(reports: Mapping[str, Mapping[str, Any]]) -> SeedsSummary:
    """Mean, spread and paired differences per matcher over several comparisons.

    Args:
        reports: Scene label (e.g. ``"seed0"``) -> that scene's comparison report.json
            content (``{"runs": {matcher: report}, "skipped": {...}}``).
    """
    seeds = list(reports)
    matchers: list[str] = []
    for rep in reports.values():
        for m in rep.get("runs") or {}:
            if m not in matchers:
                matchers.append(m)
    ccds: list[str] = []
    for rep in reports.values():
        for run in (rep.get("runs") or {}).values():
            for c in (run.get("matching") or {}).get("ccds") or {}:
                if c not in ccds:
                    ccds.append(c)
    per_ccd = [MetricSpec(f"ncp_{c}", f"{c} NCP", _ccd(c, "ncp"), "higher") for c in ccds]
    per_ccd += [MetricSpec(f"sdu_{c}", f"{c} SDU (%)", _ccd(c, "sdu_pct"), "higher") for c in ccds]
    specs = [*SEED_METRICS[:2], *per_ccd, *SEED_METRICS[2:]]
    metrics: dict[str, dict[str, Spread]] = {}
    values: dict[str, dict[str, list[float | None]]] = {}
    for spec in specs:
        per: dict[str, list[float | None]] = {}
        for m in matchers:
            vals: list[float | None] = []
            for s in seeds:
                run = (reports[s].get("runs") or {}).get(m)
                v = None if run is None else spec.get(run)
                vals.append(None if v is None else float(v))
            per[m] = vals
        if any(v is not None for vs in per.values() for v in vs):
            values[spec.key] = per
            metrics[spec.key] = {m: Spread.of(vs) for m, vs in per.items()}
    pairs = [
        paired_difference(a, b, spec, values[spec.key][a], values[spec.key][b])
        for spec in specs
        if spec.headline and spec.key in values
        for i, a in enumerate(matchers)
        for b in matchers[i + 1 :]
    ]
    failed: dict[str, list[str]] = {}
    skipped: dict[str, str] = {}
    protocols: set[str] = set()
    for s in seeds:
        for m, run in (reports[s].get("runs") or {}).items():
            if run.get("failed"):
                failed.setdefault(m, []).append(s)
            prot = ((run.get("matching") or {}).get("settings") or {}).get("protocol")
            protocols.add(str(prot or "default"))
        for m, why in (reports[s].get("skipped") or {}).items():
            skipped.setdefault(m, why)
    out = SeedsSummary(
        seeds=seeds,
        matchers=matchers,
        metrics=metrics,
        pairs=pairs,
        failed=failed,
        skipped=skipped,
        protocol=", ".join(sorted(protocols)) or "default",
        specs=[sp for sp in specs if sp.key in metrics],
    )
    out.ranking = [
        r for spec in SEED_METRICS if spec.headline and (r := _ranking(out, spec)) is not None
    ]
    return out


def _fmt(v: float | None, digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.{digits}g}"


def _ranking(summary: SeedsSummary, spec: MetricSpec) -> str | None:
    """One sentence: matchers ordered by their mean, each gap called beyond noise or not."""
    per = summary.metrics.get(spec.key)
    if not per or not spec.better:
        return None
    ranked = [m for m in summary.matchers if per[m].mean is not None]
    if not ranked:
        return None
    ranked.sort(key=lambda m: per[m].mean, reverse=spec.better == "higher")  # type: ignore[arg-type,return-value]
    parts = [_mean_sd(per[ranked[0]], ranked[0])]
    for prev, cur in itertools.pairwise(ranked):
        p = summary.pair(spec.key, prev, cur)
        sep = " >> " if p is not None and p.beyond_noise else " ~ "
        parts.append(sep + _mean_sd(per[cur], cur))
    n = len(summary.seeds)
    ns = sorted({per[m].n for m in ranked})
    on = f"{n} seeds" if ns == [n] else f"{n} seeds ({'/'.join(map(str, ns))} with a value)"
    weak = " (a weak test with so few seeds)" if n < 6 else ""
    return (
        f"{spec.label}, {spec.better} is better, over {on}: "
        + "".join(parts)
        + f"; '>>' = ranks ahead, the paired gap beyond noise (|mean| > {NOISE_SE:g} SE)"
        f"{weak}; '~' = within noise."
    )


def _mean_sd(s: Spread, name: str) -> str:
    sd = f" +- {_fmt(s.std)}" if s.std is not None else ""
    return f"{name} {_fmt(s.mean)}{sd}"


def seeds_table(summary: SeedsSummary) -> tuple[list[str], list[list[Any]]]:
    """Per matcher and metric: mean, std, min-max and n (one row per matcher and metric).

    The matcher whose gap to every other is beyond noise on a headline metric is marked
    ``*`` (best) in the ``beyond noise`` column, and the pairs beyond noise are listed.
    """
    header = ["Metric", "Matcher", "mean", "std", "min", "max", "n", "beyond noise vs"]
    rows = []
    for spec in summary.specs:
        per = summary.metrics.get(spec.key)
        if not per:
            continue
        for m, s in per.items():
            marks = []
            if spec.headline:
                for o in summary.matchers:
                    p = summary.pair(spec.key, m, o) if o != m else None
                    if p is not None and p.beyond_noise:
                        word = "better" if p.better == m else "worse" if p.better else "differs"
                        marks.append(f"{word} than {o}")
            rows.append([spec.label, m, s.mean, s.std, s.min, s.max, s.n, "; ".join(marks) or "-"])
    return header, rows


def pairs_table(summary: SeedsSummary) -> tuple[list[str], list[list[Any]]]:
    """Paired differences ``a - b`` of the headline metrics, with the noise verdict."""
    header = ["Metric", "a", "b", "mean a-b", "SE", "n", "beyond noise", "p (t)", "p (Wilcoxon)"]
    labels = {s.key: s.label for s in summary.specs}
    rows = [
        [
            labels[p.metric],
            p.a,
            p.b,
            p.mean,
            p.se,
            p.n,
            ("yes: " + p.better + " better" if p.better else "yes") if p.beyond_noise else "no",
            p.p_ttest,
            p.p_wilcoxon,
        ]
        for p in summary.pairs
    ]
    return header, rows


def figure_seeds(summary: SeedsSummary, path: str | os.PathLike[str], dpi: int = 110) -> Path:
    """The headline over seeds: mean bars, std error bars, one dot per seed.

    A matcher whose gap to the best is within noise carries ``~`` above its bar; ``*``
    marks one beyond noise from the best (worse). Each panel names its direction.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    specs = [s for s in SEED_METRICS if s.headline and s.key in summary.metrics]
    names = summary.matchers
    fig = Figure(figsize=(max(3.0 * len(specs), 9.0), 4.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, max(len(specs), 1)))
    x = np.arange(len(names), dtype=float)
    for ax, spec in zip(axes, specs, strict=False):
        per = summary.metrics[spec.key]
        mean = np.array([np.nan if per[m].mean is None else per[m].mean for m in names])
        std = np.array([0.0 if per[m].std is None else per[m].std for m in names])
        ax.bar(x, np.nan_to_num(mean), 0.7, color=[f"C{i % 10}" for i in range(len(names))])
        ax.errorbar(x, np.nan_to_num(mean), yerr=std, fmt="none", ecolor="0.2", capsize=3)
        for xi, m in zip(x, names, strict=True):
            vals = [v for v in per[m].values if v is not None]
            ax.scatter(np.full(len(vals), xi), vals, s=12, c="black", zorder=3)
        ok = [i for i, v in enumerate(mean) if math.isfinite(v)]
        if ok and spec.better:
            best = (max if spec.better == "higher" else min)(ok, key=lambda i: mean[i])
            for i in ok:
                if i == best:
                    mark = "best"
                else:
                    p = summary.pair(spec.key, names[best], names[i])
                    mark = "*" if p is not None and p.beyond_noise else "~"
                top = max([mean[i] + std[i], *[v for v in per[names[i]].values if v is not None]])
                ax.text(x[i], top, mark, ha="center", va="bottom", fontsize=8, fontweight="bold")
        ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
        arrow = "\u2191" if spec.better == "higher" else "\u2193"
        ax.set_title(f"{spec.label}\n{arrow} {spec.better} is better", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
    fig.suptitle(
        f"Matchers over {len(summary.seeds)} seeds: mean, std (bars), seeds (dots); "
        f"* = gap to the best beyond noise (|mean paired diff| > {NOISE_SE:g} SE), "
        "~ = within noise",
        fontsize=9,
    )
    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    with atomic_path(path) as tmp:
        canvas.print_png(tmp)
    return Path(path)


def write_seeds_report(
    summary: SeedsSummary,
    folder: str | os.PathLike[str],
    *,
    title: str = "",
    links: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """Write ``seeds.json``, ``seeds.csv``, ``pairs.csv``, ``report.md``, ``report.html``.

    Args:
        summary: The summary.
        folder: Output folder.
        title: The report's title.
        links: Scene label -> its comparison folder (listed in the report).

    Returns:
        Paths by name, and ``"markdown"``: the summary as Markdown (what ``demo`` prints).
    """
    from planetref.report.document import Document
    from planetref.report.tables import format_csv, format_markdown_table

    folder = Path(folder)
    paths = {"seeds_json": str(write_json_atomic(folder / "seeds.json", summary.to_dict()))}
    sh, sr = seeds_table(summary)
    ph, pr = pairs_table(summary)
    paths["seeds_csv"] = str(write_text_atomic(folder / "seeds.csv", format_csv(sh, sr)))
    paths["pairs_csv"] = str(write_text_atomic(folder / "pairs.csv", format_csv(ph, pr)))
    fig = None
    if summary.matchers:
        fig = figure_seeds(summary, folder / "figures" / "headline_seeds.png")
        paths["headline"] = str(fig)
    n = len(summary.seeds)
    title = title or f"Matchers over {n} seeds"
    intro = (
        f"{n} scenes ({', '.join(summary.seeds)}); front-end protocol: {summary.protocol}. "
        f"A gap between two matchers is beyond noise when the mean of their paired "
        f"differences (same scene) exceeds {NOISE_SE:g} standard errors of those differences"
        + (
            f"; with {n} seeds this is a weak test (a paired t-test would need about "
            "4.3 SE at 3 seeds for p < 0.05; the Wilcoxon signed-rank test cannot reach "
            "p < 0.05 below 6 seeds)."
            if n < 6
            else "."
        )
    )
    doc = Document(title)
    doc.para(intro)
    doc.heading("Ranking")
    doc.items(summary.ranking or ["No metric with values."])
    doc.figure(
        fig,
        "Headline metrics over the seeds: bar = mean, error bar = std, dots = seeds; "
        "* = worse than the best beyond noise, ~ = within noise of the best.",
    )
    doc.heading("Mean and spread per matcher")
    doc.table("Every metric of Tables 1-2, the true error and the true OR over the seeds", sh, sr)
    doc.heading("Paired differences")
    doc.table("Paired differences a - b (same scene) of the headline metrics", ph, pr)
    if summary.failed:
        doc.heading("Failed runs")
        doc.items([f"`{m}`: {', '.join(s)}" for m, s in summary.failed.items()])
    if summary.skipped:
        doc.heading("Skipped matchers (could not run)")
        doc.items([f"`{m}`: {why}" for m, why in summary.skipped.items()])
    if links:
        doc.heading("Per-scene comparisons")
        doc.items([f"{k}: `{v}`" for k, v in links.items()])
    paths.update(doc.write(folder))
    md = [f"# {title}", "", intro, "", "## Ranking", ""]
    md += [f"- {r}" for r in summary.ranking] + ["", "## Mean and spread per matcher", ""]
    md += [format_markdown_table(sh, sr), "", "## Paired differences", ""]
    md += [format_markdown_table(ph, pr), ""]
    paths["markdown"] = "\n".join(md)
    return paths
