"""New drivers and new roads: the held-out data sets (``registry.HOLDOUT``) under one protocol.

The protocol was fixed before any held-out number was seen, and nothing in it is chosen on the
held-out data (``shared/holdout/README.md``): fitting held-out vehicles on their fitting windows
with the documented defaults and scoring them on their later held-out windows is evaluation.

1. **Scenarios**: 5 s scenarios of one simulated follower behind its replayed leader in the
   held-out windows (:func:`~bayesdrive.simulation.scenarios.platoon_scenarios`), the first
   ``max_scenarios`` in the selection rule's order; a data set without leaders (no such scenario)
   is reported with the reason.
2. **Per-vehicle model** (``idm-smc``, the model the comparison is about): the IDM's six
   parameters fitted by ``smc`` with its defaults (``particles`` per vehicle) to each simulated
   follower's own *fitting* window; each rollout draws one of that follower's posterior draws. A
   follower whose fitting window has no usable step has no fit, and its scenarios are dropped for
   every method (counted in ``scenarios_dropped_without_fit``).
3. **Population predictive** (``idm-population``): the hierarchical population model of the
   training data set of the same kind (:data:`TRAINING_DATA`: NGSIM I-80 chains for NGSIM sets,
   OpenACC Vicolungo for OpenACC and ACC sets), estimated in two stages
   (:func:`~bayesdrive.inference.population.two_stage.two_stage`) from the highway experiment's
   per-vehicle smc posteriors of that set's fitting windows (validated against the joint fit in
   ``tests/inference/test_population.py``); every follower is treated as a driver with no data of its own:
   each rollout draws its parameters from the population distribution of a new driver.
4. **Pooled posterior** (``idm-smc-pooled-ngsim``, when given): the earlier generalisation row,
   every follower drawing from the pooled per-vehicle smc draws of the NGSIM I-80 chains,
   whatever the data set.
5. **Baselines** (:func:`~bayesdrive.simulation.baselines.baseline_policy`, as the highway
   experiment builds them): ``idm-default``, ``idm-lm`` (the IDM fitted by Levenberg-Marquardt
   per follower on its fitting window), ``cv`` and ``blackbox`` (trained on the fitting windows
   of every vehicle of the held-out data set).
6. **Calibration** (:func:`calibrate_data_set`, a step of its own): the IDM and the final model
   that ``criticize`` chose on the training data set of the same kind (never chosen on held-out
   data), each fitted by ``smc`` (defaults) to the same simulated followers' fitting windows;
   their forecasts 1, 2, 3 and 5 s ahead over every held-out window of those followers, from the
   ``filtered`` start with ``stationary`` beside it: CRPS of gap, position and speed, the energy
   score of the (gap, speed) path, the predictive mean's RMSE, the coverage of the 50% and 90%
   central predictive intervals and the PIT histogram of the position
   (:func:`~bayesdrive.simulation.calibration.predictive_calibration`).
7. **Metrics** (:func:`~bayesdrive.simulation.metrics.evaluate_policy`, one rollout key for every
   method, so methods differ by their parameters only): RMSE of position and speed at each
   scenario's last step and collisions. **Paired intervals**: per scenario, the RMSE of the
   learned model minus that of the other method (negative: the learned model is closer), their
   mean and a 95% percentile bootstrap interval over scenarios (:data:`BOOTSTRAP_DRAWS`
   resamples, seeded), for the per-vehicle and the population-predictive model against every
   other method.
8. **The final model's forecast** (with ``final``: the model ``criticize`` chose on the training
   data set of the same kind, when it is not the IDM): fitted like the IDM, it forecasts the
   scenarios whose follower has the observed history the ``filtered`` start reads
   (:func:`~bayesdrive.simulation.scenarios.with_history`), from that start, beside the per-vehicle
   IDM and the baselines on the same scenarios (each from its own forecast start). Paired, per
   scenario at the horizon: the CRPS of the position and the squared error of the predictive
   mean's position (:data:`FORECAST_METRICS`), final model minus each method, with the bootstrap
   interval of point 7.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import xarray as xr

from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import scored_series
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.closed_loop import forecast_start
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.core.output import load_result, metadata, save_result
from bayesdrive.inference.fit import fit
from bayesdrive.inference.population.two_stage import two_stage
from bayesdrive.simulation.baselines import Policy, baseline_policy
from bayesdrive.simulation.blackbox import TrainConfig
from bayesdrive.simulation.calibration import LEAD_TIMES_S, predictive_calibration
from bayesdrive.simulation.metrics import evaluate_policy
from bayesdrive.simulation.posterior import pooled_policy, population_policy, posterior_policy
from bayesdrive.simulation.scenarios import ScenarioSet, platoon_scenarios, with_history

__all__ = [
    "ACC_NOTES",
    "BASELINES",
    "BOOTSTRAP_DRAWS",
    "FORECAST_METRICS",
    "HORIZON_S",
    "LEARNED",
    "PROTOCOL",
    "TRAINING_DATA",
    "HoldoutConfig",
    "calibrate_data_set",
    "evaluate_data_set",
    "fit_followers",
    "holdout_scenarios",
    "paired_difference",
    "population_from",
]

HORIZON_S = 5.0
PER_VEHICLE = "idm-smc"
POPULATION = "idm-population"
POOLED = "idm-smc-pooled-ngsim"
LEARNED = (PER_VEHICLE, POPULATION)
BASELINES = ("idm-default", "idm-lm", "cv", "blackbox")
BOOTSTRAP_DRAWS = 2000
METRICS = ("rmse_position_m", "rmse_speed_mps")
FORECAST_METRICS = ("crps_position_m", "predictive_mean_sq_error_m2")
"""What the final model's forecast comparison pairs per scenario (module docstring, point 8)."""

TRAINING_DATA = {
    "acc_platoon_fhwa": "openacc_vicolungo",
    "ngsim_i80_pairs_a": "ngsim_i80_chains",
    "ngsim_i80_pairs_b": "ngsim_i80_chains",
    "ngsim_i80_pairs_raw_c": "ngsim_i80_chains",
    "ngsim_us101_vehicles": "ngsim_i80_chains",
    "openacc_casale": "openacc_vicolungo",
    "openacc_zalazone": "openacc_vicolungo",
}
"""The training data set whose population predicts each held-out data set's drivers."""

# What each folder's PROVENANCE.txt and the JRC notes beside it say about who drives.
ACC_NOTES = {
    "acc_platoon_fhwa": "every follower drives on adaptive cruise control (an ACC platoon)",
    "openacc_casale": "the follower drives on adaptive cruise control (OpenACC Casale notes), "
    "apart from the moments its driver braked by hand",
    "openacc_zalazone": "followers drive on adaptive cruise control, except in the all-human "
    "no_ACC recordings (OpenACC ZalaZone notes)",
}
# Recordings driven by hand inside a mostly-ACC data set, by the folder their scenario ids start
# with, so the note can count the scenarios that are not ACC.
HUMAN_SCENES = {"openacc_zalazone": "no_ACC/"}

PROTOCOL = (
    "Every held-out data set with leaders: 5 s scenarios of one follower behind its replayed "
    "leader in the held-out windows. idm-smc: the IDM fitted by smc (defaults) to each follower's "
    "own fitting window, one posterior draw per rollout. idm-population: the hierarchical "
    "population (two-stage, from the highway experiment's per-vehicle fits) of the training "
    "data set of the same kind (NGSIM I-80 chains for NGSIM "
    "sets, OpenACC Vicolungo for OpenACC and ACC sets), each follower a new driver drawn from it "
    "per rollout. idm-smc-pooled-ngsim: the earlier row, the pooled per-vehicle NGSIM I-80 "
    "posterior for every follower. Baselines as in the highway experiment: idm-default, idm-lm "
    "(LM fit per follower on its fitting window), cv, blackbox (trained on the set's fitting "
    "windows). Paired differences: per scenario, learned minus other method's RMSE at the "
    f"horizon, mean and 95% percentile bootstrap interval over scenarios ({BOOTSTRAP_DRAWS} "
    "resamples). Nothing was chosen or tuned on these data."
)


class HoldoutConfig(NamedTuple):
    """Sizes and seeds of one run: smc particles per vehicle, rollouts per scenario, at most
    ``max_scenarios`` scenarios per data set (None: all), the fits' seed, the rollouts' seed
    (also the bootstrap's), the seed of what baselines train, the black box's training."""

    particles: int
    rollouts: int
    max_scenarios: int | None
    fit_seed: int
    rollout_seed: int
    baseline_seed: int
    blackbox: TrainConfig = TrainConfig()


def holdout_scenarios(traj: Trajectories, max_scenarios: int | None) -> ScenarioSet:
    """The protocol's scenarios of a held-out data set (module docstring, point 1)."""
    found = platoon_scenarios(traj, vehicles_per_scenario=1, horizon_s=HORIZON_S)
    return found.first(max_scenarios)


def population_from(trees: Mapping[str, xr.DataTree], name: str, *, draws: int, seed: int):
    """The driver population of training data set ``name``: the two-stage hierarchical estimator
    on the per-vehicle posteriors ``trees`` (the highway experiment's smc fits, by label) of every
    label ``name`` or ``name:part`` together."""
    parts = [tree for label, tree in trees.items() if label.split(":")[0] == name]
    if not parts:
        raise ValueError(f"no per-vehicle fit of {name} among {sorted(trees)}")
    combined = xr.DataTree.from_dict(
        {"posterior": xr.concat([tree["posterior"].to_dataset() for tree in parts], "vehicle")}
    )
    combined.attrs = parts[0].attrs
    return two_stage(jax.random.key(seed), combined, num_particles=draws)


def paired_difference(
    learned: list[float], other: list[float], seed: int, draws: int = BOOTSTRAP_DRAWS
) -> dict[str, float | int]:
    """Mean of the per-scenario differences ``learned - other`` and its 95% percentile bootstrap
    interval over scenarios (``draws`` resamples of the scenarios with replacement)."""
    difference = np.asarray(learned, np.float64) - np.asarray(other, np.float64)
    rng = np.random.default_rng(seed)
    resampled = rng.choice(difference, size=(draws, len(difference))).mean(axis=1)
    low, high = np.quantile(resampled, [0.025, 0.975])
    return {
        "mean": float(difference.mean()),
        "low": float(low),
        "high": float(high),
        "scenarios": len(difference),
    }


def _paired_against(
    rows: Mapping[str, Any], learned: str, metrics: tuple[str, ...], seed: int
) -> dict[str, dict[str, Any]]:
    """:func:`paired_difference` of method ``learned`` minus every other method of ``rows`` (each
    with its per-scenario ``by_scenario`` values), for each of ``metrics``."""
    return {
        other: {
            metric: paired_difference(
                rows[learned]["by_scenario"][metric], rows[other]["by_scenario"][metric], seed
            )
            for metric in metrics
        }
        for other in rows
        if other != learned
    }


def _acc_note(name: str, scenarios: ScenarioSet) -> str | None:
    note = ACC_NOTES.get(name)
    human = HUMAN_SCENES.get(name)
    if note is None or human is None:
        return note
    count = sum(s.scenario_id.startswith(human) for s in scenarios.scenarios)
    return f"{note}: {count} of {len(scenarios.scenarios)} scenario(s) are all-human"


def _row(policy: Policy, result: dict[str, Any]) -> dict[str, Any]:
    return {
        "policy": policy.description,
        "scenarios": result["scenarios"],
        "rmse_position_m": result["rmse_position_m"],
        "rmse_speed_mps": result["rmse_speed_mps"],
        "collisions": result["collisions"],
        "by_scenario": {metric: [s[metric] for s in result["by_scenario"]] for metric in METRICS},
    }


def fit_followers(
    traj: Trajectories,
    config: HoldoutConfig,
    model: DriverModel,
    scenarios: ScenarioSet,
    path: Path | None = None,
) -> xr.DataTree:
    """smc fits (defaults, the protocol's seed) of ``model`` to the fitting windows of the
    simulated followers of ``scenarios``. With ``path``, a fit saved there is read instead, else
    the new fit is saved there: the evaluation's per-vehicle IDM fit then serves the calibration,
    which fits the same followers the same way (the caller removes a stale file)."""
    if path is not None and path.exists():
        return load_result(path)
    tree = fit(
        jax.random.key(config.fit_seed),
        traj,
        model=model,
        engine="smc",
        num_particles=config.particles,
        seed=config.fit_seed,
        vehicle_ids=scenarios.simulated_ids,
    )
    if path is not None:
        save_result(tree, path)
    return tree


def evaluate_data_set(
    name: str,
    traj: Trajectories,
    config: HoldoutConfig,
    population: xr.DataTree,
    pooled: xr.DataTree | None = None,
    fit_path: Path | None = None,
    final: DriverModel | None = None,
    final_fit_path: Path | None = None,
) -> dict[str, Any]:
    """The protocol (module docstring) on one held-out data set ``name`` read as ``traj``, with
    ``population`` the population of its training data set (:func:`population_from`) and
    ``pooled`` the NGSIM I-80 per-vehicle smc fit for the earlier pooled row (None: no such row);
    the per-vehicle fit is kept in ``fit_path`` (:func:`fit_followers`), ``final``'s in
    ``final_fit_path``.

    Returns ``{"error": reason}`` when the data hold no scenario, else the scenario set, the
    per-method rows (``models``), the paired differences (``paired[learned][other]`` for each
    metric), the ACC note (None for human drivers) and, with ``final``, its forecast comparison
    (``final_model``, point 8).
    """
    found = holdout_scenarios(traj, config.max_scenarios)
    if not found.scenarios:
        return {"error": f"no {HORIZON_S:g} s leader-follower window in its held-out part"}
    per_vehicle = fit_followers(traj, config, IDM, found, fit_path)
    scenarios = found.within({str(v) for v in per_vehicle["posterior"]["vehicle"].values})
    if not scenarios.scenarios:
        return {"error": "no simulated follower has a usable step in its fitting window"}
    ids = scenarios.simulated_ids
    policies = {
        PER_VEHICLE: posterior_policy(PER_VEHICLE, IDM, per_vehicle, metadata(per_vehicle)),
        POPULATION: population_policy(POPULATION, IDM, population, ids),
    }
    if pooled is not None:
        policies[POOLED] = pooled_policy(POOLED, IDM, pooled, metadata(pooled), ids)
    for baseline in BASELINES:
        policies[baseline] = baseline_policy(
            baseline,
            jax.random.key(config.baseline_seed),
            traj,
            ids,
            blackbox_config=config.blackbox,
        )
    models = {
        label: _row(
            policy,
            evaluate_policy(
                jax.random.key(config.rollout_seed),
                policy,
                scenarios,
                num_rollouts=config.rollouts,
            ),
        )
        for label, policy in policies.items()
    }
    paired = {
        learned: _paired_against(models, learned, METRICS, config.rollout_seed)
        for learned in LEARNED
    }
    forecast = None
    if final is not None:
        final_tree = fit_followers(traj, config, final, scenarios, final_fit_path)
        label = f"{final.name}-smc"
        compared = {
            label: posterior_policy(label, final, final_tree, metadata(final_tree)),
            PER_VEHICLE: policies[PER_VEHICLE],
            **{baseline: policies[baseline] for baseline in BASELINES},
        }
        fitted = {str(v) for v in final_tree["posterior"]["vehicle"].values}
        forecast = _forecast_comparison(traj, config, label, compared, scenarios.within(fitted))
    return {
        "scenario_set": scenarios.summary(),
        "scenarios_dropped_without_fit": len(found.scenarios) - len(scenarios.scenarios),
        "training_data": metadata(population)["data_source"],
        "population_vehicles": int(population["posterior"].sizes["vehicle"]),
        # Reported beside the rows, never acted on: divergences or few effective draws per
        # vehicle in the two-stage weights weaken the population's row.
        "population_divergences": int(population["sample_stats"]["diverging"].sum()),
        "population_min_importance_ess": float(population["sample_stats"]["importance_ess"].min()),
        "acc": _acc_note(name, scenarios),
        "models": models,
        "paired": paired,
        **({} if forecast is None else {"final_model": forecast}),
    }


def _forecast_comparison(
    traj: Trajectories,
    config: HoldoutConfig,
    final: str,
    policies: Mapping[str, Policy],
    scenarios: ScenarioSet,
) -> dict[str, Any]:
    """Point 8 of the protocol: ``policies`` (the final model's labelled ``final``) on the
    ``scenarios`` with the observed history, each from its forecast start, and the paired
    differences of :data:`FORECAST_METRICS`, final model minus each other method."""
    forecast_set, without_history = with_history(scenarios, traj)
    if not forecast_set.scenarios:
        return {"error": "no scenario's follower has the observed history the filtered start reads"}
    rows = {}
    for label, policy in policies.items():
        start = forecast_start(policy.model)
        result = evaluate_policy(
            jax.random.key(config.rollout_seed),
            policy,
            forecast_set,
            num_rollouts=config.rollouts,
            start=start,
        )
        rows[label] = {
            "policy": policy.description,
            "start": start,
            "scenarios": result["scenarios"],
            "crps_position_m": result["crps_position_m"],
            "predictive_mean_rmse_position_m": result["predictive_mean_rmse_position_m"],
            "rmse_position_m": result["rmse_position_m"]["mean"],
            "collisions": result["collisions"]["total"],
            "by_scenario": {
                metric: [s[metric] for s in result["by_scenario"]] for metric in FORECAST_METRICS
            },
        }
    return {
        "label": final,
        "scenarios": len(forecast_set.scenarios),
        "left_out_without_history": without_history,
        "models": rows,
        "paired": _paired_against(rows, final, FORECAST_METRICS, config.rollout_seed),
    }


def calibrate_data_set(
    traj: Trajectories,
    config: HoldoutConfig,
    models: tuple[DriverModel, ...],
    fit_paths: Mapping[str, Path] | None = None,
) -> dict[str, Any]:
    """Point 6 of the protocol on one held-out data set read as ``traj``: for each of ``models``
    (the IDM and the training set's final model), smc fits of the protocol's simulated followers
    on their fitting windows (kept in ``fit_paths[model.name]`` where given, see
    :func:`fit_followers`) and the forecast scores of their predictive on the held-out windows
    (:data:`~bayesdrive.simulation.calibration.LEAD_TIMES_S`). Returns ``{"error": reason}`` without such followers."""
    found = holdout_scenarios(traj, config.max_scenarios)
    if not found.scenarios:
        return {"error": f"no {HORIZON_S:g} s leader-follower window in its held-out part"}
    series = scored_series(traj, vehicle_ids=found.simulated_ids)
    results = {}
    for model in models:
        tree = fit_followers(traj, config, model, found, (fit_paths or {}).get(model.name))
        results[model.name] = predictive_calibration(
            jax.random.key(config.rollout_seed),
            model,
            tree,
            series,
            num_rollouts=config.rollouts,
        )
    return {"lead_times_s": list(LEAD_TIMES_S), "models": results}
