"""The emcee engine: seeded reproducibility, exact answer in one dimension, the result layout.

The exact check mirrors tests/inference/test_nuts.py: sigma of one IDM vehicle (64 steps, sigma = 0.5,
seed 3) against quadrature. emcee's draws are thinned by the autocorrelation time, so they are
treated as independent: the mean must lie within 4 sd / sqrt(draws) of the exact mean and the sd
within 4 / sqrt(2 draws) relative (each fails with probability about 1e-4 for a correct sampler).
The same check must fail for the deliberately wrong sd-doubled likelihood.
"""

import logging

import emcee as emcee_lib
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.drivers.base import fill_params
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.diagnostics.agreement import grid_posterior
from bayesdrive.inference.diagnostics.sbc import sd_doubled
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import emcee
from bayesdrive.inference.fit import fit

SEED = 3
OPTIONS = {"num_steps": 1200, "num_particles": 500}


@pytest.fixture(scope="module")
def vehicle():
    params = jax.vmap(lambda th: fill_params(IDM, ("sigma",), th))(jnp.array([[0.5]]))
    return simulate_following(jax.random.key(SEED), IDM, params, num_steps=64)


@pytest.fixture(scope="module")
def result(vehicle):
    return emcee.run(jax.random.key(SEED), vehicle, model=IDM, params=["sigma"], **OPTIONS)


def matches_exact(vehicle, draws: np.ndarray) -> bool:
    grid, density = grid_posterior(vehicle, IDM, "sigma")
    mean = np.trapezoid(grid * density, grid)
    sd = np.sqrt(np.trapezoid((grid - mean) ** 2 * density, grid))
    n = draws.size
    return abs(draws.mean() - mean) <= 4 * sd / np.sqrt(n) and abs(draws.std() / sd - 1) <= 4 / (
        np.sqrt(2 * n)
    )


def test_emcee_matches_exact_posterior(vehicle, result):
    assert matches_exact(vehicle, result.posterior["sigma"])


def test_sd_doubled_likelihood_fails_the_same_check(vehicle):
    wrong = emcee.run(
        jax.random.key(SEED), vehicle, model=sd_doubled(IDM), params=["sigma"], **OPTIONS
    )
    assert not matches_exact(vehicle, wrong.posterior["sigma"])


def test_same_seed_gives_identical_chains_and_other_seeds_differ(vehicle, result):
    again = emcee.run(jax.random.key(SEED), vehicle, model=IDM, params=["sigma"], **OPTIONS)
    np.testing.assert_array_equal(again.posterior["sigma"], result.posterior["sigma"])
    np.testing.assert_array_equal(again.sample_stats["seed"][1], result.sample_stats["seed"][1])
    other = emcee.run(jax.random.key(SEED + 1), vehicle, model=IDM, params=["sigma"], **OPTIONS)
    assert not np.array_equal(other.posterior["sigma"], result.posterior["sigma"])


def test_layout_single_chain_thinned_by_autocorrelation(result):
    draws = result.posterior["sigma"]
    assert draws.shape[0] == 1 and draws.shape[2] == 1
    tau = result.sample_stats["autocorr_time"][1]
    thin = result.sample_stats["thin"][1]
    assert result.sample_stats["autocorr_time"][0] == ("vehicle", "param")
    assert thin[0] == int(np.ceil(tau.max()))
    walkers = result.options["num_walkers"]
    steps, burn = (result.sample_stats[k][1][0] for k in ("num_steps", "num_burn"))
    assert walkers == 32 and burn == steps // 2  # the burn-in stays half of an extended run too
    # Kept: every thin-th step after burn-in, all walkers; at most num_particles of them.
    available = walkers * len(range(burn + thin[0] - 1, steps, thin[0]))
    assert result.sample_stats["kept_draws"][1][0] == available
    assert draws.shape[1] == min(available, OPTIONS["num_particles"])
    assert bool(result.sample_stats["autocorr_reliable"][1][0]) == (
        steps - burn > emcee.AUTOCORR_RELIABLE_FACTOR * tau.max()
    )


def test_walker_rule():
    assert [emcee.num_walkers_for(d) for d in (1, 6, 8, 9, 12)] == [32, 32, 32, 36, 48]


def test_too_few_walkers_are_refused(vehicle):
    with pytest.raises(ValueError, match="num_walkers"):
        emcee.run(jax.random.key(0), vehicle, model=IDM, params=["sigma", "tau"], num_walkers=3)


def test_a_short_run_extends_to_fifty_tau_and_a_capped_one_warns_with_the_next_step(
    vehicle, caplog
):
    """300 steps (150 kept) are under 50 tau of sigma: the run continues its chains, doubling,
    up to 8x (2400), and passes fit's checks. Negative control: capped at 300 steps the same run
    must fail the 50-tau check, and the warning must say what to run next."""
    options = {"model": IDM, "engine": "emcee", "params": ["sigma"], "draws": 1000}
    extended = fit(jax.random.key(SEED), vehicle, num_steps=300, **options)
    steps = int(extended["sample_stats"]["num_steps"].values[0])
    assert 300 < steps <= emcee.MAX_EXTENSION * 300
    assert metadata(extended)["convergence"]["problems"] == []
    with caplog.at_level(logging.WARNING, logger="bayesdrive.inference.diagnostics.convergence"):
        capped = fit(jax.random.key(SEED), vehicle, num_steps=300, max_steps=300, **options)
    assert int(capped["sample_stats"]["num_steps"].values[0]) == 300
    problems = metadata(capped)["convergence"]["problems"]
    assert ("sim0", "sigma", "autocorr") in {
        (p["vehicle"], p["param"], p["check"]) for p in problems
    }
    warnings = [r.getMessage() for r in caplog.records if "not converged" in r.getMessage()]
    assert warnings and all("next: " in w and "--steps 600" in w for w in warnings)


def _trap_target(points: np.ndarray) -> np.ndarray:
    """A standard normal in 2-D with a far, narrow local mode of tiny mass at (20, 20): a
    walker there proposes only points of far lower density, so it stays."""
    main = -0.5 * np.sum(points**2, axis=-1)
    trap = -20.0 - 0.5 * np.sum(((points - 20.0) / 0.05) ** 2, axis=-1) + 2 * np.log(1 / 0.05)
    return np.logaddexp(main, trap)


def _ensemble(seed: int, trapped: bool, steps: int = 600):
    rng = np.random.default_rng(seed)
    start = rng.normal(size=(32, 2))
    if trapped:
        start[5] = 20.0 + 0.01 * rng.normal(size=2)
    sampler = emcee_lib.EnsembleSampler(32, 2, _trap_target, vectorize=True)
    sampler.run_mcmc(
        emcee_lib.State(start, random_state=np.random.RandomState(seed).get_state()), steps
    )
    return sampler


def test_a_walker_stranded_in_a_local_mode_is_found_and_restarted_beside_the_others():
    """Seeds 0-4: walker 5 starts in the trap and is still there after 600 steps (the failure
    the rule is for); the rule flags it and no other, and the restart puts it among the free
    walkers. Negative control: the same ensemble started without the trap flags no walker."""
    for seed in range(5):
        sampler = _ensemble(seed, trapped=True)
        assert np.all(sampler.get_last_sample().coords[5] > 19)
        stuck = emcee.stuck_walkers(sampler.get_log_prob(discard=300))
        assert np.flatnonzero(stuck) == [5]
        state, count = emcee.restart_stuck(sampler, stuck, np.random.default_rng(seed))
        assert count == 1 and np.all(np.abs(state.coords) < 6)
        free = _ensemble(seed, trapped=False)
        none_stuck = emcee.stuck_walkers(free.get_log_prob(discard=300))
        assert not none_stuck.any()
        state, count = emcee.restart_stuck(free, none_stuck, np.random.default_rng(seed))
        assert count == 0 and np.array_equal(state.coords, free.get_last_sample().coords)


def test_a_window_too_short_for_the_quantile_flags_nothing():
    sampler = _ensemble(0, trapped=True, steps=emcee.STUCK_MIN_WINDOW - 1)
    assert not emcee.stuck_walkers(sampler.get_log_prob()).any()


@pytest.mark.parametrize("starts, peak", [(emcee.MODE_STARTS, 0.8), (1, 0.2)])
def test_the_start_polishes_several_candidates_and_keeps_the_best_mode(starts, peak):
    """A broad lesser mode at 0.2 (height 0) and a narrow peak at 0.8 (height 5, width 0.05): the
    most probable candidate (0.25) lies in the broad mode's basin, the second (0.68) in the peak's.
    Polishing several finds the peak; polishing the best alone (the negative control) stays in
    the lesser mode."""

    def log_density(theta):
        x = theta[..., 0]
        return jnp.maximum(-(((x - 0.2) / 0.3) ** 2), 5.0 - ((x - 0.8) / 0.05) ** 2)

    candidates = jnp.array([[[0.25], [0.68]], [[0.05], [0.95]]])
    bounds = type("Bounds", (), {"lower": jnp.zeros(1), "upper": jnp.ones(1)})()
    mode = emcee._posterior_mode(
        candidates,
        lambda p: np.asarray(log_density(jnp.asarray(p))),
        jax.value_and_grad(log_density),
        bounds,
        starts=starts,
    )
    assert mode == pytest.approx([peak], abs=1e-3)
