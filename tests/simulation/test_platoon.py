"""String stability and wave speed on chains built by hand, where both are known exactly."""

import numpy as np
import pytest

from bayesdrive.simulation.platoon import (
    amplification,
    chain_pairs,
    newell_shifts,
    platoon_measures,
    platoon_summary,
    wave_speed,
)

DT = 0.1
STEPS = 81  # 8 s of states


def head_trajectory():
    """A congested head that slows from 12 to 6 m/s and back (a wave to time)."""
    t = np.arange(STEPS) * DT
    v = 9.0 + 3.0 * np.cos(2 * np.pi * t / 8.0)
    x = np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])
    return x, v


def newell_chain(tau_steps: int, distance: float, followers: int):
    """Followers that repeat the vehicle ahead exactly, tau_steps later and distance behind; before
    the shift starts they hold the ahead vehicle's first speed (their own past)."""
    x, v = head_trajectory()
    xs, vs = [x], [v]
    for _ in range(followers):
        ahead_x, ahead_v = xs[-1], vs[-1]
        v_next = np.concatenate([np.full(tau_steps, ahead_v[0]), ahead_v[:-tau_steps]])
        x_next = np.concatenate(
            [
                ahead_x[0] - distance - ahead_v[0] * DT * np.arange(tau_steps, 0, -1),
                ahead_x[:-tau_steps] - distance,
            ]
        )
        xs.append(x_next)
        vs.append(v_next)
    return np.array(xs), np.array(vs)


def test_newell_chain_gives_its_lag_distance_and_wave_speed():
    x, v = newell_chain(tau_steps=12, distance=7.5, followers=3)
    shifts = newell_shifts(*chain_pairs(x[0], v[0], x[1:], v[1:]), DT)
    np.testing.assert_allclose(shifts[:, 0], 1.2, atol=1e-9)
    np.testing.assert_allclose(shifts[:, 1], 7.5, atol=1e-9)
    assert wave_speed(shifts) == pytest.approx(7.5 / 1.2)
    # Negative control: another chain's lag and distance give another speed.
    x, v = newell_chain(tau_steps=20, distance=9.0, followers=3)
    other = newell_shifts(*chain_pairs(x[0], v[0], x[1:], v[1:]), DT)
    assert wave_speed(other) == pytest.approx(9.0 / 2.0)


def test_amplification_of_a_chain_that_scales_speed_variation():
    x, v = head_trajectory()
    # Each follower's speed deviates from 9 m/s by 1.5x its predecessor's (no lag needed).
    speeds = np.stack([9.0 + 1.5**k * (v - 9.0) for k in range(4)])
    positions = np.stack([x - 10.0 * k for k in range(4)])
    variances, _ = platoon_measures(positions[0], speeds[0], positions[1:], speeds[1:], DT)
    assert amplification(variances) == pytest.approx(1.5)
    # A faithful copy neither grows nor damps.
    same, _ = platoon_measures(x, v, np.stack([x - 8, x - 16]), np.stack([v, v]), DT)
    assert amplification(same) == pytest.approx(1.0)


def test_rollout_axes_give_pairs_of_their_own_and_steady_predecessors_are_left_out():
    x, v = newell_chain(tau_steps=10, distance=8.0, followers=2)
    rollouts = np.stack([x[1:], x[1:]]), np.stack([v[1:], v[1:]])
    variances, shifts = platoon_measures(x[0], v[0], *rollouts, DT)
    assert variances.shape == (4, 2) and shifts.shape == (4, 2)
    steady = np.full(STEPS, 12.0)
    steady_x = 12.0 * DT * np.arange(STEPS)
    _, none = platoon_measures(steady_x, steady, steady_x[None] - 8.0, steady[None], DT)
    assert none.shape == (0, 2)
    summary = platoon_summary({"simulated": variances}, {"simulated": none})
    assert summary["wave_speed_mps"]["simulated_upstream"] is None
    assert summary["string_stability"]["simulated_pairs"] == 4


def test_a_scene_shorter_than_twice_the_largest_lag_has_no_shift():
    x, v = head_trajectory()
    short = slice(0, 40)  # 4 s: a 3 s lag would leave 1 s of overlap
    assert newell_shifts(
        x[None, short], v[None, short], x[None, short] - 8, v[None, short], DT
    ).shape == (0, 2)


def test_lags_outside_the_search_range_and_free_flow_are_not_timed():
    x, v = newell_chain(tau_steps=30, distance=8.0, followers=2)  # 3 s: beyond the 2.5 s searched
    assert newell_shifts(*chain_pairs(x[0], v[0], x[1:], v[1:]), DT).shape == (0, 2)
    x, v = newell_chain(tau_steps=12, distance=8.0, followers=2)
    fast = v + 20.0  # the same wave at 29 m/s: free flow
    fast_x = x + 20.0 * DT * np.arange(STEPS)
    variances, shifts = platoon_measures(fast_x[0], fast[0], fast_x[1:], fast[1:], DT)
    assert shifts.shape == (0, 2) and variances.shape == (2, 2)
