"""The held-out protocol (bayesdrive.experiments.holdout) on a tiny case: every method's row and
paired interval, never a number reached on held-out data."""

from __future__ import annotations

import html
import math
import types
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest
import xarray as xr

from bayesdrive.data import registry
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.experiments.holdout import (
    BASELINES,
    FORECAST_METRICS,
    LEARNED,
    POOLED,
    PROTOCOL,
    TRAINING_DATA,
    HoldoutConfig,
    calibrate_data_set,
    evaluate_data_set,
    paired_difference,
    population_from,
)
from bayesdrive.inference.core.output import load_result
from bayesdrive.inference.fit import fit
from bayesdrive.reports.html import Section
from bayesdrive.reports.paper_report import calibration_section, holdout_section, holdout_table
from bayesdrive.simulation.blackbox import TrainConfig
from bayesdrive.simulation.calibration import (
    by_vehicle_difference,
    constant_velocity_offsets,
    pit_summary,
    point_scores,
)
from bayesdrive.simulation.follower_rollout import RolloutWindows
from bayesdrive.simulation.posterior import population_policy

MODEL = Path(__file__).resolve().parents[2] / "models" / "ngsim_i80_chains_idm_smc.nc"
# Two leader-follower pairs of 35 s: the smallest held-out case with leaders.
HELD_OUT = "ngsim_i80_pairs_raw_c"


def test_every_held_out_set_has_a_training_set_of_its_kind():
    assert set(TRAINING_DATA) == set(registry.HOLDOUT)
    assert set(TRAINING_DATA.values()) <= set(registry.DATASETS)


def test_paired_interval_brackets_the_mean_and_is_seeded():
    rng = np.random.default_rng(0)
    learned, other = rng.normal(size=12), rng.normal(size=12)
    first = paired_difference(learned, other, seed=5)
    assert first == paired_difference(learned, other, seed=5)
    assert first["mean"] == pytest.approx(np.mean(learned - other))
    assert first["low"] < first["mean"] < first["high"] and first["scenarios"] == 12
    # One scenario: no spread to resample, the interval is the difference itself.
    single = paired_difference([2.0], [0.5], seed=5)
    assert single["low"] == single["mean"] == single["high"] == 1.5


def test_population_policy_draws_each_driver_per_rollout_from_the_new_driver_draws():
    tree = load_result(MODEL)
    names = ["v_des", "tau"]
    rows = np.array([[20.0 + d, 1.0 + d / 10] for d in range(8)]).reshape(2, 4, 2)
    tree["sample_stats"] = xr.DataTree(
        xr.Dataset(
            {"population_new_driver": (("chain", "draw", "param"), rows)}, coords={"param": names}
        )
    )
    policy = population_policy("pop", IDM, tree, ["a", "b"])
    params = policy.params_for(jax.random.key(0), ("a", "b"), 40)
    drawn = np.stack([np.asarray(params.v_des), np.asarray(params.tau)], axis=-1)
    flat = rows.reshape(-1, 2)
    assert all(np.isclose(flat, pair).all(axis=1).any() for pair in drawn.reshape(-1, 2))
    # New drivers: the two vehicles and the rollouts draw apart, not one driver for all.
    assert len({tuple(pair) for pair in drawn.reshape(-1, 2)}) > 2
    assert not np.array_equal(drawn[:, 0], drawn[:, 1])
    # What the population does not describe stays at the fit's fixed values (here defaults).
    np.testing.assert_allclose(
        np.asarray(params.d_min), IDM.specs[IDM.param_names.index("d_min")].default
    )


@pytest.mark.extended
@pytest.mark.realdata
def test_protocol_on_two_vehicles_gives_every_row_and_paired_intervals(data_dir, holdout_dir):
    held_out = registry.load_holdout(HELD_OUT, holdout_dir=holdout_dir)
    pairs = list(pd.unique(held_out.scenes["scene_id"]))[:2]
    traj = held_out.subset(
        held_out.scenes.loc[held_out.scenes["scene_id"].isin(pairs), "vehicle_id"]
    )
    training = registry.load(TRAINING_DATA[HELD_OUT], data_dir=data_dir)
    # The smallest fits: their draws only feed the rows, their quality is not checked.
    per_vehicle = fit(
        jax.random.key(0),
        training,
        num_particles=32,
        vehicle_ids=training.vehicle_ids[1:3],
    )
    name = TRAINING_DATA[HELD_OUT]
    population = population_from({name: per_vehicle}, name, draws=16, seed=0)
    config = HoldoutConfig(
        particles=32,
        rollouts=2,
        max_scenarios=None,
        fit_seed=1,
        rollout_seed=2,
        baseline_seed=3,
        blackbox=TrainConfig(hidden=(8,), steps=20, batch_size=64),
    )
    final = get_model("idm+autocorrelated_noise")
    result = evaluate_data_set(HELD_OUT, traj, config, population, pooled=population, final=final)

    models = result["models"]
    assert set(models) == {*LEARNED, POOLED, *BASELINES}
    scenarios = result["scenario_set"]["scenarios"]
    assert scenarios >= 1 and result["acc"] is None
    for row in models.values():
        assert row["scenarios"] == scenarios
        assert math.isfinite(row["rmse_position_m"]["mean"])
        assert math.isfinite(row["rmse_speed_mps"]["mean"])
        assert row["collisions"]["total"] >= 0
    for learned in LEARNED:
        assert set(result["paired"][learned]) == set(models) - {learned}
        for metrics in result["paired"][learned].values():
            for paired in metrics.values():
                assert paired["scenarios"] == scenarios
                assert paired["low"] <= paired["mean"] <= paired["high"]
    table = holdout_table(result)
    assert list(table["method"]) == list(models)
    for learned in LEARNED:
        column = f"{learned} minus this, position (m) [95%]"
        assert (table.loc[table["method"] != learned, column] != "-").all()
        assert (table.loc[table["method"] == learned, column] == "-").all()
    section = Section("held out")
    holdout_section(
        section,
        {"protocol": PROTOCOL, "data_sets": {HELD_OUT: result, "none": {"error": "no leaders"}}},
    )
    page = "".join(section.parts)
    assert PROTOCOL in html.unescape(page) and "none: not evaluated: no leaders" in page
    assert "idm-smc minus this, position (m) [95%]" in page
    assert "idm-population minus this, position (m) [95%]" in page
    # The final model's forecast, from the filtered start, against the IDM and every baseline on
    # the same scenarios; its paired differences are the per-scenario means' differences.
    forecast = result["final_model"]
    label = f"{final.name}-smc"
    assert forecast["label"] == label and forecast["scenarios"] >= 1
    assert set(forecast["models"]) == {label, "idm-smc", *BASELINES}
    assert forecast["models"][label]["start"] == "filtered"
    assert set(forecast["paired"]) == set(forecast["models"]) - {label}
    for other, metrics in forecast["paired"].items():
        for metric in FORECAST_METRICS:
            ours = forecast["models"][label]["by_scenario"][metric]
            theirs = forecast["models"][other]["by_scenario"][metric]
            assert len(ours) == len(theirs) == forecast["scenarios"]
            assert metrics[metric]["mean"] == pytest.approx(np.mean(ours) - np.mean(theirs))
            assert metrics[metric]["low"] <= metrics[metric]["mean"] <= metrics[metric]["high"]
    assert "final minus this, CRPS [95%]" in page


def test_pit_summary_counts_coverage_exactly():
    """Evenly spread PITs: the central 50% and 90% intervals hold exactly those shares and the
    histogram is flat; PITs piled in the tails cover too little and fail the chi-square."""
    even = pit_summary((np.arange(1000) + 0.5) / 1000)
    assert even["coverage_50"] == 0.5 and even["coverage_90"] == 0.9
    assert even["pit_counts"] == [100] * 10 and even["pit_chi2_p"] == 1.0
    tails = pit_summary(np.r_[np.full(400, 0.01), np.full(400, 0.99), np.full(200, 0.5)])
    assert tails["coverage_90"] == 0.2 and tails["pit_chi2_p"] < 1e-6
    assert pit_summary(np.zeros(0))["coverage_50"] is None


def test_point_scores_split_the_rollout_rmse_and_score_a_point_forecast_by_its_error():
    """Hand-made offsets: the RMSE over rollouts is the predictive mean's error and the spread
    in quadrature; a row of equal rollouts (a point forecast) has CRPS = absolute error."""
    offsets = np.array([[1.0, 3.0, 2.0, 2.0], [-1.0, -1.0, -1.0, -1.0]])
    scores = point_scores(offsets)
    assert scores["rmse_mean_m"] == pytest.approx(np.sqrt((2.0**2 + 1.0) / 2))
    assert scores["spread_m"] == pytest.approx(np.sqrt((0.5 + 0.0) / 2))
    assert scores["rmse_rollouts_m"] ** 2 == pytest.approx(
        scores["rmse_mean_m"] ** 2 + scores["spread_m"] ** 2
    )
    # Row 1: E|X| = 2, E|X - X'| = (pairs 2,1,1,1,1,0 twice over 16) = 12/16; row 2: 1.
    assert scores["crps_m"] == pytest.approx(((2.0 - 0.5 * 12 / 16) + 1.0) / 2)
    assert scores["mae_median_m"] == pytest.approx((2.0 + 1.0) / 2)
    assert point_scores(np.zeros((0, 4)))["crps_m"] is None


def test_constant_velocity_offsets_are_zero_at_constant_speed_and_minus_half_a_t_squared():
    """Hand-made increments: at a constant 10 m/s constant velocity is exact; under a constant
    acceleration a it ends a T**2 / 2 behind after T seconds."""
    dt, horizon, a = 0.1, 50, 0.8
    t = np.arange(200) * dt
    v = 10.0 + a * t
    dx = 10.0 * dt + a * (t + dt / 2) * dt
    windows = RolloutWindows(np.array([0, 1]), np.array([0, 60]), horizon)
    series = types.SimpleNamespace(
        dt=dt, v=np.stack([np.full(200, 10.0), v]), dx=np.stack([np.full(200, 10.0 * dt), dx])
    )
    offsets = constant_velocity_offsets(series, windows)
    assert offsets == pytest.approx([0.0, -a * (horizon * dt) ** 2 / 2])


def test_by_vehicle_difference_weighs_drivers_not_windows():
    """Vehicle 0 has three windows of +1, vehicle 1 one of -1: the mean is 0 (vehicles), not
    0.5 (windows), and the t interval across the two vehicles brackets it."""
    out = by_vehicle_difference(np.array([1.0, 1.0, 1.0, -1.0]), np.array([0, 0, 0, 1]))
    assert out["vehicles"] == 2 and out["mean"] == 0.0
    assert out["low"] < 0.0 < out["high"]
    assert by_vehicle_difference(np.array([2.0]), np.array([3]))["low"] is None


@pytest.mark.realdata
def test_calibration_on_two_vehicles_gives_coverage_per_model_and_horizon(holdout_dir, tmp_path):
    held_out = registry.load_holdout(HELD_OUT, holdout_dir=holdout_dir)
    pairs = list(pd.unique(held_out.scenes["scene_id"]))[:2]
    traj = held_out.subset(
        held_out.scenes.loc[held_out.scenes["scene_id"].isin(pairs), "vehicle_id"]
    )
    config = HoldoutConfig(
        particles=32, rollouts=20, max_scenarios=None, fit_seed=1, rollout_seed=2, baseline_seed=3
    )
    delayed = get_model("idm+reaction_delay")
    result = calibrate_data_set(traj, config, (IDM, delayed))
    assert result["lead_times_s"] == [1.0, 2.0, 3.0, 5.0]
    for model in (IDM, delayed):
        entry = result["models"][model.name]
        assert entry["vehicles"] >= 1 and entry["rollouts"] == 20 and entry["windows"] >= 1
        for start in ("filtered", "stationary"):
            for h in entry["starts"][start]["horizons"].values():
                assert sum(h["pit_counts"]) == h["windows"] == entry["windows"]
                assert 0.0 <= h["coverage_50"] <= h["coverage_90"] <= 1.0
                assert h["rmse_rollouts_m"] ** 2 == pytest.approx(
                    h["rmse_mean_m"] ** 2 + h["spread_m"] ** 2
                )
                # With the leader replayed the gap's error is the position's, negated.
                assert h["crps_gap_m"] == pytest.approx(h["crps_m"])
                assert h["constant_velocity_rmse_m"] > 0.0 and h["energy_score"] > 0.0
                paired = h["minus_constant_velocity"]["crps_minus_abs_error_m"]
                assert paired["vehicles"] == entry["vehicles"] and np.isfinite(paired["mean"])
    # The plain IDM has no state beyond position and speed: both starts are the same forecast.
    idm = result["models"][IDM.name]["starts"]
    assert idm["filtered"] == idm["stationary"]
    section = Section("calibration")
    calibration = {"data_sets": {HELD_OUT: {**result, "training_data": "t"}}}
    calibration_section(section, calibration, tmp_path)
    assert (tmp_path / "holdout_pit.png").exists()
    assert "90% interval covers" in "".join(section.parts)
