r"""The hierarchical population model: how parameters vary from driver to driver, fitted jointly
with NUTS (the ``hierarchical`` engine of :data:`~bayesdrive.inference.fit.ENGINES`).

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

The same model fitted from per-vehicle results instead of the data is
:func:`bayesdrive.inference.population.two_stage.two_stage`; summaries of either view are in
:mod:`bayesdrive.inference.population.summary`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Unpack

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from jax import Array
from numpyro.infer.util import constrain_fn, potential_energy

from bayesdrive.data.views import FollowerArrays
from bayesdrive.inference.core.likelihood import series_loglik
from bayesdrive.inference.core.output import EngineResult
from bayesdrive.inference.core.vehicles import prepare
from bayesdrive.inference.engines.nuts import INIT_RADIUS, NUTSInputs, sample_nuts, sampler_settings

__all__ = ["MU_PRIOR_SD", "POPULATION_PRIORS", "TAU_PRIOR_SCALE", "natural_units", "run"]

MU_PRIOR_SD = 1.5
TAU_PRIOR_SCALE = 1.0
# The per-vehicle sample site: logit-scale parameters (centred) or standardised offsets.
VEHICLE_SITE = {True: "z", False: "eps"}
POPULATION_PRIORS = (
    f"logit-of-box scale: z = mu + tau_pop * eps, eps ~ N(0, 1); mu ~ N(0, {MU_PRIOR_SD}^2), "
    f"tau_pop ~ HalfNormal({TAU_PRIOR_SCALE}), per parameter"
)


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
    centred: bool = False,
    **inputs: Unpack[NUTSInputs],
) -> EngineResult:
    """Fit the hierarchical population model (module docstring) jointly to all vehicles, with
    the sampler's options :class:`~bayesdrive.inference.engines.nuts.NUTSOptions`.

    One joint NUTS run of ``num_chains`` vectorised chains (each with its own warm-up) and
    ``num_particles`` draws in all: unlike the per-vehicle engines the vehicles are coupled
    through the population, which replaces the uniform prior box (so ``prior`` must be None).
    ``progress`` is called once, when the run is done.
    """
    if inputs.get("prior") is not None:
        raise ValueError("the hierarchical model has its own population prior; prior must be None")
    sampler, inputs = sampler_settings(inputs)
    problem = prepare("hierarchical", arrays, inputs, num_particles=2000, whole_series=True)
    model, names, box, fixed_values = problem.model, problem.names, problem.box, problem.fixed
    series, num_vehicles = problem.series, problem.num_vehicles
    if num_vehicles < 2:
        raise ValueError("a population model needs at least 2 vehicles")
    config = sampler.with_draws(problem.num_particles)
    num_chains = config.num_chains

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
            "population_median": (population_dims, natural_units(mu, box)),
            "population_new_driver": (population_dims, natural_units(z_new, box)),
        },
        log_likelihood=np.asarray(log_likelihood),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={**config._asdict(), "population_priors": POPULATION_PRIORS},
    )
    if problem.progress is not None:
        problem.progress(num_vehicles, num_vehicles)
    return result


def natural_units(z: Array | np.ndarray, box: Any) -> np.ndarray:
    """Logit-of-box values back in natural units (float64)."""
    lower, width = np.asarray(box.lower), np.asarray(box.upper - box.lower)
    return lower + width / (1.0 + np.exp(-np.asarray(z, dtype=np.float64)))
