r"""Gaussian execution noise on the acceleration, within the vehicle's physical limits: the step law
the base models share.

For a model with mean acceleration :math:`\mu` (the IDM's, Gipps', ...) and execution-noise sd
:math:`\sigma` (the paper's :math:`\sigma_{IDM}`), over one step of length :math:`\Delta t`,

.. math::

    a = \min\big(\max(\mu + \sigma z,\ -b_{phys}),\ a_{ceil}\big), \quad z \sim N(0, 1), \quad
    v' = \max(0, v + a\Delta t), \quad x' = x + \tfrac{1}{2}(v + v')\Delta t.

**Physical limits** (constants, m/s^2): the applied acceleration never brakes harder than
:math:`b_{phys}` = ``MAX_BRAKING`` = 9 (tyre-road friction on dry asphalt, about 0.9 g: no car
brakes harder) and never exceeds ``MAX_ACCELERATION`` = 6 (a passenger car's traction and engine
limit at traffic speeds). A driver who asks for more gets the limit: the noise is *censored*
there, as a pedal pressed to the floor is.

**Collision-free by construction.** Behind a leader the ceiling :math:`a_{ceil}`
(:func:`acceleration_ceiling`) is also the largest acceleration that keeps Gipps' safe-distance
condition: were the leader to brake at :math:`b_{phys}` to a stop from now on, the follower,
braking at :math:`b_{phys}` after this step, would still stop ``SAFETY_GAP`` = 0.1 m behind it,

.. math::

    \tfrac{1}{2}(v + v')\Delta t + \frac{v'^2}{2 b_{phys}} + \tfrac{1}{2} v'\Delta t
    \le s - s_{safe} + \frac{v_l^2}{2 b_{phys}}

(this step's travel plus an upper bound of the discrete stop from :math:`v'`, against a lower
bound of the leader's stop), and that the gap at the end of this step is at least
:math:`s_{safe}` if the leader brakes at :math:`b_{phys}` through it. A state that meets the
condition keeps it when the follower brakes at the limit, so the ceiling is then never below the
floor: from such a state (every equilibrium of car following is one), behind leaders that brake no
harder than :math:`b_{phys}`, no step ever ends in a collision, whatever the noise or the mean
rule (a reaction delay included). The rule applies to the applied acceleration, the deterministic
rule's share included; drivers keep it in normal driving (in recorded data it binds on
near-collision artefacts of the trajectory reconstruction). Where no acceleration above
:math:`-b_{phys}` satisfies it, the ceiling is the floor (plus two ``LIMIT_TOLERANCE``, so the two
limits stay apart): the car brakes as hard as it can.

While the speed stays positive, :math:`x' = x + v\Delta t + a\Delta t^2/2`, so inside the limits
the position has sd :math:`\sigma\Delta t^2/2` (the paper's own code used
:math:`\sigma\Delta t^2`, a factor 2 off).

**What the likelihood scores.** Next position and next speed are both functions of the one random
acceleration, so their joint density is degenerate (a line in the plane). We score the next
*position increment* :math:`x' - x` (as the paper does), with density
:math:`\mathcal N(v\Delta t + \mu\Delta t^2/2,\ (\sigma\Delta t^2/2)^2)` where the implied
acceleration :math:`\hat a = 2(x' - x - v\Delta t)/\Delta t^2` lies strictly inside the limits;
the observed next speed becomes the conditioning state of the following step, and it decides
censoring. Each censored outcome is a class scored by its probability under the raw normal
acceleration, so the law is normalised exactly (stop mass, limit masses and the density over the
moving outcomes inside the limits sum to 1):

* an observed stop (:math:`v' \le v_{stop}` = ``STOP_SPEED``, real data holds exact stops and
  smoothing leaves values like 1e-5): :math:`P(a \le a_{stop})`,
  :math:`a_{stop} = (v_{stop} - v)/\Delta t` (0 when :math:`a_{stop} < -b_{phys}`: no car stops
  from there in one step; 1 when the ceiling forces the stop);
* a moving step at the floor (:math:`\hat a \le -b_{phys}` + ``LIMIT_TOLERANCE``, which also reads
  a harder braking in data as braking at the limit): :math:`P(a_{stop} < a \le -b_{phys} + tol)`;
* a moving step at the ceiling (:math:`\hat a \ge a_{ceil}` - ``LIMIT_TOLERANCE``):
  :math:`P(a \ge a_{ceil} - tol)`.

Classifying at the same thresholds that censor keeps the law normalised, and the tolerance
(0.01 m/s^2) is far above the float32 round-off of an implied acceleration (about 1e-4 m/s^2 at
10 Hz). In the NGSIM chains the position is exactly the trapezoid-integrated speed and OpenACC
positions are the integrated Doppler speed (see the readers), so scoring position or speed uses
the same information there. Increments are relative to the current state, so float32 never loses
the density on positions of hundreds of metres.

A base model supplies its mean acceleration and parameter specs (one marked ``execution_noise``);
:func:`execution_noise_model` makes it a :class:`~bayesdrive.drivers.base.DriverModel`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import (
    DriverModel,
    EgoState,
    ParamSpec,
    car_following_at,
    parameter_noise_sd,
)

__all__ = [
    "EXECUTION_NOISE_SD",
    "LIMIT_TOLERANCE",
    "MAX_ACCELERATION",
    "MAX_BRAKING",
    "SAFETY_GAP",
    "STOP_SPEED",
    "IncrementLaw",
    "acceleration_ceiling",
    "censored_observation",
    "censored_step",
    "exact_initial_sample",
    "exact_observation_logpdf",
    "execution_noise_model",
    "implied_acceleration",
    "increment_law",
    "noisy_step",
    "step_logpdf",
]

# Speeds below 1 mm/s are a stop: smoothing leaves values like 1e-5 where the car stands still.
STOP_SPEED = 1e-3
# Physical limits of the applied acceleration, m/s^2 (module docstring).
MAX_BRAKING = 9.0
MAX_ACCELERATION = 6.0
# The gap (m) the ceiling keeps to a leader; above the few centimetres the bounds of the discrete
# stops leave at crawling speeds (v < MAX_BRAKING dt).
SAFETY_GAP = 0.1
# Implied accelerations this close to a limit (m/s^2) are read as at it (module docstring).
LIMIT_TOLERANCE = 0.01
# The base models' execution-noise sd: the noise is the same quantity in each (the paper's
# sigma_IDM), so it has one prior and one pf grid step.
EXECUTION_NOISE_SD = ParamSpec(
    "sigma", "m/s^2", 0.3, 0.02, 2.0, "execution-noise sd", grid_step=0.1, execution_noise=True
)


def implied_acceleration(v: Array, dx: Array, dt: Array) -> Array:
    """The acceleration that turns speed ``v`` into position increment ``dx`` over ``dt``."""
    return 2.0 * (dx - v * dt) / dt**2


def acceleration_ceiling(v: Array, inputs) -> Array:
    """The largest acceleration applied from speed ``v`` with the car-following ``inputs`` (gap,
    lead_v, has_leader, dt): ``MAX_ACCELERATION``, or behind a leader the most after which the
    follower, braking at ``MAX_BRAKING``, still stops ``SAFETY_GAP`` behind a leader that brakes at
    that limit to a stop from now on, and keeps that gap at the end of this step (module
    docstring); never below the floor plus two ``LIMIT_TOLERANCE``."""
    dt = inputs.dt
    brake_step = MAX_BRAKING * dt
    lead_stop = inputs.lead_v**2 / (2.0 * MAX_BRAKING)  # no discrete stop is shorter
    # Travel this step, (v + v') dt / 2, plus a stop from v' (at most v'^2 / (2 b) + v' dt / 2)
    # within the room: v'^2 / (2 b) + v' dt <= room, room = gap - safety + lead stop - v dt / 2.
    room = inputs.gap - SAFETY_GAP + lead_stop - 0.5 * v * dt
    reach = jnp.sqrt(jnp.maximum(brake_step**2 + 2.0 * MAX_BRAKING * room, 0.0))
    stoppable = (reach - brake_step - v) / dt
    # This step alone: the gap at its end at least the safety gap, the leader braking through it.
    lead_step = jnp.where(
        inputs.lead_v >= brake_step, inputs.lead_v * dt - 0.5 * brake_step * dt, lead_stop
    )
    step_end = 2.0 * (inputs.gap - SAFETY_GAP + lead_step - v * dt) / dt**2
    safe = jnp.where(inputs.has_leader > 0, jnp.minimum(stoppable, step_end), MAX_ACCELERATION)
    return jnp.clip(safe, -MAX_BRAKING + 2.0 * LIMIT_TOLERANCE, MAX_ACCELERATION)


def noisy_step(
    key: Array, state: EgoState, mean_acc: Array, sigma: Array, dt: Array, ceiling: Array
) -> EgoState:
    """One step of Gaussian execution noise around ``mean_acc``, the applied acceleration censored
    at ``-MAX_BRAKING`` and ``ceiling`` (:func:`acceleration_ceiling`), speed clipped at 0."""
    raw = mean_acc + sigma * jax.random.normal(key, jnp.shape(mean_acc))
    acc = jnp.minimum(jnp.maximum(raw, -MAX_BRAKING), ceiling)
    next_v = jnp.maximum(0.0, state.v + acc * dt)
    return EgoState(x=state.x + 0.5 * (state.v + next_v) * dt, v=next_v)


def _log_normal_mass(
    low: Array, high: Array, low_open: Array, high_open: Array, possible: Array
) -> Array:
    """log(Phi(high) - Phi(low)), an open end standing for -inf (low) or +inf (high), accurate in
    both tails (a difference of survival functions above 0); -inf where ``possible`` is False or
    the interval is empty. Every branch stays finite, so gradients do too."""
    empty = ~possible | (~low_open & ~high_open & (low >= high))
    upper = ~low_open & (low > 0.0)
    # Phi(high) - Phi(low) = Phi(b) - Phi(a), with a, b = -high, -low in the upper tail.
    a = jnp.where(upper, -high, low)
    b = jnp.where(upper, -low, high)
    a_open = jnp.where(upper, high_open, low_open) | empty
    b_open = (~upper & high_open) | empty
    log_a = jnp.where(a_open, -jnp.inf, norm.logcdf(jnp.where(a_open, 0.0, a)))
    log_b = jnp.where(b_open, 0.0, norm.logcdf(jnp.where(b_open, 0.0, b)))
    mass = log_b + jnp.log1p(-jnp.exp(log_a - log_b))
    return jnp.where(empty, -jnp.inf, mass)


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
    ceiling: Array,
    *,
    may_be_censored: bool | Array = True,
) -> Array:
    """Exact log-density of the observed next state under :func:`noisy_step` with ``ceiling``
    (module docstring: a moving step inside the limits has a density, a stop or a step at a limit
    the probability of its class).

    ``may_be_censored`` False promises that the observed step is none of those (next speed above
    ``STOP_SPEED``, implied acceleration inside the limits): the class probability, whose normal
    log-CDFs cost more than all the rest, is then not computed. A boolean array decides when the
    program runs (one ``lax.cond`` around the class probability alone, a real branch where the
    flag is not batched), so a caller can decide once for a whole series."""
    law = increment_law(state.v, mean_acc, sigma, dt)
    dx = next_state.x - state.x
    # N(dx; law.mean, law.sd) through the standardised acceleration: the log of the sd then splits
    # into log(sigma), once per parameter vector, and log(dt^2 / 2), once per step, instead of a
    # log for every pair (most of the likelihood's cost).
    z = (implied_acceleration(state.v, dx, dt) - mean_acc) / sigma
    inside = norm.logpdf(z) - jnp.log(sigma) - jnp.log(0.5 * dt**2)

    def with_classes() -> Array:
        stopped, at_floor, at_ceiling = _step_classes(state.v, next_state.v, dx, dt, ceiling)
        floor_at, ceiling_at = -MAX_BRAKING + LIMIT_TOLERANCE, ceiling - LIMIT_TOLERANCE
        # The censored acceleration reaches a stop from below the floor never, above the ceiling
        # always.
        stop_at = (STOP_SPEED - jnp.asarray(state.v)) / dt  # an array, so ~ negates its comparisons
        unreachable, forced = stop_at < -MAX_BRAKING, stop_at >= ceiling
        floor_z, ceiling_z = (floor_at - mean_acc) / sigma, (ceiling_at - mean_acc) / sigma
        # Raw-acceleration interval of each class: stop (-inf, stop], floor (stop, floor],
        # ceiling [max(ceiling, stop), inf); a moving step where the stop is forced is impossible.
        low = jnp.where(at_floor, law.stop_z, jnp.maximum(ceiling_z, law.stop_z))
        low_open = stopped | (at_floor & unreachable)
        high = jnp.where(stopped, law.stop_z, floor_z)
        high_open = at_ceiling | (stopped & forced)
        possible = jnp.where(stopped, ~unreachable, ~forced)
        censored = _log_normal_mass(low, high, low_open, high_open, possible)
        return jnp.where(stopped | at_floor | at_ceiling, censored, inside)

    if isinstance(may_be_censored, bool):
        return with_classes() if may_be_censored else inside
    return jax.lax.cond(may_be_censored, with_classes, lambda: inside)


def _step_classes(
    v: Array, next_v: Array, dx: Array, dt: Array, ceiling: Array
) -> tuple[Array, Array, Array]:
    """The censored classes of an observed step (module docstring): a stop; a moving step at the
    floor; a moving step at the ceiling (not at the floor). Disjoint; data alone decide them."""
    acc = implied_acceleration(v, dx, dt)
    stopped = jnp.asarray(next_v) <= STOP_SPEED
    at_floor = ~stopped & (acc <= -MAX_BRAKING + LIMIT_TOLERANCE)
    at_ceiling = ~stopped & ~at_floor & (acc >= ceiling - LIMIT_TOLERANCE)
    return stopped, at_floor, at_ceiling


def censored_step(v: Array, next_v: Array, dx: Array, dt: Array, ceiling: Array) -> Array:
    """Whether an observed step is scored by a class probability (:func:`step_logpdf`): a stop, or
    an implied acceleration at a limit; depends on the data alone."""
    stopped, at_floor, at_ceiling = _step_classes(v, next_v, dx, dt, ceiling)
    return stopped | at_floor | at_ceiling


def censored_observation(state: EgoState, next_state: EgoState, inputs) -> Array:
    """:func:`censored_step` of an observed step whose ceiling comes from the car-following
    ``inputs`` (gap, lead_v, has_leader, dt): the ``censored`` declaration of every model scored by
    :func:`step_logpdf` (:class:`~bayesdrive.drivers.base.DriverModel`)."""
    ceiling = acceleration_ceiling(state.v, inputs)
    return censored_step(state.v, next_state.v, next_state.x - state.x, inputs.dt, ceiling)


def exact_observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
    """The state is observed exactly: the observation carries no density of its own (log 1 = 0)."""
    del params, state, obs
    return jnp.zeros(())


def exact_initial_sample(key: Array, params, obs: EgoState) -> EgoState:
    """With exact observations the first state is the first observation."""
    del key, params
    return obs


def execution_noise_model(
    name: str,
    params_type: type,
    specs: tuple[ParamSpec, ...],
    mean_acceleration,
    noise_sd=None,
    inputs_at=car_following_at,
    scene: str | None = None,
) -> DriverModel:
    """A driver model that applies ``mean_acceleration`` with Gaussian execution noise of sd
    ``noise_sd(params, state)`` (default: the parameter ``specs`` mark ``execution_noise``;
    :func:`noisy_step`, scored exactly by :func:`step_logpdf`), state observed exactly, reading the
    inputs ``inputs_at`` builds, which need the series' ``scene`` part beyond car following (None:
    none). The base models and the criticism's Gaussian extensions differ only in their mean
    acceleration and inputs (and, for speed-dependent noise, the sd)."""
    noise_sd = parameter_noise_sd(specs) if noise_sd is None else noise_sd

    def transition_sample(key: Array, params, state: EgoState, inputs) -> EgoState:
        mean_acc = mean_acceleration(params, state, inputs)
        ceiling = acceleration_ceiling(state.v, inputs)
        return noisy_step(key, state, mean_acc, noise_sd(params, state), inputs.dt, ceiling)

    def transition_logpdf(
        params,
        state: EgoState,
        next_state: EgoState,
        inputs,
        *,
        may_be_censored: bool | Array = True,
    ) -> Array:
        mean_acc = mean_acceleration(params, state, inputs)
        ceiling = acceleration_ceiling(state.v, inputs)
        sd = noise_sd(params, state)
        return step_logpdf(
            state, next_state, mean_acc, sd, inputs.dt, ceiling, may_be_censored=may_be_censored
        )

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
        censored=censored_observation,
        scene=scene,
        noise_sd=noise_sd,
    )
