"""The smc engine: exact against a conjugate model, calibrated on simulated IDM data, reproducible."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import Array
from jax.scipy.stats import norm
from scipy.stats import multivariate_normal

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.execution_noise import (
    MAX_ACCELERATION,
    STOP_SPEED,
    exact_initial_sample,
    exact_observation_logpdf,
    noisy_step,
    step_logpdf,
)
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import smc

DT = 0.1


# --- a driver model whose mean acceleration is linear in its parameters -----------------------
class LinearParams(NamedTuple):
    """a = b0 + b1 (lead_v - v), Gaussian execution noise of known sd sigma."""

    b0: Array
    b1: Array
    sigma: Array


def linear_mean(params, state, inputs):
    return params.b0 + params.b1 * (inputs.lead_v - state.v)


def linear_sample(key, params, state, inputs):
    mean_acc = linear_mean(params, state, inputs)
    return noisy_step(key, state, mean_acc, params.sigma, inputs.dt, MAX_ACCELERATION)


def linear_logpdf(params, state, next_state, inputs):
    mean_acc = linear_mean(params, state, inputs)
    return step_logpdf(state, next_state, mean_acc, params.sigma, inputs.dt, MAX_ACCELERATION)


SIGMA = 0.5
LINEAR = DriverModel(
    name="linear",
    params_type=LinearParams,
    specs=(
        ParamSpec("b0", "m/s^2", 0.0, -5.0, 5.0, "intercept"),
        ParamSpec("b1", "1/s", 0.0, -5.0, 5.0, "gain on the speed difference"),
        ParamSpec("sigma", "m/s^2", SIGMA, 0.01, 2.0, "known noise sd"),
    ),
    mean_acceleration=linear_mean,
    transition_sample=linear_sample,
    transition_logpdf=linear_logpdf,
    observation_logpdf=exact_observation_logpdf,
    initial_sample=exact_initial_sample,
)


class GaussianPrior(NamedTuple):
    """Independent normal priors: the interface smc needs is logpdf(theta) and sample(key, shape)."""

    mean: Array
    sd: Array

    def logpdf(self, theta):
        return jnp.sum(norm.logpdf(theta, self.mean, self.sd))

    def sample(self, key, shape=()):
        return self.mean + self.sd * jax.random.normal(key, (*shape, self.mean.shape[0]))


PRIOR = GaussianPrior(mean=jnp.array([0.0, 0.5]), sd=jnp.array([1.0, 1.0]))
COPIES = 12  # independent SMC runs on the same series, to measure the Monte Carlo error
STEPS = 60


def linear_series(seed: int) -> FollowerArrays:
    """One series simulated from the linear model (b0 = 0.3, b1 = 0.6), copied COPIES times."""
    params = LinearParams(jnp.asarray(0.3), jnp.asarray(0.6), jnp.asarray(SIGMA))
    t = jnp.arange(STEPS) * DT
    lead_v = 15.0 + 3.0 * jnp.sin(2 * jnp.pi * t / 6.0)

    def step(v, xs):
        key, lead = xs
        inputs = CarFollowingInputs(jnp.asarray(20.0), lead, jnp.asarray(1.0), jnp.asarray(DT))
        nxt = LINEAR.transition_sample(key, params, EgoState(jnp.asarray(0.0), v), inputs)
        return nxt.v, (v, nxt.v, nxt.x)

    keys = jax.random.split(jax.random.key(seed), STEPS)
    _, (v, next_v, dx) = jax.lax.scan(step, jnp.asarray(14.0), (keys, lead_v))

    def copies(a):
        return np.tile(np.asarray(a, dtype=np.float64), (COPIES, 1))

    return FollowerArrays(
        vehicle_ids=tuple(f"copy{i}" for i in range(COPIES)),
        v=copies(v),
        next_v=copies(next_v),
        dx=copies(dx),
        gap=np.full((COPIES, STEPS), 20.0),
        lead_v=copies(lead_v),
        has_leader=np.ones((COPIES, STEPS)),
        mask=np.ones((COPIES, STEPS)),
        t=copies(t),
        dt=DT,
    )


def closed_form(arrays: FollowerArrays, sigma: float):
    """Exact log-evidence of the dx series, posterior mean and sd of (b0, b1), in float64.

    dx = v dt + a dt^2 / 2 with a ~ N(b0 + b1 (lead_v - v), sigma^2), so y = 2 (dx - v dt) / dt^2
    is a Gaussian linear regression; the density of dx carries the Jacobian (dt^2 / 2)^-T.
    """
    v, dx, lead_v = arrays.v[0], arrays.dx[0], arrays.lead_v[0]
    y = 2.0 * (dx - v * DT) / DT**2
    design = np.stack([np.ones_like(v), lead_v - v], axis=1)
    m0, s0 = np.asarray(PRIOR.mean, np.float64), np.diag(np.asarray(PRIOR.sd, np.float64) ** 2)
    marginal_cov = sigma**2 * np.eye(len(y)) + design @ s0 @ design.T
    log_evidence = multivariate_normal(design @ m0, marginal_cov).logpdf(y)
    log_evidence -= len(y) * np.log(DT**2 / 2.0)
    precision = np.linalg.inv(s0) + design.T @ design / sigma**2
    cov = np.linalg.inv(precision)
    mean = cov @ (np.linalg.solve(s0, m0) + design.T @ y / sigma**2)
    return log_evidence, mean, np.sqrt(np.diag(cov))


@pytest.fixture(scope="module")
def conjugate_run():
    arrays = linear_series(seed=11)
    assert np.all(arrays.next_v > STOP_SPEED)  # no censored stop: the closed form applies
    result = smc.run(
        jax.random.key(12),
        arrays,
        model=LINEAR,
        params=("b0", "b1"),
        fixed={"sigma": SIGMA},
        num_particles=1000,
        prior=PRIOR,
        sequential=True,
    )
    draws = np.stack([result.posterior["b0"][0], result.posterior["b1"][0]], axis=-1)
    return arrays, result, draws  # draws: (particle, copy, 2)


def evidence_matches(result, log_evidence: float) -> bool:
    """Mean over the COPIES runs within 3 Monte Carlo standard errors (their sd / sqrt(COPIES))."""
    runs = np.asarray(result.sample_stats["log_evidence"][1], dtype=np.float64)
    standard_error = runs.std(ddof=1) / np.sqrt(len(runs))
    return abs(runs.mean() - log_evidence) <= 3 * standard_error


def moments_match(draws: np.ndarray, mean: np.ndarray, sd: np.ndarray) -> bool:
    """Per-run posterior means and sds, averaged over runs, within 4 Monte Carlo standard errors
    (the spread of the per-run estimates / sqrt(COPIES)) of the closed form."""
    ok = True
    for estimates, exact in ((draws.mean(axis=0), mean), (draws.std(axis=0), sd)):
        standard_error = estimates.std(axis=0, ddof=1) / np.sqrt(COPIES)
        ok &= bool(np.all(np.abs(estimates.mean(axis=0) - exact) <= 4 * standard_error))
    return ok


def test_smc_log_evidence_matches_the_closed_form(conjugate_run):
    arrays, result, _ = conjugate_run
    log_evidence, _, _ = closed_form(arrays, SIGMA)
    assert evidence_matches(result, log_evidence)


def test_smc_posterior_matches_the_closed_form(conjugate_run):
    arrays, _, draws = conjugate_run
    _, mean, sd = closed_form(arrays, SIGMA)
    assert moments_match(draws, mean, sd)


def test_the_conjugate_checks_catch_a_25_percent_noise_error(conjugate_run):
    # The same checks against the answer for a wrong noise sd must fail: they have the power to
    # see an engine that scored the wrong density.
    arrays, result, draws = conjugate_run
    log_evidence, mean, sd = closed_form(arrays, 1.25 * SIGMA)
    assert not evidence_matches(result, log_evidence)
    assert not moments_match(draws, mean, sd)


def test_smc_rejuvenates_with_sane_acceptance(conjugate_run):
    _, result, _ = conjugate_run
    resampled = result.sample_stats["resampled"][1]
    acceptance = result.sample_stats["acceptance"][1]
    assert resampled.any(axis=1).all()
    # Acceptance is recorded exactly where a rejuvenation ran, and the adapted random walk moves.
    assert np.array_equal(np.isfinite(acceptance), resampled)
    assert 0.05 < np.nanmean(acceptance) < 0.9


def test_closing_moves_run_until_the_draws_decorrelate(conjugate_run):
    _, result, _ = conjugate_run
    moves = np.asarray(result.sample_stats["final_moves"][1])
    correlation = np.asarray(result.sample_stats["final_correlation"][1])
    options = result.options
    threshold = max(options["decorrelation"], 3.5 / np.sqrt(options["num_particles"]))
    # Whole blocks of final_moves, stopped by the rule or by the cap, never past the cap.
    assert np.all(moves % options["final_moves"] == 0)
    assert np.all(moves <= options["max_final_moves"])
    assert np.all((correlation <= threshold) | (moves >= options["max_final_moves"]))


# --- recovery on the stochastic IDM --------------------------------------------------------
RECOVERY_VEHICLES = 20
RECOVERY_PARAMS = ("v_des", "sigma")


@pytest.fixture(scope="module")
def recovery():
    """20 followers whose (v_des, sigma) are drawn from the uniform prior, the rest at defaults."""
    key_truth, key_sim = jax.random.split(jax.random.key(2024))
    box = IDM.prior(RECOVERY_PARAMS)
    truth = np.asarray(box.sample(key_truth, (RECOVERY_VEHICLES,)), dtype=np.float64)
    params = IDM.params_type(
        *(
            jnp.asarray(truth[:, RECOVERY_PARAMS.index(s.name)])
            if s.name in RECOVERY_PARAMS
            else jnp.full(RECOVERY_VEHICLES, s.default)
            for s in IDM.specs
        )
    )
    arrays = simulate_following(key_sim, IDM, params, num_steps=100)
    return truth, arrays


def fit_recovery(arrays, seed, **options):
    return smc.run(
        jax.random.key(seed),
        arrays,
        model=IDM,
        params=RECOVERY_PARAMS,
        num_particles=400,
        **options,
    )


def test_smc_90_percent_intervals_cover_at_the_nominal_rate(recovery):
    truth, arrays = recovery
    result = fit_recovery(arrays, seed=7)
    covered = 0
    for k, name in enumerate(RECOVERY_PARAMS):
        draws = result.posterior[name][0]  # (particle, vehicle)
        low, high = np.quantile(draws, [0.05, 0.95], axis=0)
        covered += int(np.sum((low <= truth[:, k]) & (truth[:, k] <= high)))
    # 40 intervals, Bin(40, 0.9) if calibrated: P(count <= 30) = 0.5%, so >= 31 is required.
    assert covered >= 31, covered
    # ...and the posteriors are informative: sigma's sd far below the prior's (1.98 / sqrt 12).
    prior_sd = (2.0 - 0.02) / np.sqrt(12)
    assert np.mean(result.posterior["sigma"][0].std(axis=0)) < 0.25 * prior_sd


def test_smc_same_seed_is_bit_identical_and_seeds_differ(recovery):
    _, arrays = recovery
    first, again, other = (fit_recovery(arrays, seed) for seed in (3, 3, 4))
    for name in RECOVERY_PARAMS:
        assert np.array_equal(first.posterior[name], again.posterior[name])
        assert not np.array_equal(first.posterior[name], other.posterior[name])
    assert np.array_equal(first.log_likelihood, again.log_likelihood)


def test_masked_steps_contribute_nothing(recovery):
    _, arrays = recovery
    mask = arrays.mask.copy()
    mask[:, 40:60] = 0.0
    clean = arrays._replace(mask=mask)
    # Absurd values on the masked steps: a leak of any of them would change the posterior.
    garbage = clean._replace(
        dx=np.where(mask > 0, arrays.dx, 1e3), gap=np.where(mask > 0, arrays.gap, 0.01)
    )
    a, b = fit_recovery(clean, seed=5, sequential=True), fit_recovery(garbage, seed=5)
    for name in RECOVERY_PARAMS:
        assert np.array_equal(a.posterior[name], b.posterior[name])
    assert np.array_equal(a.sample_stats["log_evidence"][1], b.sample_stats["log_evidence"][1])
    assert not a.sample_stats["resampled"][1][:, 40:60].any()
    # The sequential pass (diagnostics only) changes no draw: b ran without it.
    assert "resampled" not in b.sample_stats
