r"""The hierarchical population model fitted from per-vehicle results (a two-stage estimator):
:func:`two_stage`."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
import xarray as xr
from jax import Array
from numpyro.infer.util import constrain_fn, potential_energy

from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import (
    metadata,
    psis_loo_check,
    set_metadata,
)
from bayesdrive.inference.engines.nuts import INIT_RADIUS, NUTSConfig, sample_nuts
from bayesdrive.inference.population.hierarchical import (
    MU_PRIOR_SD,
    POPULATION_PRIORS,
    TAU_PRIOR_SCALE,
    natural_units,
)

__all__ = ["two_stage"]


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
                "population_median": (population_dims, natural_units(mu, box)),
                "population_new_driver": (population_dims, natural_units(z_new, box)),
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
