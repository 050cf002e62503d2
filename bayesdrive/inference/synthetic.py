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

The follower reads its inputs through its model (``model.inputs_at`` on a buffer of the one
series that the simulation writes into step by step: speeds, gaps, the leader's speed and
acceleration, the leader's age; no second vehicle ahead), and carries the model's own state, so
any registered model is simulated, extensions and composites included. A model that reads its
past starts with a history of the constant start (its first steps are never scored: engines score
a step only with a full usable history behind it).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import AheadArrays, FollowerArrays, history_steps
from bayesdrive.drivers.base import DriverModel, EgoState, Series

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

    history = history_steps(dt) if model.reads_history else 0

    def one_vehicle(key, vehicle_params, lead_v, start_v, start_gap):
        # The buffer's first ``history`` steps are the constant start, then the simulated steps.
        length = history + num_steps + 1
        lead = jnp.concatenate([jnp.full(history, lead_v[0]), lead_v])
        zeros = jnp.zeros(length)
        buffer = Series(
            v=jnp.full(length, start_v),
            next_v=zeros,
            dx=jnp.full(length, start_v * dt),
            gap=jnp.full(length, start_gap),
            lead_v=lead,
            has_leader=jnp.ones(length),
            mask=jnp.ones(length),
            dt=jnp.full(length, dt),
            ahead=AheadArrays(
                lead_acc=jnp.concatenate([zeros[:1], jnp.diff(lead) / dt]),
                gap2=jnp.full(length, 100.0),
                lead2_v=jnp.ones(length),
                has_leader2=zeros,
                lead_age=jnp.arange(length, dtype=zeros.dtype),
            ),
        )
        start = model.initial_sample(
            jax.random.fold_in(key, num_steps), vehicle_params, EgoState(x=0.0, v=start_v)
        )

        def step(carry, xs):
            state, buf = carry
            key, j = xs
            v, gap = buf.v[j], buf.gap[j]
            inputs = model.inputs_at(buf, j, history)
            nxt = model.transition_sample(key, vehicle_params, state._replace(x=0.0), inputs)
            lead_dx = 0.5 * (buf.lead_v[j] + buf.lead_v[j + 1]) * dt
            buf = buf._replace(
                v=buf.v.at[j + 1].set(nxt.v),
                dx=buf.dx.at[j].set(nxt.x),
                gap=buf.gap.at[j + 1].set(gap + lead_dx - nxt.x),
            )
            return (nxt, buf), (v, nxt.v, nxt.x, gap)

        keys = jax.random.split(key, num_steps)
        steps = history + jnp.arange(num_steps)
        _, out = jax.lax.scan(step, (start, buffer), (keys, steps))
        return out

    v, next_v, dx, gap = jax.vmap(one_vehicle)(
        jax.random.split(key_noise, num_vehicles),
        params,
        lead_v,
        lead_v[:, 0],
        2.0 + headway * lead_v[:, 0],
    )

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
        lead_age=np.broadcast_to(history + np.arange(num_steps, dtype=float), shape).copy(),
    )
    return FollowerArrays(
        vehicle_ids=tuple(f"sim{i}" for i in range(num_vehicles)),
        v=host(v),
        next_v=host(next_v),
        dx=host(dx),
        gap=host(gap),
        lead_v=host(lead_v[:, :-1]),
        has_leader=np.ones(shape),
        mask=np.ones(shape),
        t=np.broadcast_to(host(t[:-1]), shape).copy(),
        dt=float(dt),
        ahead=ahead,
    )
