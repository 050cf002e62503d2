"""Figures of generated scenes: speed and gap densities (KDE) and the leader-follower sweep."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure

from bayesdrive.data.atomic import write_atomic
from bayesdrive.simulation.generate import SWEEP_DIFFERENCES
from bayesdrive.simulation.metrics import kde
from bayesdrive.simulation.rollout import Rollout

__all__ = ["plot_speed_gap_kde", "plot_sweep"]


def _save(fig, path: Path) -> Path:
    write_atomic(Path(path), lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    return Path(path)


def plot_speed_gap_kde(
    samples: Mapping[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str
) -> Path:
    """KDEs of speeds (m/s) and bumper gaps (m); ``samples`` maps a label to (speeds, gaps)."""
    fig = Figure(figsize=(10, 3.8), layout="tight")
    ax_v, ax_g = fig.subplots(1, 2)
    all_v = np.concatenate([np.ravel(v) for v, _ in samples.values()])
    all_g = np.concatenate([np.ravel(g) for _, g in samples.values()])
    v_grid = np.linspace(0.0, np.nanpercentile(all_v, 99.5) * 1.1, 300)
    g_grid = np.linspace(0.0, np.nanpercentile(all_g, 99) * 1.1, 300)
    for label, (speeds, gaps) in samples.items():
        ax_v.plot(v_grid, kde(np.ravel(speeds), v_grid), label=label)
        ax_g.plot(g_grid, kde(np.ravel(gaps), g_grid), label=label)
    ax_v.set(xlabel="speed (m/s)", ylabel="density", title="speed")
    ax_g.set(xlabel="bumper gap (m)", ylabel="density", title="gap to leader")
    ax_v.legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def plot_sweep(sweep: Rollout, dt: float, path: Path, title: str) -> Path:
    """Follower speed and gap over time of a :func:`~bayesdrive.simulation.generate.median_sweep`,
    one line per desired-speed difference (follower - leader)."""
    time_s = np.arange(sweep.v.shape[-1]) * dt
    follower_speed, gap = np.asarray(sweep.v[:, 1]), np.asarray(sweep.gap[:, 1])
    differences = SWEEP_DIFFERENCES
    fig = Figure(figsize=(10, 3.8), layout="tight")
    ax_v, ax_g = fig.subplots(1, 2)
    colours = colormaps["coolwarm"](np.linspace(0, 1, len(differences)))
    for colour, diff, v, g in zip(colours, differences, follower_speed, gap, strict=True):
        ax_v.plot(time_s, v, color=colour, label=f"{diff:+.0f} m/s")
        ax_g.plot(time_s, g, color=colour)
    ax_v.set(xlabel="time (s)", ylabel="follower speed (m/s)")
    ax_g.set(xlabel="time (s)", ylabel="bumper gap (m)")
    ax_g.legend(
        *ax_v.get_legend_handles_labels(),
        title="desired-speed difference",
        fontsize=7,
        ncol=2,
        loc="upper left",
    )
    fig.suptitle(title)
    return _save(fig, path)
