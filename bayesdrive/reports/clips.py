"""Material for a human Turing test: paired top-down clips of a real and a simulated scene, in the
same styling, shown in a seeded random order, with an answer sheet kept apart.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from bayesdrive.data.atomic import write_atomic, write_text_atomic

__all__ = ["render_clip", "write_clip_pair"]

LANE_WIDTH_M = 3.7
CAR_WIDTH_M = 1.8
VIEW_M = 120.0


def render_clip(
    x: np.ndarray, lengths: np.ndarray, dt: float, path: Path, *, every: int = 2
) -> Path:
    """An animated GIF of cars on one lane seen from above; ``x`` (cars, steps) front positions.

    The view follows the platoon's centre, so only the relative motion shows, as in the paper's
    clips. Every ``every``-th step becomes a frame.
    """
    x = np.asarray(x, dtype=float)
    frames = range(0, x.shape[1], every)
    fig = Figure(figsize=(6.0, 1.2), layout="tight")
    ax = fig.subplots()
    ax.set_ylim(-LANE_WIDTH_M, LANE_WIDTH_M)
    ax.set_yticks([])
    ax.set_xlabel("m")
    ax.axhline(LANE_WIDTH_M / 2, color="grey", lw=1)
    ax.axhline(-LANE_WIDTH_M / 2, color="grey", lw=1)
    cars = [
        ax.add_patch(Rectangle((0.0, -CAR_WIDTH_M / 2), length, CAR_WIDTH_M, color="tab:blue"))
        for length in lengths
    ]

    def draw(step: int):
        centre = float(np.nanmean(x[:, step]))
        ax.set_xlim(centre - VIEW_M / 2, centre + VIEW_M / 2)
        for car, front, length in zip(cars, x[:, step], lengths, strict=True):
            car.set_x(front - length)
        return cars

    animation = FuncAnimation(fig, draw, frames=frames, blit=False)
    write_atomic(
        Path(path),
        lambda tmp: animation.save(tmp, writer=PillowWriter(fps=round(1 / (dt * every)))),
    )
    return Path(path)


def write_clip_pair(
    real_x: np.ndarray,
    simulated_x: np.ndarray,
    lengths: np.ndarray,
    dt: float,
    out: Path,
    name: str,
    rng: np.random.Generator,
) -> dict[str, str]:
    """Two clips, ``<name>_A.gif`` and ``<name>_B.gif``, one real and one simulated in an order
    drawn from ``rng``; returns the answer-sheet entry (which letter is real)."""
    real_first = bool(rng.integers(2))
    order = (real_x, simulated_x) if real_first else (simulated_x, real_x)
    for letter, x in zip("AB", order, strict=True):
        render_clip(x, lengths, dt, out / f"{name}_{letter}.gif")
    return {"pair": name, "real": "A" if real_first else "B"}


def write_answer_sheet(entries: list[dict[str, str]], path: Path) -> Path:
    write_text_atomic(Path(path), json.dumps(entries, indent=2) + "\n")
    return Path(path)
