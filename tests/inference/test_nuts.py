"""The nuts engine: exact answer in one dimension, same seed -> same bits, the result layout.

The exact check: one vehicle simulated by the stochastic IDM (64 steps, sigma = 0.5, seed 3),
sigma inferred with the other parameters at their (true) defaults, so the posterior is a 1-D
integral computed by quadrature (:func:`bayesdrive.inference.agreement.grid_posterior`). NUTS
must match its mean within 4 Monte Carlo standard errors (ArviZ MCSE) and its sd within
4 / sqrt(2 ESS) relative (the sampling sd of an sd estimate), both failing with probability
about 1e-4 for a correct sampler. Other SBC-based checks of nuts live in tests/inference/test_sbc.py.
"""

import arviz
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.drivers.base import fill_params
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference import nuts
from bayesdrive.inference.agreement import grid_posterior
from bayesdrive.inference.likelihood import series_loglik, step_inputs
from bayesdrive.inference.synthetic import simulate_following

SEED = 3
OPTIONS = {"num_chains": 4, "num_warmup": 200, "num_particles": 1000}


@pytest.fixture(scope="module")
def vehicle():
    params = jax.vmap(lambda th: fill_params(IDM, ("sigma",), th))(jnp.array([[0.5]]))
    return simulate_following(jax.random.key(SEED), IDM, params, num_steps=64)


@pytest.fixture(scope="module")
def result(vehicle):
    return nuts.run(jax.random.key(SEED), vehicle, model=IDM, params=["sigma"], **OPTIONS)


def test_nuts_matches_exact_posterior(vehicle, result):
    grid, density = grid_posterior(vehicle, IDM, "sigma")
    exact_mean = np.trapezoid(grid * density, grid)
    exact_sd = np.sqrt(np.trapezoid((grid - exact_mean) ** 2 * density, grid))
    draws = result.posterior["sigma"][:, :, 0]
    mcse = float(arviz.mcse(draws, chain_axis=0, draw_axis=1))
    ess = float(arviz.ess(draws, chain_axis=0, draw_axis=1))
    assert abs(draws.mean() - exact_mean) <= 4 * mcse, (draws.mean(), exact_mean, mcse)
    assert abs(draws.std() / exact_sd - 1) <= 4 / np.sqrt(2 * ess), (draws.std(), exact_sd, ess)


def test_same_seed_gives_identical_draws(vehicle, result):
    again = nuts.run(jax.random.key(SEED), vehicle, model=IDM, params=["sigma"], **OPTIONS)
    np.testing.assert_array_equal(again.posterior["sigma"], result.posterior["sigma"])
    for name, (_, values) in result.sample_stats.items():
        np.testing.assert_array_equal(again.sample_stats[name][1], values, err_msg=name)


def test_result_layout_and_divergences_reported(vehicle, result):
    chains, per_chain = OPTIONS["num_chains"], OPTIONS["num_particles"] // OPTIONS["num_chains"]
    assert result.posterior["sigma"].shape == (chains, per_chain, 1)
    dims, diverging = result.sample_stats["diverging"]
    assert dims == ("chain", "draw", "vehicle") and diverging.shape == (chains, per_chain, 1)
    assert diverging.dtype == bool
    assert result.sample_stats["step_size"][1].shape == (1, chains)
    depth = result.sample_stats["tree_depth"][1]
    steps = result.sample_stats["n_steps"][1]
    assert np.all((2 ** (depth - 1) <= steps) & (steps <= 2**depth - 1))
    assert result.options["target_accept_prob"] == 0.95
    assert result.options["dense_mass"] is False


def test_pointwise_log_likelihood_scores_every_stored_draw(vehicle, result):
    assert result.log_likelihood.shape == (4, 250, 1, vehicle.mask.shape[1])
    series = jax.tree.map(lambda a: a[0], step_inputs(vehicle, IDM))
    theta = result.posterior["sigma"][2, 7, 0]
    expected = series_loglik(IDM, ("sigma",), IDM.defaults(), jnp.array([theta]), series)
    np.testing.assert_allclose(result.log_likelihood[2, 7, 0], expected, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"num_chains": 0}, "num_chains"),
        ({"num_particles": 2, "num_chains": 2}, "2 draws per chain"),
        ({"target_accept_prob": 1.0}, "target_accept_prob"),
    ],
)
def test_bad_settings_are_refused(vehicle, options, message):
    with pytest.raises(ValueError, match=message):
        nuts.run(jax.random.key(0), vehicle, model=IDM, params=["sigma"], **options)
