r"""The sampler core's kernels: the pure pieces that the SMC core
(:mod:`bayesdrive.inference.core.smc`) assembles into ``smc`` (the default engine) and the held-out
continuation of the criticism (:mod:`bayesdrive.inference.engines.heldout_evidence`), so there is one
temperature search, one random-walk move and one set of stopping rules:

* :func:`next_temperature`: the largest temperature whose reweighting keeps a target effective
  sample size (bisection; Jasra et al. 2011);
* :func:`walk_step`: one random-walk Metropolis-Hastings move of a particle cloud on the logit
  scale of the prior box (key first, :class:`WalkState` in, ``(state, info)`` out), its scale
  adapted towards a target acceptance rate;
* the stopping rules of a run of moves: :func:`moves_until_moved` (move until every particle has
  likely moved, Drovandi & Pettitt 2011) and :func:`moves_until_decorrelated` (move until the
  draws no longer correlate with where they started).

**The move.** Where the prior has finite bounds the walk acts on
:math:`u = \mathrm{logit}((\theta - l)/(h - l))` (on :math:`\theta` itself elsewhere) and the
target on :math:`u` carries the Jacobian, so parameters piled against a bound move as freely as any
other and no proposal leaves the support. The proposal is Gaussian, ``chol`` (a Cholesky factor
of the cloud's covariance of u) times :math:`e^{s}`; after each move :math:`s` moves by
acceptance minus ``target_acceptance``. The target is
:math:`\log p(\theta) + \ell_a(\theta) + \lambda\, \ell_t(\theta)`: an *anchor* log-likelihood
fully included and a *tempered* one at power :math:`\lambda` (plain tempering has anchor 0).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from bayesdrive.inference.core.weights import effective_sample_size

__all__ = [
    "Box",
    "Independent",
    "Move",
    "Target",
    "WalkInfo",
    "WalkState",
    "decorrelation_threshold",
    "fixed_moves",
    "from_free",
    "log_jacobian",
    "moves_until_decorrelated",
    "moves_until_moved",
    "next_temperature",
    "paired_step",
    "to_free",
    "walk_step",
]


class Box(NamedTuple):
    """Prior bounds per parameter (-inf / inf where unbounded): the logit map's domain."""

    lower: Array
    upper: Array

    @property
    def bounded(self) -> Array:
        return jnp.isfinite(self.lower) & jnp.isfinite(self.upper)


def to_free(theta: Array, box: Box) -> Array:
    """u = logit((theta - lower) / (upper - lower)) where bounded, theta elsewhere."""
    scaled = (theta - box.lower) / (box.upper - box.lower)
    return jnp.where(box.bounded, jax.scipy.special.logit(scaled), theta)


def from_free(u: Array, box: Box) -> Array:
    """The inverse of :func:`to_free`."""
    return jnp.where(box.bounded, box.lower + (box.upper - box.lower) * jax.nn.sigmoid(u), u)


def log_jacobian(u: Array, box: Box) -> Array:
    """log |d theta / d u|, summed over parameters."""
    per_param = jnp.log(box.upper - box.lower) + jax.nn.log_sigmoid(u) + jax.nn.log_sigmoid(-u)
    return jnp.sum(jnp.where(box.bounded, per_param, 0.0), axis=-1)


def next_temperature(log_lik: Array, lam: Array, ess_fraction: float, iterations: int) -> Array:
    """The largest temperature in (lam, 1] whose reweighting by (new - lam) * log_lik keeps an
    ESS of ``ess_fraction * N``, by ``iterations`` bisection steps (1 if that keeps it already).

    A stage always advances by at least 1e-6, so a cloud the bisection cannot split still
    reaches 1."""
    target = ess_fraction * log_lik.shape[0]

    def halve(_, bracket):
        keeps, breaks = bracket
        middle = 0.5 * (keeps + breaks)
        fine = effective_sample_size((middle - lam) * log_lik) >= target
        return jnp.where(fine, middle, keeps), jnp.where(fine, breaks, middle)

    keeps, _ = jax.lax.fori_loop(0, iterations, halve, (lam, jnp.ones_like(lam)))
    return jnp.where(
        effective_sample_size((1.0 - lam) * log_lik) >= target,
        1.0,
        jnp.maximum(keeps, lam + 1e-6),
    )


class Target(NamedTuple):
    """What every move is invariant for, p(theta) exp(anchor(theta) + power * tempered(theta))
    less its ``power``: ``loglik(theta) -> (anchor, tempered)`` and ``prior_logpdf(theta) -> log p``
    take (N, d); the moves walk on the logit scale of ``box``."""

    loglik: Callable[[Array], tuple[Array, Array]]
    prior_logpdf: Callable[[Array], Array]
    box: Box


class WalkState(NamedTuple):
    """A particle cloud under a random walk: theta (N, d), its log prior, anchor and tempered
    log-likelihoods (N,), and the log of the proposal scale ()."""

    theta: Array
    log_prior: Array
    anchor: Array
    tempered: Array
    log_scale: Array


class WalkInfo(NamedTuple):
    """acceptance: the fraction of particles whose proposal was accepted ()."""

    acceptance: Array


def _normal(key: Array, shape: tuple[int, ...], dtype) -> Array:
    """Standard normals of ``shape``, the bits of ``jax.random.normal`` for the flat shape, made
    as one flat vector before the reshape. On CPU the compiler otherwise fuses the inverse-erf
    transform into the consumer of the (N, d) array, whose short rows do not vectorise: the draw
    then costs several times more than the flat one (partitionable threefry is slower for a 2-d
    shape too), more than a move's likelihood."""
    flat = jax.random.normal(key, (math.prod(shape),), dtype=dtype)
    return jax.lax.optimization_barrier(flat).reshape(shape)


def _metropolis(
    key: Array,
    state: WalkState,
    free: Array,
    prop_free: Array,
    log_proposal_ratio: Array,
    *,
    target: Target,
    power: Array,
) -> tuple[WalkState, Array]:
    """Accept or reject every particle's proposal ``prop_free`` (free scale) for the target
    p(theta) exp(anchor + power * tempered); ``log_proposal_ratio`` is log q(u | u') - log q(u' | u)
    (0 for a symmetric proposal). Returns the state (log_scale unchanged) and the acceptance rate."""
    box = target.box
    proposal = from_free(prop_free, box)
    prop_prior = target.prior_logpdf(proposal)
    prop_anchor, prop_tempered = target.loglik(proposal)
    log_ratio = (
        prop_prior
        + prop_anchor
        + power * prop_tempered
        + log_jacobian(prop_free, box)
        - (state.log_prior + state.anchor + power * state.tempered + log_jacobian(free, box))
        + log_proposal_ratio
    )
    # Outside the prior support the likelihood may be NaN: the comparison rejects it.
    accept = jnp.isfinite(prop_prior) & (
        jnp.log(jax.random.uniform(key, (free.shape[0],))) < log_ratio
    )
    moved = WalkState(
        theta=jnp.where(accept[:, None], proposal, state.theta),
        log_prior=jnp.where(accept, prop_prior, state.log_prior),
        anchor=jnp.where(accept, prop_anchor, state.anchor),
        tempered=jnp.where(accept, prop_tempered, state.tempered),
        log_scale=state.log_scale,
    )
    return moved, jnp.mean(accept)


def _walk_proposal(key: Array, free: Array, log_scale: Array, chol: Array) -> Array:
    """The random walk's proposal on the free scale (symmetric: no proposal ratio)."""
    return free + jnp.exp(log_scale) * (_normal(key, free.shape, free.dtype) @ chol.T)


def walk_step(
    key: Array,
    state: WalkState,
    *,
    target: Target,
    power: Array,
    chol: Array,
    target_acceptance: float,
) -> tuple[WalkState, WalkInfo]:
    """One random-walk MH move of every particle, invariant for ``target`` at ``power`` (module
    docstring)."""
    key_step, key_accept = jax.random.split(key)
    free = to_free(state.theta, target.box)
    prop_free = _walk_proposal(key_step, free, state.log_scale, chol)
    moved, rate = _metropolis(
        key_accept, state, free, prop_free, jnp.zeros(()), target=target, power=power
    )
    moved = moved._replace(log_scale=state.log_scale + rate - target_acceptance)
    return moved, WalkInfo(acceptance=rate)


class Independent(NamedTuple):
    """A multivariate Student-t on the free scale, fitted to a particle cloud: its centre (d,),
    the Cholesky factor L of its scale matrix (d, d), L's inverse, and its degrees of freedom, a
    whole number (the chi-square mixing variable is then a sum of squared normals, far cheaper
    than a gamma draw). Build it with :meth:`of`."""

    mean: Array
    chol: Array
    whiten: Array
    df: int

    @classmethod
    def of(cls, mean: Array, chol: Array, df: int) -> Independent:
        # A triangular solve inside every move is far slower on CPU than one product with L^-1.
        eye = jnp.eye(chol.shape[-1], dtype=chol.dtype)
        return cls(mean, chol, jax.scipy.linalg.solve_triangular(chol, eye, lower=True), df)

    def log_density(self, free: Array) -> Array:
        """log q(u) up to a constant, for (N, d) points."""
        centred = (free - self.mean) @ self.whiten.T
        distance = jnp.sum(centred * centred, axis=-1)
        return -0.5 * (self.df + self.mean.shape[-1]) * jnp.log1p(distance / self.df)

    def sample(self, key_normal: Array, key_mix: Array, num: int, dtype) -> Array:
        """``num`` draws (num, d) on the free scale."""
        normal = _normal(key_normal, (num, self.mean.shape[-1]), dtype) @ self.chol.T
        mix = jnp.sum(_normal(key_mix, (num, self.df), dtype) ** 2, axis=1)
        return self.mean + normal * jnp.sqrt(self.df / mix)[:, None]


def paired_step(
    key: Array,
    state: WalkState,
    *,
    target: Target,
    power: Array,
    proposal: Independent,
    target_acceptance: float,
) -> tuple[WalkState, WalkInfo]:
    """An independent MH move from ``proposal`` (South, Pettitt & Drovandi 2019: the proposal
    ignores where the particle is, so an accepted move forgets the start at once), then a
    random-walk move with the proposal's covariance, as :func:`walk_step` (its scale adapted).
    Both are invariant for ``target`` at ``power``. The acceptance is the chance that a particle
    moved in either, 1 - (1 - a1)(1 - a2), so the stopping rules count the pair as one move.

    The two halves are one scanned body that computes both proposals and selects one: the target
    (the likelihood, most of a sampler's program) is then traced and compiled once, not twice."""

    def half(state: WalkState, xs: tuple[Array, Array]) -> tuple[WalkState, Array]:
        key, is_walk = xs
        key_normal, key_mix, key_accept_independent = jax.random.split(key, 3)
        key_step, key_accept_walk = jax.random.split(key)
        free = to_free(state.theta, target.box)
        independent = proposal.sample(key_normal, key_mix, free.shape[0], free.dtype)
        walk = _walk_proposal(key_step, free, state.log_scale, proposal.chol)
        prop_free = jnp.where(is_walk, walk, independent)
        ratio = jnp.where(
            is_walk, 0.0, proposal.log_density(free) - proposal.log_density(independent)
        )
        key_accept = jnp.stack([key_accept_independent, key_accept_walk])[is_walk.astype(int)]
        moved, rate = _metropolis(
            key_accept, state, free, prop_free, ratio, target=target, power=power
        )
        adapted = jnp.where(is_walk, state.log_scale + rate - target_acceptance, state.log_scale)
        return moved._replace(log_scale=adapted), rate

    keys = jnp.stack(jax.random.split(key))
    state, rates = jax.lax.scan(half, state, (keys, jnp.array([False, True])))
    return state, WalkInfo(acceptance=1.0 - (1.0 - rates[0]) * (1.0 - rates[1]))


Move = Callable[[Array, WalkState], tuple[WalkState, WalkInfo]]


def moves_until_moved(
    key: Array,
    state: WalkState,
    move: Move,
    *,
    num_moves: int,
    unmoved_tolerance: float,
    max_moves: int,
) -> tuple[WalkState, Array, Array]:
    """Apply ``move`` at least ``num_moves`` times, then until the estimated probability that a
    particle has not moved at all, prod(1 - acceptance), is at most ``unmoved_tolerance``, at most
    ``max_moves`` times. Returns the state, the number of moves and the sum of acceptance rates."""
    dtype = state.theta.dtype

    def unfinished(carry):
        _, count, unmoved, _ = carry
        return (count < num_moves) | ((unmoved > unmoved_tolerance) & (count < max_moves))

    def body(carry):
        state, count, unmoved, rate_sum = carry
        state, info = move(jax.random.fold_in(key, count), state)
        return state, count + 1, unmoved * (1.0 - info.acceptance), rate_sum + info.acceptance

    one, zero = jnp.ones((), dtype), jnp.zeros((), dtype)
    state, count, _, rate_sum = jax.lax.while_loop(
        unfinished, body, (state, jnp.zeros((), jnp.int32), one, zero)
    )
    return state, count.astype(dtype), rate_sum


def fixed_moves(key: Array, state: WalkState, move: Move, count: int) -> tuple[WalkState, Array]:
    """Apply ``move`` exactly ``count`` times; returns the state and the mean acceptance."""

    def scanned(state, key):
        state, info = move(key, state)
        return state, info.acceptance

    state, rates = jax.lax.scan(scanned, state, jax.random.split(key, count))
    return state, jnp.mean(rates)


def decorrelation_threshold(decorrelation: float, num_particles: int) -> Array:
    """The largest correlation of the draws with their start at which
    :func:`moves_until_decorrelated` stops: ``decorrelation``, or about 3.5 / sqrt(N) where
    that is larger, since below it the largest of d sample correlations over N particles is
    noise, not mixing."""
    return jnp.maximum(decorrelation, 3.5 / jnp.sqrt(num_particles))


def moves_until_decorrelated(
    key: Array,
    state: WalkState,
    move: Move,
    *,
    box: Box,
    block: int,
    max_moves: int,
    threshold: Array,
) -> tuple[WalkState, Array, Array, Array]:
    """Apply ``move`` in blocks of ``block`` until no parameter's draws (on the free scale)
    correlate with their values at the start by more than ``threshold`` (or ``max_moves``).

    The correlation across particles between start and current position is the kernel's
    autocorrelation at that lag, measured on the target itself. Returns the state, the mean
    acceptance, the number of moves and the final largest |correlation|."""
    start = to_free(state.theta, box)
    start = start - start.mean(axis=0)  # centred once; every block compares against it
    start_sq = jnp.sum(start * start, axis=0)

    def largest_correlation(theta: Array) -> Array:
        now = to_free(theta, box)
        now = now - now.mean(axis=0)
        corr = jnp.sum(start * now, axis=0) / jnp.sqrt(start_sq * jnp.sum(now * now, axis=0))
        return jnp.max(jnp.abs(corr))

    def run_block(carry):
        state, key, done, accepted, _ = carry
        key, key_block = jax.random.split(key)
        state, rate = fixed_moves(key_block, state, move, block)
        return (state, key, done + block, accepted + rate * block, largest_correlation(state.theta))

    def more(carry):
        _, _, done, _, corr = carry
        return (done < max_moves) & (corr > threshold)

    zero = jnp.zeros((), state.theta.dtype)
    # The first block runs inside the loop (an infinite correlation to start), not peeled off
    # it: a peeled block is another copy of the move, and of the likelihood, to trace and compile.
    start_carry = (state, key, jnp.zeros((), jnp.int32), zero, jnp.full((), jnp.inf, zero.dtype))
    state, _, done, accepted, corr = jax.lax.while_loop(more, run_block, start_carry)
    return state, accepted / done, done, corr
