"""Closed-loop rollouts of a driver model through a scenario, vectorised over vehicles and rollouts.

One rollout: the head (and, in merge scenes, the merging car) replays the data; every simulated
vehicle starts from its observed state at t0 (through ``model.initial_sample``) and then moves by
``model.transition_sample`` only, fed the *simulated* gap to its leader:
``gap = x_leader - x - length_leader`` and the leader's simulated (or replayed) speed. The inputs
come from the model itself (``model.inputs_at``) on a buffer of the simulated vehicles' series
written step by step, so any model runs, extensions included; a model that reads its past sees,
before the rollout's start, its initial state held. Nothing
here knows the IDM: any :class:`~bayesdrive.drivers.base.DriverModel` runs. ``lax.scan`` runs the
steps, ``vmap`` the vehicles within a step and the rollouts; one compilation serves every scenario
of the same shape.

Positions are float32 metres from the scenario's origin (the head's position at t0 for a platoon,
the merge point for a merge scene), so a 5 s horizon never adds small increments to large numbers.

**Keys** (:func:`rollout_keys`): the key splits into one key per rollout; a rollout key splits
into ``init`` (one key per vehicle for ``initial_sample``) and ``steps`` (one key per step, each
split into one per vehicle). The same key gives bit-identical rollouts.

**Events**, per rollout, vehicle and step t = 1 .. T (after the t-th transition):
collision: bumper gap to the leader <= 0 (vehicle lengths included);
hard braking: realised acceleration (v_t - v_{t-1}) / dt <= :data:`HARD_BRAKING_MPS2`;
off road: the vehicle's front passed the end of its lane (``road_end``; +inf on the main lane).
Steps past the end of a scene (``step_mask`` = 0, merge episodes) count nothing.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import AheadArrays, MergeArrays, history_steps
from bayesdrive.drivers.base import DriverModel, EgoState, Series, fill_params
from bayesdrive.simulation.scenarios import Scenario

__all__ = [
    "HARD_BRAKING_MPS2",
    "Rollout",
    "RolloutKeys",
    "SceneArrays",
    "broadcast_params",
    "draw_particles",
    "platoon_scene",
    "rollout",
    "rollout_keys",
    "scene_arrays",
]

# The paper's hard-braking threshold.
HARD_BRAKING_MPS2 = -3.0


class SceneArrays(NamedTuple):
    """What the simulator needs of one scene (float32; positions from the scenario's origin).

    head_x, head_v, head_present: (T + 1,) the replayed leader of the first simulated vehicle
        (head_present = 0 where it is absent: the first vehicle then drives on free road).
    x0, v0: (N,) observed state of the simulated vehicles at t0, front to back.
    lead_length: (N,) length of each simulated vehicle's leader.
    road_end: (N,) position where each simulated vehicle's lane ends (+inf: it does not).
    step_mask: (T,) 1 for real steps, 0 for padding past the end of the scene.
    merge_x, merge_v, merge_present: (K, T + 1) replayed merge-lane vehicles (K = 0: none).
    merge_length: (K,) their lengths.
    dt: () step length (s).
    """

    head_x: Array
    head_v: Array
    head_present: Array
    x0: Array
    v0: Array
    lead_length: Array
    road_end: Array
    step_mask: Array
    merge_x: Array
    merge_v: Array
    merge_present: Array
    merge_length: Array
    dt: Array


class Rollout(NamedTuple):
    """Simulated trajectories and events, leading axes (rollout, vehicle).

    x, v, gap: (R, N, T + 1) position (from the scenario's origin), speed and bumper gap to the leader; index 0
        is the initial state. collision, hard_braking, off_road: (R, N, T) booleans for steps 1..T.
    """

    x: Array
    v: Array
    gap: Array
    collision: Array
    hard_braking: Array
    off_road: Array


def scene_arrays(scenario: Scenario) -> SceneArrays:
    """A scenario as simulator input: positions shifted by the scenario's origin, float32."""
    f32 = partial(jnp.asarray, dtype=jnp.float32)
    num_simulated = len(scenario.simulated_ids)
    head_x = np.where(scenario.head_present > 0, scenario.x[0] - scenario.origin, 0.0)
    return SceneArrays(
        head_x=f32(head_x),
        head_v=f32(np.where(scenario.head_present > 0, scenario.v[0], 0.0)),
        head_present=f32(scenario.head_present),
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
    )


def platoon_scene(
    head_v: np.ndarray, x0: np.ndarray, v0: np.ndarray, *, length: float, dt: float
) -> SceneArrays:
    """A synthetic platoon: the head starts at x = 0 and drives the speeds ``head_v`` (T + 1,)
    (positions by the trapezoid rule); the simulated vehicles start at ``x0`` with speeds ``v0``
    (front to back); every car is ``length`` metres long. For tests and speed benchmarks."""
    head_v = np.asarray(head_v, np.float64)
    steps, num_vehicles = len(head_v) - 1, len(x0)
    head_x = np.concatenate([[0.0], np.cumsum(0.5 * (head_v[1:] + head_v[:-1]) * dt)])
    f32 = partial(jnp.asarray, dtype=jnp.float32)
    no_merge_lane = jnp.zeros((0, steps + 1), jnp.float32)
    return SceneArrays(
        head_x=f32(head_x),
        head_v=f32(head_v),
        head_present=jnp.ones(steps + 1, jnp.float32),
        x0=f32(x0),
        v0=f32(v0),
        lead_length=jnp.full(num_vehicles, length, jnp.float32),
        road_end=jnp.full(num_vehicles, jnp.inf, jnp.float32),
        step_mask=jnp.ones(steps, jnp.float32),
        merge_x=no_merge_lane,
        merge_v=no_merge_lane,
        merge_present=no_merge_lane,
        merge_length=jnp.zeros(0, jnp.float32),
        dt=f32(dt),
    )


class RolloutKeys(NamedTuple):
    """The keys of one rollout: init (N,) and steps (T, N)."""

    init: Array
    steps: Array


def rollout_keys(key: Array, num_steps: int, num_vehicles: int) -> RolloutKeys:
    """The documented key schedule of one rollout (module docstring)."""
    key_init, key_steps = jax.random.split(key)
    per_step = jax.random.split(key_steps, num_steps)
    return RolloutKeys(
        init=jax.random.split(key_init, num_vehicles),
        steps=jax.vmap(lambda k: jax.random.split(k, num_vehicles))(per_step),
    )


def _from_leaders(head: Array, followers: Array) -> Array:
    """Each simulated vehicle's leader's values: the head's for the first, vehicle k-1's for
    vehicle k; for one step (head (), followers (N,)) or a path (head (T + 1,), followers
    (N, T + 1))."""
    return jnp.concatenate([jnp.asarray(head)[None], followers[:-1]])


def _start_buffer(scene: SceneArrays) -> Series:
    """The simulated vehicles' series (N, T + 1), to be written step by step; the replayed merge
    lane is known in advance."""
    num_vehicles, length = scene.x0.shape[0], scene.head_x.shape[0]
    zeros = jnp.zeros((num_vehicles, length), jnp.float32)
    merge = None
    if scene.merge_x.shape[0] > 0:

        def per_vehicle(values: Array) -> Array:
            return jnp.broadcast_to(values, (num_vehicles, *values.shape))

        # Distances to the merge point (x = 0) are measured from the front bumper.
        merge = MergeArrays(
            ego_to_merge=zeros,
            merge_to_merge=per_vehicle(-scene.merge_x.T),
            merge_v=per_vehicle(scene.merge_v.T),
            merge_length=per_vehicle(jnp.broadcast_to(scene.merge_length, scene.merge_x.T.shape)),
            merge_present=per_vehicle(scene.merge_present.T),
        )
    return Series(
        *(zeros for _ in range(7)),
        dt=jnp.broadcast_to(scene.dt, zeros.shape),
        merge=merge,
        ahead=AheadArrays(zeros, zeros, zeros, zeros, zeros),
    )


def _written(buffer: Series, scene: SceneArrays, t: Array, state) -> Series:
    """``buffer`` with every simulated vehicle's step t written: its speed, the *simulated* gap
    to its leader and the leader's speed, the second vehicle ahead, the leader's acceleration,
    and (in merge scenes) its distance to the merge point."""
    gap = _from_leaders(scene.head_x[t], state.x) - state.x - scene.lead_length
    lead_v = _from_leaders(scene.head_v[t], state.v)
    has_leader = _from_leaders(scene.head_present[t], jnp.ones_like(state.x))
    # The head's own leader is not replayed: the first vehicle sees no second vehicle ahead.
    has_leader2 = _from_leaders(0.0, has_leader) * has_leader
    before = jnp.maximum(t - 1, 0)
    earlier = jnp.where(t > 0, buffer.lead_v[:, before], lead_v)
    # Leaders never change in a scene; a replayed head that appears starts a new leader.
    kept_leader = (t > 0) & (buffer.has_leader[:, before] > 0) & (has_leader > 0)
    lead_age = jnp.where(kept_leader, buffer.ahead.lead_age[:, before] + 1.0, 0.0)
    column = {"v": state.v, "gap": gap, "lead_v": lead_v, "has_leader": has_leader}
    ahead = {
        "lead_acc": (lead_v - earlier) / scene.dt,
        "gap2": jnp.where(has_leader2 > 0, gap + _from_leaders(0.0, gap), 100.0),
        "lead2_v": jnp.where(has_leader2 > 0, _from_leaders(1.0, lead_v), 1.0),
        "has_leader2": has_leader2,
        "lead_age": lead_age,
    }
    buffer = buffer._replace(
        **{k: getattr(buffer, k).at[:, t].set(c) for k, c in column.items()},
        ahead=buffer.ahead._replace(
            **{k: getattr(buffer.ahead, k).at[:, t].set(c) for k, c in ahead.items()}
        ),
    )
    if buffer.merge is not None:
        merge = buffer.merge._replace(ego_to_merge=buffer.merge.ego_to_merge.at[:, t].set(-state.x))
        buffer = buffer._replace(merge=merge)
    return buffer


def _one_rollout(
    key: Array, model: DriverModel, params: Any, scene: SceneArrays, history: int
) -> Rollout:
    num_steps = scene.step_mask.shape[0]
    num_vehicles = scene.x0.shape[0]
    keys = rollout_keys(key, num_steps, num_vehicles)
    observed = EgoState(x=scene.x0, v=scene.v0)
    start = jax.vmap(model.initial_sample)(keys.init, params, observed)

    def step(carry, scan_in):
        state, buffer = carry
        t, step_keys = scan_in
        buffer = _written(buffer, scene, t, state)
        inputs = jax.vmap(lambda row: model.inputs_at(row, t, history))(buffer)
        moved = jax.vmap(model.transition_sample)(step_keys, params, state, inputs)
        buffer = buffer._replace(dx=buffer.dx.at[:, t].set(moved.x - state.x))
        return (moved, buffer), moved

    _, path = jax.lax.scan(step, (start, _start_buffer(scene)), (jnp.arange(num_steps), keys.steps))
    x = jnp.concatenate([start.x[:, None], path.x.T], axis=1)
    v = jnp.concatenate([start.v[:, None], path.v.T], axis=1)
    gap = _from_leaders(scene.head_x, x) - x - scene.lead_length[:, None]
    has_leader = _from_leaders(scene.head_present, jnp.ones_like(x)) > 0
    real = scene.step_mask[None, :] > 0
    acceleration = jnp.diff(v, axis=1) / scene.dt
    return Rollout(
        x=x,
        v=v,
        gap=gap,
        collision=(gap[:, 1:] <= 0) & has_leader[:, 1:] & real,
        hard_braking=(acceleration <= HARD_BRAKING_MPS2) & real,
        off_road=(x[:, 1:] > scene.road_end[:, None]) & real,
    )


def rollout(
    key: Array,
    model: DriverModel,
    params: Any,
    scene: SceneArrays,
    *,
    num_rollouts: int,
    dt: float | None = None,
) -> Rollout:
    """``num_rollouts`` closed-loop rollouts of ``model`` through ``scene``.

    ``params`` is the model's parameter NamedTuple with every leaf shaped (num_rollouts, N): one
    parameter set per rollout and simulated vehicle (see :func:`broadcast_params` and
    :func:`draw_particles`). Keys follow :func:`rollout_keys` after one split per rollout.
    ``dt`` (the scene's step as a Python number) is needed where ``scene`` is traced (inside
    ``jit``): it sets how much history a model that reads its past is given.
    """
    step = float(scene.dt) if dt is None else dt
    history = history_steps(step) if model.reads_history else 0
    return _rollouts(key, model, params, scene, num_rollouts=num_rollouts, history=history)


@partial(jax.jit, static_argnames=("model", "num_rollouts", "history"))
def _rollouts(key, model, params, scene, *, num_rollouts, history):
    keys = jax.random.split(key, num_rollouts)
    return jax.vmap(_one_rollout, in_axes=(0, None, 0, None, None))(
        keys, model, params, scene, history
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
