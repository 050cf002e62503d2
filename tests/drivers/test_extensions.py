"""The model extensions: nesting, sampler/density agreement, and each effect's defining property."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import scored_series
from bayesdrive.drivers.base import (
    CarFollowingInputs,
    EgoState,
    car_following_at,
    device_series,
    fill_params,
)
from bayesdrive.drivers.extensions import CAUSES, NO_CAUSE, extend
from bayesdrive.drivers.extensions.autocorrelated_noise import (
    NoiseMemoryInputs,
    implied_acceleration,
)
from bayesdrive.drivers.extensions.cut_in import cah_acceleration
from bayesdrive.drivers.extensions.inputs import ExtendedInputs, history_steps, inputs_at
from bayesdrive.drivers.idm import IDM, idm_acceleration
from bayesdrive.inference.core.likelihood import StepInputs, step_inputs
from tests.compiled import step_logpdfs
from tests.followers import DT, corrected_follower, single_lane

K = history_steps(DT)


def make_inputs(**overrides) -> ExtendedInputs:
    """A car-following situation with a varied history (values chosen by hand, physical)."""
    lags = jnp.arange(K + 1, dtype=jnp.float32)
    fields = {
        "gap": jnp.float32(18.0),
        "lead_v": jnp.float32(11.0),
        "has_leader": jnp.float32(1.0),
        "dt": jnp.float32(DT),
        "lead_acc": jnp.float32(-1.5),
        "gap2": jnp.float32(42.0),
        "lead2_v": jnp.float32(8.0),
        "has_leader2": jnp.float32(1.0),
        "lead_age": jnp.float32(100.0),
        "lag_v": 12.0 + 0.05 * lags,
        "lag_gap": 18.0 + 0.3 * lags,
        "lag_lead_v": 11.0 + 0.12 * lags,
    }
    fields.update(overrides)
    return ExtendedInputs(**fields)


def read_by(model, inputs: ExtendedInputs, previous_dx=1.215, earlier_dx=1.21):
    """``inputs`` as ``model`` reads them: the extensions that change the mean rule read all of
    them, the white-noise IDM and its speed-dependent noise the current car following, the
    autocorrelated noise the car following now and two steps before (from the history window)."""
    if model.inputs_at is car_following_at:
        return inputs.car_following
    if model.name.endswith("+autocorrelated_noise"):
        previous = CarFollowingInputs(
            inputs.lag_gap[1], inputs.lag_lead_v[1], inputs.has_leader, inputs.dt
        )
        earlier = CarFollowingInputs(
            inputs.lag_gap[2], inputs.lag_lead_v[2], inputs.has_leader, inputs.dt
        )
        return NoiseMemoryInputs(
            inputs.car_following,
            previous,
            inputs.lag_v[1],
            jnp.float32(previous_dx),
            earlier,
            inputs.lag_v[2],
            jnp.float32(earlier_dx),
        )
    return inputs


STATE = EgoState(jnp.float32(0.0), jnp.float32(12.0))
# Values that switch each effect on strongly (inside the prior bounds).
ON = {
    "reaction_delay": 0.73,
    "autocorrelated_noise": 0.8,
    "speed_dependent_noise": 0.15,
    "second_leader_anticipation": 0.6,
    "cut_in_overreaction": 0.99,
    "leader_acceleration_anticipation": 0.5,
    "state_correction": -0.5,
}
# Causes whose state is lifted from the observed past (each step scored on its own) and causes
# with a hidden state (scored through their filter).
LIFTED = tuple(c for c in CAUSES if extend(c, IDM).model.filter is None)
FILTERED = tuple(c for c in CAUSES if extend(c, IDM).model.filter is not None)


def params_for(extended, effect=None):
    base = extended.model.defaults()
    if effect is None:
        return base
    return base._replace(**{extended.new_params[0]: jnp.float32(effect)})


def test_every_cause_has_a_lifted_or_filtered_extension():
    assert set(LIFTED) | set(FILTERED) == set(CAUSES)
    assert set(FILTERED) == {"drifting_parameters", "measurement_noise"}


@pytest.mark.parametrize("cause", LIFTED)
def test_extension_switched_off_is_the_base_model(cause):
    """At its default ("off") value every extension scores any step exactly like the IDM."""
    extended = extend(cause, IDM)
    every = make_inputs()
    inputs = read_by(extended.model, every)
    params = params_for(extended)
    state = extended.model.lift(params, STATE, inputs)
    base_params = IDM.defaults()
    for dx, next_v in ((1.18, 11.6), (1.25, 12.9), (1.10, 10.2)):
        nxt = EgoState(jnp.float32(dx), jnp.float32(next_v))
        ours = extended.model.transition_logpdf(params, state, nxt, inputs)
        base = IDM.transition_logpdf(base_params, STATE, nxt, every.car_following)
        np.testing.assert_allclose(ours, base, rtol=1e-6, atol=1e-5)


def quadratic_moments(logpdf_of_dx, centre: float, spread: float) -> tuple[float, float]:
    """Mean and sd of a Gaussian log-density in dx, read off its values at three points."""
    points = np.array([centre - spread, centre, centre + spread])
    values = np.array([float(logpdf_of_dx(p)) for p in points])
    curvature = (values[0] - 2 * values[1] + values[2]) / spread**2
    slope = (values[2] - values[0]) / (2 * spread)
    sd = math.sqrt(-1.0 / curvature)
    return centre + slope * sd**2, sd


@pytest.mark.parametrize("cause", LIFTED)
def test_sampler_agrees_with_density(cause):
    """transition_sample's increments follow the Gaussian that transition_logpdf scores.

    KS test of 4000 sampled increments (seed 0) against the mean and sd read off the log-density;
    the same test must reject a sampler with twice the sd (the paper's factor-2 bug), so it has
    power. Tolerance: KS p > 0.001 for the real sampler, p < 1e-6 for the wrong one.
    """
    extended = extend(cause, IDM)
    params = params_for(extended, ON[cause])
    inputs = read_by(extended.model, make_inputs())
    # A known previous residual, so the AR(1) conditional is exercised too.
    state = extended.model.lift(params, STATE, inputs)
    keys = jax.random.split(jax.random.key(0), 4000)
    sampled = jax.vmap(lambda k: extended.model.transition_sample(k, params, state, inputs))(keys)
    increments = np.asarray(sampled.x, np.float64)

    def logpdf_of_dx(dx):
        nxt = EgoState(jnp.float32(dx), jnp.float32(12.0))
        return extended.model.transition_logpdf(params, state, nxt, inputs)

    mean, sd = quadratic_moments(logpdf_of_dx, float(np.mean(increments)), 0.002)
    assert stats.kstest(increments, stats.norm(mean, sd).cdf).pvalue > 1e-3
    wrong = mean + 2.0 * (increments - mean)
    assert stats.kstest(wrong, stats.norm(mean, sd).cdf).pvalue < 1e-6


def perceived_idm(gap, own_then, lead_then) -> jax.Array:
    """The IDM at the ego's current speed, perceiving ``gap`` and the closing speed
    ``own_then - lead_then`` (the ego's and the leader's speeds as they were)."""
    return idm_acceleration(IDM.defaults(), STATE.v, gap, STATE.v - (own_then - lead_then), 1.0)


@pytest.mark.parametrize("steps_back", [0, 3, 7])
def test_reaction_delay_at_whole_steps_reads_the_lagged_inputs(steps_back):
    """A delay of exactly k steps perceives the gap and the closing speed of k steps ago; the own
    speed in the free-road and time-gap terms is the current one."""
    extended = extend("reaction_delay", IDM)
    params = params_for(extended, steps_back * DT)
    inputs = make_inputs()
    got = extended.model.mean_acceleration(params, STATE, inputs)
    expected = perceived_idm(
        inputs.lag_gap[steps_back],
        inputs.lag_v[steps_back],
        inputs.lag_lead_v[steps_back],
    )
    np.testing.assert_allclose(got, expected, rtol=2e-5)


def test_reaction_delay_keeps_the_own_speed_current():
    """The ego's speed history rises 1 m/s per step (12 m/s now, 19 m/s 7 steps ago). On free
    road nothing of a leader is perceived, so a delay of 0.7 s changes nothing: the free-road term
    reads the current speed. Behind a leader whose gap and speed histories are flat, the result is
    the IDM at the current speed with the closing speed of 0.7 s ago."""
    extended = extend("reaction_delay", IDM)
    params = params_for(extended, 0.7)
    rising = 12.0 + jnp.arange(K + 1, dtype=jnp.float32)
    free_road = make_inputs(has_leader=jnp.float32(0.0), lag_v=rising)
    got = extended.model.mean_acceleration(params, STATE, free_road)
    current = idm_acceleration(IDM.defaults(), STATE.v, 18.0, 11.0, 0.0)
    np.testing.assert_allclose(got, current, rtol=1e-6)
    then = idm_acceleration(IDM.defaults(), rising[7], 18.0, 11.0, 0.0)
    assert abs(float(then) - float(current)) > 0.3
    flat = make_inputs(
        lag_v=rising,
        lag_gap=jnp.full(K + 1, 18.0, jnp.float32),
        lag_lead_v=jnp.full(K + 1, 11.0, jnp.float32),
    )
    got = extended.model.mean_acceleration(params, STATE, flat)
    np.testing.assert_allclose(got, perceived_idm(18.0, rising[7], 11.0), rtol=2e-5)
    whole_rule_delayed = idm_acceleration(IDM.defaults(), rising[7], 18.0, 11.0, 1.0)
    assert abs(float(got) - float(whole_rule_delayed)) > 0.3


def test_a_leader_that_cut_in_is_perceived_from_its_entry_on():
    """0.7 s of delay, but the leader cut in 2 steps ago: its gap and the closing speed are
    perceived as on entry (lag 2); an old leader would be lag 7."""
    extended = extend("reaction_delay", IDM)
    params = params_for(extended, 0.7)
    inputs = make_inputs(lead_age=jnp.float32(2.0))
    got = extended.model.mean_acceleration(params, STATE, inputs)
    expected = perceived_idm(inputs.lag_gap[2], inputs.lag_v[2], inputs.lag_lead_v[2])
    np.testing.assert_allclose(got, expected, rtol=2e-5)
    old_leader = perceived_idm(inputs.lag_gap[7], inputs.lag_v[7], inputs.lag_lead_v[7])
    assert abs(float(got) - float(old_leader)) > 0.05


def test_reaction_delay_interpolates_between_samples():
    """0.25 s at 10 Hz is half way from lag 2 to lag 3, for every delayed input."""
    extended = extend("reaction_delay", IDM)
    params = params_for(extended, 0.25)
    inputs = make_inputs()
    got = extended.model.mean_acceleration(params, STATE, inputs)

    def between(lagged):
        return 0.5 * lagged[2] + 0.5 * lagged[3]

    # float32: 0.25 / 0.1 = 2.5 exactly enough; the interpolation weight is 0.5.
    expected = perceived_idm(
        between(inputs.lag_gap), between(inputs.lag_v), between(inputs.lag_lead_v)
    )
    np.testing.assert_allclose(got, expected, rtol=2e-5)


def test_autocorrelated_noise_lift_recovers_the_drawn_residual():
    """Simulate two steps; lifting the second from the observed first recovers its residual."""
    extended = extend("autocorrelated_noise", IDM)
    params = params_for(extended, 0.7)
    model = extended.model
    inputs0 = make_inputs()
    state0 = model.initial_sample(jax.random.key(1), params, STATE)
    first = model.transition_sample(jax.random.key(2), params, state0, read_by(model, inputs0))
    # The observed second step: its history holds the first step's speed, gap and increment.
    inputs1 = read_by(
        model,
        make_inputs(
            lag_v=inputs0.lag_v.at[1].set(STATE.v),
            lag_gap=inputs0.lag_gap.at[1].set(inputs0.gap),
            lag_lead_v=inputs0.lag_lead_v.at[1].set(inputs0.lead_v),
        ),
        previous_dx=first.x,
    )
    lifted = extended.model.lift(params, EgoState(jnp.float32(0.0), first.v), inputs1)
    np.testing.assert_allclose(lifted.residual, first.residual, atol=2e-4)
    applied = implied_acceleration(STATE.v, first.x, DT)
    base = idm_acceleration(IDM.defaults(), STATE.v, inputs0.gap, inputs0.lead_v, 1.0)
    np.testing.assert_allclose(first.residual, applied - base, atol=2e-4)
    # The step before is observed too (two steps back in the history, its increment read_by's
    # 1.21 m): both residuals are known.
    assert float(lifted.known) == 2.0
    history = make_inputs()
    earlier = history.lag_v[2], history.lag_gap[2], history.lag_lead_v[2]
    applied_before = implied_acceleration(earlier[0], 1.21, DT)
    base_before = idm_acceleration(IDM.defaults(), *earlier, 1.0)
    np.testing.assert_allclose(lifted.earlier_residual, applied_before - base_before, atol=2e-4)


@pytest.mark.parametrize(
    ("dt", "lag", "steps"), [(0.1, 0.0, 20000), (0.5, 0.0, 20000), (0.1, 0.2, 100000)]
)
def test_autocorrelated_noise_is_an_ornstein_uhlenbeck_error(dt, lag, steps):
    """A long simulated residual chain has sd sigma and the autocorrelations of the AR(2) with
    roots r_e = T / (T + dt) and r_l = T_l / (T_l + dt): the correlation time T = 0.5 s is in
    seconds, the per-step correlation follows the data's step (0.83 at 10 Hz, 0.5 at 2 Hz without
    a lag); a 0.2 s lag adds the root 2/3 at 10 Hz and lifts the lag-one correlation to 0.96.

    Constant inputs, seed 3, sigma = 0.3. Without the lag 20000 steps: the lag-1 sample correlation
    has sd about (1 - rho^2) / sqrt(n) < 0.01, we allow 0.03, and the sd 5%. With it, 100000 steps
    (about 1800 effective ones for the sd), the same tolerances; the lag-one correlation of the
    error without the lag (0.83) is 0.13 away, so a lag that did nothing fails.
    """
    extended = extend("autocorrelated_noise", IDM)
    params = params_for(extended, 0.5)._replace(noise_lag_s=jnp.float32(lag))
    inputs = read_by(extended.model, make_inputs(dt=jnp.float32(dt)))
    start = extended.model.initial_sample(jax.random.key(0), params, STATE)

    def step(state, key):
        moved = extended.model.transition_sample(
            key, params, state._replace(x=0.0, v=STATE.v), inputs
        )
        return moved, moved.residual

    _, residuals = jax.lax.scan(step, start, jax.random.split(jax.random.key(3), steps))
    residuals = np.asarray(residuals, np.float64)[100:]
    assert abs(residuals.std() - 0.3) < 0.05 * 0.3
    r_e, r_l = 0.5 / (0.5 + dt), lag / (lag + dt)
    lag_one = (r_e + r_l) / (1 + r_e * r_l)
    lag_two = (r_e + r_l) * lag_one - r_e * r_l
    assert abs(np.corrcoef(residuals[1:], residuals[:-1])[0, 1] - lag_one) < 0.03
    assert abs(np.corrcoef(residuals[2:], residuals[:-2])[0, 1] - lag_two) < 0.03


def test_speed_dependent_noise_sd_grows_with_speed():
    """The density's sd in acceleration units is sigma (1 + k v) / (1 + 10 k): sigma at 10 m/s,
    whatever the slope; the leader 80 m ahead keeps every speed's step inside the physical limits,
    where the density is Gaussian."""
    extended = extend("speed_dependent_noise", IDM)
    params = params_for(extended, 0.15)
    for v in (2.0, 10.0, 12.0, 25.0):
        state = EgoState(jnp.float32(0.0), jnp.float32(v))
        inputs = read_by(extended.model, make_inputs(gap=jnp.float32(80.0)))

        def logpdf_of_dx(dx, state=state, inputs=inputs):
            nxt = EgoState(jnp.float32(dx), state.v)
            return extended.model.transition_logpdf(params, state, nxt, inputs)

        _, sd_dx = quadratic_moments(logpdf_of_dx, v * DT, 0.002)
        expected = 0.3 * (1 + 0.15 * v) / (1 + 0.15 * 10.0)
        np.testing.assert_allclose(sd_dx / (0.5 * DT**2), expected, rtol=2e-3)


def test_second_leader_keeps_the_homogeneous_steady_state():
    """Equal gaps and speeds ahead: the anticipation weight changes nothing (module docstring)."""
    extended = extend("second_leader_anticipation", IDM)
    homogeneous = make_inputs(gap2=jnp.float32(2 * 18.0), lead2_v=jnp.float32(11.0))
    base = IDM.mean_acceleration(IDM.defaults(), STATE, homogeneous.car_following)
    for w in (0.0, 0.4, 1.0):
        got = extended.model.mean_acceleration(params_for(extended, w), STATE, homogeneous)
        np.testing.assert_allclose(got, base, rtol=1e-5)


def test_second_leader_braking_makes_the_follower_brake_earlier():
    """A slow second vehicle ahead lowers the acceleration in proportion to the weight."""
    extended = extend("second_leader_anticipation", IDM)
    slow_ahead = make_inputs(lead2_v=jnp.float32(5.0))
    a0, a_half, a1 = (
        float(extended.model.mean_acceleration(params_for(extended, w), STATE, slow_ahead))
        for w in (0.0, 0.5, 1.0)
    )
    assert a1 < a_half < a0
    np.testing.assert_allclose(a_half, 0.5 * (a0 + a1), rtol=1e-5)
    toward_second = idm_acceleration(IDM.defaults(), 12.0, 0.5 * 42.0, 5.0, 1.0)
    np.testing.assert_allclose(a1, toward_second, rtol=1e-5)


def test_cah_branches_by_hand():
    """The CAH of Kesting et al. (2010) in both branches, computed by hand.

    Leader faster and not braking (v=10, v_l=12, s=8, a_l=0): v_l (v - v_l) = -24 < 0 = -2 s a_l,
    first branch: a = v^2 a_l / (v_l^2 - 2 s a_l) = 0.
    Stopped leader (v=12, v_l=0, s=6, a_l=0): 0 < 0 is false, second branch: -144/12 = -12.
    Closing on a braking leader (v=15, v_l=10, s=20, a_l=-1): v_l (v - v_l) = 50 > 40, so the
    second branch: a = a_l - (v - v_l)^2 / (2 s) = -1 - 25/40 = -1.625.
    Leader braking to a stop first (v=10, v_l=5, s=30, a_l=-2): 5 * 5 = 25 <= 120: first branch,
    a = 100 * (-2) / (25 + 120) = -1.3793.
    """
    a_max = jnp.float32(3.0)
    np.testing.assert_allclose(cah_acceleration(10.0, 8.0, 12.0, 0.0, a_max), 0.0, atol=1e-6)
    np.testing.assert_allclose(cah_acceleration(12.0, 6.0, 0.0, 0.0, a_max), -12.0, rtol=1e-6)
    np.testing.assert_allclose(cah_acceleration(15.0, 20.0, 10.0, -1.0, a_max), -1.625, rtol=1e-6)
    np.testing.assert_allclose(
        cah_acceleration(10.0, 30.0, 5.0, -2.0, a_max), -200.0 / 145.0, rtol=1e-6
    )


def test_cah_relaxes_a_cut_in_but_not_an_emergency():
    """A cut-in at 6 m by a slightly faster car: the IDM brakes hard, the enhanced IDM hardly.

    A stopped obstacle at the same gap (a real emergency) still gets at least the braking the
    CAH says is needed (12 m/s^2, see the hand values above): the heuristic does not make the
    driver ignore danger.
    """
    extended = extend("cut_in_overreaction", IDM)
    cool = params_for(extended, 0.99)
    cut_in = make_inputs(gap=jnp.float32(6.0), lead_v=jnp.float32(12.5), lead_acc=jnp.float32(0.0))
    idm = float(IDM.mean_acceleration(IDM.defaults(), STATE, cut_in.car_following))
    enhanced = float(extended.model.mean_acceleration(cool, STATE, cut_in))
    assert idm < -3.0
    assert enhanced > 0.5 * idm
    stopped = make_inputs(gap=jnp.float32(6.0), lead_v=jnp.float32(0.0), lead_acc=jnp.float32(0.0))
    idm_stop = float(IDM.mean_acceleration(IDM.defaults(), STATE, stopped.car_following))
    enhanced_stop = float(extended.model.mean_acceleration(cool, STATE, stopped))
    assert enhanced_stop <= -12.0
    assert enhanced_stop >= idm_stop


def test_leader_acceleration_adds_its_weighted_clipped_value():
    """The IDM's acceleration (defaults, v = 12, s = 18, v_l = 11) plus w times the
    leader's acceleration, the latter clipped to [-9, 6] m/s^2 (a misread speed jump of 20 m/s^2
    counts as -9); without a leader, and for w = 0, the IDM alone."""
    extended = extend("leader_acceleration_anticipation", IDM)
    idm = float(idm_acceleration(IDM.defaults(), 12.0, 18.0, 11.0, 1.0))
    for lead_acc, counted in ((-1.5, -1.5), (2.0, 2.0), (-20.0, -9.0), (20.0, 6.0)):
        inputs = make_inputs(lead_acc=jnp.float32(lead_acc))
        for w in (0.0, 0.3, 1.0):
            got = extended.model.mean_acceleration(params_for(extended, w), STATE, inputs)
            np.testing.assert_allclose(got, idm + w * counted, rtol=1e-5, atol=1e-6)
    free_road = make_inputs(has_leader=jnp.float32(0.0), lead_acc=jnp.float32(-3.0))
    free = float(idm_acceleration(IDM.defaults(), 12.0, 18.0, 11.0, 0.0))
    got = extended.model.mean_acceleration(params_for(extended, 0.8), STATE, free_road)
    np.testing.assert_allclose(got, free, rtol=1e-6)


def test_unknown_cause_is_refused_with_the_known_ones():
    with pytest.raises(KeyError, match="reaction_delay"):
        extend("bad_weather", IDM)
    assert extend(NO_CAUSE, IDM).model is IDM


def three_car_platoon() -> Trajectories:
    """Leader A, B behind it, C behind B; 3 s at 10 Hz; A accelerates at 0.5 m/s^2."""
    t = np.round(np.arange(30) * DT, 6)
    v_a = 10.0 + 0.5 * t
    x_a = 100.0 + 10.0 * t + 0.25 * t**2
    v_b = np.full_like(t, 10.0)
    x_b = 70.0 + 10.0 * t
    v_c = np.full_like(t, 9.0)
    x_c = 40.0 + 9.0 * t
    return single_lane(
        t,
        (("A", x_a, v_a, None, None), ("B", x_b, v_b, "A", x_a), ("C", x_c, v_c, "B", x_b)),
        source="platoon",
    )


def test_scored_series_second_vehicle_leader_acceleration_and_history():
    """gap2 = sum of the two bumper gaps; lead_acc = backward difference; K steps unscored."""
    series = scored_series(three_car_platoon())
    assert series.vehicle_ids == ("B", "C")
    b, c = 0, 1
    steps = 29
    # C's second vehicle ahead is A: gap2 = (x_B - 4.5 - x_C) + (x_A - 4.5 - x_B).
    t = np.arange(steps) * DT
    expected_gap2 = (100.0 + 10 * t + 0.25 * t**2 - 4.5 - 4.5) - (40.0 + 9.0 * t)
    ahead = series.ahead
    np.testing.assert_allclose(ahead.gap2[c, :steps], expected_gap2, atol=1e-9)
    np.testing.assert_allclose(ahead.lead2_v[c, :steps], 10.0 + 0.5 * t, atol=1e-9)
    assert ahead.has_leader2[c, :steps].all() and not ahead.has_leader2[b, :steps].any()
    # B's leader A accelerates at 0.5: backward differences from the second sample on.
    np.testing.assert_allclose(ahead.lead_acc[b, 1:steps], 0.5, atol=1e-9)
    np.testing.assert_allclose(ahead.lead_acc[c, 1:steps], 0.0, atol=1e-9)
    scored = series.windows.fit + series.windows.heldout
    assert not scored[:, :K].any()
    # Every later step is scored except the one that straddles the split (in neither window).
    assert (scored[:, K:steps] == 0).sum(axis=1).tolist() == [1, 1]


def test_inputs_at_reads_the_history_window():
    series = scored_series(three_car_platoon())
    data = jax.tree.map(lambda a: a[1], device_series(series))
    j = K + 3
    inputs = inputs_at(data, j, K)
    np.testing.assert_allclose(inputs.lag_gap, series.gap[1, j - np.arange(K + 1)], rtol=1e-6)
    np.testing.assert_allclose(inputs.gap2, series.ahead.gap2[1, j], rtol=1e-6)


def test_fill_params_round_trip_of_an_extension():
    """Extension parameters sit after the base model's, in the documented order."""
    extended = extend("reaction_delay", IDM)
    names = extended.model.param_names
    assert names[: len(IDM.param_names)] == IDM.param_names
    theta = jnp.arange(len(names), dtype=jnp.float32)
    params = fill_params(extended.model, names, theta)
    assert float(params.reaction_time) == len(names) - 1


def platoon_steps(model):
    series = scored_series(three_car_platoon())
    return jax.tree.map(lambda a: a[1], step_inputs(series, model))


@pytest.mark.parametrize("cause", FILTERED)
def test_filter_switched_off_is_the_base_model(cause):
    """With its parameter at 0 the filter gives the base model's one-step densities exactly."""
    extended = extend(cause, IDM)
    steps = platoon_steps(extended.model)
    ours = extended.model.filter(params_for(extended), steps)
    base_steps = platoon_steps(IDM)
    base = jax.vmap(
        lambda i, v, nv, dx: IDM.transition_logpdf(
            IDM.defaults(), EgoState(0.0 * v, v), EgoState(dx, nv), i
        )
    )(base_steps.inputs, base_steps.v, base_steps.next_v, base_steps.dx)
    np.testing.assert_allclose(ours, base, rtol=1e-5, atol=1e-4)


def simulate_follower(cause: str, effect: float, seed: int, steps: int = 3000):
    """One follower of the extension model behind a replayed leader (speed 10-14 m/s), simulated
    in a scan; returns the model, its parameters and StepInputs of the record (for measurement
    noise the recorded positions carry the noise; speeds and gaps are exact)."""

    extended = extend(cause, IDM)
    params = params_for(extended, effect)
    lead_v = 12.0 + 2.0 * jnp.sin(jnp.arange(steps + 1) * DT / 4.0)
    lead_dx = 0.5 * (lead_v[:-1] + lead_v[1:]) * DT
    key = jax.random.key(seed)
    start = extended.model.initial_sample(
        key, params, EgoState(jnp.float32(0.0), jnp.float32(12.0))
    )

    def step(carry, t):
        state, gap = carry
        inputs = read_by(extended.model, make_inputs(gap=gap, lead_v=lead_v[t]))
        moved = extended.model.transition_sample(
            jax.random.fold_in(key, t), params, state._replace(x=jnp.float32(0.0)), inputs
        )
        record = (state.v, moved.v, moved.x, inputs)
        return (moved, gap + lead_dx[t] - moved.x), record

    _, (v, next_v, dx, inputs) = jax.lax.scan(step, (start, jnp.float32(25.0)), jnp.arange(steps))
    if cause == "measurement_noise":
        noise = effect * jax.random.normal(jax.random.key(seed + 1), (steps + 1,))
        dx = dx + jnp.diff(noise)
    ones = jnp.ones(steps)
    return extended, params, StepInputs(v, next_v, dx, ones, inputs, ones, 0 * ones)


def test_measurement_noise_filter_is_maximised_at_the_true_noise():
    """Data simulated with 2 cm position noise (3000 steps, seed 12): the filter's log density
    over a grid of noise levels peaks at the true one (the MLE's relative sd is ~1.3% here, the
    grid steps 15%), and beats the base model (noise 0) by > 1000 nats. A filter with a wrong
    predictive variance (e.g. 2 s^2 for the new reading) would peak elsewhere."""
    extended, params, steps = simulate_follower("measurement_noise", 0.02, seed=12)
    grid = 0.02 * np.array([0.7, 0.85, 1.0, 1.15, 1.4])
    totals = [
        float(jnp.sum(extended.model.filter(params._replace(sigma_obs=s), steps))) for s in grid
    ]
    assert int(np.argmax(totals)) == 2
    base = float(jnp.sum(extended.model.filter(params._replace(sigma_obs=0.0), steps)))
    assert totals[2] - base > 1000.0


def test_drift_filter_prefers_the_true_drift():
    """Time gap drifting at 0.1 s/sqrt(s) (3000 steps, seed 13): the filter's log density at the true
    drift beats no drift by > 20 nats and a drift 4 times too large."""
    extended, params, steps = simulate_follower("drifting_parameters", 0.1, seed=13)

    def total(q):
        return float(jnp.sum(extended.model.filter(params._replace(tau_drift=q), steps)))

    assert total(0.1) - total(0.0) > 20.0
    assert total(0.1) > total(0.4)


def drift_log_likelihood(tmp_path):
    """The drift model's log-likelihood on the unconstrained scale (NumPyro's logit of the box), on
    the independent generator's drifting time gap (``time_gap_drift``, amplitude drawn in
    0.2-0.35 of tau, 60 s, seed 20261207, the first follower with steps; 419 steps), as a function
    of one point; and the parameters' names."""
    from bayesdrive.data.readers import read
    from bayesdrive.data.views import follower_arrays
    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.core.likelihood import fixed_params, series_loglik
    from trafficgen import generate

    path = tmp_path / "drift.csv"
    generate(
        20261207, path, {"time_gap_drift": (0.2, 0.35)}, platoons=1, followers=6, duration_s=60.0
    )
    arrays = follower_arrays(read(path, format="ngsim_raw"), window="fit")
    model = get_model("idm+drifting_parameters")
    series = jax.tree.map(lambda a: a[0], step_inputs(arrays, model))
    lower = jnp.asarray([spec.lower for spec in model.specs])
    upper = jnp.asarray([spec.upper for spec in model.specs])
    names, fixed = model.param_names, fixed_params(model, None)

    def total(z):
        theta = lower + (upper - lower) * jax.nn.sigmoid(z)
        return series_loglik(model, names, fixed, theta, series).sum()

    return total, names


@pytest.mark.parametrize(
    "start",
    [
        # Here nuts' warm-up stalled on this vehicle with the filter that linearised by the
        # derivative at the mean, and the scan of d_min jumped 104 nats: the filtered time gap met
        # the clip to tau's box.
        (-0.76, 1.099, -0.22, -1.554, 1.268, -1.156, 1.308),
        # Here it stalled with a smooth clip and the same derivative, and the scan of d_min jumped
        # 18 nats: the time gap met the IDM's floored dynamic gap.
        (-0.02, 1.511, -1.383, -1.006, 0.944, -2.299, 1.783),
    ],
)
def test_drift_filter_likelihood_does_not_jump(tmp_path, start):
    """The drift filter's log-likelihood is continuous in the parameters, also where the filtered
    time gap crosses a kink of the rule (the IDM's floored dynamic gap, the clip to tau's box;
    ``reports/convergence/drifting_nuts.md``). Each of the seven parameters is scanned over +-1e-3
    on the unconstrained scale in 2001 points (data: :func:`drift_log_likelihood`). Tolerance:
    neighbours differ by at most 0.01 nats (float32 rounding of the 419-step sum is ~1e-4)."""
    total, names = drift_log_likelihood(tmp_path)
    scan_total = jax.jit(jax.vmap(total))
    offsets = jnp.linspace(-1e-3, 1e-3, 2001)
    largest = {}
    for j, name in enumerate(names):
        scan = jnp.asarray(start)[None, :] + jnp.zeros((offsets.size, len(names))).at[:, j].set(
            offsets
        )
        largest[name] = float(np.abs(np.diff(np.asarray(scan_total(scan), dtype=np.float64))).max())
    assert max(largest.values()) < 0.01, f"largest jump per parameter (nats): {largest}"


def test_drift_filter_gradient_is_finite_where_nuts_starts(tmp_path):
    """The gradient of the drift filter's log-likelihood is finite at 2000 uniform points of
    (-2, 2)^7 on the unconstrained scale, where nuts starts its chains (key 0; data:
    :func:`drift_log_likelihood`). A slope whose difference step followed the filtered sd
    overflowed to NaN at about 1% of such points (reports/convergence/drifting_nuts.md)."""
    total, names = drift_log_likelihood(tmp_path)
    points = jax.random.uniform(jax.random.key(0), (2000, len(names)), minval=-2.0, maxval=2.0)
    gradients = np.asarray(jax.jit(jax.vmap(jax.grad(total)))(points))
    finite = np.isfinite(gradients).all(axis=1)
    assert finite.all(), f"{(~finite).sum()} of 2000 points have a non-finite gradient"


@pytest.mark.parametrize(
    ("composite", "off", "equals"),
    [
        ("idm+reaction_delay+autocorrelated_noise", {"noise_time_s": 0.0}, "idm+reaction_delay"),
        (
            "idm+reaction_delay+autocorrelated_noise",
            {"reaction_time": 0.0},
            "idm+autocorrelated_noise",
        ),
        (
            "idm+second_leader_anticipation+speed_dependent_noise",
            {"anticipation": 0.0},
            "idm+speed_dependent_noise",
        ),
    ],
)
def test_a_composite_with_one_extension_off_scores_like_the_other(composite, off, equals):
    """Composition nests: switching one extension off leaves the model with the other, step by
    step on a recorded platoon (scored through each model's own inputs)."""
    from bayesdrive.drivers.registry import get_model

    series = scored_series(three_car_platoon())
    joined, single = get_model(composite), get_model(equals)
    on = {"reaction_time": 0.37, "noise_time_s": 0.2, "anticipation": 0.5, "noise_speed_slope": 0.1}
    values = {name: on.get(name, getattr(joined.defaults(), name)) for name in joined.param_names}
    values.update(off)
    joined_params = joined.params_type(*(jnp.float32(values[n]) for n in joined.param_names))
    single_params = single.params_type(*(jnp.float32(values[n]) for n in single.param_names))
    scored = np.asarray(series.windows.fit + series.windows.heldout) > 0

    def logpdfs(model, params):
        return np.asarray(
            jax.vmap(lambda steps: step_logpdfs(model, params, steps))(step_inputs(series, model))
        )

    ours, theirs = logpdfs(joined, joined_params), logpdfs(single, single_params)
    np.testing.assert_allclose(ours[scored], theirs[scored], rtol=1e-5, atol=1e-4)
    # Negative control: with both on, the composite differs from either alone.
    both = joined.params_type(
        *(jnp.float32(on.get(n, getattr(joined_params, n))) for n in joined.param_names)
    )
    differs = logpdfs(joined, both)
    assert np.abs(differs[scored] - theirs[scored]).max() > 1e-2


def test_composition_rules_refuse_in_one_line():
    from bayesdrive.drivers.registry import canonical_name, get_model

    assert canonical_name("autocorrelated_noise+idm+reaction_delay") == (
        "idm+reaction_delay+autocorrelated_noise"
    )
    assert get_model("autocorrelated_noise+reaction_delay+idm") is get_model(
        "idm+reaction_delay+autocorrelated_noise"
    )
    for name, words in (
        ("idm+reaction_delay+second_leader_anticipation", "one of each kind"),
        ("idm+drifting_parameters+autocorrelated_noise", "composes with no other"),
        ("idm+speed_dependent_noise+measurement_noise", "white execution noise"),
        ("cidm+reaction_delay", "car-following inputs only"),
    ):
        with pytest.raises(KeyError, match=words):
            get_model(name)


def test_lead_age_restarts_exactly_where_a_vehicle_cuts_in(tmp_path):
    """On data of the independent generator with cut-ins, the leader's age is 0 where the gap
    jumps (a new leader) and counts up elsewhere (seed 4)."""
    from bayesdrive.data.readers import read
    from trafficgen import generate

    path = tmp_path / "cut_ins.csv"
    generate(4, path, {}, platoons=1, followers=4, duration_s=40.0, cut_ins=6)
    series = scored_series(read(path, format="ngsim_raw"))
    age, gap = series.ahead.lead_age, series.gap
    usable = (series.mask[:, 1:] > 0) & (series.mask[:, :-1] > 0)
    expected_change = (series.lead_v[:, :-1] - series.v[:, :-1]) * series.dt
    jumps = np.abs(np.diff(gap, axis=1) - expected_change) > 1.0
    restarts = age[:, 1:] == 0
    assert restarts[usable].any()
    np.testing.assert_array_equal(restarts[usable], jumps[usable])
    counted = usable & ~restarts
    np.testing.assert_array_equal(age[:, 1:][counted], age[:, :-1][counted] + 1)


def lagged_error_follower(lag_s: float, seed: int, steps: int = 3000) -> Trajectories:
    """A follower written here in numpy, sharing no code with the model: the IDM (defaults, delta
    4) behind a leader at 14 m/s that starts 120 m ahead, plus an error that is an
    Ornstein-Uhlenbeck process of correlation time 1 s passed through a first-order lag of time
    ``lag_s`` (two backward-Euler filters), scaled to sd 0.3 m/s^2. Exact kinematics per 0.1 s."""
    rng = np.random.default_rng(seed)
    r_e, r_l = 1.0 / (1.0 + DT), lag_s / (lag_s + DT)
    error = np.zeros(steps)
    lagged = np.zeros(steps)
    for t in range(1, steps):
        error[t] = r_e * error[t - 1] + math.sqrt(1 - r_e**2) * rng.standard_normal()
        lagged[t] = r_l * lagged[t - 1] + (1 - r_l) * error[t]
    lagged *= 0.3 / lagged[200:].std()
    v_des, d_min, tau, a_max, b_pref = 30.0, 2.0, 1.0, 3.0, 2.0
    t = np.round(np.arange(steps + 1) * DT, 6)
    x_lead, v_lead = 120.0 + 14.0 * t, np.full(steps + 1, 14.0)
    x, v = np.zeros(steps + 1), np.full(steps + 1, 14.0)
    for k in range(steps):
        gap = x_lead[k] - 4.5 - x[k]
        wanted = d_min + max(
            0.0, v[k] * tau + v[k] * (v[k] - v_lead[k]) / (2 * math.sqrt(a_max * b_pref))
        )
        acc = a_max * (1 - (v[k] / v_des) ** 4 - (wanted / gap) ** 2) + lagged[k]
        x[k + 1] = x[k] + v[k] * DT + 0.5 * acc * DT**2
        v[k + 1] = v[k] + acc * DT
    return single_lane(
        t, (("L", x_lead, v_lead, None, None), ("F", x, v, "L", x_lead)), source="lagged"
    )


@pytest.mark.parametrize(("lag_s", "best"), [(0.2, 0.2), (0.0, 0.0)])
def test_the_noise_lag_is_found_where_the_data_hide_it(lag_s, best):
    """On the numpy follower above (3000 steps, seed 21), the model's log density over a grid of
    lags, at the true correlation time and the generator's other values, peaks at the lag the
    data hide: 0.2 s (per-step root 2/3, against 1/2 and 3/4 for the grid's neighbours), and 0
    on data without a lag, the negative control. A lag the density ignored, or a root misplaced
    in the AR(2), would peak elsewhere."""
    model = extend("autocorrelated_noise", IDM).model
    series = scored_series(lagged_error_follower(lag_s, seed=21))
    steps = jax.tree.map(lambda a: a[0], step_inputs(series, model))
    grid = (0.0, 0.1, 0.2, 0.3, 0.45)

    def total(lag):
        params = model.defaults()._replace(
            sigma=jnp.float32(0.3), noise_time_s=jnp.float32(1.0), noise_lag_s=jnp.float32(lag)
        )
        scores = step_logpdfs(model, params, steps)
        return float(jnp.sum(jnp.where(steps.mask > 0, scores, 0.0)))

    totals = [total(lag) for lag in grid]
    assert grid[int(np.argmax(totals))] == best


def test_state_correction_off_is_the_base_rule_and_on_adds_its_features():
    """All coefficients 0: the IDM's mean acceleration. Coefficients (0.3, -0.2, -0.5): the IDM's
    plus their sum with the features written here by hand (tanh of (v - 15)/10, (s - 20)/20 and
    (v - v_lead)/2); without a leader only the speed term remains, whatever the gap holds."""
    model = extend("state_correction", IDM).model
    off = model.defaults()
    on = off._replace(
        corr_speed=jnp.float32(0.3), corr_gap=jnp.float32(-0.2), corr_closing=jnp.float32(-0.5)
    )
    base = IDM.defaults()
    for v, gap, lead_v, has in (
        (12.0, 18.0, 11.0, 1.0),
        (25.0, 60.0, 27.0, 1.0),
        (9.0, 1e9, 0.0, 0.0),
    ):
        inputs = make_inputs(
            gap=jnp.float32(gap), lead_v=jnp.float32(lead_v), has_leader=jnp.float32(has)
        )
        state = EgoState(jnp.float32(0.0), jnp.float32(v))
        rule = float(IDM.mean_acceleration(base, state, inputs.car_following))
        assert float(model.mean_acceleration(off, state, inputs)) == pytest.approx(rule)
        added = 0.3 * math.tanh((v - 15.0) / 10.0) + has * (
            -0.2 * math.tanh((gap - 20.0) / 20.0) - 0.5 * math.tanh((v - lead_v) / 2.0)
        )
        got = float(model.mean_acceleration(on, state, inputs))
        assert got == pytest.approx(rule + added, abs=1e-5)


@pytest.mark.parametrize(("hidden", "best"), [(-0.6, -0.6), (0.0, 0.0)])
def test_the_state_correction_is_found_where_the_data_hide_it(hidden, best):
    """On the numpy follower above (3000 steps, seed 22), the model's log density over a grid of
    the closing coefficient, at the generator's other values, peaks at the coefficient the data
    hide: -0.6 m/s^2, and 0 on data without one, the negative control. A feature with the wrong
    sign, centre or scale, or one the density ignored, would peak elsewhere."""
    model = extend("state_correction", IDM).model
    series = scored_series(corrected_follower(hidden, seed=22))
    steps = jax.tree.map(lambda a: a[0], step_inputs(series, model))
    grid = (-1.0, -0.8, -0.6, -0.4, -0.2, 0.0, 0.2)
    defaults = model.defaults()._replace(
        v_des=jnp.float32(30.0),
        d_min=jnp.float32(2.0),
        tau=jnp.float32(1.0),
        a_max=jnp.float32(3.0),
        b_pref=jnp.float32(2.0),
        sigma=jnp.float32(0.3),
    )

    def total(coefficient):
        scores = step_logpdfs(
            model, defaults._replace(corr_closing=jnp.float32(coefficient)), steps
        )
        return float(jnp.sum(jnp.where(steps.mask > 0, scores, 0.0)))

    totals = [total(c) for c in grid]
    assert grid[int(np.argmax(totals))] == best, dict(zip(grid, np.round(totals, 1), strict=True))
