r"""``smc``, the default engine: exact sequential inference for static parameters.

Resample-move SMC, also known as IBIS (Chopin 2002, Biometrika 89:539), run independently for each
vehicle. Particles start as prior draws. At step t every particle is reweighted by the exact
one-step density of the observed transition (the incremental likelihood), so the weighted set
targets :math:`p(\theta \mid y_{1:t})`. When the effective sample size falls below
``ess_threshold * N`` the set is resampled (systematic) and rejuvenated by ``num_moves``
random-walk Metropolis-Hastings moves that leave :math:`p(\theta \mid y_{1:t})` invariant: the
proposal is Gaussian with the particles' weighted covariance times :math:`s^2`, starting from
:math:`s = 2.38/\sqrt d` (Roberts, Gelman & Gilks 1997) and adapted per vehicle towards an
acceptance rate of ``target_acceptance`` (log s moves by acceptance - target after every move).
Each move scores the likelihood of steps 1..t, vectorised over steps within blocks of
:data:`SCORE_BLOCK` steps, so it costs about t steps, not the padded length. Because the
parameters are static, nothing here is approximate beyond Monte Carlo error: the log-evidence
:math:`\sum_t \log \sum_i W_{t-1}^i\, p(y_t \mid \theta^i)` is unbiased on the natural scale, and
at the end the set is resampled once more and moved ``num_moves`` times against the full
posterior, so the returned draws are equally weighted.

Vehicles are independent: one vehicle's whole filter is a ``lax.scan`` over steps with
rejuvenation under ``lax.cond``. Vehicles run in compiled chunks; inside a chunk ``vehicle_batch``
of them are vectorised together. With ``vehicle_batch = 1`` (the default) ``lax.cond`` stays a real
branch: under ``vmap`` it would turn into a select that pays for the O(N T) rejuvenation at every
step of every vehicle (``benchmarks/bench_filters.py`` measures both).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.likelihood import (
    StepInputs,
    check_model,
    fixed_params,
    map_vehicles,
    param_names,
    particles_loglik,
    score_draws,
    series_loglik,
    static_key,
    step_inputs,
)
from bayesdrive.inference.output import (
    EngineResult,
    particle_log_likelihood,
    particle_posterior,
    thinned_draws,
)
from bayesdrive.inference.resampling import count_distinct_sorted, systematic
from bayesdrive.inference.weights import (
    convergence_curve,
    effective_sample_size,
    weighted_mean_cov,
)

__all__ = ["SCORE_BLOCK", "SMCConfig", "run"]

# Steps per block when a move re-scores the series seen so far (the data's length bucket).
SCORE_BLOCK = 64


class SMCConfig(NamedTuple):
    """Settings of the resample-move sampler (see the module docstring)."""

    num_particles: int
    ess_threshold: float = 0.5
    num_moves: int = 5
    target_acceptance: float = 0.234


class _Particles(NamedTuple):
    theta: Array  # (N, d)
    log_weight: Array  # (N,) unnormalised
    log_lik: Array  # (N,) log-likelihood of the steps seen so far
    log_prior: Array  # (N,)
    log_scale: Array  # () log of the random-walk scale s


class _VehicleOutput(NamedTuple):
    theta: Array  # (N, d) equally weighted posterior draws
    log_evidence: Array  # ()
    ess: Array  # (T,) before any resampling at that step
    resampled: Array  # (T,)
    acceptance: Array  # (T,) mean MH acceptance of the moves, NaN where none ran
    unique: Array  # (T,) distinct ancestors surviving resampling, NaN where none happened
    mean: Array  # (T, d) weighted particle mean after reweighting
    convergence: Array  # (T,)
    final_acceptance: Array  # () of the closing moves


def _smc_vehicle(
    key: Array,
    series: StepInputs,
    *,
    model: DriverModel,
    names: tuple[str, ...],
    fixed: Any,
    prior: Any,
    width: Array,
    config: SMCConfig,
) -> _VehicleOutput:
    """The whole resample-move filter for one vehicle's (T,) series."""
    n = config.num_particles
    num_steps = series.mask.shape[0]
    step_index = jnp.arange(num_steps)
    key_init, key_steps, key_final = jax.random.split(key, 3)
    theta = prior.sample(key_init, (n,))
    log_prior_of = jax.vmap(prior.logpdf)
    # A floor on the proposal covariance keeps moves alive when resampling leaves one survivor.
    jitter = jnp.diag((1e-4 * width) ** 2)

    # Moves score steps 0..t in blocks, so their cost grows with t instead of the padded length.
    extra = -num_steps % SCORE_BLOCK
    # Only the step axis is padded (merge scenes carry a trailing merge-slot axis).
    padded = jax.tree.map(
        lambda a: jnp.pad(a, [(0, extra)] + [(0, 0)] * (a.ndim - 1), mode="edge"), series
    )
    padded = padded._replace(mask=jnp.pad(series.mask, (0, extra)))  # the extra steps are unused

    def log_lik_up_to(particles: Array, last_step: Array) -> Array:
        def add_block(block, total):
            start = block * SCORE_BLOCK
            part = jax.tree.map(
                lambda a: jax.lax.dynamic_slice_in_dim(a, start, SCORE_BLOCK), padded
            )
            seen = part._replace(mask=part.mask * (start + jnp.arange(SCORE_BLOCK) <= last_step))
            return total + jax.vmap(lambda th: series_loglik(model, names, fixed, th, seen).sum())(
                particles
            )

        zero = jnp.zeros(particles.shape[0], particles.dtype)
        return jax.lax.fori_loop(0, last_step // SCORE_BLOCK + 1, add_block, zero)

    def resample_move(key: Array, state: _Particles, last_step: Array):
        """Systematic resampling, then MH moves targeting p(theta | y_1..last_step)."""
        key_resample, key_moves = jax.random.split(key)
        _, cov = weighted_mean_cov(state.theta, state.log_weight)
        chol = jnp.linalg.cholesky(cov + jitter)
        parents = systematic(key_resample, state.log_weight)
        theta, log_lik, log_prior = (
            state.theta[parents],
            state.log_lik[parents],
            state.log_prior[parents],
        )
        unique = count_distinct_sorted(parents)

        def move(carry, key):
            theta, log_lik, log_prior, log_scale = carry
            key_step, key_accept = jax.random.split(key)
            noise = jax.random.normal(key_step, theta.shape, dtype=theta.dtype) @ chol.T
            proposal = theta + jnp.exp(log_scale) * noise
            prop_prior = log_prior_of(proposal)
            prop_lik = log_lik_up_to(proposal, last_step)
            log_ratio = prop_prior + prop_lik - log_prior - log_lik
            # Outside the prior support the likelihood may be NaN; the finite check rejects it.
            accept = jnp.isfinite(prop_prior) & (
                jnp.log(jax.random.uniform(key_accept, (n,))) < log_ratio
            )
            rate = jnp.mean(accept)
            carry = (
                jnp.where(accept[:, None], proposal, theta),
                jnp.where(accept, prop_lik, log_lik),
                jnp.where(accept, prop_prior, log_prior),
                log_scale + rate - config.target_acceptance,
            )
            return carry, rate

        (theta, log_lik, log_prior, log_scale), rates = jax.lax.scan(
            move,
            (theta, log_lik, log_prior, state.log_scale),
            jax.random.split(key_moves, config.num_moves),
        )
        moved = _Particles(theta, jnp.zeros(n, theta.dtype), log_lik, log_prior, log_scale)
        return moved, jnp.mean(rates), unique.astype(theta.dtype)

    def step(carry, xs):
        state, log_evidence = carry
        inputs, t, key = xs
        increment = particles_loglik(model, names, fixed, state.theta, inputs)
        log_weight = state.log_weight + increment
        # log sum_i W_i p(y_t | theta_i): exactly 0 on masked steps, where increment == 0.
        log_evidence += jax.nn.logsumexp(log_weight) - jax.nn.logsumexp(state.log_weight)
        state = state._replace(log_weight=log_weight, log_lik=state.log_lik + increment)
        ess = effective_sample_size(log_weight)
        mean, _ = weighted_mean_cov(state.theta, log_weight)
        rejuvenate = (inputs.mask > 0) & (ess < config.ess_threshold * n)
        nan = jnp.full((), jnp.nan, state.theta.dtype)
        state, acceptance, unique = jax.lax.cond(
            rejuvenate,
            lambda: resample_move(key, state, t),
            lambda: (state, nan, nan),
        )
        return (state, log_evidence), (ess, rejuvenate, acceptance, unique, mean)

    start = _Particles(
        theta=theta,
        log_weight=jnp.zeros(n, theta.dtype),
        log_lik=jnp.zeros(n, theta.dtype),
        log_prior=log_prior_of(theta),
        log_scale=jnp.log(2.38 / jnp.sqrt(theta.shape[-1])).astype(theta.dtype),
    )
    (state, log_evidence), (ess, resampled, acceptance, unique, means) = jax.lax.scan(
        step,
        (start, jnp.zeros((), theta.dtype)),
        (series, step_index, jax.random.split(key_steps, num_steps)),
    )
    last_live = jnp.max(jnp.where(series.mask > 0, step_index, 0))
    final, final_acceptance, _ = resample_move(key_final, state, last_live)
    return _VehicleOutput(
        theta=final.theta,
        log_evidence=log_evidence,
        ess=ess,
        resampled=resampled,
        acceptance=acceptance,
        unique=unique,
        mean=means,
        convergence=convergence_curve(means, width),
        final_acceptance=final_acceptance,
    )


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    model: DriverModel,
    params: Sequence[str] | None = None,
    fixed: Mapping[str, float] | None = None,
    num_particles: int = 1000,
    prior: Any = None,
    progress: Callable[[int, int], None] | None = None,
    ess_threshold: float = 0.5,
    num_moves: int = 5,
    target_acceptance: float = 0.234,
    log_likelihood_draws: int = 200,
    vehicle_chunk: int = 32,
    vehicle_batch: int = 1,
) -> EngineResult:
    """Resample-move SMC for every vehicle of ``arrays`` (module docstring).

    ``prior`` is any object with ``logpdf(theta)`` and ``sample(key, shape)`` over the inferred
    parameters (default: the model's uniform prior box). The log-likelihood group scores
    ``min(log_likelihood_draws, num_particles)`` evenly spaced draws of the equally weighted
    final particles (a thinned but still exact posterior sample).
    """
    check_model(model)
    names = param_names(model, params)
    if not 0.0 < ess_threshold <= 1.0:
        raise ValueError(f"ess_threshold must be in (0, 1], got {ess_threshold}")
    if num_particles < 2 or num_moves < 1:
        raise ValueError(
            f"need num_particles >= 2 and num_moves >= 1, got {num_particles}, {num_moves}"
        )
    box = model.prior(names)
    prior = box if prior is None else prior
    fixed_values = fixed_params(model, fixed)
    config = SMCConfig(
        num_particles=num_particles,
        ess_threshold=ess_threshold,
        num_moves=num_moves,
        target_acceptance=target_acceptance,
    )
    per_vehicle = functools.partial(
        _smc_vehicle,
        model=model,
        names=names,
        fixed=fixed_values,
        prior=prior,
        width=box.upper - box.lower,
        config=config,
    )
    prior_key = static_key(prior)
    cache_key = (
        None
        if prior_key is None
        else ("smc", model, names, config, prior_key, static_key(fixed_values))
    )
    series = step_inputs(arrays)
    keys = jax.random.split(key, series.mask.shape[0])
    out, compile_time, run_time = map_vehicles(
        per_vehicle,
        (keys, series),
        chunk=vehicle_chunk,
        batch=vehicle_batch,
        progress=progress,
        cache_key=cache_key,
    )
    scored = thinned_draws(num_particles, log_likelihood_draws)
    log_lik = score_draws(model, names, fixed_values, out.theta[:, scored], series)
    vehicle_step = ("vehicle", "step")
    return EngineResult(
        posterior=particle_posterior(names, out.theta),
        sample_stats={
            "ess": (vehicle_step, out.ess),
            "resampled": (vehicle_step, out.resampled),
            "acceptance": (vehicle_step, out.acceptance),
            "unique_particles": (vehicle_step, out.unique),
            "particle_mean": (("vehicle", "step", "param"), out.mean),
            "convergence": (vehicle_step, out.convergence),
            "log_evidence": (("vehicle",), out.log_evidence),
            "final_acceptance": (("vehicle",), out.final_acceptance),
        },
        log_likelihood=particle_log_likelihood(log_lik),
        log_likelihood_draws=scored,
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            **config._asdict(),
            "resampler": "systematic",
            "log_likelihood_draws": len(scored),
            "vehicle_chunk": vehicle_chunk,
            "vehicle_batch": vehicle_batch,
        },
    )
