"""The nuts engine: exact answer in one dimension, same seed -> same bits, the result layout.

The exact check: one vehicle simulated by the stochastic IDM (64 steps, sigma = 0.5, seed 3),
sigma inferred with the other parameters at their (true) defaults, so the posterior is a 1-D
integral computed by quadrature (:func:`bayesdrive.inference.diagnostics.agreement.grid_posterior`). NUTS
must match its mean within 4 Monte Carlo standard errors (ArviZ MCSE) and its sd within
4 / sqrt(2 ESS) relative (the sampling sd of an sd estimate), both failing with probability
about 1e-4 for a correct sampler. Other SBC-based checks of nuts live in tests/inference/test_sbc.py.
"""

import logging

import arviz
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.drivers.base import fill_params
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.core.likelihood import series_loglik, step_inputs
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.diagnostics.agreement import grid_posterior
from bayesdrive.inference.diagnostics.convergence import chain_problems
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import nuts
from bayesdrive.inference.fit import fit

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
        ({"max_extension": 0}, "max_extension"),
        ({"max_extension": 2, "first_extension": 4}, "first_extension"),
    ],
)
def test_bad_settings_are_refused(vehicle, options, message):
    with pytest.raises(ValueError, match=message):
        nuts.run(jax.random.key(0), vehicle, model=IDM, params=["sigma"], **options)


def fake_sampler(passes_from: dict[str, int], steps: int):
    """Stands in for one NUTS run (``nuts._run_vehicles``): per vehicle, seeded random-walk chains
    (they fail R-hat and ESS) below the extension factor ``passes_from[vehicle]``, independent
    normal draws (they pass) from it on. Records each run's factor and vehicles."""
    calls = []

    def run_vehicles(problem, key, config, chunk, batch, progress):
        calls.append((config.thin, problem.vehicle_ids))
        assert config.num_warmup == config.thin * OPTIONS["num_warmup"]
        rng = np.random.default_rng(config.thin)
        shape = (config.num_chains, config.num_samples // config.thin, len(problem.names))
        theta = np.stack(
            [
                rng.normal(size=shape).cumsum(axis=1)
                if config.thin < passes_from[vehicle]
                else rng.normal(size=shape)
                for vehicle in problem.vehicle_ids
            ]
        )
        zeros = np.zeros(theta.shape[:3])
        out = nuts._VehicleOutput(
            theta=theta,
            log_likelihood=np.zeros((*theta.shape[:3], steps)),
            diverging=zeros.astype(bool),
            tree_depth=zeros,
            num_steps=zeros,
            accept_prob=zeros,
            energy=zeros,
            lp=zeros,
            step_size=zeros[:, :, 0],
        )
        return out, 0.0, 0.0

    return run_vehicles, calls


def two_vehicles(vehicle):
    return vehicle.subset(np.array([0, 0]))._replace(vehicle_ids=("steady", "slow"))


def test_failing_vehicles_alone_are_extended_until_they_pass(vehicle, monkeypatch):
    """The first run has FIRST_EXTENSION (4) times the warm-up and draws; 'slow' passes only from
    16x: it alone reruns, at 16x, the cap, and passes; 'steady' keeps its first draws."""
    run_vehicles, calls = fake_sampler(
        {"steady": 1, "slow": nuts.MAX_EXTENSION}, vehicle.mask.shape[1]
    )
    monkeypatch.setattr(nuts, "_run_vehicles", run_vehicles)
    result = nuts.run(
        jax.random.key(SEED), two_vehicles(vehicle), model=IDM, params=["sigma"], **OPTIONS
    )
    assert calls == [(nuts.FIRST_EXTENSION, ("steady", "slow")), (16, ("slow",))]
    np.testing.assert_array_equal(result.sample_stats["extension"][1], [4, 16])
    assert result.posterior["sigma"].shape == (4, 250, 2)  # thinned back to the stored count
    for i, name in enumerate(("steady", "slow")):
        draws = result.posterior["sigma"][:, :, i, None]
        assert chain_problems(name, ("sigma",), draws) == []


def test_extension_stops_at_the_cap_and_fit_warns_with_the_next_step(vehicle, monkeypatch, caplog):
    """Negative control: 'slow' would need 16x; started at 1x with the cap at 2x it stops there,
    still failing, and every warning line names the vehicle, the parameter and what to run next."""
    run_vehicles, calls = fake_sampler({"steady": 1, "slow": 16}, vehicle.mask.shape[1])
    monkeypatch.setattr(nuts, "_run_vehicles", run_vehicles)
    with caplog.at_level(logging.WARNING, logger="bayesdrive.inference.diagnostics.convergence"):
        tree = fit(
            jax.random.key(SEED),
            two_vehicles(vehicle),
            model=IDM,
            engine="nuts",
            params=["sigma"],
            draws=OPTIONS["num_particles"],
            chains=OPTIONS["num_chains"],
            warmup=OPTIONS["num_warmup"],
            max_extension=2,
            first_extension=1,
        )
    assert calls == [(1, ("steady", "slow")), (2, ("slow",))]
    np.testing.assert_array_equal(tree["sample_stats"]["extension"].values, [1, 2])
    convergence = metadata(tree)["convergence"]
    assert {p["vehicle"] for p in convergence["problems"]} == {"slow"}
    assert {p["check"] for p in convergence["problems"]} == {"rhat", "ess_bulk", "ess_tail"}
    assert "--draws 4000 --warmup 800" in convergence["next_step"]
    warnings = [r.getMessage() for r in caplog.records if "not converged" in r.getMessage()]
    assert len(warnings) == 3
    assert all("vehicle slow, parameter sigma" in w and "next: " in w for w in warnings)


def test_the_next_extension_covers_the_ess_shortfall():
    assert nuts._next_factor(1, 1.1) == 2  # at least double
    assert nuts._next_factor(1, 2.5) == 4  # 2.5 * 1.25 = 3.1 draws' worth: the next power of two
    assert nuts._next_factor(2, 1.0) == 4
