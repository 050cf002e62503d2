"""String stability and the speed of stop-and-go waves, measured by one rule on simulated and on
observed platoons.

A platoon is a chain: a replayed head, then followers, each following the one before it. Every
consecutive pair (predecessor, follower) gives two measurements over the scene's real states:

* **Speed-variation amplification** (string stability): the variances of the two speed series
  over the window. Pooled over pairs, ``sqrt(sum var(follower) / sum var(predecessor))`` is the
  factor by which speed variation grows from one vehicle to the next: above 1 a disturbance grows
  down the platoon (string unstable), below 1 it is damped. Pooling the variances, rather than
  averaging per-pair ratios, keeps a nearly constant predecessor from dominating.
* **Wave speed** (Newell 2002, "A simplified car-following theory: a lower order model"): a
  follower repeats its predecessor's trajectory shifted by a time ``tau`` and a distance ``d``,
  ``x_f(t + tau) = x_p(t) - d``, so a change of speed travels back (upstream) at ``d / tau``. Per
  pair, ``tau`` is the lag (0 to :data:`MAX_LAG_S`) that minimises the mean squared difference
  ``v_f(t + tau) - v_p(t)`` and ``d`` the mean of ``x_p(t) - x_f(t + tau)`` over the overlap. Pooled,
  the wave speed is ``sum d / sum tau``. Newell's shift describes congested traffic, so only pairs
  whose predecessor is congested (mean speed at most :data:`CONGESTED_SPEED`) and whose speed
  varies (sd at least :data:`MIN_PREDECESSOR_SPEED_SD`; a steady one has no wave to time) are
  timed, and a lag at either end of the search range (0 or :data:`MAX_LAG_S`) is not identified
  and is left out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "CONGESTED_SPEED",
    "MAX_LAG_S",
    "MIN_PREDECESSOR_SPEED_SD",
    "amplification",
    "chain_pairs",
    "newell_shifts",
    "platoon_measures",
    "platoon_summary",
    "wave_speed",
]

# Newell's lags are around 1-2 s; 2.5 s, with as long an overlap, fits the 5 s scenes.
MAX_LAG_S = 2.5
# Below this (m/s) the predecessor's speed is steady, and a lag cannot be read off it.
MIN_PREDECESSOR_SPEED_SD = 0.5
# Above this mean speed (m/s, 54 km/h) traffic flows freely and waves do not travel back.
CONGESTED_SPEED = 15.0


def chain_pairs(
    head_x: np.ndarray, head_v: np.ndarray, x: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every (predecessor, follower) pair of a chain, flattened: predecessor x and v, follower x
    and v, each (M, S). head_x, head_v: (S,); x, v: (..., N, S), followers front to back (leading
    axes, e.g. rollouts, give pairs of their own)."""
    x, v = np.asarray(x, np.float64), np.asarray(v, np.float64)
    head_x = np.broadcast_to(np.asarray(head_x, np.float64), (*x.shape[:-2], 1, x.shape[-1]))
    head_v = np.broadcast_to(np.asarray(head_v, np.float64), head_x.shape)
    ahead_x = np.concatenate([head_x, x[..., :-1, :]], axis=-2)
    ahead_v = np.concatenate([head_v, v[..., :-1, :]], axis=-2)
    steps = x.shape[-1]
    return tuple(a.reshape(-1, steps) for a in (ahead_x, ahead_v, x, v))


def newell_shifts(
    ahead_x: np.ndarray, ahead_v: np.ndarray, x: np.ndarray, v: np.ndarray, dt: float
) -> np.ndarray:
    """The Newell shifts (module docstring), (K, 2) of lag (s) and distance (m), of the K of M
    pairs of (M, S) series whose lag is identified (inside the search range). A scene too short
    for the largest lag plus as long an overlap gets (0, 2)."""
    steps = ahead_v.shape[-1]
    max_lag = round(MAX_LAG_S / dt)
    if steps < 2 * max_lag:
        return np.zeros((0, 2))
    misfit = np.stack(
        [
            np.mean((v[:, lag:] - ahead_v[:, : steps - lag]) ** 2, axis=-1)
            for lag in range(max_lag + 1)
        ],
        axis=-1,
    )
    lag = np.argmin(misfit, axis=-1)
    identified = np.flatnonzero((lag > 0) & (lag < max_lag))
    distance = [np.mean(ahead_x[m, : steps - lag[m]] - x[m, lag[m] :]) for m in identified]
    return np.stack([lag[identified] * dt, np.array(distance, np.float64)], axis=-1).reshape(-1, 2)


def amplification(variances: np.ndarray) -> float | None:
    """The pooled speed-variation amplification of (M, 2) speed variances (predecessor,
    follower); None if no predecessor's speed varies."""
    ahead = float(np.sum(variances[:, 0]))
    return float(np.sqrt(np.sum(variances[:, 1]) / ahead)) if ahead > 0 else None


def wave_speed(shifts: np.ndarray) -> float | None:
    """The pooled upstream wave speed (m/s) of Newell shifts; None if no pair has a lag."""
    lags = float(np.sum(shifts[:, 0]))
    return float(np.sum(shifts[:, 1]) / lags) if lags > 0 else None


def platoon_measures(
    head_x: np.ndarray, head_v: np.ndarray, x: np.ndarray, v: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """A chain's per-pair measurements: (M, 2) speed variances (predecessor, follower), and the
    identified Newell shifts (K, 2) of the pairs whose predecessor is congested and varies its
    speed (module docstring)."""
    ahead_x, ahead_v, x, v = chain_pairs(head_x, head_v, x, v)
    variances = np.stack([np.var(ahead_v, axis=-1), np.var(v, axis=-1)], axis=-1)
    timed = (np.sqrt(variances[:, 0]) >= MIN_PREDECESSOR_SPEED_SD) & (
        ahead_v.mean(axis=-1) <= CONGESTED_SPEED
    )
    return variances, newell_shifts(ahead_x[timed], ahead_v[timed], x[timed], v[timed], dt)


def platoon_summary(
    variances: dict[str, np.ndarray], shifts: dict[str, np.ndarray]
) -> dict[str, Any]:
    """Both measures pooled, for each side ("simulated", "observed"), JSON-ready."""
    return {
        "string_stability": {
            "note": "speed-variation amplification per vehicle, sqrt(sum var(follower) / sum "
            "var(predecessor)) over consecutive pairs; above 1: string unstable",
            **{f"{side}_amplification": amplification(p) for side, p in variances.items()},
            **{f"{side}_pairs": len(p) for side, p in variances.items()},
        },
        "wave_speed_mps": {
            "note": "Newell's upstream wave speed, sum d / sum tau over the pairs whose "
            f"predecessor's mean speed is at most {CONGESTED_SPEED} m/s and speed sd at least "
            f"{MIN_PREDECESSOR_SPEED_SD} m/s, and whose lag lies strictly inside 0-{MAX_LAG_S} s",
            **{f"{side}_upstream": wave_speed(s) for side, s in shifts.items()},
            **{f"{side}_pairs": len(s) for side, s in shifts.items()},
        },
    }
