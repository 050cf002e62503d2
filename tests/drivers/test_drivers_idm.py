"""The IDM pinned against hand arithmetic, and its stochastic one-step density checked against an
independent scipy formula and against its own sampler."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.execution_noise import (
    LIMIT_TOLERANCE,
    MAX_BRAKING,
    STOP_SPEED,
    acceleration_ceiling,
)
from bayesdrive.drivers.idm import IDM, idm_acceleration
from bayesdrive.inference.core.likelihood import StepInputs, step_logpdfs

DT = 0.1
# Textbook parameters used in the hand computations below.
HAND = IDM.params_type(
    v_des=30.0, d_min=2.0, tau=1.0, a_max=3.0, b_pref=2.0, sigma=IDM.spec("sigma").default
)
# float32 carries ~7 significant digits; the hand values below are exact to 1e-6.
ACC_TOL = 1e-5


def acceleration(v, gap, lead_v, has_leader=1.0, params=HAND):
    return float(idm_acceleration(params, jnp.asarray(v), gap, lead_v, has_leader))


def test_closing_leader_matches_hand_computation():
    # v=10, v_des=30, gap=20, lead_v=8 (closing at 2 m/s), d_min=2, tau=1, a_max=3, b_pref=2:
    #   sqrt(a_max b_pref) = sqrt(6) = 2.4494897
    #   d_des = 2 + max(0, 10*1 + 10*2 / (2*2.4494897)) = 2 + 10 + 4.0824829 = 16.0824829
    #   (d_des/gap)^2 = 0.8041241^2 = 0.6466156;  (v/v_des)^4 = (1/3)^4 = 1/81 = 0.0123457
    #   a = 3 (1 - 0.0123457 - 0.6466156) = 3 * 0.3410387 = 1.023116
    assert acceleration(10.0, 20.0, 8.0) == pytest.approx(1.023116, abs=ACC_TOL)


def test_free_road_matches_hand_computation_and_ignores_gap():
    # v=20, v_des=30, no leader: a = 3 (1 - (2/3)^4) = 3 (1 - 16/81) = 3 * 65/81 = 2.407407
    for junk_gap in (0.0, 1e-3, 500.0, float("nan")):
        assert acceleration(20.0, junk_gap, 0.0, has_leader=0.0) == pytest.approx(
            2.407407, abs=ACC_TOL
        )


def test_dynamic_term_is_floored_at_zero_for_a_fast_receding_leader():
    # v=10, lead_v=30: dynamic = 10*1 + 10*(10-30) / (2*2.4494897) = 10 - 40.82 < 0 -> floored at 0,
    #   d_des = d_min = 2;  a = 3 (1 - 1/81 - (2/20)^2) = 3 (1 - 0.0123457 - 0.01) = 2.932963
    # Without the floor d_des would be negative and its square would brake the car.
    assert acceleration(10.0, 20.0, 30.0) == pytest.approx(2.932963, abs=ACC_TOL)


def test_acceleration_exponent_is_four():
    # v=15, v_des=30, free road: delta=4 gives 3 (1 - (1/2)^4) = 3 * 15/16 = 2.8125
    # (delta=2 would give 3 * 3/4 = 2.25).
    assert acceleration(15.0, 100.0, 0.0, has_leader=0.0) == pytest.approx(2.8125, abs=ACC_TOL)


def test_standstill_at_jam_distance_is_an_equilibrium():
    # v=0, lead_v=0, gap=d_min=2: d_des = 2, a = 3 (1 - 0 - (2/2)^2) = 0
    assert acceleration(0.0, 2.0, 0.0) == pytest.approx(0.0, abs=ACC_TOL)


def _step_inputs(gap, lead_v, dt=DT):
    return CarFollowingInputs(
        gap=jnp.asarray(gap, dtype=float),
        lead_v=jnp.asarray(lead_v, dtype=float),
        has_leader=jnp.ones_like(jnp.asarray(gap, dtype=float)),
        dt=jnp.full(np.shape(gap), dt, dtype=float),
    )


@jax.jit
@functools.partial(jax.vmap, in_axes=(None, 0, 0, 0, 0))
def _model_logpdf(params, v, dx, next_v, inputs):
    state = EgoState(jnp.zeros(()), v)
    return IDM.transition_logpdf(params, state, EgoState(dx, next_v), inputs)


def _logpdf(params, v, dx, next_v, inputs):
    """The model's density of observed (dx, next_v) from (x=0, v), one value per step."""

    def f(values):
        return jnp.asarray(values, dtype=float)

    return np.asarray(_model_logpdf(params, f(v), f(dx), f(next_v), inputs), dtype=np.float64)


@jax.jit
@functools.partial(jax.vmap, in_axes=(None, 0, 0))
def _model_mean(params, v, inputs):
    return IDM.mean_acceleration(params, EgoState(jnp.zeros(()), v), inputs)


def _mean_acc(params, v, inputs):
    return np.asarray(_model_mean(params, jnp.asarray(v, dtype=float), inputs), dtype=np.float64)


def _censored_logpdf(v, dx, next_v, a, sigma, ceiling):
    """The censored step law (drivers/execution_noise.py) written again with scipy in float64:
    the Gaussian increment density inside the limits, else the log-probability of the observed
    class under the clipped acceleration (none below the floor, all of it from the ceiling on)."""
    acc = 2.0 * (dx - v * DT) / DT**2
    raw = stats.norm(a, sigma)
    stop_at = (STOP_SPEED - v) / DT
    floor_at, ceiling_at = -MAX_BRAKING + LIMIT_TOLERANCE, ceiling - LIMIT_TOLERANCE
    stopped = next_v <= STOP_SPEED
    floor = ~stopped & (acc <= floor_at)
    top = ~stopped & ~floor & (acc >= ceiling_at)
    reachable, forced = stop_at >= -MAX_BRAKING, stop_at >= ceiling
    with np.errstate(divide="ignore", invalid="ignore"):
        log_stop = np.where(reachable, raw.logcdf(stop_at), -np.inf)
        log_stop = np.where(forced, 0.0, log_stop)
        log_floor = raw.logcdf(floor_at) + np.log1p(-np.exp(log_stop - raw.logcdf(floor_at)))
        log_floor = np.where(forced | (stop_at >= floor_at), -np.inf, log_floor)
        log_top = np.where(forced, -np.inf, raw.logsf(np.maximum(ceiling_at, stop_at)))
    censored = np.where(stopped, log_stop, np.where(floor, log_floor, log_top))
    inside = stats.norm.logpdf(dx, v * DT + 0.5 * a * DT**2, sigma * DT**2 / 2)
    return np.where(stopped | floor | top, censored, inside)


def _scipy_case(n: int = 400):
    """Steps with observed increments within +-3 sd of the unbounded prediction (some beyond the
    floor or the ceiling), every 4th an observed stop from 0-1.2 m/s (beyond 0.9 m/s no car stops
    in one step), and their log-densities by scipy (an independent formula)."""
    rng = np.random.default_rng(20240611)
    params = IDM.defaults()
    sigma = float(params.sigma)
    stopped = np.arange(n) % 4 == 0
    v = np.where(stopped, rng.uniform(0.0, 1.2, n), rng.uniform(0.0, 30.0, n))
    inputs = _step_inputs(rng.uniform(2.0, 60.0, n), rng.uniform(0.0, 30.0, n))
    a = _mean_acc(params, v, inputs)
    predicted = v * DT + 0.5 * a * DT**2
    dx = predicted + rng.uniform(-3, 3, n) * sigma * DT**2 / 2
    next_v = np.where(stopped, 0.0, np.maximum(v + a * DT, 1.0))
    ceiling = np.asarray(
        jax.vmap(acceleration_ceiling)(jnp.asarray(v, dtype=float), inputs), np.float64
    )
    expected = _censored_logpdf(v, dx, next_v, a, sigma, ceiling)
    return params, v, dx, next_v, inputs, stopped, expected


def assert_matches_scipy(got, expected):
    """Equal within SCIPY_TOL, -inf (an impossible observation) where scipy says so."""
    np.testing.assert_array_equal(np.isneginf(got), np.isneginf(expected))
    possible = np.isfinite(expected)
    np.testing.assert_allclose(got[possible], expected[possible], **SCIPY_TOL)


# float32 increments of ~3 m carry ~2e-7 m rounding = 1e-4 sd: well under 2e-3 nats.
SCIPY_TOL = {"atol": 2e-3, "rtol": 1e-5}


def test_step_logpdf_matches_an_independent_scipy_formula():
    params, v, dx, next_v, inputs, stopped, expected = _scipy_case()
    got = _logpdf(params, v, dx, next_v, inputs)
    assert_matches_scipy(got, expected)
    # The case reaches every class: possible and impossible stops, the floor, the ceiling.
    acc = 2.0 * (dx - v * DT) / DT**2
    assert np.isneginf(expected[stopped]).any() and np.isfinite(expected[stopped]).any()
    assert (acc[~stopped] <= -MAX_BRAKING).sum() >= 5


def test_series_density_matches_the_scipy_formula_with_and_without_stops():
    # The whole-series density skips the stop term on a series without a stop: on one with stops
    # it must score them, on the moving steps alone it must give the moving densities.
    params, v, dx, next_v, inputs, stopped, expected = _scipy_case()

    def series(rows):
        def f(values):
            return jnp.asarray(np.asarray(values)[rows], dtype=float)

        steps = StepInputs(
            v=f(v),
            next_v=f(next_v),
            dx=f(dx),
            mask=f(np.ones(len(v))),
            inputs=jax.tree.map(lambda a: a[rows], inputs),
        )
        scored = jax.jit(functools.partial(step_logpdfs, IDM))(params, steps)
        return np.asarray(scored, dtype=np.float64)

    everything = np.arange(len(v))
    assert_matches_scipy(series(everything), expected)
    acc = 2.0 * (dx - v * DT) / DT**2
    inside = np.flatnonzero(~stopped & (acc > -MAX_BRAKING + 0.1) & (acc < 5.0))
    assert_matches_scipy(series(inside), expected[inside])
    # Negative control: the stop steps scored as moving ones are far from their stop mass.
    as_moving = _logpdf(params, v, dx, np.where(stopped, 1.0, next_v), inputs)
    assert np.min(np.abs(as_moving[stopped] - expected[stopped])) > 1.0


# A state that splits its mass between stopping and moving: v=0.4 m/s, 1.6 m behind a stopped
# leader, the IDM brakes at about -3.9 m/s^2, so v + a dt is within one sd (sigma dt) of 0.
NEAR_STOP = {"v": 0.4, "gap": 1.6, "lead_v": 0.0}
# A state that cannot stop within a step (v + a dt is hundreds of sd above 0).
CRUISING = {"v": 12.0, "gap": 25.0, "lead_v": 11.0}


def _scalar_state(case):
    params = IDM.defaults()
    inputs = _step_inputs(case["gap"], case["lead_v"])
    a = float(IDM.mean_acceleration(params, EgoState(0.0, case["v"]), inputs))
    return params, inputs, a


def test_step_density_integrates_to_one_with_the_stop_mass():
    # P(observed stop) + the moving density integrated over every increment whose next speed is
    # above STOP_SPEED (speed v' = v + a dt > STOP_SPEED <=> dx > (v + STOP_SPEED) dt / 2).
    params, _, a = _scalar_state(NEAR_STOP)
    v, sigma = NEAR_STOP["v"], float(params.sigma)
    sd = sigma * DT**2 / 2

    def density(dx, next_v):
        n = len(dx)
        inputs = _step_inputs(np.full(n, NEAR_STOP["gap"]), np.full(n, NEAR_STOP["lead_v"]))
        return np.exp(_logpdf(params, np.full(n, v), dx, next_v, inputs))

    p_stop = density(np.array([0.0]), np.array([0.0]))[0]
    grid = np.linspace((v + STOP_SPEED) * DT / 2, v * DT + 0.5 * a * DT**2 + 10 * sd, 8001)
    moving = np.trapezoid(density(grid, np.ones_like(grid)), grid)
    assert 0.2 < p_stop < 0.8, "the test state should split its mass between stop and move"
    # The trapezoid rule on 8001 points over ~12 sd is exact to ~1e-6; float32 to ~1e-4.
    assert p_stop + moving == pytest.approx(1.0, abs=1e-3)


def _sample_steps(key, case, n):
    params, inputs, a = _scalar_state(case)
    state = EgoState(jnp.zeros(()), jnp.asarray(case["v"], dtype=float))
    draws = jax.jit(jax.vmap(IDM.transition_sample, in_axes=(0, None, None, None)))(
        jax.random.split(key, n), params, state, inputs
    )
    return params, a, np.asarray(draws.x, np.float64), np.asarray(draws.v, np.float64)


# Monte Carlo checks: 20000 draws, seeds stated; a correct sampler/density pair passes each
# p-value threshold with probability 0.999, and the seed fixes the outcome.
MC_DRAWS = 20_000


def test_sampled_increments_follow_the_scored_gaussian_and_the_factor_two_bug_fails():
    params, a, dx, next_v = _sample_steps(jax.random.key(11), CRUISING, MC_DRAWS)
    v = CRUISING["v"]
    assert np.all(next_v > STOP_SPEED)
    predicted = v * DT + 0.5 * a * DT**2
    sigma = float(params.sigma)
    right = stats.kstest(dx, stats.norm(predicted, sigma * DT**2 / 2).cdf)
    assert right.pvalue > 1e-3
    # The paper's code scored the position with sd sigma dt^2: the same draws reject it outright.
    factor_two = stats.kstest(dx, stats.norm(predicted, sigma * DT**2).cdf)
    assert factor_two.pvalue < 1e-12


def test_sampled_stop_frequency_and_moving_increments_match_the_density():
    params, a, dx, next_v = _sample_steps(jax.random.key(12), NEAR_STOP, MC_DRAWS)
    v, sigma = NEAR_STOP["v"], float(params.sigma)
    inputs = _step_inputs([NEAR_STOP["gap"]], [NEAR_STOP["lead_v"]])
    p_stop = float(np.exp(_logpdf(params, [v], [0.0], [0.0], inputs))[0])
    stopped = next_v <= STOP_SPEED
    # 4 binomial sd: about 0.014 here.
    assert abs(stopped.mean() - p_stop) < 4 * np.sqrt(p_stop * (1 - p_stop) / MC_DRAWS)

    # Moving draws: the scored Gaussian truncated to next speeds above STOP_SPEED.
    z = (dx[~stopped] - (v * DT + 0.5 * a * DT**2)) / (sigma * DT**2 / 2)
    z_low = -(v + a * DT - STOP_SPEED) / (sigma * DT)
    mass_low = stats.norm.cdf(z_low)
    truncated_cdf = lambda q: (stats.norm.cdf(q) - mass_low) / (1 - mass_low)  # noqa: E731
    assert stats.kstest(z, truncated_cdf).pvalue > 1e-3


def test_float32_increments_keep_the_density_where_absolute_positions_lose_it():
    rng = np.random.default_rng(5)
    n = 2000
    params = IDM.defaults()
    sigma = float(params.sigma)
    v = rng.uniform(5.0, 25.0, n)
    inputs = _step_inputs(rng.uniform(10.0, 40.0, n), rng.uniform(5.0, 25.0, n))
    a = _mean_acc(params, v, inputs)
    predicted = v * DT + 0.5 * a * DT**2
    sd = sigma * DT**2 / 2  # 1.5 mm: float32 positions near 500 m are spaced 61 um apart
    dx = predicted + sd * rng.standard_normal(n)
    x_start = rng.uniform(300.0, 800.0, n)
    x_next = x_start + dx
    exact = stats.norm.logpdf(dx, predicted, sd)  # float64 throughout
    # The Gaussian density holds inside the physical limits (steps well inside them here).
    ceiling = np.asarray(jax.vmap(acceleration_ceiling)(jnp.asarray(v, dtype=float), inputs))
    inside = (a > -MAX_BRAKING + 1.0) & (a < ceiling - 1.0)
    assert inside.sum() > n / 2

    from_increments = _logpdf(params, v, dx.astype(np.float32), np.ones(n), inputs)
    assert np.max(np.abs(from_increments - exact)[inside]) < 1e-3

    # What the increments avoid: subtracting two float32 positions of hundreds of metres.
    dx_from_positions = x_next.astype(np.float32) - x_start.astype(np.float32)
    from_positions = _logpdf(params, v, dx_from_positions, np.ones(n), inputs)
    assert np.median(np.abs(from_positions - exact)[inside]) > 1e-3


def _leader_speed_profiles(rng, cases, steps):
    """Leader speeds that brake hard (down to -9 m/s^2), stop, and accelerate (up to +3 m/s^2)
    in random spells of 0.5-6 s, speeds clipped to [0, 35] m/s."""
    speeds = np.empty((cases, steps + 1))
    speeds[:, 0] = rng.uniform(5.0, 30.0, cases)
    accelerations = np.empty((cases, steps))
    for case in range(cases):
        t = 0
        while t < steps:
            spell = int(rng.integers(5, 60))
            hard_brake = rng.random() < 0.35
            accelerations[case, t : t + spell] = (
                rng.uniform(-9.0, -4.0) if hard_brake else rng.uniform(-4.0, 3.0)
            )
            t += spell
    for t in range(steps):
        speeds[:, t + 1] = np.clip(speeds[:, t] + accelerations[:, t] * DT, 0.0, 35.0)
    return speeds


def _closest_approach(key, params, gap0, v0, lead_v, lead_dx, has_leader):
    """Smallest bumper gap of a stochastic IDM follower behind a replayed leader."""

    def step(carry, leader):
        gap, v, key = carry
        key, step_key = jax.random.split(key)
        speed, increment = leader
        inputs = CarFollowingInputs(gap, speed, has_leader, jnp.asarray(DT, dtype=float))
        moved = IDM.transition_sample(step_key, params, EgoState(jnp.zeros(()), v), inputs)
        gap = gap + increment - moved.x
        return (gap, moved.v, key), gap

    _, gaps = jax.lax.scan(step, (gap0, v0, key), (lead_v, lead_dx))
    return gaps.min()


@pytest.mark.parametrize("follows_leader", [True, False], ids=["idm", "ignores-leader"])
def test_idm_follower_never_collides_behind_a_randomly_braking_leader(follows_leader):
    # 500 cases of 60 s, numpy seed 2024 for the leaders, JAX key 2024 for the execution noise, at
    # the default parameters INCLUDING the default noise sigma = 0.3 m/s^2 (no collision occurs,
    # so the deterministic limit is not needed). Each follower starts at the leader's speed +-3 m/s
    # and at 0.7-1.5 times the IDM equilibrium gap (d_min + v tau) / sqrt(1 - (v/v_des)^4).
    # The "ignores-leader" variant (the interaction term switched off) must crash: the check bites.
    cases, steps = 500, 600
    rng = np.random.default_rng(2024)
    speeds = _leader_speed_profiles(rng, cases, steps)
    lead_dx = 0.5 * (speeds[:, :-1] + speeds[:, 1:]) * DT
    params = IDM.defaults()
    v_des, d_min, tau = float(params.v_des), float(params.d_min), float(params.tau)
    equilibrium = (d_min + speeds[:, 0] * tau) / np.sqrt(1.0 - (speeds[:, 0] / v_des) ** 4)
    gap0 = equilibrium * rng.uniform(0.7, 1.5, cases)
    v0 = np.clip(speeds[:, 0] + rng.uniform(-3.0, 3.0, cases), 0.0, None)
    has_leader = jnp.asarray(1.0 if follows_leader else 0.0)

    closest = jax.jit(jax.vmap(_closest_approach, in_axes=(0, None, 0, 0, 0, 0, None)))(
        jax.random.split(jax.random.key(2024), cases),
        params,
        jnp.asarray(gap0, dtype=float),
        jnp.asarray(v0, dtype=float),
        jnp.asarray(speeds[:, :-1], dtype=float),
        jnp.asarray(lead_dx, dtype=float),
        has_leader,
    )
    collisions = int(np.sum(np.asarray(closest) <= 0.0))
    if follows_leader:
        assert collisions == 0, f"{collisions} of {cases} followers hit their leader"
    else:
        assert collisions > cases // 2
