"""The drifting time gap's filtered start: the law its filter gives of the offset from a series'
history, and the forecast that starts from it.

The data are a follower driven by an IDM written here in numpy (not the library's rule or
simulator), with a time gap that differs from the fitted one by a known amount.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.data.views import AheadArrays
from bayesdrive.drivers.base import EgoState, Series
from bayesdrive.drivers.registry import get_model

DRIFTING = get_model("idm+drifting_parameters")
DT = 0.1
STEPS = 600
# The fitted parameters; the data's driver differs from them in its time gap only.
FITTED = {
    "v_des": 30.0,
    "d_min": 2.0,
    "tau": 1.2,
    "a_max": 1.5,
    "b_pref": 2.0,
    "sigma": 0.1,
    "tau_drift": 0.1,
}


def follower(tau, seed: int) -> Series:
    """A follower behind a leader whose speed swings between 7 and 13 m/s, driven by the IDM
    (written here) with time gap ``tau`` (a number, or one per step) and white acceleration noise
    of sd 0.05 m/s^2."""
    rng = np.random.default_rng(seed)
    tau_at = np.broadcast_to(np.asarray(tau, float), (STEPS,))
    t = np.arange(STEPS + 1) * DT
    lead_v = 10.0 + 3.0 * np.sin(2 * np.pi * t / 20.0)
    lead_x = 30.0 + np.concatenate([[0.0], np.cumsum(lead_v[:-1] * DT)])
    x, v = np.zeros(STEPS + 1), np.zeros(STEPS + 1)
    v[0] = 10.0
    p = FITTED
    for j in range(STEPS):
        tau = tau_at[j]
        gap = lead_x[j] - x[j] - 5.0
        desired = p["d_min"] + max(
            0.0, v[j] * tau + v[j] * (v[j] - lead_v[j]) / (2 * np.sqrt(p["a_max"] * p["b_pref"]))
        )
        a = p["a_max"] * (1 - (v[j] / p["v_des"]) ** 4 - (desired / gap) ** 2)
        a += 0.05 * rng.standard_normal()
        v[j + 1] = max(0.0, v[j] + a * DT)
        x[j + 1] = x[j] + v[j] * DT + 0.5 * (v[j + 1] - v[j]) * DT
    gap = lead_x - x - 5.0
    f32 = lambda a: jnp.asarray(a[:STEPS], jnp.float32)  # noqa: E731
    ones = jnp.ones(STEPS, jnp.float32)
    return Series(
        v=f32(v),
        next_v=jnp.asarray(v[1:], jnp.float32),
        dx=jnp.asarray(np.diff(x), jnp.float32),
        gap=f32(gap),
        lead_v=f32(lead_v),
        has_leader=ones,
        mask=ones,
        dt=ones * DT,
        ahead=AheadArrays(
            lead_acc=f32(np.concatenate([[0.0], np.diff(lead_v) / DT])),
            gap2=f32(gap + 50.0),
            lead2_v=f32(lead_v),
            has_leader2=0 * ones,
            lead_age=jnp.arange(STEPS, dtype=jnp.float32),
        ),
    )


def fitted_params(**overrides):
    values = FITTED | overrides
    return DRIFTING.params_type(*(jnp.float32(values[n]) for n in DRIFTING.param_names))


def law(series: Series, until: int, **overrides):
    mean, var = DRIFTING.filtered_start.law(fitted_params(**overrides), series, jnp.asarray(until))
    return float(mean), float(var)


@pytest.mark.parametrize("shift", [0.6, -0.4])
def test_the_filtered_offset_finds_the_drivers_time_gap(shift):
    """After 60 s the filtered offset is the driver's time gap minus the fitted one, within 0.15 s
    (an IDM whose time gap is off by 0.4-0.6 s); the negative control, a driver with the fitted
    time gap, leaves it within 0.15 s of 0."""
    mean, var = law(follower(FITTED["tau"] + shift, seed=1), STEPS)
    assert mean == pytest.approx(shift, abs=0.15)
    assert 0 < var < 0.1**2 * STEPS * DT  # the data narrowed the random walk's spread
    control, _ = law(follower(FITTED["tau"], seed=2), STEPS)
    assert abs(control) < 0.15


def test_the_filter_comes_back_from_below_the_box():
    """Fitted time gap 0.3 s, near the box's floor 0.1 s; the driver keeps a time gap of -0.6 s
    (tailgating, below the box) for 30 s, then 1.0 s for 30 s (seeds 11-13). At the switch the
    filtered offset sits on the floor (-0.2, within 0.01); at the end it is the driver's 1.0 s
    minus the fitted 0.3 s, within 0.1. A filter whose mean could leave the box ran to an offset
    of -28 s, where the rule is flat, and never came back."""
    time_gap = np.where(np.arange(STEPS) < STEPS // 2, -0.6, 1.0)
    for seed in (11, 12, 13):
        series = follower(time_gap, seed)
        at_switch, _ = law(series, STEPS // 2, tau=0.3)
        at_end, _ = law(series, STEPS, tau=0.3)
        assert at_switch == pytest.approx(0.1 - 0.3, abs=0.01)
        assert at_end == pytest.approx(1.0 - 0.3, abs=0.1)


def test_the_law_reads_only_the_steps_before_its_start():
    """What the series holds from ``until`` on does not change the law there (no look-ahead); no
    step before it: the prior (offset 0, known); no drift (tau_drift = 0): the fitted time gap."""
    series = follower(FITTED["tau"] + 0.6, seed=3)
    until = STEPS // 2
    altered = series._replace(dx=series.dx.at[until:].multiply(1.5))
    assert law(series, until) == law(altered, until)
    assert law(series, until) != law(series, until + 10)
    assert law(series, 0) == (0.0, 0.0)
    assert law(series, STEPS, tau_drift=0.0) == (0.0, 0.0)


def test_a_start_draws_the_offset_from_the_law():
    """Offsets drawn from a law (0.3, 0.2^2): mean and sd within 0.01 of it over 20,000 keys
    (seed 5); the observed position and speed are kept."""
    keys = jax.random.split(jax.random.key(5), 20_000)
    here = EgoState(jnp.float32(0.0), jnp.float32(11.0))
    draw = jax.vmap(lambda k: DRIFTING.filtered_start.draw(k, fitted_params(), here, (0.3, 0.04)))
    states = draw(keys)
    assert float(states.tau_offset.mean()) == pytest.approx(0.3, abs=0.01)
    assert float(states.tau_offset.std()) == pytest.approx(0.2, abs=0.01)
    assert np.all(np.asarray(states.v) == 11.0) and np.all(np.asarray(states.x) == 0.0)
