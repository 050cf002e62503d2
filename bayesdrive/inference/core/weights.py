"""Particle weights in log space and particle-set diagnostics.

Weights never leave log space: normalising, averaging and the effective sample size all go through
``logsumexp``, so a likelihood of exp(-1000) never underflows to a zero weight.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.scipy.special import logsumexp

__all__ = [
    "convergence_curve",
    "effective_sample_size",
    "log_mean_weight",
    "normalize",
    "weighted_mean_cov",
]


def normalize(log_weights: Array) -> Array:
    """Log weights shifted so that their exponentials sum to 1."""
    return log_weights - logsumexp(log_weights)


def log_mean_weight(log_weights: Array) -> Array:
    """log(mean(exp(log_weights))): an evidence increment when the previous weights were equal."""
    return logsumexp(log_weights) - jnp.log(log_weights.shape[-1])


def effective_sample_size(log_weights: Array) -> Array:
    """Kish's effective sample size (sum w)^2 / sum w^2, between 1 and the number of particles."""
    # Shifting by the maximum is exact, so float32 keeps its precision on log weights near -1e3.
    shifted = log_weights - jnp.max(log_weights)
    return jnp.exp(2.0 * logsumexp(shifted) - logsumexp(2.0 * shifted))


def weighted_mean_cov(particles: Array, log_weights: Array) -> tuple[Array, Array]:
    """Weighted mean (d,) and covariance (d, d) of particles (N, d) under log weights (N,)."""
    w = jnp.exp(normalize(log_weights))
    mean = w @ particles
    centred = particles - mean
    return mean, (centred * w[:, None]).T @ centred


def convergence_curve(means: Array, width: Array) -> Array:
    """The paper's convergence curve: distance of each step's particle mean to the final mean.

    ``means`` (T, d) are the particle-set means after each step, ``width`` (d,) the prior widths;
    returns (T,) root-mean-square over parameters of (mean_t - mean_T) / width: 0 at the end, 0.5
    where every mean still sits at the centre of a uniform prior and ends at one of its bounds.
    """
    return jnp.sqrt(jnp.mean(((means - means[-1]) / width) ** 2, axis=-1))
