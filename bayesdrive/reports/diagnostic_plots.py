"""Pictures of engine diagnostics: marginal overlays, agreement heat maps, SBC rank ECDFs.

Figures are drawn on matplotlib ``Figure`` objects with the Agg canvas (no pyplot, no global
backend switch) and written atomically as PNG.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure

from bayesdrive.data.atomic import write_atomic
from bayesdrive.inference.diagnostics.agreement import MEAN_TOLERANCE_SD
from bayesdrive.inference.diagnostics.sbc import SBCOutcome

__all__ = ["plot_agreement_heatmap", "plot_marginals", "plot_rank_ecdf", "save_figure"]

# Engines keep their colour across every figure.
ENGINE_COLOURS = {
    "smc": "#1f77b4",
    "nuts": "#d62728",
    "emcee": "#2ca02c",
    "pf": "#9467bd",
    "lm": "#8c564b",
}
FALLBACK_COLOURS = ("#ff7f0e", "#17becf", "#bcbd22", "#7f7f7f", "#e377c2")


def save_figure(figure: Figure, path: Path) -> Path:
    """Render ``figure`` with the Agg canvas and write it as PNG atomically."""
    FigureCanvasAgg(figure)
    path = Path(path)
    write_atomic(path, lambda tmp: figure.savefig(tmp, format="png", dpi=110))
    return path


def _colour(label: str, index: int) -> str:
    return ENGINE_COLOURS.get(label, FALLBACK_COLOURS[index % len(FALLBACK_COLOURS)])


def plot_marginals(
    trees: Mapping[str, xr.DataTree],
    out_dir: Path,
    *,
    vehicles: Sequence[str] | None = None,
    max_vehicles: int = 15,
    bins: int = 40,
) -> list[Path]:
    """One PNG per parameter: each vehicle's marginal posterior density, one outline per result.

    ``trees`` maps a label (engine) to a result; vehicles default to the first ``max_vehicles``
    that every result has. Histograms share bins within a panel, so outlines compare directly.
    """
    posteriors = {label: tree["posterior"].to_dataset() for label, tree in trees.items()}
    first = next(iter(posteriors.values()))
    shared = [
        v
        for v in map(str, first["vehicle"].values)
        if all(v in set(map(str, p["vehicle"].values)) for p in posteriors.values())
    ]
    chosen = list(vehicles) if vehicles is not None else shared[:max_vehicles]
    params = [n for n in first.data_vars if all(n in p for p in posteriors.values())]
    columns = min(5, len(chosen))
    rows = math.ceil(len(chosen) / columns)
    written = []
    for name in params:
        figure = Figure(figsize=(3.0 * columns, 2.3 * rows + 0.6), layout="constrained")
        axes = figure.subplots(rows, columns, squeeze=False)
        for panel, vehicle in enumerate(chosen):
            ax = axes.flat[panel]
            draws = {
                label: np.asarray(p[name].sel(vehicle=vehicle).values, dtype=float).ravel()
                for label, p in posteriors.items()
            }
            low = min(np.quantile(d, 0.001) for d in draws.values())
            high = max(np.quantile(d, 0.999) for d in draws.values())
            edges = np.linspace(low, high, bins + 1) if high > low else bins
            for index, (label, values) in enumerate(draws.items()):
                ax.hist(
                    values,
                    bins=edges,
                    density=True,
                    histtype="step",
                    linewidth=1.3,
                    color=_colour(label, index),
                    label=label,
                )
            ax.set_title(vehicle, fontsize=8)
            ax.tick_params(labelsize=7)
            ax.set_yticks([])
        for ax in list(axes.flat)[len(chosen) :]:
            ax.set_visible(False)
        handles, labels = axes.flat[0].get_legend_handles_labels()
        figure.legend(handles, labels, loc="outside lower center", ncols=len(labels), fontsize=8)
        figure.suptitle(f"posterior of {name} per vehicle", fontsize=10)
        written.append(save_figure(figure, Path(out_dir) / f"marginals_{name}.png"))
    return written


def plot_agreement_heatmap(table: pd.DataFrame, path: Path) -> Path:
    """Per engine pair, |difference of means| in posterior sds for every vehicle and parameter.

    Colour bands: below the 0.1 sd criterion, up to 0.5, up to 1, above 1. Cells that fail the
    agreement criterion (means or sds) are marked with a cross.
    """
    pairs = list(dict.fromkeys(zip(table["a"], table["b"], strict=True)))
    params = list(dict.fromkeys(table["param"]))
    vehicles = list(dict.fromkeys(table["vehicle"]))
    colours = ["#e8f5e9", "#fff3b0", "#ffb74d", "#d32f2f"]
    # The last band is open-ended: anything above 1 sd takes its colour.
    cmap = ListedColormap(colours).with_extremes(over=colours[-1])
    norm = BoundaryNorm([0.0, MEAN_TOLERANCE_SD, 0.5, 1.0, 2.0], cmap.N)
    columns = min(3, len(pairs))
    rows_of_panels = math.ceil(len(pairs) / columns)
    figure = Figure(
        figsize=(
            1.5 + 0.55 * len(params) * columns + 1.0 * columns,
            (1.2 + 0.26 * len(vehicles)) * rows_of_panels + 0.6,
        ),
        layout="constrained",
    )
    grid_axes = figure.subplots(rows_of_panels, columns, squeeze=False)
    for ax in list(grid_axes.flat)[len(pairs) :]:
        ax.set_visible(False)
    axes = list(grid_axes.flat)[: len(pairs)]
    image = None
    for ax, (a, b) in zip(axes, pairs, strict=True):
        rows = table[(table["a"] == a) & (table["b"] == b)]
        grid = rows.pivot(index="vehicle", columns="param", values="mean_diff_sd")
        grid = grid.reindex(index=vehicles, columns=params).abs()
        fails = rows.pivot(index="vehicle", columns="param", values="agree")
        fails = ~fails.reindex(index=vehicles, columns=params).astype(bool)
        image = ax.imshow(grid.to_numpy(), cmap=cmap, norm=norm, aspect="auto")
        for i, j in zip(*np.nonzero(fails.to_numpy()), strict=True):
            ax.text(j, i, "x", ha="center", va="center", fontsize=8, color="black")
        ax.set_xticks(range(len(params)), params, rotation=45, ha="right", fontsize=8)
        ax.set_yticks(range(len(vehicles)), vehicles, fontsize=7)
        ax.set_title(f"{b} vs {a}", fontsize=9)
    bar = figure.colorbar(image, ax=list(grid_axes.flat), ticks=[0.05, 0.3, 0.75, 1.5], shrink=0.5)
    bar.ax.set_yticklabels(["< 0.1", "0.1-0.5", "0.5-1", "> 1"], fontsize=8)
    bar.set_label("|difference of means| / posterior sd", fontsize=8)
    figure.suptitle("engine agreement (x: fails |Δmean| or sd-ratio criterion)", fontsize=10)
    return save_figure(figure, path)


RANK_PANELS_PER_ROW = 4


def plot_rank_ecdf(outcome: SBCOutcome, path: Path) -> Path:
    """SBC ranks as ArviZ's PIT-ECDF difference plot (``arviz_plots.plot_ecdf_pit``), one panel
    per parameter: no binning, and ArviZ's own simultaneous uniformity test marks the ranks that
    depart. The verdict in the title is bayesdrive's (chi-square, Bonferroni over parameters).

    A rank r of L + 1 possible is shown at the PIT (r + 0.5) / (L + 1), the centre of its cell.
    """
    import arviz_plots

    pit = (outcome.ranks + 0.5) / (outcome.num_ranks + 1)
    sbc = xr.Dataset(
        {name: (("chain", "draw"), pit[None, :, k]) for k, name in enumerate(outcome.names)}
    )
    # Panels wrap after RANK_PANELS_PER_ROW; the figure grows a row's height for each row, so
    # a second row does not squeeze the panels to nothing.
    columns = min(len(outcome.names), RANK_PANELS_PER_ROW)
    rows = math.ceil(len(outcome.names) / columns)
    collection = arviz_plots.plot_ecdf_pit(
        xr.DataTree.from_dict({"prior_sbc": sbc}),
        backend="matplotlib",
        col_wrap=columns,
        figure_kwargs={
            "figsize": (max(7.0, 3.2 * columns), 2.6 * rows + 0.9),
            "layout": "constrained",
        },
        visuals={
            "xlabel": {"text": "rank of the truth / (draws + 1)"},
            "ylabel": {"text": "ECDF - uniform CDF"},
        },
    )
    figure = collection.viz.ds["figure"].item()
    verdict = "no miscalibration found" if outcome.calibrated else "MISCALIBRATED"
    worst = float(np.min(outcome.chi2_pvalue))
    figure.suptitle(
        f"SBC {outcome.engine} fitting {outcome.fit_model}: {outcome.ranks.shape[0]} "
        f"replications, {outcome.num_steps} steps\n{verdict} at alpha={outcome.alpha} "
        f"(chi-square, Bonferroni; smallest p {worst:.2g}); p in panels: ArviZ's ECDF test",
        fontsize=9,
    )
    return save_figure(figure, path)
