r"""``lm``: per-vehicle Levenberg-Marquardt fit with a Laplace (Gaussian) posterior approximation.

A fast baseline beside the exact engines, on the same likelihood. For a vehicle with moving steps
t (masked in, next speed above ``STOP_SPEED``), the model's one-step density is Gaussian in the
position increment with sd :math:`\sigma\Delta t^2/2` (see :mod:`bayesdrive.drivers.idm`), so its
log-likelihood is :math:`-\tfrac{1}{2\sigma^2}\sum_t r_t^2` + const with the residuals

.. math::

    r_t = \frac{dx_t - (v_t\Delta t + a(\theta)\Delta t^2/2)}{\Delta t^2/2}
        = \underbrace{\frac{dx_t - v_t\Delta t}{\Delta t^2/2}}_{\text{implied acceleration}}
          - a(\theta),

where :math:`a(\theta)` is ``model.mean_acceleration`` (never re-implemented here) and the implied
acceleration is computed in float64 before any cast. Observed stops are censored steps (their
likelihood is a normal CDF, not a residual) and are left out of the least squares; how many per
vehicle is recorded in ``sample_stats.censored_steps``.

**Transformed space.** MINPACK's LM is unconstrained, so every fitted parameter is optimised as
:math:`z = \mathrm{logit}((\theta - l)/(u - l))` on its prior box :math:`[l, u]` (the map NumPyro
uses for a bounded uniform); :math:`\theta = l + (u - l)\,\mathrm{sigmoid}(z)` never leaves the
box. Residuals and their Jacobian (``jax.jacfwd``) are compiled once per padded series length.
Each vehicle is fitted from two starts, the model defaults and the prior centre (z = 0), and the
fit with the lower cost is kept (the first on a tie); no randomness is involved. A default on the
edge of its box (an extension switched off at its prior's lower bound) has no finite z, and from
an infinite z, where the Jacobian vanishes, LM would not move: that start is moved inside the box
by ``EDGE_FRACTION`` of its width.

**Noise sd.** :math:`\sigma` (the parameter whose spec is marked ``execution_noise``) does not
enter the residuals. When it is inferred it is estimated as
the residual RMS with :math:`n - p` degrees of freedom, :math:`s^2 = \sum_t r_t^2/(n - p)`
(``sample_stats.sigma_hat``); otherwise the fixed value is used below in place of :math:`s`.

**Posterior approximation (Laplace / Gauss-Newton).** The draws are from the posterior of the model
linearised at the fit :math:`\hat z`, with a flat prior on z and :math:`p(\sigma) \propto 1/\sigma`:

.. math::

    \sigma^2 \sim \frac{\sum_t r_t^2}{\chi^2_{n-p}}, \qquad
    z \mid \sigma \sim \mathcal N\big(\hat z,\ \sigma^2 (J^\top J)^{-1}\big),

:math:`J = \partial r / \partial z` at :math:`\hat z`, mapped to parameters through the sigmoid.
So the covariance is :math:`s^2 (J^\top J)^{-1}` in the fitted space at :math:`\sigma = s`, and the
sd of :math:`\sigma` is the sampling spread of the RMS (about :math:`s/\sqrt{2(n-p)}`); with a fixed
:math:`\sigma` only z is drawn. It is a Gaussian approximation in the transformed space: skewed in
parameter space near a bound, and blind to multimodality. Where :math:`J^\top J` is numerically
singular, its small eigenvalues are floored at ``1e-10`` of the largest, the draws in that
direction spread to the box edges, and ``sample_stats.identified`` is False (``converged`` too).
That happens when the data cannot inform a parameter (v_des in congestion) and, above all, when the
best fit lies on the edge of the box, where the sigmoid is flat (``sample_stats.at_bound``): on the
NGSIM I-80 fit windows most vehicles have one, e.g. b_pref at its upper bound. A Gaussian cannot
describe such a posterior; use a sampling engine there. The draws come from one
numpy generator per vehicle, seeded from the vehicle's own key (the seed with its id folded in,
:mod:`bayesdrive.inference.core.vehicles`; ``sample_stats.seed``), so a vehicle's draws are the same
whichever vehicles it is fitted with; the fit itself is deterministic and needs no key.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import Any, NamedTuple, Unpack

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from scipy.optimize import least_squares
from scipy.special import expit

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel, EgoState, fill_params
from bayesdrive.drivers.execution_noise import STOP_SPEED, implied_acceleration
from bayesdrive.inference.core.likelihood import StepInputs, check_model
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.vehicles import one_chain_result, prepare

__all__ = ["ResidualSeries", "residual_series", "run"]

log = logging.getLogger(__name__)

# Relative eigenvalue floor of J^T J below which a direction counts as not identified.
IDENTIFIED_RTOL = 1e-10
# An estimate within this fraction of its box width from a bound counts as at the bound.
AT_BOUND = 1e-4
# How far inside its box, as a fraction of the width, a default on the box's edge starts LM.
EDGE_FRACTION = 1e-3
# Vehicle ids named in the not-converged warning (the count is always given).
WARN_IDS = 10
START_NAMES = ("defaults", "prior_centre")


class ResidualSeries(NamedTuple):
    """One vehicle's (T,) inputs to the residuals (or (V, T) for all vehicles).

    implied: the implied acceleration (:func:`~bayesdrive.drivers.execution_noise.implied_acceleration`),
    computed in float64 (m/s^2).
    used: 1 on the steps that enter the least squares (masked in and moving), else 0.
    steps: the steps with the model's own inputs (:func:`~bayesdrive.inference.core.likelihood.step_inputs`).
    """

    implied: Array
    used: Array
    steps: StepInputs


def residual_series(arrays: FollowerArrays, steps: StepInputs) -> tuple[ResidualSeries, np.ndarray]:
    """The residual inputs of every vehicle (``steps``: its steps with the model's inputs), and
    the number of censored (stopped) steps of each."""
    dt = arrays.dt
    implied = implied_acceleration(arrays.v, arrays.dx, dt)
    usable = np.asarray(steps.mask) > 0
    moving = arrays.next_v > STOP_SPEED
    series = ResidualSeries(
        implied=jnp.asarray(implied, dtype=float),
        used=jnp.asarray(usable & moving, dtype=float),
        steps=steps,
    )
    return series, (usable & ~moving).sum(axis=1)


def _box(z: np.ndarray, lower: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Parameters from the transformed space: lower + width * sigmoid(z), in float64 numpy."""
    return lower + width * expit(z)


@functools.partial(jax.jit, static_argnames=("model", "names"))
def _residuals(
    z: Array,
    series: ResidualSeries,
    fixed: Any,
    lower: Array,
    width: Array,
    *,
    model: DriverModel,
    names: tuple[str, ...],
) -> Array:
    """Implied minus model acceleration on the used steps, 0 elsewhere: (T,)."""
    # The map of _box, in JAX.
    params = fill_params(model, names, lower + width * jax.nn.sigmoid(z), fixed)

    def mean_acceleration(v, inputs):
        state = model.lift(params, EgoState(jnp.zeros_like(v), v), inputs)
        return model.mean_acceleration(params, state, inputs)

    predicted = jax.vmap(mean_acceleration)(series.steps.v, series.steps.inputs)
    return jnp.where(series.used > 0, series.implied - predicted, 0.0)


_jacobian = jax.jit(jax.jacfwd(_residuals), static_argnames=("model", "names"))


class _VehicleFit(NamedTuple):
    z: np.ndarray  # (p,) best fit in the transformed space
    jac: np.ndarray  # (T, p) at z
    sum_squares: float
    nfev: int
    status: int
    best_start: int


def _fit_vehicle(fun, jac, starts: np.ndarray, max_nfev: int | None) -> _VehicleFit:
    """LM from every start; the lowest cost wins (the earliest start on a tie)."""
    best = None
    nfev = 0
    for index, start in enumerate(starts):
        fit = least_squares(fun, start, jac=jac, method="lm", max_nfev=max_nfev)
        nfev += int(fit.nfev)
        if best is None or fit.cost < best[0].cost:
            best = (fit, index)
    fit, index = best
    return _VehicleFit(
        z=fit.x,
        jac=np.asarray(jac(fit.x), dtype=np.float64),
        sum_squares=2.0 * float(fit.cost),
        nfev=nfev,
        status=int(fit.status),
        best_start=index,
    )


def _gauss_newton_covariance(jac: np.ndarray) -> tuple[np.ndarray, bool]:
    """(J^T J)^-1 with tiny eigenvalues floored, and whether none needed the floor."""
    eigenvalues, vectors = np.linalg.eigh(jac.T @ jac)
    # The floor itself is at least the smallest normal float: with no information at all (every
    # column of J zero, e.g. a fit saturated at its prior bounds) 1 / floor stays finite.
    floor = max(IDENTIFIED_RTOL * float(eigenvalues[-1]), np.finfo(float).tiny)
    identified = bool(eigenvalues[0] > floor)
    inverse = vectors @ np.diag(1.0 / np.maximum(eigenvalues, floor)) @ vectors.T
    return inverse, identified


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    max_nfev: int | None = None,
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """Levenberg-Marquardt per vehicle of ``arrays`` and Laplace draws (module docstring).

    ``params`` are the inferred parameters (all of the model's by default); the execution-noise sd
    among them (the spec marked ``execution_noise``) is estimated from the residuals, the others
    are fitted. ``num_particles`` is the number of
    posterior draws. Only the model's uniform prior box is supported (``prior`` must be None): it
    defines the transformed space, and the fit maximises the likelihood inside it.
    ``max_nfev`` caps scipy's evaluations per start. ``sample_stats`` holds per vehicle
    ``cost`` (half the residual sum of squares, scipy's convention), ``nfev`` (over both starts),
    ``status`` (scipy's code), ``converged`` (status > 0 and identified), ``identified``,
    ``best_start`` (0 = defaults, 1 = prior centre), ``sigma_hat``, ``num_residuals``,
    ``censored_steps``, ``estimate`` [vehicle, param] (the fit itself, sigma = sigma_hat),
    ``at_bound`` [vehicle, param] (estimate within 1e-4 of the box width of a prior bound, or
    beyond it for sigma_hat) and
    ``seed``, the numpy seed of the vehicle's draws (from the vehicle's key, which is used for the
    posterior draws only).
    """

    def check(model: DriverModel) -> None:
        if model.execution_noise_param is None:
            raise ValueError(
                f"lm needs Gaussian execution noise, but model {model.name!r} marks no "
                "execution-noise sd parameter (ParamSpec.execution_noise)"
            )
        if inputs.get("prior") is not None:
            raise NotImplementedError(
                "lm fits inside the model's uniform prior box only; a custom prior "
                f"({type(inputs['prior']).__name__}) needs a sampling engine (smc, nuts, emcee)"
            )
        check_model(model, "lm")

    problem = prepare("lm", arrays, inputs, num_particles=1000, check=check)
    model, names, fixed_values = problem.model, problem.names, problem.fixed
    noise, num_particles = model.execution_noise_param, problem.num_particles
    fitted = tuple(n for n in names if n != noise)
    if not fitted:
        raise ValueError(f"lm fits parameters other than {noise!r}; got only {list(names)}")
    if num_particles < 1:
        raise ValueError(f"num_particles (posterior draws) must be >= 1, got {num_particles}")
    box = model.prior(fitted)
    lower = np.asarray(box.lower, np.float64)
    width = np.asarray(box.upper, np.float64) - lower
    defaults = np.array([model.spec(n).default for n in fitted])
    inside = np.clip((defaults - lower) / width, EDGE_FRACTION, 1.0 - EDGE_FRACTION)
    starts = np.stack([np.log(inside / (1.0 - inside)), np.zeros(len(fitted))])

    series, censored = residual_series(arrays, problem.series)
    num_vehicles = problem.num_vehicles
    num_residuals = np.asarray(series.used).sum(axis=1).astype(int)
    too_short = {
        vid: int(n)
        for vid, n in zip(arrays.vehicle_ids, num_residuals, strict=True)
        if n <= len(fitted)
    }
    if too_short:
        raise ValueError(
            f"lm needs more moving steps than the {len(fitted)} fitted parameters; "
            f"moving steps of the vehicles that have too few: {too_short}"
        )

    # Compiled once per padded shape (and cached across runs with the same model and names).
    bounds = (jnp.asarray(lower, dtype=float), jnp.asarray(width, dtype=float))
    static = {"model": model, "names": fitted}
    started = time.perf_counter()
    first = jax.tree.map(lambda a: a[0], series)
    z_example = jnp.zeros(len(fitted), dtype=first.implied.dtype)
    for compiled in (_residuals, _jacobian):
        compiled.lower(z_example, first, fixed_values, *bounds, **static).compile()
    compile_time = time.perf_counter() - started

    started = time.perf_counter()
    fits = []
    for index in range(num_vehicles):
        vehicle = jax.tree.map(lambda a, index=index: a[index], series)

        def fun(z, vehicle=vehicle):
            z = jnp.asarray(z, dtype=float)
            return np.asarray(_residuals(z, vehicle, fixed_values, *bounds, **static), np.float64)

        def jac(z, vehicle=vehicle):
            z = jnp.asarray(z, dtype=float)
            return np.asarray(_jacobian(z, vehicle, fixed_values, *bounds, **static), np.float64)

        fits.append(_fit_vehicle(fun, jac, starts, max_nfev))
        if problem.progress is not None:
            problem.progress(index + 1, num_vehicles)

    dof = num_residuals - len(fitted)
    sum_squares = np.array([f.sum_squares for f in fits])
    sigma_hat = np.sqrt(sum_squares / dof)
    covariances, identified = zip(*(_gauss_newton_covariance(f.jac) for f in fits), strict=True)
    identified = np.array(identified)
    status = np.array([f.status for f in fits])
    converged = (status > 0) & identified & np.isfinite(sum_squares)
    if not converged.all():
        failed = [v for v, ok in zip(arrays.vehicle_ids, converged, strict=True) if not ok]
        log.warning(
            "lm: %d of %d vehicle(s) not converged or not identified (see sample_stats.status, "
            "identified, at_bound), e.g. %s",
            len(failed),
            num_vehicles,
            failed[:WARN_IDS],
        )

    # Draws: sigma^2 ~ SSR / chi2(n - p) (or the fixed sigma), then z | sigma Gaussian, from one
    # numpy generator per vehicle seeded from the key (JAX's gamma sampler compiles for seconds).
    seeds = np.asarray(
        jax.vmap(lambda k: jax.random.bits(k, (), dtype=jnp.uint32))(problem.keys(key))
    ).astype(np.int64)
    draws = np.empty((num_vehicles, num_particles, len(names)))
    estimate = np.empty((num_vehicles, len(names)))
    for n, (fit, covariance) in enumerate(zip(fits, covariances, strict=True)):
        rng = np.random.default_rng(seeds[n])
        if noise in names:
            sigma_draws = np.sqrt(sum_squares[n] / rng.chisquare(dof[n], num_particles))
        else:
            sigma_draws = np.full(num_particles, float(getattr(fixed_values, noise)))
        normals = rng.standard_normal((num_particles, len(fitted)))
        z = fit.z + sigma_draws[:, None] * (normals @ np.linalg.cholesky(covariance).T)
        theta = _box(z, lower, width)
        theta_hat = _box(fit.z, lower, width)
        for column, name in enumerate(names):
            if name == noise:
                draws[n, :, column] = sigma_draws
                estimate[n, column] = sigma_hat[n]
            else:
                draws[n, :, column] = theta[:, fitted.index(name)]
                estimate[n, column] = theta_hat[fitted.index(name)]

    box_of = {s.name: (s.lower, s.upper) for s in model.specs}
    edges = np.array([box_of[n] for n in names])
    margin = AT_BOUND * (edges[:, 1] - edges[:, 0])
    at_bound = (estimate <= edges[:, 0] + margin) | (estimate >= edges[:, 1] - margin)

    log_likelihood = problem.pointwise_scores(draws)
    wall_time = time.perf_counter() - started

    vehicle = ("vehicle",)
    return one_chain_result(
        names,
        draws,
        log_likelihood,
        sample_stats={
            "cost": (vehicle, sum_squares / 2.0),
            "nfev": (vehicle, np.array([f.nfev for f in fits])),
            "status": (vehicle, status),
            "converged": (vehicle, converged),
            "identified": (vehicle, identified),
            "best_start": (vehicle, np.array([f.best_start for f in fits])),
            "sigma_hat": (vehicle, sigma_hat),
            "num_residuals": (vehicle, num_residuals),
            "censored_steps": (vehicle, np.asarray(censored, dtype=int)),
            "estimate": (("vehicle", "param"), estimate),
            "at_bound": (("vehicle", "param"), at_bound),
            "seed": (vehicle, seeds),
        },
        compile_time_s=compile_time,
        wall_time_s=wall_time,
        options={
            "num_particles": num_particles,
            "max_nfev": max_nfev,
            "starts": list(START_NAMES),
            "transform": "logit of the prior box",
            noise: "residual RMS, n - p dof" if noise in names else "fixed",
        },
    )
