"""The SMC core: its generic step by hand, and adaptive tempering against a closed form.

Seeds and tolerances are stated in each test."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import logsumexp

from bayesdrive.inference.core.kernels import Box, Target, WalkState
from bayesdrive.inference.core.smc import (
    SMCState,
    TemperingConfig,
    adaptive_tempering,
    check_finished,
    step,
)

NUM = 8
X = jnp.arange(NUM, dtype=jnp.float32)


def marking_move(key, particles):
    """A kernel that shifts every particle by 100 (so a run shows) and reports 1."""
    del key
    values, shared = particles
    return (values + 100.0, shared), jnp.ones((), jnp.float32)


@pytest.mark.parametrize(
    ("slope", "resamples"),
    [(0.01, False), (5.0, True)],  # ESS about 8 (kept) and below 4 (resampled) of 8
)
def test_the_step_reweights_and_resamples_and_moves_only_below_the_threshold(slope, resamples):
    """Eight particles 0..7 with unequal log weights, reweighted by -slope (x - 3)^2: the evidence
    increment is log sum(W exp(increment)) (numpy, float64, within 1e-5); above half the
    particles' ESS the cloud keeps its particles and the summed weights (normalised) and the
    kernel does not run (info zeros); below, the particles are resampled towards x = 3, moved,
    and equally weighted. A 0-d leaf (a shared proposal scale) passes resampling unchanged."""
    log_weights = 0.1 * X

    def potential(particles):
        values, _ = particles
        return -slope * (values - 3.0) ** 2

    state = SMCState((X, jnp.float32(0.7)), log_weights)
    new, info = step(jax.random.key(0), state, potential, marking_move, resample_below=0.5)

    increment = np.asarray(potential((X, None)), np.float64)
    old = np.asarray(log_weights, np.float64)
    expected = logsumexp(old + increment) - logsumexp(old)
    assert float(info.log_increment) == pytest.approx(expected, abs=1e-5)
    values, shared = new.particles
    assert float(shared) == pytest.approx(0.7)
    assert bool(info.resampled) is resamples
    if resamples:
        assert float(info.ess) < NUM / 2
        assert float(info.move) == 1.0
        np.testing.assert_array_equal(np.asarray(new.log_weights), np.zeros(NUM))
        np.testing.assert_array_equal(np.asarray(values), np.asarray(X)[info.ancestors] + 100.0)
        assert set(np.asarray(info.ancestors).tolist()) <= {2, 3, 4}
    else:
        assert float(info.ess) > NUM / 2
        assert float(info.move) == 0.0
        np.testing.assert_array_equal(np.asarray(values), np.asarray(X))
        np.testing.assert_array_equal(np.asarray(info.ancestors), np.arange(NUM))
        reweighted = old + increment
        np.testing.assert_allclose(
            np.asarray(new.log_weights), reweighted - logsumexp(reweighted), atol=1e-6
        )


MEAN = jnp.asarray([1.0, -2.0])
SD = jnp.asarray([0.5, 1.0])
BOX = Box(jnp.full(2, -10.0), jnp.full(2, 10.0))


def box_logpdf(theta):
    inside = jnp.all((theta >= BOX.lower) & (theta <= BOX.upper), axis=1)
    return jnp.where(inside, -jnp.log(400.0), -jnp.inf)


def gaussian_log_evidence(sd) -> float:
    """log of the integral of the uniform box prior times exp(-|theta - MEAN|^2 / (2 sd^2)): the
    box holds the Gaussian up to 8 sd (truncation below 1e-14)."""
    return float(np.sum(np.log(np.sqrt(2 * np.pi) * np.asarray(sd))) - np.log(400.0))


@jax.jit
def tempered_gaussian(key, max_stages):
    """Adaptive tempering from the box prior to the unnormalised Gaussian likelihood above, 1024
    particles, at least 5 moves a stage until every particle has likely moved."""

    def loglik(theta):
        return jnp.zeros(theta.shape[0]), -0.5 * jnp.sum(((theta - MEAN) / SD) ** 2, axis=1)

    key_prior, key_run = jax.random.split(key)
    theta = jax.random.uniform(key_prior, (1024, 2), minval=-10.0, maxval=10.0)
    anchor, tempered = loglik(theta)
    start = WalkState(theta, box_logpdf(theta), anchor, tempered, jnp.log(2.38 / jnp.sqrt(2.0)))
    config = TemperingConfig(num_particles=1024, num_moves=5)
    return adaptive_tempering(
        key_run,
        start,
        target=Target(loglik, box_logpdf, BOX),
        config=config,
        max_stages=max_stages,
    )


def test_adaptive_tempering_recovers_a_gaussian_evidence_and_posterior():
    """Seed 3: the log evidence within 0.2 nats of the closed form, the posterior means within
    0.1 sd and sds within 10%. Negative control: the closed forms of a likelihood 1.25 times as
    wide (evidence 0.45 nats higher, sds 25% wider) fail the same checks."""
    run = tempered_gaussian(jax.random.key(3), 200)
    assert float(run.temperature) == 1.0
    draws = np.asarray(run.particles.theta, np.float64)

    def matches(sd) -> bool:
        evidence_ok = abs(float(run.log_evidence) - gaussian_log_evidence(sd)) < 0.2
        mean_ok = np.all(np.abs(draws.mean(axis=0) - np.asarray(MEAN)) < 0.1 * np.asarray(sd))
        sd_ok = np.all(np.abs(draws.std(axis=0) / np.asarray(sd) - 1.0) < 0.1)
        return bool(evidence_ok and mean_ok and sd_ok)

    assert matches(SD)
    assert not matches(1.25 * SD)
    # Every stage ran at least num_moves moves; the adapted walk accepts at a sane rate.
    assert float(run.moves) >= 5 * int(run.stages)
    assert 0.1 < float(run.acceptance_sum / run.moves) < 0.6


def test_tempering_stops_at_max_stages_and_the_shortfall_is_an_error():
    """Seed 3 again, one stage allowed: tempering stops below temperature 1, and
    ``check_finished`` names the vehicle that fell short (vehicle axis last)."""
    run = tempered_gaussian(jax.random.key(3), 1)
    assert int(run.stages) == 1 and float(run.temperature) < 1.0
    temperatures = np.asarray([[1.0, float(run.temperature)], [1.0, 1.0]])
    with pytest.raises(FloatingPointError, match=r"within 1 stages for vehicle\(s\) \['b'\]"):
        check_finished(temperatures, ("a", "b"), "smc", 1)
    check_finished(np.ones((2, 2)), ("a", "b"), "smc", 1)
