r"""The black-box baseline: a small MLP driving policy trained by behavioural cloning.

It stands in for the paper's GAIL policy (a neural policy with no traffic rule built in): the
same role in the comparison, not the same training method. Features are the ego speed v, the
bumper gap d and the relative speed :math:`v_l - v` (standardised with the training mean and sd);
two tanh hidden layers output a Gaussian acceleration, mean :math:`\mu` and sd
:math:`s \in (0.02, 2)` m/s^2 (the IDM's sigma bounds, through a sigmoid). The step is the IDM's
stochastic step with :math:`(\mu, s)` in place of :math:`(a_{IDM}, \sigma)`
(:func:`~bayesdrive.drivers.execution_noise.noisy_step`,
:func:`~bayesdrive.drivers.execution_noise.step_logpdf`), so the
policy is trained by maximising exactly the one-step likelihood the IDM engines use, on every
usable car-following step of the *fitting* windows, with a small Adam written here (optax is
not a dependency). It is only defined with a leader (the training steps all have one).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState
from bayesdrive.drivers.execution_noise import (
    acceleration_ceiling,
    exact_initial_sample,
    exact_observation_logpdf,
    noisy_step,
    step_logpdf,
)

__all__ = [
    "FEATURES",
    "MLP",
    "BlackboxParams",
    "TrainConfig",
    "TrainResult",
    "blackbox_model",
    "mlp_outputs",
    "train_blackbox",
]

FEATURES = ("v", "gap", "lead_v - v")
SD_MIN, SD_MAX = 0.02, 2.0


class MLP(NamedTuple):
    """Weights of the policy network and the feature standardisation it was trained with."""

    weights: tuple[Array, ...]
    biases: tuple[Array, ...]
    feature_mean: Array
    feature_scale: Array


class BlackboxParams(NamedTuple):
    """The black box has no per-vehicle parameters: one network drives every vehicle."""


class TrainConfig(NamedTuple):
    """Behavioural-cloning settings: hidden widths, Adam steps, minibatch size, learning rate."""

    hidden: tuple[int, ...] = (32, 32)
    steps: int = 3000
    batch_size: int = 2048
    learning_rate: float = 3e-3


class TrainResult(NamedTuple):
    """The trained network and the mean training loss (negative log-likelihood per step) per
    Adam step."""

    net: MLP
    losses: np.ndarray


def _features(v: Array, gap: Array, lead_v: Array) -> Array:
    return jnp.stack([v, gap, lead_v - v], axis=-1)


def mlp_outputs(net: MLP, v: Array, gap: Array, lead_v: Array) -> tuple[Array, Array]:
    """Mean acceleration and its sd (m/s^2) the policy gives for ego speed, gap and leader speed."""
    hidden = (_features(v, gap, lead_v) - net.feature_mean) / net.feature_scale
    for w, b in zip(net.weights[:-1], net.biases[:-1], strict=True):
        hidden = jnp.tanh(hidden @ w + b)
    out = hidden @ net.weights[-1] + net.biases[-1]
    sd = SD_MIN + (SD_MAX - SD_MIN) * jax.nn.sigmoid(out[..., 1])
    return out[..., 0], sd


def blackbox_model(net: MLP) -> DriverModel:
    """The trained network as a :class:`DriverModel` (no parameters: see :class:`BlackboxParams`)."""

    def mean_acceleration(params, state: EgoState, inputs: CarFollowingInputs) -> Array:
        del params
        return mlp_outputs(net, state.v, inputs.gap, inputs.lead_v)[0]

    def transition_sample(key, params, state: EgoState, inputs: CarFollowingInputs) -> EgoState:
        del params
        mean, sd = mlp_outputs(net, state.v, inputs.gap, inputs.lead_v)
        return noisy_step(key, state, mean, sd, inputs.dt, acceleration_ceiling(state.v, inputs))

    def transition_logpdf(params, state, next_state, inputs: CarFollowingInputs) -> Array:
        del params
        mean, sd = mlp_outputs(net, state.v, inputs.gap, inputs.lead_v)
        ceiling = acceleration_ceiling(state.v, inputs)
        return step_logpdf(state, next_state, mean, sd, inputs.dt, ceiling)

    return DriverModel(
        name="blackbox",
        params_type=BlackboxParams,
        specs=(),
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=exact_observation_logpdf,
        initial_sample=exact_initial_sample,
    )


class _AdamState(NamedTuple):
    step: Array
    first: tuple
    second: tuple


def _adam_update(
    grads: tuple, state: _AdamState, learning_rate: float, b1=0.9, b2=0.999, eps=1e-8
) -> tuple[tuple, _AdamState]:
    """One Adam step (Kingma & Ba 2015): the parameter updates and the new moment estimates."""
    step = state.step + 1
    first = jax.tree.map(lambda m, g: b1 * m + (1 - b1) * g, state.first, grads)
    second = jax.tree.map(lambda s, g: b2 * s + (1 - b2) * g**2, state.second, grads)
    scale = learning_rate * jnp.sqrt(1 - b2**step) / (1 - b1**step)
    updates = jax.tree.map(lambda m, s: -scale * m / (jnp.sqrt(s) + eps), first, second)
    return updates, _AdamState(step, first, second)


def _usable_steps(arrays: FollowerArrays) -> dict[str, np.ndarray]:
    usable = arrays.mask > 0
    if not usable.any():
        raise ValueError("no usable steps to train the black-box policy on")
    return {
        name: getattr(arrays, name)[usable].astype(np.float32)
        for name in ("v", "next_v", "dx", "gap", "lead_v")
    }


def _init_net(key: Array, hidden: tuple[int, ...], rows: dict[str, np.ndarray]) -> MLP:
    features = np.stack([rows["v"], rows["gap"], rows["lead_v"] - rows["v"]], axis=-1)
    widths = (len(FEATURES), *hidden, 2)
    keys = jax.random.split(key, len(widths) - 1)
    weights = tuple(
        jax.random.normal(k, (n_in, n_out)) / np.sqrt(n_in)
        for k, n_in, n_out in zip(keys, widths[:-1], widths[1:], strict=True)
    )
    return MLP(
        weights=weights,
        biases=tuple(jnp.zeros(n) for n in widths[1:]),
        feature_mean=jnp.asarray(features.mean(axis=0)),
        feature_scale=jnp.asarray(features.std(axis=0) + 1e-6),
    )


class _Rows(NamedTuple):
    v: Array
    next_v: Array
    dx: Array
    gap: Array
    lead_v: Array


def _negative_loglik(net: MLP, rows: _Rows, dt: Array) -> Array:
    state = EgoState(x=jnp.zeros_like(rows.v), v=rows.v)
    next_state = EgoState(x=rows.dx, v=rows.next_v)
    inputs = CarFollowingInputs(rows.gap, rows.lead_v, jnp.ones_like(rows.v), dt)
    logpdf = blackbox_model(net).transition_logpdf(BlackboxParams(), state, next_state, inputs)
    return -jnp.mean(logpdf)


@partial(jax.jit, static_argnames=("config",))
def _adam_fit(
    net: MLP, rows: _Rows, dt: Array, batch_keys: Array, config: TrainConfig
) -> tuple[MLP, Array]:
    def loss(layers: tuple, index: Array) -> Array:
        # Only weights and biases are trained; the standardisation stays at the data's values.
        trainable = net._replace(weights=layers[0], biases=layers[1])
        return _negative_loglik(trainable, jax.tree.map(lambda a: a[index], rows), dt)

    def step(carry, batch_key):
        layers, adam = carry
        index = jax.random.randint(batch_key, (config.batch_size,), 0, rows.v.shape[0])
        value, grads = jax.value_and_grad(loss)(layers, index)
        updates, adam = _adam_update(grads, adam, config.learning_rate)
        return (jax.tree.map(jnp.add, layers, updates), adam), value

    layers = (net.weights, net.biases)
    zeros = jax.tree.map(jnp.zeros_like, layers)
    start = (layers, _AdamState(jnp.zeros((), jnp.int32), zeros, zeros))
    (trained, _), losses = jax.lax.scan(step, start, batch_keys)
    return net._replace(weights=trained[0], biases=trained[1]), losses


def train_blackbox(key: Array, arrays: FollowerArrays, config: TrainConfig) -> TrainResult:
    """Fit the policy by maximum likelihood on every usable step of ``arrays`` (use the fitting
    window) with minibatch Adam (minibatches drawn with replacement); the same key gives the same
    network."""
    key_init, key_batches = jax.random.split(key)
    rows = _usable_steps(arrays)
    net = _init_net(key_init, config.hidden, rows)
    trained, losses = _adam_fit(
        net,
        _Rows(**{name: jnp.asarray(values) for name, values in rows.items()}),
        jnp.float32(arrays.dt),
        jax.random.split(key_batches, config.steps),
        config,
    )
    return TrainResult(trained, np.asarray(losses))
