"""``fit``: run an inference engine on trajectories and get the result tree; ``summary`` of it.

Engines live in :data:`ENGINES` (name -> function). Every engine has the signature of
:class:`Engine` and returns an :class:`~bayesdrive.inference.core.output.EngineResult`; ``fit`` adds
the metadata, builds the one result layout of :mod:`bayesdrive.inference.core.output` and checks
convergence (:mod:`bayesdrive.inference.diagnostics.convergence`), so another engine joins by adding itself
to :data:`ENGINES` and :data:`INFERENCE_LIBRARY`.

Sizes: the filters (:data:`PARTICLE_ENGINES`) take ``num_particles``; every other engine takes
``draws`` (posterior draws in all), and the MCMC engines ``chains`` and ``warmup`` too
(:data:`MCMC_OPTIONS` names them as each engine does).
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
from bayesdrive.inference.core.likelihood import check_model, param_names
from bayesdrive.inference.core.output import EngineResult, build_tree, metadata, set_metadata
from bayesdrive.inference.diagnostics.convergence import check_convergence, log_problems
from bayesdrive.inference.engines import emcee, lm, nuts, pf, pmmh, smc
from bayesdrive.inference.population import hierarchical

__all__ = [
    "BATCHED_ENGINES",
    "ENGINES",
    "INFERENCE_LIBRARY",
    "MCMC_OPTIONS",
    "PARTICLE_ENGINES",
    "Engine",
    "check_engine_model",
    "first_vehicles",
    "fit",
    "get_engine",
    "summary",
]


class Engine(Protocol):
    """An inference engine: every vehicle of ``arrays``; its keyword arguments are every engine's
    :class:`~bayesdrive.inference.core.vehicles.EngineInputs` and its own options."""

    def __call__(self, key: Array, arrays: FollowerArrays, **options: Any) -> EngineResult: ...


ENGINES: dict[str, Engine] = {
    "smc": smc.run,
    "pf": pf.run,
    "nuts": nuts.run,
    "emcee": emcee.run,
    "lm": lm.run,
    "hierarchical": hierarchical.run,
    "pmmh": pmmh.run,
}
# The package that draws each engine's samples (ArviZ's inference_library attribute).
INFERENCE_LIBRARY = {
    "smc": "bayesdrive",
    "pf": "bayesdrive",
    "nuts": "numpyro",
    "emcee": "emcee",
    "lm": "scipy",
    "hierarchical": "numpyro",
    "pmmh": "bayesdrive",
}
PARTICLE_ENGINES = ("smc", "pf")
# Engines that vectorise vehicles on request (``vehicle_batch``).
BATCHED_ENGINES = ("smc", "nuts")
DEFAULT_SIZE = 1000
# fit's chains and warmup as each MCMC engine calls them (emcee's chains are its walkers).
MCMC_OPTIONS = {
    "nuts": {"chains": "num_chains", "warmup": "num_warmup"},
    "hierarchical": {"chains": "num_chains", "warmup": "num_warmup"},
    "pmmh": {"chains": "num_chains", "warmup": "num_warmup"},
    "emcee": {"chains": "num_walkers", "warmup": "num_burn"},
}


# Engines that score each vehicle's whole series at once (a model with a state filter fits them;
# smc's optional sequential pass does not, and refuses such a model itself).
WHOLE_SERIES = frozenset({"nuts", "emcee", "hierarchical", "smc"})


def check_engine_model(engine: str, model: DriverModel) -> None:
    """Refuse, in one line and before any work, an engine-model pair that cannot work: pmmh needs
    a model with an observation model; the other engines need exactly observed states, and those
    that score one step at a time (pf, lm) need a model without a state filter."""
    get_engine(engine)
    if engine == "pmmh":
        pmmh.check_model(model)
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
    num_particles: int | None = None,
    draws: int | None = None,
    chains: int | None = None,
    warmup: int | None = None,
    window: Window = "fit",
    fixed: Mapping[str, float] | None = None,
    seed: int | None = None,
    prior: Any = None,
    max_vehicles: int | None = None,
    vehicle_ids: Sequence[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    source: str = "FollowerArrays",
    pointwise: bool = True,
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
    ``num_particles`` (smc, pf; default 1000) or ``draws`` (the other engines: posterior draws in
    all, default 1000; ``num_particles`` is taken as ``draws`` there, as before), ``chains`` and
    ``warmup`` (MCMC engines, :data:`MCMC_OPTIONS`) size the run. ``engine_options`` go to the engine (e.g.
    ``ess_threshold`` for smc, ``epochs`` for pf). ``pointwise=False`` leaves the log_likelihood
    group out (every draw scored on every step: PSIS-LOO and ``arviz.compare`` need it, and for
    many vehicles it is most of the file and of the time after sampling). Returns the result tree
    (:mod:`bayesdrive.inference.core.output`); its metadata ``convergence`` holds the checks of
    :func:`~bayesdrive.inference.diagnostics.convergence.check_convergence`, whose problems are also logged
    as warnings.
    """
    run_engine = get_engine(engine)
    check_engine_model(engine, model)
    size, sizes = _sizes(engine, num_particles, draws, chains, warmup)
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
        inputs, repairs = dict(data.inputs), data.repairs
    else:
        arrays, data_format, flagged = data, "arrays", None
        inputs = repairs = None
    if max_vehicles is not None:
        arrays = first_vehicles(arrays, max_vehicles)
    result = run_engine(
        key,
        arrays,
        model=model,
        params=names,
        fixed=fixed,
        num_particles=size,
        prior=prior,
        progress=progress,
        pointwise=pointwise,
        **sizes,
        **engine_options,
    )
    defaults = {s.name: s.default for s in model.specs if s.name not in names}
    tree = build_tree(
        posterior=result.posterior,
        sample_stats=result.sample_stats,
        # Engines that score inside their sampler (nuts, pmmh, hierarchical) still have scores.
        log_likelihood=result.log_likelihood if pointwise else None,
        arrays=arrays,
        specs=model.specs,
        prior=result.prior,
        inference_library=INFERENCE_LIBRARY[engine],
        markov_chains=engine in MCMC_OPTIONS,
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
            **({"num_particles": size} if engine in PARTICLE_ENGINES else {}),
            "units": {s.name: s.unit for s in model.specs},
            "num_vehicles": len(arrays.vehicle_ids),
            "usable_steps": int(np.asarray(arrays.mask).sum()),
            "flagged_samples": flagged,
            "input_sha256": inputs,
            "input_repairs": repairs,
            "max_vehicles": max_vehicles,
            "engine_options": result.options,
            "compile_time_s": result.compile_time_s,
            "wall_time_s": result.wall_time_s,
        },
    )
    report = check_convergence(tree)
    log_problems(report)
    set_metadata(tree, convergence=report.as_metadata())
    return tree


def _sizes(
    engine: str,
    num_particles: int | None,
    draws: int | None,
    chains: int | None,
    warmup: int | None,
) -> tuple[int, dict[str, int]]:
    """The engine's ``num_particles`` argument (particles or draws) and its chain/warm-up options."""
    if engine in PARTICLE_ENGINES:
        if draws is not None or chains is not None or warmup is not None:
            raise ValueError(
                f"engine {engine!r} is sized by its particles (num_particles); draws apply to "
                f"{', '.join(sorted(set(ENGINES) - set(PARTICLE_ENGINES)))}, chains and warmup "
                f"to {', '.join(sorted(MCMC_OPTIONS))}"
            )
        return (DEFAULT_SIZE if num_particles is None else num_particles), {}
    if num_particles is not None and draws is not None:
        raise ValueError(f"engine {engine!r} takes draws, not both draws and num_particles")
    size = next((n for n in (draws, num_particles) if n is not None), DEFAULT_SIZE)
    given = {"chains": chains, "warmup": warmup}
    names = MCMC_OPTIONS.get(engine, {})
    unknown = [k for k, v in given.items() if v is not None and k not in names]
    if unknown:
        raise ValueError(f"engine {engine!r} has no {' or '.join(unknown)} option")
    return size, {names[k]: v for k, v in given.items() if v is not None}


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
        "num_draws",
        "num_chains",
        "units",
        "data_source",
        "window",
        "flagged_samples",
        "input_sha256",
        "input_repairs",
        "max_vehicles",
        "usable_steps",
        "wall_time_s",
        "compile_time_s",
        "engine_options",
        "convergence",
        "psis_loo",
        "code",
        "created_at",
    )
    result = {**{k: meta[k] for k in keys if k in meta}, "vehicles": vehicles}
    if "log_evidence" in stats:
        result["log_evidence"] = dict(
            zip(vehicle_ids, stats["log_evidence"].values.astype(float).tolist(), strict=True)
        )
    return result
