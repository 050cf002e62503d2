"""Held-out forecasts: one follower behind its replayed leader, from each held-out window's start.

The multi-step checks, the gain's RMSE and the held-out calibration need what the model does when
its own errors feed back: each held-out window of ``horizon_s`` seconds is a scene of the one
simulator (:mod:`bayesdrive.drivers.closed_loop`) with the follower simulated and everything ahead
of it replayed from the data (its leader as the scene's head, the leader's own leader as the second
vehicle ahead). Positions are the follower's, from its observed position at the window's start,
so the simulated gap is the observed gap minus the accumulated position offset of the simulated
follower,

    gap_sim[j] = gap_obs[j] - (x_sim[j] - x_obs[j]),

and float32 never holds a kilometre-sized position. Each scene carries the data's series over the
steps before the window as its past, so the ``filtered`` start (the default: a forecast) reads
the observed history, and ``stationary`` is the same window without it. A model with a hidden
state (a drifting parameter) is filtered over the vehicle's whole series before the window, per
rollout's posterior draw (``model.filtered_start``), and each rollout draws its hidden state from
that law.

Windows are fixed by rule, never by results: consecutive, non-overlapping windows from the first
scored held-out step, kept when every step of the window is scored.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays, history_steps
from bayesdrive.drivers.base import DriverModel, Series, device_series, fill_params
from bayesdrive.drivers.closed_loop import FILTERED, SceneArrays, rollout_scenes
from bayesdrive.drivers.extensions.compose import ExtendedModel

__all__ = ["RolloutWindows", "Rollouts", "heldout_windows", "rollout"]


class RolloutWindows(NamedTuple):
    """Held-out windows: ``start[w]`` is the first step of window w of vehicle ``row[w]``."""

    row: np.ndarray
    start: np.ndarray
    horizon: int


class Rollouts(NamedTuple):
    """Forecast errors, simulated minus observed, (window, rollout, horizon step) for steps
    1..H: ``offset`` of the position (m; the gap's is its negative), ``speed_offset`` of the
    speed (m/s); ``collisions`` (window, rollout): the simulated gap reached <= 0; ``start``:
    the simulator's start (:data:`~bayesdrive.drivers.closed_loop.STARTS`)."""

    windows: RolloutWindows
    offset: np.ndarray
    speed_offset: np.ndarray
    collisions: np.ndarray
    start: str

    def per_vehicle(self, values: np.ndarray, num_vehicles: int) -> np.ndarray:
        """Mean of per-window ``values`` over each vehicle's windows (NaN for a vehicle without)."""
        out = np.full(num_vehicles, np.nan)
        for row in np.unique(self.windows.row):
            out[row] = values[self.windows.row == row].mean()
        return out

    def rmse_per_vehicle(self, num_vehicles: int) -> np.ndarray:
        """Root mean square position error over each vehicle's windows, rollouts and steps."""
        if self.offset.size == 0:
            return np.full(num_vehicles, np.nan)
        return np.sqrt(self.per_vehicle((self.offset**2).mean(axis=(1, 2)), num_vehicles))


def heldout_windows(series: FollowerArrays, horizon_s: float) -> RolloutWindows:
    """Consecutive non-overlapping held-out windows whose every step is scored (module docstring)."""
    horizon = round(horizon_s / series.dt)
    rows, starts = [], []
    for row, scored in enumerate(series.windows.heldout > 0):
        steps = np.flatnonzero(scored)
        if len(steps) == 0:
            continue
        start = steps[0]
        while start + horizon <= scored.shape[0] and scored[start : start + horizon].all():
            rows.append(row)
            starts.append(start)
            start += horizon
    return RolloutWindows(np.asarray(rows, int), np.asarray(starts, int), horizon)


def _window_scenes(data: Series, windows: RolloutWindows, past: int) -> SceneArrays:
    """Each window as a scene (leaves with a leading window axis), sliced from ``data`` (one
    series (vehicle, step), padded by ``past`` steps before and ``horizon + 1`` after): gathering
    whole rows first would hold a series per window, out of memory with one-step windows."""
    horizon = windows.horizon

    def cut(a: Array, row: Array, first: Array, length: int) -> Array:
        return jax.lax.dynamic_slice(a, (row, first), (1, length))[0]

    def one(row: Array, start: Array) -> SceneArrays:
        at = start + past  # the window's start in the padded arrays

        def window(a: Array) -> Array:
            return cut(a, row, at, horizon + 1)

        gap, ahead = window(data.gap), data.ahead
        travelled = jnp.concatenate([jnp.zeros(1, gap.dtype), jnp.cumsum(window(data.dx)[:-1])])
        before = jax.tree.map(lambda a: cut(a, row, start, past)[None], data._replace(merge=None))
        zeros = jnp.zeros_like(gap)
        return SceneArrays(
            head_x=travelled + gap,
            head_v=window(data.lead_v),
            head_present=window(data.has_leader),
            head_gap=zeros if ahead is None else window(ahead.gap2) - gap,
            head_lead_v=zeros if ahead is None else window(ahead.lead2_v),
            head_has_leader=zeros if ahead is None else window(ahead.has_leader2),
            x0=zeros[:1],
            v0=window(data.v)[:1],
            lead_length=zeros[:1],
            road_end=jnp.full(1, jnp.inf, gap.dtype),
            step_mask=jnp.ones(horizon, gap.dtype),
            merge_x=jnp.zeros((0, horizon + 1), gap.dtype),
            merge_v=jnp.zeros((0, horizon + 1), gap.dtype),
            merge_present=jnp.zeros((0, horizon + 1), gap.dtype),
            merge_length=jnp.zeros(0, gap.dtype),
            dt=data.dt[0, 0],
            past=before,
        )

    return jax.vmap(one)(jnp.asarray(windows.row), jnp.asarray(windows.start))


@partial(jax.jit, static_argnames="model")
def _window_laws(model: DriverModel, params: Any, data: Series, rows: Array, starts: Array) -> Any:
    def one_window(window):
        window_params, row, until = window
        vehicle = jax.tree.map(lambda a: a[row], data)
        law = jax.vmap(lambda p: model.filtered_start.law(p, vehicle, until))  # one vehicle
        return jax.vmap(law)(window_params)  # over rollouts

    # One window at a time: each filters the vehicle's whole series, once per rollout's draw.
    return jax.lax.map(one_window, (params, rows, starts))


def _filtered_laws(model: DriverModel, params: Any, data: Series, windows: RolloutWindows) -> Any:
    """The hidden state's law at each window's start under each rollout's draw (leaves (W, R, 1)):
    the model's filter over the vehicle's usable steps before the window."""
    data = data._replace(merge=None)
    return _window_laws(model, params, data, jnp.asarray(windows.row), jnp.asarray(windows.start))


def rollout(
    key: Array,
    extended: ExtendedModel,
    theta: np.ndarray,
    series: FollowerArrays,
    windows: RolloutWindows,
    *,
    num_rollouts: int = 32,
    start: str = FILTERED,
) -> Rollouts:
    """``num_rollouts`` closed-loop rollouts per window from ``start``, each with a fresh
    posterior draw.

    ``theta`` (vehicle, particle, param) are equally weighted draws of the model's parameters (in
    ``extended.model.param_names`` order). The same ``key`` gives every model the same noise and
    the same draw indices (common random numbers), so differences between models are sharper.
    """
    num_windows, horizon = len(windows.row), windows.horizon
    if num_windows == 0:
        empty = np.zeros((0, num_rollouts, horizon))
        return Rollouts(windows, empty, empty, np.zeros((0, num_rollouts), bool), start)
    if series.merge is not None:
        raise ValueError(
            "held-out window rollouts replay car-following scenes; merge scenes are simulated "
            "through bayesdrive.simulation.scenarios (merge_scenarios)"
        )
    past = history_steps(series.dt)
    unpadded = device_series(series, jnp.float32)
    # Pad the step axis so every window's slice, past and horizon, stays inside the arrays.
    data = jax.tree.map(lambda a: jnp.pad(a, [(0, 0), (past, horizon + 1)], mode="edge"), unpadded)
    scenes = _window_scenes(data, windows, past)
    key_draw, key_noise = jax.random.split(key)
    picks = jax.random.randint(key_draw, (num_windows, num_rollouts), 0, theta.shape[1])
    rows = jnp.asarray(windows.row)
    thetas = jnp.asarray(theta, jnp.float32)[rows[:, None], picks]
    model = extended.model
    params = fill_params(model, model.param_names, thetas[:, :, None, :])
    hidden = start == FILTERED and model.filter is not None and model.filtered_start is not None
    rolled = rollout_scenes(
        jax.random.split(key_noise, num_windows),
        model,
        params,
        scenes,
        num_rollouts=num_rollouts,
        start=start,
        dt=series.dt,
        laws=_filtered_laws(model, params, unpadded, windows) if hidden else None,
    )
    steps = windows.start[:, None] + np.arange(horizon)[None, :]
    observed_x = np.cumsum(series.dx[windows.row[:, None], steps], axis=1)[:, None, :]
    observed_v = series.next_v[windows.row[:, None], steps][:, None, :]
    return Rollouts(
        windows,
        offset=np.asarray(rolled.x[:, :, 0, 1:], np.float64) - observed_x,
        speed_offset=np.asarray(rolled.v[:, :, 0, 1:], np.float64) - observed_v,
        collisions=np.asarray(rolled.collision[:, :, 0].any(axis=-1)),
        start=start,
    )
