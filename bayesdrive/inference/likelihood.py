"""What every particle engine shares: the per-step log-likelihood, built only from the driver-model
interface, and the loop that runs a per-vehicle engine over chunks of vehicles.

Step t of vehicle n scores the observed transition from sample t to t+1 with the model's exact
one-step density ``model.transition_logpdf`` (states relative to the current step: x = 0 and the
float64-computed increment dx). Masked steps contribute exactly 0, so padding and flagged samples
never move a posterior. The engines here assume exactly observed states (the base models'
point-mass observation model); a model with measurement noise needs a latent-state filter instead.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays, MergeArrays
from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, fill_params
from bayesdrive.drivers.cidm import MergeInputs
from bayesdrive.drivers.idm import exact_observation_logpdf

__all__ = [
    "StepInputs",
    "check_model",
    "clear_compiled",
    "fixed_params",
    "map_vehicles",
    "param_names",
    "particles_loglik",
    "score_draws",
    "series_loglik",
    "static_key",
    "step_inputs",
    "step_loglik",
]


class StepInputs(NamedTuple):
    """What one step's likelihood needs, as JAX arrays of any common leading shape.

    (vehicle, step) for a data set, (step,) for one vehicle's series, () for one step. ``dt`` is
    broadcast to the same shape so every field can be scanned over steps alike. ``merge`` (the
    merge scene, for merging models; None otherwise) has one trailing merge-slot axis more.
    """

    v: Array
    next_v: Array
    dx: Array
    gap: Array
    lead_v: Array
    has_leader: Array
    mask: Array
    dt: Array
    merge: MergeArrays | None = None


def step_inputs(arrays: FollowerArrays) -> StepInputs:
    """The (vehicle, step) arrays as JAX arrays in the default float type (float32 unless x64)."""

    def cast(values) -> Array:
        return jnp.asarray(values, dtype=float)

    return StepInputs(
        v=cast(arrays.v),
        next_v=cast(arrays.next_v),
        dx=cast(arrays.dx),
        gap=cast(arrays.gap),
        lead_v=cast(arrays.lead_v),
        has_leader=cast(arrays.has_leader),
        mask=cast(arrays.mask),
        dt=jnp.full(arrays.mask.shape, arrays.dt, dtype=float),
        merge=None if arrays.merge is None else MergeArrays(*map(cast, arrays.merge)),
    )


def param_names(model: DriverModel, params: Sequence[str] | None) -> tuple[str, ...]:
    """The inferred parameters (all of the model's when ``params`` is None), checked and in order."""
    if params is None:
        return model.param_names
    names = tuple(params)
    unknown = [n for n in names if n not in model.param_names]
    if unknown:
        raise ValueError(
            f"model {model.name!r} has no parameter(s) {unknown}; it has {list(model.param_names)}"
        )
    if not names or len(set(names)) != len(names):
        raise ValueError(f"parameters to infer must be non-empty and distinct, got {list(names)}")
    return names


def fixed_params(model: DriverModel, fixed: Mapping[str, float] | None) -> Any:
    """A full parameter tuple: ``fixed`` values where given, the model's defaults elsewhere."""
    fixed = dict(fixed or {})
    unknown = sorted(set(fixed) - set(model.param_names))
    if unknown:
        raise ValueError(
            f"fixed value(s) for unknown parameter(s) {unknown} of model {model.name!r}; "
            f"it has {list(model.param_names)}"
        )
    return model.params_type(
        *(jnp.asarray(fixed.get(s.name, s.default), dtype=float) for s in model.specs)
    )


def check_model(model: DriverModel) -> None:
    """Refuse models whose states are observed with noise: these engines condition on exact states."""
    if model.observation_logpdf is not exact_observation_logpdf:
        raise NotImplementedError(
            f"model {model.name!r} has its own observation model; the particle engines score exactly "
            "observed states and would ignore it"
        )


def step_loglik(
    model: DriverModel, names: Sequence[str], fixed: Any, theta: Array, step: StepInputs
) -> Array:
    """Log-density of one observed step for one parameter vector ``theta`` (0 where masked)."""
    params = fill_params(model, names, theta, fixed)
    state = EgoState(x=jnp.zeros_like(step.v), v=step.v)
    next_state = EgoState(x=step.dx, v=step.next_v)
    following = (step.gap, step.lead_v, step.has_leader, step.dt)
    inputs = (
        CarFollowingInputs(*following)
        if step.merge is None
        else MergeInputs(*following, *step.merge)
    )
    logp = model.transition_logpdf(params, state, next_state, inputs)
    return jnp.where(step.mask > 0, logp, 0.0)


def particles_loglik(
    model: DriverModel, names: Sequence[str], fixed: Any, particles: Array, step: StepInputs
) -> Array:
    """One step scored for every particle: (N, d) particles -> (N,)."""
    return jax.vmap(lambda theta: step_loglik(model, names, fixed, theta, step))(particles)


def series_loglik(
    model: DriverModel, names: Sequence[str], fixed: Any, theta: Array, series: StepInputs
) -> Array:
    """Every step of one vehicle's series scored for one parameter vector: -> (T,)."""
    return jax.vmap(lambda step: step_loglik(model, names, fixed, theta, step))(series)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _score_draws(model, names, fixed, particles, series):
    def one_vehicle(draws, vehicle_series):
        return jax.vmap(lambda th: series_loglik(model, names, fixed, th, vehicle_series))(draws)

    return jax.vmap(one_vehicle)(particles, series)


def score_draws(
    model: DriverModel, names: tuple[str, ...], fixed: Any, particles: Array, series: StepInputs
) -> np.ndarray:
    """Per-step log-likelihood (vehicle, draw, step) of draws (vehicle, draw, d), on every padded
    step (the result's ``log_likelihood`` group keeps the unmasked ones)."""
    return np.asarray(_score_draws(model, names, fixed, jnp.asarray(particles, float), series))


# Compiled chunk runners by cache key, so repeated fits of one shape (tests, seed studies) compile
# once per process; small, because each entry holds an executable.
_COMPILED: dict[Any, Any] = {}
_COMPILED_MAX = 8


def clear_compiled() -> None:
    """Forget every cached compiled chunk (the next fit compiles again, e.g. to time it)."""
    _COMPILED.clear()


def map_vehicles(
    per_vehicle: Callable[..., Any],
    inputs: tuple[Any, ...],
    *,
    chunk: int,
    batch: int | None,
    progress: Callable[[int, int], None] | None = None,
    cache_key: Any = None,
) -> tuple[Any, float, float]:
    """Run ``per_vehicle`` on every vehicle, ``chunk`` vehicles per compiled call.

    ``inputs`` are pytrees with a leading vehicle axis; ``per_vehicle`` gets one vehicle's slice.
    Inside a chunk, ``batch`` vehicles are vectorised together (None or 1: one after another, which
    keeps ``lax.cond`` a real branch; under ``vmap`` it becomes a select that runs both sides).
    The last chunk is padded by repeating its last vehicle, so the function compiles once, ahead
    of time. ``cache_key`` (hashable, or None for no caching) must determine ``per_vehicle``
    completely: the compiled chunk is reused for the same key and input shapes, and the compile
    time is then 0. Returns the stacked numpy outputs, the compile time and the run time (compile
    excluded) in seconds; ``progress(done, total)`` is called after each chunk.
    """
    num_vehicles = jax.tree.leaves(inputs)[0].shape[0]
    chunk = max(1, min(chunk, num_vehicles))
    batch_size = None if batch is None or batch <= 1 else min(batch, chunk)

    def run_chunk(*chunk_inputs):
        return jax.lax.map(lambda xs: per_vehicle(*xs), chunk_inputs, batch_size=batch_size)

    def chunk_at(start: int):
        rows = np.minimum(np.arange(start, start + chunk), num_vehicles - 1)
        return jax.tree.map(lambda a: a[rows], inputs)

    first = chunk_at(0)
    shapes = jax.tree.map(lambda a: (a.shape, str(a.dtype)), first)
    key = None if cache_key is None else (cache_key, chunk, batch_size, str(shapes))
    compile_time = 0.0
    if key is None or key not in _COMPILED:
        started = time.perf_counter()
        compiled = jax.jit(run_chunk).lower(*first).compile()
        compile_time = time.perf_counter() - started
        if key is not None:
            if len(_COMPILED) >= _COMPILED_MAX:
                _COMPILED.pop(next(iter(_COMPILED)))
            _COMPILED[key] = compiled
    else:
        compiled = _COMPILED[key]

    pieces, run_time = [], 0.0
    for start in range(0, num_vehicles, chunk):
        chunk_inputs = first if start == 0 else chunk_at(start)
        started = time.perf_counter()
        out = jax.block_until_ready(compiled(*chunk_inputs))
        run_time += time.perf_counter() - started
        keep = min(chunk, num_vehicles - start)
        pieces.append(jax.tree.map(lambda a, keep=keep: np.asarray(a)[:keep], out))
        if progress is not None:
            progress(start + keep, num_vehicles)
    stacked = jax.tree.map(lambda *parts: np.concatenate(parts), *pieces)
    return stacked, compile_time, run_time


def static_key(value: Any) -> Any:
    """A hashable stand-in for a prior or a parameter tuple, for ``map_vehicles``'s cache key.

    Arrays become tuples of floats; leaves other than arrays, numbers and strings give None (no
    caching), because an object hashed by identity could change between fits.
    """
    leaves, treedef = jax.tree.flatten(value)
    frozen = []
    for leaf in leaves:
        if hasattr(leaf, "shape"):
            frozen.append((np.shape(leaf), tuple(np.asarray(leaf).ravel().tolist())))
        elif isinstance(leaf, str | int | float):
            frozen.append(leaf)
        else:
            return None
    return (type(value).__qualname__, str(treedef), tuple(frozen))
