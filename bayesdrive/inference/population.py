r"""Driver populations: how parameters vary from driver to driver.

Two views, both from the same prior box and likelihood as every engine:

(a) **Pooled mixture** (the paper's population): every vehicle's posterior draws pooled into one
sample, each vehicle weighted equally (:func:`pooled_population`). It mixes between-driver spread
with each vehicle's own posterior uncertainty, so it is wider than the population whenever single
vehicles are poorly identified.

(b) **Hierarchical model** (:func:`run`, the ``hierarchical`` engine of
:data:`~bayesdrive.inference.fit.ENGINES`), fitted with NUTS. Each inferred parameter k of
vehicle v lives on the logit-of-box scale, :math:`z_{vk} = \operatorname{logit}((\theta_{vk} -
l_k) / (u_k - l_k))`, and drivers are exchangeable draws from a population,

.. math::

    z_{vk} = \mu_k + \tau_k \varepsilon_{vk}, \quad \varepsilon_{vk} \sim N(0, 1), \quad
    \mu_k \sim N(0, 1.5^2), \quad \tau_k \sim \text{HalfNormal}(1),

(non-centred, which keeps NUTS out of the funnel when single vehicles say little). The priors
are stated on the logit scale: :math:`N(0, 1.5^2)` for the population median puts it anywhere in
the box with a nearly flat density (a logit-normal with sd 1.5 is close to uniform on the box),
and HalfNormal(1) for the spread allows from identical drivers (:math:`\tau \to 0`) to drivers
spread across most of the box (:math:`\tau \approx 2`). The population-level output has no
vehicle dim and sits in ``sample_stats`` (dims chain, draw, param): ``population_mu``,
``population_tau``, the population median ``population_median`` :math:`= l + (u - l)\,
\sigma(\mu)` in natural units, and ``population_new_driver``, one draw of a new driver's
parameters per posterior draw (the posterior predictive population distribution, in natural
units). The per-vehicle parameters, shrunk towards the population, fill the usual ``posterior``
group, so ``bayesdrive diagnose`` and the agreement table treat the result like any other (but
the run is joint: unlike the per-vehicle engines, a vehicle's draws depend on the others).

Measured on 12 simulated drivers (128 steps, tau/a_max/sigma, 4 chains x 300 + 300): the
non-centred form gave 0 divergences at mean tree depth 8.1, the centred form (``centred=True``)
18 divergences at depth 5.8, so non-centred is the default.

:func:`how_drivers_differ` summarises either view per parameter: the population's median and
10-90% range in natural units, the between-driver spread against the typical within-driver
posterior sd, and the pooled mixture's range for comparison.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Unpack

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
import xarray as xr
from jax import Array
from numpyro.infer.util import constrain_fn, potential_energy

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.likelihood import series_loglik
from bayesdrive.inference.nuts import INIT_RADIUS, NUTSConfig, sample_nuts
from bayesdrive.inference.output import (
    EngineInputs,
    EngineResult,
    metadata,
    psis_loo_check,
    set_metadata,
)
from bayesdrive.inference.vehicles import prepare

__all__ = [
    "MU_PRIOR_SD",
    "POPULATION_PRIORS",
    "TAU_PRIOR_SCALE",
    "how_drivers_differ",
    "pooled_population",
    "run",
]

MU_PRIOR_SD = 1.5
TAU_PRIOR_SCALE = 1.0
# The per-vehicle sample site: logit-scale parameters (centred) or standardised offsets.
VEHICLE_SITE = {True: "z", False: "eps"}
POPULATION_PRIORS = (
    f"logit-of-box scale: z = mu + tau_pop * eps, eps ~ N(0, 1); mu ~ N(0, {MU_PRIOR_SD}^2), "
    f"tau_pop ~ HalfNormal({TAU_PRIOR_SCALE}), per parameter"
)


def pooled_population(posterior: xr.Dataset | Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The paper's pooled mixture: each parameter's draws of all vehicles in one flat sample.

    Every vehicle has the same number of draws in a result, so pooling weights vehicles equally.
    """
    return {
        name: np.asarray(values).reshape(-1)
        for name, values in posterior.items()
        if np.ndim(values) == 3
    }


def _hierarchical_model(
    box: Any, log_lik_fn: Callable[[Array, Any], Array], num_vehicles: int, centred: bool
) -> Callable[[Any], None]:
    lower, width = box.lower, box.upper - box.lower
    num_params = lower.shape[0]

    def model(series: Any) -> None:
        with numpyro.plate("param", num_params):
            mu = numpyro.sample("mu", dist.Normal(0.0, MU_PRIOR_SD))
            tau = numpyro.sample("tau_pop", dist.HalfNormal(TAU_PRIOR_SCALE))
        if centred:
            z = numpyro.sample(
                VEHICLE_SITE[centred],
                dist.Normal(mu, tau).expand([num_vehicles, num_params]).to_event(2),
            )
        else:
            eps = numpyro.sample(
                VEHICLE_SITE[centred],
                dist.Normal(0.0, 1.0).expand([num_vehicles, num_params]).to_event(2),
            )
            z = mu + tau * eps
        theta = lower + width * jax.nn.sigmoid(z)
        numpyro.deterministic("theta", theta)
        numpyro.factor("log_likelihood", jnp.sum(jax.vmap(log_lik_fn)(theta, series)))

    return model


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    num_chains: int = 4,
    num_warmup: int = 500,
    target_accept_prob: float = 0.95,
    max_tree_depth: int = 10,
    centred: bool = False,
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """Fit the hierarchical population model (module docstring) jointly to all vehicles.

    One joint NUTS run of ``num_chains`` vectorised chains (each with its own warm-up) and
    ``num_particles`` draws in all: unlike the per-vehicle engines the vehicles are coupled
    through the population, which replaces the uniform prior box (so ``prior`` must be None).
    ``progress`` is called once, when the run is done.
    """
    if inputs.get("prior") is not None:
        raise ValueError("the hierarchical model has its own population prior; prior must be None")
    problem = prepare("hierarchical", arrays, inputs, num_particles=2000, whole_series=True)
    model, names, box, fixed_values = problem.model, problem.names, problem.box, problem.fixed
    series, num_samples = problem.series, -(-problem.num_particles // max(num_chains, 1))
    num_vehicles = problem.num_vehicles
    if num_vehicles < 2:
        raise ValueError("a population model needs at least 2 vehicles")
    config = NUTSConfig(
        num_chains=num_chains,
        num_warmup=num_warmup,
        num_samples=num_samples,
        target_accept_prob=target_accept_prob,
        max_tree_depth=max_tree_depth,
    )

    def log_lik(theta: Array, vehicle: Any) -> Array:
        return series_loglik(model, names, fixed_values, theta, vehicle).sum()

    joint = _hierarchical_model(box, log_lik, num_vehicles, centred)

    def potential_fn_gen(series: Any):
        return lambda z: potential_energy(joint, (series,), {}, z)

    every_vehicle = jax.vmap(
        lambda th, vehicle: series_loglik(model, names, fixed_values, th, vehicle)
    )

    def program(key: Array, series: Any):
        key_init, key_run, key_new = jax.random.split(key, 3)
        shapes = {
            "mu": (num_chains, len(names)),
            "tau_pop": (num_chains, len(names)),
            VEHICLE_SITE[centred]: (num_chains, num_vehicles, len(names)),
        }
        init_keys = dict(zip(shapes, jax.random.split(key_init, len(shapes)), strict=True))
        z0 = {
            site: jax.random.uniform(
                init_keys[site], shape, minval=-INIT_RADIUS, maxval=INIT_RADIUS
            )
            for site, shape in shapes.items()
        }
        draws = sample_nuts(key_run, potential_fn_gen, z0, (series,), config)
        values = jax.vmap(jax.vmap(lambda z: constrain_fn(joint, (series,), {}, z, True)))(draws.z)
        theta = values["theta"]  # (chain, draw, vehicle, K)
        mu, tau = values["mu"], values["tau_pop"]
        z_new = mu + tau * jax.random.normal(key_new, mu.shape, dtype=mu.dtype)
        log_likelihood = jax.vmap(jax.vmap(lambda th: every_vehicle(th, series)))(theta)
        return draws, theta, mu, tau, z_new, log_likelihood

    started = time.perf_counter()
    compiled = jax.jit(program).lower(key, series).compile()
    compile_time = time.perf_counter() - started
    started = time.perf_counter()
    draws, theta, mu, tau, z_new, log_likelihood = jax.block_until_ready(compiled(key, series))
    run_time = time.perf_counter() - started

    theta = np.asarray(theta, dtype=np.float64)
    per_draw = ("chain", "draw")
    population_dims = ("chain", "draw", "param")
    tree_depth = np.ceil(np.log2(np.asarray(draws.num_steps, dtype=np.float64) + 1.0))
    result = EngineResult(
        posterior={name: theta[..., k] for k, name in enumerate(names)},
        sample_stats={
            "diverging": (per_draw, np.asarray(draws.diverging)),
            "tree_depth": (per_draw, tree_depth),
            "n_steps": (per_draw, np.asarray(draws.num_steps)),
            "acceptance_rate": (per_draw, np.asarray(draws.accept_prob)),
            "energy": (per_draw, np.asarray(draws.energy)),
            "lp": (per_draw, -np.asarray(draws.potential_energy)),
            "step_size": (("chain",), np.asarray(draws.step_size)[:, -1]),
            "population_mu": (population_dims, np.asarray(mu, dtype=np.float64)),
            "population_tau": (population_dims, np.asarray(tau, dtype=np.float64)),
            "population_median": (population_dims, _natural(mu, box)),
            "population_new_driver": (population_dims, _natural(z_new, box)),
        },
        log_likelihood=np.asarray(log_likelihood),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={**config._asdict(), "population_priors": POPULATION_PRIORS},
    )
    if problem.progress is not None:
        problem.progress(num_vehicles, num_vehicles)
    return result


def how_drivers_differ(tree: xr.DataTree) -> dict[str, dict[str, Any]]:
    """Per parameter: population median and 10-90% range, between- vs within-driver spread.

    ``within_sd`` is the median over vehicles of each vehicle's posterior sd; ``between_sd`` is
    the sd of the population distribution (the hierarchical engine's ``population_new_driver``
    draws when the result has them, else the vehicles' posterior means). ``pooled_q10``/``pooled_q90``
    give the paper's pooled mixture for comparison.
    """
    posterior = tree["posterior"].to_dataset()
    pooled = pooled_population(posterior)
    stats = tree["sample_stats"].to_dataset() if "sample_stats" in tree.children else None
    has_population = stats is not None and "population_mu" in stats
    out: dict[str, dict[str, Any]] = {}
    for name in posterior.data_vars:
        draws = posterior[name]
        within = draws.std(("chain", "draw"))
        row: dict[str, Any] = {
            "within_sd": float(within.median()),
            "pooled_q10": float(np.quantile(pooled[name], 0.1)),
            "pooled_q90": float(np.quantile(pooled[name], 0.9)),
        }
        if has_population:
            population = stats.sel(param=name)
            new_driver = population["population_new_driver"].values.reshape(-1)
            median = population["population_median"].values.reshape(-1)
            tau = population["population_tau"].values.reshape(-1)
            row |= {
                "source": "hierarchical",
                "median": float(np.mean(median)),
                "median_q05": float(np.quantile(median, 0.05)),
                "median_q95": float(np.quantile(median, 0.95)),
                "q10": float(np.quantile(new_driver, 0.1)),
                "q90": float(np.quantile(new_driver, 0.9)),
                "between_sd": float(np.std(new_driver)),
                "tau_pop": float(np.mean(tau)),
                "tau_pop_q05": float(np.quantile(tau, 0.05)),
                "tau_pop_q95": float(np.quantile(tau, 0.95)),
            }
        else:
            means = draws.mean(("chain", "draw")).values
            row |= {
                "source": "vehicle posterior means",
                "median": float(np.median(means)),
                "q10": float(np.quantile(means, 0.1)),
                "q90": float(np.quantile(means, 0.9)),
                "between_sd": float(np.std(means)),
            }
        # Above 1: drivers differ by more than one driver's posterior can resolve.
        row["between_over_within"] = row["between_sd"] / row["within_sd"]
        out[name] = row
    return out


def _natural(z: Array | np.ndarray, box: Any) -> np.ndarray:
    """Logit-of-box values back in natural units (float64)."""
    lower, width = np.asarray(box.lower), np.asarray(box.upper - box.lower)
    return lower + width / (1.0 + np.exp(-np.asarray(z, dtype=np.float64)))


def _logit_box_draws(tree: xr.DataTree, box: Any, names: Sequence[str]) -> np.ndarray:
    """Each vehicle's posterior draws on the logit-of-box scale, (vehicle, draw, param)."""
    posterior = tree["posterior"].to_dataset()
    theta = np.stack(
        [posterior[name].transpose("vehicle", "chain", "draw").values for name in names], axis=-1
    ).reshape(posterior.sizes["vehicle"], -1, len(names))
    unit = (theta - np.asarray(box.lower)) / np.asarray(box.upper - box.lower)
    unit = np.clip(unit, 1e-7, 1.0 - 1e-7)  # draws on a bound (float rounding) stay finite
    return np.log(unit) - np.log1p(-unit)


def two_stage(
    key: Array,
    tree: xr.DataTree,
    *,
    num_particles: int = 2000,
    num_chains: int = 4,
    num_warmup: int = 500,
) -> xr.DataTree:
    """The hierarchical model (module docstring) fitted from per-vehicle results instead of the
    data: a two-stage estimator, for populations of many vehicles fitted apart (in chunks, on a
    cluster).

    ``tree`` holds per-vehicle posteriors under the uniform prior box (any per-vehicle engine).
    On the logit scale that prior has the logistic density :math:`p_0(z)`, so vehicle v's
    marginal likelihood under a population :math:`N(\\mu, \\tau^2)` is, up to a constant,
    :math:`E_{z \\sim p(z \\mid y_v)}[N(z; \\mu, \\tau) / p_0(z)]`, estimated by the mean over
    its draws (importance sampling from the per-vehicle posterior). NUTS samples
    :math:`(\\mu, \\tau)` under the hierarchical engine's priors; each posterior draw then
    resamples one draw per vehicle with weights :math:`N(z; \\mu, \\tau) / p_0(z)` (the vehicle's
    posterior under the population), and draws a new driver. Returns ``tree`` with those
    shrunk per-vehicle draws (their log-likelihood rows taken along) and the population's
    ``sample_stats`` as :func:`run` writes them. Exact as the draws per vehicle grow; with few
    draws and a population much narrower than a vehicle's posterior the weights concentrate
    (``sample_stats/importance_ess`` reports the smallest effective sample size per vehicle).
    """
    meta = metadata(tree)
    names = tuple(tree["posterior"].data_vars)
    box = get_model(meta["model"]).prior(names)
    z = jnp.asarray(_logit_box_draws(tree, box, names), dtype=jnp.float32)
    num_vehicles, num_draws, num_params = z.shape
    if num_vehicles < 2:
        raise ValueError("a population model needs at least 2 vehicles")
    log_p0 = jnp.sum(jax.nn.log_sigmoid(z) + jax.nn.log_sigmoid(-z), axis=-1)  # (V, J)

    def log_weights(mu: Array, tau: Array) -> Array:
        return dist.Normal(mu, tau).log_prob(z).sum(-1) - log_p0

    def population(z_draws: Array) -> None:
        with numpyro.plate("param", num_params):
            mu = numpyro.sample("mu", dist.Normal(0.0, MU_PRIOR_SD))
            tau = numpyro.sample("tau_pop", dist.HalfNormal(TAU_PRIOR_SCALE))
        marginal = jax.nn.logsumexp(log_weights(mu, tau), axis=1) - jnp.log(num_draws)
        numpyro.factor("marginal_likelihood", marginal.sum())

    config = NUTSConfig(
        num_chains=num_chains,
        num_warmup=num_warmup,
        num_samples=-(-num_particles // num_chains),
    )

    def program(key: Array):
        key_init, key_run, key_pick, key_new = jax.random.split(key, 4)
        z0 = {
            site: jax.random.uniform(
                k, (num_chains, num_params), minval=-INIT_RADIUS, maxval=INIT_RADIUS
            )
            for site, k in zip(("mu", "tau_pop"), jax.random.split(key_init), strict=True)
        }
        draws = sample_nuts(
            key_run,
            lambda zd: lambda u: potential_energy(population, (zd,), {}, u),
            z0,
            (z,),
            config,
        )
        values = jax.vmap(jax.vmap(lambda u: constrain_fn(population, (z,), {}, u, True)))(draws.z)
        mu, tau = values["mu"], values["tau_pop"]
        logits = jax.vmap(jax.vmap(log_weights))(mu, tau)  # (chain, draw, V, J)
        picked = jax.random.categorical(key_pick, logits, axis=-1)  # (chain, draw, V)
        weights = jax.nn.softmax(logits, axis=-1)
        ess = 1.0 / jnp.sum(weights**2, axis=-1)
        z_new = mu + tau * jax.random.normal(key_new, mu.shape, dtype=mu.dtype)
        return draws, mu, tau, picked, ess.min(axis=-1), z_new

    started = time.perf_counter()
    compiled = jax.jit(program).lower(key).compile()
    compile_time = time.perf_counter() - started
    started = time.perf_counter()
    draws, mu, tau, picked, ess, z_new = jax.block_until_ready(compiled(key))
    run_time = time.perf_counter() - started

    picked = np.asarray(picked)
    chain_draw = tree["posterior"].to_dataset().sizes["draw"]
    source = {"chain": picked // chain_draw, "draw": picked % chain_draw}

    row_of = {str(v): i for i, v in enumerate(tree["posterior"]["vehicle"].values)}

    def shrunk(values: xr.DataArray) -> xr.DataArray:
        """The picked draw of each vehicle, along a ``vehicle`` dim or an ``obs`` dim whose
        ``vehicle`` coordinate names each observation's vehicle."""
        if "obs" in values.dims:
            row = np.array([row_of[str(v)] for v in values["vehicle"].values])
            array = values.transpose("chain", "draw", "obs").values
            obs = np.arange(array.shape[-1])[None, None, :]
            taken = array[source["chain"][..., row], source["draw"][..., row], obs]
            dims = ("chain", "draw", "obs")
        else:
            array = values.transpose("chain", "draw", "vehicle", ...).values
            taken = array[source["chain"], source["draw"], np.arange(num_vehicles)[None, None, :]]
            dims = ("chain", "draw", "vehicle", *values.dims[3:])
        coords = {k: v for k, v in values.coords.items() if k not in ("chain", "draw")}
        return xr.DataArray(taken, dims=dims, coords=coords, attrs=values.attrs)

    out = tree.copy()  # shallow: the groups replaced below are built anew
    for group in ("posterior", "log_likelihood"):
        if group in tree.children:
            out[group] = xr.DataTree(
                tree[group]
                .to_dataset()
                .map(shrunk)
                .assign_coords(chain=np.arange(num_chains), draw=np.arange(picked.shape[1]))
            )
    per_draw, population_dims = ("chain", "draw"), ("chain", "draw", "param")
    out["sample_stats"] = xr.DataTree(
        xr.Dataset(
            {
                "diverging": (per_draw, np.asarray(draws.diverging)),
                "acceptance_rate": (per_draw, np.asarray(draws.accept_prob)),
                "importance_ess": (per_draw, np.asarray(ess)),
                "population_mu": (population_dims, np.asarray(mu, dtype=np.float64)),
                "population_tau": (population_dims, np.asarray(tau, dtype=np.float64)),
                "population_median": (population_dims, _natural(mu, box)),
                "population_new_driver": (population_dims, _natural(z_new, box)),
            },
            coords={"param": list(names)},
        )
    )
    set_metadata(
        out,
        engine="two-stage hierarchical",
        per_vehicle_engine=meta.get("engine"),
        population_priors=POPULATION_PRIORS,
        two_stage_options={**config._asdict(), "draws_per_vehicle": int(num_draws)},
        compile_time_s=compile_time,
        wall_time_s=run_time,
        # The per-vehicle draws are resampled now: copies, whatever the engine that drew them.
        psis_loo=psis_loo_check(out, markov_chains=False),
    )
    return out
