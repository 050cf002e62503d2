r"""Gaussian measurement noise on observed positions, composed with any driver model.

The base models observe the state exactly. Here the true front-bumper position :math:`x_t` is
hidden and the data hold a noisy reading of it,

.. math::

    y_t = x_t + \varepsilon_t, \qquad \varepsilon_t \sim \mathcal N(0, \sigma_{obs}^2)
    \ \text{independent over time},

while the dynamics stay the base model's (same transition sampler and density). The one new
parameter:

=========  ====  =======  ============  =============================================
name       unit  default  prior bounds  meaning
=========  ====  =======  ============  =============================================
sigma_obs  m     0.05     [0.005, 1]    sd of the Gaussian position-measurement noise
=========  ====  =======  ============  =============================================

**Only positions are observations.** Recorded speeds are not scored: in both data sets the position
is (up to noise) the integrated recorded speed, so scoring both would count the same information
twice. The recorded speed enters once, as the initial latent speed where a filtered segment starts.

**Initial state.** With a flat prior on the first true position, its distribution given the first
reading is :math:`x_0 \sim \mathcal N(y_0, \sigma_{obs}^2)`; the speed starts at the recorded speed
:math:`v_0`. The likelihood a latent-state engine then estimates is :math:`p(y_{1:T} \mid y_0, v_0)`.

**Frame of reference.** As everywhere in the package, states are relative to a local origin: the
latent position is carried as its offset from the *observed* position of the same step, so the
observation of every step is ``x = 0`` on its own axis, the filter only ever adds float64-computed
observed increments, and every float32 number is centimetres to metres (resolution ~1e-7 m), never
kilometres. (A fixed per-vehicle origin would also do for the observation density: float32 resolves
~1.2e-4 m at 1-2 km, 40 times finer than the smallest ``sigma_obs`` of 5 mm; but the per-step offset
costs nothing and keeps the resolution far below the execution noise's position sd
:math:`\sigma\Delta t^2/2` as well.) Distances from the ego's front bumper forward in the inputs --
the bumper gap to the leader, the Cooperative IDM's distance to the merge point -- are measured from
the observed position; :func:`shift_ego` moves them to a latent ego ahead of it by an offset, so
the gap a latent state sees is ``leader rear - latent x``, never a gap from the noisy reading. The
leader's own reading is taken as exact: its noise is not modelled.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec

__all__ = ["EGO_DISTANCE_FIELDS", "SIGMA_OBS", "shift_ego", "with_measurement_noise"]

SIGMA_OBS = ParamSpec("sigma_obs", "m", 0.05, 0.005, 1.0, "position-measurement noise sd")

# Input fields measured from the ego's front bumper forward (CarFollowingInputs, MergeInputs).
EGO_DISTANCE_FIELDS = ("gap", "ego_to_merge")


def shift_ego(inputs: Any, offset: Array) -> Any:
    """The inputs as seen by an ego ``offset`` metres ahead of the position they were measured from.

    Every field in :data:`EGO_DISTANCE_FIELDS` that ``inputs`` has shrinks by ``offset``; the rest
    (speeds, flags, dt, other vehicles' distances) is unchanged.
    """
    if not hasattr(inputs, "gap"):
        raise TypeError(
            f"inputs of type {type(inputs).__name__} have no 'gap' field; the measurement-noise "
            f"model needs car-following inputs whose distances it can shift"
        )
    shifted = {
        name: getattr(inputs, name) - offset
        for name in EGO_DISTANCE_FIELDS
        if hasattr(inputs, name)
    }
    return inputs._replace(**shifted)


@functools.cache
def with_measurement_noise(model: DriverModel) -> DriverModel:
    """``model`` observed through Gaussian position noise (module docstring for the math).

    The result's parameters are the base model's fields followed by ``sigma_obs``; its transition
    functions are the base model's, its observation density is
    :math:`\\mathcal N(obs.x;\\ state.x,\\ \\sigma_{obs}^2)` and its initial state is drawn around
    the first reading. Engines that condition on exact states must refuse it (they would ignore the
    noise); :mod:`bayesdrive.inference.latent` filters over the hidden states. Cached: wrapping the
    same model twice returns the same object, so compiled engines are reused.
    """
    if SIGMA_OBS.name in model.param_names:
        raise ValueError(
            f"model {model.name!r} already has a {SIGMA_OBS.name!r} parameter; "
            "measurement noise is added once"
        )
    base_type = model.params_type
    params_type = NamedTuple(
        f"{base_type.__name__}WithNoise",
        [(name, Array) for name in (*model.param_names, SIGMA_OBS.name)],
    )
    params_type.__module__ = __name__
    params_type.__doc__ = (
        f"{base_type.__name__} plus sigma_obs (m), the sd of Gaussian noise on observed positions."
    )

    def base(params) -> Any:
        return base_type(*(getattr(params, name) for name in model.param_names))

    def mean_acceleration(params, state: EgoState, inputs) -> Array:
        return model.mean_acceleration(base(params), state, inputs)

    def transition_sample(key: Array, params, state: EgoState, inputs) -> Any:
        return model.transition_sample(key, base(params), state, inputs)

    def transition_logpdf(params, state: EgoState, next_state: EgoState, inputs) -> Array:
        return model.transition_logpdf(base(params), state, next_state, inputs)

    def observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
        # Positions only: the recorded speed is no observation (module docstring).
        return norm.logpdf(obs.x, state.x, params.sigma_obs)

    def initial_sample(key: Array, params, obs: EgoState) -> EgoState:
        noise = params.sigma_obs * jax.random.normal(key, jnp.shape(obs.x))
        return EgoState(x=obs.x + noise, v=jnp.broadcast_to(obs.v, jnp.shape(noise)))

    return DriverModel(
        name=f"{model.name}+obs_noise",
        params_type=params_type,
        specs=(*model.specs, SIGMA_OBS),
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=observation_logpdf,
        initial_sample=initial_sample,
        inputs_at=model.inputs_at,
    )
