"""Evaluate a model closed loop on the held-out windows of a data set: what ``bayesdrive evaluate``
and ``bayesdrive.evaluate`` run.

The data is a file, a folder or a data set name (held-out names too: evaluation is what they are
for). Merge-episode data gives merge scenes (the cooperating main-lane driver simulated), any
other data platoon scenes (see :mod:`bayesdrive.simulation.scenarios`). The model is a baseline
name, or the driver model of a fitted posterior (a result tree or its netCDF file); a posterior
fitted on another split, window or data source is refused. A posterior fitted on some vehicles
only (``fit --vehicles N``) scores the scenarios whose simulated vehicles it has draws for; the
others are skipped, and the result names them (``skipped``). Platoon scenarios take the largest
size the data allow unless a size is given, and the result says so (``scenario_size``).
Baselines that fit (``idm-lm``, ``blackbox``) follow the held-out protocol of
:mod:`bayesdrive.experiments.holdout` on any data, held-out sets included: fitted on the fitting
windows with their documented settings, scored on the held-out windows.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data import registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import load_result, metadata
from bayesdrive.inference.distributed import chunk_rows, run_tasks
from bayesdrive.simulation.baselines import (
    BASELINES,
    CAR_FOLLOWING_ONLY,
    MERGE_ONLY,
    PER_VEHICLE_FITS,
    Policy,
    baseline_policy,
)
from bayesdrive.simulation.metrics import (
    DistributionSamples,
    ScenarioMetrics,
    evaluate_policy,
    evaluate_scenario,
    scenario_keys,
    summarize,
)
from bayesdrive.simulation.posterior import posterior_policy
from bayesdrive.simulation.scenarios import (
    MERGE_FORMAT,
    Scenario,
    ScenarioSet,
    merge_scenarios,
    platoon_scenarios,
    scenario_capacity,
)

__all__ = [
    "check_posterior_split",
    "evaluate",
    "evaluation_data",
    "evaluation_scenarios",
    "largest_scenario_size",
]

log = logging.getLogger(__name__)

# progress(stage, done, total): stage "fit" (a baseline's per-vehicle fits) or "rollouts"
# (scenarios rolled out); total is None while unknown.
Progress = Callable[[str, int, int | None], None]
# Scenarios per Dask task with a client: a few seconds of rollouts each.
DEFAULT_SCENARIO_CHUNK = 8


def evaluation_data(
    data: str | Path | Trajectories, data_dir: str | None = None
) -> tuple[Trajectories, bool]:
    """The trajectories, and whether they are a held-out data set."""
    if isinstance(data, Trajectories):
        return data, False
    held_out = registry.is_holdout_name(data)
    return registry.load_any(data, data_dir=data_dir, note_held_out=False), held_out


def _sizes_allowed(traj: Trajectories, horizon: float) -> tuple[int | None, str]:
    """The largest platoon scenario size the held-out windows allow (None: none), and the
    scenario count of every size, as one line."""
    allowed = scenario_capacity(traj, horizon_s=horizon)
    sizes = (
        ", ".join(f"{r['vehicles_per_scenario']}: {r['scenarios']}" for r in allowed)
        or "none at any size"
    )
    return (allowed[-1]["vehicles_per_scenario"] if allowed else None), sizes


def largest_scenario_size(traj: Trajectories, horizon: float) -> tuple[int, str]:
    """The largest platoon scenario size of ``horizon`` s the held-out windows of ``traj`` allow,
    and the line that says it was chosen so; a :class:`DataError` if they allow none."""
    size, sizes = _sizes_allowed(traj, horizon)
    if size is None and not traj.tracks["leader_id"].notna().any():
        raise DataError(
            f"{traj.source}: no vehicle has a recorded leader, so there is no platoon scenario "
            "(a follower behind its replayed leader) to evaluate"
        )
    if size is None:
        raise DataError(
            f"{traj.source}: no platoon scenario of {horizon} s lies in the held-out windows at "
            "any size"
        )
    return size, (
        f"{size} vehicle(s) per scenario, the largest size the data allows (scenarios per size: "
        f"{sizes}); --vehicles-per-scenario picks another"
    )


def evaluation_scenarios(
    traj: Trajectories, horizon: float, vehicles_per_scenario: int
) -> ScenarioSet:
    """The held-out scenarios of ``traj``; a :class:`DataError` says which sizes exist if none."""
    if traj.format == MERGE_FORMAT:
        found = merge_scenarios(traj, horizon_s=horizon)
    else:
        found = platoon_scenarios(
            traj, vehicles_per_scenario=vehicles_per_scenario, horizon_s=horizon
        )
    if found.scenarios:
        return found
    if found.kind == "platoon":
        _, sizes = _sizes_allowed(traj, horizon)
        raise DataError(
            f"{traj.source}: no {vehicles_per_scenario}-vehicle platoon scenario of {horizon} s "
            f"lies in the held-out windows; scenarios per size the data allows: {sizes}"
        )
    raise DataError(f"{traj.source}: no merge scenario of at least 1 s in the held-out episodes")


def _location(source: Any, data_dir: str | None) -> Path | None:
    """Where a recorded data source lives: an existing path, or a registered data set's folder."""
    if not isinstance(source, str):
        return None
    if Path(source).exists():
        return Path(source).resolve()
    if source in registry.DATASETS:
        try:
            return registry.resolve(source, data_dir).resolve()
        except DataError:
            return None
    return None


def _same_source(recorded: Any, source: str, data_dir: str | None) -> bool:
    """The same string, or a name and a path (or two paths) for the same files."""
    if recorded == source:
        return True
    where = _location(recorded, data_dir)
    return where is not None and where == _location(source, data_dir)


def check_posterior_split(
    meta: dict[str, Any],
    traj: Trajectories,
    scenarios: ScenarioSet,
    data_dir: str | None = None,
) -> None:
    """Raise :class:`DataError` unless the posterior was fitted on the fitting side of the same
    split of the same data the evaluation scores (rule, window and data source; a data set's name
    and its folder count as the same source)."""
    problems = []
    if meta.get("split_rule") != scenarios.split_rule:
        problems.append(
            f"its split rule {meta.get('split_rule')!r} is not the evaluation's "
            f"{scenarios.split_rule!r}"
        )
    if meta.get("window") != "fit":
        problems.append(f"it was fitted on the {meta.get('window')!r} window, not 'fit'")
    if not _same_source(meta.get("data_source"), traj.source, data_dir):
        problems.append(
            f"it was fitted on {meta.get('data_source')!r}, the evaluation reads {traj.source!r}"
        )
    if problems:
        raise DataError("refusing the posterior: " + "; ".join(problems))


def _fitted_scenarios(
    where: str, fitted: set[str], scenarios: ScenarioSet, *, lacking: str
) -> tuple[ScenarioSet, dict[str, Any] | None]:
    """The scenarios whose every simulated vehicle is among the ``fitted`` ids, and what was
    skipped; ``lacking`` says what the others lack."""
    kept = scenarios.within(fitted)
    unfitted = [v for v in scenarios.simulated_ids if v not in fitted]
    if not unfitted:
        return scenarios, None
    if not kept.scenarios:
        raise DataError(
            f"{where}: {len(fitted)} vehicle(s) are fitted, and every one of the "
            f"{len(scenarios.scenarios)} scenario(s) simulates a vehicle without {lacking} "
            f"({len(unfitted)} such vehicle(s), e.g. {unfitted[:5]}); fit those vehicles, or "
            "evaluate one vehicle per scenario (--vehicles-per-scenario 1)"
        )
    skipped = {
        "scenarios": len(scenarios.scenarios) - len(kept.scenarios),
        "vehicles": unfitted,
        "reason": f"simulated vehicles without {lacking} (not fitted)",
    }
    log.warning(
        "%s: %d simulated vehicle(s) without %s; scoring the %d of %d scenario(s) without them, "
        "skipping %s",
        where,
        len(unfitted),
        lacking,
        len(kept.scenarios),
        len(scenarios.scenarios),
        unfitted,
    )
    return kept, skipped


def _posterior_policy(
    posterior: str | Path | xr.DataTree,
    model_name: str,
    traj: Trajectories,
    scenarios: ScenarioSet,
    data_dir: str | None,
) -> tuple[Policy, ScenarioSet, dict[str, Any] | None]:
    where = "the posterior" if isinstance(posterior, xr.DataTree) else str(posterior)
    tree = posterior if isinstance(posterior, xr.DataTree) else load_result(posterior)
    meta = metadata(tree)
    if meta.get("model") != model_name:
        raise DataError(
            f"{where}: the posterior is of model {meta.get('model')!r}, not --model {model_name!r}"
        )
    model = get_model(model_name)
    if model.scene is not None and scenarios.kind != model.scene:
        raise DataError(
            f"{where}: model {model.name!r} reads the {model.scene} scene, so its posterior needs "
            f"{model.scene} scenes, not {scenarios.kind} scenes"
        )
    check_posterior_split(meta, traj, scenarios, data_dir)
    fitted = {str(v) for v in tree["posterior"]["vehicle"].values}
    scenarios, skipped = _fitted_scenarios(where, fitted, scenarios, lacking="posterior draws")
    policy = posterior_policy(model_name, model, tree, meta)
    details = {
        **policy.details,
        "result": where,
        "engine": meta.get("engine"),
        "fit_seed": meta.get("seed"),
        "fixed": meta.get("fixed"),
    }
    return policy._replace(details=details), scenarios, skipped


def _baseline(
    name: str,
    key: Array,
    traj: Trajectories,
    scenarios: ScenarioSet,
    heldout_data: bool,
    progress: Progress,
) -> tuple[Policy, ScenarioSet, dict[str, Any] | None]:
    """The baseline's policy, the scenarios it can score and what it skipped. Baselines that fit
    follow the held-out protocol (:mod:`bayesdrive.experiments.holdout`) on any data: fitted on
    the fitting windows with their documented settings (nothing here can change them, so nothing
    is tuned on a held-out set), scored on the held-out windows; a follower without a usable
    fitting step has no per-vehicle fit, and its scenarios are skipped."""
    skipped = None
    if name in MERGE_ONLY and scenarios.kind != "merge":
        raise DataError(f"{name} simulates merges; {traj.source} has no merge episodes")
    if name in CAR_FOLLOWING_ONLY and scenarios.kind == "merge":
        raise DataError(
            f"{name} needs fitting windows of the evaluated vehicles; merge episodes are split "
            "by episode, so held-out cooperating drivers have none"
        )
    if name in CAR_FOLLOWING_ONLY and heldout_data:
        log.warning(registry.HELD_OUT_NOTE, traj.source)
    if name in PER_VEHICLE_FITS:
        arrays = follower_arrays(traj, window="fit", vehicle_ids=scenarios.simulated_ids)
        scenarios, skipped = _fitted_scenarios(
            f"{traj.source}: {name}",
            set(arrays.vehicle_ids),
            scenarios,
            lacking="a usable step in their fitting window",
        )
    policy = baseline_policy(
        name,
        key,
        traj,
        scenarios.simulated_ids,
        progress=lambda done, total: progress("fit", done, total),
    )
    return policy, scenarios, skipped


def _scenario_chunk(
    shared: tuple[Policy, int], chunk: list[tuple[np.ndarray, Scenario]]
) -> list[tuple[ScenarioMetrics, DistributionSamples]]:
    """One task: the scenarios of a chunk, each with its key's data (runs on a worker)."""
    policy, num_rollouts = shared
    return [
        evaluate_scenario(
            jax.random.wrap_key_data(key_data), policy, scenario, num_rollouts=num_rollouts
        )
        for key_data, scenario in chunk
    ]


def _evaluate_on_cluster(
    client: Any,
    key: Array,
    policy: Policy,
    scenarios: ScenarioSet,
    *,
    num_rollouts: int,
    chunk_size: int,
    progress: Callable[[int], None],
) -> dict[str, Any]:
    """:func:`~bayesdrive.simulation.metrics.evaluate_policy` with chunks of scenarios as Dask
    tasks; ``progress(done)`` counts finished scenarios."""
    key_data = np.asarray(jax.random.key_data(scenario_keys(key, scenarios)))
    rows = chunk_rows(len(scenarios.scenarios), chunk_size)
    finished: dict[int, list] = {}

    def collect(index: int, results: list) -> None:
        finished[index] = results
        progress(sum(len(r) for r in finished.values()))

    run_tasks(
        client,
        _scenario_chunk,
        (policy, num_rollouts),
        {
            index: [(key_data[i], scenarios.scenarios[i]) for i in row]
            for index, row in enumerate(rows)
        },
        collect,
    )
    ordered = [result for index in range(len(rows)) for result in finished[index]]
    return summarize([m for m, _ in ordered], [s for _, s in ordered])


def evaluate(
    key: Array,
    data: str | Path | Trajectories,
    *,
    model: str,
    posterior: str | Path | xr.DataTree | None = None,
    horizon_s: float = 5.0,
    num_rollouts: int = 100,
    vehicles_per_scenario: int | None = None,
    seed: int | None = None,
    data_dir: str | None = None,
    progress: Progress | None = None,
    client: Any = None,
    chunk_size: int = DEFAULT_SCENARIO_CHUNK,
) -> dict[str, Any]:
    """Roll ``model`` out closed loop on the held-out windows of ``data`` and score it.

    ``model`` is a baseline (:data:`~bayesdrive.simulation.baselines.BASELINES`) or, with
    ``posterior`` (a result tree or its file), the posterior's driver model. ``key`` splits into
    a key for the policy (what a baseline fits or draws) and one for the rollouts; ``seed`` is
    recorded beside the key's data. Returns the JSON-ready result: the metrics of
    :func:`~bayesdrive.simulation.metrics.summarize`, the scenario set and the rules that chose
    it, and ``skipped`` (scenarios left out for want of posterior draws or of a per-vehicle fit;
    None if none were). Platoon scenarios simulate ``vehicles_per_scenario`` vehicles each (None:
    the largest size the data allows, and ``scenario_size`` says so; None when given).
    With a Dask ``client`` the scenarios are rolled out in chunks of ``chunk_size`` on its workers
    (the policy is built here, then sent once to each); each scenario keeps its own key, so the
    result is bit-identical to the run without.
    """
    say = progress or (lambda stage, done, total: None)
    key_policy, key_rollouts = jax.random.split(key)
    traj, heldout_data = evaluation_data(data, data_dir)
    size, size_note = vehicles_per_scenario, None
    if size is None and traj.format != MERGE_FORMAT:
        size, size_note = largest_scenario_size(traj, horizon_s)
    # Merge scenes have one simulated driver each, whatever the size asked.
    scenarios = evaluation_scenarios(traj, horizon_s, size or 1)
    if posterior is not None:
        policy, scenarios, skipped = _posterior_policy(posterior, model, traj, scenarios, data_dir)
    elif model in BASELINES:
        policy, scenarios, skipped = _baseline(
            model, key_policy, traj, scenarios, heldout_data, say
        )
    else:
        raise DataError(
            f"unknown model {model!r}: use a baseline ({', '.join(BASELINES)}) or give the "
            "fitted posterior (--posterior RESULT)"
        )
    total = len(scenarios.scenarios)
    say("rollouts", 0, total)
    if client is None:
        done = iter(range(1, total + 1))
        summary = evaluate_policy(
            key_rollouts,
            policy,
            scenarios,
            num_rollouts=num_rollouts,
            on_scenario=lambda _: say("rollouts", next(done), total),
        )
    else:
        summary = _evaluate_on_cluster(
            client,
            key_rollouts,
            policy,
            scenarios,
            num_rollouts=num_rollouts,
            chunk_size=chunk_size,
            progress=lambda done: say("rollouts", done, total),
        )
    return {
        "model": model,
        "policy": policy.description,
        "policy_details": policy.details,
        "data_source": traj.source,
        "seed": seed,
        "key_data": jax.random.key_data(key).ravel().tolist(),
        "horizon_s": horizon_s,
        "vehicles_per_scenario": scenarios.vehicles_per_scenario,
        "scenario_size": size_note,
        "split_rule": scenarios.split_rule,
        "scenario_set": scenarios.summary(),
        "skipped": skipped,
        **summary,
    }
