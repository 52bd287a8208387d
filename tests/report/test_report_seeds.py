"""Rankings over seeds: mean and spread per matcher, paired differences, the noise rule."""

from __future__ import annotations

import json
import math
import statistics

import pytest

from planetref.report.seeds import (
    SEED_METRICS,
    Spread,
    paired_difference,
    summarize_seeds,
    write_seeds_report,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _run(true_m, ncp=100, rmse=0.5, failed=False, tor3=5.0):
    if failed:
        return {
            "failed": "strip s1: only 0 matched control points",
            "matching": {"ncp": 0, "sdu_pct": 0.0, "tiles_failed": 6, "tiles_total": 6},
            "adjustment": None,
            "check": None,
        }
    return {
        "matching": {
            "ccds": {
                "ccd1": {"ncp": ncp - 40, "sdu_pct": 8.0},
                "ccd2": {"ncp": 40, "sdu_pct": 12.0},
            },
            "ncp": ncp,
            "sdu_pct": 10.0,
            "tiles_failed": 0,
            "tiles_total": 6,
            "true_outliers": {"pct_over_1px": 2 * tor3, "pct_over_3px": tor3},
            "settings": {"protocol": "default"},
        },
        "adjustment": {"rmse_px": rmse, "outlier_ratio_pct": 1.0, "mean_px": 0.4},
        "check": {
            "geoloc_rmse_m": true_m,
            "geoloc_max_m": 2 * true_m,
            "formal_rmse_m": true_m / 2,
            "true_over_formal": 2.0,
        },
        # what compare adds with three matchers or more: the excess error (m)
        "agreement": {"excess_m": 0.5 * true_m, "true_over_formal_with_excess": math.sqrt(2.0)},
    }


A = [1.0, 1.2, 1.1]
B = [2.0, 2.3, 2.1]  # a - b = -1.0, -1.1, -1.0: a clearly better
C = [1.05, 1.25, 1.0]  # a - c = -0.05, -0.05, +0.1: within noise


def _reports():
    return {
        f"seed{i}": {
            "scene": f"tiny-seed{i}",
            "runs": {
                "a": _run(A[i], ncp=100 + i),
                "b": _run(B[i], ncp=200 + 10 * i),
                "c": _run(C[i]) if i != 1 else _run(0, failed=True),
            },
            "skipped": {"loftr": "weights missing"},
        }
        for i in range(3)
    }


def test_spread_is_mean_sample_std_and_range():
    s = Spread.of([1.0, None, 2.0, 4.0, float("nan")])
    assert s.n == 3 and s.values[1] is None and s.values[4] is None
    assert s.mean == pytest.approx(7 / 3)
    assert s.std == pytest.approx(statistics.stdev([1.0, 2.0, 4.0]))
    assert (s.min, s.max) == (1.0, 4.0)
    one = Spread.of([3.0])
    assert one.std is None and one.mean == 3.0


def test_paired_difference_matches_an_independent_paired_t_test():
    from scipy import stats

    spec = next(s for s in SEED_METRICS if s.key == "geoloc_rmse_m")
    p = paired_difference("a", "b", spec, A, B)
    d = [x - y for x, y in zip(A, B, strict=True)]
    se = statistics.stdev(d) / math.sqrt(3)
    assert p.n == 3 and p.mean == pytest.approx(statistics.mean(d))
    assert p.se == pytest.approx(se)
    # t = mean / se with n - 1 degrees of freedom, two-sided.
    t = statistics.mean(d) / se
    assert p.p_ttest == pytest.approx(2 * stats.t.sf(abs(t), 2))
    assert p.beyond_noise and p.better == "a"  # lower true error is better
    assert p.p_wilcoxon is None  # below 6 seeds
    q = paired_difference("a", "c", spec, A, C)
    assert not q.beyond_noise and q.better is None
    # Higher is better for NCP: the larger one wins.
    ncp = next(s for s in SEED_METRICS if s.key == "ncp")
    r = paired_difference("x", "y", ncp, [10, 12, 11], [20, 23, 21])
    assert r.beyond_noise and r.better == "y"


def test_wilcoxon_from_six_seeds_and_a_constant_gap_is_beyond_noise():
    from scipy import stats

    spec = next(s for s in SEED_METRICS if s.key == "rmse_px")
    a = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    b = [v + 0.5 + 0.1 * i for i, v in enumerate(a)]
    p = paired_difference("a", "b", spec, a, b)
    d = [x - y for x, y in zip(a, b, strict=True)]
    assert p.p_wilcoxon == pytest.approx(stats.wilcoxon(d).pvalue)
    assert p.p_wilcoxon < 0.05 and p.beyond_noise
    same = paired_difference("a", "b", spec, [1.0, 2.0], [1.5, 2.5])
    assert same.se == 0.0 and same.beyond_noise and same.better == "a"


def test_summary_of_three_seeds_counts_failed_runs_and_ranks_with_the_seed_count(tmp_path):
    s = summarize_seeds(_reports())
    assert s.seeds == ["seed0", "seed1", "seed2"] and s.matchers == ["a", "b", "c"]
    true = s.metrics["geoloc_rmse_m"]
    assert true["a"].mean == pytest.approx(statistics.mean(A))
    assert true["a"].std == pytest.approx(statistics.stdev(A))
    # c failed at seed1: no true error there, NCP 0 counts.
    assert true["c"].n == 2 and true["c"].values[1] is None
    assert s.metrics["ncp"]["c"].n == 3 and s.metrics["ncp"]["c"].min == 0
    assert s.failed == {"c": ["seed1"]} and "loftr" in s.skipped
    assert s.metrics["true_or_3px_pct"]["a"].mean == pytest.approx(5.0)
    # Table 1 per CCD, after the totals.
    assert s.metrics["ncp_ccd1"]["a"].values == [60.0, 61.0, 62.0]
    assert s.metrics["sdu_ccd2"]["b"].mean == 12.0 and s.metrics["ncp_ccd1"]["c"].n == 2
    assert [sp.key for sp in s.specs][:4] == ["ncp", "sdu_pct", "ncp_ccd1", "ncp_ccd2"]
    ab = s.pair("geoloc_rmse_m", "b", "a")
    assert ab is not None and ab.beyond_noise and ab.better == "a"
    ac = s.pair("geoloc_rmse_m", "a", "c")
    assert ac is not None and ac.n == 2 and not ac.beyond_noise
    sentence = next(r for r in s.ranking if r.startswith("true error"))
    assert "over 3 seeds" in sentence and "weak test" in sentence
    # c (2 seeds) ~ a (within noise), then b behind a beyond noise.
    assert "c 1.02 +- 0.0354 ~ a 1.1 +- 0.1 >> b 2.13 +- 0.153" in sentence
    assert "(2/3 with a value)" in sentence

    paths = write_seeds_report(s, tmp_path, links={"seed0": "x"})
    doc = json.loads((tmp_path / "seeds.json").read_text())
    assert doc["n_seeds"] == 3 and doc["metrics"]["geoloc_rmse_m"]["b"]["mean"] == pytest.approx(
        statistics.mean(B)
    )
    assert (tmp_path / "figures" / "headline_seeds.png").read_bytes()[:8] == PNG
    md = paths["markdown"]
    assert "better than b" in md and "## Paired differences" in md
    from planetref.report.document import read_report_html

    page = read_report_html(tmp_path / "report.html")
    assert [n for n, _ in page.figures] == ["headline_seeds.png"]
    captions = [c for c, _ in page.tables]
    assert any("over the seeds" in c for c in captions)
    assert any("Paired differences" in c for c in captions)


def test_calibration_with_and_without_the_excess_over_seeds():
    """The seeds table carries true / formal and, from the comparison's three-cornered
    hat, the excess and true / formal with excess, per matcher over the seeds."""
    summary = summarize_seeds(_reports())
    keys = [sp.key for sp in summary.specs]
    assert {"true_over_formal", "excess_m", "true_over_formal_with_excess"} <= set(keys)
    a = summary.metrics["excess_m"]["a"]
    assert a.n == 3 and a.mean == pytest.approx(0.5 * sum(A) / 3)
    assert summary.metrics["true_over_formal"]["a"].mean == pytest.approx(2.0)
    assert summary.metrics["true_over_formal_with_excess"]["c"].n == 2  # seed 1 failed
