r"""``emcee``: the affine-invariant ensemble sampler (Goodman & Weare 2010), a second cross-check.

Per vehicle one ``emcee.EnsembleSampler`` with ``max(4 d, 32)`` walkers targets
the same posterior as every engine: the model's uniform prior box times the masked sum of
``model.transition_logpdf`` (the shared :func:`~bayesdrive.inference.core.likelihood.series_loglik`).
The log posterior is one jitted JAX function, vectorised over walkers (``vectorize=True``: one call
scores the whole ensemble) and compiled once for every vehicle, since all share one padded shape.

**Start.** An ensemble only contracts geometrically: walkers started at prior draws take very
many steps to find a posterior a small fraction of the prior width wide, as NGSIM's are. So, as
emcee's authors advise, walkers start in a tiny ball (``START_BALL`` of the prior width) around a
posterior mode: of ``START_CANDIDATES`` prior draws per walker, the ``MODE_STARTS`` most
probable are each polished by L-BFGS-B on the box with JAX gradients, and the best optimum wins.
One polished draw is not enough: the most probable prior draw can lie in the wide basin of a
lesser mode (on an NGSIM follower with the second-leader anticipation, a mode 5 nats below the
posterior's peak, where every walker stayed and passed its checks;
``reports/convergence/extensions_ngsim15.md``, "Stop 44"). The moves expand such a ball within
tens of steps, well inside the burn-in; the price is that a second, distant mode goes unseen (the
particle engines and NUTS' dispersed chains are the check for that).

**Moves.** ``move="stretch"`` (default): Goodman and Weare's stretch move, emcee's default.
``move="de"``: differential evolution (``DEMove``) on 80% of the steps and the DE snooker move on
20%. The DE mixture decorrelates in fewer steps, but on trafficgen followers its posterior sds
came out narrower than smc's and nuts' (tails it visits too rarely for its own autocorrelation
estimate to tell; ``reports/convergence.md``): a cross-check must not be fast and wrong, so the
stretch move stays the default and runs longer (``MAX_EXTENSION``).

**Seeding.** Each vehicle's key (the seed with its id folded in,
:mod:`bayesdrive.inference.core.vehicles`) gives its mode-search candidates, its start ball and a
32-bit seed, so a vehicle's chains are the same whichever vehicles it is fitted with, in whatever
order; the ensemble's numpy
``RandomState`` is seeded with it through ``emcee.State(p0, random_state=...)`` (emcee's own
``random_state`` setter swallows errors, so the state is handed over with the initial positions),
and the seed is recorded per vehicle. The same key gives identical chains.

**Draws.** Walkers of one ensemble are not independent chains (every move uses the others), so
R-hat over walkers means nothing. The first ``num_burn`` steps (default: half) are discarded; the
integrated autocorrelation time ``tau`` of each parameter is estimated on the rest
(``get_autocorr_time``; it is trustworthy when the kept run is longer than 50 tau,
recorded as ``autocorr_reliable``); the kept steps are thinned by ``ceil(max tau)`` and the walkers
flattened into one chain (``chain = 1``). Vehicles with different tau have different numbers of
thinned draws; all keep the same number (``num_particles``, or the smallest over vehicles if
lower), taking their latest thinned draws.

**Extension.** After ``num_steps`` each vehicle's run is checked as
:func:`~bayesdrive.inference.fit.fit` will check it: kept steps at least 50 tau, bulk and tail ESS
of the stored draws at least 400 (:mod:`bayesdrive.inference.diagnostics.convergence`). A vehicle that fails
continues the same chains, doubling the run, with the burn-in the same fraction of it, up to
``max_steps`` (default :data:`MAX_EXTENSION` times ``num_steps``, or ``num_steps`` when fewer than
:data:`~bayesdrive.inference.diagnostics.convergence.EXTENSION_MIN_DRAWS` draws are kept). Why: the
stretch move's autocorrelation time grows with the number of parameters and with a long-tailed
marginal, and it is only known once the run is long enough to estimate it
(``reports/convergence.md``). ``sample_stats`` records each vehicle's ``num_steps`` and
``num_burn``; fit's 50-tau check uses them.

**Stuck walkers.** A walker can strand in a region of far lower posterior density (a local mode,
a plateau of a parameter the data do not reach), where every stretch towards the others is
rejected; one such walker of 32 puts 3% of the draws there. Hou et al. (2012) drop such walkers;
here they restart: a walker is stuck in a window of steps when its median log posterior lies
below the typical walker's 1% quantile (the median over walkers of their ``STUCK_QUANTILE``
quantiles), which a walker at stationarity all but never does. At the end of the burn-in, and at
each extension where the whole run so far becomes burn-in, stuck walkers (judged on the last half
of the burn-in, or on the kept steps before the extension) move next to a randomly chosen free
walker; the kept steps are a Markov chain from that start, as from any other. A vehicle whose kept
steps still hold a stuck walker extends as one that fails its checks, and at the cap fit reports
it (``stuck_walkers``; ``restarted_walkers`` counts the restarts).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Unpack

import emcee
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.inference.core.likelihood import series_loglik
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.vehicles import one_chain_result, prepare
from bayesdrive.inference.diagnostics.convergence import (
    AUTOCORR_RELIABLE_FACTOR,
    EXTENSION_MIN_DRAWS,
    chain_problems,
)

__all__ = [
    "AUTOCORR_RELIABLE_FACTOR",
    "MAX_EXTENSION",
    "MODE_STARTS",
    "MOVES",
    "START_BALL",
    "START_CANDIDATES",
    "STUCK_MIN_WINDOW",
    "STUCK_QUANTILE",
    "num_walkers_for",
    "restart_stuck",
    "run",
    "stuck_walkers",
]

# Prior draws per walker searched for the optimiser's starting points, how many of the best the
# optimiser polishes (module docstring, "Start"), and the start ball's radius as a fraction of
# each prior interval.
START_CANDIDATES = 32
MODE_STARTS = 8
START_BALL = 1e-4
# A vehicle that fails fit's checks continues its run, doubling it, up to this many times
# num_steps (module docstring, "Extension").
MAX_EXTENSION = 64
# A walker is stuck when its median log posterior over a window lies below what the typical
# walker of the ensemble falls to this rarely (module docstring, "Stuck walkers"); the window must
# hold enough steps for that quantile to mean something.
STUCK_QUANTILE = 0.01
STUCK_MIN_WINDOW = 100
# The ensemble moves with their weights (module docstring, "Moves").
MOVES = {
    "de": lambda: [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)],
    "stretch": lambda: [(emcee.moves.StretchMove(), 1.0)],
}


def num_walkers_for(dim: int) -> int:
    """Ensemble size for ``dim`` parameters: max(4 dim, 32)."""
    return max(4 * dim, 32)


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    num_steps: int = 4000,
    num_burn: int | None = None,
    num_walkers: int | None = None,
    max_steps: int | None = None,
    move: str = "stretch",
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """emcee for every vehicle of ``arrays`` (module docstring).

    Each vehicle keeps its latest ``num_particles`` thinned draws, or fewer when some vehicle has
    fewer (then all keep that many). ``prior`` (default: the model's uniform box) needs
    ``logpdf(theta)`` and ``sample(key, shape)``; the mode search stays inside the box.

    ``sample_stats`` holds per vehicle ``autocorr_time`` [vehicle, param], ``thin``,
    ``kept_draws`` (before the common truncation), ``autocorr_reliable``, ``acceptance_fraction``
    (mean over walkers) and the numpy ``seed`` of its ensemble.
    """
    problem = prepare("emcee", arrays, inputs, num_particles=2000, whole_series=True)
    names, box, prior, fixed_values = problem.names, problem.box, problem.prior, problem.fixed
    model, num_particles, progress = problem.model, problem.num_particles, problem.progress
    dim = len(names)
    walkers = num_walkers_for(dim) if num_walkers is None else num_walkers
    burn = num_steps // 2 if num_burn is None else num_burn
    if max_steps is None:  # fewer draws than EXTENSION_MIN_DRAWS cannot show ESS 400
        max_steps = MAX_EXTENSION * num_steps if num_particles >= EXTENSION_MIN_DRAWS else num_steps
    if move not in MOVES:
        raise ValueError(f"unknown move {move!r}; choose one of {sorted(MOVES)}")
    if walkers < 2 * dim or not 0 <= burn < num_steps - 1 or max_steps < num_steps:
        raise ValueError(
            f"need num_walkers >= 2 * {dim}, 0 <= num_burn < num_steps - 1 and max_steps >= "
            f"num_steps, got num_walkers={walkers}, num_burn={burn}, num_steps={num_steps}, "
            f"max_steps={max_steps}"
        )
    lower, upper = np.asarray(box.lower, np.float64), np.asarray(box.upper, np.float64)
    width = upper - lower
    series, num_vehicles = problem.series, problem.num_vehicles

    def log_posterior(thetas: Array, vehicle: Any) -> Array:
        log_prior = jax.vmap(prior.logpdf)(thetas)
        log_lik = jax.vmap(lambda th: series_loglik(model, names, fixed_values, th, vehicle).sum())(
            thetas
        )
        # Outside the box the likelihood may be NaN (e.g. sigma < 0); the prior decides there.
        return jnp.where(jnp.isfinite(log_prior), log_prior + log_lik, -jnp.inf)

    def vehicle_series(i: int) -> Any:
        return jax.tree.map(lambda a: a[i], series)

    # Every move scores half of the ensemble at a time, the initial state all of it:
    # compile both shapes up front, so the timed runs hold no compilation.
    started = time.perf_counter()
    log_posterior = jax.jit(log_posterior)
    for size in {walkers, walkers // 2, walkers - walkers // 2}:
        example = jnp.broadcast_to((box.lower + box.upper) / 2, (size, dim))
        jax.block_until_ready(log_posterior(example, vehicle_series(0)))
    log_density_and_grad = jax.jit(
        jax.value_and_grad(lambda th, vehicle: log_posterior(th[None], vehicle)[0])
    )
    jax.block_until_ready(log_density_and_grad(example[0], vehicle_series(0)))
    compile_time = time.perf_counter() - started

    def vehicle_start(key: Array) -> tuple[Array, Array, Array]:
        """One vehicle's mode-search candidates, start-ball offsets and ensemble seed."""
        key_candidates, key_ball, key_seed = jax.random.split(key, 3)
        return (
            prior.sample(key_candidates, (START_CANDIDATES, walkers)),
            jax.random.normal(key_ball, (walkers, dim)),
            jax.random.bits(key_seed, (), dtype=jnp.uint32),
        )

    candidates, balls, seeds = jax.vmap(vehicle_start)(problem.keys(key))
    balls, seeds = np.asarray(balls), np.asarray(seeds).astype(np.int64)

    chains, taus, thins, kept, acceptance, run_steps = [], [], [], [], [], []
    stuck_counts, restarts = [], []
    rngs = [np.random.default_rng(seed) for seed in seeds]
    run_time = 0.0
    for i in range(num_vehicles):
        vehicle = vehicle_series(i)

        def log_prob(p: np.ndarray, vehicle=vehicle) -> np.ndarray:
            thetas = jnp.asarray(p, dtype=box.lower.dtype)
            return np.asarray(log_posterior(thetas, vehicle), dtype=np.float64)

        started = time.perf_counter()
        mode = _posterior_mode(
            candidates[i],
            lambda p, vehicle=vehicle: log_prob(p, vehicle),
            lambda th, vehicle=vehicle: log_density_and_grad(th, vehicle),
            box,
        )
        start = np.clip(
            mode + START_BALL * width * balls[i],
            lower + START_BALL * width,
            upper - START_BALL * width,
        )
        sampler = emcee.EnsembleSampler(walkers, dim, log_prob, moves=MOVES[move](), vectorize=True)
        state = emcee.State(start, random_state=np.random.RandomState(seeds[i]).get_state())
        restarted = 0
        if burn:
            sampler.run_mcmc(state, burn, progress=False)
            late_burn = stuck_walkers(sampler.get_log_prob(discard=burn // 2))
            state, restarted = restart_stuck(sampler, late_burn, rngs[i])
        sampler.run_mcmc(state, num_steps - burn, progress=False)
        steps, vehicle_burn = num_steps, burn
        while True:
            # tol=0: the 50-tau check is recorded per vehicle (autocorr_reliable), not logged.
            tau = sampler.get_autocorr_time(discard=vehicle_burn, tol=0)
            thin = max(1, math.ceil(float(np.max(tau))))
            draws = sampler.get_chain(discard=vehicle_burn, thin=thin, flat=True)
            stuck = stuck_walkers(sampler.get_log_prob(discard=vehicle_burn))
            if steps >= max_steps or (
                not stuck.any()
                and _converged(
                    problem.vehicle_ids[i], names, draws[-num_particles:], tau, steps - vehicle_burn
                )
            ):
                break
            # Extension: double the run, continuing the same chains; the burn-in stays the
            # same fraction of it, so the first steps, furthest from stationarity, are dropped.
            # Where all that ran so far becomes burn-in, stuck walkers restart there.
            more = min(steps, max_steps - steps)
            new_burn = (steps + more) * burn // num_steps
            state = None
            if new_burn >= steps:
                state, count = restart_stuck(sampler, stuck, rngs[i])
                restarted += count
            sampler.run_mcmc(state, more, progress=False)
            vehicle_burn = new_burn
            steps += more
        run_time += time.perf_counter() - started
        chains.append(draws)
        taus.append(tau)
        thins.append(thin)
        run_steps.append((steps, vehicle_burn))
        kept.append(len(draws))
        stuck_counts.append(int(stuck.sum()))
        restarts.append(restarted)
        acceptance.append(float(np.mean(sampler.acceptance_fraction)))
        if progress is not None:
            progress(i + 1, num_vehicles)

    started = time.perf_counter()
    common = min(*kept, num_particles)
    theta = np.stack([draws[-common:] for draws in chains])  # (vehicle, draw, d)
    log_lik = problem.pointwise_scores(theta)  # (vehicle, draw, step)
    run_time += time.perf_counter() - started
    tau_array = np.asarray(taus)
    steps_array, burn_array = np.asarray(run_steps).T
    return one_chain_result(
        names,
        theta,
        log_lik,
        sample_stats={
            "autocorr_time": (("vehicle", "param"), tau_array),
            "thin": (("vehicle",), np.asarray(thins)),
            "kept_draws": (("vehicle",), np.asarray(kept)),
            "autocorr_reliable": (
                ("vehicle",),
                (steps_array - burn_array) > AUTOCORR_RELIABLE_FACTOR * tau_array.max(axis=1),
            ),
            "num_steps": (("vehicle",), steps_array),
            "num_burn": (("vehicle",), burn_array),
            "acceptance_fraction": (("vehicle",), np.asarray(acceptance)),
            "stuck_walkers": (("vehicle",), np.asarray(stuck_counts)),
            "restarted_walkers": (("vehicle",), np.asarray(restarts)),
            "seed": (("vehicle",), seeds),
        },
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            "num_steps": num_steps,
            "num_burn": burn,
            "num_walkers": walkers,
            "max_steps": max_steps,
            "move": move,
        },
    )


def stuck_walkers(log_prob: np.ndarray) -> np.ndarray:
    """(steps, walkers) log posteriors -> which walkers are stuck (module docstring): a walker
    whose median lies below the median over walkers of their STUCK_QUANTILE quantiles. None is,
    in a window shorter than STUCK_MIN_WINDOW steps."""
    if len(log_prob) < STUCK_MIN_WINDOW:
        return np.zeros(log_prob.shape[1], bool)
    floor = np.median(np.quantile(log_prob, STUCK_QUANTILE, axis=0))
    return np.median(log_prob, axis=0) < floor


def restart_stuck(
    sampler: emcee.EnsembleSampler, stuck: np.ndarray, rng: np.random.Generator
) -> tuple[emcee.State, int]:
    """The ensemble's last state, with each ``stuck`` walker (:func:`stuck_walkers`) moved next to
    a randomly chosen free walker (a tiny ball, as at the start), and how many moved."""
    coords = sampler.get_last_sample().coords.copy()
    count = int(stuck.sum())
    if count == 0 or count == len(stuck):
        return emcee.State(coords), 0
    free = coords[~stuck]
    donors = free[rng.choice(len(free), size=count)]
    coords[stuck] = donors + START_BALL * free.std(axis=0) * rng.standard_normal(donors.shape)
    return emcee.State(coords), count


def _converged(
    vehicle: str, names: tuple[str, ...], draws: np.ndarray, tau: np.ndarray, kept_steps: int
) -> bool:
    """Whether one vehicle's run passes fit's emcee checks: at least 50 tau after burn-in, and
    bulk and tail ESS of the stored (thinned, flattened) draws."""
    if kept_steps < AUTOCORR_RELIABLE_FACTOR * float(np.max(tau)):
        return False
    return not chain_problems(vehicle, names, draws[None], rhat=False)


def _posterior_mode(
    candidates: Array,
    log_prob: Callable[[np.ndarray], np.ndarray],
    log_density_and_grad: Callable[[Array], tuple[Array, Array]],
    box: Any,
    starts: int = MODE_STARTS,
) -> np.ndarray:
    """A posterior mode: the ``starts`` most probable of (batches, walkers, d) prior draws, each
    polished by L-BFGS-B, the best optimum (never worse than the best draw)."""
    scores = np.stack([log_prob(np.asarray(batch)) for batch in candidates]).ravel()
    flat = np.asarray(candidates).reshape(-1, candidates.shape[-1]).astype(np.float64)
    order = np.argsort(-np.where(np.isnan(scores), -np.inf, scores), kind="stable")

    def negative(theta: np.ndarray) -> tuple[float, np.ndarray]:
        value, grad = log_density_and_grad(jnp.asarray(theta, dtype=box.lower.dtype))
        return -float(value), -np.asarray(grad, dtype=np.float64)

    bounds = list(zip(np.asarray(box.lower), np.asarray(box.upper), strict=True))
    # A float32 line search may stop early, so the best draw itself stays a candidate.
    best, best_score = flat[order[0]], scores[order[0]]
    for index in order[:starts]:
        found = scipy.optimize.minimize(
            negative, flat[index], jac=True, method="L-BFGS-B", bounds=bounds
        )
        if -found.fun > best_score:
            best, best_score = found.x, -found.fun
    return best
