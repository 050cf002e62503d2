"""Scene generation (the paper's last section): synthetic platoons whose drivers are drawn from a
parameter distribution, a scene preset (``models/presets/*.json``) or a fitted posterior.

A generated scene is one lane of ``num_vehicles`` cars; the first drives on free road, every other
one follows the car ahead, all by the same stochastic driver model through the closed-loop
simulator (:func:`bayesdrive.simulation.rollout.rollout`), each with its own parameter draw.

Initial conditions follow one documented rule, chosen before any result was seen: every car starts
at the common speed ``START_SPEED_FRACTION`` x the smallest desired speed in its platoon (so nobody
starts above its own desired speed) and at the model's equilibrium gap for that speed under its own
parameters (:func:`equilibrium_gap`), so a scene starts in a steady state and what follows is the
drivers' own dynamics. Any car-following model works that marks its desired-speed parameter
(``ParamSpec.desired_speed``).
"""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, fill_params
from bayesdrive.drivers.registry import base_model
from bayesdrive.simulation.rollout import (
    Rollout,
    SceneArrays,
    broadcast_params,
    platoon_scene,
    rollout,
)

__all__ = [
    "CAR_LENGTH_M",
    "START_SPEED_FRACTION",
    "SWEEP_DIFFERENCES",
    "Preset",
    "desired_speed_name",
    "draw_pooled",
    "draw_preset",
    "equilibrium_gap",
    "generate_scenes",
    "load_preset",
    "median_sweep",
    "pair_sweep",
]

START_SPEED_FRACTION = 0.8
# Desired-speed differences (follower - leader, m/s) of the leader-follower sweep.
SWEEP_DIFFERENCES = np.arange(-8.0, 8.1, 2.0)
CAR_LENGTH_M = 4.5
# The equilibrium gap is searched in [0, 1 km]; 40 halvings reach float32 precision there.
EQUILIBRIUM_SEARCH_M = 1000.0
BISECTIONS = 40


class Preset(NamedTuple):
    """Independent normal distributions per parameter (mean, sd), truncated to positive values."""

    name: str
    model: str
    description: str
    means: dict[str, float]
    sds: dict[str, float]


def load_preset(path: Path) -> Preset:
    """Read a scene preset (JSON: name, model, description, params {name: {mean, sd}})."""
    spec = json.loads(Path(path).read_text())
    missing = {"name", "model", "params"} - set(spec)
    if missing:
        raise ValueError(f"{path}: preset lacks {sorted(missing)}")
    params = spec["params"]
    return Preset(
        name=spec["name"],
        model=spec["model"],
        description=spec.get("description", ""),
        means={k: float(v["mean"]) for k, v in params.items()},
        sds={k: float(v["sd"]) for k, v in params.items()},
    )


def draw_preset(
    key: Array, model: DriverModel, preset: Preset, num_rollouts: int, num_vehicles: int
) -> Any:
    """One parameter set per rollout and vehicle (leaves (R, N)) from the preset's normals,
    truncated at zero (the same law as redrawing every non-positive value)."""
    names = tuple(preset.means)
    unknown = set(names) - set(model.param_names)
    if unknown:
        raise ValueError(
            f"preset {preset.name!r} names {sorted(unknown)}, not {model.name} parameters"
        )
    mean = jnp.asarray([preset.means[n] for n in names], jnp.float32)
    sd = jnp.asarray([preset.sds[n] for n in names], jnp.float32)
    standard = jax.random.truncated_normal(
        key, -mean / sd, jnp.inf, (num_rollouts, num_vehicles, len(names)), jnp.float32
    )
    base = broadcast_params(model.defaults(), num_rollouts, num_vehicles)
    return fill_params(model, names, mean + sd * standard, base)


def draw_pooled(
    key: Array,
    model: DriverModel,
    names: tuple[str, ...],
    particles: np.ndarray,
    num_rollouts: int,
    num_vehicles: int,
    fixed: Any = None,
) -> Any:
    """Parameter sets drawn from the paper's pooled mixture: all vehicles' posterior particles
    (shape (vehicles, particles, len(names))) pooled, each generated driver one uniform draw."""
    pool = jnp.asarray(np.reshape(particles, (-1, particles.shape[-1])), jnp.float32)
    index = jax.random.randint(key, (num_rollouts, num_vehicles), 0, pool.shape[0])
    base = broadcast_params(
        model.defaults() if fixed is None else fixed, num_rollouts, num_vehicles
    )
    return fill_params(model, names, pool[index], base)


def equilibrium_gap(model: DriverModel, params: Any, v: Array, dt: float) -> Array:
    """The bumper gap at which ``model``'s mean acceleration is zero at speed ``v`` behind a leader
    at the same speed, for every driver of ``params`` (leaves (N,)).

    Found by bisection on the base model's own rule (an extended model's base: in a steady state
    a delay, a memory of past noise or a second leader change nothing), so no model needs a
    formula of its own: a car-following rule brakes harder the shorter the gap, and below its
    desired speed it accelerates on an open road, so the acceleration changes sign once in the
    gap.
    """
    base = base_model(model)
    base_params = base.params_type(*params[: len(base.specs)])
    speed = jnp.broadcast_to(v, jnp.shape(jax.tree.leaves(params)[0]))
    state = EgoState(jnp.zeros_like(speed), speed)

    def mean_acceleration(gap):
        inputs = CarFollowingInputs(gap, speed, jnp.ones_like(speed), jnp.full_like(speed, dt))
        return base.mean_acceleration(base_params, state, inputs)

    def halve(_, bracket):
        low, high = bracket
        middle = 0.5 * (low + high)
        too_close = mean_acceleration(middle) < 0
        return jnp.where(too_close, middle, low), jnp.where(too_close, high, middle)

    start = (jnp.zeros_like(speed), jnp.full_like(speed, EQUILIBRIUM_SEARCH_M))
    low, high = jax.lax.fori_loop(0, BISECTIONS, halve, start)
    return 0.5 * (low + high)


def desired_speed_name(model: DriverModel) -> str:
    """The name of ``model``'s desired-speed parameter; a ValueError if it marks none."""
    name = model.desired_speed_param
    if name is None:
        raise ValueError(
            f"model {model.name!r} marks no desired-speed parameter (ParamSpec.desired_speed): "
            "scene generation starts platoons below it and sweeps it"
        )
    return name


def _steady_platoon(model: DriverModel, params: Any, num_steps: int, dt: float) -> SceneArrays:
    """Initial state of one platoon (module docstring); the first car has no leader."""
    start_speed = START_SPEED_FRACTION * jnp.min(getattr(params, desired_speed_name(model)))
    gaps = equilibrium_gap(model, params, start_speed, dt)
    # Car k starts behind car k-1 by its own equilibrium gap plus one car length.
    spacing = gaps[1:] + CAR_LENGTH_M
    x0 = -jnp.concatenate([jnp.zeros(1), jnp.cumsum(spacing)])
    # The platoon of the shared scene builder with its head absent: the first car drives alone.
    scene = platoon_scene(
        jnp.zeros(num_steps + 1, jnp.float32),
        x0,
        jnp.full(x0.shape[0], start_speed, jnp.float32),
        length=CAR_LENGTH_M,
        dt=dt,
    )
    return scene._replace(head_present=jnp.zeros(num_steps + 1, jnp.float32))


@partial(jax.jit, static_argnames=("model", "num_steps", "dt"))
def generate_scenes(
    key: Array, model: DriverModel, params: Any, *, num_steps: int, dt: float
) -> Rollout:
    """One generated scene per rollout: ``params`` leaves shaped (R, N), R scenes of N cars.

    Returns the simulator's :class:`Rollout` with leading axes (scene, vehicle); each scene is one
    rollout of its own platoon, with its own initial state.
    """
    scene_keys = jax.random.split(key, jax.tree.leaves(params)[0].shape[0])

    def one(scene_key, scene_params):
        scene = _steady_platoon(model, scene_params, num_steps, dt)
        single = jax.tree.map(lambda leaf: leaf[None], scene_params)
        result = rollout(scene_key, model, single, scene, num_rollouts=1, dt=dt)
        return jax.tree.map(lambda leaf: leaf[0], result)

    return jax.vmap(one)(scene_keys, params)


def pair_sweep(
    key: Array,
    model: DriverModel,
    base_params: Any,
    desired_speed_differences: np.ndarray,
    *,
    duration_s: float,
    dt: float,
) -> Rollout:
    """The leader-follower sweep: for each difference d, a leader with ``base_params`` and a
    follower whose desired speed is the leader's + d (everything else equal). Leading axes
    (difference, vehicle) with vehicle 0 the leader."""
    diffs = jnp.asarray(desired_speed_differences, jnp.float32)
    num_steps = round(duration_s / dt)

    def pair(values):
        return jnp.stack([values, values])

    params = jax.tree.map(
        lambda leaf: jnp.broadcast_to(pair(jnp.asarray(leaf, jnp.float32)), (diffs.shape[0], 2)),
        base_params,
    )
    name = desired_speed_name(model)
    params = params._replace(**{name: getattr(params, name).at[:, 1].add(diffs)})
    return generate_scenes(key, model, params, num_steps=num_steps, dt=dt)


def median_sweep(key: Array, model: DriverModel, params: Any, *, duration_s: float, dt: float):
    """:func:`pair_sweep` over :data:`SWEEP_DIFFERENCES` at the median of drawn ``params``."""
    base = jax.tree.map(lambda leaf: np.median(np.asarray(leaf)), params)
    return pair_sweep(key, model, base, SWEEP_DIFFERENCES, duration_s=duration_s, dt=dt)
