"""``bayesdrive fit``: per-vehicle parameter distributions from trajectories, saved to a folder.

DATA is a file, a folder or a data set name; a held-out name is read from the held-out folder
(``--data-dir``, else as :func:`bayesdrive.data.registry.holdout_dir` finds it) with a logged
note: fitting its vehicles with fixed settings is evaluation, tuning anything on it is not.
Merge episodes are fitted per stay of the cooperating car behind the merging car, with the
merge scene beside every step, so ``--model cidm`` learns c too. OUT gets result.nc (the result tree, :mod:`bayesdrive.inference.core.output`), summary.json
(:func:`bayesdrive.inference.fit.summary`) and, for pf and ``smc --sequential``, the per-step
diagnostics ess.png, unique_particles.png and convergence.png, then manifest.json last (arguments, seed, complete);
the folder is all of one run or none (:mod:`bayesdrive.data.outputs`: a complete one is replaced
only with ``--force``). Bad input ends with a one-line ``error: ...`` on standard error and exit
code 2; a fit that fails a convergence check (:mod:`bayesdrive.inference.diagnostics.convergence`) is still
written, warns naming each vehicle and parameter, and exits with code 3.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ColumnMap,
    ForceResults,
    LengthUnits,
    check_cluster_options,
    column_map_options,
    console,
    emit_json,
    err_console,
    fail,
    progress_bar,
    results_command,
    results_folder,
)
from bayesdrive.cli.names import CAUSES, ENGINES, FIT_CHUNK_SIZE, MODELS

__all__ = ["fit"]


CLUSTER_HELP = (
    "Fit chunks of vehicles on Dask: local[:N] starts N single-threaded process workers (default: "
    "one per core), tcp://HOST:PORT uses a running scheduler. Same result as without; an "
    "interrupted run resumes from its finished chunks."
)
JSON_HELP = "Write summary.json's content to OUT too ('-' for standard output, then nothing else)."
# Vehicles listed in the printed table; summary.json has all of them.
SHOWN_VEHICLES = 10
NOT_CONVERGED = 3


def _size(result: dict[str, Any]) -> str:
    from bayesdrive.inference.fit import PARTICLE_ENGINES

    if result["engine"] in PARTICLE_ENGINES:
        return f"{result['num_particles']} particles"
    walkers = result["engine_options"].get("num_walkers")
    # emcee's --chains are the walkers of one ensemble, stored as one chain.
    of_walkers = f" of {walkers} walkers" if walkers else ""
    return f"{result['num_draws']} draws in {result['num_chains']} chain(s){of_walkers}"


def _print(result: dict[str, Any], out: Path, written: list[str]) -> None:
    params = result["params"]
    table = Table(
        title=escape(
            f"{result['engine']} on {result['model']}: {len(result['vehicles'])} vehicle(s) of "
            f"{result['data_source']} ({result['window']} window), {_size(result)}; "
            "posterior mean ± sd"
        )
    )
    table.add_column("vehicle")
    for name in params:
        table.add_column(escape(f"{name} [{result['units'][name]}]"), justify="right")
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
    checked = result["convergence"]
    if checked["unchecked"]:
        console.print(escape(f"convergence not checked: {checked['unchecked']}"))
    else:
        console.print(escape(f"convergence checks: {', '.join(checked['checks'])}"))
    console.print(escape(f"wrote {', '.join(written)} to {out}"))


@results_command
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
    particles: int | None = typer.Option(
        None, "--particles", help="smc, pf: particles per vehicle (default 1000)."
    ),
    draws: int | None = typer.Option(
        None,
        "--draws",
        help="Other engines: posterior draws per vehicle, all chains (default 1000).",
    ),
    chains: int | None = typer.Option(
        None, "--chains", help="nuts, hierarchical, pmmh: chains; emcee: walkers of its ensemble."
    ),
    warmup: int | None = typer.Option(
        None, "--warmup", help="nuts, hierarchical, pmmh: warm-up iterations; emcee: burn-in steps."
    ),
    steps: int | None = typer.Option(
        None, "--steps", help="emcee only: steps per walker, burn-in included (default 4000)."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the engine's random key."),
    format: str | None = typer.Option(
        None, "--format", help="Reader format (default: detected or the data set's)."
    ),
    window: str = typer.Option("fit", "--window", help="Steps to fit on: fit or all."),
    vehicles: int | None = typer.Option(
        None, "--vehicles", help="Only the first N vehicles with usable steps (quick runs)."
    ),
    epochs: int | None = typer.Option(None, "--epochs", help="pf only: epochs (default 1)."),
    sequential: bool = typer.Option(
        False,
        "--sequential",
        help="smc only: also run its pass along the data, for the per-step plots (ESS, distinct "
        "particles, learning curve); the draws do not change.",
    ),
    vehicle_batch: int | None = typer.Option(
        None,
        "--vehicle-batch",
        help="smc, nuts: vehicles vectorised together (default 1, best on CPU cores; on a GPU, "
        "hundreds). Draws then differ from the default's in the last bits, not with the device "
        "count.",
    ),
    pointwise: bool = typer.Option(
        True,
        "--pointwise/--no-pointwise",
        help="Keep result.nc's log_likelihood group: every draw scored on every usable step, "
        "which PSIS-LOO and arviz.compare read. --no-pointwise leaves it out: a smaller file, "
        "less time after sampling.",
    ),
    data_dir: str | None = typer.Option(
        None, "--data-dir", help="Folder holding data sets (held-out ones for a held-out name)."
    ),
    columns: ColumnMap = None,
    units: LengthUnits = None,
    json_out: str | None = typer.Option(None, "--json", metavar="OUT", help=JSON_HELP),
    cluster: str | None = typer.Option(None, "--cluster", help=CLUSTER_HELP),
    chunk_size: int | None = typer.Option(
        None,
        "--chunk-size",
        help=f"With --cluster: vehicles per task (default {FIT_CHUNK_SIZE}).",
    ),
    force: ForceResults = False,
) -> None:
    """Fit per-vehicle parameter distributions and write result.nc, summary.json and plots."""
    # Imported here so that `bayesdrive fit --help` does not import JAX.
    import jax

    from bayesdrive.data import registry
    from bayesdrive.data.errors import DataError
    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference import distributed
    from bayesdrive.inference.core.likelihood import param_names
    from bayesdrive.inference.core.output import save_result
    from bayesdrive.inference.fit import (
        BATCHED_ENGINES,
        PARTICLE_ENGINES,
        check_engine_model,
        summary,
    )
    from bayesdrive.inference.fit import fit as fit_model
    from bayesdrive.reports.filter_plots import write_filter_plots
    from bayesdrive.simulation.scenarios import fit_input

    if window not in ("fit", "all"):
        raise fail(
            f"--window must be 'fit' or 'all' (held-out steps are never fitted), not {window!r}"
        )
    if epochs is not None and engine != "pf":
        raise fail("--epochs applies to --engine pf only")
    if sequential and engine != "smc":
        raise fail("--sequential applies to --engine smc only")
    if steps is not None and engine != "emcee":
        raise fail("--steps applies to --engine emcee only")
    if particles is not None and engine not in PARTICLE_ENGINES:
        raise fail(
            f"--particles applies to {' and '.join(PARTICLE_ENGINES)}; {engine} takes --draws"
        )
    check_cluster_options(cluster, chunk_size)
    if vehicle_batch is not None and engine not in BATCHED_ENGINES:
        raise fail(f"--vehicle-batch applies to {' and '.join(BATCHED_ENGINES)} only")
    if vehicle_batch is not None and vehicle_batch < 1:
        raise fail(f"--vehicle-batch must be at least 1, got {vehicle_batch}")
    if cluster is not None and engine in distributed.JOINT_ENGINES:
        raise fail(f"--cluster fits vehicles apart; --engine {engine} fits them jointly")
    options = {
        name: value
        for name, value in (
            ("epochs", epochs),
            ("num_steps", steps),
            ("vehicle_batch", vehicle_batch),
            ("sequential", sequential or None),
        )
        if value is not None
    }
    # A cluster run keeps its finished chunks when interrupted, for the next run to reuse.
    results = results_folder(
        out, "fit", force=force, json_out=json_out, resumable=cluster is not None
    )
    try:
        # Checked before reading any data, so a typo fails at once.
        driver = get_model(model)
        check_engine_model(engine, driver)
        names = (
            None if params is None else param_names(driver, [p.strip() for p in params.split(",")])
        )
        format, reader_options = column_map_options(format, columns, units)
        traj = registry.load_any(data, format=format, data_dir=data_dir, **reader_options)
        fitted = fit_input(traj, window)
        with progress_bar() as bar:
            where = "" if cluster is None else f" on {cluster}"
            task = bar.add_task(f"{engine}{where}: compiling, then fitting vehicles", total=None)
            settings = {
                "model": driver,
                "engine": engine,
                "params": names,
                "num_particles": particles,
                "draws": draws,
                "chains": chains,
                "warmup": warmup,
                "window": window,
                "seed": seed,
                "max_vehicles": vehicles,
                "source": traj.source,
                "pointwise": pointwise,
                "progress": lambda done, total: bar.update(task, completed=done, total=total),
                **options,
            }
            if cluster is None:
                tree = fit_model(jax.random.key(seed), fitted, **settings)
            else:
                with distributed.open_cluster(cluster) as client:
                    tree = distributed.fit_on_cluster(
                        client,
                        jax.random.key(seed),
                        fitted,
                        folder=results.path,
                        chunk_size=chunk_size or distributed.DEFAULT_CHUNK_SIZE,
                        **settings,
                    )
    except (DataError, KeyError, ValueError, NotImplementedError) as error:
        raise fail(str(error.args[0] if isinstance(error, KeyError) else error)) from None

    result = summary(tree)
    emit_json(result, str(results.path / "summary.json"))
    plots = write_filter_plots(tree, results.path)
    try:
        save_result(tree, results.path / "result.nc")
    except ImportError as error:
        raise fail(f"cannot write {Path(out) / 'result.nc'}: {error}") from None
    distributed.remove_chunks(results.path)
    folder = results.commit()
    if not emit_json(result, json_out):
        _print(result, folder, ["result.nc", "summary.json", *(p.name for p in plots)])
    problems = result["convergence"]["problems"]
    if problems:
        err_console.print(
            f"[yellow]warning:[/yellow] {len(problems)} convergence problem(s) (listed in "
            "summary.json under convergence; run longer or with more draws); exit code 3",
            soft_wrap=True,
        )
        raise typer.Exit(NOT_CONVERGED)
