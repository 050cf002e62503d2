"""Scenes of the paper's closed-loop rollouts and the parameters of their simulated vehicles.

The simulator itself is :mod:`bayesdrive.drivers.closed_loop` (one step, one rollout, the
``stationary`` and ``filtered`` starts, synthetic platoons); this module turns a
:class:`~bayesdrive.simulation.scenarios.Scenario` into its
:class:`~bayesdrive.drivers.closed_loop.SceneArrays` and draws the per-rollout parameters, and
re-exports the simulator's names for the simulation's callers.

Positions are float32 metres from the scenario's origin (the head's position at t0 for a platoon,
the merge point for a merge scene), so a 5 s horizon never adds small increments to large numbers.
A scenario carries its observed history before t0 where
:func:`~bayesdrive.simulation.scenarios.with_history` added it, so that it can start ``filtered``.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.drivers.base import DriverModel, fill_params
from bayesdrive.drivers.closed_loop import (
    HARD_BRAKING_MPS2,
    Rollout,
    SceneArrays,
    platoon_scene,
    rollout,
    rollout_keys,
)
from bayesdrive.simulation.scenarios import Scenario

__all__ = [
    "HARD_BRAKING_MPS2",
    "Rollout",
    "SceneArrays",
    "broadcast_params",
    "draw_particles",
    "platoon_scene",
    "rollout",
    "rollout_keys",
    "scene_arrays",
]


def scene_arrays(scenario: Scenario) -> SceneArrays:
    """A scenario as simulator input: positions shifted by the scenario's origin, float32."""
    f32 = partial(jnp.asarray, dtype=jnp.float32)
    num_simulated = len(scenario.simulated_ids)
    head_x = np.where(scenario.head_present > 0, scenario.x[0] - scenario.origin, 0.0)
    return SceneArrays(
        head_x=f32(head_x),
        head_v=f32(np.where(scenario.head_present > 0, scenario.v[0], 0.0)),
        head_present=f32(scenario.head_present),
        # The head's own leader is not replayed: the first vehicle sees no second vehicle ahead.
        head_gap=jnp.zeros_like(f32(head_x)),
        head_lead_v=jnp.zeros_like(f32(head_x)),
        head_has_leader=jnp.zeros_like(f32(head_x)),
        x0=f32(scenario.x[1:, 0] - scenario.origin),
        v0=f32(scenario.v[1:, 0]),
        lead_length=f32(scenario.length[:-1]),
        road_end=jnp.full(num_simulated, jnp.inf, jnp.float32),
        step_mask=f32(scenario.step_mask),
        merge_x=f32(np.where(scenario.merge_present > 0, scenario.merge_x - scenario.origin, 0.0)),
        merge_v=f32(np.where(scenario.merge_present > 0, scenario.merge_v, 0.0)),
        merge_present=f32(scenario.merge_present),
        merge_length=f32(scenario.merge_length),
        dt=f32(scenario.dt),
        past=None if scenario.past is None else jax.tree.map(f32, scenario.past),
    )


def broadcast_params(params: Any, num_rollouts: int, num_vehicles: int) -> Any:
    """One fixed parameter set (scalar leaves) for every rollout and vehicle: leaves (R, N)."""
    return jax.tree.map(
        lambda leaf: jnp.broadcast_to(jnp.asarray(leaf, jnp.float32), (num_rollouts, num_vehicles)),
        params,
    )


def draw_particles(
    key: Array,
    model: DriverModel,
    names: tuple[str, ...],
    particles: np.ndarray | Array,
    num_rollouts: int,
    fixed: Any = None,
) -> Any:
    """Per rollout and vehicle, one equally weighted particle of that vehicle's posterior.

    particles: (N, P, D) draws of the parameters ``names`` per simulated vehicle; each rollout
    picks, independently per vehicle, a uniformly random particle. Parameters not in ``names``
    come from ``fixed`` (default: the model's defaults). Returns leaves shaped (R, N).
    """
    particles = jnp.asarray(particles, jnp.float32)
    num_vehicles, num_particles, _ = particles.shape
    index = jax.random.randint(key, (num_rollouts, num_vehicles), 0, num_particles)
    theta = particles[jnp.arange(num_vehicles)[None, :], index]
    base = model.defaults() if fixed is None else fixed
    return fill_params(model, names, theta, broadcast_params(base, num_rollouts, num_vehicles))
