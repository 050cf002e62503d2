"""``bayesdrive fit``: per-vehicle parameter distributions from trajectories, saved to a folder.

DATA is a file, a folder or a data set name (held-out names are refused: nothing is fitted on
them). Merge episodes are fitted per stay of the cooperating car behind the merging car, with the
merge scene beside every step, so ``--model cidm`` learns c too. OUT gets result.nc (the result tree, :mod:`bayesdrive.inference.output`), summary.json
(:func:`bayesdrive.inference.fit.summary`) and the filter diagnostics ess.png,
unique_particles.png and convergence.png. Bad input ends with a one-line ``error: ...`` on
standard error and exit code 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from bayesdrive.cli.common import console, emit_json, err_console, fail
from bayesdrive.data import registry
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.extensions import CAUSES
from bayesdrive.drivers.registry import MODELS, get_model
from bayesdrive.inference.fit import ENGINES, check_engine_model, summary
from bayesdrive.inference.fit import fit as fit_model
from bayesdrive.inference.likelihood import param_names
from bayesdrive.inference.output import save_result
from bayesdrive.reports.filter_plots import write_filter_plots
from bayesdrive.simulation.scenarios import (
    MERGE_FIT_STAY_S,
    merge_follower_arrays,
    merge_scenarios,
)

__all__ = ["fit"]

JSON_HELP = "Write summary.json's content to OUT too ('-' for standard output, then nothing else)."
# Vehicles listed in the printed table; summary.json has all of them.
SHOWN_VEHICLES = 10


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


def merge_arrays(traj: Trajectories, window: str) -> FollowerArrays:
    """Merge episodes are fitted per stay of a cooperating car behind the merging car, with the
    merge scene beside each step; ``fit`` uses the fitting episodes only (split by episode)."""
    scenarios = merge_scenarios(
        traj, horizon_s=MERGE_FIT_STAY_S, episodes="fit" if window == "fit" else "all"
    )
    return merge_follower_arrays(scenarios)


def _print(result: dict[str, Any], out: Path, written: list[str]) -> None:
    params = result["params"]
    table = Table(
        title=escape(
            f"{result['engine']} on {result['model']}: {len(result['vehicles'])} vehicle(s) of "
            f"{result['data_source']} ({result['window']} window), {result['num_particles']} "
            "particles; posterior mean ± sd"
        )
    )
    table.add_column("vehicle")
    for name in params:
        table.add_column(name, justify="right")
    for vehicle, entry in list(result["vehicles"].items())[:SHOWN_VEHICLES]:
        table.add_row(
            escape(vehicle), *(f"{entry[n]['mean']:.3g} ± {entry[n]['sd']:.2g}" for n in params)
        )
    console.print(table)
    hidden = len(result["vehicles"]) - SHOWN_VEHICLES
    if hidden > 0:
        console.print(f"... and {hidden} more vehicle(s) in summary.json")
    console.print(
        f"flagged samples in the data (left out): {result['flagged_samples']}; "
        f"usable steps: {result['usable_steps']}"
    )
    console.print(
        f"inference {result['wall_time_s']:.2f} s, compilation {result['compile_time_s']:.2f} s; "
        f"seed {result['seed']}"
    )
    console.print(escape(f"wrote {', '.join(written)} to {out}"))


def fit(
    data: str = typer.Argument(..., help="A file, a folder, or a data set name."),
    out: str = typer.Option(..., "--out", help="Folder for result.nc, summary.json and plots."),
    model: str = typer.Option(
        "idm",
        "--model",
        help=f"Driver model: {', '.join(MODELS)}, or a base joined by '+' to an extension "
        f"({', '.join(CAUSES)}), e.g. idm+reaction_delay.",
    ),
    engine: str = typer.Option("smc", "--engine", help=f"Engine: {', '.join(ENGINES)}."),
    params: str | None = typer.Option(
        None, "--params", help="Comma-separated parameters to infer (default: all)."
    ),
    particles: int = typer.Option(1000, "--particles", help="Particles per vehicle."),
    seed: int = typer.Option(0, "--seed", help="Seed of the engine's random key."),
    format: str | None = typer.Option(
        None, "--format", help="Reader format (default: detected or the data set's)."
    ),
    window: str = typer.Option("fit", "--window", help="Steps to fit on: fit or all."),
    vehicles: int | None = typer.Option(
        None, "--vehicles", help="Only the first N vehicles with usable steps (quick runs)."
    ),
    epochs: int | None = typer.Option(None, "--epochs", help="pf only: epochs (default 1)."),
    data_dir: str | None = typer.Option(None, "--data-dir", help="Folder holding data sets."),
    json_out: str | None = typer.Option(None, "--json", metavar="OUT", help=JSON_HELP),
) -> None:
    """Fit per-vehicle parameter distributions and write result.nc, summary.json and plots."""
    folder = Path(out)
    if window not in ("fit", "all"):
        raise fail(
            f"--window must be 'fit' or 'all' (held-out steps are never fitted), not {window!r}"
        )
    if epochs is not None and engine != "pf":
        raise fail("--epochs applies to --engine pf only")
    options = {} if epochs is None else {"epochs": epochs}
    try:
        # Checked before reading any data, so a typo fails at once.
        driver = get_model(model)
        check_engine_model(engine, driver)
        names = (
            None if params is None else param_names(driver, [p.strip() for p in params.split(",")])
        )
        traj = registry.load(data, format=format, data_dir=data_dir)
        fitted = traj if traj.format != "merge_episodes" else merge_arrays(traj, window)
        with _progress() as bar:
            task = bar.add_task(f"{engine}: compiling, then fitting vehicles", total=None)
            tree = fit_model(
                jax.random.key(seed),
                fitted,
                source=traj.source,
                model=driver,
                engine=engine,
                params=names,
                num_particles=particles,
                window=window,
                seed=seed,
                max_vehicles=vehicles,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
                **options,
            )
    except (DataError, KeyError, ValueError, NotImplementedError) as error:
        raise fail(str(error.args[0] if isinstance(error, KeyError) else error)) from None

    result = summary(tree)
    emit_json(result, str(folder / "summary.json"))
    plots = write_filter_plots(tree, folder)
    try:
        save_result(tree, folder / "result.nc")
    except ImportError as error:
        raise fail(f"cannot write {folder / 'result.nc'}: {error}") from None
    if not emit_json(result, json_out):
        _print(result, folder, ["result.nc", "summary.json", *(p.name for p in plots)])
