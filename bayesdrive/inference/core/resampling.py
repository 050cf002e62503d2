"""Resampling schemes: ancestor indices drawn in proportion to log weights.

All three are unbiased (each particle's expected number of copies is N times its normalised
weight); systematic resampling has the lowest variance and is the engines' default.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import Array

from bayesdrive.inference.core.weights import normalize

__all__ = ["RESAMPLERS", "count_distinct_sorted", "multinomial", "stratified", "systematic"]


def _invert_cdf(log_weights: Array, positions: Array) -> Array:
    """Indices i with cdf[i-1] <= u < cdf[i] for sorted positions u in [0, 1)."""
    cdf = jnp.cumsum(jnp.exp(normalize(log_weights)))
    # Rounding can leave cdf[-1] a hair below 1; rescale so no position falls off the end.
    cdf = cdf / cdf[-1]
    indices = jnp.searchsorted(cdf, positions, side="right")
    return jnp.minimum(indices, log_weights.shape[0] - 1).astype(jnp.int32)


def systematic(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Systematic resampling: one uniform offset u shared by the positions (j + u) / num.

    Computed without a search, in O(N): particle i owns the positions below its cumulative weight,
    ceil(num * cdf_i - u) of them, so the ancestor of position j is the number of particles that
    own at most j positions (a histogram and a cumulative sum). On a CPU this is much faster than
    a binary search per position, with the same result.
    """
    n = log_weights.shape[0] if num is None else num
    cdf = jnp.cumsum(jnp.exp(normalize(log_weights)))
    cdf = cdf / cdf[-1]
    offset = jax.random.uniform(key, (), dtype=cdf.dtype)
    owned = jnp.clip(jnp.ceil(n * cdf - offset), 0, n).astype(jnp.int32)
    counts = jnp.zeros(n + 1, jnp.int32).at[owned].add(1)
    return jnp.minimum(jnp.cumsum(counts)[:n], log_weights.shape[0] - 1)


def stratified(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Stratified resampling: one uniform position in each of ``num`` equal strata."""
    n = log_weights.shape[0] if num is None else num
    positions = (jnp.arange(n) + jax.random.uniform(key, (n,))) / n
    return _invert_cdf(log_weights, positions)


def multinomial(key: Array, log_weights: Array, num: int | None = None) -> Array:
    """Multinomial resampling: ``num`` independent draws from the weights."""
    n = log_weights.shape[0] if num is None else num
    return jax.random.categorical(key, log_weights, shape=(n,)).astype(jnp.int32)


RESAMPLERS: dict[str, Callable[[Array, Array, int | None], Array]] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
}


def count_distinct_sorted(indices: Array) -> Array:
    """Distinct ancestors among sorted indices (systematic and stratified ones come sorted).

    The number of particles that survive a resampling: the usual degeneracy diagnostic, O(N).
    """
    return 1 + jnp.sum(indices[1:] != indices[:-1])
