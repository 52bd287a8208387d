"""Figures and a statistic of the adjustment: residual vector fields and the headline.

* :func:`residual_pattern`: does a residual field hold a systematic pattern? The
  nearest-neighbour vector correlation ``C = sum_i v_i . m_i / sqrt(sum_i |v_i|^2
  sum_i |m_i|^2)``, with ``v_i`` the residual vector of point ``i`` and ``m_i`` the mean
  residual vector of its ``k`` nearest neighbours (image coordinates, same CCD). White
  noise gives ``C ~ 0``; a smooth field (an uncorrected systematic error) gives ``C``
  near 1. Significance by a permutation test (the vectors shuffled over the positions).
  A pattern is reported when ``C >= PATTERN_MIN_C`` and ``p <= PATTERN_MAX_P``.
* :func:`figure_residual_vectors`: the seed's Fig. 4: residuals per CCD, one panel each
  in its own image coordinates, with a reference arrow, check points and outliers, and
  the pattern note.
* :func:`figure_headline`: the comparison's headline (NCP, SDU, RMSE before/after, OR,
  true error before/after) with the scene, units and which direction is better.

Residuals are ``(line, sample)`` in pixels, projected minus observed (as
:mod:`planetref.adjust.metrics` defines them); ``x`` is the sample, ``y`` the line.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from planetref.report.ccd_panels import ccd_panels, finish_ccd_panel
from planetref.report.figures_matching import ccd_colour, save

__all__ = [
    "PATTERN_MAX_P",
    "PATTERN_MIN_C",
    "ResidualPattern",
    "figure_headline",
    "figure_jitter",
    "figure_residual_vectors",
    "residual_pattern",
]

PATTERN_MIN_C = 0.3
"""Nearest-neighbour vector correlation from which a residual field is called systematic."""
PATTERN_MAX_P = 0.01
"""Permutation p-value up to which the correlation counts as significant."""


@dataclass(frozen=True)
class ResidualPattern:
    """Spatial correlation of a residual vector field.

    Attributes:
        c: Nearest-neighbour vector correlation (see the module docstring); NaN if
            fewer than ``k + 2`` points.
        p_value: Permutation p-value of ``c`` (one-sided, ``c`` larger than chance).
        n: Points used.
        k: Neighbours per point.
        systematic: ``c >= PATTERN_MIN_C`` and ``p_value <= PATTERN_MAX_P``.
    """

    c: float
    p_value: float
    n: int
    k: int
    systematic: bool

    def note(self) -> str:
        """One line for a figure or report."""
        if not math.isfinite(self.c):
            return f"pattern test: too few points ({self.n})"
        verdict = (
            "SYSTEMATIC PATTERN: neighbouring residuals agree (an error the model does not "
            "absorb, or matching errors shared by neighbouring matches)\n"
            if self.systematic
            else "no systematic pattern"
        )
        return (
            f"{verdict} (nearest-neighbour correlation C = {self.c:.2f}, p = {self.p_value:.3f}, "
            f"k = {self.k}, n = {self.n}; flagged when C >= {PATTERN_MIN_C} and "
            f"p <= {PATTERN_MAX_P})"
        )


def _nn_corr(v: np.ndarray, nbr: np.ndarray) -> float:
    m = v[nbr].mean(axis=1)
    den = math.sqrt(float(np.sum(v * v)) * float(np.sum(m * m)))
    return float(np.sum(v * m)) / den if den > 0 else 0.0


def residual_pattern(
    line: ArrayLike,
    sample: ArrayLike,
    d_line: ArrayLike,
    d_sample: ArrayLike,
    *,
    group: ArrayLike | None = None,
    k: int = 6,
    n_permutations: int = 199,
    seed: int = 0,
) -> ResidualPattern:
    """Nearest-neighbour correlation of residual vectors and its permutation p-value.

    Args:
        line: Image line of each point (px).
        sample: Image sample (px).
        d_line: Line residual (px).
        d_sample: Sample residual (px).
        group: Per point a group label (e.g. the CCD): neighbours are found within the
            group only; permutations shuffle over all points, so that an offset shared
            by a group counts as a pattern too.
        k: Neighbours per point.
        n_permutations: Shuffles for the p-value (p >= 1 / (n_permutations + 1)).
        seed: Random seed of the shuffles.
    """
    from scipy.spatial import cKDTree

    pos = np.column_stack([np.asarray(line, float), np.asarray(sample, float)])
    v = np.column_stack([np.asarray(d_line, float), np.asarray(d_sample, float)])
    grp = np.zeros(len(pos), int) if group is None else np.unique(group, return_inverse=True)[1]
    ok = np.all(np.isfinite(pos), 1) & np.all(np.isfinite(v), 1)
    pos, v, grp = pos[ok], v[ok], grp[ok]
    members = [np.flatnonzero(grp == g) for g in np.unique(grp)]
    members = [m for m in members if len(m) >= k + 2]
    n = int(sum(len(m) for m in members))
    if not members:
        return ResidualPattern(float("nan"), float("nan"), len(pos), k, False)
    idx = np.concatenate(members)
    nbr_parts, offset = [], 0
    for m in members:
        _, nb = cKDTree(pos[m]).query(pos[m], k=k + 1)
        nbr_parts.append(nb[:, 1:] + offset)
        offset += len(m)
    nbr = np.concatenate(nbr_parts)
    vv = v[idx]
    c = _nn_corr(vv, nbr)
    rng = np.random.default_rng(seed)
    # Shuffling over every position (not within groups) also catches a per-CCD offset.
    hits = sum(_nn_corr(vv[rng.permutation(n)], nbr) >= c for _ in range(n_permutations))
    p = (hits + 1) / (n_permutations + 1)
    return ResidualPattern(c, p, n, k, bool(c >= PATTERN_MIN_C and p <= PATTERN_MAX_P))


def _nice(x: float) -> float:
    """A round arrow length (1, 2 or 5 times a power of ten) near ``x``."""
    if not x > 0 or not math.isfinite(x):
        return 1.0
    e = math.floor(math.log10(x))
    return min((m * 10.0**e for m in (1, 2, 5, 10)), key=lambda v: abs(math.log(v / x)))


def figure_residual_vectors(
    result: Any,
    image_sizes: Mapping[str, tuple[int, int]],
    path: str | os.PathLike[str],
    *,
    title: str = "",
    scale: float | None = None,
    dpi: int = 110,
) -> Path:
    """The seed's Fig. 4: residual vectors per CCD, each in its own image coordinates.

    Inliers are drawn as arrows in the CCD's colour, check points as black arrows,
    outliers as crosses. A reference arrow gives the length of a round number of pixels;
    the title says whether neighbouring residuals correlate (:func:`residual_pattern`).

    Args:
        result: An :class:`~planetref.adjust.result.AdjustmentResult` of one camera (or any
            object with ``network``, ``cameras``, ``residual`` and ``status``).
        image_sizes: CCD name -> ``(n_lines, n_samples)``, left to right.
        path: Output PNG.
        title: Figure title.
        scale: Image pixels drawn per pixel of residual (default: the 95th percentile
            residual drawn 6 % of the mean CCD width long).
        dpi: Resolution.
    """
    from matplotlib.lines import Line2D

    net = result.network
    cam = result.cameras[net.camera_ids[0]]
    names = np.array([cam.ccd_names[k] for k in net.obs_ccd])
    r = np.asarray(result.residual, float)
    status = np.asarray(result.status).astype(str)
    inl, chk, out = status == "inlier", status == "check", status == "outlier"
    order = list(image_sizes)
    widths = [image_sizes[c][1] for c in order]
    max_h = max(image_sizes[c][0] for c in order)
    length = np.hypot(r[inl | chk, 0], r[inl | chk, 1])
    length = length[np.isfinite(length)]
    p95 = float(np.percentile(length, 95)) if length.size else 1.0
    scale = scale or 0.06 * float(np.mean(widths)) / max(p95, 1e-6)
    ref_px = _nice(p95)
    pattern = residual_pattern(
        net.obs_line[inl], net.obs_sample[inl], r[inl, 0], r[inl, 1], group=names[inl]
    )
    fig, axes, _ = ccd_panels(image_sizes, order, 1.6)
    q = None
    for i, (ax, c) in enumerate(zip(axes, order, strict=True)):
        _nl, ns = image_sizes[c]
        on = names == c
        for sel, colour, lw in ((inl & on, ccd_colour(i), 0.004), (chk & on, "black", 0.005)):
            if sel.any():
                q = ax.quiver(
                    net.obs_sample[sel],
                    net.obs_line[sel],
                    r[sel, 1] * scale,
                    r[sel, 0] * scale,
                    angles="xy",
                    scale_units="xy",
                    scale=1.0,
                    width=lw,
                    color=colour,
                )
        if (out & on).any():
            ax.scatter(net.obs_sample[out & on], net.obs_line[out & on], s=14, marker="x", c="0.4")
        rms = float(np.sqrt(np.nanmean(np.sum(r[inl & on] ** 2, 1)))) if (inl & on).any() else 0.0
        ax.set_title(f"{c}: {int((inl & on).sum())} inliers, RMSE {rms:.2f} px", fontsize=8)
        finish_ccd_panel(ax, ns, max_h)
    axes[0].set_ylabel("line (px)", fontsize=8)
    if q is not None:
        q.axes.quiverkey(
            q,
            0.86,
            0.025,
            ref_px * scale,
            f"reference: {ref_px:g} px",
            labelpos="E",
            coordinates="figure",
            color="black",
            fontproperties={"size": 8},
        )
    handles = [
        Line2D([], [], color=ccd_colour(0), lw=1.5, label="inlier residual (CCD colour)"),
        Line2D([], [], color="black", lw=1.5, label=f"check point ({int(chk.sum())})"),
        Line2D([], [], color="0.4", marker="x", lw=0, label=f"outlier ({int(out.sum())})"),
    ]
    fig.legend(handles=handles, loc="outside lower left", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(
        (title or "residuals after adjustment")
        + f"\narrows magnified x{scale:.0f} (reference arrow {ref_px:g} px)\n"
        + pattern.note(),
        fontsize=8,
        color="#b2182b" if pattern.systematic else "black",
    )
    return save(fig, path, dpi)


OR_AXIS_TOP_PCT = 10.0
"""The headline's outlier-ratio axis runs from 0 to this (%) unless a value exceeds it."""


def _label(v: float) -> str:
    """A bar's value: whole numbers from 100 up, three significant digits below."""
    if not math.isfinite(v):
        return "n/a"
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return float("nan")
    return f if math.isfinite(f) else float("nan")


def _panels(runs: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """What the headline draws: per panel a label, direction, values and spreads."""
    names = list(runs)

    def per(get: Any) -> list[float]:
        out = []
        for n in names:
            try:
                out.append(_num(get(runs[n])))
            except (KeyError, TypeError, AttributeError):
                out.append(float("nan"))
        return out

    def spread(get: Any) -> list[list[float]]:
        out = []
        for n in names:
            try:
                out.append([_num(v) for v in get(runs[n])])
            except (KeyError, TypeError, AttributeError):
                out.append([])
        return out

    adj = lambda r: r["adjustment"]  # noqa: E731
    panels = [
        {
            "label": "NCP (matched control points)",
            "unit": "count",
            "better": "higher",
            "after": per(lambda r: r["matching"]["ncp"]),
            "dots": spread(lambda r: [v["ncp"] for v in r["matching"]["ccds"].values()]),
            "dots_label": "per CCD",
        },
        {
            "label": "SDU (spatial distribution)",
            "unit": "%",
            "better": "higher",
            "after": per(lambda r: r["matching"]["sdu_pct"]),
            "dots": spread(lambda r: [v["sdu_pct"] for v in r["matching"]["ccds"].values()]),
            "dots_label": "per CCD",
        },
        {
            "label": "RMSE of image residuals",
            "unit": "px",
            "better": "lower",
            "before": per(lambda r: adj(r)["rmse_px_before"]),
            "after": per(lambda r: adj(r)["rmse_px"]),
            "dots": spread(lambda r: [v["rmse_px"] for v in adj(r).get("ccds", {}).values()]),
            "dots_label": "per CCD",
        },
        {
            "label": "OR (outlier ratio)",
            "unit": "%",
            "better": "lower",
            "after": per(lambda r: adj(r)["outlier_ratio_pct"]),
            "dots": [[] for _ in names],
            # A fixed 0-10 % axis (wider only when a value exceeds it): on an axis fitted
            # to the values, 0.07 % against zeros fills the panel and looks like the worst
            # of results; the seed paper's outlier ratios are a few per cent.
            "axis_top": OR_AXIS_TOP_PCT,
        },
    ]
    if any(r.get("check") for r in runs.values()):
        chk = lambda r: r["check"]  # noqa: E731
        panels.append(
            {
                "label": "true geolocation error",
                "unit": "m",
                "better": "lower",
                "before": per(lambda r: chk(r)["geoloc_rmse_m_before"]),
                "after": per(lambda r: chk(r)["geoloc_rmse_m"]),
                "dots": spread(
                    lambda r: [v["after"]["rms_m"] for v in chk(r).get("ccds", {}).values()]
                ),
                "dots_label": "per CCD",
                "max": per(lambda r: chk(r)["geoloc_max_m"]),
            }
        )
    return panels


def figure_headline(
    runs: Mapping[str, Mapping[str, Any]],
    path: str | os.PathLike[str],
    *,
    scene: str = "",
    dpi: int = 110,
) -> Path:
    """The comparison's headline figure: one panel per metric, one bar per matcher.

    Bars are the values after the adjustment; where a value before exists (RMSE, true
    error) it is drawn as a hollow bar beside it; dots give the per-CCD spread; the true
    error has a whisker to its maximum. Each panel names its unit and which direction is
    better; every bar carries its value. The axes are linear from 0: they fit the values
    after the adjustment, and a value before that is more than 3x larger is cut at the
    top of the panel (an upward arrow and its value mark it); the outlier ratio's axis
    runs to at least :data:`OR_AXIS_TOP_PCT`.

    Args:
        runs: Matcher -> its georef report (report.json content).
        path: Output PNG.
        scene: Scene name for the title.
        dpi: Resolution.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    names = list(runs)
    panels = _panels(runs)
    fig = Figure(figsize=(max(3.0 * len(panels), 9.0), 4.2), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    x = np.arange(len(names), dtype=float)
    for ax, p in zip(axes, panels, strict=True):
        after = np.asarray(p["after"], float)
        has_before = "before" in p
        w = 0.38 if has_before else 0.7
        xa = x + (w / 2 if has_before else 0.0)
        colours = [f"C{i % 10}" for i in range(len(names))]
        ax.bar(xa, np.nan_to_num(after), w, color=colours)
        tops = np.nan_to_num(after).copy()
        for j, (xi, d) in enumerate(zip(xa, p.get("dots", []), strict=False)):
            d = [v for v in d if math.isfinite(v)]
            if d:
                ax.scatter(np.full(len(d), xi), d, s=90, c="black", zorder=3, marker="_", lw=1.2)
                tops[j] = max(tops[j], max(d))
        if "max" in p:
            mx = np.asarray(p["max"], float)
            ax.errorbar(
                xa,
                np.nan_to_num(after),
                yerr=[np.zeros_like(after), np.nan_to_num(np.maximum(mx - after, 0))],
                fmt="none",
                ecolor="0.2",
                capsize=3,
                lw=0.8,
            )
            tops = np.fmax(tops, np.nan_to_num(mx))
        # Linear axes only (bars on a log axis have no meaningful length). The axis fits
        # the values after the adjustment; a value before that is far larger runs off the
        # top of the panel, marked and labelled with its value.
        top = 1.18 * float(np.max(tops)) if np.max(tops) > 0 else 1.0
        top = max(top, float(p.get("axis_top", 0.0)))
        if has_before:
            before = np.asarray(p["before"], float)
            # Within 3x of the values after, the bars before are drawn whole; beyond,
            # they would squash those values to slivers.
            highest = float(np.max(np.nan_to_num(np.r_[before, 0.0])))
            if highest <= 3.0 * top:
                top = max(top, 1.18 * highest)
            drawn = np.minimum(np.nan_to_num(before), top)
            ax.bar(x - w / 2, drawn, w, color="white", edgecolor="0.35", hatch="//")
            for xi, v, d in zip(x - w / 2, before, drawn, strict=True):
                if not math.isfinite(v):
                    continue
                if d < v:  # cut at the top of the axis: say so, and give the value
                    ax.text(
                        xi,
                        top * 0.985,
                        f"\u2191{_label(v)}",
                        ha="center",
                        va="top",
                        fontsize=6,
                        color="0.2",
                        rotation=90,
                        bbox={"facecolor": "white", "edgecolor": "none", "pad": 0.5},
                    )
                else:
                    ax.text(xi, v, _label(v), ha="center", va="bottom", fontsize=6, color="0.35")
        for xi, v, t in zip(xa, after, tops, strict=True):
            ax.text(
                xi,
                t,
                _label(v),
                ha="center",
                va="bottom",
                fontsize=7,
                fontweight="bold",
            )
        ax.set_ylim(0, top)
        if np.all(np.nan_to_num(after) == 0) and not has_before:
            ax.text(
                0.5,
                0.5,
                "0 for every matcher",
                transform=ax.transAxes,
                ha="center",
                fontsize=8,
                color="0.3",
            )
        ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(f"{p['label'].split(' (')[0]} ({p['unit']})", fontsize=8)
        arrow = "\u2191" if p["better"] == "higher" else "\u2193"
        ax.set_title(f"{p['label']}\n{arrow} {p['better']} is better", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
    legend = [
        Patch(
            facecolor="white",
            edgecolor="0.35",
            hatch="//",
            label="before adjustment (\u2191 value: cut at the top of the axis)",
        ),
        Patch(facecolor="C0", label="after adjustment (one colour per matcher)"),
        Patch(facecolor="black", label="dashes: per-CCD values; whisker: maximum"),
    ]
    fig.legend(
        handles=legend,
        loc="outside lower center",
        ncol=3,
        fontsize=7,
        frameon=False,
    )
    fig.suptitle(f"Matcher comparison{': ' + scene if scene else ''}", fontsize=11)
    return save(fig, path, dpi)


def figure_jitter(
    time_s: ArrayLike,
    jitter_urad: ArrayLike,
    sigma_urad: ArrayLike,
    path: str | os.PathLike[str],
    *,
    truth_urad: ArrayLike | None = None,
    limit_hz: float | None = None,
    title: str = "",
    dpi: int = 110,
) -> Path:
    """The estimated jitter per axis: time series (with 2 sigma) and amplitude spectrum.

    Args:
        time_s: Times of the dense nodes (s), ``(m,)``, evenly spaced.
        jitter_urad: Estimated roll, pitch, yaw (urad), ``(m, 3)``.
        sigma_urad: Their formal sigmas (urad), ``(m, 3)``.
        path: Output PNG.
        truth_urad: The truth's pointing relative to the seed (urad), ``(m, 3)``, or
            ``None``; drawn less its quadratic trend (the seed's smooth error), axes
            with NaN not drawn.
        limit_hz: The resolution limit, drawn on the spectra.
        title: Figure title.
        dpi: Resolution.
    """
    from matplotlib.figure import Figure

    t = np.asarray(time_s, float)
    est = np.asarray(jitter_urad, float)
    sig = np.asarray(sigma_urad, float)
    tru = None if truth_urad is None else np.asarray(truth_urad, float)
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    axes = fig.subplots(3, 2, width_ratios=(2.2, 1.0))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    freq = np.fft.rfftfreq(len(t), dt)

    def spectrum(y: np.ndarray) -> np.ndarray:
        # Single-sided amplitude of a Hann-windowed series (a sinusoid of amplitude A
        # peaks near A).
        w = np.hanning(len(y))
        return np.asarray(2.0 * np.abs(np.fft.rfft((y - y.mean()) * w)) / w.sum())

    for k, name in enumerate(("roll", "pitch", "yaw")):
        ax, sp = axes[k]
        ax.fill_between(t, est[:, k] - 2 * sig[:, k], est[:, k] + 2 * sig[:, k],
                        color="tab:blue", alpha=0.2, lw=0, label="2 sigma (formal)")  # fmt: skip
        ax.plot(t, est[:, k], color="tab:blue", lw=1.2, label="estimated")
        sp.plot(freq, spectrum(est[:, k]), color="tab:blue", lw=1.2, label="estimated")
        if tru is not None and np.all(np.isfinite(tru[:, k])):
            # The truth relative to the node model holds the node model's own smooth
            # error too; its quadratic trend is taken out to show the jitter.
            base = np.stack([(t - t.mean()) ** q for q in range(3)], 1)
            y = tru[:, k] - base @ np.linalg.lstsq(base, tru[:, k], rcond=None)[0]
            ax.plot(t, y, color="black", lw=0.9, ls="--", label="truth (trend removed)")
            sp.plot(freq, spectrum(y), color="black", lw=0.9, ls="--", label="truth")
        if limit_hz is not None and math.isfinite(limit_hz):
            sp.axvline(limit_hz, color="tab:red", lw=0.8, label="resolution limit")
        ax.set_ylabel(f"{name} (urad)")
        sp.set_ylabel("amplitude (urad)")
        ax.grid(alpha=0.3)
        sp.grid(alpha=0.3)
    axes[2][0].set_xlabel("time (s)")
    axes[2][1].set_xlabel("frequency (Hz)")
    axes[0][0].legend(fontsize=7, loc="upper right")
    axes[0][1].legend(fontsize=7, loc="upper right")
    if title:
        fig.suptitle(title)
    return save(fig, path, dpi)
