"""``bayesdrive evaluate``: closed-loop rollouts of a model on held-out windows, scored.

What runs is :func:`bayesdrive.simulation.evaluation.evaluate` (its docstring says which data,
scenarios and posteriors it takes); this module parses the options, shows progress and prints the
metric table. Bad input ends with a one-line ``error: ...`` on standard error and exit code 2.
"""

from __future__ import annotations

from typing import Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ForceJson,
    JsonOut,
    check_cluster_options,
    check_json_out,
    console,
    emit_json,
    fail,
    progress_bar,
)
from bayesdrive.cli.names import BASELINES, SCENARIO_CHUNK_SIZE

__all__ = ["evaluate"]


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
    skipped = result["skipped"]
    if skipped:
        console.print(
            escape(
                f"skipped {skipped['scenarios']} scenario(s): {skipped['reason']}: "
                f"{', '.join(skipped['vehicles'])}"
            )
        )
    if result["scenario_size"]:
        console.print(escape(f"scenario size: {result['scenario_size']}"))
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
    vehicles_per_scenario: int | None = typer.Option(
        None,
        "--vehicles-per-scenario",
        min=1,
        help="Simulated vehicles per platoon scenario, behind one replayed head (default: the "
        "largest size the data allows, and the output says so).",
    ),
    data_dir: str | None = typer.Option(
        None, "--data-dir", help="Folder holding the data sets (held-out ones for a held-out name)."
    ),
    json_out: JsonOut = None,
    force: ForceJson = False,
    cluster: str | None = typer.Option(
        None,
        "--cluster",
        help="Roll out chunks of scenarios on Dask: local[:N] starts N single-threaded process "
        "workers (default: one per core), tcp://HOST:PORT uses a running scheduler. Same result "
        "as without.",
    ),
    chunk_size: int | None = typer.Option(
        None,
        "--chunk-size",
        min=1,
        help=f"With --cluster: scenarios per task (default {SCENARIO_CHUNK_SIZE}).",
    ),
) -> None:
    """Roll a model out closed loop on the held-out windows and print the metric table."""
    # Imported here so that `bayesdrive evaluate --help` does not import JAX.
    import jax

    from bayesdrive.data.errors import DataError
    from bayesdrive.inference import distributed
    from bayesdrive.simulation import evaluation

    check_json_out(json_out, force)
    check_cluster_options(cluster, chunk_size)
    with progress_bar() as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int | None) -> None:
            if stage not in tasks:
                label = f"fitting {model}" if stage == "fit" else f"rolling out {model}"
                tasks[stage] = bar.add_task(label, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        options = {
            "model": model,
            "posterior": posterior,
            "horizon_s": horizon,
            "num_rollouts": rollouts,
            "vehicles_per_scenario": vehicles_per_scenario,
            "seed": seed,
            "data_dir": data_dir,
            "progress": progress,
        }
        try:
            if cluster is None:
                result = evaluation.evaluate(jax.random.key(seed), data, **options)
            else:
                with distributed.open_cluster(cluster) as client:
                    result = evaluation.evaluate(
                        jax.random.key(seed),
                        data,
                        **options,
                        client=client,
                        chunk_size=chunk_size or evaluation.DEFAULT_SCENARIO_CHUNK,
                    )
        except (DataError, OSError, KeyError, ValueError) as error:
            raise fail(str(error)) from None
    if not emit_json(result, json_out):
        _print(result)
