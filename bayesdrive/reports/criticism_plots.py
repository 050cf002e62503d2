"""Pictures of a criticism run: one figure per family of checks, and the gains of the causes.

Every function takes a :class:`~bayesdrive.criticism.criticize.CriticismResult` (or its checks) and
writes PNG files with matplotlib's Agg backend; nothing here computes a statistic.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from bayesdrive.criticism.checks import Check
from bayesdrive.criticism.criticize import CriticismResult
from bayesdrive.data.atomic import write_atomic

__all__ = ["plot_criticism"]

# Kolmogorov's 5% critical value for the sup of a Brownian bridge.
CUSUM_CRITICAL = 1.358


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return path


def _by_name(checks: list[Check]) -> dict[str, Check]:
    return {c.name: c for c in checks}


def _calibration(check: Check, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    counts, edges = check.figure["counts"], check.figure["edges"]
    ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="#7a9cc6", edgecolor="k")
    ax.axhline(counts.sum() / len(counts), color="k", ls="--", lw=1, label="uniform")
    ax.set_xlabel("PIT of the observed position increment")
    ax.set_ylabel("held-out steps")
    ax.set_title(
        f"{check.title}\ncoverage 50%: {check.figure['coverage_50']:.2f}, "
        f"90%: {check.figure['coverage_90']:.2f}; chi2 p = {check.p_value:.2g}",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    return _save(fig, path)


def _correlations(acf: Check, ccf: Check, path: Path) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    ax = axes[0]
    lags = acf.figure["lags"]
    ax.bar(lags, acf.figure["acf"], color="#7a9cc6")
    ax.plot(lags, acf.figure["band"], "k--", lw=1, label="95% white-noise band")
    ax.plot(lags, -acf.figure["band"], "k--", lw=1)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("lag (steps)")
    ax.set_ylabel("autocorrelation of z")
    ax.set_title(f"{acf.title}\nlag 1: {acf.statistic:.3f}, p = {acf.p_value:.2g}", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[1]
    lags_s = ccf.figure["lags_s"]
    ax.bar(lags_s, ccf.figure["ccf"], width=0.8 * (lags_s[1] - lags_s[0]), color="#c68f7a")
    ax.plot(lags_s, ccf.figure["band"], "k--", lw=1)
    ax.plot(lags_s, -ccf.figure["band"], "k--", lw=1)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("lag of the leader's acceleration (s)")
    ax.set_ylabel("correlation with z")
    ax.set_title(f"{ccf.title}\np (Bonferroni over lags) = {ccf.p_value:.2g}", fontsize=9)
    return _save(fig, path)


def _covariates(checks: dict[str, Check], path: Path) -> Path:
    keys = [name.removeprefix("variance_vs_") for name in checks if name.startswith("variance_vs_")]
    fig, axes = plt.subplots(2, len(keys), figsize=(3.2 * len(keys), 5.6), squeeze=False)
    for col, key in enumerate(keys):
        for row, kind in enumerate(("variance", "mean")):
            check = checks[f"{kind}_vs_{key}"]
            ax = axes[row, col]
            f = check.figure
            ax.errorbar(f["centres"], f["means"], yerr=2 * f["ses"], fmt="o-", ms=3, lw=1)
            ax.axhline(0, color="k", ls="--", lw=1)
            ax.set_xlabel(f["label"], fontsize=8)
            if col == 0:
                ax.set_ylabel("mean of z^2 - 1" if kind == "variance" else "mean of z", fontsize=8)
            ax.set_title(f"r = {check.statistic:.3f}, p = {check.p_value:.2g}", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("Residual variance (top) and mean (bottom) against covariates, +-2 se", fontsize=9)
    return _save(fig, path)


def _change_points(check: Check, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for trace in check.figure["paths"]:
        ax.plot(np.linspace(0, 1, len(trace)), trace, lw=0.7, alpha=0.6)
    for sign in (-1, 1):
        ax.axhline(sign * CUSUM_CRITICAL, color="k", ls="--", lw=1)
    ax.set_xlabel("fraction of the held-out window")
    ax.set_ylabel("standardised CUSUM of z")
    return _save_vehicle_share(fig, ax, check, "cross the 5% line", path)


def _save_vehicle_share(fig, ax, check: Check, flagged_means: str, path: Path) -> Path:
    """Title a per-vehicle test's figure with how many vehicles it flags, and save it."""
    ax.set_title(
        f"{textwrap.fill(check.title, 70)}\n{check.summary['flagged']} of "
        f"{check.summary['vehicles']} vehicles {flagged_means}; p = {check.p_value:.2g}",
        fontsize=9,
    )
    return _save(fig, path)


def _gain_drift(check: Check, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    block_s = check.figure["block_s"]
    for gains, p in zip(check.figure["slopes"], check.figure["p_values"], strict=True):
        ax.plot(
            block_s * (np.arange(len(gains)) + 0.5),
            gains,
            "o-" if p < 0.05 else "-",
            ms=3,
            lw=1.2 if p < 0.05 else 0.6,
            alpha=0.8 if p < 0.05 else 0.4,
        )
    ax.axhline(0, color="k", ls="--", lw=1)
    ax.set_xlabel(f"time in the record (s), centres of {block_s:g} s blocks")
    ax.set_ylabel("block gain - the vehicle's mean\n(z per m/s^2 of predicted acceleration)")
    return _save_vehicle_share(fig, ax, check, "differ at 5% (marked)", path)


def _multistep(check: Check, path: Path) -> Path:
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    f = check.figure
    axes[0].plot(f["time_s"], f["coverage"], "o-", ms=2)
    axes[0].axhline(0.9, color="k", ls="--", lw=1, label="nominal 90%")
    axes[0].set_ylim(0, 1.02)
    axes[0].set_xlabel("horizon (s)")
    axes[0].set_ylabel("coverage of the observed position")
    axes[0].legend(fontsize=8)
    axes[1].plot(f["time_s"], f["rmse"], "o-", ms=2)
    axes[1].set_xlabel("horizon (s)")
    axes[1].set_ylabel("position RMSE (m)")
    example = f["example"]
    for trace in example:
        axes[2].plot(f["time_s"], trace, color="#7a9cc6", lw=0.6, alpha=0.6)
    axes[2].axhline(0, color="k", lw=1.2, label="observed")
    axes[2].set_xlabel("time in window (s)")
    axes[2].set_ylabel("simulated - observed position (m)")
    axes[2].set_title("first held-out window", fontsize=9)
    axes[2].legend(fontsize=8)
    fig.suptitle(
        f"{check.title}: end-of-horizon coverage {check.statistic:.2f} "
        f"over {check.summary['windows']} windows",
        fontsize=9,
    )
    return _save(fig, path)


def _per_vehicle_values(check: Check) -> np.ndarray:
    return np.asarray(check.figure.get("scores", check.figure.get("values", [])), float)


def _per_vehicle_label(check: Check) -> str:
    """What a screening check's per-vehicle value is, for its y axis."""
    if "parameter" in check.summary:
        return f"held-out score in {check.summary['parameter']}"
    if "per_vehicle" in check.summary:
        return check.summary["per_vehicle"]
    return check.title.removeprefix("Per-vehicle ").removesuffix(", across vehicles")


def _by_vehicle(checks: list[Check], path: Path) -> Path:
    """The screening checks with one value per vehicle: each vehicle's value, their mean +-2 se,
    and the zero line. Screening checks without per-vehicle values (change points) have their own
    figure and get no empty panel here."""
    screening = [c for c in checks if c.screening and _per_vehicle_values(c).size]
    cols = min(4, len(screening))
    rows = int(np.ceil(len(screening) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat[len(screening) :]:
        ax.set_visible(False)
    rng = np.random.default_rng(0)  # horizontal jitter of the dots only
    for ax, check in zip(axes.flat, screening, strict=False):
        values = _per_vehicle_values(check)
        ax.plot(rng.uniform(-0.2, 0.2, values.size), values, "o", ms=3, alpha=0.7)
        se = values.std(ddof=1) / np.sqrt(values.size) if values.size > 1 else 0.0
        ax.errorbar([0.5], [values.mean()], yerr=[2 * se], fmt="s", color="k", ms=4)
        ax.axhline(0, color="k", ls="--", lw=0.8)
        ax.set_xticks([0.0, 0.5], ["vehicles", "mean"], fontsize=8)
        ax.set_xlim(-0.5, 1.0)
        ax.set_ylabel(_per_vehicle_label(check), fontsize=8, wrap=True)
        title = check.name.removeprefix("score_").replace("_", " ")
        ax.set_title(f"{title}\np = {check.p_value:.2g}", fontsize=9)
        ax.tick_params(labelsize=8)
    fig.suptitle(
        "Screening checks: one value per vehicle (dots), mean +-2 se (square)", fontsize=10
    )
    return _save(fig, path)


# The causes figure's bar colours: better than the current model, worse, neither.
BETTER, WORSE, NEUTRAL = "#4a9a4a", "#c0504d", "#999999"


def _causes(result: CriticismResult, path: Path) -> Path:
    report = result.report
    scores = {
        c.name.removeprefix("score_"): c for c in result.checks if c.name.startswith("score_")
    }
    names = [c["name"] for c in report["causes"]]
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    y = np.arange(len(names))
    axes[0].barh(y, [scores[n].statistic if n in scores else 0.0 for n in names], color="#7a9cc6")
    axes[0].axvline(1.2816, color="k", ls="--", lw=1, label="one-sided 10%")
    axes[0].set_yticks(y, names, fontsize=8)
    axes[0].set_xlabel("score-test z (held-out)")
    axes[0].legend(fontsize=8)
    for ax, part, field, se_field, label in (
        (axes[1], "gain", "elpd", "se", "held-out elpd gain (nats)"),
        (
            axes[2],
            "gain",
            "rmse_position_change",
            "rmse_position_change_se",
            "rollout RMSE change (m)",
        ),
        (
            axes[3],
            "forecast",
            "energy_score_gain",
            "energy_score_gain_se",
            "forecast gain: energy score, current - extension",
        ),
    ):
        gains = [c.get(part) for c in report["causes"]]
        # None: not fitted, or not computable (e.g. no rollouts, a non-finite density).
        values = [g[field] if g and g[field] is not None else np.nan for g in gains]
        errors = [2 * g[se_field] if g and g[se_field] is not None else 0.0 for g in gains]
        if field == "rmse_position_change":  # no test decides this change: its sign, +-2 se
            colours = [
                BETTER if v + e < 0 else WORSE if v - e > 0 else NEUTRAL
                for v, e in zip(values, errors, strict=True)
            ]
        else:
            colours = [BETTER if g and g["significant"] else NEUTRAL for g in gains]
        ax.barh(y, values, xerr=errors, color=colours)
        ax.axvline(0, color="k", lw=0.8)
        ax.set_yticks(y, [] if ax is not axes[0] else names)
        ax.set_xlabel(label + ", +-2 se")
    axes[1].set_title(f"verdict: {report['verdict']} (green: significant after Holm)", fontsize=9)
    axes[2].set_title("green: lower, red: higher, by more than 2 se", fontsize=9)
    adopted = ", ".join(report.get("adopted", [])) or "nothing"
    axes[3].set_title(f"adopted: {adopted} (green: better after Holm)", fontsize=9)
    return _save(fig, path)


def plot_criticism(result: CriticismResult, out_dir: str | Path) -> list[Path]:
    """Write every criticism figure into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    checks = _by_name(result.checks)
    written = [
        _calibration(checks["calibration"], out / "calibration.png"),
        _correlations(
            checks["autocorrelation"], checks["leader_cross_correlation"], out / "correlations.png"
        ),
        _covariates(
            {k: v for k, v in checks.items() if k.startswith(("variance_vs_", "mean_vs_"))},
            out / "covariates.png",
        ),
        _change_points(checks["change_points"], out / "change_points.png"),
        _gain_drift(checks["gain_drift"], out / "gain_drift.png"),
        _by_vehicle(result.checks, out / "screening.png"),
        _causes(result, out / "causes.png"),
    ]
    if checks["multistep"].figure:
        written.append(_multistep(checks["multistep"], out / "multistep.png"))
    return written
