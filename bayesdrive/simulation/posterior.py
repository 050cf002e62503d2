"""Posterior draws of a saved result as simulator parameters, per vehicle or pooled.

A result tree (:mod:`bayesdrive.inference.core.output`) holds, per parameter, draws shaped
(chain, draw, vehicle). The simulator wants, per vehicle, a (draws, parameters) matrix; the paper's
scene generation uses the pooled mixture of all vehicles' draws, and drivers with no data of their
own draw from the hierarchical engine's population distribution of a new driver.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data.readers._common import DEFAULT_LENGTH_M
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import metadata
from bayesdrive.simulation.baselines import Policy, particle_policy
from bayesdrive.simulation.rollout import draw_particles, platoon_scene, rollout

__all__ = [
    "fixed_params",
    "particles_by_vehicle",
    "pooled_policy",
    "population_draws",
    "population_policy",
    "posterior_policy",
    "posterior_predictive",
]


def particles_by_vehicle(tree: xr.DataTree, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Vehicle id -> (chain * draw, len(names)) matrix of that vehicle's posterior draws."""
    posterior = tree["posterior"].to_dataset()
    stacked = np.stack(
        [posterior[n].transpose("vehicle", "chain", "draw").values for n in names], axis=-1
    )
    flat = stacked.reshape(stacked.shape[0], -1, len(names))
    return {str(v): flat[i] for i, v in enumerate(posterior["vehicle"].values)}


def fixed_params(model: DriverModel, meta: Mapping[str, Any]) -> Any:
    """The model's parameters at the values the fit held fixed (its defaults where unrecorded)."""
    fixed = meta.get("fixed") or {}
    return model.params_type(*(float(fixed.get(s.name, s.default)) for s in model.specs))


def posterior_policy(
    name: str, model: DriverModel, tree: xr.DataTree, meta: Mapping[str, Any]
) -> Policy:
    """Each simulated vehicle draws one of its own posterior draws per rollout."""
    names = tuple(meta["params"])
    return particle_policy(
        name,
        model,
        names,
        particles_by_vehicle(tree, names),
        fixed_params(model, meta),
        f"{name}: the vehicle's own {meta.get('engine')} posterior, one draw per rollout",
    )


def pooled_policy(
    name: str,
    model: DriverModel,
    tree: xr.DataTree,
    meta: Mapping[str, Any],
    vehicle_ids: list[str],
) -> Policy:
    """Every vehicle in ``vehicle_ids`` draws from the pooled draws of all fitted vehicles (the
    paper's population mixture): for vehicles the fit never saw, e.g. held-out data sets."""
    names = tuple(meta["params"])
    pool = np.concatenate(list(particles_by_vehicle(tree, names).values()))
    return particle_policy(
        name,
        model,
        names,
        dict.fromkeys(vehicle_ids, pool),
        fixed_params(model, meta),
        f"{name}: pooled {meta.get('engine')} posterior of {len(pool)} draws over fitted vehicles",
    )


def population_draws(tree: xr.DataTree) -> tuple[tuple[str, ...], np.ndarray]:
    """The hierarchical engine's draws of a new driver's parameters
    (``sample_stats/population_new_driver``, one per posterior draw): the parameter names and a
    (chain * draw, parameters) matrix."""
    stats = tree["sample_stats"].to_dataset() if "sample_stats" in tree.children else None
    if stats is None or "population_new_driver" not in stats:
        raise ValueError(
            "the result holds no population distribution (sample_stats/population_new_driver): "
            "fit with the hierarchical engine, or export per vehicle or posterior draws"
        )
    new_driver = stats["population_new_driver"].transpose("chain", "draw", "param")
    names = tuple(str(p) for p in new_driver["param"].values)
    return names, new_driver.values.reshape(-1, len(names))


def population_policy(
    name: str, model: DriverModel, tree: xr.DataTree, vehicle_ids: list[str]
) -> Policy:
    """Every vehicle in ``vehicle_ids`` is a new driver: each rollout draws its parameters from
    the population distribution of the hierarchical fit ``tree`` (:func:`population_draws`), so
    nothing of the vehicle's own data is used."""
    names, draws = population_draws(tree)
    return particle_policy(
        name,
        model,
        names,
        dict.fromkeys(vehicle_ids, draws),
        fixed_params(model, metadata(tree)),
        f"{name}: a new driver drawn per rollout from the hierarchical population of "
        f"{tree['posterior'].sizes['vehicle']} fitted vehicles ({len(draws)} draws)",
    )


def posterior_predictive(
    key: Array,
    result: xr.DataTree,
    leader_speed: Sequence[float] | np.ndarray,
    *,
    dt: float,
    gap: float | Sequence[float],
    speed: float | Sequence[float] | None = None,
    vehicles: Sequence[str] | None = None,
    num_rollouts: int = 100,
    length: float = DEFAULT_LENGTH_M,
) -> xr.Dataset:
    """Simulate followers closed loop behind an observed leader, each follower drawing its
    parameters from a fitted vehicle's posterior (one draw per rollout).

    leader_speed: the leader's speeds (m/s), one every ``dt`` seconds; it is replayed, its
        positions the trapezoid rule of its speeds from 0.
    gap: each follower's bumper gap (m) to the car ahead at the start (one value for all, or one
        per follower); speed: their speeds at the start (default: the leader's first speed).
    vehicles: the fitted vehicles whose posteriors drive the followers, front to back (default:
        every vehicle of ``result``, in its order). length: every car's length (m; default the
        readers' passenger car).
    The key splits into one key for the draws and one for the rollouts
    (:mod:`bayesdrive.simulation.rollout`). Returns x (m, the leader's start at 0), v (m/s) and
    the bumper gap (m) per rollout, vehicle and time, the replayed leader, and the collision and
    hard-braking events of each step.
    """
    meta = metadata(result)
    model = get_model(meta["model"])
    if model.scene is not None:
        raise ValueError(
            f"model {model.name!r} reads the {model.scene} scene, which a replayed leader does not "
            f"give; simulate it with `bayesdrive evaluate` on {model.scene} scenes"
        )
    names = tuple(meta["params"])
    draws = particles_by_vehicle(result, names)
    chosen = list(draws) if vehicles is None else [str(v) for v in vehicles]
    missing = [v for v in chosen if v not in draws]
    if missing:
        raise KeyError(f"no posterior draws for vehicle(s) {missing}; fitted: {list(draws)}")
    head_v = np.asarray(leader_speed, dtype=np.float64)
    if head_v.ndim != 1 or len(head_v) < 2 or not np.all(np.isfinite(head_v)):
        raise ValueError("leader_speed must be a 1-d series of at least 2 finite speeds (m/s)")
    gaps = np.broadcast_to(np.asarray(gap, dtype=np.float64), (len(chosen),))
    if not np.all(gaps > 0):
        raise ValueError(f"every starting bumper gap must be positive (m), got {gaps.tolist()}")
    v0 = np.broadcast_to(
        np.asarray(head_v[0] if speed is None else speed, dtype=np.float64), (len(chosen),)
    )
    # Front bumpers, front to back: each car one length and one gap behind the one ahead.
    x0 = -np.cumsum(gaps + length)
    scene = platoon_scene(head_v, x0, v0, length=length, dt=dt)
    key_draws, key_rollouts = jax.random.split(key)
    params = draw_particles(
        key_draws,
        model,
        names,
        np.stack([draws[v] for v in chosen]),
        num_rollouts,
        fixed=fixed_params(model, meta),
    )
    simulated = rollout(key_rollouts, model, params, scene, num_rollouts=num_rollouts)
    time = np.arange(len(head_v)) * dt
    dims, step_dims = ("rollout", "vehicle", "time"), ("rollout", "vehicle", "step")
    return xr.Dataset(
        {
            "x": (dims, np.asarray(simulated.x), {"units": "m"}),
            "v": (dims, np.asarray(simulated.v), {"units": "m/s"}),
            "gap": (dims, np.asarray(simulated.gap), {"units": "m"}),
            "collision": (step_dims, np.asarray(simulated.collision)),
            "hard_braking": (step_dims, np.asarray(simulated.hard_braking)),
            "leader_x": ("time", np.asarray(scene.head_x), {"units": "m"}),
            "leader_v": ("time", head_v, {"units": "m/s"}),
        },
        coords={
            "rollout": np.arange(num_rollouts),
            "vehicle": chosen,
            "time": ("time", time, {"units": "s"}),
            "step": np.arange(1, len(head_v)),
        },
        attrs={
            "model": model.name,
            "engine": str(meta.get("engine")),
            "fit_seed": str(meta.get("seed")),
            "key_data": np.asarray(jax.random.key_data(key)).ravel().tolist(),
            "description": "followers simulated closed loop behind a replayed leader, "
            "parameters drawn per rollout from each vehicle's posterior",
        },
    )
