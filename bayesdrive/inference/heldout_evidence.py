r"""Fitting any (extended) driver model and scoring its held-out predictive density, per vehicle.

**Why a second assembly beside ``smc``.** The engines fit one window; the criticism needs the
fitting-window posterior *and* its continuation into the held-out window (phase 2 below), whose
normalising constant is the held-out predictive density. Both are assembled from the sampler
core (:mod:`bayesdrive.inference.kernels`: the temperature search, the random-walk move on the
logit scale and the stopping rules), and every model's steps come from the model itself
(:func:`~bayesdrive.inference.likelihood.step_inputs`, :func:`~bayesdrive.inference.likelihood.step_logpdfs`).
For the base model its log-evidence is checked against ``smc``'s in the tests.

**The sampler.** Adaptive-tempering SMC (Del Moral, Doucet & Jasra 2006; Jasra et al. 2011) for
each vehicle. Phase 1 bridges from the prior to the fitting-window posterior through
:math:`\pi_\lambda \propto p(\theta)\, p(y_{fit} \mid \theta)^\lambda`, each temperature chosen by
bisection so that the incremental weights keep an effective sample size of ``ess_target * N``;
after each reweighting the particles are resampled (systematic) and moved by ``num_moves``
random-walk Metropolis-Hastings steps invariant for :math:`\pi_\lambda` (on the logit scale of the
prior box, Gaussian proposal with the particles' covariance there scaled by :math:`s`, :math:`s`
adapted towards acceptance 0.234). The product
of the mean incremental weights estimates :math:`p(y_{fit})` (``log_z_fit``).

**How many moves.** A fixed handful of moves at acceptance ~0.23 leaves about a third of the
particles where resampling put them (0.77^4 = 0.35); stage after stage the cloud then loses
spread, and a posterior that is broad along a curved ridge (the noise sd at standstill against its
growth with speed, in the speed-dependent-noise extension) can end up one narrow sliver of it.
The held-out density continued from such a cloud is that of one parameter value, not of the
posterior: in a detection run one vehicle's held-out density fell 4216 nats below the base
model's, although the extension nests it (posterior sd of the slope 0.005, while the fit-window
log-likelihood stays within 5 nats of its maximum for slopes from 0.11 to 0.49; with 16 moves, or
512 particles, the sd was 0.08-0.13 and that vehicle gained 6-8 nats). With
``unmoved_tolerance`` c > 0 each stage keeps moving, past ``num_moves``, until the estimated
probability that a particle has not moved at all, :math:`\prod_m (1 - \text{acceptance}_m)`, is
at most c (Drovandi & Pettitt 2011, c = 0.01; South, Pettitt & Drovandi 2019), at most
``max_moves`` moves; c = 0 keeps exactly ``num_moves``. The default is c = 0.01 with 128 particles:
on 20 vehicles x 60 s with a hidden reaction delay it ran in 0.8 times the time of 5 fixed moves
with 256 particles (side by side) and gave the same verdict and ranking, with gains within 5%
(reaction delay 921 +- 213 nats against 906 +- 212); the detection study
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
(:func:`~bayesdrive.inference.vehicles.vehicle_keys`), so a vehicle's fit is the same bits whichever
other vehicles are fitted beside it: a criticism split into chunks of vehicles on a cluster gives
the plain run's result (:func:`~bayesdrive.inference.distributed.fit_model_on_cluster`).

Everything runs in the default float type (float32 unless x64 is on); tempering keeps the
log-likelihood differences between particles, not their absolute values, in the weights.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import fill_params
from bayesdrive.drivers.extensions.compose import ExtendedModel
from bayesdrive.inference.kernels import (
    Box,
    WalkState,
    fixed_moves,
    moves_until_moved,
    next_temperature,
    to_free,
    walk_step,
)
from bayesdrive.inference.likelihood import StepInputs, step_inputs, step_logpdfs
from bayesdrive.inference.resampling import systematic
from bayesdrive.inference.vehicles import vehicle_keys
from bayesdrive.inference.weights import log_mean_weight

__all__ = [
    "DEFAULT_CONFIG",
    "FitConfig",
    "FitResult",
    "fit_model",
    "join_fits",
]


class FitConfig(NamedTuple):
    """Settings of the tempering sampler (module docstring)."""

    num_particles: int = 128
    num_moves: int = 4
    ess_target: float = 0.5
    max_stages: int = 200
    bridge_max_stages: int = 30
    stuck_margin: float = 10.0
    target_acceptance: float = 0.234
    # Keep moving past num_moves until prod(1 - acceptance) <= this (0: exactly num_moves).
    unmoved_tolerance: float = 0.01
    max_moves: int = 64


DEFAULT_CONFIG = FitConfig()
# Bisection steps of the temperature search.
BISECTION_STEPS = 50


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


class _Cloud(NamedTuple):
    theta: Array  # (N, d)
    log_prior: Array  # (N,)
    anchor: Array  # (N,) log-likelihood fully included in the target
    tempered: Array  # (N,) log-likelihood being tempered in
    lam: Array  # () current temperature
    log_z: Array  # ()
    log_scale: Array  # ()
    stages: Array  # ()
    max_stages: Array  # () stop after this many stages even if lam < 1
    accepted: Array  # () sum of acceptance rates
    moves: Array  # () number of move sweeps


def _temper(
    key: Array,
    cloud: _Cloud,
    loglik: Callable[[Array], tuple[Array, Array]],
    prior: Any,
    config: FitConfig,
) -> _Cloud:
    """Temper ``cloud.tempered`` in from lam = 0 to 1 (module docstring); anchor stays at 1.

    Each stage is the sampler core's (:mod:`bayesdrive.inference.kernels`): the next temperature
    by bisection, systematic resampling, then random-walk moves on the logit scale of the prior
    box with the resampled cloud's covariance, until every particle has likely moved."""
    d = cloud.theta.shape[1]
    box = Box(prior.lower, prior.upper)
    prior_logpdf = jax.vmap(prior.logpdf)
    # A floor on the proposal covariance keeps moves alive when resampling leaves one survivor.
    jitter = jnp.diag(jnp.full(d, 1e-6, cloud.theta.dtype))

    def stage(carry):
        cloud, key = carry
        key, key_resample, key_moves = jax.random.split(key, 3)
        new_lam = next_temperature(cloud.tempered, cloud.lam, config.ess_target, BISECTION_STEPS)
        increment = (new_lam - cloud.lam) * cloud.tempered
        log_z = cloud.log_z + log_mean_weight(increment)
        parents = systematic(key_resample, increment)
        walk = WalkState(
            theta=cloud.theta[parents],
            log_prior=cloud.log_prior[parents],
            anchor=cloud.anchor[parents],
            tempered=cloud.tempered[parents],
            log_scale=cloud.log_scale,
        )
        free = to_free(walk.theta, box)
        chol = jnp.linalg.cholesky(jnp.cov(free, rowvar=False).reshape(d, d) + jitter)
        move = functools.partial(
            walk_step,
            loglik=loglik,
            prior_logpdf=prior_logpdf,
            power=new_lam,
            chol=chol,
            box=box,
            target_acceptance=config.target_acceptance,
        )
        if config.unmoved_tolerance > 0:
            walk, num_moves, rate_sum = moves_until_moved(
                key_moves,
                walk,
                move,
                num_moves=config.num_moves,
                unmoved_tolerance=config.unmoved_tolerance,
                max_moves=config.max_moves,
            )
        else:
            walk, rate = fixed_moves(key_moves, walk, move, config.num_moves)
            num_moves = jnp.asarray(config.num_moves, walk.theta.dtype)
            rate_sum = rate * num_moves
        moved = _Cloud(
            theta=walk.theta,
            log_prior=walk.log_prior,
            anchor=walk.anchor,
            tempered=walk.tempered,
            lam=new_lam,
            log_z=log_z,
            log_scale=walk.log_scale,
            stages=cloud.stages + 1,
            max_stages=cloud.max_stages,
            accepted=cloud.accepted + rate_sum,
            moves=cloud.moves + num_moves,
        )
        return moved, key

    def unfinished(carry):
        cloud, _ = carry
        return (cloud.lam < 1.0) & (cloud.stages < cloud.max_stages)

    cloud, _ = jax.lax.while_loop(unfinished, stage, (cloud, key))
    return cloud


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
    finished: Array
    acceptance: Array


def _fit_vehicle(
    key: Array,
    steps: StepInputs,
    start_theta: Array | None,
    from_prior: Array,
    *,
    extended: ExtendedModel,
    config: FitConfig,
) -> _VehicleFit:
    """Both phases for one vehicle (module docstring and :func:`fit_model`).

    Phase 1 tempers ``tempered`` in on top of ``anchor`` (see :func:`_temper`): from the prior,
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

    zero = jnp.zeros((), theta.dtype)
    cloud = _Cloud(
        theta=theta,
        log_prior=jax.vmap(prior.logpdf)(theta),
        anchor=jnp.zeros(theta.shape[0], theta.dtype),
        tempered=jnp.zeros(theta.shape[0], theta.dtype),
        lam=zero,
        log_z=zero,
        log_scale=jnp.log(2.38 / jnp.sqrt(theta.shape[-1])).astype(theta.dtype),
        stages=jnp.zeros((), jnp.int32),
        max_stages=jnp.zeros((), jnp.int32),
        accepted=zero,
        moves=zero,
    )
    fit_limit = jnp.where(from_prior, config.max_stages, config.bridge_max_stages)

    def phase_step(cloud: _Cloud, xs):
        # One traced body for both phases keeps the compiled program (and compile time) small.
        phase, key = xs
        anchor, tempered = split(phase, cloud.theta)
        cloud = cloud._replace(
            anchor=anchor,
            tempered=tempered,
            lam=zero,
            log_z=zero,
            stages=jnp.zeros_like(cloud.stages),
            max_stages=jnp.where(phase > 0, config.max_stages, fit_limit).astype(jnp.int32),
        )
        cloud = _temper(key, cloud, lambda th: split(phase, th), prior, config)
        return cloud, (cloud.theta, cloud.log_z, cloud.stages, cloud.lam)

    cloud, (thetas, log_z, stages, lam) = jax.lax.scan(
        phase_step, cloud, (jnp.arange(2), jnp.stack([key_fit, key_held]))
    )
    return _VehicleFit(
        theta=thetas[0],
        log_z_fit=log_z[0],
        log_z_held=log_z[1],
        stages_fit=stages[0],
        stages_held=stages[1],
        finished=jnp.all(lam >= 1.0),
        acceptance=cloud.accepted / jnp.maximum(cloud.moves, 1.0),
    )


# Compiled per-batch programs, keyed by model, settings and input shapes: every criticism run in a
# process (and every test) reuses them, so a model compiles once per padded shape.
_COMPILED: dict[Any, Any] = {}


def _compiled_batch(
    extended: ExtendedModel,
    config: FitConfig,
    keys: Array,
    steps: StepInputs,
    start_theta: Array | None,
    from_prior: Array,
):
    """The jitted, vmapped per-vehicle fit for this batch shape; returns (function, compile time)."""
    leaves = jax.tree.leaves((steps, start_theta, from_prior))
    shapes = tuple((a.shape, str(a.dtype)) for a in leaves)
    signature = (extended, config, keys.shape, start_theta is None, shapes)
    if signature in _COMPILED:
        return _COMPILED[signature], 0.0
    per_vehicle = functools.partial(_fit_vehicle, extended=extended, config=config)
    started = time.perf_counter()
    compiled = jax.jit(jax.vmap(per_vehicle)).lower(keys, steps, start_theta, from_prior).compile()
    _COMPILED[signature] = compiled
    return compiled, time.perf_counter() - started


def fit_model(
    key: Array,
    series: FollowerArrays,
    extended: ExtendedModel,
    *,
    config: FitConfig = DEFAULT_CONFIG,
    start: FitResult | None = None,
    vehicle_batch: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> FitResult:
    """Fit ``extended`` to every vehicle's fitting window and score its held-out window.

    All the model's parameters are inferred under its uniform prior box. Vehicles are vectorised
    ``vehicle_batch`` at a time (the last batch is padded by repeating its last vehicle, so one
    program serves every batch: one compile per model and padded shape, cached for the process).
    ``series`` comes from :func:`~bayesdrive.data.views.scored_series` (its ``windows`` are the
    scored steps); ``progress(done, total)`` is called after each batch. Batching changes only the speed, not the algorithm: under ``vmap``
    the tempering and move loops run until the batch's slowest vehicle is done, so one vehicle
    at a time (the default) was 1.6-2.2x faster at fixed moves and 1.7-2.3x at moves until moved
    (20 vehicles x 60 s, 256 particles; a single vehicle's 256 particles x steps already fill
    the vector units).

    With ``start`` (the base model's fit of the same series and particle count), an extension
    whose phase 1 from the prior ends with a fit-window log evidence more than ``stuck_margin``
    below the base model's is refitted by a **bridge**: phase 1 then starts from the base
    posterior, each particle paired with a prior draw of the new parameters, and tempers the
    likelihood from the extension switched off (which is the base model) to the extension; the
    fit with the higher fit-window evidence is kept. The extension contains the base model, so its
    evidence can only fall that far below the base's when the sampler is stuck in a poor mode (a
    large AR coefficient absorbing a misfit mean, seen in tests); starting where the base model
    fits gets it out. A bridge is capped at ``bridge_max_stages`` (it is slow when the two
    posteriors are far apart, which is exactly when the prior start works). The choice uses the
    fitting window only. ``from_prior`` records it per vehicle.
    """
    steps = step_inputs(series, extended.model)
    num_vehicles = len(series.vehicle_ids)
    # Batches are multiples of 8 vehicles, so data sets of similar size share one compiled program.
    batch = max(1, min(vehicle_batch, 8 * math.ceil(num_vehicles / 8)))
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

    def run(rows: np.ndarray, from_prior: bool):
        """Fit the vehicles ``rows`` in padded batches; returns numpy outputs and times."""
        flag = jnp.full(batch, from_prior)

        def batch_inputs(first: int):
            picked = rows[np.minimum(np.arange(first, first + batch), len(rows) - 1)]
            chosen = None if start_theta is None else start_theta[picked]
            return keys[picked], jax.tree.map(lambda a: a[picked], steps), chosen, flag

        compiled, compile_time = _compiled_batch(extended, config, *batch_inputs(0))
        pieces, run_time = [], 0.0
        for first in range(0, len(rows), batch):
            started = time.perf_counter()
            out = jax.block_until_ready(compiled(*batch_inputs(first)))
            run_time += time.perf_counter() - started
            keep = min(batch, len(rows) - first)
            pieces.append(jax.tree.map(lambda a, keep=keep: np.asarray(a)[:keep], out))
            if progress is not None:
                progress(first + keep, num_vehicles)
        out = jax.tree.map(lambda *parts: np.concatenate(parts), *pieces)
        return out, compile_time, run_time

    everyone = np.arange(num_vehicles)
    out, compile_time, run_time = run(everyone, from_prior=True)
    from_prior = np.ones(num_vehicles, bool)
    log_z_fit = np.asarray(out.log_z_fit, np.float64)
    if start is not None:
        # The extension contains the base model (switched off), so its evidence cannot fall far
        # below the base's: if it does, the sampler is stuck in a poor mode; bridge instead.
        stuck = np.flatnonzero(~out.finished | (log_z_fit < start.log_z_fit - config.stuck_margin))
        if stuck.size:
            bridged, _, more_time = run(stuck, from_prior=False)
            run_time += more_time
            bridged_z = bridged.log_z_fit + start.log_z_fit[stuck]
            better = bridged.finished & (~out.finished[stuck] | (bridged_z > log_z_fit[stuck]))
            rows = stuck[better]
            chosen = jax.tree.map(lambda a: np.asarray(a)[better], bridged)
            out = jax.tree.map(lambda whole, part: _put(whole, rows, part), out, chosen)
            log_z_fit[rows] = bridged_z[better]
            from_prior[rows] = False
    if not out.finished.all():
        raise FloatingPointError(
            f"{extended.name}: tempering did not reach the posterior within {config.max_stages} "
            f"stages for vehicle rows {np.flatnonzero(~out.finished).tolist()}"
        )
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
