r"""``nuts``: the No-U-Turn sampler (NumPyro), a cross-check of the particle engines.

Per vehicle the model is the particle engines' posterior, written as a NumPyro model: the inferred
parameters ``theta ~ Uniform(lower, upper)`` on the model's prior box (NumPyro samples them in an
unconstrained space through the logit-of-box transform and adds the Jacobian), and the likelihood
``numpyro.factor`` of the masked sum of ``model.transition_logpdf`` over the vehicle's steps (the
shared :func:`~bayesdrive.inference.core.likelihood.series_loglik`).

**One compiled program, per-vehicle adaptation.** ``numpyro.infer.MCMC`` recompiles at every
``run()``, and batching all vehicles into one joint model (a vehicle plate) would make them share
one step size and one mass matrix, although their posterior scales differ by orders of magnitude
(a vehicle that never brakes hardly constrains ``b_pref``). So this engine drives NumPyro's
functional kernel, ``numpyro.infer.hmc.hmc(potential_fn_gen=...)``, directly: for one vehicle its
``num_chains`` chains are vectorised (``vmap``, NumPyro's ``chain_method="vectorized"``), each with
its own warm-up (dual-averaging step size and a diagonal mass matrix on Stan's windowed schedule),
and vehicles run through :func:`~bayesdrive.inference.core.vehicles.map_vehicles`, compiled once ahead
of time for all of them. Each vehicle's chains draw from the vehicle's own key (the seed with its
id folded in, :mod:`bayesdrive.inference.core.vehicles`), so a vehicle's draws are bit-identical
whichever vehicles it is fitted with, in whatever order or chunk. ``vehicle_batch`` vectorises that many vehicles together; NUTS trees are
``while`` loops, so a vectorised batch waits for its deepest tree at every iteration: one
vehicle at a time was faster than all in one batch (``benchmarks/bench_agreement.py
--nuts-batch`` measures both), so the default is 1.

``target_accept_prob`` defaults to 0.95, not NumPyro's 0.8: on real NGSIM followers the default
gave 67 divergences over 15 vehicles and 0.95 gave one (the team's measurement); on the 15 vehicles
of ``benchmarks/bench_agreement.py`` (all six parameters) 0.95 still met 20, 18 of them in one
vehicle. Divergences are reported per chain, draw and vehicle in ``sample_stats.diverging``
(never hidden); ``bayesdrive diagnose`` adds R-hat, bulk and
tail ESS and MCSE.

``dense_mass=True`` adapts a full mass matrix instead of a diagonal one. Measured on NGSIM vehicle
124 (``a_max``/``b_pref``/``tau`` correlated; 4 chains x 2000 draws after 1000 warm-up): minimum tail
ESS 224 diagonal, 1213 dense, with half the leapfrog steps per draw. On vehicle 140 (a long
``v_des`` tail) neither mass matrix, nor a 3000-iteration warm-up, gave a tail ESS above 700 per
8000 draws; only more draws did. Over all 15 vehicles of ``benchmarks/bench_agreement.py`` the
dense matrix met 727 divergences (467 on vehicle 11, whose posterior presses on prior bounds), the
diagonal one 31 with fewer draws: so the default stays diagonal.

**Starts.** Each chain starts at the most probable of ``init_candidates`` (default 16) uniform
draws in (-2, 2) on the unconstrained scale, each chain from draws of its own, so the starts stay
dispersed. One uniform draw (NumPyro's ``init_to_uniform``) was not enough for a model with a
state filter: far from the posterior, a filtered likelihood that changes by tens of nats within
1e-6 of a point shrinks warm-up's step size towards 1e-7, and a chain started in such a place
never leaves it. The drifting time gap's filter had such places until its mean was kept inside
tau's box (``reports/convergence/drifting_nuts.md``, "Stop 44" and "Stop 45").

**Extension.** After the run every vehicle's stored draws go through the checks that
:func:`~bayesdrive.inference.fit.fit` runs afterwards (R-hat, bulk and tail ESS,
:func:`~bayesdrive.inference.diagnostics.convergence.chain_problems`, same limits). A vehicle that fails runs
again from fresh dispersed starts, with its key folded with the factor, with a power of two times
the warm-up and the draws (the one that covers the worst ESS shortfall, at least double the last),
up to ``max_extension`` (:data:`MAX_EXTENSION`) times, and keeps every factor-th draw, so every
vehicle stores the same number. Why (``reports/convergence.md``): at the default 250 draws a chain
the six IDM parameters' bulk and tail ESS fell short of 400 on nearly every vehicle, slowest for
the ridge parameters ``v_des`` (unidentified in following without free driving: the posterior
spreads to the upper bound) and ``d_min`` (piled on the lower bound); more draws, not a dense mass
matrix, closed the gap; and since the first run at 250 draws a chain was wasted on nearly every
vehicle, the first run already has :data:`FIRST_EXTENSION` times the warm-up and draws (thinned
alike). ``sample_stats.extension`` records each vehicle's factor; a vehicle
still failing at the cap is left to fit's warnings, which then say what to try next.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple, TypedDict, Unpack

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from jax import Array
from numpyro.distributions.transforms import biject_to
from numpyro.infer.hmc import hmc
from numpyro.infer.util import potential_energy

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.core.likelihood import StepInputs, series_loglik
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.vehicles import (
    log_likelihood_draws,
    posterior_draws,
    prepare,
    static_key,
)
from bayesdrive.inference.diagnostics.convergence import EXTENSION_MIN_DRAWS, chain_problems

__all__ = [
    "FIRST_EXTENSION",
    "INIT_RADIUS",
    "MAX_EXTENSION",
    "NUTSConfig",
    "NUTSDraws",
    "run",
    "sample_nuts",
]

# Chains start uniformly in (-2, 2) on the unconstrained scale (NumPyro's init_to_uniform): the
# middle 76% of each prior interval, so chains start dispersed as R-hat needs.
INIT_RADIUS = 2.0
# A vehicle that fails its checks runs again with 2, 4, ... up to this many times the warm-up and
# draws (module docstring, "Extension").
MAX_EXTENSION = 16
# The first run's factor: at fit's 1000 draws an unextended run fell short on nearly every vehicle
# of six or seven parameters, and 4x passed in a fraction of the time extension from 1x took
# (module docstring, "Extension").
FIRST_EXTENSION = 4
# An extension asks for this much more ESS than the shortfall it covers (see _next_factor).
EXTENSION_MARGIN = 1.25


class NUTSConfig(NamedTuple):
    """Settings of the sampler (see the module docstring)."""

    num_chains: int = 4
    num_warmup: int = 500
    num_samples: int = 500
    target_accept_prob: float = 0.95
    max_tree_depth: int = 10
    dense_mass: bool = False
    # Each chain starts at the most probable of this many uniform draws in the start radius
    # (module docstring, "Starts").
    init_candidates: int = 16
    # Keep every thin-th post-warm-up draw (an extended run stores as many draws as the first).
    thin: int = 1

    def with_draws(self, num_particles: int) -> NUTSConfig:
        """These settings with ``num_particles`` draws in all over the chains (rounded up per
        chain)."""
        return self._replace(num_samples=-(-num_particles // max(self.num_chains, 1)))


class NUTSOptions(TypedDict, total=False):
    """The sampler's options that nuts and the hierarchical engine take (defaults:
    :class:`NUTSConfig`'s; the draws per chain follow from ``num_particles``)."""

    num_chains: int
    num_warmup: int
    target_accept_prob: float
    max_tree_depth: int
    dense_mass: bool
    init_candidates: int


class NUTSInputs(EngineInputs, NUTSOptions, total=False):
    """What an engine on NUTS takes beside its own options: every engine's inputs and the
    sampler's options."""


def sampler_settings(inputs: NUTSInputs) -> tuple[NUTSConfig, EngineInputs]:
    """The sampler's options given in ``inputs`` as settings (:class:`NUTSConfig`'s defaults for
    the others; :meth:`NUTSConfig.with_draws` sets the draws per chain) and the engine inputs
    left."""
    given = {k: v for k, v in inputs.items() if k in NUTSOptions.__annotations__}
    return NUTSConfig(**given), {k: v for k, v in inputs.items() if k not in given}


class NUTSDraws(NamedTuple):
    """Post-warm-up output of :func:`sample_nuts`: unconstrained draws and per-draw statistics.

    Every field has leading dims (chain, draw); ``z`` keeps the pytree layout of the initial values.
    """

    z: Any
    diverging: Array
    num_steps: Array
    accept_prob: Array
    energy: Array
    potential_energy: Array
    step_size: Array


def sample_nuts(
    key: Array,
    potential_fn_gen: Callable[..., Callable[[Any], Array]],
    init_z: Any,
    model_args: tuple[Any, ...],
    config: NUTSConfig,
) -> NUTSDraws:
    """NUTS chains, one per leading entry of ``init_z``, vectorised, each with its own warm-up.

    ``potential_fn_gen(*model_args)`` returns the potential energy (minus the log density on the
    unconstrained scale, Jacobian included) of a point shaped like one chain's ``init_z``. Pure and
    traceable: call it under ``jit``/``vmap``.
    """
    init_kernel, sample_kernel = hmc(potential_fn_gen=potential_fn_gen, algo="NUTS")

    def one_chain(key: Array, z0: Any) -> NUTSDraws:
        state = init_kernel(
            z0,
            num_warmup=config.num_warmup,
            target_accept_prob=config.target_accept_prob,
            max_tree_depth=config.max_tree_depth,
            dense_mass=config.dense_mass,
            model_args=model_args,
            rng_key=key,
        )

        def iterate(state, _):
            state = sample_kernel(state, model_args=model_args)
            return state, NUTSDraws(
                z=state.z,
                diverging=state.diverging,
                num_steps=state.num_steps,
                accept_prob=state.accept_prob,
                energy=state.energy,
                potential_energy=state.potential_energy,
                step_size=state.adapt_state.step_size,
            )

        # One scan over warm-up and sampling (warm-up draws dropped afterwards): a second loop
        # would trace and compile the whole NUTS tree builder a second time.
        _, draws = jax.lax.scan(iterate, state, length=config.num_warmup + config.num_samples)
        # The last draw of every thin-long stretch: the final draw is always kept.
        start = config.num_warmup + config.thin - 1
        return jax.tree.map(lambda a: a[start :: config.thin], draws)

    num_chains = jax.tree.leaves(init_z)[0].shape[0]
    return jax.vmap(one_chain)(jax.random.split(key, num_chains), init_z)


def _box_model(
    box: Any, log_lik_fn: Callable[[Array, Any], Array], prior: Any
) -> Callable[[Any], None]:
    """The NumPyro model of one vehicle: uniform prior on the box, the likelihood as a factor.

    A custom ``prior`` (with ``logpdf``) is added as a factor on top of the uniform base, so its
    density is exact wherever its support lies inside the box.
    """

    def vehicle_model(series: Any) -> None:
        theta = numpyro.sample("theta", dist.Uniform(box.lower, box.upper).to_event(1))
        if prior is not None:
            numpyro.factor("prior", prior.logpdf(theta))
        numpyro.factor("log_likelihood", log_lik_fn(theta, series))

    return vehicle_model


class _VehicleOutput(NamedTuple):
    theta: Array  # (chain, draw, d)
    log_likelihood: Array  # (chain, draw, T)
    diverging: Array  # (chain, draw)
    tree_depth: Array
    num_steps: Array
    accept_prob: Array
    energy: Array
    lp: Array
    step_size: Array  # (chain,)


def _nuts_vehicle(
    key: Array,
    series: StepInputs,
    *,
    model: DriverModel,
    names: tuple[str, ...],
    fixed: Any,
    box: Any,
    prior: Any,
    config: NUTSConfig,
) -> _VehicleOutput:
    """Warm-up and sampling of ``config.num_chains`` vectorised chains for one vehicle."""

    def log_lik(theta: Array, series: StepInputs) -> Array:
        return series_loglik(model, names, fixed, theta, series).sum()

    vehicle_model = _box_model(box, log_lik, prior)

    def potential_fn_gen(series: StepInputs):
        return functools.partial(potential_energy, vehicle_model, (series,), {})

    key_init, key_run = jax.random.split(key)
    candidates = jax.random.uniform(
        key_init,
        (config.num_chains, config.init_candidates, len(names)),
        minval=-INIT_RADIUS,
        maxval=INIT_RADIUS,
    )
    potential = jax.vmap(jax.vmap(lambda z: potential_fn_gen(series)({"theta": z})))(candidates)
    best = jnp.argmin(jnp.where(jnp.isnan(potential), jnp.inf, potential), axis=1)
    z0 = jnp.take_along_axis(candidates, best[:, None, None], axis=1)[:, 0]
    draws = sample_nuts(key_run, potential_fn_gen, {"theta": z0}, (series,), config)
    to_box = biject_to(dist.Uniform(box.lower, box.upper).support)
    theta = to_box(draws.z["theta"])

    per_draw = jax.vmap(jax.vmap(lambda th: series_loglik(model, names, fixed, th, series)))
    # NUTS builds trees of 2^k - 1 leapfrog steps: depth k = log2(steps + 1), rounded up.
    tree_depth = jnp.ceil(jnp.log2(draws.num_steps.astype(theta.dtype) + 1.0))
    return _VehicleOutput(
        theta=theta,
        log_likelihood=per_draw(theta),
        diverging=draws.diverging,
        tree_depth=tree_depth,
        num_steps=draws.num_steps,
        accept_prob=draws.accept_prob,
        energy=draws.energy,
        lp=-draws.potential_energy,
        step_size=draws.step_size[:, -1],
    )


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    vehicle_chunk: int = 32,
    vehicle_batch: int = 1,
    max_extension: int | None = None,
    first_extension: int | None = None,
    **inputs: Unpack[NUTSInputs],
) -> EngineResult:
    """NUTS for every vehicle of ``arrays`` with the model's uniform prior box (module docstring),
    with the sampler's options :class:`NUTSOptions`.

    Posterior draws are (chain, draw, vehicle): ``num_particles`` draws in all, ``num_particles /
    num_chains`` (rounded up) per chain after ``num_warmup`` warm-up iterations. ``prior`` (default:
    the uniform box) needs ``logpdf(theta)`` and support inside the box. ``sample_stats`` holds per draw ``diverging``,
    ``tree_depth``, ``n_steps``, ``acceptance_rate``, ``energy`` and ``lp`` (the log density on the
    unconstrained scale), the adapted ``step_size`` per vehicle and chain, and ``extension``, the
    factor each vehicle's warm-up and draws were extended by (1: none; at most ``max_extension``,
    a power of two or the cap itself). ``max_extension`` defaults to :data:`MAX_EXTENSION` from
    :data:`~bayesdrive.inference.diagnostics.convergence.EXTENSION_MIN_DRAWS` draws on, else 1 (fewer
    draws cannot show ESS 400, so extending them would only cost time). ``first_extension`` is
    the factor of the first run (default :data:`FIRST_EXTENSION`, at most ``max_extension``, 1
    where ``max_extension`` is).
    """
    sampler, inputs = sampler_settings(inputs)
    problem = prepare("nuts", arrays, inputs, num_particles=2000, whole_series=True)
    num_particles = problem.num_particles
    config = sampler.with_draws(num_particles)
    num_chains, num_warmup, num_samples = config.num_chains, config.num_warmup, config.num_samples
    if num_chains < 1 or num_warmup < 1 or num_samples < 2:
        raise ValueError(
            "need num_chains >= 1, num_warmup >= 1 and at least 2 draws per chain, got "
            f"num_chains={num_chains}, num_warmup={num_warmup}, num_particles={num_particles}"
        )
    enough = num_chains * num_samples >= EXTENSION_MIN_DRAWS
    if max_extension is None:
        max_extension = MAX_EXTENSION if enough else 1
    if max_extension < 1:
        raise ValueError(f"max_extension must be at least 1, got {max_extension}")
    if first_extension is None:
        first_extension = min(FIRST_EXTENSION, max_extension) if enough else 1
    if not 1 <= first_extension <= max_extension:
        raise ValueError(
            f"first_extension must be in [1, max_extension={max_extension}], got {first_extension}"
        )
    if not 0.0 < config.target_accept_prob < 1.0:
        raise ValueError(f"target_accept_prob must be in (0, 1), got {config.target_accept_prob}")
    out, compile_time, run_time = _run_vehicles(
        problem,
        key,
        _scaled(config, first_extension),
        vehicle_chunk,
        vehicle_batch,
        problem.progress,
    )
    # Extension: vehicles that fail the convergence checks run again, from their own keys folded
    # with the factor, with factor x the warm-up and draws, thinned back to the stored count. A
    # vehicle's factors follow from its own draws alone, so its result does not depend on which
    # vehicles it is fitted with.
    factors = np.full(problem.num_vehicles, first_extension, dtype=np.int64)
    shortfalls = _shortfalls(problem, out.theta)
    while True:
        next_factors = {
            i: min(_next_factor(int(factors[i]), short), max_extension)
            for i, short in enumerate(shortfalls)
            if short is not None and factors[i] < max_extension
        }
        if not next_factors:
            break
        for factor in sorted(set(next_factors.values())):
            rows = np.asarray([i for i, f in next_factors.items() if f == factor])
            subset = problem._replace(
                series=jax.tree.map(lambda a, rows=rows: a[rows], problem.series),
                vehicle_ids=tuple(problem.vehicle_ids[i] for i in rows),
            )
            extended, extra_compile, extra_run = _run_vehicles(
                subset,
                jax.random.fold_in(key, factor),
                _scaled(config, factor),
                vehicle_chunk,
                vehicle_batch,
                None,
            )
            out = jax.tree.map(lambda a, b, rows=rows: _replace_rows(a, rows, b), out, extended)
            factors[rows] = factor
            compile_time, run_time = compile_time + extra_compile, run_time + extra_run
            for i, short in zip(rows, _shortfalls(subset, extended.theta), strict=True):
                shortfalls[i] = short

    def chain_draw_vehicle(values: np.ndarray) -> np.ndarray:
        return np.moveaxis(values, 0, -1)  # (vehicle, chain, draw) -> (chain, draw, vehicle)

    per_draw = ("chain", "draw", "vehicle")
    return EngineResult(
        posterior=posterior_draws(problem.names, out.theta),
        sample_stats={
            "diverging": (per_draw, chain_draw_vehicle(out.diverging)),
            "tree_depth": (per_draw, chain_draw_vehicle(out.tree_depth)),
            "n_steps": (per_draw, chain_draw_vehicle(out.num_steps)),
            "acceptance_rate": (per_draw, chain_draw_vehicle(out.accept_prob)),
            "energy": (per_draw, chain_draw_vehicle(out.energy)),
            "lp": (per_draw, chain_draw_vehicle(out.lp)),
            "step_size": (("vehicle", "chain"), out.step_size),
            "extension": (("vehicle",), factors),
        },
        log_likelihood=log_likelihood_draws(out.log_likelihood),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            **config._asdict(),
            "vehicle_chunk": vehicle_chunk,
            "vehicle_batch": vehicle_batch,
            "max_extension": max_extension,
        },
    )


def _scaled(config: NUTSConfig, factor: int) -> NUTSConfig:
    """``config`` with ``factor`` times the warm-up and draws, keeping every factor-th draw."""
    return config._replace(
        num_warmup=factor * config.num_warmup,
        num_samples=factor * config.num_samples,
        thin=factor,
    )


def _run_vehicles(
    problem: Any,
    key: Array,
    config: NUTSConfig,
    chunk: int,
    batch: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[_VehicleOutput, float, float]:
    """One NUTS run of ``config`` on every vehicle of ``problem``: outputs (vehicle, ...)."""
    out, compile_time, run_time = problem.run(
        _nuts_vehicle,
        key,
        settings=("nuts", config, static_key(problem.given_prior)),
        chunk=chunk,
        batch=batch,
        progress=progress,
        box=problem.box,
        prior=problem.given_prior,
        config=config,
    )
    return jax.tree.map(lambda a: a[0], out), compile_time, run_time  # the one replicate


def _shortfalls(problem: Any, theta: np.ndarray) -> list[float | None]:
    """Per vehicle of draws (vehicle, chain, draw, d): None if they pass every convergence check,
    else the worst shortfall, the largest ESS_MIN / ESS (at least 2 where R-hat fails)."""
    shortfalls: list[float | None] = []
    for i, vehicle in enumerate(problem.vehicle_ids):
        problems = chain_problems(vehicle, problem.names, theta[i])
        shortfalls.append(
            max(2.0 if p.check == "rhat" else p.limit / max(p.value, 1.0) for p in problems)
            if problems
            else None
        )
    return shortfalls


def _next_factor(factor: int, shortfall: float) -> int:
    """The next extension: the power of two that covers the ESS shortfall with a quarter to spare
    (ESS grows about with the draws until the stored draws are nearly independent), at least
    double the last."""
    wanted = factor * EXTENSION_MARGIN * shortfall
    return max(2 * factor, 2 ** math.ceil(math.log2(wanted)))


def _replace_rows(values: np.ndarray, rows: np.ndarray, new: np.ndarray) -> np.ndarray:
    values = np.array(values)
    values[rows] = new
    return values
