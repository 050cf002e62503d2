"""``fit``: run an inference engine on trajectories and get the result tree; ``summary`` of it.

Engines live in :data:`ENGINES` (name -> function). Every engine has the signature of
:class:`Engine` and returns an :class:`~bayesdrive.inference.output.EngineResult`; ``fit`` adds
the metadata and builds the one result layout of :mod:`bayesdrive.inference.output`, so another
engine (nuts, emcee, lm) joins by adding itself to :data:`ENGINES`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import jax
import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import FollowerArrays, Window, follower_arrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference import ensemble, latent, lm, nuts, pf, population, smc
from bayesdrive.inference.likelihood import check_model, param_names
from bayesdrive.inference.output import EngineResult, build_tree, metadata

__all__ = [
    "ENGINES",
    "Engine",
    "check_engine_model",
    "first_vehicles",
    "fit",
    "get_engine",
    "summary",
]


class Engine(Protocol):
    """An inference engine: every vehicle of ``arrays``, parameters ``params`` (None: all)."""

    def __call__(
        self,
        key: Array,
        arrays: FollowerArrays,
        *,
        model: DriverModel,
        params: Sequence[str] | None,
        fixed: Mapping[str, float] | None,
        num_particles: int,
        prior: Any,
        progress: Callable[[int, int], None] | None,
        **options: Any,
    ) -> EngineResult: ...


ENGINES: dict[str, Engine] = {
    "smc": smc.run,
    "pf": pf.run,
    "nuts": nuts.run,
    "emcee": ensemble.run,
    "lm": lm.run,
    "hierarchical": population.run,
    "pmmh": latent.run,
}


# Engines that score each vehicle's whole series at once (a model with a state filter fits them).
WHOLE_SERIES = frozenset({"nuts", "emcee", "hierarchical"})


def check_engine_model(engine: str, model: DriverModel) -> None:
    """Refuse, in one line and before any work, an engine-model pair that cannot work: pmmh needs
    a model with an observation model; the other engines need exactly observed states, and those
    that score one step at a time (smc, pf, lm) need a model without a state filter."""
    get_engine(engine)
    if engine == "pmmh":
        latent.check_model(model)
    else:
        check_model(model, engine, whole_series=engine in WHOLE_SERIES)


def get_engine(name: str) -> Engine:
    """The engine called ``name``; a ValueError lists the known ones."""
    if name not in ENGINES:
        raise ValueError(f"unknown engine {name!r}; choose one of {sorted(ENGINES)}")
    return ENGINES[name]


def fit(
    key: Array,
    data: Trajectories | FollowerArrays,
    *,
    model: DriverModel = IDM,
    engine: str = "smc",
    params: Sequence[str] | None = None,
    num_particles: int = 1000,
    window: Window = "fit",
    fixed: Mapping[str, float] | None = None,
    seed: int | None = None,
    prior: Any = None,
    max_vehicles: int | None = None,
    vehicle_ids: Sequence[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    source: str = "FollowerArrays",
    **engine_options: Any,
) -> xr.DataTree:
    """Infer per-vehicle distributions over ``params`` of ``model`` from ``data``.

    ``data`` is a :class:`Trajectories` (its ``window`` is cut with
    :func:`~bayesdrive.data.views.follower_arrays`) or ready :class:`FollowerArrays` (then
    ``window`` should name the window they were built for and ``source`` the data they came
    from; both are only recorded). Parameters not
    inferred take ``fixed`` values, else the model's defaults. ``seed`` is recorded in the metadata
    beside the key's own data. ``prior`` (default: the model's uniform box) needs
    ``logpdf(theta)`` and ``sample(key, shape)``. ``max_vehicles`` keeps only the first vehicles
    that have usable steps (quick runs); ``vehicle_ids`` fits only those vehicles of a
    :class:`Trajectories` (their leaders are still read). ``progress(done, total)`` is called as vehicles finish.
    ``engine_options`` go to the engine (e.g.
    ``ess_threshold`` for smc, ``epochs`` for pf). Returns the result tree
    (:mod:`bayesdrive.inference.output`).
    """
    run_engine = get_engine(engine)
    check_engine_model(engine, model)
    names = param_names(model, params)
    fixed = dict(fixed or {})
    both = sorted(set(fixed) & set(names))
    if both:
        raise ValueError(f"parameter(s) {both} are both inferred and fixed")
    if isinstance(data, Trajectories):
        arrays = follower_arrays(
            data, window=window, vehicle_ids=None if vehicle_ids is None else list(vehicle_ids)
        )
        source, data_format, flagged = data.source, data.format, len(data.flags)
    else:
        arrays, data_format, flagged = data, "arrays", None
    if max_vehicles is not None:
        arrays = first_vehicles(arrays, max_vehicles)
    result = run_engine(
        key,
        arrays,
        model=model,
        params=names,
        fixed=fixed,
        num_particles=num_particles,
        prior=prior,
        progress=progress,
        **engine_options,
    )
    defaults = {s.name: s.default for s in model.specs if s.name not in names}
    return build_tree(
        posterior=result.posterior,
        sample_stats=result.sample_stats,
        log_likelihood=result.log_likelihood,
        log_likelihood_draws=result.log_likelihood_draws,
        arrays=arrays,
        metadata={
            "engine": engine,
            "model": model.name,
            "params": list(names),
            "fixed": {**defaults, **{k: float(v) for k, v in fixed.items()}},
            "prior": "uniform box (model bounds)" if prior is None else type(prior).__name__,
            "seed": seed,
            "key_data": np.asarray(jax.random.key_data(key)).ravel().tolist(),
            "data_source": source,
            "data_format": data_format,
            "window": window,
            "num_particles": num_particles,
            "num_vehicles": len(arrays.vehicle_ids),
            "usable_steps": int(np.asarray(arrays.mask).sum()),
            "flagged_samples": flagged,
            "max_vehicles": max_vehicles,
            "engine_options": result.options,
            "compile_time_s": result.compile_time_s,
            "wall_time_s": result.wall_time_s,
        },
    )


def first_vehicles(arrays: FollowerArrays, count: int) -> FollowerArrays:
    """The first ``count`` vehicles of ``arrays`` (all of them when there are fewer)."""
    if count < 1:
        raise ValueError(f"the number of vehicles must be positive, got {count}")
    return arrays.subset(slice(0, count))


def _describe(values: np.ndarray) -> dict[str, float]:
    q05, q95 = np.quantile(values, [0.05, 0.95])
    return {
        "mean": float(np.mean(values)),
        "sd": float(np.std(values)),
        "q05": float(q05),
        "q95": float(q95),
    }


def summary(tree: xr.DataTree) -> dict[str, Any]:
    """The figures of summary.json: the run's metadata; ``vehicles``: per vehicle and parameter the
    posterior mean, sd and 5%/95% quantiles; ``log_evidence`` per vehicle where the engine
    reports one."""
    meta = metadata(tree)
    posterior = tree["posterior"].to_dataset()
    stats = tree["sample_stats"].to_dataset()
    vehicle_ids = [str(v) for v in posterior["vehicle"].values]
    vehicles = {
        vehicle: {
            name: _describe(posterior[name].values[:, :, i].ravel()) for name in meta["params"]
        }
        for i, vehicle in enumerate(vehicle_ids)
    }
    keys = (
        "engine",
        "model",
        "seed",
        "params",
        "fixed",
        "num_particles",
        "data_source",
        "window",
        "flagged_samples",
        "max_vehicles",
        "usable_steps",
        "wall_time_s",
        "compile_time_s",
        "engine_options",
        "created_at",
    )
    result = {**{k: meta.get(k) for k in keys}, "vehicles": vehicles}
    if "log_evidence" in stats:
        result["log_evidence"] = dict(
            zip(vehicle_ids, stats["log_evidence"].values.astype(float).tolist(), strict=True)
        )
    return result
