"""``bayesdrive evaluate``: closed-loop rollouts of a model on held-out windows, scored.

DATA is a file, a folder or a data set name (held-out names too: evaluation is what they are
for). Merge-episode data gives merge scenes (the cooperating main-lane driver simulated), any
other data platoon scenes (see :mod:`bayesdrive.simulation.scenarios`). The model is a baseline
name, or the driver model of a fitted posterior given with ``--posterior RESULT``; a posterior
fitted on another split, window or data source is refused, and so is one without draws for a
simulated vehicle. Bad input ends with a one-line ``error: ...`` on standard error and exit code 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from bayesdrive.cli.common import check_json_out, console, emit_json, err_console, fail
from bayesdrive.data import registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.output import load_result, metadata
from bayesdrive.simulation.baselines import (
    BASELINES,
    CAR_FOLLOWING_ONLY,
    MERGE_ONLY,
    Policy,
    baseline_policy,
)
from bayesdrive.simulation.metrics import evaluate_policy
from bayesdrive.simulation.posterior import posterior_policy
from bayesdrive.simulation.scenarios import (
    ScenarioSet,
    merge_scenarios,
    platoon_scenarios,
    scenario_capacity,
)

__all__ = ["check_posterior_split", "evaluate"]

MERGE_FORMAT = "merge_episodes"
JSON_HELP = "Write the result as JSON to OUT ('-' for standard output, then nothing else there)."


def _load(data: str, data_dir: str | None) -> tuple[Trajectories, bool]:
    """The trajectories, and whether they are a held-out data set."""
    if data in registry.HOLDOUT and not Path(data).exists():
        return registry.load_holdout(data, holdout_dir=data_dir), True
    return registry.load(data, data_dir=data_dir), False


def _scenarios(traj: Trajectories, horizon: float, vehicles_per_scenario: int) -> ScenarioSet:
    if traj.format == MERGE_FORMAT:
        found = merge_scenarios(traj, horizon_s=horizon)
    else:
        found = platoon_scenarios(
            traj, vehicles_per_scenario=vehicles_per_scenario, horizon_s=horizon
        )
    if found.scenarios:
        return found
    if found.kind == "platoon":
        allowed = scenario_capacity(traj, horizon_s=horizon)
        sizes = (
            ", ".join(f"{r['vehicles_per_scenario']}: {r['scenarios']}" for r in allowed)
            or "none at any size"
        )
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


def _posterior_policy(
    path: Path, model_name: str, traj: Trajectories, scenarios: ScenarioSet, data_dir: str | None
) -> Policy:
    tree = load_result(path)
    meta = metadata(tree)
    if meta.get("model") != model_name:
        raise DataError(
            f"{path}: the posterior is of model {meta.get('model')!r}, not --model {model_name!r}"
        )
    check_posterior_split(meta, traj, scenarios, data_dir)
    model = get_model(model_name)
    if model.name == CIDM.name and scenarios.kind != "merge":
        raise DataError(f"{path}: a Cooperative-IDM posterior needs merge scenes, not platoons")
    vehicles = {str(v) for v in tree["posterior"]["vehicle"].values}
    missing = [v for v in scenarios.simulated_ids if v not in vehicles]
    if missing:
        raise DataError(f"{path}: the posterior has no draws for simulated vehicle(s) {missing}")
    policy = posterior_policy(model_name, model, tree, meta)
    details = {
        **policy.details,
        "result": str(path),
        "engine": meta.get("engine"),
        "fit_seed": meta.get("seed"),
        "fixed": meta.get("fixed"),
    }
    return policy._replace(details=details)


def _baseline(
    name: str, key, traj: Trajectories, scenarios: ScenarioSet, heldout_data: bool
) -> Policy:
    if name in MERGE_ONLY and scenarios.kind != "merge":
        raise DataError(f"{name} simulates merges; {traj.source} has no merge episodes")
    if name in CAR_FOLLOWING_ONLY and scenarios.kind == "merge":
        raise DataError(
            f"{name} needs fitting windows of the evaluated vehicles; merge episodes are split "
            "by episode, so held-out cooperating drivers have none"
        )
    if name in CAR_FOLLOWING_ONLY and heldout_data:
        raise DataError(
            f"{name} fits on the data it evaluates; {traj.source} is held out for evaluation "
            "only: nothing may be fitted on it"
        )
    with _progress() as bar:
        task = bar.add_task(f"fitting {name}", total=None)
        return baseline_policy(
            name,
            key,
            traj,
            scenarios.simulated_ids,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )


def _progress() -> Progress:
    # On stderr: stdout may carry the JSON.
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err_console,
        transient=True,
    )


def _mean_sd(summary: dict[str, Any]) -> str:
    sd = summary["sd"]
    return f"{summary['mean']:.3f}" + (f" ± {sd:.3f}" if sd is not None else "")


def _print(result: dict[str, Any]) -> None:
    scenes = result["scenario_set"]
    table = Table(
        title=escape(
            f"{result['model']} on {result['data_source']}: {result['scenarios']} {scenes['kind']} "
            f"scenario(s), {result['vehicles']} simulated vehicle-windows, "
            f"{result['rollouts']} rollout(s), {result['horizon_s']} s"
        )
    )
    table.add_column("metric")
    table.add_column("value", justify="right")
    paper = result["paper_mae_last_step"]
    rows = [
        ("RMSE position at the horizon (m), mean ± sd over scenarios", result["rmse_position_m"]),
        ("RMSE speed at the horizon (m/s)", result["rmse_speed_mps"]),
        ("paper's metric: MAE position at the last step (m)", paper["position_m"]),
        ("paper's metric: MAE speed at the last step (m/s)", paper["speed_mps"]),
    ]
    for label, summary in rows:
        table.add_row(label, _mean_sd(summary))
    collisions, braking = result["collisions"], result["hard_braking"]
    table.add_row("collisions (events, all rollouts)", str(collisions["total"]))
    table.add_row("vehicle-rollouts that collide", f"{collisions['fraction']:.2%}")
    table.add_row(
        "hard-braking steps (a <= -3 m/s^2), per rollout / data",
        f"{braking['per_rollout']:.1f} / {braking['data_total']}",
    )
    table.add_row("off-road steps", str(result["off_road"]["total"]))
    for label, key in (
        ("speed (m/s)", "speed_distribution_mps"),
        ("gap (m)", "gap_distribution_m"),
    ):
        distance = result[key]
        table.add_row(
            f"{label} distribution vs data: Wasserstein / KS",
            f"{distance['wasserstein']:.3f} / {distance['ks']:.3f}",
        )
    console.print(table)
    console.print(escape(f"scenarios: {scenes['selection_rule']}"))
    console.print(escape(f"split: {result['split_rule']}"))
    console.print(f"seed {result['seed']}")


def evaluate(
    data: str = typer.Argument(..., help="A file, a folder, or a data set name."),
    model: str = typer.Option(
        ...,
        "--model",
        help=f"A baseline ({', '.join(BASELINES)}) or, with --posterior, the posterior's model.",
    ),
    posterior: str | None = typer.Option(
        None, "--posterior", help="A result.nc written by `bayesdrive fit`."
    ),
    horizon: float = typer.Option(5.0, "--horizon", help="Simulated horizon (s)."),
    rollouts: int = typer.Option(100, "--rollouts", min=1, help="Rollouts per scenario."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random draw (recorded)."),
    vehicles_per_scenario: int = typer.Option(
        4,
        "--vehicles-per-scenario",
        min=1,
        help="Simulated vehicles per platoon scenario, behind one replayed head (4: an OpenACC "
        "platoon behind its leader).",
    ),
    data_dir: str | None = typer.Option(
        None, "--data-dir", help="Folder holding the data sets (held-out ones for a held-out name)."
    ),
    json_out: str | None = typer.Option(None, "--json", metavar="OUT", help=JSON_HELP),
) -> None:
    """Roll a model out closed loop on the held-out windows and print the metric table."""
    check_json_out(json_out)
    key_policy, key_rollouts = jax.random.split(jax.random.key(seed))
    try:
        traj, heldout_data = _load(data, data_dir)
        scenarios = _scenarios(traj, horizon, vehicles_per_scenario)
        if posterior is not None:
            policy = _posterior_policy(Path(posterior), model, traj, scenarios, data_dir)
        elif model in BASELINES:
            policy = _baseline(model, key_policy, traj, scenarios, heldout_data)
        else:
            raise DataError(
                f"unknown model {model!r}: use a baseline ({', '.join(BASELINES)}) or give the "
                "fitted posterior with --posterior RESULT"
            )
        with _progress() as bar:
            task = bar.add_task(f"rolling out {model}", total=len(scenarios.scenarios))
            summary = evaluate_policy(
                key_rollouts,
                policy,
                scenarios,
                num_rollouts=rollouts,
                on_scenario=lambda _: bar.advance(task),
            )
    except (DataError, OSError, KeyError, ValueError) as error:
        raise fail(escape(str(error))) from None
    result = {
        "model": model,
        "policy": policy.description,
        "policy_details": policy.details,
        "data_source": traj.source,
        "seed": seed,
        "horizon_s": horizon,
        "vehicles_per_scenario": scenarios.vehicles_per_scenario,
        "split_rule": scenarios.split_rule,
        "scenario_set": scenarios.summary(),
        **summary,
    }
    if not emit_json(result, json_out):
        _print(result)
