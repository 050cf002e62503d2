r"""The SMC core: one generic step on a particle state, and adaptive tempering as a layer over it.

Every sequential Monte Carlo sampler of the package is assembled here (BlackJAX's
``smc.base.step`` and ``adaptive_tempered`` are the shape; Del Moral, Doucet & Jasra 2006):

* :func:`step`, ``step(key, state, potential, move) -> (state, info)``: reweight the particles by
  an incremental log potential, resample them (systematic) when the effective sample size falls
  below ``resample_below * N``, and move the resampled particles by a Markov kernel. The kernel
  comes in built: whatever it adapts to the particles (the proposal's covariance) is computed
  by the caller, outside the step. The info carries the log of the weighted mean incremental
  weight (the evidence increment), the ESS before resampling, the ancestors and the move's info.
* :func:`tempering_step` and :func:`adaptive_tempering`: the targets
  :math:`p(\theta)\, e^{\ell_a(\theta)} e^{\lambda \ell_t(\theta)}` from :math:`\lambda = 0` to
  1, each next :math:`\lambda` the largest whose reweighting keeps an ESS of
  ``ess_threshold * N`` (:func:`~bayesdrive.inference.core.kernels.next_temperature`, bisection,
  Jasra et al. 2011), the particles resampled at every stage and moved by :func:`stage_moves`
  of :func:`cloud_move` until every particle has likely moved. The product of the stages' mean
  incremental weights estimates the normalising constant, unbiased.

One rule each, shared by every sampler: the proposal is fitted to the particles by
:func:`fit_cloud` (their weighted mean and covariance on the free scale, after reweighting and
before resampling, so every particle counts); a stage moves until the estimated probability
that a particle has not moved is at most ``unmoved_tolerance`` (Drovandi & Pettitt 2011;
exactly ``num_moves`` with 0); tempering stops at :math:`\lambda = 1` or after ``max_stages``;
:class:`TemperingConfig` holds the settings. The kernels themselves (the random walk on the logit
scale of the prior box, the independent Student-t move, the stopping rules of a run of moves)
are :mod:`bayesdrive.inference.core.kernels`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.inference.core.kernels import (
    Box,
    Independent,
    Move,
    Target,
    WalkState,
    moves_until_moved,
    next_temperature,
    paired_step,
    to_free,
    walk_step,
)
from bayesdrive.inference.core.resampling import systematic
from bayesdrive.inference.core.weights import effective_sample_size, normalize, weighted_mean_cov

__all__ = [
    "BISECTION_STEPS",
    "Cloud",
    "SMCInfo",
    "SMCState",
    "StageMoves",
    "TemperingConfig",
    "TemperingState",
    "adaptive_tempering",
    "check_finished",
    "cloud_move",
    "fit_cloud",
    "stage_moves",
    "step",
    "tempering_step",
]

# Bisection steps of the temperature search (2^-40: far below any temperature increment used).
BISECTION_STEPS = 40
# A floor on the proposal covariance keeps moves alive when resampling leaves one survivor.
JITTER = 1e-6


class SMCState(NamedTuple):
    """A weighted particle cloud: ``particles`` a pytree whose leaves carry a leading particle
    axis (N, ...) (0-d leaves, such as a proposal scale, are shared by the cloud and pass
    resampling unchanged) and their unnormalised ``log_weights`` (N,)."""

    particles: Any
    log_weights: Array


class SMCInfo(NamedTuple):
    """What one :func:`step` did.

    log_increment: () log of the weighted mean incremental weight, the evidence increment.
    ess: () effective sample size after reweighting, before any resampling.
    resampled: () whether the particles were resampled and moved.
    ancestors: (N,) each particle's parent (itself where not resampled).
    move: the move's info; zeros where it did not run.
    """

    log_increment: Array
    ess: Array
    resampled: Array
    ancestors: Array
    move: Any


def step(
    key: Array,
    state: SMCState,
    potential: Callable[[Any], Array],
    move: Callable[[Array, Any], tuple[Any, Any]],
    *,
    resample_below: float,
    resample: Callable[[Array, Array], Array] = systematic,
) -> tuple[SMCState, SMCInfo]:
    """Reweight by ``potential(particles)`` (N,) incremental log weights, then, when the ESS is
    below ``resample_below * N`` (``inf``: always), resample and ``move(key, particles) ->
    (particles, info)``; otherwise keep the reweighted cloud, its log weights normalised (module
    docstring)."""
    key_resample, key_move = jax.random.split(key)
    log_weights = state.log_weights + potential(state.particles)
    num = log_weights.shape[0]
    ess = effective_sample_size(log_weights)
    log_increment = jax.nn.logsumexp(log_weights) - jax.nn.logsumexp(state.log_weights)

    def resample_and_move():
        ancestors = resample(key_resample, log_weights)
        chosen = jax.tree.map(lambda a: a[ancestors] if a.ndim else a, state.particles)
        moved, info = move(key_move, chosen)
        return SMCState(moved, jnp.zeros_like(log_weights)), ancestors, info

    def keep():
        unmoved = jax.eval_shape(move, key_move, state.particles)[1]
        info = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), unmoved)
        # Normalised, so that weights kept over many steps stay near 0 in float32.
        kept = SMCState(state.particles, normalize(log_weights))
        return kept, jnp.arange(num, dtype=jnp.int32), info

    if resample_below == float("inf"):
        # Always: no branch in the program (under vmap a branch would run both sides).
        new_state, ancestors, info = resample_and_move()
        return new_state, SMCInfo(log_increment, ess, jnp.asarray(True), ancestors, info)
    resampled = ess < resample_below * num
    new_state, ancestors, info = jax.lax.cond(resampled, resample_and_move, keep)
    return new_state, SMCInfo(log_increment, ess, resampled, ancestors, info)


class TemperingConfig(NamedTuple):
    """Settings of adaptive tempering and its moves (module docstring).

    ess_threshold: the fraction of particles whose ESS each temperature keeps (a sampler that
        resamples on the ESS, such as smc's pass along the data, uses it as its trigger too).
    num_moves: moves per stage at least; then until prod(1 - acceptance) <= ``unmoved_tolerance``
        (0: exactly ``num_moves``), at most ``max_moves``.
    max_stages: tempering stops here even below temperature 1 (the caller reports it).
    target_acceptance: the random walk's scale adapts towards this acceptance rate.
    independent: pair every random-walk move with an independent Student-t move of
        ``independent_df`` degrees of freedom fitted to the cloud.
    """

    num_particles: int
    num_moves: int
    ess_threshold: float = 0.5
    unmoved_tolerance: float = 0.01
    max_moves: int = 64
    max_stages: int = 200
    target_acceptance: float = 0.234
    independent: bool = False
    independent_df: int = 5


class Cloud(NamedTuple):
    """The proposal's fit to a particle cloud on the free scale: mean (d,) and the Cholesky
    factor of the covariance (d, d)."""

    mean: Array
    chol: Array


def fit_cloud(theta: Array, log_weights: Array, box: Box) -> Cloud:
    """The weighted mean and covariance of ``theta`` (N, d) on the free scale, the one
    covariance rule of every move (module docstring), floored by :data:`JITTER`."""
    mean, cov = weighted_mean_cov(to_free(theta, box), log_weights)
    jitter = jnp.diag(jnp.full(mean.shape, JITTER, mean.dtype))
    return Cloud(mean, jnp.linalg.cholesky(cov + jitter))


def cloud_move(cloud: Cloud, *, target: Target, power: Array, config: TemperingConfig) -> Move:
    """One move invariant for ``target`` at ``power``: a random walk with the cloud's covariance,
    paired (``config.independent``) with an independent move from a Student-t with the cloud's
    mean and covariance."""
    if not config.independent:
        return functools.partial(
            walk_step,
            target=target,
            power=power,
            chol=cloud.chol,
            target_acceptance=config.target_acceptance,
        )
    return functools.partial(
        paired_step,
        target=target,
        power=power,
        proposal=Independent.of(cloud.mean, cloud.chol, config.independent_df),
        target_acceptance=config.target_acceptance,
    )


class StageMoves(NamedTuple):
    """count: moves run (); acceptance_sum: their acceptance rates summed ()."""

    count: Array
    acceptance_sum: Array


def stage_moves(
    move: Move, *, num_moves: int, unmoved_tolerance: float, max_moves: int
) -> Callable[[Array, WalkState], tuple[WalkState, StageMoves]]:
    """``move`` repeated by the one stop rule (module docstring), as a kernel for :func:`step`."""

    def run(key: Array, walk: WalkState) -> tuple[WalkState, StageMoves]:
        walk, count, acceptance_sum = moves_until_moved(
            key,
            walk,
            move,
            num_moves=num_moves,
            unmoved_tolerance=unmoved_tolerance,
            max_moves=max_moves if unmoved_tolerance > 0 else num_moves,
        )
        return walk, StageMoves(count, acceptance_sum)

    return run


class TemperingState(NamedTuple):
    """The tempering layer's state: the cloud (:class:`~bayesdrive.inference.core.kernels.WalkState`,
    ``tempered`` the log-likelihood being tempered in), its log weights (N,), the temperature (),
    the log normalising constant so far (), and counts: stages (), moves () and the sum of their
    acceptance rates ()."""

    particles: WalkState
    log_weights: Array
    temperature: Array
    log_evidence: Array
    stages: Array
    moves: Array
    acceptance_sum: Array


def tempering_step(
    key: Array,
    state: TemperingState,
    *,
    target: Target,
    config: TemperingConfig,
) -> tuple[TemperingState, SMCInfo]:
    """One stage: the next temperature by bisection, the proposal fitted to the reweighted cloud,
    then :func:`step` (resampling at every stage) with the stage's moves at that temperature."""
    particles = state.particles
    temperature = next_temperature(
        particles.tempered, state.temperature, config.ess_threshold, BISECTION_STEPS
    )

    def potential(walk: WalkState) -> Array:
        return (temperature - state.temperature) * walk.tempered

    cloud = fit_cloud(particles.theta, state.log_weights + potential(particles), target.box)
    move = cloud_move(cloud, target=target, power=temperature, config=config)
    kernel = stage_moves(
        move,
        num_moves=config.num_moves,
        unmoved_tolerance=config.unmoved_tolerance,
        max_moves=config.max_moves,
    )
    smc, info = step(
        key,
        SMCState(particles, state.log_weights),
        potential,
        kernel,
        resample_below=float("inf"),
    )
    return TemperingState(
        particles=smc.particles,
        log_weights=smc.log_weights,
        temperature=temperature,
        log_evidence=state.log_evidence + info.log_increment,
        stages=state.stages + 1,
        moves=state.moves + info.move.count,
        acceptance_sum=state.acceptance_sum + info.move.acceptance_sum,
    ), info


def adaptive_tempering(
    key: Array,
    particles: WalkState,
    *,
    target: Target,
    config: TemperingConfig,
    max_stages: Array | int | None = None,
) -> TemperingState:
    """Temper ``particles.tempered`` in from temperature 0 to 1 on top of ``particles.anchor``,
    stage after stage (:func:`tempering_step`, stage s on ``fold_in(key, s)``), until the
    temperature is 1 or after ``max_stages`` stages (default ``config.max_stages``; an array
    lets one compiled program serve several limits); ``particles`` are equally weighted."""
    limit = config.max_stages if max_stages is None else max_stages
    dtype = particles.theta.dtype
    zero = jnp.zeros((), dtype)
    start = TemperingState(
        particles=particles,
        log_weights=jnp.zeros(particles.theta.shape[0], dtype),
        temperature=zero,
        log_evidence=zero,
        stages=jnp.zeros((), jnp.int32),
        moves=zero,
        acceptance_sum=zero,
    )

    def unfinished(state: TemperingState) -> Array:
        return (state.temperature < 1.0) & (state.stages < limit)

    def stage(state: TemperingState) -> TemperingState:
        state, _ = tempering_step(
            jax.random.fold_in(key, state.stages),
            state,
            target=target,
            config=config,
        )
        return state

    return jax.lax.while_loop(unfinished, stage, start)


def check_finished(
    temperature: np.ndarray, vehicle_ids: Sequence[str], sampler: str, max_stages: int
) -> None:
    """Raise a FloatingPointError naming every vehicle whose final ``temperature`` (any leading
    axes, vehicle last) is below 1: tempering stopped at ``max_stages`` short of the posterior."""
    short = np.flatnonzero(
        np.any(np.asarray(temperature) < 1.0, axis=tuple(range(np.ndim(temperature) - 1)))
    )
    if short.size:
        raise FloatingPointError(
            f"{sampler}: tempering did not reach the posterior within {max_stages} stages for "
            f"vehicle(s) {[vehicle_ids[i] for i in short]}"
        )
