"""Closed-loop rollouts of one follower behind its replayed leader, over held-out windows.

The multi-step checks and the gain's RMSE need what the model does when its own errors feed back:
each held-out window of ``horizon_s`` seconds starts from the observed state, the follower is then
driven by the model (``transition_sample``; any extended model, its state lifted from the observed
past at the start), and everything ahead of it is replayed from the data. The simulated gap is the
observed gap minus the accumulated position offset of the simulated follower,

    gap_sim[j] = gap_obs[j] - (x_sim[j] - x_obs[j]),

(the same for the gap to the second vehicle ahead), so only increments are ever added and float32
never holds a kilometre-sized position. The inputs come from the model's own ``inputs_at`` on a
local buffer of the one series that holds the observed
history before the window and the simulated values inside it, so a reaction delay sees the data
before the window and its own simulation after.

This complements ``bayesdrive.simulation`` (platoon scenarios with base inputs): it handles the
extended inputs and states the extensions need, for one follower at a time.

Windows are fixed by rule, never by results: consecutive, non-overlapping windows from the first
scored held-out step, kept when every step of the window is scored.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import EgoState, Series, device_series, fill_params
from bayesdrive.drivers.extensions.compose import ExtendedModel

__all__ = ["RolloutWindows", "Rollouts", "heldout_windows", "rollout"]


class RolloutWindows(NamedTuple):
    """Held-out windows: ``start[w]`` is the first step of window w of vehicle ``row[w]``."""

    row: np.ndarray
    start: np.ndarray
    horizon: int


class Rollouts(NamedTuple):
    """Position offsets simulated minus observed (m): (window, rollout, horizon step)."""

    windows: RolloutWindows
    offset: np.ndarray
    collisions: np.ndarray  # (window, rollout): the simulated gap reached <= 0

    def rmse_per_vehicle(self, num_vehicles: int) -> np.ndarray:
        """Root mean square position error over each vehicle's windows, rollouts and steps."""
        out = np.full(num_vehicles, np.nan)
        if self.offset.size == 0:
            return out
        squared = (self.offset**2).mean(axis=(1, 2))
        for row in np.unique(self.windows.row):
            out[row] = np.sqrt(squared[self.windows.row == row].mean())
        return out


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


def _window_buffer(data: Series, row: Array, start: Array, history: int, horizon: int) -> Series:
    """Vehicle ``row``'s arrays from ``history`` steps before ``start`` to the end of the window,
    sliced straight from the (vehicle, step) arrays: gathering the row first would hold a whole
    series per window, which runs out of memory with one-step windows on long recordings."""
    length = history + horizon + 1

    def cut(a: Array) -> Array:
        corner = (row, start - history) + (0,) * (a.ndim - 2)
        return jax.lax.dynamic_slice(a, corner, (1, length, *a.shape[2:]))[0]

    return jax.tree.map(cut, data)


def _one_rollout(
    key: Array,
    extended: ExtendedModel,
    params,
    buffer: Series,
    history: int,
    horizon: int,
) -> tuple[Array, Array]:
    """Simulate ``horizon`` steps from local index ``history``; returns offsets and a collision."""
    model = extended.model
    zero = jnp.zeros_like(buffer.v[0])
    first_inputs = model.inputs_at(buffer, history, history)
    state = model.lift(params, EgoState(zero, buffer.v[history]), first_inputs)
    observed = buffer

    def step(carry, k):
        state, buf, offset = carry
        j = history + k
        inputs = model.inputs_at(buf, j, history)
        moved = model.transition_sample(
            jax.random.fold_in(key, k), params, state._replace(x=zero), inputs
        )
        offset = offset + moved.x - observed.dx[j]
        buf = buf._replace(
            v=buf.v.at[j + 1].set(moved.v),
            dx=buf.dx.at[j].set(moved.x),
            gap=buf.gap.at[j + 1].set(observed.gap[j + 1] - offset),
        )
        if buf.ahead is not None:
            ahead = buf.ahead
            gap2 = ahead.gap2.at[j + 1].set(observed.ahead.gap2[j + 1] - offset)
            buf = buf._replace(ahead=ahead._replace(gap2=gap2))
        return (moved, buf, offset), offset

    _, offsets = jax.lax.scan(step, (state, buffer, zero), jnp.arange(horizon))
    crashed = jnp.any(observed.gap[history + 1 : history + horizon + 1] - offsets <= 0)
    return offsets, crashed


@functools.partial(jax.jit, static_argnames=("extended", "history", "horizon"))
def _rollout_windows(keys, thetas, buffers, *, extended, history, horizon):
    """(window, rollout) keys and parameter draws, (window,) buffers -> offsets, collisions."""
    names = extended.model.param_names

    def per_window(window_keys, window_thetas, buffer):
        def per_draw(key, theta):
            params = fill_params(extended.model, names, theta)
            return _one_rollout(key, extended, params, buffer, history, horizon)

        return jax.vmap(per_draw)(window_keys, window_thetas)

    return jax.vmap(per_window)(keys, thetas, buffers)


def rollout(
    key: Array,
    extended: ExtendedModel,
    theta: np.ndarray,
    series: FollowerArrays,
    windows: RolloutWindows,
    *,
    num_rollouts: int = 32,
) -> Rollouts:
    """``num_rollouts`` closed-loop rollouts per window, each with a fresh posterior draw.

    ``theta`` (vehicle, particle, param) are equally weighted draws of the model's parameters (in
    ``extended.model.param_names`` order). The same ``key`` gives every model the same noise and
    the same draw indices (common random numbers), so RMSE differences between models are sharper.
    """
    num_windows = len(windows.row)
    if num_windows == 0:
        return Rollouts(
            windows, np.zeros((0, num_rollouts, windows.horizon)), np.zeros((0, num_rollouts), bool)
        )
    history = series.history
    data = device_series(series)
    # Pad the step axis so every window's buffer slice stays inside the arrays.
    pad = [(0, 0), (history, windows.horizon + 1)]
    data = jax.tree.map(lambda a: jnp.pad(a, pad + [(0, 0)] * (a.ndim - 2), mode="edge"), data)
    key_draw, key_noise = jax.random.split(key)
    picks = jax.random.randint(key_draw, (num_windows, num_rollouts), 0, theta.shape[1])
    rows = jnp.asarray(windows.row)
    thetas = jnp.asarray(theta, dtype=data.v.dtype)[rows[:, None], picks]
    buffers = jax.vmap(
        lambda row, start: _window_buffer(data, row, start + history, history, windows.horizon)
    )(rows, jnp.asarray(windows.start))
    offsets, crashed = _rollout_windows(
        jax.random.split(key_noise, (num_windows, num_rollouts)),
        thetas,
        buffers,
        extended=extended,
        history=history,
        horizon=windows.horizon,
    )
    return Rollouts(windows, np.asarray(offsets, np.float64), np.asarray(crashed))
