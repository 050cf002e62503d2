r"""``smc``, the default engine: exact sequential inference for static parameters.

Per vehicle: adaptive tempering on the whole series, closing moves, and, on request, a
sequential pass for per-step diagnostics. All exact up to Monte Carlo error.

**Tempering** (Del Moral, Doucet & Jasra 2006): prior draws, targets
:math:`p(\theta)\, p(y_{1:T} \mid \theta)^\lambda` with each next :math:`\lambda` found by bisection
so that the reweighting keeps an ESS of ``ess_threshold * N``, then resampling and
``temper_moves`` moves per stage, up to :math:`\lambda = 1`. Its log-evidence (``log_evidence``,
the product of the stages' mean incremental weights) is unbiased. Why tempering rather than the
particles of a pass along the data: on real NGSIM followers the posterior along the data can
switch modes. Vehicle 107 (``benchmarks/bench_agreement.py``) is unimodal near v_des 8 at
t = 100, bimodal at t = 150 and in the other mode (v_des 30, d_min 1.7, 22 nats higher) at the
end; after t = 100 a pass along the data held 0-5 of 4000 particles in the far mode in three of
four seeds, and no local move crosses back. Along :math:`\lambda` the final mode is favoured
from the start, so tempering finds it in every seed tried.

**Moves** are the sampler core's (:mod:`bayesdrive.inference.kernels`, shared with the
criticism's held-out continuation), on u = logit((theta - lower) / (upper - lower)) where the
prior has finite bounds (theta itself elsewhere), the target on u carrying the Jacobian, so
parameters piled against a prior bound move freely. By default a move is a random walk with the
cloud's covariance of u times :math:`s^2`, :math:`s` starting at :math:`2.38/\sqrt d` (Roberts,
Gelman & Gilks 1997) and adapted towards an acceptance rate of ``target_acceptance`` (log s moves
by acceptance - target after every move).

``independent=True`` pairs each random-walk move with an independent Metropolis-Hastings move
from a multivariate Student-t (``independent_df`` degrees of freedom) with the cloud's mean and
covariance of u, which forgets the start whenever it is accepted. With ``temper_moves=10,
final_moves=5, max_final_moves=1000, num_moves=3`` it agrees with the NUTS reference as the
random walk does (``benchmarks/bench_smc_moves.py``; fewer moves a stage left a tempering-path
bias that closing moves do not remove: on vehicle 140, 3 paired moves a stage put the v_des mean
at 17.7 against 14.6). The random walk stays the default: it was faster per move than the
likelihood once the likelihood got cheap (integer powers, the stop term only on series with a
stop), so the paired moves' fewer closing moves no longer pay (``reports/agreement/smc_moves.md``).

**Closing moves.** After the last stage, moves under the full posterior run in blocks of
``final_moves`` until every parameter's draws correlate with their values at the start of this
closing phase by at most ``decorrelation`` (or the noise level 3.5 / sqrt(N) of that correlation,
if larger; at most ``max_final_moves``): the correlation across particles is the kernel's
autocorrelation at that lag, measured on the target. A fixed count was not enough: on NGSIM
vehicle 140 80 random-walk moves left the tempering path's excess mass in the long v_des tail
(mean 15.5 against 14.6 from 400 000 NUTS draws), 240 removed it (14.64).

**Sequential pass** (``sequential=True``, off by default; it changes no draw): resample-move SMC
along the data, also known as IBIS (Chopin 2002, Biometrika 89:539), from its own prior draws.
At step t every particle is reweighted by the exact one-step density of the observed transition,
so the weighted set targets :math:`p(\theta \mid y_{1:t})`; when the ESS falls below
``ess_threshold * N`` it is resampled (systematic) and rejuvenated by ``num_moves`` moves that
score steps 1..t, in blocks of :data:`SCORE_BLOCK` steps. It gives the per-step diagnostics
(ESS, distinct particles, the learning curve) and ``sequential_log_evidence``; one far below
``log_evidence`` flags a mode switch like vehicle 107's.

**Replicates.** Draws of one SMC run are correlated through resampling in a way no
autocorrelation along the draw order measures. ``replicates`` independent runs (replicate r of a
vehicle runs on the vehicle's key with r folded in) fill the posterior's ``chain`` dimension, so the Monte Carlo standard error of a
posterior mean is the spread of the replicate means
(:func:`bayesdrive.inference.agreement.mcse_mean`); per-step diagnostics are replicate 0's.

Vehicles are independent, each with its own key derived from the seed and its id
(:mod:`bayesdrive.inference.vehicles`), so its draws are bit-identical whichever vehicles it is
fitted with, in whatever order or chunk. Vehicles run in compiled chunks; inside a chunk
``vehicle_batch`` of them are vectorised together: the tempering and closing loops then run until
the batch's slowest vehicle is done, and the sequential pass's rejuvenation under ``lax.cond``
becomes a select paid at every step (``benchmarks/bench_filters.py``), so on CPU cores one vehicle
at a time (the default) is fastest.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.kernels import (
    Box,
    Independent,
    WalkState,
    alternating,
    fixed_moves,
    independent_step,
    moves_until_decorrelated,
    next_temperature,
    to_free,
    walk_step,
)
from bayesdrive.inference.likelihood import StepInputs, particles_loglik, series_loglik
from bayesdrive.inference.output import EngineResult
from bayesdrive.inference.resampling import count_distinct_sorted, systematic
from bayesdrive.inference.vehicles import (
    log_likelihood_draws,
    posterior_draws,
    prepare,
    static_key,
)
from bayesdrive.inference.weights import (
    convergence_curve,
    effective_sample_size,
    log_mean_weight,
    weighted_mean_cov,
)

__all__ = ["SCORE_BLOCK", "SMCConfig", "run"]

# Steps per block when a move re-scores the series seen so far (the data's length bucket).
SCORE_BLOCK = 64
# Bisection steps of the temperature search (2^-40: far below any temperature increment used).
BISECTION_STEPS = 40


class SMCConfig(NamedTuple):
    """Settings of the resample-move sampler (see the module docstring)."""

    num_particles: int
    ess_threshold: float = 0.5
    num_moves: int = 5
    temper_moves: int = 20
    final_moves: int = 80
    max_final_moves: int = 2000
    decorrelation: float = 0.1
    target_acceptance: float = 0.234
    independent: bool = False
    independent_df: int = 5
    sequential: bool = False


def _score_lengths(num_steps: int) -> list[int]:
    """The lengths SCORE_BLOCK * 2^k, up to the first that covers ``num_steps``."""
    buckets = max(1, math.ceil(num_steps / SCORE_BLOCK)).bit_length()
    if 2 ** (buckets - 1) * SCORE_BLOCK < num_steps:
        buckets += 1
    return [SCORE_BLOCK * 2**k for k in range(buckets)]


def _lengths_taken(mask: np.ndarray) -> tuple[int, ...]:
    """The score lengths the vehicles of ``mask`` (vehicle, step) take, each the shortest that
    covers its last usable step. Only these become branches of the program: every branch is a
    copy of the likelihood, most of the program's size and compile time, and a fit of a few
    vehicles takes one or two of the lengths a long series allows."""
    lengths = np.asarray(_score_lengths(mask.shape[1]))
    last = np.max(np.where(mask > 0, np.arange(mask.shape[1]), 0), axis=1)
    return tuple(sorted({int(n) for n in lengths[np.searchsorted(lengths, last, side="right")]}))


class _Particles(NamedTuple):
    theta: Array  # (N, d)
    log_weight: Array  # (N,) unnormalised
    log_lik: Array  # (N,) log-likelihood of the steps seen so far
    log_prior: Array  # (N,)
    log_scale: Array  # () log of the random-walk scale s


class _SequentialPass(NamedTuple):
    log_evidence: Array  # ()
    ess: Array  # (T,) before any resampling at that step
    resampled: Array  # (T,)
    acceptance: Array  # (T,) mean MH acceptance of the moves, NaN where none ran
    unique: Array  # (T,) distinct ancestors surviving resampling, NaN where none happened
    mean: Array  # (T, d) weighted particle mean after reweighting
    convergence: Array  # (T,)


class _VehicleOutput(NamedTuple):
    theta: Array  # (N, d) equally weighted posterior draws, from the tempering stage
    log_evidence: Array  # () of the tempering stage
    temper_stages: Array  # ()
    temper_acceptance: Array  # () mean over the tempering stages
    final_acceptance: Array  # () of the closing moves
    final_moves: Array  # () closing moves run until the draws decorrelated
    final_correlation: Array  # () largest |corr| between closing draws and their start
    sequential: _SequentialPass | None  # only with ``config.sequential``


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
    score_lengths: tuple[int, ...],
) -> _VehicleOutput:
    """Tempering, closing moves and (with ``config.sequential``) the sequential pass for one
    vehicle's (T,) series."""
    n = config.num_particles
    num_steps = series.mask.shape[0]
    step_index = jnp.arange(num_steps)
    key_init, key_steps, key_final = jax.random.split(key, 3)
    theta = prior.sample(key_init, (n,))
    log_prior_of = jax.vmap(prior.logpdf)
    # Moves act on u = logit((theta - lower) / (upper - lower)) where the prior has finite bounds
    # (theta itself elsewhere): parameters piled against a bound move as freely as any other, and
    # a random walk never proposes outside the support. The target on u carries the Jacobian.
    box = Box(
        jnp.broadcast_to(getattr(prior, "lower", -jnp.inf), width.shape),
        jnp.broadcast_to(getattr(prior, "upper", jnp.inf), width.shape),
    )

    # A floor on the proposal covariance keeps moves alive when resampling leaves one survivor.
    jitter = jnp.diag(jnp.full(width.shape, 1e-6, width.dtype))

    # The sequential pass's moves score steps 0..t in blocks, so their cost grows with t instead
    # of the padded length. Tempering and closing moves score the whole series in one call on the
    # shortest of the lengths SCORE_BLOCK * 2^k that covers the vehicle's last usable step: a loop
    # over blocks ran several times slower on CPU, and a length chosen by the vehicle alone keeps
    # its draws independent of how far its chunk is padded. ``score_lengths`` are the lengths the
    # fit's vehicles take (:func:`_lengths_taken`). Under ``vmap`` (vehicle batches) a branch on
    # the length would run every branch, so there (no lengths) the padded series is scored whole.
    lengths = _score_lengths(num_steps)
    # Only the step axis is padded (merge scenes carry a trailing merge-slot axis).
    padded = jax.tree.map(
        lambda a: jnp.pad(a, [(0, lengths[-1] - num_steps)] + [(0, 0)] * (a.ndim - 1), mode="edge"),
        series,
    )
    padded = padded._replace(mask=jnp.pad(series.mask, (0, lengths[-1] - num_steps)))

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

    def log_lik_first(length: int, particles: Array) -> Array:
        first = jax.tree.map(lambda a: a[:length], padded)
        return jax.vmap(lambda th: series_loglik(model, names, fixed, th, first).sum())(particles)

    last_live = jnp.max(jnp.where(series.mask > 0, step_index, 0))
    if score_lengths:
        # The vehicle's own length is among them, so the first one past its last step is it.
        shortest = jnp.searchsorted(jnp.asarray(score_lengths), last_live, side="right")
        branches = [functools.partial(log_lik_first, length) for length in score_lengths]

        def log_lik_whole(particles: Array) -> Array:
            return jax.lax.switch(shortest, branches, particles)
    else:
        log_lik_whole = functools.partial(log_lik_first, num_steps)

    def walker(cloud: tuple[Array, Array], log_lik: Callable[[Array], Array], power=1.0):
        """The kernels' move targeting p(theta) exp(log_lik(theta))^power: a random walk with the
        cloud's covariance, paired with an independent move from a Student-t fitted to the cloud
        (``cloud``: its mean and the Cholesky factor of its covariance, free scale)."""

        def loglik(theta: Array) -> tuple[Array, Array]:
            return jnp.zeros(theta.shape[0], theta.dtype), log_lik(theta)

        target = dict(loglik=loglik, prior_logpdf=log_prior_of, power=power, box=box)
        mean, chol = cloud
        walk = functools.partial(
            walk_step, chol=chol, target_acceptance=config.target_acceptance, **target
        )
        if not config.independent:
            return walk
        proposal = Independent.of(mean, chol, config.independent_df)
        return alternating(functools.partial(independent_step, proposal=proposal, **target), walk)

    def as_walk(state: _Particles) -> WalkState:
        zero = jnp.zeros_like(state.log_lik)
        return WalkState(state.theta, state.log_prior, zero, state.log_lik, state.log_scale)

    def from_walk(walk: WalkState, log_weight: Array) -> _Particles:
        return _Particles(walk.theta, log_weight, walk.tempered, walk.log_prior, walk.log_scale)

    def moves(key: Array, state: _Particles, cloud, log_lik, count, power=1.0):
        """``count`` MH moves targeting p(theta) exp(log_lik(theta))^power; mean acceptance."""
        walk, rate = fixed_moves(key, as_walk(state), walker(cloud, log_lik, power), count)
        return from_walk(walk, state.log_weight), rate

    def fit_cloud(state: _Particles) -> tuple[Array, Array]:
        mean, cov = weighted_mean_cov(to_free(state.theta, box), state.log_weight)
        return mean, jnp.linalg.cholesky(cov + jitter)

    def resample_move(key: Array, state: _Particles, log_lik, num_moves: int, power: Array = 1.0):
        """Systematic resampling, then MH moves targeting p(theta) exp(log_lik(theta))^power."""
        key_resample, key_moves = jax.random.split(key)
        cloud = fit_cloud(state)
        parents = systematic(key_resample, state.log_weight)
        resampled = _Particles(
            state.theta[parents],
            jnp.zeros(n, state.theta.dtype),
            state.log_lik[parents],
            state.log_prior[parents],
            state.log_scale,
        )
        moved, rate = moves(key_moves, resampled, cloud, log_lik, num_moves, power)
        return moved, rate, count_distinct_sorted(parents).astype(state.theta.dtype)

    def decorrelate(key: Array, state: _Particles):
        """Moves under the full posterior until the draws decorrelate from their start (module
        docstring): on NGSIM vehicle 140 a fixed 80 moves left the tempering path's excess mass
        in the long v_des tail. Below about 3.5 / sqrt(N) the largest of d sample correlations
        is noise, not mixing."""
        walk, acceptance, done, corr = moves_until_decorrelated(
            key,
            as_walk(state),
            walker(fit_cloud(state), log_lik_whole),
            box=box,
            block=config.final_moves,
            max_moves=config.max_final_moves,
            threshold=jnp.maximum(config.decorrelation, 3.5 / jnp.sqrt(n)),
        )
        return from_walk(walk, state.log_weight), acceptance, done, corr

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
            lambda: resample_move(
                key, state, functools.partial(log_lik_up_to, last_step=t), config.num_moves
            ),
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
    sequential = None
    if config.sequential:
        (_, log_evidence), (ess, resampled, acceptance, unique, means) = jax.lax.scan(
            step,
            (start, jnp.zeros((), theta.dtype)),
            (series, step_index, jax.random.split(key_steps, num_steps)),
        )
        sequential = _SequentialPass(
            log_evidence=log_evidence,
            ess=ess,
            resampled=resampled,
            acceptance=acceptance,
            unique=unique,
            mean=means,
            convergence=convergence_curve(means, width),
        )

    def temper(carry):
        """One tempering stage: the next power by bisection, reweight, resample and move."""
        state, power, log_z, key, stages, accepted = carry
        key, key_move = jax.random.split(key)
        new_power = next_temperature(state.log_lik, power, config.ess_threshold, BISECTION_STEPS)
        increment = (new_power - power) * state.log_lik
        state, rate, _ = resample_move(
            key_move,
            state._replace(log_weight=increment),
            log_lik_whole,
            config.temper_moves,
            new_power,
        )
        return (
            state,
            new_power,
            log_z + log_mean_weight(increment),
            key,
            stages + 1,
            accepted + rate,
        )

    key_prior, key_temper, key_closing = jax.random.split(key_final, 3)
    theta = prior.sample(key_prior, (n,))
    zero = jnp.zeros((), theta.dtype)
    fresh = start._replace(theta=theta, log_lik=log_lik_whole(theta), log_prior=log_prior_of(theta))
    tempered, _, tempered_log_evidence, _, stages, accepted = jax.lax.while_loop(
        lambda carry: carry[1] < 1.0,
        temper,
        (fresh, zero, zero, key_temper, jnp.zeros((), jnp.int32), zero),
    )
    final, final_acceptance, final_moves, final_correlation = decorrelate(key_closing, tempered)
    return _VehicleOutput(
        theta=final.theta,
        log_evidence=tempered_log_evidence,
        temper_stages=stages,
        temper_acceptance=accepted / stages,
        final_acceptance=final_acceptance,
        final_moves=final_moves,
        final_correlation=final_correlation,
        sequential=sequential,
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
    temper_moves: int = 20,
    final_moves: int = 80,
    max_final_moves: int = 2000,
    decorrelation: float = 0.1,
    target_acceptance: float = 0.234,
    replicates: int = 1,
    vehicle_chunk: int = 32,
    vehicle_batch: int = 1,
    independent: bool = False,
    independent_df: int = 5,
    sequential: bool = False,
) -> EngineResult:
    """Tempering and closing moves (and, with ``sequential``, the per-step pass along the data)
    for every vehicle of ``arrays`` (module docstring).

    ``prior`` is any object with ``logpdf(theta)`` and ``sample(key, shape)`` over the inferred
    parameters (default: the model's uniform prior box); if it has ``lower`` and ``upper`` the
    moves work on their logit scale. ``replicates`` independent runs of ``num_particles`` each
    become the posterior's chains. The log-likelihood group scores every final particle.
    """
    if not 0.0 < ess_threshold <= 1.0:
        raise ValueError(f"ess_threshold must be in (0, 1], got {ess_threshold}")
    if not 0.0 < decorrelation < 1.0:
        raise ValueError(f"decorrelation must be in (0, 1), got {decorrelation}")
    if max_final_moves < final_moves:
        raise ValueError(
            f"max_final_moves ({max_final_moves}) must be at least final_moves ({final_moves})"
        )
    if independent_df < 1 or int(independent_df) != independent_df:
        raise ValueError(f"independent_df must be a whole number >= 1, got {independent_df}")
    if num_particles < 2 or min(num_moves, temper_moves, final_moves, replicates) < 1:
        raise ValueError(
            "need num_particles >= 2 and num_moves, temper_moves, final_moves, replicates >= 1, "
            f"got {num_particles}, {num_moves}, {temper_moves}, {final_moves}, {replicates}"
        )
    problem = prepare("smc", arrays, model=model, params=params, fixed=fixed, prior=prior)
    config = SMCConfig(
        num_particles=num_particles,
        ess_threshold=ess_threshold,
        num_moves=num_moves,
        temper_moves=temper_moves,
        final_moves=final_moves,
        max_final_moves=max_final_moves,
        decorrelation=decorrelation,
        target_acceptance=target_acceptance,
        independent=independent,
        independent_df=int(independent_df),
        sequential=sequential,
    )
    score_lengths = _lengths_taken(np.asarray(problem.series.mask)) if vehicle_batch <= 1 else ()
    per_vehicle = functools.partial(
        _smc_vehicle,
        model=model,
        names=problem.names,
        fixed=problem.fixed,
        prior=problem.prior,
        width=problem.box.upper - problem.box.lower,
        config=config,
        score_lengths=score_lengths,
    )
    out, compile_time, run_time = problem.run(
        per_vehicle,
        key,
        replicates=replicates,
        chunk=vehicle_chunk,
        batch=vehicle_batch,
        progress=progress,
        cache_key=problem.cache_key("smc", config, static_key(problem.prior), score_lengths),
    )
    theta = np.moveaxis(out.theta, 0, 1)  # (vehicle, replicate, particle, d)
    log_lik = problem.score(theta.reshape(problem.num_vehicles, -1, theta.shape[-1]))
    per_replicate = ("chain", "vehicle")
    sample_stats = {
        # The mean of unbiased evidence estimates is one, with the replicates' spread shown.
        "log_evidence": (
            ("vehicle",),
            jax.nn.logsumexp(out.log_evidence, axis=0) - np.log(replicates),
        ),
        "replicate_log_evidence": (per_replicate, out.log_evidence),
        "temper_stages": (per_replicate, out.temper_stages),
        "temper_acceptance": (per_replicate, out.temper_acceptance),
        "final_acceptance": (per_replicate, out.final_acceptance),
        "final_moves": (per_replicate, out.final_moves),
        "final_correlation": (per_replicate, out.final_correlation),
    }
    if sequential:
        first = jax.tree.map(lambda a: a[0], out.sequential)  # replicate 0's pass
        vehicle_step = ("vehicle", "step")
        sample_stats |= {
            "particle_ess": (vehicle_step, first.ess),
            "resampled": (vehicle_step, first.resampled),
            "acceptance": (vehicle_step, first.acceptance),
            "unique_particles": (vehicle_step, first.unique),
            "particle_mean": (("vehicle", "step", "param"), first.mean),
            "convergence": (vehicle_step, first.convergence),
            "sequential_log_evidence": (("vehicle",), first.log_evidence),
        }
    return EngineResult(
        posterior=posterior_draws(problem.names, theta),
        sample_stats=sample_stats,
        log_likelihood=log_likelihood_draws(log_lik.reshape(*theta.shape[:3], -1)),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            **config._asdict(),
            "replicates": replicates,
            "resampler": "systematic",
            "vehicle_chunk": vehicle_chunk,
            "vehicle_batch": vehicle_batch,
        },
    )
