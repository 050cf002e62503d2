"""The latent-state engine against an exact oracle, and PMMH recovery on simulated noisy data.

Oracle: on LINEAR car-following with Gaussian execution noise and Gaussian position noise the
state-space model is linear Gaussian, so a Kalman filter (numpy, float64, absolute positions
around 1.5 km) gives the exact log-likelihood the particle filter estimates. The filter's estimate
of the *likelihood* is unbiased, so the seed-average we compare is log(mean_i exp(loglik_i)) over
M independent seeds: an estimate with the variance of one run with M*N particles.

Tolerance: the log-likelihood of a bootstrap filter has variance ~ kappa T / N (T scored steps, N
particles). We require kappa <= KAPPA_MAX = 4 nats^2 per step (a budget; the filter measures about
2.5 on this model) and allow Z = 4 standard deviations of the seed-average:
TOL(N) = Z sqrt(KAPPA_MAX T / (N M)), which shrinks like 1/sqrt(N). Its bias, about
-kappa T / (2 N M), is below 0.01 nats here. A filter whose observation sd is 10 % too large
misses the Kalman value by more than a nat on this series and must fail.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.cidm import MergeInputs
from bayesdrive.drivers.execution_noise import exact_initial_sample, exact_observation_logpdf
from bayesdrive.drivers.idm import IDM, IDMParams
from bayesdrive.drivers.measurement_noise import shift_ego, with_measurement_noise
from bayesdrive.inference.core.likelihood import fixed_params
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.core.vehicles import vehicle_keys
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines.pmmh import (
    latent_data,
    noisy_readings,
    pmmh,
    run,
    state_filter_loglik,
)
from bayesdrive.inference.fit import fit

# ---------------------------------------------------------------------------------------------
# A linear car-following model through the driver-model interface (no speed clip: linear Gaussian)


class LinearParams(NamedTuple):
    """a = k1 (gap - d0) + k2 (lead_v - v) + N(0, sigma^2); k1 (1/s^2), k2 (1/s), d0 (m)."""

    k1: Array
    k2: Array
    d0: Array
    sigma: Array


def _linear_mean(params, state, inputs):
    return params.k1 * (inputs.gap - params.d0) + params.k2 * (inputs.lead_v - state.v)


def _linear_sample(key, params, state, inputs):
    acc = _linear_mean(params, state, inputs) + params.sigma * jax.random.normal(key)
    dt = inputs.dt
    return EgoState(x=state.x + state.v * dt + 0.5 * acc * dt**2, v=state.v + acc * dt)


def _linear_logpdf(params, state, next_state, inputs):
    dt = inputs.dt
    mean = state.v * dt + 0.5 * _linear_mean(params, state, inputs) * dt**2
    return norm.logpdf(next_state.x - state.x, mean, 0.5 * params.sigma * dt**2)


LINEAR = DriverModel(
    name="linear",
    params_type=LinearParams,
    specs=(
        ParamSpec("k1", "1/s^2", 0.1, 0.0, 1.0, "gap gain"),
        ParamSpec("k2", "1/s", 0.5, 0.0, 2.0, "relative-speed gain"),
        ParamSpec("d0", "m", 10.0, 0.0, 50.0, "target gap"),
        ParamSpec("sigma", "m/s^2", 0.5, 0.01, 3.0, "execution-noise sd"),
    ),
    mean_acceleration=_linear_mean,
    transition_sample=_linear_sample,
    transition_logpdf=_linear_logpdf,
    observation_logpdf=exact_observation_logpdf,
    initial_sample=exact_initial_sample,
    noise_sd=lambda params, state: params.sigma,  # declared: white Gaussian execution noise
)
NOISY_LINEAR = with_measurement_noise(LINEAR)
TRUTH = {"k1": 0.1, "k2": 0.5, "d0": 10.0, "sigma": 0.5, "sigma_obs": 0.05}
DT = 0.1
NUM_STEPS = 50
SIMULATION_SEED = 7  # numpy seed of the simulated series
FILTER_SEED = 11  # jax.random.key(FILTER_SEED) split into NUM_SEEDS filter keys
NUM_SEEDS = 64
KAPPA_MAX = 4.0
Z = 4.0


def tolerance(num_particles: int, num_scored: int) -> float:
    return Z * np.sqrt(KAPPA_MAX * num_scored / (num_particles * NUM_SEEDS))


def simulate_linear(num_steps: int) -> dict[str, np.ndarray]:
    """Absolute positions (float64) of a leader and a linear follower, and noisy follower readings."""
    rng = np.random.default_rng(SIMULATION_SEED)
    k1, k2, d0, sigma, sigma_obs = (TRUTH[k] for k in ("k1", "k2", "d0", "sigma", "sigma_obs"))
    t = np.arange(num_steps + 1) * DT
    lead_v = 20.0 + 3.0 * np.sin(2 * np.pi * t / 8.0)
    lead_rear = 1530.0 + np.concatenate([[0.0], np.cumsum(0.5 * (lead_v[1:] + lead_v[:-1]) * DT)])
    x, v = np.empty(num_steps + 1), np.empty(num_steps + 1)
    x[0], v[0] = 1500.0, 20.0
    for i in range(num_steps):
        acc = k1 * (lead_rear[i] - x[i] - d0) + k2 * (lead_v[i] - v[i]) + sigma * rng.normal()
        x[i + 1] = x[i] + v[i] * DT + 0.5 * acc * DT**2
        v[i + 1] = v[i] + acc * DT
    y = x + sigma_obs * rng.normal(size=num_steps + 1)
    return {"y": y, "v": v, "lead_rear": lead_rear, "lead_v": lead_v}


def kalman_loglik(
    series: dict[str, np.ndarray], mask: np.ndarray, initial_speed_sd: float = 0.0
) -> float:
    """Exact log p(readings | first reading of each segment) by a Kalman filter on (x, v).

    x' = x + v dt + a dt^2/2, v' = v + a dt, a = k1 (L - x - d0) + k2 (lead_v - v) + sigma eps:
    s' = F s + c + g sigma eps with g = (dt^2/2, dt). A segment starts at t = 0 and after every
    masked step, from x ~ N(y_t, sigma_obs^2) and v ~ N(the recorded speed, initial_speed_sd^2)
    (0: the latent engine's initial state).
    """
    k1, k2, d0, sigma, sigma_obs = (TRUTH[k] for k in ("k1", "k2", "d0", "sigma", "sigma_obs"))
    y, v, lead_rear, lead_v = (series[k] for k in ("y", "v", "lead_rear", "lead_v"))
    g = np.array([DT**2 / 2, DT])
    transition = np.eye(2) + np.outer(g, [-k1, -k2]) + np.array([[0.0, DT], [0.0, 0.0]])
    process = sigma**2 * np.outer(g, g)
    loglik = 0.0
    for t in range(len(mask)):
        if t == 0 or not mask[t - 1]:
            mean, cov = np.array([y[t], v[t]]), np.diag([sigma_obs**2, initial_speed_sd**2])
        if not mask[t]:
            continue
        mean = transition @ mean + g * (k1 * (lead_rear[t] - d0) + k2 * lead_v[t])
        cov = transition @ cov @ transition.T + process
        innovation_var = cov[0, 0] + sigma_obs**2
        residual = y[t + 1] - mean[0]
        loglik -= 0.5 * (np.log(2 * np.pi * innovation_var) + residual**2 / innovation_var)
        gain = cov[:, 0] / innovation_var
        mean = mean + gain * residual
        cov = cov - np.outer(gain, cov[0])
    return loglik


def follower_arrays_of(series: dict[str, np.ndarray], mask: np.ndarray) -> FollowerArrays:
    """The data layer's view of one follower: float64 increments and gaps from the readings."""
    num_steps = len(mask)

    def row(values) -> np.ndarray:
        return np.asarray(values, dtype=np.float64)[None, :num_steps]

    y = series["y"]
    return FollowerArrays(
        vehicle_ids=("linear0",),
        v=row(series["v"][:-1]),
        next_v=row(series["v"][1:]),
        dx=row(np.diff(y)),
        gap=row(series["lead_rear"][:-1] - y[:-1]),
        lead_v=row(series["lead_v"][:-1]),
        has_leader=np.ones((1, num_steps)),
        mask=row(mask),
        t=row(np.arange(num_steps) * DT),
        dt=DT,
    )


@partial(jax.jit, static_argnames=("model", "num_particles"))
def _filter_runs(keys, model, params, observations, inputs, num_particles):
    def one(key):
        return state_filter_loglik(key, model, params, observations, inputs, num_particles)[0]

    return jax.vmap(one)(keys)


def filter_logliks(model: DriverModel, arrays: FollowerArrays, num_particles: int) -> np.ndarray:
    """NUM_SEEDS independent filter estimates for the one vehicle in ``arrays``."""
    observations, inputs = jax.tree.map(lambda a: a[0], latent_data(arrays, model))
    params = model.params_type(*(jnp.asarray(TRUTH[name]) for name in model.param_names))
    keys = jax.random.split(jax.random.key(FILTER_SEED), NUM_SEEDS)
    logliks = _filter_runs(keys, model, params, observations, inputs, num_particles)
    return np.asarray(logliks, dtype=np.float64)


def log_mean_exp(values: np.ndarray) -> float:
    top = values.max()
    return float(top + np.log(np.mean(np.exp(values - top))))


@pytest.fixture(scope="module")
def linear_series():
    return simulate_linear(NUM_STEPS)


@pytest.mark.parametrize("num_particles", [256, 1024])
def test_filter_matches_kalman(linear_series, num_particles):
    mask = np.ones(NUM_STEPS)
    exact = kalman_loglik(linear_series, mask)
    arrays = follower_arrays_of(linear_series, mask)
    estimate = log_mean_exp(filter_logliks(NOISY_LINEAR, arrays, num_particles))
    assert abs(estimate - exact) < tolerance(num_particles, NUM_STEPS), (estimate, exact)


def test_observation_sd_ten_percent_off_fails_the_kalman_check(linear_series):
    """A filter that scores readings with a 10 % too large sd (initial spread right) is caught."""

    def too_wide(params, state, obs):
        wide = params._replace(sigma_obs=1.1 * params.sigma_obs)
        return NOISY_LINEAR.observation_logpdf(wide, state, obs)

    wrong = NOISY_LINEAR._replace(observation_logpdf=too_wide)
    mask = np.ones(NUM_STEPS)
    exact = kalman_loglik(linear_series, mask)
    estimate = log_mean_exp(filter_logliks(wrong, follower_arrays_of(linear_series, mask), 1024))
    assert abs(estimate - exact) > tolerance(1024, NUM_STEPS), (estimate, exact)


def test_holes_and_padding_restart_the_filter(linear_series):
    """Masked steps end a segment; the estimate is the sum of the segments' exact log-likelihoods."""
    mask = np.ones(NUM_STEPS)
    mask[[12, 30, 31]] = 0.0  # a one-step hole and a two-step hole
    mask[-6:] = 0.0  # trailing padding
    exact = kalman_loglik(linear_series, mask)
    assert exact != pytest.approx(kalman_loglik(linear_series, np.ones(NUM_STEPS)))
    arrays = follower_arrays_of(linear_series, mask)
    estimate = log_mean_exp(filter_logliks(NOISY_LINEAR, arrays, 1024))
    assert abs(estimate - exact) < tolerance(1024, int(mask.sum())), (estimate, exact)


def test_padding_leaves_the_estimate_and_info_unchanged(linear_series):
    arrays = follower_arrays_of(linear_series, np.ones(NUM_STEPS))
    observations, inputs = jax.tree.map(lambda a: a[0], latent_data(arrays, NOISY_LINEAR))
    params = NOISY_LINEAR.params_type(*(jnp.asarray(TRUTH[n]) for n in NOISY_LINEAR.param_names))
    padding = 14

    def pad(a):
        return jnp.concatenate([a, jnp.full((padding,), a[-1])])

    padded_obs = jax.tree.map(pad, observations)._replace(
        mask=jnp.concatenate([observations.mask, jnp.zeros(padding)])
    )
    key = jax.random.key(3)
    plain, info = state_filter_loglik(key, NOISY_LINEAR, params, observations, inputs, 64)
    padded, padded_info = state_filter_loglik(
        key, NOISY_LINEAR, params, padded_obs, jax.tree.map(pad, inputs), 64
    )
    np.testing.assert_allclose(padded, plain, rtol=1e-6)
    np.testing.assert_allclose(jnp.sum(info.log_increments), plain, rtol=1e-5)
    assert np.all(np.asarray(padded_info.ess[NUM_STEPS:]) == 64)
    assert not np.any(np.asarray(padded_info.resampled[NUM_STEPS:]))
    assert np.all(np.asarray(padded_info.log_increments[NUM_STEPS:]) == 0.0)
    # Resampling is triggered by the ESS rule: it happens, and only below half the particles.
    resampled = np.asarray(info.resampled)
    assert resampled.any()
    assert np.all(np.asarray(info.ess)[resampled] < 32)


def test_filter_refuses_bad_input(linear_series):
    arrays = follower_arrays_of(linear_series, np.ones(NUM_STEPS))
    observations, inputs = jax.tree.map(lambda a: a[0], latent_data(arrays, NOISY_LINEAR))
    params = NOISY_LINEAR.defaults()
    short = inputs._replace(lead_v=inputs.lead_v[:-1])
    with pytest.raises(ValueError, match=r"inputs\.lead_v"):
        state_filter_loglik(jax.random.key(0), NOISY_LINEAR, params, observations, short, 64)
    with pytest.raises(ValueError, match="num_state_particles"):
        state_filter_loglik(jax.random.key(0), NOISY_LINEAR, params, observations, inputs, 1)


# ---------------------------------------------------------------------------------------------
# The measurement-noise wrapper


def test_wrapper_adds_sigma_obs_and_keeps_the_dynamics():
    noisy = with_measurement_noise(IDM)
    assert noisy.param_names == (*IDM.param_names, "sigma_obs")
    spec = noisy.spec("sigma_obs")
    assert (spec.lower, spec.default, spec.upper, spec.unit) == (0.0, 0.0, 0.5, "m")
    params = noisy.defaults()._replace(sigma_obs=jnp.asarray(0.2))
    base = IDMParams(*params[:-1])
    state = EgoState(x=jnp.asarray(0.3), v=jnp.asarray(12.0))
    inputs = CarFollowingInputs(*map(jnp.asarray, (15.0, 11.0, 1.0, 0.1)))
    key = jax.random.key(5)
    assert noisy.transition_sample(key, params, state, inputs) == IDM.transition_sample(
        key, base, state, inputs
    )
    nxt = EgoState(x=jnp.asarray(1.5), v=jnp.asarray(11.9))
    assert noisy.transition_logpdf(params, state, nxt, inputs) == IDM.transition_logpdf(
        base, state, nxt, inputs
    )
    # Observation density: N(reading; latent x, sigma_obs), written out by hand.
    reading = EgoState(x=jnp.asarray(0.0), v=jnp.asarray(99.0))  # the speed must not matter
    expected = -0.5 * np.log(2 * np.pi * 0.2**2) - 0.5 * (0.3 / 0.2) ** 2
    np.testing.assert_allclose(noisy.observation_logpdf(params, state, reading), expected, 1e-6)
    with pytest.raises(ValueError, match="already has"):
        with_measurement_noise(noisy)


def test_initial_state_is_spread_around_the_first_reading():
    noisy = with_measurement_noise(IDM)
    params = noisy.defaults()._replace(sigma_obs=jnp.asarray(0.2))
    reading = EgoState(x=jnp.asarray(0.0), v=jnp.asarray(13.0))
    draws = jax.vmap(lambda k: noisy.initial_sample(k, params, reading))(
        jax.random.split(jax.random.key(9), 4000)
    )
    # 4000 draws (key 9): the mean's sd is 0.2/sqrt(4000) = 0.003; the sd's relative sd ~1.1%.
    assert abs(float(jnp.mean(draws.x))) < 4 * 0.2 / np.sqrt(4000)
    assert abs(float(jnp.std(draws.x)) / 0.2 - 1.0) < 0.05
    assert np.all(np.asarray(draws.v) == 13.0)


def test_shift_ego_moves_every_ego_distance():
    follow = CarFollowingInputs(*map(jnp.asarray, (20.0, 10.0, 1.0, 0.1)))
    assert shift_ego(follow, 0.5) == follow._replace(gap=19.5)
    merge = MergeInputs(
        *map(jnp.asarray, (20.0, 10.0, 1.0, 0.1, 50.0)),
        merge_to_merge=jnp.asarray([30.0]),
        merge_v=jnp.asarray([9.0]),
        merge_length=jnp.asarray([4.5]),
        merge_present=jnp.asarray([1.0]),
    )
    shifted = shift_ego(merge, 0.5)
    assert (float(shifted.gap), float(shifted.ego_to_merge)) == (19.5, 49.5)
    assert float(shifted.merge_to_merge[0]) == 30.0
    with pytest.raises(TypeError, match="no 'gap'"):
        shift_ego(EgoState(x=1.0, v=2.0), 0.5)


# ---------------------------------------------------------------------------------------------
# PMMH on simulated IDM data with measurement noise
#
# Two followers, 15 s each, tau = 1.5 s and sigma_obs = 10 cm, the other IDM parameters known. The
# chains start off the truth (tau 1.3 s, sigma_obs 15 cm): the test checks where the posterior
# sits and how wide it is; convergence from dispersed prior draws is a benchmark study
# (benchmarks/bench_latent.py), too slow for CI.

NOISY_IDM = with_measurement_noise(IDM)
PMMH_TRUTH = {"tau": 1.5, "sigma_obs": 0.1}
PMMH_NAMES = ("tau", "sigma_obs")
# The parameters not inferred, at their true values (the IDM defaults).
KNOWN = {spec.name: spec.default for spec in IDM.specs if spec.name != "tau"}
PMMH_START = (1.3, 0.15)
PMMH_SEED = 1
PMMH_NUM_CHAINS, PMMH_NUM_DRAWS, PMMH_NUM_VEHICLES = 2, 300, 2
# 48 left one chain at 5% acceptance: the likelihood estimate was too noisy.
PMMH_STATE_PARTICLES = 64


@pytest.fixture(scope="module")
def noisy_idm_data():
    """IDM followers (tau 1.5 s, other parameters at the defaults) read with 10 cm noise: the known
    parameters as a full tuple, the engine's readings and inputs, and the arrays."""
    truth = NOISY_IDM.defaults()._replace(**{k: jnp.asarray(v) for k, v in PMMH_TRUTH.items()})
    known = fixed_params(NOISY_IDM, KNOWN)
    sim_key, noise_key = jax.random.split(jax.random.key(2024))
    vehicles = jax.tree.map(lambda a: jnp.full((PMMH_NUM_VEHICLES,), a), IDMParams(*truth[:-1]))
    exact = simulate_following(sim_key, IDM, vehicles, num_steps=150)
    arrays = noisy_readings(noise_key, exact, PMMH_TRUTH["sigma_obs"])
    return known, latent_data(arrays, NOISY_IDM), arrays


def run_pmmh(seed: int, model: DriverModel, data):
    known, (observations, inputs), arrays = data
    return pmmh(
        vehicle_keys(jax.random.key(seed), arrays.vehicle_ids),
        model,
        PMMH_NAMES,
        observations,
        inputs,
        num_iterations=PMMH_NUM_DRAWS,
        num_warmup=200,
        num_state_particles=PMMH_STATE_PARTICLES,
        proposal_scale=(0.01, 0.01),
        num_chains=PMMH_NUM_CHAINS,
        init=jnp.asarray(PMMH_START),
        fixed=known,
    )


def recovery_failures(result) -> list[str]:
    """Per vehicle, pooled over chains: the posterior mean within 5 % (tau) and 20 % (sigma_obs)
    of the truth and within 4 posterior sds of it, and the posterior informative (sd below 5 % of
    the truth for tau, 20 % for sigma_obs). Returns what failed."""
    samples = np.asarray(result.samples)
    failures = []
    for column, (name, tolerance_rel) in enumerate((("tau", 0.05), ("sigma_obs", 0.20))):
        true_value = PMMH_TRUTH[name]
        draws = samples[..., column].reshape(-1, samples.shape[2])
        mean, sd = draws.mean(axis=0), draws.std(axis=0)
        if not np.all(np.abs(mean - true_value) < tolerance_rel * true_value):
            failures.append(f"{name} mean {mean} not within {tolerance_rel:.0%} of {true_value}")
        if not np.all(np.abs(mean - true_value) < 4 * sd):
            failures.append(f"{name} mean {mean} more than 4 sd {sd} from {true_value}")
        if not np.all(sd < tolerance_rel * true_value):
            failures.append(f"{name} sd {sd} not below {tolerance_rel:.0%} of {true_value}")
    return failures


@pytest.fixture(scope="module")
def pmmh_result(noisy_idm_data):
    return run_pmmh(PMMH_SEED, NOISY_IDM, noisy_idm_data)


def test_pmmh_recovers_sigma_obs_and_tau(pmmh_result):
    shape = (PMMH_NUM_CHAINS, PMMH_NUM_DRAWS, PMMH_NUM_VEHICLES)
    assert pmmh_result.samples.shape == (*shape, len(PMMH_NAMES))
    assert pmmh_result.log_likelihood.shape == shape
    acceptance = np.asarray(pmmh_result.acceptance_rate)
    assert np.all((acceptance > 0.05) & (acceptance < 0.6)), acceptance
    assert recovery_failures(pmmh_result) == []


def test_pmmh_same_seed_gives_identical_chains(pmmh_result, noisy_idm_data):
    again = run_pmmh(PMMH_SEED, NOISY_IDM, noisy_idm_data)
    for first, second in zip(pmmh_result[:3], again[:3], strict=True):
        np.testing.assert_array_equal(np.asarray(first), np.asarray(second))
    other = run_pmmh(PMMH_SEED + 1, NOISY_IDM, noisy_idm_data)
    assert not np.array_equal(np.asarray(other.samples), np.asarray(pmmh_result.samples))


def test_pmmh_refuses_an_initial_point_outside_the_prior(noisy_idm_data):
    known, (observations, inputs), arrays = noisy_idm_data
    with pytest.raises(ValueError, match="outside the prior box"):
        pmmh(
            vehicle_keys(jax.random.key(0), arrays.vehicle_ids),
            NOISY_IDM,
            PMMH_NAMES,
            observations,
            inputs,
            num_iterations=2,
            num_state_particles=8,
            proposal_scale=0.01,
            init=jnp.asarray([1.5, 2.0]),  # sigma_obs = 2 m is above its 1 m bound
            fixed=known,
        )


def test_fit_with_the_pmmh_engine_gives_the_shared_layout(noisy_idm_data):
    """``fit(..., engine="pmmh")`` builds the package's result tree (same settings as the recovery
    run, so the compiled chains are reused; the layout is checked here, not the values)."""
    _, _, arrays = noisy_idm_data
    tree = fit(
        jax.random.key(PMMH_SEED),
        arrays,
        model=NOISY_IDM,
        engine="pmmh",
        params=PMMH_NAMES,
        num_particles=PMMH_NUM_CHAINS * PMMH_NUM_DRAWS,
        window="all",
        fixed=KNOWN,
        seed=PMMH_SEED,
        num_state_particles=PMMH_STATE_PARTICLES,
        num_chains=PMMH_NUM_CHAINS,
        num_warmup=200,
        proposal_scale=(0.01, 0.01),
        init=jnp.asarray(PMMH_START),
    )
    assert metadata(tree)["engine"] == "pmmh"
    assert metadata(tree)["seed"] == PMMH_SEED
    posterior = tree["posterior"].to_dataset()
    assert posterior["sigma_obs"].shape == (PMMH_NUM_CHAINS, PMMH_NUM_DRAWS, PMMH_NUM_VEHICLES)
    log_lik = tree["log_likelihood"].to_dataset()["dx"].values
    assert log_lik.shape == (PMMH_NUM_CHAINS, PMMH_NUM_DRAWS, int(arrays.full_history_mask.sum()))
    assert np.all(np.isfinite(log_lik))
    stats = tree["sample_stats"].to_dataset()
    assert stats["acceptance_rate"].shape == (PMMH_NUM_CHAINS, PMMH_NUM_VEHICLES)
    ess = stats["filter_ess"].values
    assert np.all((ess >= 1.0) & (ess <= PMMH_STATE_PARTICLES))


def test_engine_refuses_exact_models_and_custom_priors(noisy_idm_data):
    _, _, arrays = noisy_idm_data
    with pytest.raises(ValueError, match="measurement_noise"):
        run(jax.random.key(0), arrays, model=IDM)
    with pytest.raises(ValueError, match="prior"):
        run(jax.random.key(0), arrays, model=NOISY_IDM, prior=NOISY_IDM.prior())
