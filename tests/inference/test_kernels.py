"""The sampler core's kernels against exact targets (seeds and tolerances in each test)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from bayesdrive.inference.core.kernels import (
    Box,
    Independent,
    Target,
    WalkState,
    fixed_moves,
    from_free,
    next_temperature,
    paired_step,
    to_free,
    walk_step,
)
from bayesdrive.inference.core.weights import effective_sample_size

BOX = Box(jnp.asarray([-4.0, 0.0]), jnp.asarray([4.0, 3.0]))


def test_the_temperature_search_keeps_the_target_ess():
    """Log-likelihoods of 1000 particles (seed 0): the next temperature's weights have an ESS of
    half the particles (within 1 particle), and a flat likelihood goes straight to 1."""
    log_lik = -50.0 * jax.random.uniform(jax.random.key(0), (1000,))
    lam = next_temperature(log_lik, jnp.float32(0.0), 0.5, 40)
    assert 0.0 < float(lam) < 1.0
    ess = float(effective_sample_size(lam * log_lik))
    assert abs(ess - 500.0) < 1.0
    assert float(next_temperature(jnp.zeros(1000), jnp.float32(0.3), 0.5, 40)) == 1.0


def test_the_logit_map_round_trips():
    theta = jnp.asarray([[-3.9, 0.01], [0.0, 1.5], [3.5, 2.99]])
    np.testing.assert_allclose(from_free(to_free(theta, BOX), BOX), theta, rtol=1e-5, atol=1e-5)


def target_draws(key, n):
    """n draws of the test target: N(0.5, 0.8^2) and an Exponential(1) truncated to [0, 3]."""
    normal = 0.5 + 0.8 * jax.random.normal(key, (n,))
    exponential = stats.truncexpon.rvs(3.0, size=n, random_state=np.random.default_rng(1))
    return jnp.stack([normal, jnp.asarray(exponential, jnp.float32)], axis=1)


def target_loglik(th):
    return jnp.zeros(th.shape[0]), stats_normal_logpdf(th[:, 0]) - th[:, 1]


def box_logpdf(th):
    inside = jnp.all((th >= BOX.lower) & (th <= BOX.upper), axis=1)
    return jnp.where(inside, 0.0, -jnp.inf)


class _Uncorrected(Independent):
    """The independent proposal with its density left out of the acceptance ratio: a wrong
    kernel, whose stationary law is the target times the proposal."""

    def log_density(self, free):
        return jnp.zeros(free.shape[0])


def test_independent_moves_leave_their_target_invariant():
    """The target of the walk's test, 4000 draws of it (seed 2) moved 20 times by the paired
    move (independent then random walk) whose Student-t (5 df) is deliberately off: centred one
    unit away on the free scale, 1.3 times too wide. They stay distributed as the target (KS
    p > 0.001 per parameter). Leaving the proposal density out of the ratio (a wrong kernel) is
    rejected (p < 1e-6), so the check sees the correction."""
    key_draw, key_move = jax.random.split(jax.random.key(2))
    theta = target_draws(key_draw, 4000)
    anchor, tempered = target_loglik(theta)
    start = WalkState(theta, box_logpdf(theta), anchor, tempered, jnp.float32(np.log(1.7)))
    free = to_free(theta, BOX)
    chol = 1.3 * jnp.linalg.cholesky(jnp.cov(free, rowvar=False))
    target = dict(target=Target(target_loglik, box_logpdf, BOX), power=1.0)

    def moved(kind):
        proposal = kind.of(free.mean(axis=0) + 1.0, chol, 5)
        pair = functools.partial(paired_step, proposal=proposal, target_acceptance=0.234, **target)
        state, rate = fixed_moves(key_move, start, pair, 20)
        assert 0.05 < float(rate) < 0.95
        return np.asarray(state.theta, np.float64)

    exact = moved(Independent)
    assert stats.kstest(exact[:, 0], stats.norm(0.5, 0.8).cdf).pvalue > 1e-3
    assert stats.kstest(exact[:, 1], stats.truncexpon(3.0).cdf).pvalue > 1e-3
    wrong = moved(_Uncorrected)
    assert stats.kstest(wrong[:, 0], stats.norm(0.5, 0.8).cdf).pvalue < 1e-6


def test_the_walk_leaves_its_target_invariant():
    """Target: N(0.5, 0.8^2) (the box [-4, 4] cuts ~1e-5 of it) and an Exponential(1) truncated
    to the box [0, 3], independent. 4000 particles drawn from the target (seed 1) and moved 60
    times stay distributed as the target (KS p > 0.001 per parameter); the same walk at power 0.5
    (a different target) is rejected (p < 1e-6), so the check has power."""
    key_draw, key_move = jax.random.split(jax.random.key(1))
    theta = target_draws(key_draw, 4000)
    loglik, prior_logpdf = target_loglik, box_logpdf
    anchor, tempered = loglik(theta)
    start = WalkState(theta, prior_logpdf(theta), anchor, tempered, jnp.float32(np.log(1.7)))
    chol = jnp.linalg.cholesky(jnp.cov(to_free(theta, BOX), rowvar=False))

    def moved(power):
        move = functools.partial(
            walk_step,
            target=Target(loglik, prior_logpdf, BOX),
            power=power,
            chol=chol,
            target_acceptance=0.234,
        )
        state, rate = fixed_moves(key_move, start, move, 60)
        assert 0.05 < float(rate) < 0.9
        return np.asarray(state.theta, np.float64)

    exact = moved(1.0)
    assert stats.kstest(exact[:, 0], stats.norm(0.5, 0.8).cdf).pvalue > 1e-3
    assert stats.kstest(exact[:, 1], stats.truncexpon(3.0).cdf).pvalue > 1e-3
    flatter = moved(0.5)
    assert stats.kstest(flatter[:, 0], stats.norm(0.5, 0.8).cdf).pvalue < 1e-6


def stats_normal_logpdf(x):
    return jax.scipy.stats.norm.logpdf(x, 0.5, 0.8)
