"""Pictures of a particle engine's diagnostics, drawn from a result tree (engines draw nothing).

Each function takes a result tree (:mod:`bayesdrive.inference.core.output`) with the particle engines'
``sample_stats`` and writes one PNG atomically. Figures are built on matplotlib's object API with
the Agg canvas, so nothing touches pyplot's global state. Steps outside a vehicle's usable mask are
left out of every trace; thin lines are vehicles, the thick line their median (drawn where at
least half of them have data).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bayesdrive.data.atomic import write_atomic

__all__ = ["plot_convergence", "plot_ess", "plot_unique_particles", "write_filter_plots"]

# Beyond this many vehicles, individual traces turn into a grey mass; the median still uses all.
MAX_TRACES = 60


def _traces(tree: xr.DataTree, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vehicle, step) values of a sample_stats variable, NaN off the usable mask, and the time
    axis in seconds from each vehicle's first step."""
    values = tree["sample_stats"][name].values.astype(np.float64)
    mask = tree["observed_data"]["mask"].values > 0
    dt = float(tree["observed_data"].attrs["dt"])
    return np.where(mask, values, np.nan), np.arange(values.shape[1]) * dt


def _draw(ax: Axes, seconds: np.ndarray, values: np.ndarray, *, points: bool = False) -> None:
    style = {"marker": ".", "linestyle": "none", "markersize": 3} if points else {"lw": 0.7}
    for row in values[:MAX_TRACES]:
        ax.plot(seconds, row, color="0.55", alpha=0.5, **style)
    if not points:
        # Where fewer than half the vehicles still have data, a "median" is one or two series.
        live = np.isfinite(values).sum(axis=0) >= max(1, len(values) / 2)
        median = np.full(values.shape[1], np.nan)
        median[live] = np.nanmedian(values[:, live], axis=0)
        ax.plot(seconds, median, color="C0", lw=2.0, label="median over vehicles")
        ax.legend(loc="best", fontsize=8)
    ax.set_xlabel("time in series (s)")
    ax.grid(alpha=0.3)


def _save(path: str | Path, build: Callable[[Axes], None], title: str) -> Path:
    figure = Figure(figsize=(7.0, 4.0), layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    build(ax)
    ax.set_title(title, fontsize=10)
    path = Path(path)
    write_atomic(path, lambda tmp: figure.savefig(tmp, format="png", dpi=120))
    return path


def _title(tree: xr.DataTree, what: str) -> str:
    vehicles = tree["posterior"].sizes["vehicle"]
    return f"{what}: {tree.attrs.get('engine')} on {tree.attrs.get('model')}, {vehicles} vehicle(s)"


def plot_ess(tree: xr.DataTree, path: str | Path) -> Path:
    """Effective sample size / N before resampling at each step."""
    values, seconds = _traces(tree, "particle_ess")
    particles = float(tree.attrs["num_particles"])

    def build(ax: Axes) -> None:
        _draw(ax, seconds, values / particles)
        ax.set_ylim(0.0, 1.05)
        ax.set_ylabel("ESS / N")

    return _save(path, build, _title(tree, "Effective sample size"))


def plot_unique_particles(tree: xr.DataTree, path: str | Path) -> Path:
    """Distinct ancestors kept by each resampling (only steps that resampled have a point)."""
    values, seconds = _traces(tree, "unique_particles")
    particles = float(tree.attrs["num_particles"])

    def build(ax: Axes) -> None:
        _draw(ax, seconds, values / particles, points=True)
        ax.set_ylim(0.0, 1.05)
        ax.set_ylabel("distinct ancestors / N")

    return _save(path, build, _title(tree, "Particles surviving resampling"))


def plot_convergence(tree: xr.DataTree, path: str | Path) -> Path:
    """The paper's convergence curve: distance of the particle mean to its final value, in prior
    widths (root mean square over parameters)."""
    values, seconds = _traces(tree, "convergence")

    def build(ax: Axes) -> None:
        _draw(ax, seconds, values)
        ax.set_ylim(bottom=0.0)
        ax.set_ylabel("|mean - final mean| / prior width")

    return _save(path, build, _title(tree, "Convergence of the particle mean"))


def write_filter_plots(tree: xr.DataTree, out_dir: str | Path) -> list[Path]:
    """All three pictures into ``out_dir``: ess.png, unique_particles.png, convergence.png; none
    for a result without per-step filter statistics (the MCMC engines and lm: ``diagnose`` is
    their picture)."""
    if "sample_stats" not in tree.children or "particle_ess" not in tree["sample_stats"].data_vars:
        return []
    out_dir = Path(out_dir)
    return [
        plot_ess(tree, out_dir / "ess.png"),
        plot_unique_particles(tree, out_dir / "unique_particles.png"),
        plot_convergence(tree, out_dir / "convergence.png"),
    ]
