r"""Fitting any (extended) driver model and scoring its held-out predictive density, per vehicle.

**Beside ``smc``.** The engines fit one window; the criticism needs the fitting-window posterior
*and* its continuation into the held-out window (phase 2 below), whose normalising constant is
the held-out predictive density. Both this and ``smc`` run the one adaptive tempering of the SMC
core (:mod:`bayesdrive.inference.core.smc`: its step, temperature search, proposal fit, moves and
stop rules, with one settings type, :class:`~bayesdrive.inference.core.smc.TemperingConfig`), and
every model's steps come from the model itself
(:func:`~bayesdrive.inference.core.likelihood.step_inputs`, :func:`~bayesdrive.inference.core.likelihood.step_logpdfs`).
For the base model its log-evidence is checked against ``smc``'s in the tests.

**The sampler.** Adaptive-tempering SMC (Del Moral, Doucet & Jasra 2006; Jasra et al. 2011) for
each vehicle. Phase 1 bridges from the prior to the fitting-window posterior through
:math:`\pi_\lambda \propto p(\theta)\, p(y_{fit} \mid \theta)^\lambda`, each temperature chosen by
bisection so that the incremental weights keep an effective sample size of
``ess_threshold * N``; after each reweighting the particles are resampled (systematic) and moved
by at least ``num_moves`` random-walk Metropolis-Hastings steps invariant for
:math:`\pi_\lambda` (on the logit scale of the prior box, Gaussian proposal with the reweighted
particles' covariance there scaled by :math:`s`, :math:`s` adapted towards acceptance 0.234). The
product of the mean incremental weights estimates :math:`p(y_{fit})` (``log_z_fit``).

**How many moves.** A fixed handful of moves at acceptance ~0.23 leaves about a third of the
particles where resampling put them (0.77^4 = 0.35); stage after stage the cloud then loses
spread, and a posterior that is broad along a curved ridge (the noise sd at standstill against its
growth with speed, in the speed-dependent-noise extension) can end up one narrow sliver of it.
The held-out density continued from such a cloud is that of one parameter value, not of the
posterior: in a detection run one vehicle's held-out density fell thousands of nats below the
base model's, although the extension nests it: the cloud had collapsed on a slope the fit-window
likelihood barely constrains, and more moves or particles removed the loss. With
``unmoved_tolerance`` c > 0 each stage keeps moving, past ``num_moves``, until the estimated
probability that a particle has not moved at all, :math:`\prod_m (1 - \text{acceptance}_m)`, is
at most c (Drovandi & Pettitt 2011, c = 0.01; South, Pettitt & Drovandi 2019), at most
``max_moves`` moves; c = 0 keeps exactly ``num_moves``. The default is c = 0.01 with 128 particles:
side by side with 5 fixed moves and 256 particles, on followers with a hidden reaction delay, it
took less time and gave the same verdict and ranking; the detection study
(``benchmarks/bench_detection.py``) uses exactly it.

Phase 2 **continues from the fitting-window posterior, without refitting**, to the posterior
given all data, through :math:`p(\theta \mid y_{fit})\, p(y_{held} \mid y_{fit}, \theta)^\lambda`.
Its normalising constant is exactly the held-out predictive density

.. math::

    p(y_{held} \mid y_{fit}) = \int p(y_{held} \mid y_{fit}, \theta)\, p(\theta \mid y_{fit})\,d\theta
    = \frac{p(y_{fit}, y_{held})}{p(y_{fit})},

i.e. the sum of the one-step predictive log densities of the held-out steps (leave-future-out:
each step is predicted from everything before it); ``log_z_held`` estimates its log. With exactly
observed states the density of the held-out steps given :math:`\theta` and the past is the product
of the one-step densities of those steps (the Markov property; the autocorrelated-noise state is
lifted from the step before, which may lie in the fitting window).

**Keys.** Each vehicle draws from its own key, the run's key with the vehicle's id folded in
(:func:`~bayesdrive.inference.core.vehicles.vehicle_keys`), so a vehicle's fit is the same bits whichever
other vehicles are fitted beside it: a criticism split into chunks of vehicles on a cluster gives
the plain run's result (:func:`~bayesdrive.inference.distributed.fit_model_on_cluster`).

Everything runs in the default float type (float32 unless x64 is on); tempering keeps the
log-likelihood differences between particles, not their absolute values, in the weights.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import fill_params
from bayesdrive.drivers.extensions.compose import ExtendedModel
from bayesdrive.inference.core.kernels import Box, Target, WalkState
from bayesdrive.inference.core.likelihood import StepInputs, step_inputs, step_logpdfs
from bayesdrive.inference.core.smc import TemperingConfig, adaptive_tempering, check_finished
from bayesdrive.inference.core.vehicles import map_vehicles, vehicle_keys

__all__ = [
    "BRIDGE_MAX_STAGES",
    "DEFAULT_CONFIG",
    "STUCK_MARGIN",
    "FitResult",
    "fit_model",
    "join_fits",
]

# The criticism's sampler: 128 particles, at least 4 moves a stage, then until every particle has
# likely moved (module docstring, "How many moves").
DEFAULT_CONFIG = TemperingConfig(num_particles=128, num_moves=4)
# A bridge from the base posterior is capped at this many stages (see fit_model).
BRIDGE_MAX_STAGES = 30
# Log evidence (nats) below the base model's at which an extension's fit counts as stuck.
STUCK_MARGIN = 10.0


class FitResult(NamedTuple):
    """Per-vehicle output of :func:`fit_model` (numpy).

    theta: (vehicle, particle, param) equally weighted draws from p(theta | fitting window).
    names: the parameter names, in the column order of ``theta``.
    log_z_fit: (vehicle,) log p(y_fit).
    log_z_held: (vehicle,) log p(y_held | y_fit), the held-out log predictive density.
    stages_fit, stages_held: (vehicle,) tempering stages used by each phase.
    from_prior: (vehicle,) True where phase 1 started from the prior, False where the bridge from
        the base posterior was used (see :func:`fit_model`).
    acceptance: (vehicle,) mean Metropolis-Hastings acceptance over all moves.
    compile_time_s, run_time_s: compile time and run time (compile excluded).
    """

    model: ExtendedModel
    names: tuple[str, ...]
    theta: np.ndarray
    log_z_fit: np.ndarray
    log_z_held: np.ndarray
    stages_fit: np.ndarray
    stages_held: np.ndarray
    from_prior: np.ndarray
    acceptance: np.ndarray
    compile_time_s: float
    run_time_s: float

    def take(self, rows) -> FitResult:
        """The fits of some vehicle rows (an index array or range)."""
        index = np.asarray(rows)
        per_vehicle = {
            name: value[index]
            for name, value in self._asdict().items()
            if isinstance(value, np.ndarray)
        }
        return self._replace(**per_vehicle)


def join_fits(parts: list[FitResult]) -> FitResult:
    """Fits of consecutive groups of vehicles as one (times summed)."""
    first = parts[0]
    joined = {
        name: np.concatenate([getattr(part, name) for part in parts])
        for name, value in first._asdict().items()
        if isinstance(value, np.ndarray)
    }
    return first._replace(
        **joined,
        compile_time_s=sum(part.compile_time_s for part in parts),
        run_time_s=sum(part.run_time_s for part in parts),
    )


def _window_logliks(
    extended: ExtendedModel, names: tuple[str, ...], theta: Array, steps: StepInputs
) -> tuple[Array, Array]:
    """(fit, held-out) log-likelihood sums for one parameter vector; unscored steps give 0."""
    logp = step_logpdfs(extended.model, fill_params(extended.model, names, theta), steps)
    fit = jnp.sum(jnp.where(steps.fit > 0, logp, 0.0))
    held = jnp.sum(jnp.where(steps.heldout > 0, logp, 0.0))
    return fit, held


def _new_and_old_columns(extended: ExtendedModel) -> tuple[np.ndarray, np.ndarray]:
    """Columns of the extension's new parameters and of the model it extends, in its layout."""
    names = extended.model.param_names
    new = [names.index(name) for name in extended.new_params]
    return np.array(new, int), np.array([i for i in range(len(names)) if i not in new], int)


class _VehicleFit(NamedTuple):
    theta: Array
    log_z_fit: Array
    log_z_held: Array
    stages_fit: Array
    stages_held: Array
    temperature: Array  # (phase,) where each phase's tempering stopped (1: finished)
    acceptance: Array


def _fit_vehicle(
    key: Array,
    steps: StepInputs,
    start_theta: Array | None,
    from_prior: Array,
    *,
    extended: ExtendedModel,
    config: TemperingConfig,
) -> _VehicleFit:
    """Both phases for one vehicle (module docstring and :func:`fit_model`).

    Phase 1 tempers ``tempered`` in on top of ``anchor``
    (:func:`~bayesdrive.inference.core.smc.adaptive_tempering`): from the prior,
    anchor 0 and tempered the fit-window log-likelihood; as a bridge from ``start_theta`` (base
    posterior draws, paired with prior draws of the new parameters), anchor the extension switched
    off (= the base model) and tempered the log-likelihood ratio of the extension to it. Which one
    is a runtime flag, so one compiled program serves both. Phase 2 continues with anchor the
    fit-window and tempered the held-out log-likelihood.
    """
    names = extended.model.param_names
    prior = extended.model.prior(names)
    key_prior, key_new, key_fit, key_held = jax.random.split(key, 4)
    theta = prior.sample(key_prior, (config.num_particles,))
    can_bridge = start_theta is not None
    if can_bridge:
        # The new parameters may sit anywhere among the model's (composites keep kind order).
        new_columns, old_columns = _new_and_old_columns(extended)
        new = extended.model.prior(extended.new_params).sample(key_new, (config.num_particles,))
        bridged = theta.at[:, old_columns].set(start_theta).at[:, new_columns].set(new)
        theta = jnp.where(from_prior, theta, bridged)
        off = jnp.asarray(
            [extended.model.spec(n).default for n in extended.new_params], theta.dtype
        )
    bridging = jnp.where(from_prior, 0.0, 1.0).astype(theta.dtype)

    def windows(th: Array) -> tuple[Array, Array, Array]:
        """(fit, held-out, fit with the extension off) log-likelihoods of one parameter vector."""
        if not can_bridge:
            fit, held = _window_logliks(extended, names, th, steps)
            return fit, held, jnp.zeros_like(fit)
        # On and off in one vectorised call, so the likelihood is traced (and compiled) once.
        both = jnp.stack([th, th.at[new_columns].set(off)])
        fit, held = jax.vmap(lambda t: _window_logliks(extended, names, t, steps))(both)
        return fit[0], held[0], fit[1]

    def split(phase: Array, th: Array) -> tuple[Array, Array]:
        """(anchor, tempered) of every particle in phase 0 (fitting) or 1 (held-out)."""
        fit, held, fit_off = jax.vmap(windows)(th)
        anchor = jnp.where(phase > 0, fit, bridging * fit_off)
        tempered = jnp.where(phase > 0, held, fit - bridging * fit_off)
        return anchor, tempered

    log_prior_of = jax.vmap(prior.logpdf)
    zero = jnp.zeros(theta.shape[0], theta.dtype)
    log_scale = jnp.log(2.38 / jnp.sqrt(theta.shape[-1])).astype(theta.dtype)
    fit_limit = jnp.where(from_prior, config.max_stages, BRIDGE_MAX_STAGES)

    def phase_step(carry, xs):
        # One traced body for both phases keeps the compiled program (and compile time) small.
        walk, moves, acceptance_sum = carry
        phase, key = xs
        anchor, tempered = split(phase, walk.theta)
        run = adaptive_tempering(
            key,
            walk._replace(anchor=anchor, tempered=tempered),
            target=Target(
                functools.partial(split, phase), log_prior_of, Box(prior.lower, prior.upper)
            ),
            config=config,
            max_stages=jnp.where(phase > 0, config.max_stages, fit_limit),
        )
        carry = (run.particles, moves + run.moves, acceptance_sum + run.acceptance_sum)
        return carry, (run.particles.theta, run.log_evidence, run.stages, run.temperature)

    start = WalkState(theta, log_prior_of(theta), zero, zero, log_scale)
    (_, moves, acceptance_sum), (thetas, log_z, stages, temperature) = jax.lax.scan(
        phase_step,
        (start, zero[0], zero[0]),
        (jnp.arange(2), jnp.stack([key_fit, key_held])),
    )
    return _VehicleFit(
        theta=thetas[0],
        log_z_fit=log_z[0],
        log_z_held=log_z[1],
        stages_fit=stages[0],
        stages_held=stages[1],
        temperature=temperature,
        acceptance=acceptance_sum / jnp.maximum(moves, 1.0),
    )


def fit_model(
    key: Array,
    series: FollowerArrays,
    extended: ExtendedModel,
    *,
    config: TemperingConfig = DEFAULT_CONFIG,
    start: FitResult | None = None,
    vehicle_batch: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> FitResult:
    """Fit ``extended`` to every vehicle's fitting window and score its held-out window.

    All the model's parameters are inferred under its uniform prior box. Vehicles run through
    :func:`~bayesdrive.inference.core.vehicles.map_vehicles`, as every engine's do: one vehicle per
    compiled call by default, or ``vehicle_batch`` of them vectorised together (one compile per
    model, settings and padded shape, cached for the process). ``series`` comes from
    :func:`~bayesdrive.data.views.scored_series` (its ``windows`` are the scored steps);
    ``progress(done, total)`` is called as vehicles finish. Batching changes only the speed, not
    the algorithm: under ``vmap`` the tempering and move loops run until the batch's slowest
    vehicle is done, so one vehicle at a time (the default) is faster on CPU cores.

    With ``start`` (the base model's fit of the same series and particle count), an extension
    whose phase 1 from the prior ends with a fit-window log evidence more than
    :data:`STUCK_MARGIN` below the base model's is refitted by a **bridge**: phase 1 then starts
    from the base posterior, each particle paired with a prior draw of the new parameters, and
    tempers the likelihood from the extension switched off (which is the base model) to the
    extension; the fit with the higher fit-window evidence is kept. The extension contains the
    base model, so its evidence can only fall that far below the base's when the sampler is stuck
    in a poor mode (a large AR coefficient absorbing a misfit mean, seen in tests); starting where
    the base model fits gets it out. A bridge is capped at :data:`BRIDGE_MAX_STAGES` stages (it is
    slow when the two posteriors are far apart, which is exactly when the prior start works). The
    choice uses the fitting window only. ``from_prior`` records it per vehicle.
    """
    steps = step_inputs(series, extended.model)
    num_vehicles = len(series.vehicle_ids)
    keys = vehicle_keys(key, series.vehicle_ids)
    start_theta = None
    if start is not None:
        expected = (num_vehicles, config.num_particles)
        _, old_columns = _new_and_old_columns(extended)
        if (
            start.names != tuple(extended.model.param_names[i] for i in old_columns)
            or start.theta.shape[:2] != expected
        ):
            raise ValueError(
                f"start fit ({start.model.name}, {start.theta.shape}) does not match "
                f"{extended.name} with {config.num_particles} particles on {num_vehicles} vehicles"
            )
        start_theta = jnp.asarray(start.theta, dtype=steps.v.dtype)
    per_vehicle = functools.partial(_fit_vehicle, extended=extended, config=config)

    def run(rows: np.ndarray, from_prior: bool, report: Callable[[int, int], None] | None):
        """Fit the vehicles ``rows``; returns numpy outputs, compile and run time."""
        # Rows picked in numpy: a JAX gather would compile a program per input shape.
        inputs = (
            keys[rows],
            jax.tree.map(lambda a: np.asarray(a)[rows], steps),
            None if start_theta is None else np.asarray(start_theta)[rows],
            np.full(len(rows), from_prior),
        )
        # The chunk is one batch, so the bridge's few vehicles reuse the first pass's program.
        return map_vehicles(
            per_vehicle,
            inputs,
            chunk=vehicle_batch,
            batch=vehicle_batch,
            progress=report,
            cache_key=("heldout_evidence", extended, config),
        )

    out, compile_time, run_time = run(np.arange(num_vehicles), True, progress)
    finished = np.all(out.temperature >= 1.0, axis=1)
    from_prior = np.ones(num_vehicles, bool)
    log_z_fit = np.asarray(out.log_z_fit, np.float64)
    if start is not None:
        # The extension contains the base model (switched off), so its evidence cannot fall far
        # below the base's: if it does, the sampler is stuck in a poor mode; bridge instead.
        stuck = np.flatnonzero(~finished | (log_z_fit < start.log_z_fit - STUCK_MARGIN))
        if stuck.size:
            bridged, more_compile, more_time = run(stuck, False, None)
            compile_time += more_compile
            run_time += more_time
            bridged_z = bridged.log_z_fit + start.log_z_fit[stuck]
            bridged_finished = np.all(bridged.temperature >= 1.0, axis=1)
            better = bridged_finished & (~finished[stuck] | (bridged_z > log_z_fit[stuck]))
            rows = stuck[better]
            chosen = jax.tree.map(lambda a: np.asarray(a)[better], bridged)
            out = jax.tree.map(lambda whole, part: _put(whole, rows, part), out, chosen)
            log_z_fit[rows] = bridged_z[better]
            from_prior[rows] = False
    check_finished(out.temperature.T, series.vehicle_ids, extended.name, config.max_stages)
    return FitResult(
        model=extended,
        names=extended.model.param_names,
        theta=out.theta,
        log_z_fit=log_z_fit,
        log_z_held=out.log_z_held,
        stages_fit=out.stages_fit,
        stages_held=out.stages_held,
        from_prior=from_prior,
        acceptance=out.acceptance,
        compile_time_s=compile_time,
        run_time_s=run_time,
    )


def _put(whole: np.ndarray, rows: np.ndarray, part: np.ndarray) -> np.ndarray:
    """``whole`` with ``rows`` replaced by ``part``."""
    whole = np.array(whole)
    whole[rows] = part
    return whole
