"""Baseline policies, run through the same simulator as fitted posteriors.

A :class:`Policy` is a driver model plus a rule that gives every simulated vehicle of a scenario
its parameters for every rollout. Baselines (names in :data:`BASELINES`):

* ``idm-default``: the IDM at Treiber's textbook values as the paper lists them (v_des 30 m/s,
  tau 1.0 s, d_min 2 m, a_max 3 m/s^2, b_pref 2 m/s^2), deterministic (sigma = 0: every rollout
  is the same).
* ``idm-nls``: the IDM at the paper's published nonlinear-least-squares fit (v_des 17.837 m/s,
  tau 0.918 s, d_min 5.249 m, a_max 0.758 m/s^2, b_pref 3.811 m/s^2), deterministic.
* ``idm-lm``: the IDM fitted per vehicle by Levenberg-Marquardt on its own *fitting* window
  (:mod:`bayesdrive.inference.engines.lm`), deterministic at the fitted values.
* ``cv`` / ``ca``: constant velocity / constant acceleration +1 m/s^2 (the paper's value),
  deterministic; the :data:`CONSTANT_ACCELERATION` model below.
* ``blackbox``: a behavioural-cloning MLP policy (:mod:`bayesdrive.simulation.blackbox`) trained
  on the fitting windows of all vehicles.

Merge baselines (merge scenes only; the cooperating main-lane driver is simulated):

* ``cidm-c1``: the Cooperative IDM with c = 1 (yields to every merging car that arrives first) at
  the ``idm-default`` IDM parameters, deterministic.
* ``idm-nomerge``: the ``idm-default`` IDM, which ignores merging cars.

The per-vehicle fits (``idm-lm``) and the trained black box need fitting windows of the very
vehicles or scenes evaluated; merge scenes are split by episode, so the held-out cooperating
drivers have none: those two baselines run on platoon scenes only.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.cidm import CIDM, CIDMParams
from bayesdrive.drivers.execution_noise import (
    MAX_ACCELERATION,
    exact_initial_sample,
    exact_observation_logpdf,
    noisy_step,
    step_logpdf,
)
from bayesdrive.drivers.idm import IDM, IDMParams
from bayesdrive.inference.engines import lm
from bayesdrive.simulation.blackbox import (
    BlackboxParams,
    TrainConfig,
    blackbox_model,
    train_blackbox,
)
from bayesdrive.simulation.rollout import broadcast_params, draw_particles

__all__ = [
    "BASELINES",
    "CAR_FOLLOWING_ONLY",
    "CONSTANT_ACCELERATION",
    "IDM_DEFAULT_PARAMS",
    "IDM_NLS_PARAMS",
    "MERGE_ONLY",
    "PER_VEHICLE_FITS",
    "ConstantAccelerationParams",
    "Policy",
    "baseline_policy",
    "blackbox_policy",
    "fixed_policy",
    "lm_policy",
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


# A baseline that does not react to its leader does not brake to avoid it either (the paper's
# constant-velocity baseline collides): the physical limits only, no collision-free ceiling.
def _constant_sample(key, params, state, inputs) -> EgoState:
    mean_acc = _constant_mean(params, state, inputs)
    return noisy_step(key, state, mean_acc, params.sigma, inputs.dt, MAX_ACCELERATION)


def _constant_logpdf(params, state, next_state, inputs) -> Array:
    mean_acc = _constant_mean(params, state, inputs)
    return step_logpdf(state, next_state, mean_acc, params.sigma, inputs.dt, MAX_ACCELERATION)


CONSTANT_ACCELERATION = DriverModel(
    name="constant-acceleration",
    params_type=ConstantAccelerationParams,
    specs=(
        ParamSpec("acc", "m/s^2", 0.0, -5.0, 5.0, "constant acceleration", grid_step=0.1),
        ParamSpec(
            "sigma",
            "m/s^2",
            0.0,
            0.0,
            2.0,
            "execution-noise sd (0: deterministic)",
            grid_step=0.1,
            execution_noise=True,
        ),
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


def lm_policy(
    key: Array,
    traj: Trajectories,
    vehicle_ids: list[str],
    progress: Callable[[int, int], None] | None = None,
) -> Policy:
    """``idm-lm``: the IDM's five rule parameters fitted by Levenberg-Marquardt on each vehicle's
    own fitting window, then simulated deterministically (sigma = 0) at the fit. The fit is
    deterministic; ``key`` only feeds the engine's posterior draws, which are not used."""
    arrays = follower_arrays(traj, window="fit", vehicle_ids=vehicle_ids)
    unfit = sorted(set(vehicle_ids) - set(arrays.vehicle_ids))
    if unfit:
        raise DataError(
            f"{traj.source}: idm-lm: vehicle(s) {unfit} have no usable car-following step in "
            "their fitting window, so they cannot be fitted"
        )
    names = tuple(n for n in IDM.param_names if n != IDM.execution_noise_param)
    fit = lm.run(
        key,
        arrays,
        model=IDM,
        params=names,
        progress=progress,
        num_particles=1,
    )
    estimate = fit.sample_stats["estimate"][1]
    by_vehicle = {
        vid: IDMParams(**dict(zip(names, map(float, row), strict=True)), sigma=0.0)
        for vid, row in zip(arrays.vehicle_ids, estimate, strict=True)
    }
    policy = per_vehicle_policy(
        "idm-lm", IDM, by_vehicle, "IDM fitted per vehicle by LM on its fitting window, sigma = 0"
    )
    converged = fit.sample_stats["converged"][1]
    details = {
        **policy.details,
        "fitted": list(names),
        "not_converged": [v for v, ok in zip(arrays.vehicle_ids, converged, strict=True) if not ok],
    }
    return policy._replace(details=details)


def blackbox_policy(key: Array, traj: Trajectories, config: TrainConfig) -> Policy:
    """``blackbox``: the MLP policy trained by behavioural cloning on every vehicle's fitting
    window (:mod:`bayesdrive.simulation.blackbox`); ``key`` seeds the training."""
    trained = train_blackbox(key, follower_arrays(traj, window="fit"), config)
    policy = fixed_policy(
        "blackbox",
        blackbox_model(trained.net),
        BlackboxParams(),
        "MLP policy by behavioural cloning on the fitting windows (stands in for GAIL)",
    )
    details = {
        "config": config._asdict(),
        "final_training_loss": float(np.mean(trained.losses[-100:])),
    }
    return policy._replace(details=details)


_FIXED = {
    "idm-default": (IDM, IDM_DEFAULT_PARAMS, "IDM at Treiber's defaults, sigma = 0"),
    "idm-nls": (IDM, IDM_NLS_PARAMS, "IDM at the paper's published NLS fit, sigma = 0"),
    "cv": (CONSTANT_ACCELERATION, ConstantAccelerationParams(0.0, 0.0), "constant velocity"),
    "ca": (
        CONSTANT_ACCELERATION,
        ConstantAccelerationParams(1.0, 0.0),
        "constant acceleration +1 m/s^2",
    ),
    "cidm-c1": (
        CIDM,
        CIDMParams(*IDM_DEFAULT_PARAMS, c=1.0),
        "Cooperative IDM, c = 1, IDM at Treiber's defaults, sigma = 0",
    ),
    "idm-nomerge": (IDM, IDM_DEFAULT_PARAMS, "IDM at Treiber's defaults ignoring merging cars"),
}
BASELINES = ("idm-default", "idm-nls", "idm-lm", "cv", "ca", "blackbox", "cidm-c1", "idm-nomerge")
MERGE_ONLY = frozenset({"cidm-c1", "idm-nomerge"})
CAR_FOLLOWING_ONLY = frozenset({"idm-lm", "blackbox"})
# Baselines fitted per simulated vehicle: a vehicle without a usable fitting step has no fit.
PER_VEHICLE_FITS = frozenset({"idm-lm"})


def baseline_policy(
    name: str,
    key: Array,
    traj: Trajectories,
    vehicle_ids: list[str],
    *,
    blackbox_config: TrainConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Policy:
    """The baseline ``name`` (one of :data:`BASELINES`) for the simulated ``vehicle_ids``.

    ``key`` seeds what is trained or drawn (black box, LM engine); ``progress(done, total)``
    follows the per-vehicle fits.
    """
    if name in _FIXED:
        return fixed_policy(name, *_FIXED[name])
    if name == "idm-lm":
        return lm_policy(key, traj, vehicle_ids, progress)
    if name == "blackbox":
        return blackbox_policy(key, traj, blackbox_config or TrainConfig())
    raise KeyError(f"unknown baseline {name!r}; known: {', '.join(BASELINES)}")
