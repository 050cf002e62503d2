"""Resamplers are unbiased: each particle's mean number of copies is N times its weight."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.inference.core.resampling import RESAMPLERS, count_distinct_sorted, systematic
from bayesdrive.inference.core.weights import effective_sample_size, log_mean_weight, normalize

SEED = 20240601
REPEATS = 2000
# Weights spanning 30 orders of magnitude in log space, one exactly zero (log = -inf): the
# resamplers must work on log weights without underflow and never pick a zero-weight particle.
LOG_WEIGHTS = jnp.array([-1000.0, -1001.0, -1000.5, -jnp.inf, -1069.0, -999.2, -1002.0])
N = LOG_WEIGHTS.shape[0]


def mean_counts(resample, jit: bool) -> tuple[np.ndarray, np.ndarray]:
    """Mean copies per particle over REPEATS resamplings, and N * w."""

    def counts(key):
        return jnp.bincount(resample(key, LOG_WEIGHTS), length=N)

    batched = jax.vmap(counts)
    if jit:
        batched = jax.jit(batched)
    keys = jax.random.split(jax.random.key(SEED), REPEATS)
    expected = N * np.exp(np.asarray(normalize(LOG_WEIGHTS), dtype=np.float64))
    return np.asarray(batched(keys), dtype=np.float64).mean(axis=0), expected


def within_tolerance(observed: np.ndarray, expected: np.ndarray) -> bool:
    """|mean - N w| <= 5 standard errors of a multinomial count (an upper bound on the standard
    error of systematic and stratified counts) plus 1e-9, for every particle."""
    w = expected / N
    standard_error = np.sqrt(N * w * (1 - w) / REPEATS)
    return bool(np.all(np.abs(observed - expected) <= 5 * standard_error + 1e-9))


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("name", sorted(RESAMPLERS))
def test_resampler_is_unbiased(name, jit):
    observed, expected = mean_counts(RESAMPLERS[name], jit)
    assert within_tolerance(observed, expected), (name, observed, expected)
    assert observed[3] == 0.0  # the zero-weight particle is never chosen


def test_a_biased_resampler_fails_the_same_check():
    # Systematic resampling without its random offset always takes the left end of each stratum.
    def no_offset(key, log_weights, num=None):
        del key
        cdf = jnp.cumsum(jnp.exp(normalize(log_weights)))
        positions = jnp.arange(N) / N
        return jnp.minimum(jnp.searchsorted(cdf / cdf[-1], positions, side="right"), N - 1)

    observed, expected = mean_counts(no_offset, jit=True)
    assert not within_tolerance(observed, expected)


def test_systematic_indices_are_sorted_and_distinct_count_matches():
    parents = systematic(jax.random.key(SEED), LOG_WEIGHTS)
    assert np.all(np.diff(np.asarray(parents)) >= 0)
    assert int(count_distinct_sorted(parents)) == len(np.unique(np.asarray(parents)))


def test_weight_summaries_in_log_space():
    equal = jnp.full(5, -2000.0)  # exp underflows in float32; the log-space formulas must not
    assert float(effective_sample_size(equal)) == pytest.approx(5.0, rel=1e-5)
    assert float(log_mean_weight(equal)) == pytest.approx(-2000.0, rel=1e-6)
    one_alive = jnp.array([0.0, -jnp.inf, -jnp.inf])
    assert float(effective_sample_size(one_alive)) == pytest.approx(1.0, rel=1e-6)
