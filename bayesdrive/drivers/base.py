r"""The driver-model interface every engine and the simulator share.

A driver model is a parameter NamedTuple (its docstring states the math) plus pure functions of
ONE vehicle and ONE parameter particle; callers ``vmap`` them over particles and vehicles:

* ``mean_acceleration(params, state, inputs) -> a``: the deterministic rule (IDM, C-IDM, ...).
* ``transition_sample(key, params, state, inputs) -> next_state``: one stochastic step.
* ``transition_logpdf(params, state, next_state, inputs) -> log p``: the exact one-step density
  of an observed next state (see :mod:`bayesdrive.drivers.execution_noise` for which quantity
  it scores).
* ``observation_logpdf(params, state, obs) -> log p``: the observation model. For the base models
  the state is observed exactly (a point mass); an observation model (measurement noise, video
  noise) replaces it.
* ``initial_sample(key, params, obs) -> state``: the first latent state given the first observation.
* ``inputs_at(series, j, history) -> inputs``: the model's own per-step inputs, read from step ``j``
  of one vehicle's :class:`Series` (the device form of the one series representation,
  :class:`~bayesdrive.data.views.FollowerArrays`); ``history`` is the number of past steps a model
  may read. Engines, the criticism and its rollouts get inputs only through it, so a model that
  reads the merge scene, the second vehicle ahead or its own past needs no engine to know.
* ``lift(params, state, inputs) -> state``: the model's full state at an exactly observed step
  (identity unless the state remembers more than position and speed, e.g. the last noise).
* ``filter(params, steps) -> (T,)``: for a model with a hidden state, the one-step predictive log
  densities of one vehicle's steps from a state filter; None when each step is scored on its own.
* ``filtered_start``: optional, for a model with a hidden state, how a forecast starts from the
  observed history (:class:`FilteredStart`: the filter's law of the hidden state before a step of
  one vehicle's series, and a draw of the full state from it).
* ``censored(state, next_state, inputs) -> bool``: optional, whether an observed step (the
  observed states, relative to the current step, and the model's inputs) may be scored by a class
  probability (a stop, a step at a physical limit), from the data alone. A model that declares it
  takes a keyword ``may_be_censored`` (a bool or a boolean scalar array, default True) in
  ``transition_logpdf`` and, where it has one, ``filter``: False promises that no step they score
  is censored, so they skip the class probabilities, whose normal log-CDFs cost more than the rest
  of the density. The likelihood tells them, for every model alike: a step-by-step density on
  each step (True only on a series' usable censored steps), a filter once per series
  (:func:`bayesdrive.inference.core.likelihood.step_logpdfs`). None: the densities are always called
  without the keyword. A model made by replacing ``transition_logpdf`` or ``filter`` must keep
  that keyword or clear ``censored``.

States are kept *relative to the current step*: engines pass ``x = 0`` and the observed increment
``dx = x[t+1] - x[t]`` (computed in float64 by the data layer), so float32 never subtracts two
positions of hundreds of metres.

A :class:`DriverModel` bundles those functions with the parameter names, defaults and the prior
(independent uniform priors on documented bounds, the same for every engine), and declares what
engines and the simulator need to know about it, so that none of them asks which model it holds
(by its name, a function's identity or a parameter's name):

* ``observation``: how its states are observed, :data:`EXACT` or the name of its observation model;
* ``scene``: the scene part of the series it needs beyond car following (``"merge"``), or None;
* ``noise_sd``: the sd of its white Gaussian execution noise at a state of position and speed
  alone, or None where its step is another law (a memory, a hidden state);
* on its :class:`ParamSpec`\ s, ``execution_noise`` marks the parameter that scales that noise
  and ``desired_speed`` the desired speed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import AheadArrays, FollowerArrays, MergeArrays

__all__ = [
    "EXACT",
    "CarFollowingInputs",
    "DriverModel",
    "EgoState",
    "FilteredStart",
    "ParamSpec",
    "PriorBox",
    "Series",
    "car_following_at",
    "car_following_part",
    "device_series",
    "fill_params",
    "observed_lift",
    "parameter_noise_sd",
    "params_type",
]

# ``DriverModel.observation`` of a model whose states are observed exactly.
EXACT = "exact"


class EgoState(NamedTuple):
    """Longitudinal state of one vehicle: position x (m, relative to the current step) and speed v."""

    x: Array
    v: Array


class CarFollowingInputs(NamedTuple):
    """Exogenous inputs at one step, read from the leader's *observed* trajectory.

    gap: bumper-to-bumper gap to the leader at the current step (m); ignored without a leader.
    lead_v: the leader's speed (m/s).
    has_leader: 1.0 with a leader, 0.0 on free road (float so it vmaps and differentiates cleanly).
    dt: step length (s).
    """

    gap: Array
    lead_v: Array
    has_leader: Array
    dt: Array


class Series(NamedTuple):
    """The one series (:class:`~bayesdrive.data.views.FollowerArrays`) as JAX arrays, what
    ``inputs_at`` reads: fields (vehicle, step), or (step,) for one vehicle; ``dt`` is broadcast
    to the same shape, the scene parts carry their own trailing axes (None where absent)."""

    v: Array
    next_v: Array
    dx: Array
    gap: Array
    lead_v: Array
    has_leader: Array
    mask: Array
    dt: Array
    merge: MergeArrays | None = None
    ahead: AheadArrays | None = None


def device_series(arrays: FollowerArrays, dtype: Any = float) -> Series:
    """``arrays`` cast to JAX arrays of ``dtype`` (the default float type unless given)."""

    def cast(values) -> Array:
        return jnp.asarray(values, dtype=dtype)

    def part(values):
        return None if values is None else type(values)(*map(cast, values))

    return Series(
        v=cast(arrays.v),
        next_v=cast(arrays.next_v),
        dx=cast(arrays.dx),
        gap=cast(arrays.gap),
        lead_v=cast(arrays.lead_v),
        has_leader=cast(arrays.has_leader),
        mask=cast(arrays.mask),
        dt=cast(np.full(arrays.mask.shape, arrays.dt)),  # filled on the host: no program per shape
        merge=part(arrays.merge),
        ahead=part(arrays.ahead),
    )


def car_following_part(inputs: Any) -> CarFollowingInputs:
    """The car-following part of a model's richer inputs (any with gap, lead_v, has_leader, dt):
    what a base model reads of them. Inputs types expose it as their ``car_following``."""
    return CarFollowingInputs(inputs.gap, inputs.lead_v, inputs.has_leader, inputs.dt)


def car_following_at(series: Series, j: Array, history: int) -> CarFollowingInputs:
    """The base models' inputs: step ``j``'s gap, leader speed and leader flag."""
    del history
    return CarFollowingInputs(series.gap[j], series.lead_v[j], series.has_leader[j], series.dt[j])


def observed_lift(params: Any, state: EgoState, inputs: Any) -> EgoState:
    """The observed state is the whole state (no extra state to recover)."""
    del params, inputs
    return state


class ParamSpec(NamedTuple):
    """One parameter: name, unit, default, prior bounds (uniform prior), and what it means.

    What engines need to know about a parameter is said here, so no engine names one:
    ``grid_step`` is the step of the ``pf`` engine's grid (in the parameter's unit; None: the
    caller must pass one), ``execution_noise`` marks the sd of the Gaussian execution noise
    (``lm`` estimates it from its residuals instead of fitting it), and ``desired_speed`` the
    desired speed on free road (scene generation starts platoons below it and sweeps it).
    """

    name: str
    unit: str
    default: float
    lower: float
    upper: float
    doc: str
    grid_step: float | None = None
    execution_noise: bool = False
    desired_speed: bool = False


def params_type(type_name: str, specs: Sequence[ParamSpec]) -> type:
    """A parameter NamedTuple with one field per spec, in order (the docstring lists units)."""
    cls = NamedTuple(type_name, [(s.name, Array) for s in specs])
    cls.__doc__ = f"{type_name}: " + ", ".join(f"{s.name} ({s.unit}): {s.doc}" for s in specs)
    return cls


class PriorBox(NamedTuple):
    """Independent uniform priors on [lower, upper] for a chosen subset of parameters."""

    names: tuple[str, ...]
    lower: Array
    upper: Array

    def logpdf(self, theta: Array) -> Array:
        inside = jnp.all((theta >= self.lower) & (theta <= self.upper))
        return jnp.where(inside, -jnp.sum(jnp.log(self.upper - self.lower)), -jnp.inf)

    def sample(self, key: Array, shape: Sequence[int] = ()) -> Array:
        return jax.random.uniform(
            key, (*shape, len(self.names)), minval=self.lower, maxval=self.upper
        )


class FilteredStart(NamedTuple):
    """How a forecast of a model with a hidden state starts from observed data.

    ``law(params, series, until) -> law``: the hidden state's law at step ``until`` of one
    vehicle's :class:`Series` (fields (T,)), from the model's state filter run over the usable
    steps before it (any pytree). ``draw(key, params, state, law) -> state``: the full state at the
    observed ``state`` (position and speed), its hidden part drawn from ``law``.
    """

    law: Callable[[Any, Series, Array], Any]
    draw: Callable[[Array, Any, EgoState, Any], Any]


class DriverModel(NamedTuple):
    """A driver model: parameter layout, prior and the pure per-vehicle functions.

    ``reads_history``: its density reads the steps before the scored one (a delay, a memory of the
    last noise), so engines score only steps with a full history of usable steps behind them.
    ``observation``, ``scene`` and ``noise_sd`` are its declarations (module docstring).
    """

    name: str
    params_type: type
    specs: tuple[ParamSpec, ...]
    mean_acceleration: Callable[..., Array]
    transition_sample: Callable[..., Any]
    transition_logpdf: Callable[..., Array]
    observation_logpdf: Callable[..., Array]
    initial_sample: Callable[..., Any]
    inputs_at: Callable[[Series, Array, int], Any] = car_following_at
    lift: Callable[[Any, EgoState, Any], Any] = observed_lift
    filter: Callable[[Any, Any], Array] | None = None
    filtered_start: FilteredStart | None = None
    reads_history: bool = False
    censored: Callable[[EgoState, EgoState, Any], Array] | None = None
    observation: str = EXACT
    scene: str | None = None
    noise_sd: Callable[[Any, Any], Array] | None = None

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @property
    def observed_exactly(self) -> bool:
        """Whether its states are observed exactly (no observation model)."""
        return self.observation == EXACT

    def _marked(self, flag: str, meaning: str) -> str | None:
        marked = [s.name for s in self.specs if getattr(s, flag)]
        if len(marked) > 1:
            raise ValueError(f"model {self.name!r} marks several {meaning}s: {marked}")
        return marked[0] if marked else None

    @property
    def execution_noise_param(self) -> str | None:
        """The name of the execution-noise sd parameter (None if the model marks none)."""
        return self._marked("execution_noise", "execution-noise sd")

    @property
    def desired_speed_param(self) -> str | None:
        """The name of the desired-speed parameter (None if the model marks none)."""
        return self._marked("desired_speed", "desired speed")

    def spec(self, name: str) -> ParamSpec:
        for s in self.specs:
            if s.name == name:
                return s
        raise KeyError(f"model {self.name!r} has no parameter {name!r}; it has {self.param_names}")

    def defaults(self) -> Any:
        return self.params_type(*(jnp.asarray(s.default) for s in self.specs))

    def prior(self, names: Sequence[str] | None = None) -> PriorBox:
        chosen = tuple(names) if names is not None else self.param_names
        specs = [self.spec(n) for n in chosen]
        return PriorBox(
            chosen,
            jnp.asarray([s.lower for s in specs]),
            jnp.asarray([s.upper for s in specs]),
        )


def parameter_noise_sd(specs: Sequence[ParamSpec]) -> Callable[[Any, Any], Array]:
    """The ``noise_sd`` of a model whose execution-noise sd is the parameter its ``specs`` mark
    (``ParamSpec.execution_noise``), whatever the state; a ValueError if none or several."""
    marked = [s.name for s in specs if s.execution_noise]
    if len(marked) != 1:
        raise ValueError(f"one parameter must be marked execution_noise=True, got {marked}")
    (name,) = marked

    def noise_sd(params: Any, state: Any) -> Array:
        del state
        return getattr(params, name)

    return noise_sd


def fill_params(model: DriverModel, names: Sequence[str], theta: Array, fixed: Any = None) -> Any:
    """Parameters with ``names`` taken from the vector ``theta`` and the rest from ``fixed``.

    ``fixed`` defaults to the model's documented defaults. Works under ``jit``/``vmap``/``grad``.
    """
    base = model.defaults() if fixed is None else fixed
    position = {n: i for i, n in enumerate(names)}
    unknown = set(names) - set(model.param_names)
    if unknown:
        raise KeyError(f"model {model.name!r} has no parameter(s) {sorted(unknown)}")
    return model.params_type(
        *(theta[..., position[n]] if n in position else getattr(base, n) for n in model.param_names)
    )
