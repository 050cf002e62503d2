"""The paper's experiments on the real data, each a step that saves its results into an output
folder and is skipped on a re-run when its results are already there.

Every choice below was fixed before any result was seen, and none was made on held-out data:

* **Seeds** (:data:`SEEDS`): one per step, fixed constants; every result records its seed.
* **Scenario size**: the paper used 15 scenarios of 20 vehicles over 5 s. Our data does not hold
  20-vehicle platoons in held-out windows, so each data set uses the largest platoon size that
  still gives at least 15 scenarios (``scenario_capacity``): 5 simulated vehicles for the NGSIM
  chains and 4 (a whole platoon behind its leader) for OpenACC.
* **Drivers**: OpenACC's main comparison uses the two all-human recordings; the recording whose
  followers drive on adaptive cruise control is evaluated apart, as a contrast.
* **Fits** see only each simulated vehicle's fitting window (the split rule of
  :mod:`bayesdrive.data.views`); every score is on the later held-out window.
* **Held-out data sets** follow one protocol (:mod:`bayesdrive.experiments.holdout`): each
  follower fitted on its own fitting window with the fixed defaults, new drivers predicted from
  the population fitted on the training data set of the same kind, nothing chosen on them.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd

from bayesdrive.data import registry
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories, summary
from bayesdrive.data.views import FollowerArrays, pooled_series
from bayesdrive.drivers.base import DriverModel, PriorBox
from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.closed_loop import STATIONARY, forecast_start
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.experiments.holdout import (
    PROTOCOL,
    TRAINING_DATA,
    HoldoutConfig,
    calibrate_data_set,
    evaluate_data_set,
    population_from,
)
from bayesdrive.inference.core.output import load_result, metadata, save_result
from bayesdrive.inference.core.vehicles import clear_compiled
from bayesdrive.inference.fit import first_vehicles, fit
from bayesdrive.inference.fit import summary as fit_summary
from bayesdrive.reports.model_card import model_card
from bayesdrive.reports.paper_report import criticism_folder
from bayesdrive.simulation.baselines import baseline_policy
from bayesdrive.simulation.generate import (
    draw_pooled,
    draw_preset,
    generate_scenes,
    load_preset,
    median_sweep,
)
from bayesdrive.simulation.metrics import evaluate_policy, observed_data
from bayesdrive.simulation.posterior import (
    fixed_params,
    particles_by_vehicle,
    pooled_policy,
    posterior_policy,
)
from bayesdrive.simulation.rollout import rollout, scene_arrays
from bayesdrive.simulation.scenarios import (
    MERGE_FIT_STAY_S,
    ScenarioSet,
    merge_follower_arrays,
    merge_scenarios,
    platoon_scenarios,
    with_history,
)
from bayesdrive.simulation.two_sample import (
    LEVEL_FEATURES,
    boosted_two_sample_test,
    classifier_two_sample_test,
    segment_features,
    trajectory_features,
)

__all__ = ["FULL", "OPTIONAL_STEPS", "QUICK", "SEEDS", "Settings", "main_steps", "run_all"]

log = logging.getLogger(__name__)

SEEDS = {
    "fit_smc": 11,
    "fit_pf": 12,
    "fit_merge": 13,
    "evaluate": 21,
    "baselines": 22,
    "turing": 31,
    "scenes": 41,
    "holdout": 51,
    "holdout_fit": 52,
    "prior_sensitivity": 61,
    "criticism": 71,
}
PRESET_DIR = Path(__file__).resolve().parents[2] / "models" / "presets"
HIGHWAY_SIZES = {"ngsim_i80_chains": 5, "openacc_vicolungo": 4}
ACC_RECORDING = "JRC-VC_260219_part3"
LEARNED = ("idm-smc", "idm-pf")
BASELINE_MODELS = ("idm-default", "idm-nls", "idm-lm", "cv", "ca", "blackbox")
MERGE_DATA = "ngsim_merge_episodes"
MERGE_MODELS = ("cidm-c1", "idm-nomerge", "cv")
CLIP_PAIRS = 3
# Folds of the boosted Turing classifier, grouped by vehicle.
TURING_FOLDS = 5
# Key of the criticism's final model among a highway step's fits (beside "smc" and "pf").
FINAL = "final"
# The steps a run may leave out, by name, with what each runs. No other step reads their results,
# so a run without them computes the others bit for bit as a run with them.
OPTIONAL_STEPS = {
    "turing": "the automated Turing test",
    "holdout": "generalisation to and calibration on the held-out data sets",
}


@dataclass(frozen=True, kw_only=True)
class Settings:
    """Sizes of one run; ``quick`` keeps every step but shrinks it to run in minutes."""

    # The defaults are the full run's sizes.
    name: str = "full"
    smc_particles: int = 1024
    pf_particles: int = 1024
    pf_epochs: int = 3
    rollouts: int = 100
    max_scenarios: int | None = None
    generated_scenes: int = 20
    holdout_max_scenarios: int | None = 30
    prior_sensitivity_vehicles: int = 10
    # The criticism reads this many scenes of each data set (None: all), from its first scene or
    # from the one ``criticism_first_scene`` names. NGSIM I-80's first 8 scenes were the pilot
    # run whose forecast gain sized this one (models/README.md): the run reads the next 32.
    criticism_scenes: int | None = 32
    criticism_first_scene: tuple[tuple[str, int], ...] = (("ngsim_i80_chains", 8),)
    criticism_particles: int = 128
    criticism_rollouts: int = 32
    criticism_seconds: float = 120.0
    # Held-out data sets evaluated (None: every one of registry.HOLDOUT).
    holdout_sets: tuple[str, ...] | None = None
    # Rounds of the criticism's loop (each extends the model by the round before's verdict).
    criticism_rounds: int = 3
    # Highway labels the criticism runs on (None: every one but the acc-contrast recordings).
    criticised: tuple[str, ...] | None = None
    # Label permutations of the boosted Turing classifier's test (each refits it on every fold).
    turing_permutations: int = 99
    # Which of OPTIONAL_STEPS run (every other step always runs).
    optional_steps: tuple[str, ...] = tuple(OPTIONAL_STEPS)


FULL = Settings()
# The quick run criticises NGSIM I-80 alone and evaluates one held-out set, the first NGSIM one:
# every step runs, but the long series (OpenACC recordings, the ACC platoon's 1400 s fitting
# windows) are left to the full run, which takes every one.
QUICK = Settings(
    name="quick",
    smc_particles=128,
    pf_particles=128,
    pf_epochs=1,
    rollouts=6,
    max_scenarios=2,
    generated_scenes=2,
    holdout_max_scenarios=1,
    prior_sensitivity_vehicles=2,
    criticism_scenes=1,
    criticism_first_scene=(),
    criticism_particles=64,
    criticism_rollouts=4,
    criticism_seconds=25.0,
    holdout_sets=("ngsim_i80_pairs_a",),
    criticism_rounds=1,
    criticised=("ngsim_i80_chains",),
    turing_permutations=19,
)


def main_steps(settings: Settings) -> Settings:
    """``settings`` without the optional steps: the README's main job, sized to run in 20 minutes
    on 2 cores (``reproduce --full`` adds them)."""
    return replace(settings, optional_steps=())


def holdout_names(settings: Settings) -> list[str]:
    """The held-out data sets a run evaluates, in :data:`registry.HOLDOUT`'s order."""
    chosen = settings.holdout_sets
    return [name for name in registry.HOLDOUT if chosen is None or name in chosen]


def _save_json(path: Path, payload: Any) -> None:
    write_text_atomic(path, json.dumps(payload, indent=2, default=_plain) + "\n")


def _plain(value):
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(type(value).__name__)


def cached(out: Path, name: str, compute: Callable[[], dict], force: bool) -> dict:
    """Load ``out/name.json`` if present (a finished step), else compute and save it."""
    path = out / f"{name}.json"
    if path.exists() and not force:
        log.info("reusing %s", path)
        return json.loads(path.read_text())
    result = compute()
    _save_json(path, result)
    return result


def highway_folder(out: Path, label: str) -> Path:
    """Where the highway experiment on ``label`` keeps its fits and evaluation."""
    return out / "highway" / label.replace(":", "_")


def fit_paths(experiment: dict, folder: Path) -> dict[str, Path]:
    """The saved fits of a step, which records them by name inside its folder (so a results
    folder may move, or be staged elsewhere and renamed into place)."""
    return {name: folder / Path(recorded).name for name, recorded in experiment["fits"].items()}


def highway_data(name: str) -> dict[str, Trajectories]:
    """The highway data sets as evaluated: OpenACC split into human and ACC recordings."""
    traj = registry.load(name)
    if name != "openacc_vicolungo":
        return {name: traj}
    scenes = traj.scenes
    acc = scenes.loc[scenes["scene_id"] == ACC_RECORDING, "vehicle_id"]
    human = scenes.loc[scenes["scene_id"] != ACC_RECORDING, "vehicle_id"]
    return {f"{name}:human": traj.subset(human), f"{name}:acc-contrast": traj.subset(acc)}


def _highway_scenarios(label: str, traj: Trajectories, settings: Settings) -> ScenarioSet:
    """The platoon scenarios of a highway data set at its fixed size (module docstring)."""
    size = HIGHWAY_SIZES[label.split(":")[0]]
    found = platoon_scenarios(traj, vehicles_per_scenario=size, horizon_s=5.0)
    return found.first(settings.max_scenarios)


def _covered(scenarios: ScenarioSet, trees: dict[str, Any]) -> ScenarioSet:
    """Scenarios whose simulated vehicles all have a posterior in every tree (a vehicle whose
    fitting window has no usable step has none); every model is scored on this same set."""
    return scenarios.within(
        set.intersection(
            *({str(v) for v in t["posterior"]["vehicle"].values} for t in trees.values())
        )
    )


def fit_step(
    out: Path,
    traj: Trajectories,
    vehicle_ids: list[str],
    engine: str,
    settings: Settings,
    force: bool,
    model: DriverModel = IDM,
) -> Path:
    """Fit every parameter of ``model`` (the IDM's six by default) per vehicle on its fitting
    window; save ``<engine>.nc`` (``<model>-<engine>.nc`` for another model)."""
    path = out / (f"{engine}.nc" if model is IDM else f"{model.name}-{engine}.nc")
    if path.exists() and not force:
        return path
    seed = SEEDS[f"fit_{engine}"]
    options = {"epochs": settings.pf_epochs} if engine == "pf" else {}
    particles = settings.smc_particles if engine == "smc" else settings.pf_particles
    tree = fit(
        jax.random.key(seed),
        traj,
        model=model,
        engine=engine,
        num_particles=particles,
        seed=seed,
        vehicle_ids=vehicle_ids,
        **options,
    )
    save_result(tree, path)
    _save_json(out / f"{path.stem}_summary.json", fit_summary(tree))
    return path


def highway_step(
    out: Path,
    label: str,
    traj: Trajectories,
    settings: Settings,
    force: bool,
    final_model: str | None = None,
) -> dict:
    """Fit, then score learned models and baselines on the held-out platoon scenarios; with
    ``final_model`` (the criticism's final model, when it is not the IDM) that model too, fitted
    by smc like the IDM."""
    out.mkdir(parents=True, exist_ok=True)
    scenarios = _highway_scenarios(label, traj, settings)
    vehicle_ids = scenarios.simulated_ids
    results_nc = {e: fit_step(out, traj, vehicle_ids, e, settings, force) for e in ("smc", "pf")}
    if final_model is not None and final_model != IDM.name:
        results_nc[FINAL] = fit_step(
            out, traj, vehicle_ids, "smc", settings, force, model=get_model(final_model)
        )
    trees = {e: load_result(p) for e, p in results_nc.items()}
    covered = _covered(scenarios, trees)
    # Forecasts start from the state filtered from each scenario's observed history.
    scored, without_history = with_history(covered, traj)

    def evaluate(name: str, policy, start: str) -> dict:
        started = time.perf_counter()
        result = evaluate_policy(
            jax.random.key(SEEDS["evaluate"]),
            policy,
            scored,
            num_rollouts=settings.rollouts,
            start=start,
        )
        return {
            "model": name,
            "policy": policy.description,
            "start": start,
            "seconds": time.perf_counter() - started,
            **result,
        }

    rows = {}
    for tree in trees.values():
        name, policy = _learned_policy(tree)
        rows[name] = evaluate(name, policy, forecast_start(policy.model))
        # The same rollouts without the observed history, beside the forecast.
        rows[f"{name} ({STATIONARY})"] = evaluate(name, policy, STATIONARY)
    for name in BASELINE_MODELS:
        policy = baseline_policy(
            name, jax.random.key(SEEDS["baselines"]), traj, scored.simulated_ids
        )
        rows[name] = evaluate(name, policy, forecast_start(policy.model))
    return {
        "label": label,
        "scenario_set": scored.summary(),
        "scenarios_dropped_without_posterior": len(scenarios.scenarios) - len(covered.scenarios),
        "scenarios_dropped_without_history": without_history,
        "fits": {e: p.name for e, p in results_nc.items()},
        "models": rows,
        "seed": SEEDS["evaluate"],
        "rollouts": settings.rollouts,
    }


def _learned_policy(tree) -> tuple[str, Any]:
    """A fitted result as a simulation policy named ``<model>-<engine>`` (each vehicle draws from
    its own posterior)."""
    meta = metadata(tree)
    name = f"{meta['model']}-{meta['engine']}"
    return name, posterior_policy(name, get_model(meta["model"]), tree, meta)


def _merge_fit(
    out: Path, arrays: FollowerArrays, model, engine: str, settings: Settings, force: bool
) -> Path:
    """Fit ``model`` to the pooled V2 stays of the fitting episodes; saved (and reused) as
    ``<model>_<engine>.nc``."""
    path = out / f"{model.name}_{engine}.nc"
    if force or not path.exists():
        seed = SEEDS["fit_merge"]
        tree = fit(
            jax.random.key(seed),
            arrays,
            model=model,
            engine=engine,
            num_particles=settings.smc_particles,
            seed=seed,
            source=MERGE_DATA,
        )
        save_result(tree, path)
    return path


def merge_step(out: Path, settings: Settings, force: bool) -> dict:
    """The merging experiment: C-IDM (c included) and LM-fitted IDM learned per cooperating-car
    stay on the fitting episodes and pooled (held-out episodes hold other drivers), against
    baselines that need no fit, on the held-out merge episodes."""
    out.mkdir(parents=True, exist_ok=True)
    traj = registry.load(MERGE_DATA)
    scenarios = merge_scenarios(traj, horizon_s=5.0).first(
        settings.max_scenarios and 4 * settings.max_scenarios
    )
    # The stays are short (median 3 s): each alone leaves the parameters near their prior, so
    # all of them share one parameter set (complete pooling).
    stays = merge_follower_arrays(merge_scenarios(traj, horizon_s=MERGE_FIT_STAY_S, episodes="fit"))
    if settings.max_scenarios is not None:
        stays = first_vehicles(stays, 4 * settings.max_scenarios)
    fitting = pooled_series(stays, "fitting-episode cooperating cars")
    fits = {
        "cidm-smc": (CIDM, _merge_fit(out, fitting, CIDM, "smc", settings, force)),
        "idm-lm": (IDM, _merge_fit(out, fitting, IDM, "lm", settings, force)),
    }
    trees = {name: load_result(path) for name, (_, path) in fits.items()}
    policies = {
        name: pooled_policy(
            name, model, trees[name], metadata(trees[name]), list(scenarios.simulated_ids)
        )
        for name, (model, _) in fits.items()
    }
    for name in MERGE_MODELS:
        policies[name] = baseline_policy(
            name, jax.random.key(SEEDS["baselines"]), traj, scenarios.simulated_ids
        )
    rows = {
        name: {
            "model": name,
            "policy": policy.description,
            **evaluate_policy(
                jax.random.key(SEEDS["evaluate"]), policy, scenarios, num_rollouts=settings.rollouts
            ),
        }
        for name, policy in policies.items()
    }
    posterior = trees["cidm-smc"]["posterior"]
    return {
        "fits": {name: path.name for name, (_, path) in fits.items()},
        "scenario_set": scenarios.summary(),
        "fitting_stays": len(stays.vehicle_ids),
        "fitting_steps": int(fitting.mask.sum()),
        "fitting_stay_horizon_s": MERGE_FIT_STAY_S,
        "cidm_posterior": {
            name: {
                "mean": float(posterior[name].mean()),
                "sd": float(posterior[name].std()),
                "q05": float(posterior[name].quantile(0.05)),
                "q95": float(posterior[name].quantile(0.95)),
            }
            for name in CIDM.param_names
        },
        "cooperation_draws": posterior["c"].values.ravel().tolist(),
        "models": rows,
        "seed": SEEDS["evaluate"],
        "fit_seed": SEEDS["fit_merge"],
    }


def parameter_table(trees: dict[str, Any]) -> pd.DataFrame:
    """Posterior mean per vehicle and parameter, with the data set as a column."""
    frames = []
    for label, tree in trees.items():
        meta = metadata(tree)
        names = tuple(meta["params"])
        for vehicle, draws in particles_by_vehicle(tree, names).items():
            frames.append(
                {
                    "data": label,
                    "vehicle": vehicle,
                    **dict(zip(names, draws.mean(axis=0), strict=True)),
                }
            )
    return pd.DataFrame(frames)


def turing_models(
    label: str, traj: Trajectories, trees: dict[str, Any], settings: Settings
) -> tuple[ScenarioSet, dict[str, Any]]:
    """The held-out platoon scenarios the Turing test compares on (those every fitted tree
    covers) and its models: each fitted tree's policy, the default IDM and constant velocity."""
    scenarios = _covered(_highway_scenarios(label, traj, settings), trees)
    policies = dict(_learned_policy(t) for t in trees.values())
    for name in ("idm-default", "cv"):
        policies[name] = baseline_policy(
            name, jax.random.key(SEEDS["baselines"]), traj, scenarios.simulated_ids
        )
    return scenarios, policies


def _turing_rollout(policy, scenario, index: int):
    """The one rollout of ``policy`` on the ``index``-th scenario that the Turing test compares."""
    key = jax.random.fold_in(jax.random.key(SEEDS["turing"]), index)
    key_params, key_roll = jax.random.split(key)
    params = policy.params_for(key_params, scenario.simulated_ids, 1)
    return rollout(key_roll, policy.model, params, scene_arrays(scenario), num_rollouts=1)


def turing_comparison(
    scenarios: ScenarioSet, policies: dict[str, Any], permutations: int
) -> dict[str, dict]:
    """Both classifier two-sample tests of the real held-out segments (one per simulated vehicle
    and scenario) against one rollout of each policy on the same scenarios: the logistic
    regression on :func:`segment_features`, once on all six and once on the speed and gap levels
    only (``levels_only``), and the gradient-boosted trees on :func:`trajectory_features` with
    folds grouped by vehicle (``boosted``; leave-one-vehicle-out where fewer than
    :data:`TURING_FOLDS` vehicles)."""
    dt = scenarios.dt
    real_v, real_g, real_lead, vehicles = [], [], [], []
    for scenario in scenarios.scenarios:
        data = observed_data(scenario)
        real_v.append(data.v)
        real_g.append(data.gap)
        real_lead.append(scenario.v[:-1])
        vehicles.extend(scenario.simulated_ids)
    real_v, real_g = np.concatenate(real_v), np.concatenate(real_g)
    real = segment_features(real_v, real_g, dt)
    real_trajectory = trajectory_features(real_v, real_g, np.concatenate(real_lead), dt)
    groups = np.array(vehicles)
    folds = min(TURING_FOLDS, len(set(vehicles)))
    rows = {}
    for name, policy in policies.items():
        sim_v, sim_g, sim_lead = [], [], []
        for index, scenario in enumerate(scenarios.scenarios):
            simulated = _turing_rollout(policy, scenario, index)
            speed = np.asarray(simulated.v[0], dtype=np.float64)
            sim_v.append(speed)
            sim_g.append(np.asarray(simulated.gap[0]))
            # The replayed head leads the first follower; each simulated car leads the next.
            sim_lead.append(np.vstack([scenario.v[:1], speed[:-1]]))
        sim_v, sim_g = np.concatenate(sim_v), np.concatenate(sim_g)
        generated = segment_features(sim_v, sim_g, dt)
        rows[name] = {
            **classifier_two_sample_test(real, generated, seed=SEEDS["turing"])._asdict(),
            "levels_only": classifier_two_sample_test(
                real[:, LEVEL_FEATURES], generated[:, LEVEL_FEATURES], seed=SEEDS["turing"]
            )._asdict(),
            "boosted": boosted_two_sample_test(
                real_trajectory,
                trajectory_features(sim_v, sim_g, np.concatenate(sim_lead), dt),
                real_groups=groups,
                generated_groups=groups,
                seed=SEEDS["turing"],
                folds=folds,
                permutations=permutations,
            )._asdict(),
        }
    return rows


def turing_step(
    out: Path, highway: dict[str, dict], trajs: dict[str, Trajectories], settings: Settings
) -> dict:
    """The automated Turing test of every highway label (:func:`turing_comparison`). Also
    writes the material for a human test: paired clips (real and idm-smc, seeded order) in
    ``out``, and the answer sheet beside that folder, never in it."""
    from bayesdrive.reports.clips import write_answer_sheet, write_clip_pair

    out.mkdir(parents=True, exist_ok=True)
    order_rng = np.random.default_rng(SEEDS["turing"])
    answers = []
    results = {}
    for label, experiment in highway.items():
        folder = highway_folder(out.parent, label)
        trees = {e: load_result(p) for e, p in fit_paths(experiment, folder).items()}
        scenarios, policies = turing_models(label, trajs[label], trees, settings)
        results[label] = turing_comparison(scenarios, policies, settings.turing_permutations)
        if "contrast" in label:
            continue
        for index, scenario in enumerate(scenarios.scenarios[:CLIP_PAIRS]):
            simulated = _turing_rollout(policies["idm-smc"], scenario, index)
            real_x = scenario.x - scenario.origin
            sim_x = np.vstack([real_x[:1], np.asarray(simulated.x[0])])
            answers.append(
                write_clip_pair(
                    real_x,
                    sim_x,
                    scenario.length,
                    scenario.dt,
                    out,
                    f"{label.replace(':', '_')}_{index}",
                    order_rng,
                )
            )
    # Outside the clips' folder: whoever is handed the clips to judge blind must not get it.
    sheet = write_answer_sheet(answers, out.parent / f"{out.name}_answer_sheet.json")
    return {
        "classifier": results,
        "clips": str(out),
        "answer_sheet": str(sheet),
        "pairs": len(answers),
    }


def scenes_step(
    out: Path, trees: dict[str, Any], data: dict[str, Trajectories], settings: Settings
) -> dict:
    """Generated scenes from the paper's presets and from our pooled posteriors, against the data's
    speed and gap distributions (saved as arrays for the report's KDE plots)."""
    from bayesdrive.reports.scene_plots import plot_speed_gap_kde, plot_sweep

    out.mkdir(parents=True, exist_ok=True)
    key = jax.random.key(SEEDS["scenes"])
    num_steps, vehicles = 600, 16
    sources, sweeps, presets = {}, [], []
    for preset_file in sorted(PRESET_DIR.glob("*.json")):
        preset = load_preset(preset_file)
        presets.append(
            {
                "preset": preset.name,
                **{n: f"{m} ± {preset.sds[n]}" for n, m in preset.means.items()},
            }
        )
        key, sub_params, sub_scenes, sub_sweep = jax.random.split(key, 4)
        params = draw_preset(sub_params, IDM, preset, settings.generated_scenes, vehicles)
        sources[preset.name] = generate_scenes(sub_scenes, IDM, params, num_steps=num_steps, dt=0.1)
        sweep = median_sweep(sub_sweep, IDM, params, duration_s=num_steps * 0.1, dt=0.1)
        path = out / f"sweep_{preset.name}.png"
        plot_sweep(
            sweep,
            0.1,
            path,
            f"leader-follower sweep over desired-speed difference ({preset.name}, median draws)",
        )
        sweeps.append(path.name)
    for label, tree in trees.items():
        meta = metadata(tree)
        names = tuple(meta["params"])
        particles = np.stack(list(particles_by_vehicle(tree, names).values()))
        key, sub_params, sub_scenes = jax.random.split(key, 3)
        params = draw_pooled(
            sub_params,
            IDM,
            names,
            particles,
            settings.generated_scenes,
            vehicles,
            fixed_params(IDM, meta),
        )
        sources[f"ours: {label}"] = generate_scenes(
            sub_scenes, IDM, params, num_steps=num_steps, dt=0.1
        )
    figures, table = [], []
    for label, traj in data.items():
        tracks = traj.tracks
        real = (tracks["v"].to_numpy(), tracks["gap"].dropna().to_numpy())
        samples = {f"data: {label}": real}
        for name, generated in sources.items():
            samples[name] = (np.asarray(generated.v)[:, 1:], np.asarray(generated.gap)[:, 1:])
        path = out / f"scenes_{label.replace(':', '_')}.png"
        plot_speed_gap_kde(samples, path, f"speeds and gaps: generated scenes vs {label}")
        figures.append(path.name)
    for name, generated in sources.items():
        v = np.asarray(generated.v)[:, 1:]
        g = np.asarray(generated.gap)[:, 1:]
        table.append(
            {
                "source": name,
                "speed_mean_mps": float(v.mean()),
                "gap_median_m": float(np.median(g)),
                "collisions": int(np.asarray(generated.collision).any(axis=-1).sum()),
                "hard_braking_steps": int(np.asarray(generated.hard_braking).sum()),
            }
        )
    return {
        "figures": figures,
        "sweeps": sweeps,
        "presets": presets,
        "table": table,
        "seed": SEEDS["scenes"],
        "scenes": settings.generated_scenes,
        "vehicles": vehicles,
    }


def _holdout_config(settings: Settings) -> HoldoutConfig:
    return HoldoutConfig(
        particles=settings.smc_particles,
        rollouts=settings.rollouts,
        max_scenarios=settings.holdout_max_scenarios,
        fit_seed=SEEDS["holdout_fit"],
        rollout_seed=SEEDS["holdout"],
        baseline_seed=SEEDS["baselines"],
    )


def _kept_fit(path: Path, force: bool) -> Path:
    """Where a held-out fit is kept; a forced run removes the earlier one."""
    if force:
        path.unlink(missing_ok=True)
    return path


def _final_model(name: str, final_models: dict[str, str]) -> DriverModel | None:
    """The final model the criticism chose on held-out set ``name``'s training data set (by
    highway label in ``final_models``), None where that is the IDM or nothing was chosen."""
    training = TRAINING_DATA[name]
    final = next((m for label, m in final_models.items() if label.split(":")[0] == training), None)
    return None if final in (None, IDM.name) else get_model(final)


def _holdout_fit_path(folder: Path, name: str, model: DriverModel) -> Path:
    """Where the held-out steps keep ``model``'s smc fit of set ``name``'s followers."""
    return folder / f"{name}_{model.name.replace('+', '_')}_smc.nc"


def calibration_step(
    out: Path,
    final_models: dict[str, str],
    settings: Settings,
    force: bool,
    load: Callable[[str], Trajectories],
    evaluation_fits: Path,
    names: Sequence[str] | None = None,
) -> dict:
    """Calibration on the held-out windows (:func:`~bayesdrive.experiments.holdout.calibrate_data_set`)
    of every held-out data set (read by ``load``; ``names``: only these), for the IDM and the final
    model the criticism chose on the training data set of the same kind (``final_models``, by
    highway label), each set cached in ``out``. The fits are the evaluation's, kept in
    ``evaluation_fits``."""
    out.mkdir(parents=True, exist_ok=True)
    config = _holdout_config(settings)
    rows = {}
    for name in holdout_names(settings) if names is None else names:
        training = TRAINING_DATA[name]
        final = _final_model(name, final_models)
        models = (IDM,) if final is None else (IDM, final)
        try:
            traj = load(name)
        except DataError as error:
            rows[name] = {"error": str(error)}
            continue
        fits = {m.name: _holdout_fit_path(evaluation_fits, name, m) for m in models}
        rows[name] = cached(
            out,
            name,
            lambda t=traj, m=models, d=training, f=fits: {
                **calibrate_data_set(t, config, m, f),
                "training_data": d,
            },
            force,
        )
    return {"fit_seed": SEEDS["holdout_fit"], "seed": SEEDS["holdout"], "data_sets": rows}


def holdout_step(
    out: Path,
    smc_trees: dict[str, Any],
    settings: Settings,
    force: bool,
    load: Callable[[str], Trajectories],
    names: Sequence[str] | None = None,
    final_models: dict[str, str] | None = None,
) -> dict:
    """Generalisation to new drivers and new roads: the protocol of
    :mod:`bayesdrive.experiments.holdout` on every held-out data set (read by ``load``; ``names``:
    only these), each set's result cached in ``out`` beside the population fits and the
    per-vehicle fits.
    ``smc_trees`` are the highway experiment's per-vehicle fits: their vehicles are the
    populations' training drivers, and the NGSIM I-80 one gives the earlier pooled row. With
    ``final_models`` (by highway label), the final model the criticism chose on a set's training
    data forecasts it too (point 8 of the protocol). Nothing is tuned here: the held-out fits use
    the fixed defaults."""
    out.mkdir(parents=True, exist_ok=True)
    config = _holdout_config(settings)
    evaluated = holdout_names(settings) if names is None else names
    populations = {}
    for training in sorted({TRAINING_DATA[name] for name in evaluated}):
        path = out / f"population_{training}.nc"
        if force or not path.exists():
            population = population_from(
                smc_trees, training, draws=settings.smc_particles, seed=SEEDS["holdout_fit"]
            )
            save_result(population, path)
        populations[training] = path
    rows = {}
    for name in evaluated:
        try:
            traj = load(name)
        except DataError as error:  # a folder this reader cannot read is reported
            rows[name] = {"error": str(error)}
            continue
        population = load_result(populations[TRAINING_DATA[name]])
        final = _final_model(name, final_models or {})
        fit_path = _kept_fit(_holdout_fit_path(out, name, IDM), force)
        final_path = (
            None if final is None else _kept_fit(_holdout_fit_path(out, name, final), force)
        )
        rows[name] = cached(
            out,
            name,
            lambda n=name, t=traj, p=population, f=fit_path, m=final, g=final_path: (
                evaluate_data_set(
                    n,
                    t,
                    config,
                    p,
                    smc_trees["ngsim_i80_chains"],
                    fit_path=f,
                    final=m,
                    final_fit_path=g,
                )
            ),
            force,
        )
    return {
        "protocol": PROTOCOL,
        "left_out_by_settings": [n for n in registry.HOLDOUT if n not in rows],
        "fit_seed": SEEDS["holdout_fit"],
        "seed": SEEDS["holdout"],
        "rollouts": settings.rollouts,
        "populations": {name: path.name for name, path in populations.items()},
        "data_sets": rows,
    }


def prior_sensitivity_step(traj: Trajectories, vehicle_ids: list[str], settings: Settings) -> dict:
    """Refit with every prior interval twice as wide (lower bounds kept positive) and report the
    shift of posterior means in units of the original posterior sd."""
    names = IDM.param_names
    base = IDM.prior(names)
    width = base.upper - base.lower
    wide = PriorBox(names, np.maximum(base.lower - width / 2, 0.01), base.upper + width / 2)
    ids = vehicle_ids[: settings.prior_sensitivity_vehicles]
    seed = SEEDS["prior_sensitivity"]
    trees = {
        label: fit(
            jax.random.key(seed),
            traj,
            model=IDM,
            engine="smc",
            num_particles=settings.smc_particles,
            seed=seed,
            vehicle_ids=ids,
            prior=prior,
        )
        for label, prior in (("box", base), ("wide", wide))
    }
    narrow, wider = (particles_by_vehicle(t, names) for t in trees.values())
    rows = []
    for vehicle in narrow:
        for i, name in enumerate(names):
            sd = narrow[vehicle][:, i].std()
            rows.append(
                {
                    "vehicle": vehicle,
                    "param": name,
                    "mean_box": float(narrow[vehicle][:, i].mean()),
                    "mean_wide": float(wider[vehicle][:, i].mean()),
                    "shift_in_sd": float(
                        (wider[vehicle][:, i].mean() - narrow[vehicle][:, i].mean()) / sd
                    ),
                    "sd_ratio": float(wider[vehicle][:, i].std() / sd),
                }
            )
    return {
        "seed": seed,
        "wide_prior": {"lower": wide.lower.tolist(), "upper": wide.upper.tolist()},
        "rows": rows,
    }


def criticised_scenes(label: str, traj: Trajectories, settings: Settings) -> list[str]:
    """The scenes the criticism reads on highway data set ``label``: ``criticism_scenes`` of them
    (None: all), from its first or from the one ``criticism_first_scene`` names for it."""
    first = dict(settings.criticism_first_scene).get(label, 0)
    count = settings.criticism_scenes
    scenes = list(pd.unique(traj.scenes["scene_id"]))
    return scenes[first : None if count is None else first + count]


def criticism_data(label: str, traj: Trajectories, settings: Settings) -> Trajectories:
    """The criticism's data (:func:`criticism_step`): every vehicle of its scenes, so each
    follower's leader is in the data, cut to their first ``criticism_seconds``."""
    scenes = criticised_scenes(label, traj, settings)
    chosen = traj.scenes.loc[traj.scenes["scene_id"].isin(scenes), "vehicle_id"]
    return traj.subset(chosen).first_seconds(settings.criticism_seconds)


def criticism_step(out: Path, label: str, traj: Trajectories, settings: Settings) -> dict:
    """What the stochastic IDM gets wrong on real data, the named cause and its gain.

    Uses whole scenes (all vehicles of the scenes :func:`criticised_scenes` names), so every follower's
    leader is in the data, cut to their first ``criticism_seconds`` (an OpenACC recording lasts
    374 s; the fits' cost grows faster than the series length).
    """
    from bayesdrive.criticism.criticize import CriticizeConfig, criticize
    from bayesdrive.reports.criticism_plots import plot_criticism

    scenes = criticised_scenes(label, traj, settings)
    chosen = criticism_data(label, traj, settings)
    config = CriticizeConfig(
        num_particles=settings.criticism_particles,
        num_rollouts=settings.criticism_rollouts,
        max_rounds=settings.criticism_rounds,
    )
    result = criticize(chosen, seed=SEEDS["criticism"], config=config)
    figures = [p.name for p in plot_criticism(result, out)]
    return {
        "scenes": len(scenes),
        "seconds_per_scene": settings.criticism_seconds,
        **result.report,
        "figures": figures,
    }


MODEL_DESCRIPTIONS = {
    "idm": "stochastic IDM",
    "cidm": "stochastic Cooperative IDM; one parameter set pooled over the cooperating cars' "
    "stays behind merging cars in the fitting episodes",
}


def describe_model(name: str) -> str:
    """A model card's words for a (composite) model name."""
    base, *causes = name.split("+")
    words = MODEL_DESCRIPTIONS[base]
    if causes:
        words += (
            f" extended by {' and '.join(c.replace('_', ' ') for c in causes)}: what "
            "`bayesdrive criticize` adopted on this data set (reports: the criticism section)"
        )
    return words


def export_models(out: Path, fitted: dict[str, tuple[str, Path]], settings: Settings) -> list[str]:
    """Fitted driver models as artefacts: each smc posterior (posterior group and metadata only,
    float32) as ``<stem>.nc`` beside a short model card ``<stem>.md``; ``fitted`` maps a stem to
    the data label and the saved result."""
    import xarray as xr

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for stem, (label, path) in fitted.items():
        tree = load_result(path)
        posterior = tree["posterior"].to_dataset().astype("float32")
        slim = xr.DataTree.from_dict({"posterior": posterior})
        # The step length stays with the slim file: SUMO export sub-steps the IDM at it.
        slim.attrs = {**tree.attrs, "dt": float(tree["observed_data"].attrs["dt"])}
        save_result(slim, out / f"{stem}.nc")
        card = model_card(
            tree,
            title=stem,
            description=describe_model(metadata(tree)["model"]),
            label=label,
            lines=[
                f"settings: bayesdrive reproduce, '{settings.name}' run",
                "cross-engine agreement of smc with nuts and emcee on real NGSIM vehicles: "
                "reports/agreement/agreement.md; congested data leaves v_des, d_min and b_pref "
                "weakly identified",
                "regenerate: `bayesdrive reproduce --out results` (the file is "
                f"results/models/{stem}.nc)",
            ],
        )
        write_text_atomic(out / f"{stem}.md", card)
        written.append(str(out / f"{stem}.nc"))
    return written


def data_step() -> dict:
    """data info of every registered data set."""
    return {name: summary(registry.load(name)) for name in registry.DATASETS}


def release_compiled_programs() -> None:
    """Drop every compiled program kept for reuse: JAX's caches and the engines' chunk cache.

    Each kept executable holds memory and memory maps of its own, and a whole reproduction
    compiles thousands: kept to the end, they made XLA fail to allocate memory for the next
    compile in the calibration step on a 24 GB machine. A later step that needs a program again
    reads it back from the persistent compilation cache (the same executable, so the same bits)."""
    jax.clear_caches()
    clear_compiled()


class StepClock:
    """Each step's wall time in this invocation: a step ends where the next is announced, so a
    step reused from an earlier invocation shows about 0 s and is marked reused. Between steps
    the compiled programs of the one that ended are released (:func:`release_compiled_programs`).
    """

    def __init__(self, out: Path, progress: Callable[[str], None]):
        self.out = out
        self.progress = progress
        self.steps: list[dict[str, Any]] = []
        self.started = time.perf_counter()
        self.last = self.started

    def __call__(self, step: str) -> None:
        self._close()
        release_compiled_programs()
        self.steps.append({"step": step, "seconds": None})
        self.progress(step)

    def _close(self) -> None:
        now = time.perf_counter()
        if self.steps:
            self.steps[-1]["seconds"] = round(now - self.last, 1)
        self.last = now

    def finish(self) -> list[dict[str, Any]]:
        """Every step's time, and the total as the last row; saved beside the results."""
        self._close()
        rows = [*self.steps, {"step": "total", "seconds": round(self.last - self.started, 1)}]
        _save_json(self.out / "step_times.json", rows)
        return rows


def _sizes(fields: dict[str, Any]) -> dict[str, Any]:
    """Every setting of ``fields`` (a run's settings as JSON) but which optional steps run."""
    return {k: v for k, v in fields.items() if k != "optional_steps"}


def held_out_steps(
    out: Path,
    smc_trees: dict[str, Any],
    chosen: dict[str, str],
    settings: Settings,
    force: bool,
    progress: Callable[[str], None],
) -> dict[str, dict]:
    """The optional ``holdout`` steps: generalisation to the held-out data sets
    (:func:`holdout_step`), then calibration on their held-out windows (:func:`calibration_step`),
    which reuses the first's fits. ``chosen``: the criticism's final model by highway label."""
    progress("generalisation on held-out data sets")
    # Both held-out steps read every held-out set: once.
    load_holdout = functools.cache(registry.load_holdout)
    # Not "holdout": results of the earlier layout (one pooled row, no fits) are not reused.
    evaluation = cached(
        out,
        "holdout_evaluation",
        lambda: holdout_step(
            out / "holdout", smc_trees, settings, force, load_holdout, final_models=chosen
        ),
        force,
    )
    progress("calibration on held-out data sets")
    calibration = cached(
        out,
        "holdout_calibration",
        lambda: calibration_step(
            out / "holdout" / "calibration",
            chosen,
            settings,
            force,
            load_holdout,
            evaluation_fits=out / "holdout",
        ),
        force,
    )
    return {"holdout": evaluation, "holdout_calibration": calibration}


def run_all(
    out: Path, settings: Settings, *, force: bool = False, progress: Callable[[str], None] = print
) -> dict:
    """Run every experiment into ``out``, less the optional steps ``settings`` leave out
    (finished steps are reused unless ``force``); each step's time goes to
    ``out/step_times.json`` and the report (:class:`StepClock`)."""
    out.mkdir(parents=True, exist_ok=True)
    progress = StepClock(out, progress)
    recorded = out / "settings.json"
    # As JSON reads them back (tuples become lists), so a folder's own settings compare equal.
    # The optional steps may differ: a step's results do not depend on which others ran.
    wanted = _sizes(json.loads(json.dumps(settings.__dict__)))
    if recorded.exists() and not force and _sizes(json.loads(recorded.read_text())) != wanted:
        raise ValueError(
            f"{out} holds results of other settings ({recorded}); use --force or another --out"
        )
    _save_json(recorded, settings.__dict__)
    results: dict[str, Any] = {"settings": settings.__dict__, "seeds": SEEDS}
    results["steps_left_out"] = {
        step: text for step, text in OPTIONAL_STEPS.items() if step not in settings.optional_steps
    }
    progress("data sets")
    results["data"] = cached(out, "data", data_step, force)
    trajs: dict[str, Trajectories] = {}
    for name in HIGHWAY_SIZES:
        trajs.update(highway_data(name))
    # The criticism comes first: its final model joins the highway tables, the Turing test and
    # models/ beside the IDM (the acc-contrast recordings, not human drivers, are not criticised).
    main_data = {k: v for k, v in trajs.items() if not k.endswith("acc-contrast")}
    criticism = {}
    for label, traj in main_data.items():
        if settings.criticised is not None and label not in settings.criticised:
            continue
        progress(f"criticism: {label}")
        folder = criticism_folder(out, label)
        criticism[label] = cached(
            folder,
            "criticism",
            lambda t=traj, f=folder, lab=label: criticism_step(f, lab, t, settings),
            force,
        )
    results["criticism"] = criticism
    results["criticism_left_out_by_settings"] = [k for k in main_data if k not in criticism]
    highway = {}
    for label, traj in trajs.items():
        progress(f"highway experiment: {label}")
        folder = highway_folder(out, label)
        final = criticism[label]["model"] if label in criticism else None
        highway[label] = cached(
            folder,
            "evaluation",
            lambda t=traj, f=folder, lab=label, m=final: highway_step(
                f, lab, t, settings, force, final_model=m
            ),
            force,
        )
    results["highway"] = highway
    progress("merging experiment")
    results["merge"] = cached(
        out, "merge", lambda: merge_step(out / "merge", settings, force), force
    )
    highway_fits = {label: fit_paths(h, highway_folder(out, label)) for label, h in highway.items()}
    smc_trees = {label: load_result(fits["smc"]) for label, fits in highway_fits.items()}
    results["final_models"] = {
        label: metadata(load_result(fits[FINAL]))["model"]
        for label, fits in highway_fits.items()
        if FINAL in fits
    }
    pf_trees = {label: load_result(fits["pf"]) for label, fits in highway_fits.items()}
    results["parameters"] = parameter_table(smc_trees).to_dict("records")
    if "turing" in settings.optional_steps:
        progress("Turing test")
        results["turing"] = cached(
            out, "turing", lambda: turing_step(out / "turing", highway, trajs, settings), force
        )
    progress("scene generation")
    main_trees = {k: v for k, v in smc_trees.items() if not k.endswith("acc-contrast")}
    results["scenes"] = cached(
        out, "scenes", lambda: scenes_step(out / "scenes", main_trees, main_data, settings), force
    )
    if "holdout" in settings.optional_steps:
        # Only the highway labels the criticism ran on: their final models are the chosen ones.
        chosen = {k: v for k, v in results["final_models"].items() if k in criticism}
        results.update(held_out_steps(out, smc_trees, chosen, settings, force, progress))
    progress("prior sensitivity")
    chains = trajs["ngsim_i80_chains"]
    chain_ids = list(
        metadata(smc_trees["ngsim_i80_chains"]).get("vehicle_ids")
        or [str(v) for v in smc_trees["ngsim_i80_chains"]["posterior"]["vehicle"].values]
    )
    results["prior_sensitivity"] = cached(
        out, "prior_sensitivity", lambda: prior_sensitivity_step(chains, chain_ids, settings), force
    )
    fitted = {
        f"{label.replace(':', '_')}_idm_smc": (label, fits["smc"])
        for label, fits in highway_fits.items()
    }
    for label, fits in highway_fits.items():
        if FINAL in fits:
            model = metadata(load_result(fits[FINAL]))["model"]
            fitted[f"{label.replace(':', '_')}_{model.replace('+', '_')}_smc"] = (
                label,
                fits[FINAL],
            )
    fitted[f"{MERGE_DATA}_cidm_smc"] = (
        MERGE_DATA,
        fit_paths(results["merge"], out / "merge")["cidm-smc"],
    )
    progress("model export")
    results["models"] = export_models(out / "models", fitted, settings)
    results["trees"] = {"smc": smc_trees, "pf": pf_trees}
    results["step_times"] = progress.finish()
    return results
