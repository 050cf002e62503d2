"""The SUMO round trip's picture: gap, speed and acceleration distributions of the data, SUMO's
and bayesdrive's rollouts of the same drivers, side by side (``bayesdrive validate sumo``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from bayesdrive.reports.diagnostic_plots import save_figure

__all__ = ["SOURCE_LABELS", "plot_sumo_distributions"]

# Source -> legend label; drawn in this order, SUMO dashed over bayesdrive so both show.
SOURCE_LABELS = {
    "data": "data (recorded follower)",
    "bayesdrive_predictive": "bayesdrive: posterior draws with execution noise",
    "bayesdrive": "bayesdrive: exported drivers, no noise",
    "sumo": "SUMO: exported drivers",
    "sumo_control": "SUMO control: a parameter halved (must fail)",
}
_STYLES = {
    "data": {"color": "black", "linewidth": 2.2},
    "bayesdrive_predictive": {"color": "#2ca02c", "linewidth": 1.4},
    "bayesdrive": {"color": "#1f77b4", "linewidth": 3.0, "alpha": 0.6},
    "sumo": {"color": "#d62728", "linewidth": 1.4, "linestyle": "--"},
    "sumo_control": {"color": "#ff7f0e", "linewidth": 1.4, "linestyle": ":"},
}


def plot_sumo_distributions(
    samples: Mapping[str, Mapping[str, np.ndarray]],
    units: Mapping[str, str],
    path: Path,
    *,
    title: str,
) -> Path:
    """One panel per quantity: the empirical CDF of every source's pooled values.

    ``samples`` maps a source (keys of :data:`SOURCE_LABELS`) to quantity -> values; ``units``
    maps a quantity to its unit."""
    quantities = list(units)
    figure = Figure(figsize=(4.2 * len(quantities), 4.6), layout="constrained")
    axes = figure.subplots(1, len(quantities))
    for ax, quantity in zip(np.atleast_1d(axes), quantities, strict=True):
        for source, label in SOURCE_LABELS.items():
            if source not in samples:
                continue
            values = np.sort(np.ravel(samples[source][quantity]))
            cumulative = np.arange(1, len(values) + 1) / len(values)
            ax.step(values, cumulative, where="post", label=label, **_STYLES[source])
        ax.set_xlabel(f"{quantity} ({units[quantity]})")
        ax.set_ylabel("empirical CDF")
        ax.grid(alpha=0.3)
    handles, labels = np.atleast_1d(axes)[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=8)
    figure.suptitle(title, fontsize=10)
    return save_figure(figure, path)
