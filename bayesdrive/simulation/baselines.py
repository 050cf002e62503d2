"""Baseline policies, run through the same simulator as fitted posteriors.

A :class:`Policy` is a driver model plus a rule that gives every simulated vehicle of a scenario
its parameters for every rollout. Baselines (names in :data:`BASELINES`):

* ``idm-default``: the IDM at Treiber's textbook values as the paper lists them (v_des 30 m/s,
  tau 1.0 s, d_min 2 m, a_max 3 m/s^2, b_pref 2 m/s^2), deterministic (sigma = 0: every rollout
  is the same).
* ``idm-nls``: the IDM at the paper's published nonlinear-least-squares fit (v_des 17.837 m/s,
  tau 0.918 s, d_min 5.249 m, a_max 0.758 m/s^2, b_pref 3.811 m/s^2), deterministic.
* ``idm-lm``: the IDM fitted per vehicle by Levenberg-Marquardt on its own *fitting* window
  (:mod:`bayesdrive.inference.lm`), deterministic at the fitted values.
* ``cv`` / ``ca``: constant velocity / constant acceleration +1 m/s^2 (the paper's value),
  deterministic; the :data:`CONSTANT_ACCELERATION` model below.
* ``blackbox``: a behavioural-cloning MLP policy (:mod:`bayesdrive.simulation.blackbox`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.idm import (
    IDM,
    IDMParams,
    exact_initial_sample,
    exact_observation_logpdf,
    noisy_step,
    step_logpdf,
)
from bayesdrive.simulation.rollout import broadcast_params, draw_particles

__all__ = [
    "BASELINES",
    "CONSTANT_ACCELERATION",
    "IDM_DEFAULT_PARAMS",
    "IDM_NLS_PARAMS",
    "ConstantAccelerationParams",
    "Policy",
    "fixed_policy",
    "particle_policy",
    "per_vehicle_policy",
]


class ConstantAccelerationParams(NamedTuple):
    """a ~ N(acc, sigma^2) whatever the traffic: acc (m/s^2), sigma (m/s^2)."""

    acc: Array
    sigma: Array


def _constant_mean(
    params: ConstantAccelerationParams, state: EgoState, inputs: CarFollowingInputs
) -> Array:
    del inputs
    return jnp.broadcast_to(params.acc, jnp.shape(state.v))


def _constant_sample(key, params, state, inputs) -> EgoState:
    return noisy_step(key, state, _constant_mean(params, state, inputs), params.sigma, inputs.dt)


def _constant_logpdf(params, state, next_state, inputs) -> Array:
    mean_acc = _constant_mean(params, state, inputs)
    return step_logpdf(state, next_state, mean_acc, params.sigma, inputs.dt)


CONSTANT_ACCELERATION = DriverModel(
    name="constant-acceleration",
    params_type=ConstantAccelerationParams,
    specs=(
        ParamSpec("acc", "m/s^2", 0.0, -5.0, 5.0, "constant acceleration"),
        ParamSpec("sigma", "m/s^2", 0.0, 0.0, 2.0, "execution-noise sd (0: deterministic)"),
    ),
    mean_acceleration=_constant_mean,
    transition_sample=_constant_sample,
    transition_logpdf=_constant_logpdf,
    observation_logpdf=exact_observation_logpdf,
    initial_sample=exact_initial_sample,
)

IDM_DEFAULT_PARAMS = IDMParams(v_des=30.0, d_min=2.0, tau=1.0, a_max=3.0, b_pref=2.0, sigma=0.0)
IDM_NLS_PARAMS = IDMParams(
    v_des=17.837, d_min=5.249, tau=0.918, a_max=0.758, b_pref=3.811, sigma=0.0
)

# (key, simulated vehicle ids, number of rollouts) -> parameters with leaves (R, N).
ParamsFor = Callable[[Array, tuple[str, ...], int], Any]


class Policy(NamedTuple):
    """What the evaluation runs: a model, the parameters per rollout and vehicle, and a record.

    details: JSON-ready facts about the policy (fixed values, seeds, fit summaries).
    """

    name: str
    model: DriverModel
    params_for: ParamsFor
    description: str
    details: dict[str, Any]


def fixed_policy(name: str, model: DriverModel, params: Any, description: str) -> Policy:
    """Every vehicle in every rollout uses ``params`` (scalar leaves)."""

    def params_for(key: Array, vehicle_ids: tuple[str, ...], num_rollouts: int) -> Any:
        del key
        return broadcast_params(params, num_rollouts, len(vehicle_ids))

    values = {field: float(value) for field, value in params._asdict().items()}
    return Policy(name, model, params_for, description, {"params": values})


def per_vehicle_policy(
    name: str, model: DriverModel, params_by_vehicle: Mapping[str, Any], description: str
) -> Policy:
    """Each vehicle uses its own fixed parameters (e.g. a per-vehicle point fit)."""

    def params_for(key: Array, vehicle_ids: tuple[str, ...], num_rollouts: int) -> Any:
        del key
        missing = [v for v in vehicle_ids if v not in params_by_vehicle]
        if missing:
            raise KeyError(f"policy {name!r} has no parameters for vehicle(s) {missing}")
        stacked = model.params_type(
            *(
                jnp.asarray([getattr(params_by_vehicle[v], f) for v in vehicle_ids], jnp.float32)
                for f in model.params_type._fields
            )
        )
        return model.params_type(
            *(jnp.broadcast_to(leaf, (num_rollouts, len(vehicle_ids))) for leaf in stacked)
        )

    return Policy(name, model, params_for, description, {"vehicles": len(params_by_vehicle)})


def particle_policy(
    name: str,
    model: DriverModel,
    names: tuple[str, ...],
    particles_by_vehicle: Mapping[str, np.ndarray],
    fixed: Any,
    description: str,
) -> Policy:
    """Each rollout draws, per vehicle, one of that vehicle's equally weighted posterior draws
    (``particles_by_vehicle[id]``: (P, len(names))); other parameters from ``fixed``."""

    def params_for(key: Array, vehicle_ids: tuple[str, ...], num_rollouts: int) -> Any:
        missing = [v for v in vehicle_ids if v not in particles_by_vehicle]
        if missing:
            raise KeyError(f"the posterior has no draws for simulated vehicle(s) {missing}")
        stacked = np.stack([particles_by_vehicle[v] for v in vehicle_ids])
        return draw_particles(key, model, names, stacked, num_rollouts, fixed)

    return Policy(name, model, params_for, description, {"params": list(names)})


BASELINES = {
    "idm-default": lambda: fixed_policy(
        "idm-default", IDM, IDM_DEFAULT_PARAMS, "IDM at Treiber's defaults, sigma = 0"
    ),
    "idm-nls": lambda: fixed_policy(
        "idm-nls", IDM, IDM_NLS_PARAMS, "IDM at the paper's published NLS fit, sigma = 0"
    ),
    "cv": lambda: fixed_policy(
        "cv",
        CONSTANT_ACCELERATION,
        ConstantAccelerationParams(acc=0.0, sigma=0.0),
        "constant velocity",
    ),
    "ca": lambda: fixed_policy(
        "ca",
        CONSTANT_ACCELERATION,
        ConstantAccelerationParams(acc=1.0, sigma=0.0),
        "constant acceleration +1 m/s^2",
    ),
}
