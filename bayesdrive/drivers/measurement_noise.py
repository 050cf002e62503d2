r"""Gaussian measurement noise on recorded positions, composed with any driver model: one model
(``<base>+measurement_noise``, the cause of the same name) for both of its uses.

The true front-bumper position :math:`x_t` is hidden and the data hold a noisy reading of it,

.. math::

    y_t = x_t + \varepsilon_t, \qquad \varepsilon_t \sim \mathcal N(0, \sigma_{obs}^2)
    \ \text{independent over time},

while the dynamics stay the base model's (same transition sampler and density, same inputs).

=========  ====  =======  ============  =============================================
name       unit  default  prior bounds  meaning
=========  ====  =======  ============  =============================================
sigma_obs  m     0.0      [0, 0.5]      sd of the Gaussian position-measurement noise
=========  ====  =======  ============  =============================================

The default 0 is the base model exactly, so the base is nested (the criticism compares the two).

**Use 1: speeds recorded exactly** (GNSS positions beside Doppler speeds and radar gaps; the
criticism's cause). Then the true increment of a step is known once the next speed is recorded
(:math:`\Delta x_t = (v_t + v_{t+1})\Delta t/2`, the base models' kinematics), so each step
reveals the noise difference :math:`d_t = \varepsilon_{t+1} - \varepsilon_t`, and the noise itself
is a hidden scalar with an exact Gaussian filter (the model's ``filter``):
:math:`\varepsilon_t \mid \text{past} \sim N(m_t, P_t)`, starting from :math:`N(0, \sigma_{obs}^2)`
at the first step of a stretch of data (a gap in the data restarts it). The predictive density of
the recorded increment is

.. math::

    y_{t+1} - y_t \sim N\big(v_t\Delta t + a_{base}\Delta t^2/2 - m_t,\ (\sigma\Delta t^2/2)^2
    + \sigma_{obs}^2 + P_t\big),

and afterwards :math:`m_{t+1} = (m_t + d_t)\sigma_{obs}^2/(\sigma_{obs}^2 + P_t)`,
:math:`P_{t+1} = \sigma_{obs}^2 P_t/(\sigma_{obs}^2 + P_t)`. A step that ends in a stop is scored
by the base model's stop probability. Engines that score whole series (nuts, emcee) and the
criticism use this filter.

**Use 2: speeds not trusted** (the latent-state engine, pmmh). Only positions are observations
(``observation_logpdf``): in both data sets the position is, up to noise, the integrated recorded
speed, so scoring both would count the same information twice; the recorded speed enters once, as
the initial latent speed where a filtered segment starts. With a flat prior on the first true
position, its distribution given the first reading is :math:`x_0 \sim \mathcal N(y_0,
\sigma_{obs}^2)` (``initial_sample``); the likelihood a latent-state engine estimates is
:math:`p(y_{1:T} \mid y_0, v_0)`. It needs :math:`\sigma_{obs} > 0`.

**Frame of reference.** As everywhere in the package, states are relative to a local origin: the
latent position is carried as its offset from the *observed* position of the same step, so the
observation of every step is ``x = 0`` on its own axis and every float32 number is centimetres to
metres. Distances from the ego's front bumper forward in the inputs -- the bumper gap to the
leader, the Cooperative IDM's distance to the merge point -- are measured from the observed
position; :func:`shift_ego` moves them to a latent ego ahead of it by an offset, so the gap a
latent state sees is ``leader rear - latent x``. The leader's own reading is taken as exact.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec, observed_lift
from bayesdrive.drivers.execution_noise import (
    STOP_SPEED,
    acceleration_ceiling,
    increment_law,
    step_logpdf,
)

__all__ = [
    "CAUSE",
    "EGO_DISTANCE_FIELDS",
    "OLD_NAME_SUFFIX",
    "SIGMA_OBS",
    "shift_ego",
    "with_measurement_noise",
]

CAUSE = "measurement_noise"
# Results written before the two measurement-noise models became one carry this model suffix.
OLD_NAME_SUFFIX = "obs_noise"
SIGMA_OBS = ParamSpec(
    "sigma_obs", "m", 0.0, 0.0, 0.5, "position-measurement noise sd", grid_step=0.025
)

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


def _noise_filter(
    base: DriverModel, base_params, params, steps: Any, *, may_be_censored: bool | Array = True
) -> Array:
    """One-step predictive log densities of one vehicle's steps (T,) with speeds recorded exactly
    (module docstring, use 1); ``may_be_censored=False`` promises that no step ends in a stop.

    The recursion has a closed form, so it is vectorised over steps instead of scanned: in a
    stretch of data, at its k-th step (k = 0 first), P = s^2/(k + 1) and (k + 1) m = sum over the
    stretch's earlier steps i of (k_i + 1) d_i.
    """
    own = base_params(params)
    dt = steps.inputs.dt[0]
    noise_var = params.sigma_obs**2
    index = jnp.arange(steps.v.shape[0])
    usable = steps.mask > 0
    starts = usable & ~jnp.concatenate([jnp.zeros(1, bool), usable[:-1]])
    first = jax.lax.cummax(jnp.where(starts, index, 0))
    rank = (index - first).astype(steps.v.dtype)  # k: steps since the stretch began
    difference = steps.dx - 0.5 * (steps.v + steps.next_v) * dt  # d = e[t+1] - e[t]
    weighted = jnp.where(usable, (rank + 1.0) * difference, 0.0)
    before = jnp.cumsum(weighted) - weighted  # sum over earlier steps, exclusive
    # With s = 0 the noise is identically 0: the base model exactly.
    mean = jnp.where(noise_var > 0, (before - before[first]) / (rank + 1.0), 0.0)
    var = noise_var / (rank + 1.0)

    def one(inputs, v, next_v, dx, mean, var):
        state = EgoState(jnp.zeros_like(v), v)
        rule = base.mean_acceleration(own, state, inputs)
        sigma = base.noise_sd(own, state)
        law = increment_law(v, rule, sigma, dt)
        moving = norm.logpdf(dx, law.mean - mean, jnp.sqrt(law.sd**2 + noise_var + var))
        ceiling = acceleration_ceiling(v, inputs)
        stopped = step_logpdf(
            state, EgoState(dx, next_v), rule, sigma, dt, ceiling, may_be_censored=may_be_censored
        )
        return jnp.where(next_v <= STOP_SPEED, stopped, moving)

    return jax.vmap(one)(steps.inputs, steps.v, steps.next_v, steps.dx, mean, var)


@functools.cache
def with_measurement_noise(model: DriverModel) -> DriverModel:
    """``model`` observed through Gaussian position noise (module docstring for the math).

    The result's parameters are the base model's fields followed by ``sigma_obs``; its transition
    functions and inputs are the base model's; its ``filter`` scores data whose speeds are exact,
    its observation density :math:`\\mathcal N(obs.x;\\ state.x,\\ \\sigma_{obs}^2)` and initial
    state around the first reading serve the latent-state engine. Cached: wrapping the same model
    twice returns the same object, so compiled engines are reused.
    """
    if SIGMA_OBS.name in model.param_names:
        raise ValueError(
            f"model {model.name!r} already has a {SIGMA_OBS.name!r} parameter; "
            "measurement noise is added once"
        )
    if not model.observed_exactly or model.noise_sd is None or model.filter is not None:
        raise ValueError(
            f"measurement noise needs an exactly observed model with white Gaussian execution "
            f"noise on position and speed alone; {model.name!r} keeps, filters or observes more"
        )
    specs = (*model.specs, SIGMA_OBS)
    base_type = model.params_type
    params_type = NamedTuple(
        f"{base_type.__name__}WithNoise", [(spec.name, Array) for spec in specs]
    )
    params_type.__module__ = __name__
    params_type.__doc__ = (
        f"{base_type.__name__} plus sigma_obs (m), the sd of Gaussian noise on recorded positions."
    )

    def base(params) -> Any:
        return base_type(*(getattr(params, name) for name in model.param_names))

    def mean_acceleration(params, state: EgoState, inputs) -> Array:
        return model.mean_acceleration(base(params), state, inputs)

    def transition_sample(key: Array, params, state: EgoState, inputs) -> Any:
        return model.transition_sample(key, base(params), state, inputs)

    def transition_logpdf(params, state: EgoState, next_state: EgoState, inputs, **censoring):
        return model.transition_logpdf(base(params), state, next_state, inputs, **censoring)

    censored = None
    if model.censored is not None:

        def censored(state: EgoState, next_state: EgoState, inputs) -> Array:
            # The filter scores a stop by its class probability, whatever the base declares.
            stopped = next_state.v <= STOP_SPEED
            return stopped | model.censored(state, next_state, inputs)

    def observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
        # Positions only: the recorded speed is no observation (module docstring).
        return norm.logpdf(obs.x, state.x, params.sigma_obs)

    def initial_sample(key: Array, params, obs: EgoState) -> EgoState:
        noise = params.sigma_obs * jax.random.normal(key, jnp.shape(obs.x))
        return EgoState(x=obs.x + noise, v=jnp.broadcast_to(obs.v, jnp.shape(noise)))

    return DriverModel(
        name=f"{model.name}+{CAUSE}",
        params_type=params_type,
        specs=specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=observation_logpdf,
        initial_sample=initial_sample,
        inputs_at=model.inputs_at,
        lift=observed_lift,
        filter=functools.partial(_noise_filter, model, base),
        censored=censored,
        observation=CAUSE,
        scene=model.scene,
        noise_sd=lambda params, state: model.noise_sd(base(params), state),
    )
