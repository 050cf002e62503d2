r"""The Intelligent Driver Model (Treiber, Hennecke & Helbing 2000) with Gaussian execution noise.

Deterministic rule, for ego speed :math:`v`, leader speed :math:`v_l`, bumper gap :math:`d` and
relative speed :math:`r = v_l - v` (a closing leader has :math:`r < 0`):

.. math::

    a_{IDM} = a_{max}\Big[1 - (v / v_{des})^{\delta} - (d_{des} / d)^2\Big], \qquad
    d_{des} = d_{min} + \max\Big(0,\; \tau v - \frac{v\, r}{2\sqrt{a_{max} b_{pref}}}\Big),

with :math:`\delta = 4`. On free road (no leader) the interaction term is absent. The dynamic part
of :math:`d_{des}` is floored at 0 as in Treiber's formulation, so a fast-receding leader never
pulls the ego closer than :math:`d_{min}`.

Stochastic IDM (the paper's execution noise, sigma = its :math:`\sigma_{IDM}`): over one step of
length :math:`\Delta t`,

.. math::

    a \sim \mathcal N(a_{IDM}, \sigma^2), \quad v' = \max(0, v + a\Delta t), \quad
    x' = x + \tfrac{1}{2}(v + v')\Delta t.

While the speed stays positive, :math:`x' = x + v\Delta t + a\Delta t^2/2`, so the position has sd
:math:`\sigma\Delta t^2/2` (the paper's own code used :math:`\sigma\Delta t^2`, a factor 2 off).

**What the likelihood scores.** Next position and next speed are both functions of the one random
acceleration, so their joint density is degenerate (a line in the plane). We score the next
*position increment* :math:`x' - x` (as the paper does), with density
:math:`\mathcal N(v\Delta t + a_{IDM}\Delta t^2/2,\ (\sigma\Delta t^2/2)^2)`; the observed next speed
becomes the conditioning state of the following step, and it decides censoring: an observed stop
(:math:`v' \le v_{stop}` = ``STOP_SPEED``, real data holds exact stops and smoothing leaves
values like 1e-5) has probability
:math:`P(v' \le v_{stop}) = \Phi((v_{stop} - v - a_{IDM}\Delta t)/(\sigma\Delta t))`, and then the
position carries no further information. Censoring at the same threshold that classifies a stop
keeps the density normalised: stop mass plus the Gaussian over the increments of the moving
outcomes (:math:`v' > v_{stop}`) is exactly 1. In the NGSIM chains the position is exactly the
trapezoid-integrated speed and OpenACC positions are the integrated Doppler speed (see the
readers), so scoring position or speed uses the same information there. Increments are relative
to the current state, so float32 never loses the density on positions of hundreds of metres.

Parameters, units, bounds of the uniform priors (the same for every engine) and defaults
(Treiber's textbook values where the paper lists them):

=========  =======  =======  ============  ==============================================
name       unit     default  prior bounds  meaning
=========  =======  =======  ============  ==============================================
v_des      m/s      30.0     [5, 45]       desired speed on free road
d_min      m        2.0      [0.5, 10]     jam distance (minimum bumper gap at standstill)
tau        s        1.0      [0.1, 4]      safe time headway
a_max      m/s^2    3.0      [0.2, 5]      maximum acceleration
b_pref     m/s^2    2.0      [0.5, 10]     comfortable (preferred) deceleration
sigma      m/s^2    0.3      [0.02, 2]     sd of the Gaussian execution noise
=========  =======  =======  ============  ==============================================
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import (
    CarFollowingInputs,
    DriverModel,
    EgoState,
    ParamSpec,
    car_following_at,
)

__all__ = [
    "DELTA",
    "IDM",
    "STOP_SPEED",
    "IDMParams",
    "IncrementLaw",
    "equilibrium_gap",
    "execution_noise_model",
    "execution_noise_sd",
    "idm_acceleration",
    "increment_law",
    "noisy_step",
    "step_logpdf",
]

# An integer, so powers of it compile to multiplications: a float exponent is exp(4 log x),
# which made the likelihood about 6x slower.
DELTA = 4
# Speeds below 1 mm/s are a stop: smoothing leaves values like 1e-5 where the car stands still.
STOP_SPEED = 1e-3
# The interaction term diverges at zero gap; the simulator counts a collision long before.
MIN_GAP = 0.1

# pf grid steps: v_des and sigma are the paper's; the others are about 1-5% of the prior width,
# fine against what one 20 s trajectory can resolve.
IDM_SPECS = (
    ParamSpec("v_des", "m/s", 30.0, 5.0, 45.0, "desired speed", grid_step=0.5),
    ParamSpec("d_min", "m", 2.0, 0.5, 10.0, "jam distance", grid_step=0.5),
    ParamSpec("tau", "s", 1.0, 0.1, 4.0, "safe time headway", grid_step=0.1),
    ParamSpec("a_max", "m/s^2", 3.0, 0.2, 5.0, "maximum acceleration", grid_step=0.1),
    ParamSpec("b_pref", "m/s^2", 2.0, 0.5, 10.0, "comfortable deceleration", grid_step=0.5),
    ParamSpec(
        "sigma", "m/s^2", 0.3, 0.02, 2.0, "execution-noise sd", grid_step=0.1, execution_noise=True
    ),
)


class IDMParams(NamedTuple):
    r"""Stochastic IDM: :math:`a \sim N(a_{IDM}(v, d, r), \sigma^2)` (module docstring for the rule).

    v_des (m/s), d_min (m), tau (s), a_max (m/s^2), b_pref (m/s^2), sigma (m/s^2).
    """

    v_des: Array
    d_min: Array
    tau: Array
    a_max: Array
    b_pref: Array
    sigma: Array


def idm_acceleration(params, v: Array, gap: Array, lead_v: Array, has_leader: Array) -> Array:
    """The deterministic IDM acceleration; ``params`` needs v_des, d_min, tau, a_max, b_pref."""
    free = 1.0 - (v / params.v_des) ** DELTA
    closing = v - lead_v  # = -r: positive while the ego gains on its leader
    dynamic = v * params.tau + v * closing / (2.0 * jnp.sqrt(params.a_max * params.b_pref))
    desired_gap = params.d_min + jnp.maximum(0.0, dynamic)
    # A safe gap of 1 where there is no leader keeps gradients finite; the term is masked anyway.
    safe_gap = jnp.maximum(jnp.where(has_leader > 0, gap, 1.0), MIN_GAP)
    interaction = jnp.where(has_leader > 0, (desired_gap / safe_gap) ** 2, 0.0)
    return params.a_max * (free - interaction)


def equilibrium_gap(params, v: Array) -> Array:
    """The bumper gap at which the IDM holds speed ``v`` behind a leader at the same speed:
    d_e = (d_min + tau v) / sqrt(1 - (v / v_des)^delta), for 0 <= v < v_des."""
    return (params.d_min + params.tau * v) / jnp.sqrt(1.0 - (v / params.v_des) ** DELTA)


def noisy_step(key: Array, state: EgoState, mean_acc: Array, sigma: Array, dt: Array) -> EgoState:
    """One step of Gaussian execution noise around ``mean_acc``, speed clipped at 0."""
    acc = mean_acc + sigma * jax.random.normal(key, jnp.shape(mean_acc))
    next_v = jnp.maximum(0.0, state.v + acc * dt)
    return EgoState(x=state.x + 0.5 * (state.v + next_v) * dt, v=next_v)


class IncrementLaw(NamedTuple):
    """The law of one step under :func:`noisy_step`, the one Gaussian increment density every
    density, filter and check uses: a moving step's position increment is N(``mean``, ``sd``^2);
    the step ends in a stop with probability Phi(``stop_z``)."""

    mean: Array
    sd: Array
    stop_z: Array


def increment_law(v: Array, mean_acc: Array, sigma: Array, dt: Array) -> IncrementLaw:
    """:class:`IncrementLaw` of a step from speed ``v`` with mean acceleration ``mean_acc`` and
    execution-noise sd ``sigma``."""
    return IncrementLaw(
        mean=v * dt + 0.5 * mean_acc * dt**2,
        sd=0.5 * sigma * dt**2,
        stop_z=(STOP_SPEED - v - mean_acc * dt) / (sigma * dt),
    )


def step_logpdf(
    state: EgoState,
    next_state: EgoState,
    mean_acc: Array,
    sigma: Array,
    dt: Array,
    *,
    may_stop: bool = True,
) -> Array:
    """Exact log-density of the observed next state under :func:`noisy_step` (module docstring).

    ``may_stop=False`` promises that the observed next speed is above ``STOP_SPEED``: the stop
    probability, whose normal log-CDF costs more than all the rest, is then not computed."""
    law = increment_law(state.v, mean_acc, sigma, dt)
    moving = norm.logpdf(next_state.x - state.x, law.mean, law.sd)
    if not may_stop:
        return moving
    stopped = norm.logcdf(law.stop_z)
    return jnp.where(next_state.v <= STOP_SPEED, stopped, moving)


def _mean_acceleration(params: IDMParams, state: EgoState, inputs: CarFollowingInputs) -> Array:
    return idm_acceleration(params, state.v, inputs.gap, inputs.lead_v, inputs.has_leader)


def exact_observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
    """The state is observed exactly: the observation carries no density of its own (log 1 = 0)."""
    del params, state, obs
    return jnp.zeros(())


def exact_initial_sample(key: Array, params, obs: EgoState) -> EgoState:
    """With exact observations the first state is the first observation."""
    del key, params
    return obs


def execution_noise_sd(params, state) -> Array:
    """The execution-noise sd of the base models: the parameter ``sigma``, whatever the state."""
    del state
    return params.sigma


def execution_noise_model(
    name: str,
    params_type: type,
    specs: tuple[ParamSpec, ...],
    mean_acceleration,
    noise_sd=execution_noise_sd,
    inputs_at=car_following_at,
) -> DriverModel:
    """A driver model that applies ``mean_acceleration`` with Gaussian execution noise of sd
    ``noise_sd(params, state)`` (:func:`noisy_step`, scored exactly by :func:`step_logpdf`), state
    observed exactly, reading the inputs ``inputs_at`` builds. The IDM, the Cooperative IDM and the
    criticism's Gaussian extensions differ only in their mean acceleration and inputs (and, for
    speed-dependent noise, the sd)."""

    def transition_sample(key: Array, params, state: EgoState, inputs) -> EgoState:
        mean_acc = mean_acceleration(params, state, inputs)
        return noisy_step(key, state, mean_acc, noise_sd(params, state), inputs.dt)

    def transition_logpdf(params, state: EgoState, next_state: EgoState, inputs) -> Array:
        mean_acc = mean_acceleration(params, state, inputs)
        return step_logpdf(state, next_state, mean_acc, noise_sd(params, state), inputs.dt)

    def series_logpdf(params, steps) -> Array:
        # Stops are rare (2 of 187 NGSIM I-80 followers have any), and the stop term's normal
        # log-CDF cost 60% of the density: a series without a stop skips it.
        def scored(may_stop: bool) -> Array:
            def one(v, next_v, dx, inputs):
                state = EgoState(jnp.zeros_like(v), v)
                mean_acc = mean_acceleration(params, state, inputs)
                sd = noise_sd(params, state)
                return step_logpdf(
                    state, EgoState(dx, next_v), mean_acc, sd, inputs.dt, may_stop=may_stop
                )

            return jax.vmap(one)(steps.v, steps.next_v, steps.dx, steps.inputs)

        any_stop = jnp.any(steps.next_v <= STOP_SPEED)
        return jax.lax.cond(any_stop, lambda: scored(True), lambda: scored(False))

    return DriverModel(
        name=name,
        params_type=params_type,
        specs=specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=exact_observation_logpdf,
        initial_sample=exact_initial_sample,
        inputs_at=inputs_at,
        series_logpdf=series_logpdf,
    )


IDM = execution_noise_model("idm", IDMParams, IDM_SPECS, _mean_acceleration)
