r"""Video-style measurement noise: noisy positions whose speeds were *derived* from them.

Video-extracted trajectories (NGSIM and its kind) record a noisy position :math:`y_t = x_t +
\varepsilon_t`, :math:`\varepsilon_t \sim N(0, \sigma_{obs}^2)` independent over time, and publish
speeds and gaps computed by differencing those positions. The recorded speed is then no reading of
its own (it is a function of the positions) and carries noise of about
:math:`\sigma_{obs}/(\sqrt 2\,\Delta t)`: the exact-speed filter of
:mod:`bayesdrive.drivers.measurement_noise` (use 1) would condition on it as if it were exact. Here
only positions are observations and the speed is a hidden state, as in the latent-state engine's
model (use 2), but the likelihood comes from a Kalman filter instead of particles: deterministic and
differentiable, so ``nuts`` and ``emcee`` fit the model like any other.

**The filter** (``filter``, per vehicle, extended Kalman filter over the latent state :math:`s_t =
(e_t, v_t)`, the true position's offset from the reading :math:`y_t` and the true speed). The base
model moves the state by :math:`a_t \sim N(\mu(v_t, g_t - e_t), \sigma^2)`, with :math:`\mu` its
mean acceleration at the gap the latent ego sees (the recorded gap :math:`g_t` shrunk by the offset,
:func:`~bayesdrive.drivers.measurement_noise.shift_ego`): on the next reading's axis

.. math::

    e_{t+1} = e_t + v_t\Delta t + a_t\Delta t^2/2 - (y_{t+1} - y_t), \qquad
    v_{t+1} = v_t + a_t\Delta t,

and the reading is :math:`0 = e_{t+1} + \varepsilon_{t+1}`. The filter linearises :math:`\mu` in
:math:`(e, v)` around the filtered mean (its exact Jacobian by ``jax.linearize``); every other part is
linear and Gaussian, so the one-step predictive density of each reading is Gaussian with the
innovation variance. Its error is second order in the state's uncertainty (millimetres to
centimetres and centimetres per second here, against the metres over which the rule bends). A
stretch of usable steps starts at :math:`e_0 \sim N(0, \sigma_{obs}^2)` (a flat prior on the first
true position) and :math:`v_0 \sim N(\hat v_0, 1\ \mathrm{m^2/s^2})` around the recorded speed: a
vague start, since the recorded speed shares its readings with the positions scored next. So the
likelihood is :math:`p(y_{1:T} \mid y_0, \hat v_0)`, step t scoring :math:`y_{t+1}`.

**Not modelled.** The base model's stop (speed clipped at 0) is not: the filter's Gaussian speed may
go below 0, which matters only for a vehicle that stands still; the leader's readings (gap and
speed) are taken as recorded, as every other model here takes them.

=========  ====  =======  ============  =============================================
name       unit  default  prior bounds  meaning
=========  ====  =======  ============  =============================================
sigma_obs  m     0.0      [0, 0.5]      sd of the Gaussian position-measurement noise
=========  ====  =======  ============  =============================================
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import DriverModel, EgoState
from bayesdrive.drivers.measurement_noise import shift_ego, with_measurement_noise

__all__ = ["INITIAL_SPEED_SD", "NAME", "with_video_noise"]

NAME = "video_noise"
# The sd of the latent speed where a stretch of data starts, around the recorded speed (m/s).
INITIAL_SPEED_SD = 1.0


def _kalman_filter(base: DriverModel, params, steps: Any) -> Array:
    """One-step predictive log densities of one vehicle's readings (T,) (module docstring)."""
    own = base.params_type(*(getattr(params, name) for name in base.param_names))
    dt = steps.inputs.dt[0]
    reading_var = params.sigma_obs**2
    noise_loading = jnp.stack([0.5 * dt**2, dt])  # how an acceleration moves (e, v)
    kinematics = jnp.array([[1.0, dt], [0.0, 1.0]])

    def rule(state: Array, inputs) -> Array:
        ego = EgoState(jnp.zeros_like(state[1]), state[1])
        return base.mean_acceleration(own, ego, shift_ego(inputs, state[0]))

    def step(carry, xs):
        mean, cov, previous_usable = carry
        inputs, v, dx, usable = xs
        # A stretch of data starts at t = 0 and after every masked step.
        starts = previous_usable <= 0
        mean = jnp.where(starts, jnp.stack([jnp.zeros_like(v), v]), mean)
        cov = jnp.where(starts, jnp.diag(jnp.stack([reading_var, INITIAL_SPEED_SD**2])), cov)

        # One evaluation of the rule gives its value and, by two pushforwards, its Jacobian.
        acceleration, pushforward = jax.linearize(lambda state: rule(state, inputs), mean)
        slope = jax.vmap(pushforward)(jnp.eye(2, dtype=mean.dtype))
        transition = kinematics + jnp.outer(noise_loading, slope)
        predicted = kinematics @ mean + noise_loading * acceleration - jnp.stack([dx, 0.0])
        sigma = base.noise_sd(own, EgoState(jnp.zeros_like(mean[1]), mean[1]))
        process_cov = sigma**2 * jnp.outer(noise_loading, noise_loading)
        predicted_cov = transition @ cov @ transition.T + process_cov
        innovation_var = predicted_cov[0, 0] + reading_var
        logp = norm.logpdf(0.0, predicted[0], jnp.sqrt(innovation_var))
        gain = predicted_cov[:, 0] / innovation_var
        updated = predicted - gain * predicted[0]
        updated_cov = predicted_cov - innovation_var * jnp.outer(gain, gain)
        updated_cov = 0.5 * (updated_cov + updated_cov.T)

        used = usable > 0
        carry = (
            jnp.where(used, updated, mean),
            jnp.where(used, updated_cov, cov),
            usable,
        )
        return carry, logp

    zero = jnp.zeros_like(steps.v[0])
    start = (jnp.stack([zero, zero]), jnp.zeros((2, 2), zero.dtype), jnp.zeros_like(steps.mask[0]))
    _, logp = jax.lax.scan(step, start, (steps.inputs, steps.v, steps.dx, steps.mask))
    return logp


@functools.cache
def with_video_noise(model: DriverModel) -> DriverModel:
    """``model`` observed through video-style position noise (module docstring): the
    measurement-noise model's parameters, transitions, observation density and initial state (so
    the latent-state engine and the simulator treat it alike) with the Kalman filter above as its
    likelihood for ``nuts`` and ``emcee``. Cached, so compiled engines are reused."""
    noisy = with_measurement_noise(model)
    return noisy._replace(
        name=f"{model.name}+{NAME}",
        filter=functools.partial(_kalman_filter, model),
        # Its Gaussian filter scores no step by a class probability.
        censored=None,
        observation=NAME,
    )
