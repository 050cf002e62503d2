r"""The latent-state engine: a particle filter over hidden states, and PMMH over the parameters.

With measurement noise on positions (:func:`bayesdrive.drivers.measurement_noise.with_measurement_noise`)
the true states are hidden, so the likelihood of a parameter vector is an integral over state paths.
:func:`state_filter_loglik` estimates it with a bootstrap particle filter over states (Gordon et al.
1993): particles move by the model's ``transition_sample``, are weighted by its
``observation_logpdf`` and resampled systematically when the effective sample size falls below half
the particles (the SMC core's step, :func:`bayesdrive.inference.core.smc.step`, with the
observation density as its potential; the transition is the filter's proposal). The estimate of the likelihood (not of its log) is unbiased, which is what particle
marginal Metropolis-Hastings needs (Andrieu, Doucet & Holenstein 2010): :func:`pmmh` runs a
random-walk Metropolis chain over the static parameters in which the exact likelihood is replaced
by that estimate, and still targets the exact posterior.

**What is estimated.** :math:`p(y_{1:T} \mid y_0, v_0; \theta)` for every run of consecutive
usable steps (a *segment*): the first reading of a segment starts the latent state (the model's
``initial_sample``), every later reading is scored. Masked steps (padding, flagged samples, steps
outside the window) end a segment; the next usable step starts a new one, so the log-likelihood is
the sum over segments and padding contributes exactly 0.

**Frames and inputs.** Latent positions are offsets from the observed position of the same step
(see :mod:`bayesdrive.drivers.measurement_noise`): a particle at offset :math:`e_t` moves to
:math:`e_t + \Delta` on step t's axis, which is :math:`e_t + \Delta - (y_{t+1} - y_t)` on step t+1's
axis, with the observed increment ``dx`` computed in float64 by the data layer; every observation
is then ``x = 0``. The inputs are the base model's (:class:`~bayesdrive.drivers.base.CarFollowingInputs`
or the Cooperative IDM's ``MergeInputs``) with their ego distances read as positions on step t's
axis: ``gap`` is the leader's rear bumper relative to the observed ego front, i.e. the observed
bumper gap of the data layer, and each particle sees ``gap - e_t`` (``shift_ego``) -- the gap to
its own latent position, never to the noisy reading.

**Engine.** :func:`run` is the ``pmmh`` engine (the :class:`~bayesdrive.inference.fit.Engine`
signature, returning an :class:`~bayesdrive.inference.core.output.EngineResult`). Each vehicle's
chains and scoring filters draw from the vehicle's own key, the seed with its id folded in
(:mod:`bayesdrive.inference.core.vehicles`), so a vehicle's draws do not depend on the others.
Chains and vehicles are flattened into lanes of one ``vmap`` level: nested ``vmap`` of the threefry RNG multiplies XLA
compile time on CPU. **Starting values matter**: far from the posterior the
filter degenerates, its estimate's variance explodes and PMMH chains stick; warm-up from prior
draws can take thousands of iterations (``benchmarks/bench_latent.py`` measures it). Choose
``num_state_particles`` so that the estimate's sd at the posterior is about 1-1.7 nats (Doucet et
al. 2015); the variance grows like kappa T / N.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any, NamedTuple, Unpack

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel, EgoState, fill_params
from bayesdrive.drivers.measurement_noise import shift_ego
from bayesdrive.inference.core.likelihood import StepInputs, step_inputs
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.smc import SMCState
from bayesdrive.inference.core.smc import step as smc_step
from bayesdrive.inference.core.vehicles import (
    log_likelihood_draws,
    map_vehicles,
    posterior_draws,
    prepare,
    static_key,
)

__all__ = [
    "ADAPTATION_DECAY",
    "ADAPTATION_FLOOR",
    "ADAPTATION_OFFSET",
    "RESAMPLE_BELOW",
    "FilterInfo",
    "PMMHResult",
    "PositionObservations",
    "check_model",
    "latent_data",
    "noisy_readings",
    "pmmh",
    "run",
    "state_filter_loglik",
]

# Resample when the effective sample size falls below this fraction of the particles.
RESAMPLE_BELOW = 0.5
# PMMH warm-up adaptation (adaptive Metropolis, Haario et al. 2001, with Robbins-Monro gains as in
# Andrieu & Thoms 2008): the proposal covariance tracks 2.38^2/d times the chain's covariance with
# gain (i + 1 + ADAPTATION_OFFSET)^-ADAPTATION_DECAY (the offset makes the initial proposal count
# like ~20 draws, so a few early rejections cannot collapse it), plus a floor of ADAPTATION_FLOOR
# times the initial step sd so that a chain stuck during warm-up keeps proposing moves.
ADAPTATION_DECAY = 0.6
ADAPTATION_OFFSET = 20.0
ADAPTATION_FLOOR = 0.05


class PositionObservations(NamedTuple):
    """One vehicle's noisy readings, step t = the move from sample t to t+1 (leading axis: step).

    dx: observed position increment y[t+1] - y[t] (m), computed in float64 by the data layer.
    v: recorded speed at sample t (m/s); used only as the latent speed where a segment starts.
    mask: 1 where the move t -> t+1 is real and scored, 0 for padding and excluded steps.
    """

    dx: Array
    v: Array
    mask: Array


class FilterInfo(NamedTuple):
    """Per-step diagnostics of one filter run (leading axis: step; masked steps hold N, False, 0).

    ess: effective sample size after weighting by the reading at t+1, before any resampling.
    resampled: whether the particles were resampled at that step.
    log_increments: log p(y[t+1] | earlier readings of the segment); they sum to the estimate.
    """

    ess: Array
    resampled: Array
    log_increments: Array


class PMMHResult(NamedTuple):
    """PMMH chains after warm-up, dims (chain, draw, vehicle[, param]) (numpy arrays).

    samples: (chain, draw, vehicle, param) parameter draws, columns in the order of ``names``.
    log_likelihood: (chain, draw, vehicle) the likelihood estimate each draw carries.
    acceptance_rate: (chain, vehicle) fraction of accepted proposals after warm-up.
    names: the inferred parameters.
    compile_time_s, wall_time_s: compilation (0 when cached) and the sampling itself.
    """

    samples: np.ndarray
    log_likelihood: np.ndarray
    acceptance_rate: np.ndarray
    names: tuple[str, ...]
    compile_time_s: float
    wall_time_s: float


def check_model(model: DriverModel) -> None:
    """Refuse, in one line, a model whose states are observed exactly (nothing to filter)."""
    if model.observed_exactly:
        raise ValueError(
            f"engine 'pmmh' filters hidden states, but model {model.name!r} observes them exactly; "
            "use its '+measurement_noise' variant (bayesdrive.drivers.measurement_noise)"
        )


def latent_data(arrays: FollowerArrays, model: DriverModel) -> tuple[PositionObservations, Any]:
    """Readings and ``model``'s own inputs for the latent engine from the padded (vehicle, step)
    arrays.

    The data layer's bumper gap, leader rear minus observed ego front, is exactly the leader's rear
    on each step's local axis (module docstring); arrays are cast to the default float type.
    """
    return _readings(step_inputs(arrays, model))


def _readings(steps: StepInputs) -> tuple[PositionObservations, Any]:
    """The readings and the model's inputs of ``steps``."""
    return PositionObservations(dx=steps.dx, v=steps.v, mask=steps.mask), steps.inputs


def _check_series(observations: PositionObservations, inputs: Any, leading: tuple[int, ...]):
    """Every field of the readings and the inputs must share the leading shape ``leading``."""
    fields = {
        **{f"observations.{k}": v for k, v in observations._asdict().items()},
        **{f"inputs.{k}": v for k, v in inputs._asdict().items()},
    }
    wrong = {k: jnp.shape(v) for k, v in fields.items() if jnp.shape(v)[: len(leading)] != leading}
    if wrong:
        raise ValueError(
            f"readings and inputs must share the leading shape {leading}; mismatched: {wrong}"
        )


def _where(condition: Array, new: Any, old: Any) -> Any:
    """``new`` where ``condition`` holds, else ``old``, leaf by leaf (condition is a scalar)."""
    return jax.tree.map(lambda a, b: jnp.where(condition, a, b), new, old)


def state_filter_loglik(
    key: Array,
    model: DriverModel,
    params: Any,
    observations: PositionObservations,
    inputs: Any,
    num_state_particles: int,
) -> tuple[Array, FilterInfo]:
    """Bootstrap-filter estimate of one vehicle's log-likelihood for fixed ``params``.

    ``observations`` and ``inputs`` have a leading step axis (T,); ``params`` is the model's
    parameter tuple. Returns the log of an unbiased likelihood estimate (module docstring for what
    is conditioned on) and per-step :class:`FilterInfo`. Each step's randomness comes from
    ``fold_in(key, step)``, so padding a series with masked steps leaves the estimate unchanged.
    Pure and traceable: ``jit`` and ``vmap`` it freely (``num_state_particles`` static).
    """
    if num_state_particles < 2:
        raise ValueError(f"num_state_particles must be at least 2, got {num_state_particles}")
    num_steps = jnp.shape(observations.mask)[0]
    _check_series(observations, inputs, (num_steps,))
    n = num_state_particles
    uniform = jnp.full((n,), -jnp.log(n))
    zero = jnp.zeros((), dtype=observations.dx.dtype)

    def step(carry, xs):
        states, log_weights, loglik, previous_mask = carry
        t, obs, inp = xs
        init_key, move_key, resample_key = jax.random.split(jax.random.fold_in(key, t), 3)

        # A segment starts after a masked step (and at t = 0): fresh particles, equal weights.
        first_reading = EgoState(x=zero, v=obs.v)
        fresh = jax.vmap(lambda k: model.initial_sample(k, params, first_reading))(
            jax.random.split(init_key, n)
        )
        starts = previous_mask <= 0
        states = _where(starts, fresh, states)
        log_weights = jnp.where(starts, uniform, log_weights)

        def move(k, state):
            moved = model.transition_sample(k, params, state, shift_ego(inp, state.x))
            # Re-centre on the next observed position.
            return moved._replace(x=moved.x - obs.dx)

        moved = jax.vmap(move)(jax.random.split(move_key, n), states)
        # The next reading sits at 0 on its own axis; its speed is no observation (NaN says so).
        reading = EgoState(x=zero, v=jnp.full_like(zero, jnp.nan))

        def potential(particles: EgoState) -> Array:
            return jax.vmap(lambda s: model.observation_logpdf(params, s, reading))(particles)

        # The SMC core's step, the transition above being the filter's proposal: reweight by the
        # reading, resample below half the particles' ESS; nothing moves after resampling.
        filtered, info = smc_step(
            resample_key,
            SMCState(moved, log_weights),
            potential,
            lambda _, particles: (particles, None),
            resample_below=RESAMPLE_BELOW,
        )

        used = obs.mask > 0
        increment = jnp.where(used, info.log_increment, 0.0)
        carry = (
            _where(used, filtered.particles, states),
            jnp.where(used, filtered.log_weights, log_weights),
            loglik + increment,
            obs.mask,
        )
        return carry, FilterInfo(
            ess=jnp.where(used, info.ess, float(n)),
            resampled=used & info.resampled,
            log_increments=increment,
        )

    placeholder = EgoState(x=jnp.zeros((n,), zero.dtype), v=jnp.zeros((n,), zero.dtype))
    start = (placeholder, uniform, zero, jnp.zeros_like(observations.mask[0]))
    (_, _, loglik, _), info = jax.lax.scan(
        step, start, (jnp.arange(num_steps), observations, inputs)
    )
    return loglik, info


def pmmh(
    keys: Array,
    model: DriverModel,
    names: Sequence[str],
    observations: PositionObservations,
    inputs: Any,
    *,
    num_iterations: int,
    num_state_particles: int,
    proposal_scale: float | Sequence[float],
    num_chains: int = 4,
    num_warmup: int = 0,
    init: Array | None = None,
    fixed: Any = None,
    vehicle_chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> PMMHResult:
    """Particle marginal Metropolis-Hastings for every vehicle.

    ``observations`` and ``inputs`` have leading axes (vehicle, step). For each chain and vehicle a
    random-walk Metropolis chain moves the parameters ``names`` (the others from ``fixed``, a full
    parameter tuple, default the model's defaults) by Gaussian steps. A proposal outside the
    uniform prior box is rejected; inside, it is accepted with probability
    min(1, L(proposal) / L(current)), both likelihoods estimated by :func:`state_filter_loglik` with
    ``num_state_particles`` particles, and the current estimate is kept until the next acceptance
    (which is what makes PMMH exact).

    The steps start with sd ``proposal_scale`` times each parameter's prior width (a scalar or one
    value per name). During the ``num_warmup`` discarded iterations the proposal covariance adapts
    to 2.38^2/d times the chain's running covariance (adaptive Metropolis; see
    :data:`ADAPTATION_DECAY`); it is frozen for the ``num_iterations`` kept ones, so those form an
    ordinary, exact PMMH chain. Chains start at ``init`` (broadcast to (chain, vehicle, param)) or,
    by default, at independent prior draws.

    ``keys`` hold one PRNG key per vehicle (vehicle,), e.g. from
    :func:`~bayesdrive.inference.core.vehicles.vehicle_keys`; all of a vehicle's randomness comes from
    its key, so results do not depend on ``vehicle_chunk``: how many vehicles one compiled call
    vectorises (default: all);
    ``progress(done, total)`` is called after each chunk. Chains and vehicles are vectorised with
    ``vmap``, iterations run in ``lax.scan``; compiled once per model, settings and shape.
    """
    names = tuple(names)
    prior = model.prior(names)
    num_vehicles, num_steps = jnp.shape(observations.mask)
    _check_series(observations, inputs, (num_vehicles, num_steps))
    scale = np.broadcast_to(np.asarray(proposal_scale, dtype=float), (len(names),))
    if not np.all(scale > 0):
        raise ValueError(f"proposal_scale must be positive, got {proposal_scale!r}")
    if num_iterations < 1 or num_warmup < 0 or num_chains < 1:
        raise ValueError(
            f"need num_iterations >= 1, num_warmup >= 0, num_chains >= 1; got {num_iterations}, "
            f"{num_warmup}, {num_chains}"
        )
    if num_state_particles < 2:
        raise ValueError(f"num_state_particles must be at least 2, got {num_state_particles}")

    if jnp.shape(keys)[:1] != (num_vehicles,):
        raise ValueError(f"need one key per vehicle ({num_vehicles}), got keys {jnp.shape(keys)}")
    init_keys, chain_keys = jnp.swapaxes(jax.vmap(jax.random.split)(keys), 0, 1)
    if init is None:
        start = jax.vmap(lambda k: prior.sample(k, (num_chains,)))(init_keys)
    else:
        shape = (num_chains, num_vehicles, len(names))
        start = jnp.swapaxes(jnp.broadcast_to(jnp.asarray(init, dtype=float), shape), 0, 1)
        outside = ~np.asarray(jnp.isfinite(jax.vmap(jax.vmap(prior.logpdf))(start)))
        if outside.any():
            vehicle, chain = np.argwhere(outside)[0]
            raise ValueError(
                f"init for chain {chain}, vehicle {vehicle} is {np.asarray(start[vehicle, chain])} "
                f"for {names}, outside the prior box [{np.asarray(prior.lower)}, "
                f"{np.asarray(prior.upper)}]"
            )
    fixed = model.defaults() if fixed is None else fixed
    step_sd = scale * np.asarray(prior.upper - prior.lower)
    fixed_key = static_key(fixed)
    # Everything the compiled chain depends on besides the input shapes.
    cache_key = (
        None
        if fixed_key is None
        else (
            "pmmh",
            model,
            names,
            fixed_key,
            tuple(step_sd.tolist()),
            num_state_particles,
            num_warmup,
            num_iterations,
        )
    )
    chain = partial(
        _chain,
        model=model,
        names=names,
        fixed=fixed,
        step_sd=step_sd,
        num_state_particles=num_state_particles,
        num_warmup=num_warmup,
        num_iterations=num_iterations,
    )
    # One lane per (vehicle, chain): a single vmap level compiles far faster than nested ones.
    lane_keys = jax.vmap(lambda k: jax.random.split(k, num_chains))(chain_keys)
    (thetas, logliks, acceptance), compile_time, run_time = _map_lanes(
        chain,
        (lane_keys, start),
        (observations, inputs),
        vehicle_chunk=num_vehicles if vehicle_chunk is None else vehicle_chunk,
        progress=progress,
        cache_key=cache_key,
    )
    # (vehicle, chain, draw, ...) -> (chain, draw, vehicle, ...)
    return PMMHResult(
        samples=np.moveaxis(thetas, 0, 2),
        log_likelihood=np.moveaxis(logliks, 0, 2),
        acceptance_rate=acceptance.T,
        names=names,
        compile_time_s=compile_time,
        wall_time_s=run_time,
    )


def _map_lanes(
    per_lane: Callable[..., Any],
    lane_inputs: tuple[Any, ...],
    vehicle_inputs: tuple[Any, ...],
    *,
    vehicle_chunk: int,
    progress: Callable[[int, int], None] | None = None,
    cache_key: Any = None,
) -> tuple[Any, float, float]:
    """``per_lane`` over lanes: ``lane_inputs`` have leading axes (vehicle, lane), and each
    vehicle's ``vehicle_inputs`` (leading axis vehicle) go to all its lanes. Runs through
    :func:`~bayesdrive.inference.core.vehicles.map_vehicles` with the lanes of ``vehicle_chunk``
    vehicles vectorised together; outputs come back as (vehicle, lane, ...)."""
    num_vehicles, num_lanes = jax.tree.leaves(lane_inputs)[0].shape[:2]
    flat = jax.tree.map(lambda a: a.reshape(num_vehicles * num_lanes, *a.shape[2:]), lane_inputs)
    repeated = jax.tree.map(lambda a: jnp.repeat(a, num_lanes, axis=0), vehicle_inputs)
    chunk = min(vehicle_chunk, num_vehicles) * num_lanes
    out, compile_time, run_time = map_vehicles(
        per_lane,
        (*flat, *repeated),
        chunk=chunk,
        batch=chunk,
        progress=None
        if progress is None
        else lambda done, total: progress(done // num_lanes, total // num_lanes),
        cache_key=cache_key,
    )
    unflat = jax.tree.map(lambda a: a.reshape(num_vehicles, num_lanes, *a.shape[1:]), out)
    return unflat, compile_time, run_time


class _Proposal(NamedTuple):
    """The adaptive random walk's state: running mean of the chain and the proposal covariance."""

    mean: Array
    cov: Array


def _chain(
    key: Array,
    theta0: Array,
    observations: PositionObservations,
    inputs: Any,
    *,
    model: DriverModel,
    names: tuple[str, ...],
    fixed: Any,
    step_sd: np.ndarray,
    num_state_particles: int,
    num_warmup: int,
    num_iterations: int,
) -> tuple[Array, Array, Array]:
    """One PMMH chain of one vehicle from ``theta0``: the kept draws (draw, param), the estimates
    they carry (draw,) and the acceptance rate after warm-up."""
    prior = model.prior(names)
    step_sd = jnp.asarray(step_sd, dtype=prior.lower.dtype)
    floor = jnp.diag((ADAPTATION_FLOOR * step_sd) ** 2)
    optimal_scale = 2.38**2 / len(names)  # Gelman, Roberts & Gilks 1996

    def loglik(k: Array, theta: Array) -> Array:
        params = fill_params(model, names, theta, fixed)
        value, _ = state_filter_loglik(k, model, params, observations, inputs, num_state_particles)
        return jnp.where(jnp.isnan(value), -jnp.inf, value)

    def iteration(carry, i):
        theta, current, proposal = carry
        propose_key, filter_key, accept_key = jax.random.split(jax.random.fold_in(key, i), 3)
        root = jnp.linalg.cholesky(proposal.cov + floor)
        # Iteration 0 proposes the start itself: its estimate is accepted unless not finite.
        moves = jnp.where(i > 0, 1.0, 0.0)
        candidate_theta = theta + moves * root @ jax.random.normal(propose_key, theta.shape)
        inside = jnp.isfinite(prior.logpdf(candidate_theta))
        # Under vmap the filter runs outside the box too; -inf makes sure it cannot win.
        candidate = jnp.where(inside, loglik(filter_key, candidate_theta), -jnp.inf)
        accept = jnp.log(jax.random.uniform(accept_key)) < candidate - current
        theta = jnp.where(accept, candidate_theta, theta)
        current = jnp.where(accept, candidate, current)

        # Robbins-Monro steps with decaying gain during warm-up, none afterwards.
        gain = jnp.where(i < num_warmup, (i + 1.0 + ADAPTATION_OFFSET) ** -ADAPTATION_DECAY, 0.0)
        centred = theta - proposal.mean
        target = optimal_scale * jnp.outer(centred, centred)
        proposal = _Proposal(
            mean=proposal.mean + gain * centred,
            cov=proposal.cov + gain * (target - proposal.cov),
        )
        return (theta, current, proposal), (theta, current, accept)

    unknown = jnp.full((), -jnp.inf, step_sd.dtype)
    first = (theta0, unknown, _Proposal(mean=theta0, cov=jnp.diag(step_sd**2)))
    _, (thetas, logliks, accepted) = jax.lax.scan(
        iteration, first, jnp.arange(num_warmup + num_iterations)
    )
    kept = slice(num_warmup, None)
    return thetas[kept], logliks[kept], jnp.mean(accepted[kept])


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    num_state_particles: int = 128,
    num_chains: int = 4,
    num_warmup: int = 1000,
    proposal_scale: float | Sequence[float] = 0.01,
    init: str | Array = "prior",
    vehicle_chunk: int = 16,
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """The ``pmmh`` engine of :func:`bayesdrive.inference.fit.fit`: :func:`pmmh` on ``arrays``.

    ``model`` must observe positions with noise (:func:`~bayesdrive.drivers.measurement_noise.
    with_measurement_noise`); ``prior`` must be None (the model's uniform box). Posterior draws are
    (chain, draw, vehicle): ``num_particles`` draws in all, ``num_particles / num_chains`` (rounded
    up) per chain after ``num_warmup`` warm-up iterations, each likelihood estimated with
    ``num_state_particles`` state particles. ``init`` is "prior" (independent prior draws),
    "defaults" (every chain at the model's defaults) or starting values broadcast to
    (chain, vehicle, param), e.g. from an exact-state fit. The ``log_likelihood`` group holds, for
    every draw, the filter's per-step log-increments
    log p(y[t+1] | earlier readings): Monte Carlo estimates, not exact densities. ``sample_stats``:
    ``acceptance_rate`` [chain, vehicle], ``log_likelihood_estimate`` [chain, draw, vehicle] (the
    estimate each draw carries) and ``filter_ess`` [vehicle, step] (the state filter's effective
    sample size, averaged over the draws).
    """
    if inputs.get("prior") is not None:
        raise ValueError("engine 'pmmh' samples under the model's uniform prior box; prior=None")
    if isinstance(init, str) and init not in ("prior", "defaults"):
        raise ValueError(f"init must be 'prior', 'defaults' or an array, got {init!r}")
    problem = prepare("pmmh", arrays, inputs, num_particles=1000, check=check_model)
    model, names, fixed_values = problem.model, problem.names, problem.fixed
    num_particles = problem.num_particles
    num_draws = -(-num_particles // max(num_chains, 1))
    observations, inputs = _readings(problem.series)
    chains_keys, score_keys = jnp.swapaxes(jax.vmap(jax.random.split)(problem.keys(key)), 0, 1)
    result = pmmh(
        chains_keys,
        model,
        names,
        observations,
        inputs,
        num_iterations=num_draws,
        num_state_particles=num_state_particles,
        proposal_scale=proposal_scale,
        num_chains=num_chains,
        num_warmup=num_warmup,
        init=_starting_values(model, names, init),
        fixed=fixed_values,
        vehicle_chunk=vehicle_chunk,
        progress=problem.progress,
    )

    draws = np.moveaxis(result.samples, 2, 0)  # (vehicle, chain, draw, d)
    num_vehicles = draws.shape[0]
    lanes = num_chains * num_draws
    lane_keys = jax.vmap(lambda k: jax.random.split(k, lanes))(score_keys)
    fixed_key = static_key(fixed_values)
    (increments, ess), score_compile_time, score_run_time = _map_lanes(
        partial(
            _score_draw,
            model=model,
            names=names,
            fixed=fixed_values,
            num_state_particles=num_state_particles,
        ),
        (lane_keys, jnp.asarray(draws.reshape(num_vehicles, lanes, -1), dtype=float)),
        (observations, inputs),
        vehicle_chunk=vehicle_chunk,
        cache_key=None
        if fixed_key is None
        else ("pmmh-score", model, names, fixed_key, num_state_particles),
    )
    by_draw = (num_vehicles, num_chains, num_draws, -1)
    increments, ess = increments.reshape(by_draw), ess.reshape(by_draw)
    return EngineResult(
        posterior=posterior_draws(names, draws),
        sample_stats={
            "acceptance_rate": (("chain", "vehicle"), result.acceptance_rate),
            "log_likelihood_estimate": (("chain", "draw", "vehicle"), result.log_likelihood),
            "filter_ess": (("vehicle", "step"), ess.mean(axis=(1, 2))),
        },
        log_likelihood=log_likelihood_draws(increments),
        compile_time_s=result.compile_time_s + score_compile_time,
        wall_time_s=result.wall_time_s + score_run_time,
        options={
            "num_state_particles": num_state_particles,
            "num_chains": num_chains,
            "num_draws_per_chain": num_draws,
            "num_warmup": num_warmup,
            "proposal_scale": np.broadcast_to(proposal_scale, (len(names),)).tolist(),
            "init": init if isinstance(init, str) else "given",
            "resampler": "systematic",
            "resample_below": RESAMPLE_BELOW,
            "adaptation": {
                "decay": ADAPTATION_DECAY,
                "offset": ADAPTATION_OFFSET,
                "floor": ADAPTATION_FLOOR,
            },
            "vehicle_chunk": vehicle_chunk,
        },
    )


def _starting_values(model: DriverModel, names: tuple[str, ...], init: str | Array) -> Array | None:
    """:func:`run`'s ``init`` as :func:`pmmh` takes it (None: prior draws)."""
    if isinstance(init, str):
        return None if init == "prior" else jnp.asarray([model.spec(n).default for n in names])
    return jnp.asarray(init, dtype=float)


def _score_draw(
    key: Array,
    theta: Array,
    observations: PositionObservations,
    inputs: Any,
    *,
    model: DriverModel,
    names: tuple[str, ...],
    fixed: Any,
    num_state_particles: int,
) -> tuple[Array, Array]:
    """The filter's per-step log-increments and ESS (step,) for one vehicle under one draw."""
    params = fill_params(model, names, theta, fixed)
    _, info = state_filter_loglik(key, model, params, observations, inputs, num_state_particles)
    return info.log_increments, info.ess


def noisy_readings(key: Array, arrays: FollowerArrays, sigma_obs: float) -> FollowerArrays:
    """``arrays`` of exactly observed states, read through Gaussian position noise of sd ``sigma_obs``.

    Each sample t gets its own reading error e_t ~ N(0, sigma_obs^2), shared by the two steps that
    meet at it: the increment becomes dx + e[t+1] - e[t] and the gap (to the exactly observed
    leader) gap - e[t]. Speeds, inputs and masks are unchanged. For simulation studies and tests.
    """
    num_vehicles, num_steps = arrays.mask.shape
    errors = sigma_obs * np.asarray(
        jax.random.normal(key, (num_vehicles, num_steps + 1)), dtype=np.float64
    )
    return arrays._replace(
        dx=arrays.dx + errors[:, 1:] - errors[:, :-1], gap=arrays.gap - errors[:, :-1]
    )
