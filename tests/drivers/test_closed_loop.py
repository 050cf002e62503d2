"""The one simulator's starts (filtered from the observed history, stationary) on data from the
independent generator, and the forecast scores against scoringrules' closed forms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scoringrules

from bayesdrive.drivers.base import EgoState, device_series, fill_params
from bayesdrive.drivers.closed_loop import FILTERED, STATIONARY, check_start
from bayesdrive.drivers.extensions import as_extended
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.simulation.calibration import forecast_scores, point_scores
from bayesdrive.simulation.follower_rollout import (
    Rollouts,
    RolloutWindows,
    heldout_windows,
    rollout,
)

DELAY_AR = "idm+reaction_delay+autocorrelated_noise"


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """Two followers of the independent generator (white noise, no cut-in), 20 s: the shape the
    tempering tests use."""
    from bayesdrive.data.readers import read
    from bayesdrive.data.views import scored_series
    from trafficgen import generate

    path = tmp_path_factory.mktemp("closed_loop") / "two.csv"
    generate(8, path, None, platoons=1, followers=2, duration_s=20.0, cut_ins=0)
    return scored_series(read(path, format="ngsim_raw"))


def _theta(model, series, **values):
    theta = np.array([float(getattr(model.defaults(), n)) for n in model.param_names])
    for name, value in values.items():
        theta[model.param_names.index(name)] = value
    return np.broadcast_to(theta, (len(series.vehicle_ids), 1, len(theta))).copy()


def _first_acceleration(rolled: Rollouts, series) -> np.ndarray:
    """(window, rollout) acceleration of each rollout's first step, from its speed error."""
    row, start = rolled.windows.row, rolled.windows.start
    observed = series.next_v[row, start]
    return (rolled.speed_offset[:, :, 0] + observed[:, None] - series.v[row, start][:, None]) / (
        series.dt
    )


def test_filtered_start_recovers_the_delay_buffer_and_the_ar_residual(generated):
    """Reaction delay 0.8 s and AR noise of correlation time 1 s with a negligible sd (1e-6 m/s^2, so a rollout's
    first step is its mean): from ``filtered`` that first acceleration is the model's mean on the
    data's own series at the window's start, the delayed perception and the last residual read
    from the observed history (the engines' view of the data), within 1e-3 m/s^2 (float32
    speeds). ``stationary`` (the negative control) has neither, so it misses by far more on most
    windows. The plain IDM, without such a state, gives the same bits from both starts."""
    series = generated
    windows = heldout_windows(series, 1.0)
    assert len(windows.row) >= 4
    model = get_model(DELAY_AR)
    values = {"reaction_time": 0.8, "noise_time_s": 1.0, "sigma": 1e-6}
    theta = _theta(model, series, **values)
    key = jax.random.key(3)
    filtered, stationary = (
        rollout(key, as_extended(model), theta, series, windows, num_rollouts=2, start=start)
        for start in (FILTERED, STATIONARY)
    )
    data = device_series(series, jnp.float32)
    params = fill_params(model, model.param_names, jnp.asarray(theta[0, 0], jnp.float32))

    def mean_at(row, start):
        one = jax.tree.map(lambda a: a[row], data)
        inputs = model.inputs_at(one, start, series.history)
        state = model.lift(params, EgoState(0.0, one.v[start]), inputs)
        return model.mean_acceleration(params, state, inputs)

    expected = np.asarray(jax.jit(jax.vmap(mean_at))(windows.row, windows.start))[:, None]
    recovered = _first_acceleration(filtered, series)
    np.testing.assert_allclose(recovered, np.broadcast_to(expected, recovered.shape), atol=1e-3)
    missed = np.abs(_first_acceleration(stationary, series) - expected)[:, 0] > 0.05
    assert missed.mean() > 0.5

    plain = _theta(IDM, series)
    same = [
        rollout(key, as_extended(IDM), plain, series, windows, num_rollouts=2, start=start)
        for start in (FILTERED, STATIONARY)
    ]
    np.testing.assert_array_equal(same[0].offset, same[1].offset)
    np.testing.assert_array_equal(same[0].speed_offset, same[1].speed_offset)


def test_a_drifting_time_gap_starts_from_its_filtered_law(generated):
    """Held-out windows of ``idm+drifting_parameters``: without drift (tau_drift = 0) the filter's
    law is the fitted time gap, known, so the filtered start gives the stationary start's bits;
    with drift (0.2 s/s^0.5) the offset filtered from each window's history moves the first
    step's acceleration on most windows (by more than 0.01 m/s^2; the noise sd is 1e-6)."""
    series = generated
    windows = heldout_windows(series, 1.0)
    model = get_model("idm+drifting_parameters")
    key = jax.random.key(4)

    def both(**values):
        theta = _theta(model, series, sigma=1e-6, **values)
        return [
            rollout(key, as_extended(model), theta, series, windows, num_rollouts=2, start=start)
            for start in (FILTERED, STATIONARY)
        ]

    still = both(tau_drift=0.0)
    np.testing.assert_array_equal(still[0].offset, still[1].offset)
    assert still[0].start == FILTERED
    drifting = both(tau_drift=0.2)
    moved = np.abs(
        _first_acceleration(drifting[0], series) - _first_acceleration(drifting[1], series)
    )
    assert (moved[:, 0] > 0.01).mean() > 0.5


def test_filtered_start_refuses_a_hidden_state_it_cannot_filter_in_one_line():
    """A drifting parameter is a hidden state filtered over a window's whole history: a scene
    without the filter's laws is refused, naming the model and the start to use instead, one
    with them (held-out follower windows) is taken. An observation model is refused either way."""
    drifting = get_model("idm+drifting_parameters")
    with pytest.raises(ValueError, match=r"idm\+drifting_parameters.*no filtered laws.*stationary"):
        check_start(drifting, FILTERED, has_past=True)
    check_start(drifting, FILTERED, has_past=True, whole_history=True)
    check_start(drifting, STATIONARY, has_past=False)
    noisy = get_model("idm+measurement_noise")
    with pytest.raises(ValueError, match=r"observed through .*stationary"):
        check_start(noisy, FILTERED, has_past=True, whole_history=True)
    with pytest.raises(ValueError, match="holds none"):
        check_start(IDM, FILTERED, has_past=False)


def test_forecast_scores_match_the_closed_forms():
    """4000 normal draws (numpy, seed 7) as one window's rollouts of the position: their CRPS
    matches the closed-form CRPS of N(0, 1) at the observation (scoringrules' ``crps_normal``)
    within 0.04 (about 4 Monte Carlo sd), and the doubled spread (the negative control) does not.
    On a one-step path with no speed error the energy score is the CRPS of the gap (the energy
    score in one dimension is the CRPS)."""
    y = 0.7
    exact = float(scoringrules.crps_normal(y, 0.0, 1.0))
    draws = np.random.default_rng(7).standard_normal(4000)
    assert point_scores((draws - y)[None])["crps_m"] == pytest.approx(exact, abs=0.04)
    assert point_scores((2.0 * draws - y)[None])["crps_m"] != pytest.approx(exact, abs=0.04)

    offset = (draws[:200] - y)[None, :, None]
    rolled = Rollouts(
        RolloutWindows(np.array([0]), np.array([0]), 1),
        offset=offset,
        speed_offset=np.zeros_like(offset),
        collisions=np.zeros((1, 200), bool),
        start=FILTERED,
    )
    scores = forecast_scores(jax.random.key(0), rolled, 0.1, 0.1)
    assert scores["energy_score"] == pytest.approx(scores["crps_gap_m"], rel=1e-6)
    assert scores["crps_gap_m"] == pytest.approx(scores["crps_m"], rel=1e-6)
    assert scores["crps_speed_mps"] == 0.0 and scores["windows"] == 1
