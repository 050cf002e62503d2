"""Posterior draws of a saved result as simulator parameters, per vehicle or pooled.

A result tree (:mod:`bayesdrive.inference.output`) holds, per parameter, draws shaped
(chain, draw, vehicle). The simulator wants, per vehicle, a (draws, parameters) matrix; the paper's
scene generation and the held-out generalisation use the pooled mixture of all vehicles' draws.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import xarray as xr

from bayesdrive.drivers.base import DriverModel
from bayesdrive.simulation.baselines import Policy, particle_policy

__all__ = ["fixed_params", "particles_by_vehicle", "pooled_policy", "posterior_policy"]


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
