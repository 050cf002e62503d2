"""Synthetic car-following data with known parameters, for recovery tests and coverage studies.

Each follower is driven by the model's own stochastic step (``model.transition_sample``) behind
a replayed synthetic leader whose speed oscillates around a cruising speed (random per vehicle:
base 8-20 m/s, amplitude 2-6 m/s, period 8-20 s), starting at the leader's speed and a gap of
2 m + h v with a time headway h uniform on 1-2 s. The start must not depend on the parameters: the
engines condition on the first state, so a start such as d_min + tau v (used before) carries
information about them that no likelihood sees, and simulation-based calibration then finds
posteriors too wide for tau and d_min (too few extreme ranks; 90% coverage of tau 0.92-0.96).
The result is the :class:`~bayesdrive.data.views.FollowerArrays` an engine fits.
States are kept relative to the current step, as the engines score them, so the recorded
increments carry no float32 position round-off.

Each follower is a one-vehicle platoon of the one simulator
(:mod:`bayesdrive.drivers.closed_loop`) from its ``stationary`` start: it reads its inputs through
its model (speeds, gaps, the leader's speed, acceleration and age; no second vehicle ahead) and
carries the model's own state, so any registered model is simulated, extensions and composites
included. A model that reads its past starts with a history of the constant start (its first
steps are never scored: engines score a step only with a full usable history behind it).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import AheadArrays, FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.closed_loop import STATIONARY, platoon_scene, rollout_scenes

__all__ = ["simulate_following"]


def simulate_following(
    key: Array, model: DriverModel, params: Any, *, num_steps: int, dt: float = 0.1
) -> FollowerArrays:
    """Simulate one follower per entry of ``params`` (a parameter tuple of (V,) arrays).

    Every step is usable (mask 1) and led; vehicle ids are ``sim0``, ``sim1``, ...
    """
    num_vehicles = jnp.shape(params[0])[0]
    key_base, key_amplitude, key_period, key_phase, key_headway, key_noise = jax.random.split(
        key, 6
    )
    base = jax.random.uniform(key_base, (num_vehicles,), minval=8.0, maxval=20.0)
    amplitude = jax.random.uniform(key_amplitude, (num_vehicles,), minval=2.0, maxval=6.0)
    period = jax.random.uniform(key_period, (num_vehicles,), minval=8.0, maxval=20.0)
    phase = jax.random.uniform(key_phase, (num_vehicles,), maxval=2 * jnp.pi)
    headway = jax.random.uniform(key_headway, (num_vehicles,), minval=1.0, maxval=2.0)
    t = jnp.arange(num_steps + 1) * dt
    lead_v = base[:, None] + amplitude[:, None] * jnp.sin(
        2 * jnp.pi * t[None, :] / period[:, None] + phase[:, None]
    )

    start_v = lead_v[:, 0]
    scenes = jax.vmap(lambda lead, x0, v0: platoon_scene(lead, x0, v0, length=0.0, dt=dt))(
        lead_v, -(2.0 + headway * start_v)[:, None], start_v[:, None]
    )
    one_each = jax.tree.map(lambda leaf: jnp.reshape(leaf, (num_vehicles, 1, 1)), params)
    simulated = rollout_scenes(
        jax.random.split(key_noise, num_vehicles),
        model,
        one_each,
        scenes,
        num_rollouts=1,
        start=STATIONARY,
        dt=dt,
    )
    path = jax.tree.map(lambda leaf: leaf[:, 0, 0], simulated)

    def host(a):
        return np.asarray(a, dtype=np.float64)

    shape = (num_vehicles, num_steps)
    lead = host(lead_v)
    # The scene ahead as the simulation saw it: no second vehicle ahead, one leader throughout.
    ahead = AheadArrays(
        lead_acc=np.concatenate([np.zeros((num_vehicles, 1)), np.diff(lead[:, :-1]) / dt], 1),
        gap2=np.full(shape, 100.0),
        lead2_v=np.ones(shape),
        has_leader2=np.zeros(shape),
        lead_age=np.broadcast_to(np.arange(num_steps, dtype=float), shape).copy(),
    )
    return FollowerArrays(
        vehicle_ids=tuple(f"sim{i}" for i in range(num_vehicles)),
        v=host(path.v[:, :-1]),
        next_v=host(path.v[:, 1:]),
        dx=host(path.dx),
        gap=host(path.gap[:, :-1]),
        lead_v=host(lead_v[:, :-1]),
        has_leader=np.ones(shape),
        mask=np.ones(shape),
        t=np.broadcast_to(host(t[:-1]), shape).copy(),
        dt=float(dt),
        ahead=ahead,
    )
