r"""``smc``, the default engine: exact sequential inference for static parameters.

Per vehicle: adaptive tempering on the whole series, closing moves, and, on request, a
sequential pass for per-step diagnostics. All exact up to Monte Carlo error.

**Tempering** (Del Moral, Doucet & Jasra 2006), the SMC core's adaptive tempering
(:mod:`bayesdrive.inference.core.smc`, shared with the criticism's held-out continuation): prior
draws, targets :math:`p(\theta)\, p(y_{1:T} \mid \theta)^\lambda` with each next :math:`\lambda`
found by bisection so that the reweighting keeps an ESS of ``ess_threshold * N``, then resampling
and ``temper_moves`` moves per stage (with ``unmoved_tolerance`` > 0, more until every particle
has likely moved), up to :math:`\lambda = 1`. Its log-evidence (``log_evidence``, the product of
the stages' mean incremental weights) is unbiased. Why tempering rather than the
particles of a pass along the data: on real NGSIM followers the posterior along the data can
switch modes. Vehicle 107 (``benchmarks/bench_agreement.py``) is unimodal near v_des 8 at
t = 100, bimodal at t = 150 and in the other mode (v_des 30, d_min 1.7, 22 nats higher) at the
end; after t = 100 a pass along the data held 0-5 of 4000 particles in the far mode in three of
four seeds, and no local move crosses back. Along :math:`\lambda` the final mode is favoured
from the start, so tempering finds it in every seed tried.

**Moves** are the sampler core's (:mod:`bayesdrive.inference.core.kernels`), on
u = logit((theta - lower) / (upper - lower)) where the prior has finite bounds (theta itself
elsewhere), the target on u carrying the Jacobian, so parameters piled against a prior bound move
freely. By default a move is a random walk with the covariance of u of the reweighted cloud
(before resampling) times :math:`s^2`, :math:`s` starting at :math:`2.38/\sqrt d` (Roberts,
Gelman & Gilks 1997) and adapted towards an acceptance rate of ``target_acceptance`` (log s moves
by acceptance - target after every move).

A paired move is a random-walk move followed by an independent Metropolis-Hastings move from a
multivariate Student-t (``independent_df`` degrees of freedom) with the cloud's mean and
covariance of u, which forgets the start whenever it is accepted. The closing moves are paired
(``paired_closing=False``: the random walk alone, the earlier default); ``independent=True`` pairs the tempering stages' moves too, which left a tempering-path
bias at 10 moves a stage (``reports/agreement/smc_moves.md``), so the stages' random walk stays
the default.

**Closing moves.** After the last stage, paired moves under the full posterior run in blocks of
``final_moves`` until every parameter's draws correlate with their values at the start of this
closing phase by at most ``decorrelation`` (or the noise level 3.5 / sqrt(N) of that correlation,
if larger; at most ``max_final_moves``): the correlation across particles is the kernel's
autocorrelation at that lag, measured on the target. A fixed count was not enough: on a long
posterior tail the tempering path's excess mass outlived a fixed number of closing moves
(``reports/agreement/reference.md`` holds the long NUTS references this was judged against).
Paired rather than random-walk closing moves: where the posterior is close to a Student-t on u
the independent move decorrelates the draws in a few moves, where a random walk needs hundreds,
and small blocks stop soon after. The cap is low: where a posterior far from that shape keeps the
draws correlated for hundreds of paired moves, more of them cost most of the fit's time and did
not change its agreement with the NUTS reference (``reports/smc_levers.md``).

**Sequential pass** (``sequential=True``, off by default; it changes no draw): resample-move SMC
along the data, also known as IBIS (Chopin 2002, Biometrika 89:539), from its own prior draws.
At step t the SMC core's step (:func:`~bayesdrive.inference.core.smc.step`) reweights every
particle by the exact one-step density of the observed transition, so the weighted set targets
:math:`p(\theta \mid y_{1:t})`; when the ESS falls below ``ess_threshold * N`` it is resampled
(systematic) and rejuvenated by ``num_moves`` moves that score steps 1..t, in blocks of
:data:`SCORE_BLOCK` steps. It gives the per-step diagnostics (ESS, distinct particles, the learning
curve) and ``sequential_log_evidence``; one far below ``log_evidence`` flags a mode switch like
vehicle 107's.

**Replicates.** Draws of one SMC run are correlated through resampling in a way no
autocorrelation along the draw order measures. ``replicates`` independent runs (replicate r of a
vehicle runs on the vehicle's key with r folded in) fill the posterior's ``chain`` dimension, so the Monte Carlo standard error of a
posterior mean is the spread of the replicate means
(:func:`bayesdrive.inference.diagnostics.agreement.mcse_mean`); per-step diagnostics are replicate 0's.

Vehicles are independent, each with its own key derived from the seed and its id
(:mod:`bayesdrive.inference.core.vehicles`), so its draws are bit-identical whichever vehicles it is
fitted with, in whatever order or chunk. Vehicles run in compiled chunks; inside a chunk
``vehicle_batch`` of them are vectorised together: the tempering and closing loops then run until
the batch's slowest vehicle is done, and the sequential pass's rejuvenation under ``lax.cond``
becomes a select paid at every step (``benchmarks/bench_filters.py``), so on CPU cores one vehicle
at a time (the default) is fastest.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple, Unpack

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.core.kernels import (
    Box,
    Target,
    WalkState,
    decorrelation_threshold,
    moves_until_decorrelated,
)
from bayesdrive.inference.core.likelihood import StepInputs, particles_loglik, series_loglik
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.resampling import count_distinct_sorted
from bayesdrive.inference.core.smc import (
    SMCState,
    TemperingConfig,
    adaptive_tempering,
    check_finished,
    cloud_move,
    fit_cloud,
    stage_moves,
)
from bayesdrive.inference.core.smc import step as smc_step
from bayesdrive.inference.core.vehicles import (
    log_likelihood_draws,
    posterior_draws,
    prepare,
    static_key,
)
from bayesdrive.inference.core.weights import convergence_curve, weighted_mean_cov

__all__ = ["SCORE_BLOCK", "SMCConfig", "run"]

# Steps per block when a move re-scores the series seen so far (the data's length bucket).
SCORE_BLOCK = 64


class SMCConfig(NamedTuple):
    """Settings of the engine (module docstring): the tempering's (the core's one settings
    type), then the sequential pass's moves per rejuvenation and the closing moves'."""

    tempering: TemperingConfig
    num_moves: int = 5
    final_moves: int = 5
    max_final_moves: int = 250
    decorrelation: float = 0.1
    paired_closing: bool = True
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
    temper_acceptance: Array  # () mean over the tempering moves
    final_temperature: Array  # () 1 unless tempering stopped at max_stages
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
    tempering = config.tempering
    n = tempering.num_particles
    num_steps = series.mask.shape[0]
    step_index = jnp.arange(num_steps)
    key_init, key_steps, key_final = jax.random.split(key, 3)
    log_prior_of = jax.vmap(prior.logpdf)
    # Moves act on u = logit((theta - lower) / (upper - lower)) where the prior has finite bounds
    # (theta itself elsewhere): parameters piled against a bound move as freely as any other, and
    # a random walk never proposes outside the support. The target on u carries the Jacobian.
    box = Box(
        jnp.broadcast_to(getattr(prior, "lower", -jnp.inf), width.shape),
        jnp.broadcast_to(getattr(prior, "upper", jnp.inf), width.shape),
    )

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

    def tempered(log_lik: Callable[[Array], Array]) -> Callable[[Array], tuple[Array, Array]]:
        """The core's (anchor, tempered) split of a target: nothing anchored."""

        def loglik(theta: Array) -> tuple[Array, Array]:
            return jnp.zeros(theta.shape[0], theta.dtype), log_lik(theta)

        return loglik

    def prior_cloud(key: Array, log_lik: Callable[[Array], Array]) -> WalkState:
        theta = prior.sample(key, (n,))
        zero = jnp.zeros(n, theta.dtype)
        log_scale = jnp.log(2.38 / jnp.sqrt(theta.shape[-1])).astype(theta.dtype)
        return WalkState(theta, log_prior_of(theta), zero, log_lik(theta), log_scale)

    def sequential_step(carry, xs):
        """Reweight by step t's density; below the ESS threshold resample and move with the
        proposal fitted to the reweighted cloud, the moves scoring steps 0..t."""
        state, log_evidence = carry
        inputs, t, key = xs
        increment = particles_loglik(model, names, fixed, state.particles.theta, inputs)
        # The cloud's cached log-likelihood covers step t before the moves score it.
        seen = state.particles._replace(tempered=state.particles.tempered + increment)
        log_weights = state.log_weights + increment
        mean, _ = weighted_mean_cov(seen.theta, log_weights)
        so_far = Target(tempered(functools.partial(log_lik_up_to, last_step=t)), log_prior_of, box)
        move = cloud_move(
            fit_cloud(seen.theta, log_weights, box), target=so_far, power=1.0, config=tempering
        )
        kernel = stage_moves(
            move, num_moves=config.num_moves, unmoved_tolerance=0.0, max_moves=config.num_moves
        )
        state, info = smc_step(
            key,
            SMCState(seen, state.log_weights),
            lambda _: increment,
            kernel,
            resample_below=tempering.ess_threshold,
        )
        nan = jnp.full((), jnp.nan, mean.dtype)
        acceptance = jnp.where(
            info.resampled, info.move.acceptance_sum / jnp.maximum(info.move.count, 1.0), nan
        )
        unique = jnp.where(
            info.resampled, count_distinct_sorted(info.ancestors).astype(mean.dtype), nan
        )
        # log sum_i W_i p(y_t | theta_i): exactly 0 on masked steps, where increment == 0.
        log_evidence += info.log_increment
        # Named as the fields of :class:`_SequentialPass` they fill.
        per_step = {
            "ess": info.ess,
            "resampled": info.resampled,
            "acceptance": acceptance,
            "unique": unique,
            "mean": mean,
        }
        return (state, log_evidence), per_step

    sequential = None
    if config.sequential:
        start = prior_cloud(key_init, lambda theta: jnp.zeros(n, theta.dtype))
        (_, log_evidence), per_step = jax.lax.scan(
            sequential_step,
            (SMCState(start, jnp.zeros(n, start.theta.dtype)), jnp.zeros((), start.theta.dtype)),
            (series, step_index, jax.random.split(key_steps, num_steps)),
        )
        convergence = convergence_curve(per_step["mean"], width)
        sequential = _SequentialPass(log_evidence=log_evidence, convergence=convergence, **per_step)

    key_prior, key_temper, key_closing = jax.random.split(key_final, 3)
    posterior = Target(tempered(log_lik_whole), log_prior_of, box)
    run = adaptive_tempering(
        key_temper, prior_cloud(key_prior, log_lik_whole), target=posterior, config=tempering
    )
    # Paired closing moves under the full posterior until the draws decorrelate from their start
    # (module docstring): on NGSIM vehicle 140 a fixed 80 moves left the tempering path's excess
    # mass in the long v_des tail.
    closing = cloud_move(
        fit_cloud(run.particles.theta, run.log_weights, box),
        target=posterior,
        power=1.0,
        config=tempering._replace(independent=tempering.independent or config.paired_closing),
    )
    final, final_acceptance, final_moves, final_correlation = moves_until_decorrelated(
        key_closing,
        run.particles,
        closing,
        box=box,
        block=config.final_moves,
        max_moves=config.max_final_moves,
        threshold=decorrelation_threshold(config.decorrelation, n),
    )
    return _VehicleOutput(
        theta=final.theta,
        log_evidence=run.log_evidence,
        temper_stages=run.stages,
        temper_acceptance=run.acceptance_sum / run.moves,
        final_temperature=run.temperature,
        final_acceptance=final_acceptance,
        final_moves=final_moves,
        final_correlation=final_correlation,
        sequential=sequential,
    )


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    ess_threshold: float = 0.5,
    num_moves: int = 5,
    temper_moves: int = 20,
    unmoved_tolerance: float = 0.0,
    max_moves: int = 64,
    max_stages: int = 200,
    final_moves: int = 5,
    max_final_moves: int = 250,
    decorrelation: float = 0.1,
    paired_closing: bool = True,
    target_acceptance: float = 0.234,
    replicates: int = 1,
    vehicle_chunk: int = 32,
    vehicle_batch: int = 1,
    independent: bool = False,
    independent_df: int = 5,
    sequential: bool = False,
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """Tempering and closing moves (and, with ``sequential``, the per-step pass along the data)
    for every vehicle of ``arrays`` (module docstring).

    ``prior`` is any object with ``logpdf(theta)`` and ``sample(key, shape)`` over the inferred
    parameters (default: the model's uniform prior box); if it has ``lower`` and ``upper`` the
    moves work on their logit scale. ``replicates`` independent runs of ``num_particles`` each
    become the posterior's chains. The log-likelihood group scores every final particle.
    A tempering stage runs ``temper_moves`` moves, and with ``unmoved_tolerance`` > 0 more, up to
    ``max_moves``, until every particle has likely moved (:mod:`~bayesdrive.inference.core.smc`);
    a vehicle whose tempering has not reached the posterior after ``max_stages`` stages is an
    error.
    """
    # Tempering scores whole series, so a model with a state filter fits; the sequential pass
    # scores one step at a time from lifted states, which such a model does not have.
    problem = prepare("smc", arrays, inputs, num_particles=1000, whole_series=not sequential)
    num_particles = problem.num_particles
    if not 0.0 < ess_threshold <= 1.0:
        raise ValueError(f"ess_threshold must be in (0, 1], got {ess_threshold}")
    if not 0.0 < decorrelation < 1.0:
        raise ValueError(f"decorrelation must be in (0, 1), got {decorrelation}")
    if max_final_moves < final_moves:
        raise ValueError(
            f"max_final_moves ({max_final_moves}) must be at least final_moves ({final_moves})"
        )
    if not 0.0 <= unmoved_tolerance < 1.0 or max_moves < temper_moves or max_stages < 1:
        raise ValueError(
            "need 0 <= unmoved_tolerance < 1, max_moves >= temper_moves and max_stages >= 1, got "
            f"{unmoved_tolerance}, {max_moves} (temper_moves {temper_moves}), {max_stages}"
        )
    if independent_df < 1 or int(independent_df) != independent_df:
        raise ValueError(f"independent_df must be a whole number >= 1, got {independent_df}")
    if num_particles < 2 or min(num_moves, temper_moves, final_moves, replicates) < 1:
        raise ValueError(
            "need num_particles >= 2 and num_moves, temper_moves, final_moves, replicates >= 1, "
            f"got {num_particles}, {num_moves}, {temper_moves}, {final_moves}, {replicates}"
        )
    config = SMCConfig(
        tempering=TemperingConfig(
            num_particles=num_particles,
            num_moves=temper_moves,
            ess_threshold=ess_threshold,
            unmoved_tolerance=unmoved_tolerance,
            max_moves=max_moves,
            max_stages=max_stages,
            target_acceptance=target_acceptance,
            independent=independent,
            independent_df=int(independent_df),
        ),
        num_moves=num_moves,
        final_moves=final_moves,
        max_final_moves=max_final_moves,
        decorrelation=decorrelation,
        paired_closing=paired_closing,
        sequential=sequential,
    )
    score_lengths = _lengths_taken(np.asarray(problem.series.mask)) if vehicle_batch <= 1 else ()
    out, compile_time, run_time = problem.run(
        _smc_vehicle,
        key,
        settings=("smc", config, static_key(problem.prior), score_lengths),
        replicates=replicates,
        chunk=vehicle_chunk,
        batch=vehicle_batch,
        progress=problem.progress,
        prior=problem.prior,
        width=problem.box.upper - problem.box.lower,
        config=config,
        score_lengths=score_lengths,
    )
    check_finished(out.final_temperature, problem.vehicle_ids, "smc", max_stages)
    # The options under their engine names: a stage's moves are smc's temper_moves.
    engine_options = config._asdict()
    stage_options = engine_options.pop("tempering")._asdict()
    stage_options["temper_moves"] = stage_options.pop("num_moves")
    theta = np.moveaxis(out.theta, 0, 1)  # (vehicle, replicate, particle, d)
    log_lik = problem.pointwise_scores(theta.reshape(problem.num_vehicles, -1, theta.shape[-1]))
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
        log_likelihood=log_likelihood_draws(
            None if log_lik is None else log_lik.reshape(*theta.shape[:3], -1)
        ),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            **stage_options,
            **engine_options,
            "replicates": replicates,
            "resampler": "systematic",
            "vehicle_chunk": vehicle_chunk,
            "vehicle_batch": vehicle_batch,
        },
    )
