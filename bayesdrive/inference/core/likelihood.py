"""What every engine shares: the per-step log-likelihood, built only from the driver-model
interface (the per-vehicle preamble and loop are :mod:`bayesdrive.inference.core.vehicles`).

Step t of vehicle n scores the observed transition from sample t to t+1 with the model's exact
one-step density ``model.transition_logpdf`` (states relative to the current step: x = 0 and the
float64-computed increment dx). Masked steps contribute exactly 0, so padding and flagged samples
never move a posterior. The engines here assume exactly observed states (the base models'
point-mass observation model); a model with measurement noise needs a latent-state filter instead.
Inputs come from the model itself (``model.inputs_at`` on the one series), so no engine knows
which scene parts a model reads.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel, EgoState, device_series, fill_params

__all__ = [
    "StepInputs",
    "censoring",
    "check_model",
    "fixed_params",
    "full_history",
    "param_names",
    "particles_loglik",
    "score_draws",
    "series_loglik",
    "step_inputs",
    "step_loglik",
    "step_logpdfs",
]


class StepInputs(NamedTuple):
    """What one step's likelihood needs, as JAX arrays of any common leading shape.

    (vehicle, step) for a data set, (step,) for one vehicle's series, () for one step. ``inputs``
    are the model's own (built by its ``inputs_at``); ``mask`` marks the usable steps (a state
    filter runs through them and restarts after a gap), ``fit`` and ``heldout`` the steps a model
    comparison scores (None outside one).
    """

    v: Array
    next_v: Array
    dx: Array
    mask: Array
    inputs: Any
    fit: Array | None = None
    heldout: Array | None = None


def full_history(mask: Array, history: int) -> Array:
    """``mask`` where each of the ``history`` steps before a step is usable too, else 0."""
    usable = mask > 0
    kept = usable
    for k in range(1, history + 1):
        kept = kept & jnp.pad(usable[..., :-k], [(0, 0)] * (usable.ndim - 1) + [(k, 0)])
    return kept.astype(mask.dtype)


@functools.partial(jax.jit, static_argnums=(0, 2, 3))
def _inputs_and_mask(
    inputs_at: Any, series: Any, history: int, reads_history: bool
) -> tuple[Any, Array]:
    """Every step's model inputs and the mask it is scored under, as one program per model and
    shape (eagerly, each of their many small operations compiled on its own)."""
    index = jnp.arange(series.mask.shape[1])
    inputs = jax.vmap(lambda one: jax.vmap(lambda j: inputs_at(one, j, history))(index))(series)
    return inputs, full_history(series.mask, history) if reads_history else series.mask


def step_inputs(arrays: FollowerArrays, model: DriverModel) -> StepInputs:
    """Every step of ``arrays`` with the inputs ``model`` reads, as JAX arrays in the default float
    type (float32 unless x64). A model that reads its past is scored only on steps with a full
    history behind them (:meth:`FollowerArrays.history` steps)."""
    series = device_series(arrays)
    inputs, mask = _inputs_and_mask(model.inputs_at, series, arrays.history, model.reads_history)
    windows = arrays.windows
    return StepInputs(
        v=series.v,
        next_v=series.next_v,
        dx=series.dx,
        mask=mask,
        inputs=inputs,
        fit=None if windows is None else jnp.asarray(windows.fit, dtype=series.v.dtype),
        heldout=None if windows is None else jnp.asarray(windows.heldout, dtype=series.v.dtype),
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


def check_model(model: DriverModel, engine: str, *, whole_series: bool = False) -> None:
    """Refuse, in one line and before any work, a model ``engine`` cannot evaluate: one whose
    density needs a state filter over the series unless the engine scores whole series
    (``whole_series``; such a filter handles the model's hidden state, noisy readings included),
    and one with an observation model but no filter (these engines condition on exactly observed
    states and would ignore it)."""
    if model.filter is not None:
        if not whole_series:
            raise NotImplementedError(
                f"engine {engine!r} cannot fit {model.name!r}: its density needs a state filter "
                "over the whole series and the engine scores one step at a time (use 'smc' "
                "without its sequential pass, 'nuts' or 'emcee')"
            )
    elif not model.observed_exactly:
        raise NotImplementedError(
            f"engine {engine!r} cannot fit {model.name!r}: its states are observed with noise and "
            "the engine scores exactly observed states (use engine 'pmmh')"
        )


def censoring(
    model: DriverModel, steps: StepInputs, *, usable_only: bool = False
) -> dict[str, Array]:
    """The keyword a model that declares ``censored`` steps takes in its densities: whether any
    of ``steps`` (one step, or one vehicle's (T,) series) is censored; nothing for another model.
    On a series without a censored step the densities then skip the class probabilities, at run
    time (a traced flag; :func:`~bayesdrive.drivers.execution_noise.step_logpdf`).
    ``usable_only``: only the steps whose mask is set count (for a caller that zeroes the others;
    padding reads as a stop)."""
    if model.censored is None:
        return {}
    flags = _censored_steps(model, steps)
    if usable_only:
        flags = flags & (steps.mask > 0)
    return {"may_be_censored": jnp.any(flags)}


def _censored_steps(model: DriverModel, steps: StepInputs) -> Array:
    """Whether each of ``steps`` (any leading shape) is censored (``model.censored``)."""
    observed = EgoState(jnp.zeros_like(steps.v), steps.v)
    following = EgoState(steps.dx, steps.next_v)
    censored = model.censored  # of one step: mapped over each axis of the steps
    for _ in range(jnp.ndim(steps.v)):
        censored = jax.vmap(censored)
    return censored(observed, following, steps.inputs)


# Censored steps are scored in blocks of this many (:func:`step_logpdfs`).
CENSORED_BLOCK = 16


def step_loglik(
    model: DriverModel,
    names: Sequence[str],
    fixed: Any,
    theta: Array,
    step: StepInputs,
    censored: dict[str, Array] | None = None,
) -> Array:
    """Log-density of one observed step for one parameter vector ``theta`` (0 where masked).

    The model's full state is lifted from the observed one (identity for memoryless models).
    ``censored`` is the :func:`censoring` keyword to use, where the caller decided it for more
    than this step (a superset of steps that holds a censored one scores the same)."""
    params = fill_params(model, names, theta, fixed)
    observed = EgoState(x=jnp.zeros_like(step.v), v=step.v)
    state = model.lift(params, observed, step.inputs)
    following = EgoState(x=step.dx, v=step.next_v)
    flag = censoring(model, step) if censored is None else censored
    logp = model.transition_logpdf(params, state, following, step.inputs, **flag)
    return jnp.where(step.mask > 0, logp, 0.0)


def step_logpdfs(
    model: DriverModel, params: Any, steps: StepInputs, *, may_be_censored: bool | None = None
) -> Array:
    """One-step log predictive density of every step of one vehicle's (T,) series -> (T,).

    Exactly observed models score each step on its own (from the lifted state); models with a
    hidden state run their filter over the vehicle's steps in order. A model that declares which
    steps are ``censored`` is told whether the series has one (:func:`censoring`), or
    ``may_be_censored`` where given (False: a promise that no step is). Nothing is masked here.

    A step-by-step model scores every step by its density, then only the usable censored steps
    (``steps.mask`` set) by their class probability, gathered in blocks of ``CENSORED_BLOCK``: the
    classes' normal log-CDFs cost many times the density, and a series rarely holds more than a
    few censored steps. A masked step keeps its density (callers zero it): padding reads as a
    stop. The loops run a fixed number of times, skipping empty blocks, so the function stays
    differentiable in reverse mode."""
    if may_be_censored is not None and model.censored is None:
        raise ValueError(f"model {model.name!r} declares no censored steps to skip")
    if model.filter is not None:
        flag = (
            censoring(model, steps)
            if may_be_censored is None
            else {"may_be_censored": may_be_censored}
        )
        return model.filter(params, steps, **flag)

    def one(v, next_v, dx, inputs, **censored):
        state = model.lift(params, EgoState(jnp.zeros_like(v), v), inputs)
        return model.transition_logpdf(params, state, EgoState(dx, next_v), inputs, **censored)

    columns = (steps.v, steps.next_v, steps.dx, steps.inputs)
    if model.censored is None:
        return jax.vmap(one)(*columns)
    logp = jax.vmap(functools.partial(one, may_be_censored=False))(*columns)
    if may_be_censored is False:
        return logp
    # Each step's own class, whatever the caller's flag for the series says of it.
    censored = _censored_steps(model, steps) & (steps.mask > 0)
    num_steps = censored.shape[0]
    # Every usable censored step's index, then past-the-end ones: a whole number of blocks.
    num_blocks = -(-num_steps // CENSORED_BLOCK)
    where_censored = jnp.nonzero(censored, size=num_blocks * CENSORED_BLOCK, fill_value=num_steps)[
        0
    ]
    blocks_used = -(-jnp.sum(censored) // CENSORED_BLOCK)

    def score_block(logp: Array, block: Array) -> tuple[Array, None]:
        def with_classes() -> Array:
            index = jax.lax.dynamic_slice_in_dim(
                where_censored, block * CENSORED_BLOCK, CENSORED_BLOCK
            )
            rows = jax.tree.map(lambda a: a[jnp.minimum(index, num_steps - 1)], columns)
            classes = jax.vmap(functools.partial(one, may_be_censored=True))(*rows)
            return logp.at[index].set(classes, mode="drop")  # past-the-end slots write nothing

        return jax.lax.cond(block < blocks_used, with_classes, lambda: logp), None

    return jax.lax.cond(
        blocks_used > 0,
        lambda: jax.lax.scan(score_block, logp, jnp.arange(num_blocks))[0],
        lambda: logp,
    )


def particles_loglik(
    model: DriverModel,
    names: Sequence[str],
    fixed: Any,
    particles: Array,
    step: StepInputs,
    censored: dict[str, Array] | None = None,
) -> Array:
    """One step scored for every particle: (N, d) particles -> (N,) (``censored``:
    :func:`step_loglik`)."""
    return jax.vmap(lambda theta: step_loglik(model, names, fixed, theta, step, censored))(
        particles
    )


def series_loglik(
    model: DriverModel, names: Sequence[str], fixed: Any, theta: Array, series: StepInputs
) -> Array:
    """Every step of one vehicle's series scored for one parameter vector: -> (T,) (0 where
    masked; through the model's state filter where it has one)."""
    logp = step_logpdfs(model, fill_params(model, names, theta, fixed), series)
    return jnp.where(series.mask > 0, logp, 0.0)


# Steps scored together by :func:`score_draws`: a vehicle's series is scored in blocks of this many
# steps up to its last usable one, so padding past it costs at most one block.
SCORE_BLOCK = 64


@functools.partial(jax.jit, static_argnums=(0, 1))
def _score_series(model, names, fixed, particles, series):
    def one_vehicle(draws, vehicle_series):
        return jax.vmap(lambda th: series_loglik(model, names, fixed, th, vehicle_series))(draws)

    return jax.vmap(one_vehicle)(particles, series)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _score_blocks(model, names, fixed, particles, series, num_blocks):
    block = SCORE_BLOCK

    def one_vehicle(args):
        draws, vehicle_series, vehicle_blocks = args

        def score_block(b, out):
            steps = jax.tree.map(
                lambda a: jax.lax.dynamic_slice_in_dim(a, b * block, block), vehicle_series
            )

            def one_draw(theta):
                params = fill_params(model, names, theta, fixed)
                logp = step_logpdfs(model, params, steps)
                return jnp.where(steps.mask > 0, logp, 0.0)

            return jax.lax.dynamic_update_slice_in_dim(out, jax.vmap(one_draw)(draws), b * block, 1)

        empty = jnp.zeros((draws.shape[0], vehicle_series.mask.shape[-1]), draws.dtype)
        return jax.lax.fori_loop(0, vehicle_blocks, score_block, empty)

    # Vehicles one after another (not vmapped), so the censored-step branches stay real branches.
    return jax.lax.map(one_vehicle, (particles, series, num_blocks))


def score_draws(
    model: DriverModel, names: tuple[str, ...], fixed: Any, particles: Array, series: StepInputs
) -> np.ndarray:
    """Per-step log-likelihood (vehicle, draw, step) of draws (vehicle, draw, d), on every padded
    step (the result's ``log_likelihood`` group keeps the unmasked ones; steps past a vehicle's
    last usable one are 0 without being scored)."""
    particles = jnp.asarray(particles, float)
    if model.filter is not None:  # a state filter runs over the whole series
        return np.asarray(_score_series(model, names, fixed, particles, series))
    num_steps = series.mask.shape[-1]
    padded = -(-num_steps // SCORE_BLOCK) * SCORE_BLOCK
    series = jax.tree.map(
        lambda a: jnp.pad(a, [(0, 0), (0, padded - num_steps)] + [(0, 0)] * (a.ndim - 2)), series
    )
    live = np.asarray(series.mask) > 0
    length = np.where(live.any(axis=1), padded - np.argmax(live[:, ::-1], axis=1), 0)
    num_blocks = jnp.asarray(-(-length // SCORE_BLOCK), jnp.int32)
    scores = _score_blocks(model, names, fixed, particles, series, num_blocks)
    return np.asarray(scores)[..., :num_steps]
